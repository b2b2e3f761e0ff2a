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
when it starts, restarted from an earlier target, by FFT, and still lost after it."""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, default=None,
                    help="most target frames a block (default: the CPU's, 8)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the run's result file there (default: a temporary one)")
    ap.add_argument("run_args", nargs="+", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
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

    def counted_solve(self, rows, init, *args, **kwargs):
        st["solves"] += 1
        st["solved rows"] += int(rows.numel())
        return solve(self, rows, init, *args, **kwargs)

    block_mod.Block.rescue = counted_rescue
    block_mod.Block.solve = counted_solve
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = cli_main(["run", *a.run_args, "--out", str(a.keep or Path(tmp) / "r.h5"),
                           "--overwrite", "--no-progress"])
        wall = time.perf_counter() - t0
    print(json.dumps({"rc": rc, "wall_s": round(wall, 1), **st}, indent=1))
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
