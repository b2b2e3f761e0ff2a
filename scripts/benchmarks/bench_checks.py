#!/usr/bin/env python
"""What the trust checks cost on a real series: ``stsdic run ARGS`` with and without
``--no-checks``, interleaved pairs of fresh processes, the command's own time (from the start
of ``execute``, after Python's imports; ``scripts/benchmarks/bench_cli.py``'s child) and its stages.

    python scripts/benchmarks/bench_checks.py --pairs 5 -- ../shared/data/dic-challenge-sample12/ \\
        --subset 31 --step 10 --roi 58 60 334 1020 --mask s12_mask.png --m 2

Prints each run, then the medians and the ratio checked / unchecked (issue 23 asks for at most
1.3x on sample 12 and the hourglass); ``--out FILE`` keeps them as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_cli as bc  # noqa: E402  (the timed child and run_child)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--out", default=None, help="JSON record of every run")
    ap.add_argument("run_args", nargs=argparse.REMAINDER, help="-- then stsdic run's arguments")
    args = ap.parse_args()
    run_args = [a for a in args.run_args if a != "--"] if args.run_args else []
    if not run_args:
        ap.error("give stsdic run's arguments after --")
    out_h5 = Path(tempfile.gettempdir()) / f"bench_checks_{os.getpid()}.h5"
    base = ["cli", "run", *run_args, "--out", str(out_h5), "--overwrite", "--no-progress",
            "--threads", str(args.threads)]
    cases = {"checks": base, "no checks": [*base, "--no-checks"]}
    runs: dict[str, list[dict]] = {k: [] for k in cases}
    for i in range(args.pairs):
        for name, child in cases.items():
            rec, wall, rss = bc.run_child(child, args.threads)
            if rec.get("exit"):
                raise SystemExit(f"stsdic run failed (exit {rec['exit']}): {run_args}")
            runs[name].append({**rec, "process_wall_s": wall, "max_rss_mb": rss})
            print(f"pair {i}: {name:<10} {rec['command_s']:.3f} s (checks "
                  f"{rec.get('checks_s', 0.0):.3f} s, {rss:.0f} MB)", flush=True)
    out_h5.unlink(missing_ok=True)
    med = {k: statistics.median(r["command_s"] for r in v) for k, v in runs.items()}
    ratios = [a["command_s"] / b["command_s"] for a, b in zip(runs["checks"], runs["no checks"])]
    print(f"median: checks {med['checks']:.3f} s, no checks {med['no checks']:.3f} s, "
          f"ratio {med['checks'] / med['no checks']:.3f} (pairs {min(ratios):.2f}-"
          f"{max(ratios):.2f}); {args.threads} threads")
    if args.out:
        Path(args.out).write_text(json.dumps(
            {"date": time.strftime("%Y-%m-%d"), "args": run_args, "threads": args.threads,
             "median_s": med, "ratio": med["checks"] / med["no checks"], "pair_ratios": ratios,
             "runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
