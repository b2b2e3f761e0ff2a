#!/usr/bin/env python
"""The solver on a busy machine: ours, the batched loop, ``nn.STSDIC`` and OpenCorr, idle and
with one and two competing busy processes, both import orders, interleaved, medians (issues
35 and 46).

    python scripts/benchmarks/bench_load.py                      # -> docs/bench/load-cpu.json
    python scripts/benchmarks/bench_load.py --repeats 5 --loads 0,1,2 --threads 1,2 --m 0,2
    python scripts/benchmarks/bench_load.py --old /tmp/old       # also the code of another tree
    python scripts/benchmarks/bench_load.py --order-record       # issue 46's record (below)

The data are ``bench_cli.py``'s: the 1024x1024 pair (``--m 0``) or the 5 frames t = 3..7
(``--m 2``, STS(5)) of the solver benchmark movie, 38,809 POIs (197 x 197, 5 px apart),
21x21 subsets, float32. Each run is a fresh process that times, from the images in memory,
the B-spline prefilter and ``SubsetSolver.solve`` (seeded FFT-CC + IC-GN): POI/s = N /
(prefilter + solve), ``benchmark.py``'s solve case.

Import order (``--orders lib,torch``, issue 46): ``lib`` imports torch_stsdic before torch
(so with the library's ``OMP_WAIT_POLICY=PASSIVE``, as the ``stsdic`` command runs);
``torch`` imports torch, numpy and tifffile first, as a PyTorch program does (torch's OpenMP
threads then spin while they wait, libgomp's default). ``OMP_WAIT_POLICY`` is removed from
the children's environment.

Variants: ``ours`` (this tree: the per-point C++ solve on the CPU), ``batched`` (this tree
with ``TORCH_STSDIC_PER_POINT=0``: the loop of one step of all points at a time, a barrier
per iteration, as before issue 35), ``old`` (``--old TREE``: that tree's code) and
``opencorr`` (``scripts/opencorr``'s harness, FFT-CC + IC-GN1 at every POI, when its binary
is there: ``--opencorr-bin``, default ``/tmp/opencorr/build/bench_native``; m = 0 only) and
``nn`` (this tree's ``torch_stsdic.nn.STSDIC`` forward, B = 1, the same POIs, under
``torch.no_grad()``: a learning pipeline's path; prefilter included) and ``window``
(``solve_window`` called on the 8-bit images as ``tifffile`` reads them, as a user's script
does: the conversion of its inputs included; ``--old-kind window`` times that in the old tree).
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


def child(tree: str, folder: str, pts_csv: str, m: int, threads: int, order: str = "lib",
          kind: str = "solve") -> dict[str, Any]:
    """One timed solve (``kind`` "solve": ``SubsetSolver``; "nn": ``nn.STSDIC`` forward;
    "window": ``solve_window`` on the 8-bit images as tifffile reads them, a user's call) in
    this process, with the torch_stsdic of ``tree`` imported before (``order`` "lib") or after
    (``order`` "torch") torch."""
    import importlib

    sys.path.insert(0, tree)
    if order == "torch":  # a PyTorch program: torch (and friends) first
        import numpy  # noqa: F401
        import tifffile  # noqa: F401
        import torch  # noqa: F401
    importlib.import_module("torch_stsdic")  # first for "lib": the library's OpenMP settings
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
    cfg = DICConfig(subset_size=21, m=m, dtype="float32")
    if kind == "window":
        import glob

        import tifffile

        from torch_stsdic import solve_window

        names = sorted(glob.glob(os.path.join(folder, "*.tif")))
        ref8 = tifffile.imread(names[0])
        frames8 = np.stack([tifffile.imread(n) for n in names[1:]])
        c0, t0 = time.process_time(), time.perf_counter()
        sol = solve_window(ref8, frames8[0] if m == 0 else frames8, pts, cfg)
        t2 = time.perf_counter()
        return {"time_s": t2 - t0, "cpu_s": time.process_time() - c0, "n_points": len(pts),
                "converged": float(sol.ok.float().mean()), "u": float(sol.u.median()),
                "v": float(sol.v.median()), "threads": torch.get_num_threads()}
    if kind == "nn":
        from torch_stsdic.nn import STSDIC

        net = STSDIC(cfg)
        c0, t0 = time.process_time(), time.perf_counter()
        with torch.no_grad():
            out = net.forward_full(ref.unsqueeze(0), frames.unsqueeze(0), pts)
        t2 = time.perf_counter()
        return {"time_s": t2 - t0, "cpu_s": time.process_time() - c0, "n_points": len(pts),
                "converged": float(out.ok.float().mean()), "u": float(out.disp[0, :, 0].median()),
                "v": float(out.disp[0, :, 1].median()), "threads": torch.get_num_threads()}
    solver = SubsetSolver(cfg)
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
             per_point: bool = True, order: str = "lib", kind: str = "solve"
             ) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads),
           "TORCH_STSDIC_PER_POINT": "1" if per_point else "0"}
    env.pop("OMP_WAIT_POLICY", None)  # the library's own setting
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, __file__, "--child", str(tree), str(data[0]),
                        str(data[1]), str(m), str(threads), order, kind],
                       capture_output=True, text=True, env=env, cwd=str(REPO))
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
    ap.add_argument("--variants", default="ours,batched", help="ours, batched, nn, window (old and "
                    "opencorr join by --old and when OpenCorr's binary is there)")
    ap.add_argument("--orders", default="lib,torch",
                    help="import orders: lib (torch_stsdic first), torch (torch first)")
    ap.add_argument("--order-record", action="store_true",
                    help="issue 46's record: --loads 0,1,2 --threads 1,2 --m 0 "
                         "--variants ours,nn --orders lib,torch "
                         "--out docs/bench/load-order-cpu.json")
    ap.add_argument("--old", help="another source tree, run as the variant 'old'")
    ap.add_argument("--old-kind", default="solve", choices=["solve", "nn", "window"],
                    help="what the variant 'old' times (that of ours, nn or window)")
    ap.add_argument("--note", help="what the variants stand for (e.g. what --old is), kept in "
                    "the record")
    ap.add_argument("--opencorr-bin", default="/tmp/opencorr/build/bench_native")
    ap.add_argument("--out", default=str(REPO / "docs" / "bench" / "load-cpu.json"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--summarise", metavar="RECORD",
                    help="print the table, ratios and round pairs of a record; run nothing")
    ap.add_argument("--child", nargs=7, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        tree, folder, pts_csv, m, th, order, kind = args.child
        print(TAG + json.dumps(child(tree, folder, pts_csv, int(m), int(th), order, kind)),
              flush=True)
        return
    if args.summarise:
        rec = json.loads(Path(args.summarise).read_text())
        print_table(rec["summary"])
        for r in ratios(rec["summary"]) + pair_ratios(rec["runs"]):
            print(r)
        return
    if args.order_record:
        args.loads, args.threads, args.m = "0,1,2", "1,2", "0"
        args.variants, args.orders = "ours,nn", "lib,torch"
        args.out = str(REPO / "docs" / "bench" / "load-order-cpu.json")
    import bench_cli as bc
    import benchmark as bench

    loads = [int(x) for x in args.loads.split(",")]
    threads = [int(x) for x in args.threads.split(",")]
    ms = [int(x) for x in args.m.split(",")]
    orders = args.orders.split(",")
    if any(o not in ("lib", "torch") for o in orders):
        ap.error(f"--orders: lib and/or torch, got {args.orders!r}")
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
    uptime = {"before": _uptime()}
    for load in loads:
        procs = busy(load)
        try:
            time.sleep(1.0)
            for rnd in range(args.repeats):
                cases = [(v, t, m, "-" if v == "opencorr" else o) for v in variants
                         for t in threads for m in ms for o in orders
                         if v != "opencorr" or (m == 0 and o == orders[0])]
                rng.shuffle(cases)
                for v, t, m, o in cases:
                    la = os.getloadavg()[0]
                    if v == "opencorr":
                        rec = run_opencorr(oc_bin, t)
                    else:
                        tree = Path(args.old) if v == "old" else REPO
                        kind = (args.old_kind if v == "old" else
                                v if v in ("nn", "window") else "solve")
                        rec = run_ours(tree, data[m], m, t, per_point=v != "batched", order=o,
                                       kind=kind)
                    rec.update(variant=v, threads=t, m=m, order=o, load=load, round=rnd,
                               loadavg=la)
                    runs.append(rec)
                    print(f"load {load} round {rnd} {v:<9} {o:<5} m={m} {t} thr: "
                          f"{rec['time_s']:.3f} s (loadavg {la:.2f})", flush=True)
        finally:
            stop(procs)
        summary = summarise(runs, loads, threads, ms, variants)  # written after every level
        uptime["after"] = _uptime()
        record = {"what": "issues 35, 46: POI/s idle and with competing busy processes, "
                          "both import orders",
                  "command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%d %H:%M"),
                  **({"note": args.note} if args.note else {}),
                  "machine": machine, "uptime": uptime, "n_points": N_POINTS,
                  "summary": summary, "ratios": ratios(summary),
                  "pairs": pair_ratios(runs), "runs": runs}
        Path(args.out).write_text(json.dumps(record, indent=1))
    print_table(summary)
    for r in ratios(summary) + pair_ratios(runs):
        print(r)
    print(f"-> {args.out}")


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())


def summarise(runs, loads, threads, ms, variants) -> list[dict[str, Any]]:
    out = []
    orders = sorted({r.get("order", "lib") for r in runs})
    for load in loads:
        for m in ms:
            for v in variants:
                for t in threads:
                    for o in orders:
                        sel = [r for r in runs if (r["load"], r["m"], r["variant"],
                                                   r["threads"], r.get("order", "lib")) ==
                               (load, m, v, t, o)]
                        if not sel:
                            continue
                        med = statistics.median(r["time_s"] for r in sel)
                        out.append({"load": load, "m": m, "variant": v, "threads": t,
                                    "order": o, "time_s": med, "poi_per_s": N_POINTS / med,
                                    "times": [round(r["time_s"], 3) for r in sel],
                                    "loadavg": statistics.median(r["loadavg"] for r in sel)})
    return out


def ratios(summary) -> list[str]:
    """The issue-46 comparisons of the medians: torch-first over library-first time, OpenCorr's
    time over ours (speed-up), 2 threads over 1."""
    med = {(s["load"], s["m"], s["variant"], s["threads"], s["order"]): s["time_s"]
           for s in summary}
    out = []
    for (load, m, v, t, o), sec in sorted(med.items()):
        if o == "torch" and (load, m, v, t, "lib") in med:
            out.append(f"busy {load} m={m} {v} {t} thr: torch-first / lib-first time "
                       f"{sec / med[(load, m, v, t, 'lib')]:.2f}")
        oc = med.get((load, m, "opencorr", t, "-"))
        if v == "ours" and oc:
            out.append(f"busy {load} m={m} {o}-first {t} thr: {oc / sec:.2f}x OpenCorr")
        if v != "opencorr" and t == 2 and (load, m, v, 1, o) in med:
            out.append(f"busy {load} m={m} {v} {o}-first: 2 thr / 1 thr time "
                       f"{sec / med[(load, m, v, 1, o)]:.2f}")
    return out


def pair_ratios(runs) -> list[str]:
    """The comparisons of :func:`ratios` made within each round (the runs of one round are
    minutes apart at most, so a shared machine's load changes less between them): the median
    and range over the rounds of the per-round time ratio."""
    t = {(r["load"], r["m"], r["round"], r["variant"], r.get("order", "lib"), r["threads"]):
         r["time_s"] for r in runs}
    keys = {(k[0], k[1], k[3], k[4], k[5]) for k in t}
    rounds = sorted({k[2] for k in t})
    combos = []  # (label, numerator, denominator) as (variant, order, threads)
    for (load, m, v, o, th) in sorted(keys):
        if o == "torch" and (load, m, v, "lib", th) in keys:
            combos.append((load, m, f"{v} {th} thr: torch-first / lib-first", (v, o, th),
                           (v, "lib", th)))
        if v == "ours" and (load, m, "opencorr", "-", th) in keys:
            combos.append((load, m, f"{o}-first {th} thr: OpenCorr / ours (x OpenCorr)",
                           ("opencorr", "-", th), (v, o, th)))
        if v == "ours" and (load, m, "old", o, th) in keys:
            combos.append((load, m, f"{o}-first {th} thr: ours / old", (v, o, th),
                           ("old", o, th)))
        if th == 2 and (load, m, v, o, 1) in keys:
            combos.append((load, m, f"{v} {o}: 2 thr / 1 thr", (v, o, 2), (v, o, 1)))
    out = []
    for load, m, label, num, den in combos:
        rs = [t[(load, m, r) + num] / t[(load, m, r) + den] for r in rounds
              if (load, m, r) + num in t and (load, m, r) + den in t]
        if rs:
            out.append(f"pairs busy {load} m={m} {label}: median {statistics.median(rs):.2f} "
                       f"({min(rs):.2f}-{max(rs):.2f}, {len(rs)} rounds)")
    return out


def print_table(summary) -> None:
    print(f"\n{'busy':>4} {'m':>2} {'variant':<9}{'order':<6}{'thr':>4}{'median s':>10}"
          f"{'POI/s':>9}{'loadavg':>9}")
    for s in summary:
        print(f"{s['load']:>4} {s['m']:>2} {s['variant']:<9}{s['order']:<6}{s['threads']:>4}"
              f"{s['time_s']:>10.3f}{s['poi_per_s']:>9.0f}{s['loadavg']:>9.2f}")


if __name__ == "__main__":
    main()
