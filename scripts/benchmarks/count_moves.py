#!/usr/bin/env python
"""Which host tensors a ``stsdic run`` block copies to a GPU: the copies to the device that a
CPU run cannot show (there a ``.to(device)`` of a host tensor is no copy at all), found by
tracking where each tensor was made; counted on any device.

    python scripts/benchmarks/count_moves.py                      # the hourglass
    python scripts/benchmarks/count_moves.py --out moves.json -- <stsdic run's arguments>

On a GPU a copy from the host's pageable memory to the device waits for the device's queue
(``copy_`` without ``non_blocking``: a stream synchronisation, as a value read on the host),
so a block that moves a host tensor each time it runs waits that often. A GPU profile of the
hourglass (2026-11-30, 68e2c67) counted 337 stream synchronisations a block where
:mod:`count_syncs` counted 64 reads; this script finds the copies among the difference.

Every tensor is tagged "device" or "host" where it is made: a factory (``torch.zeros``,
``arange``, ``full``, ``tensor``, ``as_tensor`` of data, ...) given a ``device`` (other than
the literal ``"cpu"``) makes a device tensor, one without, ``torch.from_numpy``, ``.cpu()``
and ``.to("cpu")`` host ones; every other operation's outputs are device tensors where one of
its tensor inputs of more than one element is (a ``TorchDispatchMode``, in the calling
thread; the frames the read-ahead thread prepares are tagged where they are handed over).
Counted in the command's own blocks (each from its solve to the next one's start, as
:mod:`count_syncs` counts them), in the calling
thread, by the line of the package that moves it: a ``.to(...)`` with a device of a host
tensor of more than one element, but :func:`torch_stsdic.movie.frames.upload`'s (pinned
memory, not waited for) and the CPU's C++ kernels' own (``kernels/native``: a GPU takes other
kernels), with the line that made the tensor. The tags are an approximation: a host tensor
computed from a device tensor (an index, a mask) is taken for a device one, so a copy may be
missed; one listed is a copy on a GPU. The run takes a GPU's choices (``--cpu-choices``: the
CPU's) and is slowed down by the tracking (use it for counts, not for speed)."""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import threading
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

sys.path.insert(0, str(Path(__file__).resolve().parent))
from count_syncs import package_line, run_blocks_counted  # noqa: E402  (one of each)
from run_parts import split_run_args  # noqa: E402  (the hourglass by default)

#: a GPU run's choices (``torch_stsdic.core.choices``), as ``count_syncs --gpu-choices``
GPU_CHOICES = ("EVERY_CANDIDATE=1,UNTIL_DONE=0,MASKED_GROUPS=1,MASKED_CHECK=1,GUESS_READS=1,"
               "COMPACT_ROWS=1,COMPACT_READING=1")
#: the factories of torch whose ``device`` says where their tensor is
FACTORIES = ("zeros", "ones", "full", "empty", "arange", "linspace", "eye", "rand", "randn",
             "randint", "tensor", "as_tensor")
_ON, _MADE = "_sts_on_device", "_sts_made_at"


def on_device(t: torch.Tensor) -> bool:
    """Whether ``t`` is tagged a device tensor."""
    return bool(getattr(t, _ON, False))


def _tag(out, device: bool, made: str | None = None) -> None:
    for t in tree_leaves(out):
        if isinstance(t, torch.Tensor):
            try:
                setattr(t, _ON, device)
                if not device and made is not None and not hasattr(t, _MADE):
                    setattr(t, _MADE, made)
            except (AttributeError, RuntimeError):  # (a tensor that takes no attributes)
                pass


def _names_device(args, kwargs) -> bool:
    """Whether a ``.to(...)`` or a factory's arguments name a device but the literal cpu."""
    dev = kwargs.get("device")
    if dev is None:
        dev = next((a for a in args if isinstance(a, (torch.device, str))), None)
    return dev is not None and dev != "cpu"


def _names_host(args, kwargs) -> bool:
    return (bool(args) and args[0] == "cpu") or kwargs.get("device") == "cpu"


