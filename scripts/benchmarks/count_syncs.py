#!/usr/bin/env python
"""How often a ``stsdic run`` block would wait for the device: the torch operations of each
block that force a host synchronisation on a GPU, counted on any device (the CPU included).

    python scripts/benchmarks/count_syncs.py                     # the hourglass, defaults
    python scripts/benchmarks/count_syncs.py --out docs/bench/syncs-hourglass-cpu.json -- \\
        ../shared/data/mudic-hourglass --roi 150 20 1120 734 --subset 31 --step 20 --m 2

Counted through a ``TorchDispatchMode`` (every aten call of the process, in the calling
thread): a value read on the host (``.item()``, ``bool()``, ``int()``, ``float()`` of a
tensor: ``aten._local_scalar_dense``; ``torch.equal``'s answer), and the operations whose
output size depends on the data (``nonzero``, ``masked_select``, boolean-mask indexing,
``unique``, ``repeat_interleave`` with a tensor of repeats): on CUDA each waits for the
device. Copies to the host (``.cpu()``, ``.numpy()``, ``.tolist()``) do not pass the
dispatcher on a CPU run; they are counted apart (``host copy``: those called in the
counting thread, patched in while counting; on a GPU each of a device tensor waits for it;
on the CPU some of them read host tensors a GPU run keeps on the host too, so they are an
upper bound there); so are the tensors made from host data with a ``device`` (``torch.tensor``,
``torch.as_tensor``: to a GPU a copy from pageable memory, which waits too; counted whatever
the device) and from numpy arrays (``torch.from_numpy``: the block loop moves them to the
device). Per block of the run itself (its passes' blocks apart), from the start of its solve
to the next block's (its results handed over, the next carry made: what the block loop's
thread does; the writer thread's copies and writes are not counted), the median over
the blocks (and, apart, the run's passes: its counts outside its blocks: the shared-motion
pass, the template's rounds, the window-length pass, setting up and writing); the run is
slowed down by the counting (use it for counts, not for speed). Of
those, the ones in the C++ CPU kernels' argument checks (``kernels/native``, and the host
work of their callers, :data:`NATIVE_CALLERS`) are shown
apart: a GPU run takes other kernels. Also counted, apart from the syncs: the launch-like
operations of a block (every dispatched operation but the views and metadata ones: on a
GPU each launches a kernel; the C++ kernels' calls are not among them), ``--ops-where N``
listing the N functions that make most of them. ``--where N`` lists the
N lines of the package that sync most over the whole run. ``--gpu-choices`` takes the
choices a GPU run makes where they differ from a CPU run's (``torch_stsdic.core.choices``:
masked rows, the model check's shorter windows all at once, every round of a loop; those
named in ``TORCH_STSDIC_CHOICES`` as named): the same results, fewer reads. ``--gpu-config``
takes a GPU's blocks and budget too (:func:`gpu_config`: 32 targets a block, its frames and
batches within 2 GiB), the closest the CPU comes to counting a GPU run.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import statistics
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_parts import split_run_args  # noqa: E402  (the hourglass by default)

#: aten operations that make the host wait for the device (by their overload packet name)
SYNCING = {"_local_scalar_dense": "host read", "equal": "host read",
           "nonzero": "data-dependent size",
           "masked_select": "data-dependent size", "unique_dim": "data-dependent size",
           "_unique2": "data-dependent size", "unique_consecutive": "data-dependent size",
           "repeat_interleave": "data-dependent size",
           # sized by their input's largest value, read on the host on CUDA (bincount's
           # max, whatever its minlength; histc's range where not given)
           "bincount": "data-dependent size", "histc": "data-dependent size",
           # linear algebra that checks its LAPACK/cuSOLVER info on the host: on CUDA a
           # wait (torch.linalg.solve, inv, cholesky: their ``_linalg_check_errors``; eigh,
           # svd, pinv, lstsq check inside; the ``_ex`` forms without ``check_errors`` do
           # not)
           "_linalg_check_errors": "linalg error check", "_linalg_eigh": "linalg error check",
           "_linalg_svd": "linalg error check", "linalg_pinv": "linalg error check",
           "linalg_lstsq": "linalg error check"}


#: where the C++ CPU kernels check their arguments on the host (a GPU run takes other paths)
NATIVE = "torch_stsdic/kernels/native"
#: functions counted with them: those that call those kernels and prepare their arguments
#: on the host (the CPU's path of a step a GPU run takes in torch:
#: ``torch_stsdic.kernels.dispatch`` picks the C++ kernels on the CPU only), and those that
#: work on host tensors on every device (a block's frame numbers from its host targets, the
#: frames of a run's blocks in the order of first use, the row of a frame in a result,
#: whose frame numbers are kept on the host)
NATIVE_CALLERS = (" _round_native", " block_frames", " frames_in_order", " row_of")
#: the counter of those (a part of the others, not added to a block's total)
CPU_ONLY = "of which in the CPU kernels' checks"
#: of those, the host copies (apart, so that a total without copies leaves them out once)
CPU_ONLY_COPIES = "of which host copies in the CPU kernels' checks"
#: the counter of the copies to the host outside the dispatcher (``.tolist()``, ``.numpy()``,
#: ``.cpu()``)
HOST_COPY = "host copy (tolist, numpy, cpu)"
#: the counter of the tensors made from host data on a device (``torch.tensor`` or
#: ``torch.as_tensor`` of Python numbers, lists or arrays with a ``device``): to a GPU each is
#: a copy from pageable memory, which waits for the device's queue (on the CPU they are
#: counted whatever the device: an upper bound, like the host copies)
TO_DEVICE = "copy to the device (tensor, as_tensor)"
#: the counter of the aten operations that would launch a kernel on a GPU (every dispatched
#: operation but the views and metadata ones, :data:`NO_LAUNCH`): a proxy of a block's
#: launches, not a sync (not added to a block's total); the C++ kernels' calls are not
#: among them (a GPU run launches a Triton kernel for each of those instead)
LAUNCHES = "operations (GPU launches, proxy)"
#: aten operations that launch no kernel (views, metadata)
NO_LAUNCH = {"view", "_unsafe_view", "reshape", "as_strided", "expand", "permute", "transpose",
             "t", "unsqueeze", "squeeze", "slice", "select", "detach", "alias", "unbind",
             "split", "split_with_sizes", "chunk", "narrow", "view_as_real", "view_as_complex",
             "_reshape_alias", "lift_fresh", "unfold", "diagonal", "movedim", "numpy_T",
             "expand_as", "view_as", "flatten", "_local_scalar_dense", "equal", "sym_size",
             "sym_stride", "sym_numel", "is_same_size", "empty", "empty_like", "empty_strided",
             "resize_", "set_"}


def package_line(depth: int = 2, function: bool = False) -> str:
    """The innermost line (``function``: function) of the package's own code on the stack
    of the caller ``depth`` frames up (these scripts' own frames passed over)."""
    frame = sys._getframe(depth)
    while frame is not None:
        path = frame.f_code.co_filename
        if "torch_stsdic" in path and "scripts/benchmarks" not in path.replace("\\", "/"):
            short = path[path.rindex("torch_stsdic"):]
            if function:
                return f"{short} {frame.f_code.co_name}"
            return f"{short}:{frame.f_lineno} {frame.f_code.co_name}"
        frame = frame.f_back
    return "(outside the package)"


class SyncCounter(TorchDispatchMode):
    """Counts the syncing operations (:data:`SYNCING`) by name, and boolean-mask indexing."""

    def __init__(self, where: bool = False, ops_where: bool = False) -> None:
        super().__init__()
        self.counts: collections.Counter[str] = collections.Counter()
        self.where: collections.Counter[str] | None = collections.Counter() if where else None
        self._saved: dict[str, object] = {}
        #: the places of the run's own blocks only (filled by :func:`count_run`)
        self.block_where: collections.Counter[str] = collections.Counter()
        #: each of the run's blocks' places outside the CPU kernels' checks (``where``)
        self.each_block_where: list[dict[str, int]] = []
        #: the launch-like operations of the run's blocks by function (``ops_where``)
        self.op_where: collections.Counter[str] | None = (
            collections.Counter() if ops_where else None)

    def __enter__(self):
        """Also count ``.tolist()``, ``.numpy()`` and ``.cpu()`` of the entering thread (they
        do not pass the dispatcher on the CPU)."""
        me = threading.get_ident()
        for name in ("tolist", "numpy", "cpu"):
            orig = getattr(torch.Tensor, name)
            self._saved[name] = orig

            def counted(t, *a, _orig=orig, **k):
                if threading.get_ident() == me:
                    self.counts[HOST_COPY] += 1
                    place = self._place()
                    if place.startswith(NATIVE) or place.endswith(NATIVE_CALLERS):
                        self.counts[CPU_ONLY] += 1
                        self.counts[CPU_ONLY_COPIES] += 1
                    if self.where is not None:
                        self.where[place] += 1
                return _orig(t, *a, **k)

            setattr(torch.Tensor, name, counted)
        for name in ("tensor", "as_tensor", "from_numpy"):
            make = getattr(torch, name)
            self._saved["torch." + name] = make

            def made(data, *a, _make=make, _name=name, **k):
                if (threading.get_ident() == me and (k.get("device") is not None
                                                     or _name == "from_numpy")
                        and not isinstance(data, torch.Tensor)):
                    self.counts[TO_DEVICE] += 1
                    if self.where is not None:
                        self.where[self._place()] += 1
                return _make(data, *a, **k)

            setattr(torch, name, made)
        return super().__enter__()

    def __exit__(self, *exc):
        for name, orig in self._saved.items():
            if name.startswith("torch."):
                setattr(torch, name[len("torch."):], orig)
            else:
                setattr(torch.Tensor, name, orig)
        self._saved = {}
        return super().__exit__(*exc)

    def _place(self, function: bool = False) -> str:
        return package_line(3, function)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name not in NO_LAUNCH:
            self.counts[LAUNCHES] += 1
            if self.op_where is not None:
                self.op_where[self._place(function=True)] += 1
        if name in SYNCING:
            self.counts[name] += 1
            place = self._place()
            if place.startswith(NATIVE) or place.endswith(NATIVE_CALLERS):
                self.counts[CPU_ONLY] += 1
            if self.where is not None:
                self.where[place] += 1
        elif name in ("index", "index_put_", "index_put") and any(
                isinstance(t, torch.Tensor) and t.dtype == torch.bool
                for t in (args[1] if len(args) > 1 and isinstance(args[1], (list, tuple))
                          else ())):
            self.counts[f"{name} (bool mask)"] += 1
            if self.where is not None:
                self.where[self._place()] += 1
        return func(*args, **(kwargs or {}))


def main(argv: list[str] | None = None) -> int:
    own, run_args = split_run_args(list(sys.argv[1:] if argv is None else argv))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("--where", type=int, default=0, metavar="N",
                    help="also list the N lines of the package that sync most (whole run)")
    ap.add_argument("--ops-where", type=int, default=0, metavar="N",
                    help="also list the N functions of the package that make the most "
                         "launch-like operations in the run's blocks (slow)")
    ap.add_argument("--gpu-choices", action="store_true",
                    help="take the choices a GPU run takes where they differ from the CPU's "
                         "(torch_stsdic.core.choices: masked rows, the model check's "
                         "shorter windows at once, every round of a loop), but those named "
                         "in TORCH_STSDIC_CHOICES")
    ap.add_argument("--targets", type=int, default=None, metavar="N",
                    help="the most target frames a block (plan.MAX_DEFAULT_BATCH, 8 on the "
                         "CPU; a GPU's 32: with --memory-mb 2048, its blocks and budget)")
    ap.add_argument("--gpu-config", action="store_true",
                    help="a GPU run's choices, blocks and budget on the CPU: --gpu-choices, "
                         "and core.config.gpu_budget_mb answering 2048 MiB on every device "
                         "(the blocks' frames and 32 targets, the solver's and the FFT "
                         "search's batches, as on a card of 20 GiB or more)")
    args = ap.parse_args(own)
    if args.gpu_config:
        args.gpu_choices = True
        gpu_config()
    if args.targets is not None:
        from torch_stsdic.movie import plan as plan_mod
        plan_mod.MAX_DEFAULT_BATCH = args.targets
    if args.gpu_choices:
        from torch_stsdic.core import choices
        named = choices.from_environment()  # (set at import already: kept as named)
        for name, value in choices.gpu_choices().items():
            if name not in named:
                setattr(choices, name, value)
    rc, per_block, counter = count_run(run_args, where=args.where > 0,
                                       ops_where=args.ops_where > 0)
    if rc:
        return rc
    kinds = sorted({k for b in per_block for k in b})
    med = {k: statistics.median(b.get(k, 0) for b in per_block) for k in kinds}
    total = [block_total(b) for b in per_block]
    rest = [block_total(b, cpu_kernels=False) for b in per_block]
    old = [block_total(b, cpu_kernels=False, copies=False) for b in per_block]
    rec = {"args": run_args, "device": "cpu", "gpu_choices": args.gpu_choices,
           "gpu_config": args.gpu_config, "targets": args.targets, "blocks": len(per_block),
           "per_block_median": med, "per_block_total_median": statistics.median(total),
           "per_block_total_range": [min(total), max(total)],
           "per_block_outside_cpu_kernels_median": statistics.median(rest),
           "per_block_outside_cpu_kernels_range": [min(rest), max(rest)],
           "per_block_outside_cpu_kernels_without_copies_median": statistics.median(old),
           # each block's, in order: the run's first two (its reference frame's and the
           # one after it) do once-a-run work (the first guesses, learning the sizes)
           "per_block_outside_cpu_kernels": rest,
           "per_block_launches": [b.get(LAUNCHES, 0) for b in per_block],
           "run_total": dict(counter.counts), "commit": _commit()}
    passes = in_passes(counter.counts, per_block)
    rec["passes"] = passes
    rec["passes_outside_cpu_kernels"] = block_total(passes, cpu_kernels=False)
    rec["passes_outside_cpu_kernels_without_copies"] = block_total(passes, cpu_kernels=False,
                                                                   copies=False)
    print(f"{len(per_block)} blocks; syncing operations a block (median): "
          f"{rec['per_block_total_median']:.0f} (range {min(total)}-{max(total)})")
    for k in kinds:
        print(f"  {k:<28} {med[k]:>6.0f}")
    print(f"  outside the CPU kernels' checks (what a GPU run's path may keep): "
          f"{statistics.median(rest):g} a block (median; range {min(rest)}-{max(rest)}); "
          f"without the host copies {statistics.median(old):.0f}")
    print(f"    each block's, in order: {', '.join(map(str, rest))}"
          + (f" (after the first two: median {statistics.median(rest[2:]):g})"
             if len(rest) > 2 else ""))
    print(f"    each block's launch-like operations, in order: "
          f"{', '.join(map(str, rec['per_block_launches']))}")
    print(f"  the run's passes (outside its blocks): {rec['passes_outside_cpu_kernels']} "
          f"outside the CPU kernels' checks ({rec['passes_outside_cpu_kernels_without_copies']}"
          f" without the host copies), {passes.get(LAUNCHES, 0)} launch-like operations")
    if counter.where is not None:
        rec["where_run_total"] = dict(counter.where.most_common(args.where))
        where_passes = counter.where - counter.block_where
        rec["where_passes"] = dict(where_passes.most_common(args.where))
        rec["where_blocks"] = dict(counter.block_where.most_common(args.where))
        print(f"where (whole run, top {args.where}):")
        for place, n in counter.where.most_common(args.where):
            print(f"  {n:>7d}  {place}")
        print(f"where (the run's passes only, top {args.where}):")
        for place, n in where_passes.most_common(args.where):
            print(f"  {n:>7d}  {place}")
        print(f"where (the run's {len(per_block)} blocks only, top {args.where}):")
        for place, n in counter.block_where.most_common(args.where):
            print(f"  {n:>7d}  {place}")
        rec["where_each_block_outside_cpu_kernels"] = counter.each_block_where
        print("where, block by block, outside the CPU kernels' checks:")
        for i, places in enumerate(counter.each_block_where):
            print(f"  block {i}: " + ", ".join(f"{n} {p}" for p, n in places.items()))
    if counter.op_where is not None:
        rec["ops_where_blocks"] = dict(counter.op_where.most_common(args.ops_where))
        print(f"launch-like operations by function (the run's {len(per_block)} blocks, "
              f"top {args.ops_where}):")
        for place, n in counter.op_where.most_common(args.ops_where):
            print(f"  {n:>7d}  {place}")
    if args.out is not None:
        args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


def gpu_config() -> None:
    """A GPU's budget on the CPU: ``gpu_budget_mb`` answers what a card of 20 GiB or more
    does (:data:`~torch_stsdic.core.config.GPU_BUDGET_MB`) wherever the package asks it
    (a block's frames and targets, the solver's and the FFT search's batches)."""
    import torch_stsdic.core.gauss_newton as gauss_newton
    import torch_stsdic.core.initial as initial
    import torch_stsdic.movie.plan as plan
    from torch_stsdic.core.config import GPU_BUDGET_MB

    def budget(device, device_mb=None):
        return GPU_BUDGET_MB

    for mod in (gauss_newton, initial, plan):
        mod.gpu_budget_mb = budget


def in_passes(run_counts: dict[str, int], per_block: list[dict[str, int]]) -> dict[str, int]:
    """The counts of a run's passes (the shared-motion pass, the template's rounds, the
    window-length pass, its set-up and its end): the run's ``run_counts`` less its blocks'
    (``per_block``), by kind."""
    passes = collections.Counter(run_counts)
    for b in per_block:
        passes.subtract(b)
    return {k: v for k, v in passes.items() if v}


def block_total(counts: dict[str, int], cpu_kernels: bool = True, copies: bool = True) -> int:
    """A block's syncing operations (``counts`` by kind): all, or without those in the CPU
    kernels' checks (``cpu_kernels`` False) or without the host copies (``copies`` False)."""
    out = sum(v for k, v in counts.items() if k not in (CPU_ONLY, CPU_ONLY_COPIES, LAUNCHES))
    if not cpu_kernels:
        out -= counts.get(CPU_ONLY, 0)
    if not copies:
        out -= counts.get(HOST_COPY, 0)
        if not cpu_kernels:  # (those left out already)
            out += counts.get(CPU_ONLY_COPIES, 0)
    return out


def count_run(run_args: list[str], where: bool = False, ops_where: bool = False
              ) -> tuple[int, list[dict[str, int]], SyncCounter]:
    """``stsdic run`` with ``run_args`` (the output to a temporary file) under a
    :class:`SyncCounter`: its exit code, the counts of each block of the run itself (its
    passes' blocks apart) and the counter (whole run)."""
    counter = SyncCounter(where=where)
    ops = collections.Counter() if ops_where else None
    per_block: list[dict[str, int]] = []
    open_block: list = []  # the run's block being counted: (counts, places) at its start

    def close_block() -> None:  # a block ends where the next starts (or the run's loop)
        if open_block:
            before, where_before = open_block.pop()
            per_block.append(dict(counter.counts - before))
            if counter.where is not None:
                here = counter.where - where_before
                counter.block_where.update(here)
                counter.each_block_where.append(
                    {p: n for p, n in here.most_common()
                     if not (p.startswith(NATIVE) or p.endswith(NATIVE_CALLERS))})

    def open_next() -> None:
        close_block()
        open_block.append((collections.Counter(counter.counts),
                           collections.Counter(counter.where or {})))

    @contextlib.contextmanager
    def solving(own: bool):  # the launch-like operations' functions: the run's blocks only
        counter.op_where = ops if own else None
        try:
            yield
        finally:
            counter.op_where = None

    rc = run_blocks_counted(run_args, counter, open_next, close_block, solving)
    counter.op_where = ops
    return rc, per_block, counter


def run_blocks_counted(run_args: list[str], counter, block_start: Callable[[], None],
                       loop_end: Callable[[], None],
                       solving: Callable[[bool], contextlib.AbstractContextManager] | None = None
                       ) -> int:
    """``stsdic run`` with ``run_args`` (the output to a temporary file) under ``counter`` (a
    context manager, entered around the whole command), telling where the run's own blocks
    (its passes' blocks apart: those of the runs nested in it) begin and end: a block from
    the start of its solve to the next block's start (its results handed over and the next
    carry made from them too: what the block loop's thread does), the last one to the end of
    the run's block loop. ``block_start()`` where each begins, ``loop_end()`` where the loop
    ends; ``solving(own)``, where given, around every block's solve (``own``: the run's).
    Returns the command's exit code."""
    import torch_stsdic.movie.block as block
    import torch_stsdic.movie.series as series
    from torch_stsdic.cli.app import main as cli_main

    depth = {"runs": 0}
    run_plan, solve_block, run_blocks = series.run_plan, block.solve_block, series._run_blocks

    def counted_run(plan, *a, **k):  # the run itself is the outermost run_plan
        depth["runs"] += 1
        try:
            return run_plan(plan, *a, **k)
        finally:
            depth["runs"] -= 1

    def counted_block(*a, **k):
        own = depth["runs"] == 1
        if own:
            block_start()
        with solving(own) if solving is not None else contextlib.nullcontext():
            return solve_block(*a, **k)

    def counted_blocks(*a, **k):  # the run's block loop: its last block ends with it
        try:
            return run_blocks(*a, **k)
        finally:
            if depth["runs"] == 1:
                loop_end()

    series.run_plan, series.solve_block = counted_run, counted_block
    series._run_blocks = counted_blocks
    try:
        with tempfile.TemporaryDirectory() as tmp, counter:
            return cli_main(["run", *run_args, "--out", str(Path(tmp) / "r.h5"),
                             "--overwrite", "--no-progress"])
    finally:
        series.run_plan, series.solve_block = run_plan, solve_block
        series._run_blocks = run_blocks


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


if __name__ == "__main__":
    sys.exit(main())
