#!/usr/bin/env python
"""The solver on a busy machine: ours, the batched loop and OpenCorr, idle and with one and
two competing busy processes, interleaved, medians (issue 35).

    python scripts/benchmarks/bench_load.py                      # -> docs/bench/load-cpu.json
    python scripts/benchmarks/bench_load.py --repeats 5 --loads 0,1,2 --threads 1,2 --m 0,2
    python scripts/benchmarks/bench_load.py --old /tmp/old       # also the code of another tree

The data are ``bench_cli.py``'s: the 1024x1024 pair (``--m 0``) or the 5 frames t = 3..7
(``--m 2``, STS(5)) of the solver benchmark movie, 38,809 POIs (197 x 197, 5 px apart),
21x21 subsets, float32. Each run is a fresh process that imports torch_stsdic before torch
(so with the library's ``OMP_WAIT_POLICY=PASSIVE``, as the ``stsdic`` command runs) and
times, from the images in memory, the B-spline prefilter and ``SubsetSolver.solve`` (seeded
FFT-CC + IC-GN): POI/s = N / (prefilter + solve), ``benchmark.py``'s solve case.

Variants: ``ours`` (this tree: the per-point C++ solve on the CPU), ``batched`` (this tree
with ``TORCH_STSDIC_PER_POINT=0``: the loop of one step of all points at a time, a barrier
per iteration, as before issue 35), ``old`` (``--old TREE``: that tree's code) and
``opencorr`` (``scripts/opencorr``'s harness, FFT-CC + IC-GN1 at every POI, when its binary
is there: ``--opencorr-bin``, default ``/tmp/opencorr/build/bench_native``; m = 0 only).
Load: ``--loads 0,1,2`` competing processes (``python -c "while True: pass"``), started
before a level's runs and killed (by pid) after them. Within a level, every round runs every
(variant, threads, m) once, in a shuffled order; medians over the rounds. The load average
is recorded before every run.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts" / "benchmarks"))
TAG = "BENCH_LOAD "
N_POINTS = 38809


def child(tree: str, folder: str, pts_csv: str, m: int, threads: int) -> dict[str, Any]:
    """One timed solve in this process, with the torch_stsdic of ``tree``."""
    import importlib

    sys.path.insert(0, tree)
    importlib.import_module("torch_stsdic")  # before torch: the library's OpenMP settings
    import numpy as np
    import torch

    from torch_stsdic import DICConfig, SubsetSolver, keep_freed_memory
    from torch_stsdic.io import load_series

    torch.set_num_threads(threads)
    keep_freed_memory()
    ser = load_series(folder)
    imgs = torch.from_numpy(np.stack([ser.numpy(i) for i in range(len(ser))]).astype(
        np.float32))
    ref, frames = imgs[0], imgs[1:]
    pts = torch.from_numpy(np.loadtxt(pts_csv, delimiter=",", skiprows=1)).float()
    t_count = frames.shape[0]
    dt = (torch.arange(t_count, dtype=torch.float32) - m).view(1, -1).expand(len(pts), -1)
    fidx = torch.arange(t_count).expand(len(pts), -1)
    solver = SubsetSolver(DICConfig(subset_size=21, m=m, dtype="float32"))
    c0, t0 = time.process_time(), time.perf_counter()
    ref_img, frames_img = solver.prepare(ref), solver.prepare(frames)
    t1 = time.perf_counter()
    sol = solver.solve(ref_img, frames_img, pts, dt, frame_index=fidx,
                       ref_pixels=ref.unsqueeze(0), frame_pixels=frames)
    t2 = time.perf_counter()
    return {"prefilter_s": t1 - t0, "solve_s": t2 - t1, "time_s": t2 - t0,
            "cpu_s": time.process_time() - c0, "n_points": len(pts),
            "converged": float(sol.ok.float().mean()), "u": float(sol.u.median()),
            "v": float(sol.v.median()), "threads": torch.get_num_threads()}


def run_ours(tree: Path, data: tuple[Path, Path], m: int, threads: int,
             per_point: bool = True) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads),
           "TORCH_STSDIC_PER_POINT": "1" if per_point else "0"}
    env.pop("OMP_WAIT_POLICY", None)  # the library's own setting
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, __file__, "--child", str(tree), str(data[0]),
                        str(data[1]), str(m), str(threads)], capture_output=True, text=True,
                       env=env, cwd=str(REPO))
    wall = time.perf_counter() - t0
    rec = next((json.loads(line[len(TAG):]) for line in p.stdout.splitlines()
                if line.startswith(TAG)), None)
    if rec is None:
        raise RuntimeError(f"child failed ({p.returncode}):\n{p.stdout[-1500:]}\n"
                           f"{p.stderr[-1500:]}")
    rec["process_wall_s"] = wall
    return rec


def run_opencorr(binary: Path, threads: int) -> dict[str, Any]:
    import bench_cli as bc
    import bench_opencorr as bo

    folder, pts_csv, _ = bc.ensure_data(0)
    ref_pgm, tar_pgm = bo.ensure_pgm(folder)
    out_csv = Path("/tmp") / f"bench_load_oc_{os.getpid()}.csv"
    rec = bo.run_opencorr(binary, ref_pgm, tar_pgm, pts_csv, threads, out_csv)
    rec["time_s"] = rec["total_s"] if "total_s" in rec else (
        rec["fftcc_s"] + rec["prep_s"] + rec["icgn_s"])
    return rec


def busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--loads", default="0,1,2")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--m", default="0,2")
    ap.add_argument("--variants", default="ours,batched")
    ap.add_argument("--old", help="another source tree, run as the variant 'old'")
    ap.add_argument("--opencorr-bin", default="/tmp/opencorr/build/bench_native")
    ap.add_argument("--out", default=str(REPO / "docs" / "bench" / "load-cpu.json"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        tree, folder, pts_csv, m, th = args.child
        print(TAG + json.dumps(child(tree, folder, pts_csv, int(m), int(th))), flush=True)
        return
    import bench_cli as bc
    import benchmark as bench

    loads = [int(x) for x in args.loads.split(",")]
    threads = [int(x) for x in args.threads.split(",")]
    ms = [int(x) for x in args.m.split(",")]
    variants = args.variants.split(",") + (["old"] if args.old else [])
    oc_bin = Path(args.opencorr_bin)
    if oc_bin.exists():
        variants.append("opencorr")
    else:
        print(f"note: no OpenCorr binary at {oc_bin} (scripts/opencorr/README.md builds it): "
              "OpenCorr not measured", file=sys.stderr)
    data = {m: bc.ensure_data(m)[:2] for m in ms}
    rng = random.Random(args.seed)
    runs: list[dict[str, Any]] = []
    machine = bench.machine_info(threads, "cpu")
    for load in loads:
        procs = busy(load)
        try:
            time.sleep(1.0)
            for rnd in range(args.repeats):
                cases = [(v, t, m) for v in variants for t in threads for m in ms
                         if v != "opencorr" or m == 0]
                rng.shuffle(cases)
                for v, t, m in cases:
                    la = os.getloadavg()[0]
                    if v == "opencorr":
                        rec = run_opencorr(oc_bin, t)
                    else:
                        tree = Path(args.old) if v == "old" else REPO
                        rec = run_ours(tree, data[m], m, t, per_point=v != "batched")
                    rec.update(variant=v, threads=t, m=m, load=load, round=rnd, loadavg=la)
                    runs.append(rec)
                    print(f"load {load} round {rnd} {v:<9} m={m} {t} thr: "
                          f"{rec['time_s']:.3f} s (loadavg {la:.2f})", flush=True)
        finally:
            stop(procs)
        summary = summarise(runs, loads, threads, ms, variants)  # written after every level
        record = {"what": "issue 35: POI/s idle and with competing busy processes",
                  "command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"),
                  "machine": machine, "n_points": N_POINTS, "summary": summary, "runs": runs}
        Path(args.out).write_text(json.dumps(record, indent=1))
    print_table(summary)
    print(f"-> {args.out}")


def summarise(runs, loads, threads, ms, variants) -> list[dict[str, Any]]:
    out = []
    for load in loads:
        for m in ms:
            for v in variants:
                for t in threads:
                    sel = [r for r in runs if (r["load"], r["m"], r["variant"], r["threads"]) ==
                           (load, m, v, t)]
                    if not sel:
                        continue
                    med = statistics.median(r["time_s"] for r in sel)
                    out.append({"load": load, "m": m, "variant": v, "threads": t,
                                "time_s": med, "poi_per_s": N_POINTS / med,
                                "times": [round(r["time_s"], 3) for r in sel],
                                "loadavg": statistics.median(r["loadavg"] for r in sel)})
    return out


def print_table(summary) -> None:
    print(f"\n{'busy':>4} {'m':>2} {'variant':<9}{'thr':>4}{'median s':>10}{'POI/s':>9}"
          f"{'loadavg':>9}")
    for s in summary:
        print(f"{s['load']:>4} {s['m']:>2} {s['variant']:<9}{s['threads']:>4}"
              f"{s['time_s']:>10.3f}{s['poi_per_s']:>9.0f}{s['loadavg']:>9.2f}")


if __name__ == "__main__":
    main()
