#!/usr/bin/env python
"""Where a warm ``stsdic run`` spends its time, by Python function: the command run ``--warm``
times in one process (first-use costs: the CUDA context, Triton's compiles, the C++ kernels'
build), then once under cProfile, the device synchronised before the clock stops.

    python scripts/benchmarks/profile_run.py --out prof.txt -- \\
        ../shared/data/mudic-hourglass --roi 150 20 1120 734 --subset 31 --step 20 --device cuda

Prints the wall time of every run; writes them and the top functions by cumulative and by own
time to ``--out``."""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--warm", type=int, default=1, help="unprofiled runs first (default 1)")
    ap.add_argument("--top", type=int, default=45)
    ap.add_argument("--out", type=Path, default=Path("profile-run.txt"))
    ap.add_argument("run_args", nargs="+", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    import torch

    from torch_stsdic.cli.app import main as cli_main

    def sync() -> None:
        if torch.cuda.is_available():
            torch.cuda.synchronize()

    lines: list[str] = []

    def say(s: str, show: bool = True) -> None:  # written as it comes: a run stopped at its
        if show:                                   # limit keeps what it wrote
            print(s, flush=True)
        lines.append(s)
        a.out.write_text("\n".join(lines) + "\n")

    with tempfile.TemporaryDirectory() as tmp:
        args = ["run", *a.run_args, "--out", str(Path(tmp) / "r.h5"), "--overwrite",
                "--no-progress"]
        for k in range(a.warm):
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                rc = cli_main(args)
            sync()
            say(f"run {k + 1} (unprofiled): {time.perf_counter() - t0:.2f} s, rc {rc}")
        pr = cProfile.Profile()
        t0 = time.perf_counter()
        pr.enable()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = cli_main(args)
        sync()
        pr.disable()
        say(f"profiled run: {time.perf_counter() - t0:.2f} s, rc {rc}")
    for key in ("cumulative", "tottime"):
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats(key).print_stats(a.top)
        say(f"\nby {key}:\n" + "\n".join(ln[:160] for ln in s.getvalue().splitlines()[5:]),
            show=False)
    print(f"tables in {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
