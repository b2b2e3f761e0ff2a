#!/usr/bin/env python3
"""Is a change slower? Times the same cases on two versions of the package, interleaved.

Each version is a git revision checked out into a temporary worktree (or the working tree
itself: ``--after .``). Every case runs in a fresh child process per version, alternating
before/after so a load change on the machine hits both alike; each child imports that
version (PYTHONPATH), warms up once, then reports the minimum CPU time of ``--repeats`` runs
(process time of all threads: on a shared machine less noisy than wall time). The ratio
after/before is what to read; absolute seconds depend on the machine and its load.

Cases (a 512 x 512 synthetic movie, 11 images, 0.3 / 0.2 px per frame, noise 2 grey
levels, 21 px subsets):

* ``solve_window m=0`` / ``m=2``: 10,000 POIs, one window;
* ``track m=2``: 2,500 POIs over the 11 images, with the trust checks (the default) and
  without them (``checks=False``; a version without that argument has no checks and runs
  the same as in the first case).

Usage::

    python scripts/benchmarks/compare_versions.py --before faf48d2  # working tree vs faf48d2
    python scripts/benchmarks/compare_versions.py --before v1 --after v2 \\
        --out docs/bench/versions-cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = r"""
import inspect, json, sys, time
import torch
import torch_stsdic as ts
from torch_stsdic import synth
case, repeats, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
torch.set_num_threads(threads)
H = 512
mv = synth.synthetic_movie((H, H), 10, motion=synth.Translation(ut=0.3, vt=0.2), noise_sigma=2.0,
                           seed=1)
imgs = torch.cat([mv.ref[None], mv.frames]).float()
def grid(k):
    ys, xs = torch.meshgrid(torch.linspace(40, H - 41, k), torch.linspace(40, H - 41, k),
                            indexing="ij")
    return torch.stack([xs.flatten(), ys.flatten()], 1)
if case.startswith("solve_window"):
    m = int(case[-1])
    cfg, pts = ts.DICConfig(subset_size=21, m=m), grid(100)
    run = lambda: ts.solve_window(imgs[0], imgs[5 - m:6 + m], pts, cfg)
else:
    kw = {}
    if "checks" in inspect.signature(ts.track).parameters:
        kw["checks"] = not case.endswith("checks=False")
    pts = grid(50)
    run = lambda: ts.track(imgs, points=pts, config=ts.DICConfig(subset_size=21, m=2),
                           progress=False, **kw)
run()
best = float("inf")
for _ in range(repeats):
    t = time.process_time(); run(); best = min(best, time.process_time() - t)
print(json.dumps(best))
"""

CASES = ["solve_window m=0", "solve_window m=2", "track m=2", "track m=2 checks=False"]


def _tree(rev: str, tmp: Path) -> Path:
    """A directory holding version ``rev`` of the package ('.' = the working tree)."""
    if rev == ".":
        return ROOT
    path = tmp / rev.replace("/", "_")
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(path), rev],
                   check=True)
    return path


def _commit(rev: str) -> str:
    if rev == ".":
        return "working tree at " + subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
            text=True).stdout.strip()
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev],
                          capture_output=True, text=True, check=True).stdout.strip()


def _run(tree: Path, case: str, repeats: int, threads: int) -> float | None:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_WAIT_POLICY": "PASSIVE"}
    p = subprocess.run([sys.executable, "-c", CHILD, case, str(repeats), str(threads)],
                       capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    if p.returncode:
        raise SystemExit(f"{case} on {tree} failed:\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="git revision of the baseline")
    ap.add_argument("--after", default=".", help="git revision, or . for the working tree")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per child (min taken)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="children per case and version, alternating (min taken)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--only", default=None, metavar="REGEX", help="cases whose name matches")
    ap.add_argument("--out", default=None, help="JSON record (default: print only)")
    args = ap.parse_args()
    cases = [c for c in CASES if args.only is None or re.search(args.only, c)]
    with tempfile.TemporaryDirectory() as tmp:
        trees = {}
        try:
            trees = {k: _tree(getattr(args, k), Path(tmp)) for k in ("before", "after")}
            times: dict[str, dict[str, float | None]] = {c: {} for c in cases}
            for case in cases:
                for _ in range(args.rounds):
                    for k, tree in trees.items():
                        t = _run(tree, case, args.repeats, args.threads)
                        old = times[case].get(k)
                        times[case][k] = t if old is None or t is None else min(old, t)
        finally:
            for tree in trees.values():
                if tree != ROOT:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                                    str(tree)], check=False)
    rows = []
    print(f"| case | before {_commit(args.before)} (s) | after (s) | after / before |")
    print("|---|---|---|---|")
    for case in cases:
        b, a = times[case].get("before"), times[case].get("after")
        ratio = a / b if a is not None and b else None
        rows.append({"case": case, "before_cpu_s": b, "after_cpu_s": a, "ratio": ratio})
        print(f"| {case} | {_fmt(b)} | {_fmt(a)} | {_fmt(ratio)} |")
    if args.out:
        load = os.getloadavg() if hasattr(os, "getloadavg") else None
        Path(args.out).write_text(json.dumps({
            "before": _commit(args.before), "after": _commit(args.after),
            "threads": args.threads, "repeats": args.repeats, "rounds": args.rounds,
            "machine": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "load_average_at_end": load, "cases": rows,
        }, indent=1) + "\n")


if __name__ == "__main__":
    main()
