#!/usr/bin/env python
"""How many solves a ``stsdic run`` makes, and how many of its rows its blocks' rescue
handles: on a GPU each solve costs its launches and host reads, so their number, not their
rows, sets the pace of a block. Counted on any device (the CPU included).

    python scripts/benchmarks/count_solves.py -- ../shared/data/mudic-hourglass \\
        --roi 150 20 1120 734 --subset 31 --step 20
    python scripts/benchmarks/count_solves.py --targets 32 -- ../shared/data/mudic-hourglass \\
        --roi 150 20 1120 734 --subset 31 --step 20 --memory-mb 1600   # a GPU's blocks on the CPU

``--targets N`` raises the CPU's most target frames a block (``plan.MAX_DEFAULT_BATCH``, 8)
to N, as a GPU's (32); the blocks get that many where ``--memory-mb`` holds their frames.
Prints the wall time, the solves and their rows, and the rescue's: calls, the rows lost
when it starts, restarted from an earlier target, by FFT, and still lost after it. With
``--work``, also where the Gauss-Newton work goes: per pass (the shared-motion pass with
the classical pass it holds, the template's rounds, the main blocks) and per caller of
``Block.solve``, its solves, rows, row-frames (each row's window length summed),
row-frame iterations (a row's frames times its iterations: the kernel's work) and seconds
(the solve's wall time, Python around the kernel included). With ``--masked`` (and a GPU's
choices, ``TORCH_STSDIC_CHOICES``): each masked solve's call site, the rows asked for, the
rows masked over and the rows prepared where ``COMPACT_ROWS`` takes them to a learned size
(:meth:`~torch_stsdic.movie.block_guess.BlockGuesses.compact`)."""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import sys
import tempfile
import time
import traceback
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, default=None,
                    help="most target frames a block (default: the CPU's, 8)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the run's result file there (default: a temporary one)")
    ap.add_argument("--work", action="store_true",
                    help="also the Gauss-Newton work per pass and caller")
    ap.add_argument("--masked", action="store_true",
                    help="also each masked solve's call site (a GPU's choices): the rows "
                         "asked for, masked over, and prepared (COMPACT_ROWS)")
    ap.add_argument("run_args", nargs="+", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    import torch

    import torch_stsdic.movie.plan as plan_mod
    from torch_stsdic.cli.app import main as cli_main
    from torch_stsdic.movie import block as block_mod

    if a.targets is not None:  # the blocks' length only: the rescue's reach stays the CPU's
        plan_mod.MAX_DEFAULT_BATCH = a.targets
    st: collections.Counter = collections.Counter()
    rescue, solve = block_mod.Block.rescue, block_mod.Block.solve

    def counted_rescue(self, carry, carried, m=None):
        st["rescue calls"] += 1
        st["most targets a block"] = max(st["most targets a block"], self.b)
        st["rows lost entering the rescue"] += int(self.lost().sum())
        out = rescue(self, carry, carried, m)
        st["rows restarted from an earlier target"] += int(out[0])
        st["rows restarted by FFT"] += int(out[1])
        st["rows lost after the rescue"] += int(self.lost().sum())
        return out

    work: dict[str, list] = collections.defaultdict(lambda: [0, 0, 0, 0, 0.0])

    def counted_solve(self, rows, init, m=None, *args, **kwargs):
        st["solves"] += 1
        st["solved rows"] += int(rows.numel())
        if not a.work:
            return solve(self, rows, init, m, *args, **kwargs)
        t0 = time.perf_counter()
        sol = solve(self, rows, init, m, *args, **kwargs)
        seconds = time.perf_counter() - t0
        names = [f.name for f in traceback.extract_stack()
                 if "torch_stsdic/movie" in f.filename.replace("\\", "/")]
        phase = ("shared motion" if "estimate_shared_motion" in names else
                 "template" if "build_series_reference" in names else "blocks")
        half = (m.long() if isinstance(m, torch.Tensor)
                else torch.full((rows.numel(),), self.run.m if m is None else int(m)))
        frames = (2 * half + 1).cpu()
        key = f"{phase}: {names[-2]} > {names[-1]}"
        w = work[key]
        w[0] += 1
        w[1] += int(rows.numel())
        w[2] += int(frames.sum())
        w[3] += int((frames * sol.iterations.long().cpu()).sum())
        w[4] += seconds
        return sol

    sites: dict[str, list] = collections.defaultdict(lambda: [0, 0, 0, 0])
    compact = block_mod.Block.compact

    def counted_compact(self, site, active):
        cap = compact(self, site, active)
        c = sites[site]
        c[0] += 1
        c[1] += int(active.sum())
        c[2] += int(active.numel())
        c[3] += int(active.numel() if cap is None else cap)
        return cap

    block_mod.Block.rescue = counted_rescue
    block_mod.Block.solve = counted_solve
    block_mod.Block.compact = counted_compact
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = cli_main(["run", *a.run_args, "--out", str(a.keep or Path(tmp) / "r.h5"),
                           "--overwrite", "--no-progress"])
        wall = time.perf_counter() - t0
    print(json.dumps({"rc": rc, "wall_s": round(wall, 1), **st}, indent=1))
    if a.work:
        total = max(1, sum(w[3] for w in work.values()))
        print(f"{'seconds':>8} {'solves':>6} {'rows':>8} {'row-frames':>10} "
              f"{'row-frame iterations':>21}  pass: caller")
        for key, w in sorted(work.items(), key=lambda kv: -kv[1][3]):
            share = 100 * w[3] / total
            print(f"{w[4]:8.2f} {w[0]:6d} {w[1]:8d} {w[2]:10d} {w[3]:12d} ({share:4.1f} %)"
                  f"  {key}")
    if a.masked:
        print("| masked solves' call site | solves | rows asked for | rows masked over | "
              "rows prepared |\n|---|---:|---:|---:|---:|")
        for site, (n, asked, over, prepared) in sites.items():
            print(f"| {site} | {n} | {asked:,} | {over:,} | {prepared:,} |")
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