class MoveCounter(TorchDispatchMode):
    """Tags every tensor made while it is entered (see the module docstring) and counts, while
    :attr:`counting` and in the entering thread, the moves of host tensors to the device by
    (place, where the tensor was made)."""

    def __init__(self) -> None:
        super().__init__()
        self.counting = False
        self.moves: collections.Counter[tuple[str, str]] = collections.Counter()
        self._me = threading.get_ident()
        self._saved: dict[str, object] = {}

    def _moved(self, t: torch.Tensor) -> None:
        if not (self.counting and threading.get_ident() == self._me) or on_device(t) \
                or t.numel() <= 1:
            return
        place, made = package_line(3), getattr(t, _MADE, "(made outside the count)")
        if "kernels/native" in place or "kernels/native" in made:
            return  # the CPU's C++ kernels' own tensors: a GPU takes other kernels
        if place.endswith(" upload"):
            return  # pinned memory, not waited for
        self.moves[(place, made)] += 1

    def __enter__(self):
        from torch_stsdic.movie import frames as frames_mod

        counter, saved = self, self._saved
        saved["to"], saved["cpu"] = to, cpu = torch.Tensor.to, torch.Tensor.cpu

        def moved(t, *a, **k):
            out = to(t, *a, **k)
            if _names_device(a, k):
                counter._moved(t)
                if out is t and not on_device(t):  # (the CPU: the same tensor, no copy)
                    out = t.view_as(t)
                _tag(out, True)
            elif _names_host(a, k):
                out = out.view_as(out) if out is t else out
                _tag(out, False, package_line() + " .to(cpu)")
            return out

        def to_host(t, *a, **k):
            out = cpu(t, *a, **k)
            out = out.view_as(out) if out is t else out
            _tag(out, False, package_line() + " .cpu()")
            return out

        torch.Tensor.to, torch.Tensor.cpu = moved, to_host
        for name in FACTORIES:
            make = saved["torch." + name] = getattr(torch, name)

            def made(*a, _make=make, _name=name, **k):
                out = _make(*a, **k)
                if a and isinstance(a[0], torch.Tensor) and "device" not in k:
                    return out  # (a tensor already: where it was)
                dev = _names_device(a[1:] if _name == "full" else (), k)
                _tag(out, dev, None if dev else f"{package_line()} torch.{_name}")
                return out

            setattr(torch, name, made)
        saved["torch.from_numpy"] = from_numpy = torch.from_numpy

        def host(a):
            out = from_numpy(a)
            _tag(out, False, f"{package_line()} torch.from_numpy")
            return out

        torch.from_numpy = host
        saved["prepared"] = prepared = frames_mod.FrameCache._prepared

        def prepared_on_device(cache, i, raw, prep):  # (made in the read-ahead thread)
            _tag(raw, True)
            _tag(prep.coeffs, True)
            return prepared(cache, i, raw, prep)

        frames_mod.FrameCache._prepared = prepared_on_device
        return super().__enter__()

    def __exit__(self, *exc):
        from torch_stsdic.movie import frames as frames_mod

        saved = self._saved
        torch.Tensor.to, torch.Tensor.cpu = saved.pop("to"), saved.pop("cpu")
        frames_mod.FrameCache._prepared = saved.pop("prepared")
        for name, orig in saved.items():
            setattr(torch, name[len("torch."):], orig)
        self._saved = {}
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        ins = [t for t in tree_leaves((args, kwargs)) if isinstance(t, torch.Tensor)]
        big = [t for t in ins if t.numel() > 1]
        dev = any(on_device(t) for t in (big or ins))
        made = next((getattr(t, _MADE, None) for t in big if hasattr(t, _MADE)), None)
        _tag(out, dev, made)
        return out


def count_run(run_args: list[str]) -> tuple[int, collections.Counter]:
    """The command's own blocks and the moves in them (:class:`MoveCounter`, counting from
    the first block's start to the end of the block loop: each block up to the next one's
    start, as :func:`count_syncs.run_blocks_counted` delimits them), running ``stsdic run``
    with ``run_args`` into a temporary folder."""
    counter, blocks = MoveCounter(), [0]

    def block_start() -> None:
        counter.counting = True
        blocks[0] += 1

    def loop_end() -> None:
        counter.counting = False

    code = run_blocks_counted(run_args, counter, block_start, loop_end)
    if code:
        raise SystemExit(f"stsdic run failed ({code})")
    return blocks[0], counter.moves


def main(argv: list[str] | None = None) -> int:
    own, run_args = split_run_args(list(sys.argv[1:] if argv is None else argv))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("--top", type=int, default=30, help="places listed (default 30)")
    ap.add_argument("--cpu-choices", action="store_true",
                    help="the CPU's choices (default: a GPU's, as count_syncs --gpu-choices)")
    args = ap.parse_args(own)
    if not args.cpu_choices:
        os.environ.setdefault("TORCH_STSDIC_CHOICES", GPU_CHOICES)
    blocks, moves = count_run(run_args)
    total = sum(moves.values())
    print(f"the command's {blocks} blocks: {total} copies of host tensors to the device "
          f"({total / max(blocks, 1):.1f} a block)")
    for (place, made), n in moves.most_common(args.top):
        print(f"  {n:>6d}  {place}  <- made at {made}")
    if args.out is not None:
        rec = {"args": run_args, "choices": os.environ.get("TORCH_STSDIC_CHOICES", ""),
               "blocks": blocks, "moves": total,
               "where": {f"{p} <- {m}": n for (p, m), n in moves.most_common(args.top)}}
        args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
