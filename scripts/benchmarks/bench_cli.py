#!/usr/bin/env python
"""``stsdic run`` end to end next to the bare solver, on the same 1024x1024 pair.

    python scripts/benchmarks/bench_cli.py  # -> docs/bench/cli-cpu.json, prints a table
    python scripts/benchmarks/bench_cli.py --repeats 5 --threads 1

The data: the solver benchmark's movie (``scripts/benchmarks/benchmark.py``: 1024x1024 8-bit
speckle, noise sigma 2, u = 1.3 + 0.15 t, v = -0.7 + 0.1 t px), its reference and the frame at t = 5
written as two TIFF files, and its 38,809 POIs (197 x 197, 5 px apart) as a CSV file; subset
21, classical DIC (``--m 0``; ``--m 2`` solves STS(5) on the frames t = 3..7 instead).

Cases, each in a fresh process (its peak RSS from ``wait4``):

- ``bare``: the images already in memory, ``SubsetSolver.prepare`` (B-spline prefilter) of
  the reference and the frames, then ``SubsetSolver.solve`` (seeded FFT-CC + IC-GN) of the
  target frame: the solver's own throughput (``benchmark.py``'s "solve" case), in a process
  set up as the command sets it up (:func:`torch_stsdic.keep_freed_memory`);
- ``bare, default malloc`` (``--default-malloc``): the same with glibc's default settings;
- ``cli``: ``stsdic run DIR --points poi.csv --subset 21 --m M --out r.h5``, checks on, timed
  inside the process by stage (reading + prefilter of the frames, planning, the solve of
  every block, the checks, the strains, writing) and as the command's own time (from the
  start of ``execute``, after Python's imports), and as a whole process (imports included);
- ``cli --no-checks``: the same without the trust checks.

POI/s counts the POIs of the deformed frame(s): ``stsdic run`` also reports the reference
frame's row (it is a target by default); its cost is part of the command's time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts" / "benchmarks"))

import benchmark as bench  # noqa: E402  (the movie, the POI grid, the machine record)

TAG = "BENCH_CLI "


def ensure_data(m: int) -> tuple[Path, Path, int]:
    """(folder of the TIFF frames, POI csv, number of deformed frames) for half-window m."""
    import numpy as np
    from PIL import Image

    movie = bench.ensure_movie(1024)
    folder = bench.cache_dir() / f"cli_pair_m{m}_v{bench.MOVIE_VERSION}"
    pts_csv = bench.cache_dir() / "cli_poi_197x5.csv"
    if not pts_csv.exists():
        pts = bench.poi_grid(1024, 197, 21, 5).numpy()
        np.savetxt(pts_csv, pts, delimiter=",", header="x,y", comments="", fmt="%g")
    t_c = int(bench.CENTRE_T)  # frames[i] is t = i + 1
    sel = list(range(t_c - 1 - m, t_c + m))
    if not folder.exists():
        data = np.load(movie)
        tmp = Path(tempfile.mkdtemp(dir=bench.cache_dir()))
        Image.fromarray(data["ref"]).save(tmp / "img000.tif")
        for j, i in enumerate(sel):
            Image.fromarray(data["frames"][i]).save(tmp / f"img{j + 1:03d}.tif")
        os.replace(tmp, folder)
    return folder, pts_csv, len(sel)


# ---------------------------------------------------------------------------------------
# children
# ---------------------------------------------------------------------------------------
def child_bare(folder: str, pts_csv: str, m: int, device: str = "cpu",
               malloc: str = "kept") -> dict[str, Any]:
    import numpy as np
    import torch

    from torch_stsdic import DICConfig, SubsetSolver, keep_freed_memory
    from torch_stsdic.io import load_series

    if malloc == "kept":
        keep_freed_memory()  # the process set up as the command sets it up

    ser = load_series(folder)
    imgs = torch.from_numpy(np.stack([ser.numpy(i) for i in range(len(ser))]).astype(
        np.float32))
    ref, frames = imgs[0], imgs[1:]
    pts = torch.from_numpy(np.loadtxt(pts_csv, delimiter=",", skiprows=1)).float()
    t_count = frames.shape[0]
    dt = (torch.arange(t_count, dtype=torch.float32) - m).view(1, -1).expand(len(pts), -1)
    fidx = torch.arange(t_count).expand(len(pts), -1)
    solver = SubsetSolver(DICConfig(subset_size=21, m=m, dtype="float32"))
    dev = torch.device(device)
    ref, frames, pts, dt, fidx = (x.to(dev) for x in (ref, frames, pts, dt, fidx))

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()
    if dev.type == "cuda":  # the first CUDA call of a process pays for its context and kernels
        solver.solve(solver.prepare(ref), solver.prepare(frames), pts[:64], dt[:64],
                     frame_index=fidx[:64], ref_pixels=ref.unsqueeze(0), frame_pixels=frames)
        sync()
    t0 = time.perf_counter()
    ref_img, frames_img = solver.prepare(ref), solver.prepare(frames)
    sync()
    t1 = time.perf_counter()
    sol = solver.solve(ref_img, frames_img, pts, dt, frame_index=fidx,
                       ref_pixels=ref.unsqueeze(0), frame_pixels=frames)
    sync()
    t2 = time.perf_counter()
    return {"prefilter_s": t1 - t0, "solve_s": t2 - t1, "time_s": t2 - t0,
            "n_points": len(pts), "converged": float(sol.ok.float().mean()),
            "u": float(sol.u.median()), "v": float(sol.v.median())}


def child_cli(argv: list[str]) -> dict[str, Any]:
    """``stsdic run`` in this process, its stages timed by wrapping the functions."""
    import torch_stsdic.cli.run as run
    import torch_stsdic.movie.checks as checks
    import torch_stsdic.movie.plan as plan
    import torch_stsdic.movie.series as series
    import torch_stsdic.movie.sinks as sinks
    from torch_stsdic import keep_freed_memory
    from torch_stsdic.cli import main

    keep_freed_memory()  # as the ``stsdic`` command does at start
    acc: dict[str, float] = {}

    def timed(owner, name, key):
        fn = getattr(owner, name)

        def wrapper(*a, **kw):
            t = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                acc[key] = acc.get(key, 0.0) + time.perf_counter() - t
        setattr(owner, name, wrapper)

    timed(run, "_track_arguments", "inputs_s")
    timed(plan, "plan_run", "plan_s")
    timed(series, "solve_block", "blocks_s")
    for nm in ("check_model", "rescue_classical", "check_fit", "check_neighbours"):
        timed(checks.BlockChecks, nm, "checks_s")
    timed(sinks.HDF5Sink, "write_rows", "write_s")
    timed(sinks.HDF5Sink, "finish", "strain_s")
    timed(run, "execute", "command_s")
    times: dict[str, float] = {}
    orig = series.FrameCache.times

    def keep_times(self):
        times.update(orig(self))
        return orig(self)
    series.FrameCache.times = keep_times
    code = main(argv)
    out = {**acc, **{f"frames_{k}": v for k, v in times.items()}, "exit": code}
    out["solve_s"] = acc.get("blocks_s", 0.0) - acc.get("checks_s", 0.0) - times.get(
        "wait_s", 0.0)
    return out


def run_child(args: list[str], threads: int) -> tuple[dict[str, Any], float, float]:
    """(the child's JSON, wall seconds, peak RSS MB) of ``python bench_cli.py --child ...``."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads),
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, __file__, "--threads", str(threads), "--child", *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    out, err = p.stdout.read(), p.stderr.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    rec = next((json.loads(line[len(TAG):]) for line in out.splitlines()
                if line.startswith(TAG)), None)
    if rec is None:
        raise RuntimeError(f"child {args} failed ({p.returncode}):\n{out[-2000:]}\n"
                           f"{err[-2000:]}")
    return rec, wall, usage.ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--m", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the bare solve and --device)")
    ap.add_argument("--default-malloc", action="store_true",
                    help="also the bare solve with glibc's default malloc settings (the "
                         "others run with keep_freed_memory, as the command does)")
    ap.add_argument("--out", default=None, help="JSON record (default docs/bench/cli-cpu.json)")
    ap.add_argument("--child", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    if args.child:
        kind, rest = args.child[0], args.child[1:]
        rec = (child_bare(*rest[:2], int(rest[2]), *rest[3:5]) if kind == "bare"
               else child_cli(rest))
        print(TAG + json.dumps(rec), flush=True)
        return
    folder, pts_csv, n_frames = ensure_data(args.m)
    out_h5 = bench.cache_dir() / f"cli_r{os.getpid()}.h5"
    cli = ["run", str(folder), "--points", str(pts_csv), "--subset", "21", "--m",
           str(args.m), "--out", str(out_h5), "--overwrite", "--no-progress",
           "--threads", str(args.threads), "--device", args.device]
    if args.m:  # the bare solver's one window: its centre frame as the only target
        cli += ["--frames", str(args.m + 1)]
    cases = {"bare": ["bare", str(folder), str(pts_csv), str(args.m), args.device],
             "cli": ["cli", *cli], "cli --no-checks": ["cli", *cli, "--no-checks"]}
    if args.default_malloc:
        cases["bare, default malloc"] = [*cases["bare"], "default"]
    runs: dict[str, list[dict[str, Any]]] = {k: [] for k in cases}
    for _ in range(args.repeats):  # interleaved: the machine's load hits every case alike
        for name, child in cases.items():
            rec, wall, rss = run_child(child, args.threads)
            runs[name].append({**rec, "process_wall_s": wall, "max_rss_mb": rss})
            own = rec.get("time_s", rec.get("command_s", float("nan")))
            print(f"# {name}: {own:.3f} s (process {wall:.2f} s, {rss:.0f} MB)", flush=True)
    out_h5.unlink(missing_ok=True)
    n = 38_809

    def med(name, key):
        vals = [r[key] for r in runs[name] if key in r]
        return statistics.median(vals) if vals else None

    summary: dict[str, Any] = {}
    for name in cases:
        t = med(name, "time_s" if name.startswith("bare") else "command_s")
        summary[name] = {
            "time_s": t, "poi_per_s": n / t, "process_wall_s": med(name, "process_wall_s"),
            "process_poi_per_s": n / med(name, "process_wall_s"),
            "max_rss_mb": med(name, "max_rss_mb"),
        }
        if name.startswith("cli"):
            summary[name]["stages_s"] = {k: med(name, k) for k in (
                "inputs_s", "plan_s", "frames_read_s", "frames_prefilter_s",
                "frames_ahead_read_s", "frames_ahead_prefilter_s", "frames_wait_s",
                "solve_s", "checks_s", "write_s", "strain_s")}
    for name in ("cli", "cli --no-checks"):
        summary[name]["vs_bare"] = summary[name]["poi_per_s"] / summary["bare"]["poi_per_s"]
    record = {"kind": "cli", "date": time.strftime("%Y-%m-%d"), "m": args.m,
              "n_points": n, "deformed_frames": n_frames, "threads": args.threads,
              "repeats": args.repeats, "device": args.device,
              "machine": bench.machine_info([args.threads], args.device),
              "summary": summary, "runs": runs}
    path = Path(args.out) if args.out else bench.BENCH_DIR / (
        f"cli-{args.device}.json" if args.m == 0 else f"cli-{args.device}-m{args.m}.json")
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"{'case':<18}{'time s':>8}{'POI/s':>9}{'x bare':>8}{'process s':>11}"
          f"{'max RSS MB':>12}")
    for name, s in summary.items():
        print(f"{name:<18}{s['time_s']:>8.2f}{s['poi_per_s']:>9.0f}"
              f"{s.get('vs_bare', 1.0):>8.2f}{s['process_wall_s']:>11.2f}"
              f"{s['max_rss_mb']:>12.0f}")
    print_stages(summary)
    print(f"-> {path}")


def print_stages(summary: dict[str, Any]) -> None:
    """One line per ``stsdic run`` case: its stage times (s)."""
    for name in ("cli", "cli --no-checks"):
        st = summary[name]["stages_s"]
        print(f"{name}: " + ", ".join(f"{k[:-2]} {v:.3f}" for k, v in st.items()
                                      if v is not None))


if __name__ == "__main__":
    main()
