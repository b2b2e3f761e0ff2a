#!/usr/bin/env python
"""Benchmark torch_stsdic: throughput (POI/s), time split and peak memory.

Presets (one command each; every preset writes a JSON record and prints a table):

    cd scripts/benchmarks   # or give the path: python scripts/benchmarks/benchmark.py ...
    python benchmark.py --quick      # seconds: smoke test (used by the test suite)
    python benchmark.py --targets    # the target cases  -> docs/bench/targets-<dev>.json
    python benchmark.py --full       # m x subset x N x dtype -> docs/bench/full-<dev>.json
    python benchmark.py --memory     # 1000-frame 1024x1024 TIFF through sts.track
    python benchmark.py --movie      # 500-frame 1024x1024 TIFF, 10,000 POIs, STS(5):
                                     # frames/s, time split -> docs/bench/movie-<dev>.json
    python benchmark.py --report     # only rewrite docs/benchmarks.md from docs/bench/

``--device cuda`` (or ``auto``) runs on the GPU; ``--threads N`` sets torch's intra-op threads
(default: all cores of the process' CPU affinity). After ``--targets/--full/--memory`` the
tables between the ``<!-- BEGIN AUTOGEN ... -->`` markers of docs/benchmarks.md are
regenerated from every JSON record in docs/bench/ (``--no-update-doc`` to skip).

Measurements
    Solver cases ("solve"): a 1024x1024 8-bit speckle movie (rendered once by
    torch_stsdic.synth, cached in the temp dir), reference at t = 0, frames t = 1..9 moving by
    u = 1.3 + 0.15 t, v = -0.7 + 0.1 t px, noise sigma 2 grey levels. A window of 2m+1 frames
    centred on t = 5 is solved at N POIs. The time is split into
      prefilter     ``solver.prepare(ref)`` + ``solver.prepare(frames)`` (B-spline coefficients)
      initial guess ``solver.initial_guess`` (FFT cross-correlation on every frame + line fit)
      iterations    ``solver.solve(..., init=p0)`` (Gauss-Newton, init given separately)
    POI/s = N / (prefilter + initial guess + iterations) ("total"); "iter POI/s" uses the
    iterations alone. One warm-up run (same case, at most 8192 POIs) precedes the timed repeats;
    the median of the repeats is reported, with the min and the process CPU time.
    Track cases: the whole ``sts.track`` call (reads, prefilter, FFT-CC, carried guesses).

    Memory: CPU - every case runs in a fresh subprocess; "peak MB" is the rise of
    ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` over the process' level after loading the
    inputs (the working set of the solve), "RSS peak" the process' absolute high-water mark.
    CUDA - ``torch.cuda.max_memory_allocated`` minus the memory allocated before the run, and
    ``cfg.memory_mb`` is sized from ``torch.cuda.mem_get_info`` (free memory).

    Movie (``--movie``): a synthetic 1024x1024 uint8 TIFF movie of ``--movie-frames`` frames
    (default 500; written once by torch_stsdic.synth into the bench cache) through the steps
    of ``sts.track`` (plan_run, an HDF5 sink, run_plan) at ``--movie-points`` POIs (default
    10,000, a regular square grid, 9 px apart), STS(5), 21x21, float32. Reported: frames/s
    and POI-frames/s over the whole run (planning and the final strains included), and the
    time split - read and
    prefilter (in the calling thread, and in the read-ahead thread, overlapped), waiting for
    frames, solve (``solve_block`` minus its wait for frames), write (the block loop's wait
    for the writer's thread, and the final ``finish``; the writer's own seconds beside the
    solves in ``writer_busy_s``) and the rest - and "overhead" = everything but the solve,
    as a share of the wall time.
    ``--movie-read-ahead 0`` switches the read-ahead thread off (the comparison case).

    Timing on CUDA brackets every stage with ``torch.cuda.synchronize()``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import importlib
import json
import math
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "benchmarks.md"
BENCH_DIR = REPO / "docs" / "bench"
CHILD_TAG = "BENCH_RESULT "
MOVIE_VERSION = 1
# the solver movie: reference at t = 0, frames at t = 1..9
MOTION = {"u0": 1.3, "v0": -0.7, "ut": 0.15, "vt": 0.1}
CENTRE_T = 5.0
NOISE = 2.0

# targets (docs/benchmarks.md): name -> (goal, comparison)
TARGETS = {
    "table1_sts5_s": (1.0, "paper: 95.7 s"),
    "table1_ratio": (4.0, "paper: 32x"),
    "cpu_classical_poi_s": (35_000.0, "OpenCorr's published 34,650 POI/s, another machine; "
                                      "measured here side by side: 53,508 on 2026-11-26, "
                                      "opencorr-cpu.json"),
    "cpu_sts5_poi_s": (10_000.0, ""),
    "gpu_classical_poi_s": (1e6, ""),
    "gpu_sts5_poi_s": (2e5, ""),
    "memory_rss_mb": (1024.0, "1000 frames x 1024x1024 uint8 = 1000 MiB on disk"),
    "movie_overhead_share": (0.20, "issue 16: everything but the solve"),
    "gpu_movie_frames_s": (100.0, "issue 16: one H100, from TIFF files"),
}


# ---------------------------------------------------------------------------------------
# machine record
# ---------------------------------------------------------------------------------------
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _git(*args: str) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                             timeout=10)
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _code_hash() -> dict[str, str]:
    """sha1 (12 hex) of the solver sources measured: the tree changes while people work."""
    out = {}
    for rel in ("core/solver.py", "core/interpolation.py", "core/initial.py", "movie/series.py"):
        p = REPO / "torch_stsdic" / rel
        if p.exists():  # keyed by the file's name, as in the records before the layer folders
            out[p.name] = hashlib.sha1(p.read_bytes()).hexdigest()[:12]
    return out


def machine_info(threads: list[int], device: str) -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {
        "cpu_model": _cpu_model(),
        "cores": _cores(),
        "logical_cpus": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": threads,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "git_commit": _git("rev-parse", "--short", "HEAD"),
        "git_dirty_files": [ln[3:] for ln in _git("status", "--porcelain").splitlines()
                            if ln[3:].startswith("torch_stsdic/")],
        "code_sha1": _code_hash(),
        "compile_mode": os.environ.get("TORCH_STSDIC_COMPILE", "default"),
        "native_mode": os.environ.get("TORCH_STSDIC_NATIVE", "default"),
        "omp_env": {k: v for k, v in os.environ.items()
                    if k.startswith(("OMP_", "MKL_", "GOMP_", "KMP_"))},
        "device": device,
    }
    try:
        import psutil

        info["physical_cores"] = psutil.cpu_count(logical=False)
        info["memory_gb"] = round(psutil.virtual_memory().total / 2**30, 1)
    except ImportError:
        pass
    if device == "cuda" and torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info["gpu"] = p.name
        info["gpu_memory_gb"] = round(p.total_memory / 2**30, 1)
        info["cuda"] = torch.version.cuda
    return info


# ---------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------
def cache_dir() -> Path:
    d = Path(os.environ.get("STSDIC_BENCH_CACHE", Path(tempfile.gettempdir()) / "stsdic_bench"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def movie_path(size: int) -> Path:
    return cache_dir() / f"movie{size}_v{MOVIE_VERSION}.npz"


def ensure_movie(size: int) -> Path:
    """Render (once) the solver benchmark movie: ref (H, W) and frames (9, H, W), uint8."""
    path = movie_path(size)
    if path.exists():
        return path
    import numpy as np
    import torch

    from torch_stsdic.synth import Translation, make_speckle, render_series

    pattern = make_speckle((size, size), seed=1)
    ref, frames = render_series(pattern, (size, size), Translation(**MOTION),
                                torch.arange(1.0, 10.0), noise_sigma=NOISE, bits=8, seed=2,
                                reference_time=None)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, ref=ref.numpy().astype(np.uint8), frames=frames.numpy().astype(np.uint8))
    os.replace(tmp, path)
    return path


def table1_path(size: int, n_frames: int) -> Path:
    return cache_dir() / f"table1_{size}x{n_frames}_v{MOVIE_VERSION}.npz"


def ensure_table1(size: int, n_frames: int) -> Path:
    """The paper's simulated movie (u = t / 20 px), noise sigma 2, 8-bit: ref + frames."""
    path = table1_path(size, n_frames)
    if path.exists():
        return path
    import numpy as np

    from torch_stsdic.synth import synthetic_movie

    mv = synthetic_movie((size, size), n_frames, noise_sigma=NOISE, bits=8)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, ref=mv.ref.numpy().astype(np.uint8), frames=mv.frames.numpy().astype(np.uint8),
             times=mv.times.numpy())
    os.replace(tmp, path)
    return path


def poi_grid(size: int, n: int, subset: int, step: int | None = None):
    """~n POIs on a square grid (n rounded to a square), or ``n`` per side at ``step`` px."""
    import torch

    margin = subset // 2 + 8  # subset + the largest displacement + interpolation taps
    if step is not None:
        side = n
        span = step * (side - 1)
        lo = margin + (size - 1 - 2 * margin - span) // 2
        pos = lo + step * torch.arange(side, dtype=torch.float64)
    else:
        side = max(2, math.ceil(math.sqrt(n)))
        pos = torch.linspace(margin, size - 1 - margin, side, dtype=torch.float64).round()
    gy, gx = torch.meshgrid(pos, pos, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)


# ---------------------------------------------------------------------------------------
# measurement helpers (child side)
# ---------------------------------------------------------------------------------------
def _maxrss_mb() -> float:
    try:
        import resource

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return r / 1024.0 if sys.platform != "darwin" else r / 2**20
    except ImportError:
        import psutil

        return psutil.Process().memory_info().rss / 2**20


def _rss_now_mb() -> float:
    """Current resident set size (Linux /proc; psutil elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, AttributeError):
        try:
            import psutil

            return psutil.Process().memory_info().rss / 2**20
        except ImportError:
            return float("nan")


class _Clock:
    def __init__(self, device: str) -> None:
        import torch

        self.cuda = device.startswith("cuda")
        self.torch = torch

    def sync(self) -> None:
        if self.cuda:
            self.torch.cuda.synchronize()

    def now(self) -> tuple[float, float]:
        self.sync()
        return time.perf_counter(), time.process_time()


def _cuda_budget_mb(fraction: float = 0.35) -> float:
    import torch

    free, _ = torch.cuda.mem_get_info()
    return max(256.0, fraction * free / 2**20)


def _summary(values: list[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "min": min(values), "n": len(values)}


def _profile(fn, top: int = 15) -> dict[str, Any]:
    """Python-level (cProfile, by own time) and op-level (torch.profiler) top entries."""
    import cProfile
    import pstats

    import torch

    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    st = pstats.Stats(prof)
    rows = []
    for (file, line, func), (_cc, nc, tt, ct, _callers) in st.stats.items():  # type: ignore
        rows.append((tt, ct, nc, f"{Path(file).name}:{line}({func})"))
    rows.sort(reverse=True)
    py = [{"function": r[3], "calls": r[2], "own_s": round(r[0], 4), "cum_s": round(r[1], 4)}
          for r in rows[:top]]
    ops = []
    try:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU]
        if torch.cuda.is_available():
            acts.append(ProfilerActivity.CUDA)
        with profile(activities=acts) as p:
            fn()
        key = "self_cpu_time_total"
        for ev in sorted(p.key_averages(), key=lambda e: getattr(e, key), reverse=True)[:top]:
            ops.append({"op": ev.key, "calls": ev.count,
                        "self_cpu_ms": round(getattr(ev, key) / 1000.0, 2)})
    except Exception as exc:  # profiler unavailable on some builds
        ops.append({"op": f"(torch.profiler failed: {exc})", "calls": 0, "self_cpu_ms": 0})
    return {"python_top": py, "ops_top": ops}


# ---------------------------------------------------------------------------------------
# cases (child side)
# ---------------------------------------------------------------------------------------
def run_solve_case(spec: dict[str, Any]) -> dict[str, Any]:
    """Prefilter / initial guess / iterations of one window at N POIs."""
    import numpy as np
    import torch

    import torch_stsdic as sts

    dev = spec["device"]
    dtype = torch.float64 if spec["dtype"] == "float64" else torch.float32
    m, subset = spec["m"], spec["subset"]
    data = np.load(spec["movie"])
    t_all = np.arange(1.0, 10.0)
    c = int(np.argmin(np.abs(t_all - CENTRE_T)))
    sel = slice(c - m, c + m + 1)
    ref = torch.from_numpy(data["ref"].astype(np.float64)).to(dev, dtype)
    frames = torch.from_numpy(data["frames"][sel].astype(np.float64)).to(dev, dtype)
    times = torch.from_numpy(t_all[sel]).to(dev, dtype)
    pts = poi_grid(ref.shape[0], spec["n"], subset, spec.get("step")).to(dev, dtype)
    n = pts.shape[0]
    memory_mb = spec.get("memory_mb") or (_cuda_budget_mb() if dev.startswith("cuda")
                                          else sts.DICConfig().budget_mb)
    cfg = sts.DICConfig(subset_size=subset, m=m, dtype=spec["dtype"], memory_mb=memory_mb,
                        initial_guess=spec.get("initial_guess") or "auto")
    solver = sts.SubsetSolver(cfg)
    t_count = frames.shape[0]
    dt = (times - times[m]).view(1, -1)
    clock = _Clock(dev)

    def once(p: torch.Tensor):
        nn_ = p.shape[0]
        dtn = dt.expand(nn_, t_count)
        fidx = torch.arange(t_count, device=dev).expand(nn_, t_count)
        ridx = torch.zeros(nn_, dtype=torch.long, device=dev)
        w0, c0 = clock.now()
        ref_img = solver.prepare(ref)
        frames_img = solver.prepare(frames)
        w1, c1 = clock.now()
        # the user's path: solve() makes its own initial guess (config.initial_guess: FFT at
        # seed POIs or at every POI); the FFT seconds come back in sol.info
        sol = solver.solve(ref_img, frames_img, p, dtn, frame_index=fidx, ref_index=ridx,
                           ref_pixels=ref.unsqueeze(0), frame_pixels=frames)
        w3, c3 = clock.now()
        ig = float(sol.info["initial_guess"].get("fft_s", 0.0))
        return (w1 - w0, ig, w3 - w1 - ig, w3 - w0, c3 - c0), sol

    base_rss = _maxrss_mb()
    if dev.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
        base_cuda = torch.cuda.memory_allocated()
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    # warm-up with the same N (allocator, threads, and torch.compile, whose use can depend
    # on the whole solve's size): a smaller warm-up let the compile land in the timed run
    once(pts[: spec.get("warmup_points") or n])
    rec: dict[str, list[float]] = {k: [] for k in ("prefilter", "initial_guess", "iterations",
                                                   "total", "cpu_total")}
    sol = None
    for _ in range(spec["repeats"]):
        tm, sol = once(pts)
        for k, v in zip(rec, tm):
            rec[k].append(v)
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    if dev.startswith("cuda"):
        peak = (torch.cuda.max_memory_allocated() - base_cuda) / 2**20
        mem_kind = "cuda max_memory_allocated"
    else:
        peak = _maxrss_mb() - base_rss
        mem_kind = "ru_maxrss rise"
    ok = sol.ok
    tc = float(times[m])
    u_true = MOTION["u0"] + MOTION["ut"] * tc
    v_true = MOTION["v0"] + MOTION["vt"] * tc
    err = torch.sqrt((sol.u - u_true) ** 2 + (sol.v - v_true) ** 2)[ok]
    med = {k: statistics.median(v) for k, v in rec.items()}
    out = {
        "n_points": n,
        "times_s": {k: _summary(v) for k, v in rec.items()},
        "median_s": med,
        "poi_per_s": n / med["total"],
        "poi_per_s_no_prefilter": n / (med["initial_guess"] + med["iterations"]),
        "poi_per_s_iterations": n / med["iterations"],
        "poi_per_cpu_s": n / med["cpu_total"],
        "cpu_over_wall": med["cpu_total"] / med["total"],
        "peak_mem_mb": peak,
        "mem_kind": mem_kind,
        "rss_peak_mb": _maxrss_mb(),
        "memory_mb_budget": memory_mb,
        "converged_frac": float(ok.float().mean()),
        "mean_iterations": float(sol.iterations.float().mean()),
        "median_err_px": float(err.median()) if err.numel() else float("nan"),
        "initial_guess": {k: v for k, v in sol.info["initial_guess"].items() if k != "fft_s"},
        "native_kernels": _native_on(),
        "load_before": load0,
        "load_after": load1,
    }
    if spec.get("profile"):
        out["profile"] = _profile(lambda: once(pts))
    return out


def _native_on() -> bool:
    from torch_stsdic.kernels import native

    return native.available()


def run_track_case(spec: dict[str, Any]) -> dict[str, Any]:
    """The paper's Table 1 through ``sts.track`` (noise sigma 2, 8-bit, float32)."""
    import numpy as np

    import torch_stsdic as sts

    dev = spec["device"]
    data = np.load(spec["movie"])
    frames, times = data["frames"], data["times"]
    ref = data["ref"].astype(np.float32)
    cfg = sts.DICConfig(subset_size=spec["subset"], m=spec["m"], dtype=spec["dtype"])
    clock = _Clock(dev)

    def once():
        w0, c0 = clock.now()
        res = sts.track(frames, reference=ref, times=times, step=spec["step"],
                        config=cfg, device=dev, progress=False)
        w1, c1 = clock.now()
        return w1 - w0, c1 - c0, res

    base_rss = _maxrss_mb()
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    once()  # warm-up
    walls, cpus = [], []
    res = None
    for _ in range(spec["repeats"]):
        w, c, res = once()
        walls.append(w)
        cpus.append(c)
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    truth = (times / 20.0)[:, None]
    u = res.u.cpu().numpy()
    ok = res.ok.cpu().numpy()
    rmse = float(np.sqrt(np.mean((u - truth)[ok] ** 2)))
    ut_err = float(np.median(np.abs(res.ut.cpu().numpy()[ok] - 0.05))) if spec["m"] else None
    med = statistics.median(walls)
    out = {
        "n_points": res.n_points,
        "n_frames": res.n_frames,
        "times_s": {"total": _summary(walls), "cpu_total": _summary(cpus)},
        "median_s": {"total": med, "cpu_total": statistics.median(cpus)},
        "poi_per_s": res.n_points * res.n_frames / med,
        "poi_per_cpu_s": res.n_points * res.n_frames / statistics.median(cpus),
        "cpu_over_wall": statistics.median(cpus) / med,
        "peak_mem_mb": _maxrss_mb() - base_rss,
        "mem_kind": "ru_maxrss rise",
        "rss_peak_mb": _maxrss_mb(),
        "converged_frac": float(res.ok.float().mean()),
        "mean_iterations": float(res.iterations.float().mean()),
        "u_rmse_px": rmse,
        "ut_median_abs_err": ut_err,
        "load_before": load0,
        "load_after": load1,
    }
    if spec.get("profile"):
        out["profile"] = _profile(once)
    return out



def _movie_rates(res: Any, wall: float, cpu: float) -> dict[str, Any]:
    """The size and rates of a whole-movie ``sts.track`` run (wall and process CPU s)."""
    return {
        "n_points": res.n_points,
        "n_frames": res.n_frames,
        "median_s": {"total": wall, "cpu_total": cpu},
        "frames_per_s": res.n_frames / wall,
        "poi_per_s": res.n_frames * res.n_points / wall,
    }

def run_memory_case(spec: dict[str, Any]) -> dict[str, Any]:
    """``sts.track`` over a TIFF stack on disk, read lazily; peak RSS of this process."""
    import torch

    import torch_stsdic as sts

    rss_import = _maxrss_mb()
    cfg = sts.DICConfig(subset_size=spec["subset"], m=spec["m"], dtype="float32",
                        memory_mb=spec.get("memory_mb") or 512.0)
    out_h5 = Path(spec["workdir"]) / "memory_result.h5"
    w0, c0 = time.perf_counter(), time.process_time()
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    trace: list[tuple[int, float, float]] = []  # rows done, current RSS, peak RSS (MB)

    def sample(done: int, total: int) -> None:
        if not trace or done - trace[-1][0] >= total / 20 or done == total:
            trace.append((done, round(_rss_now_mb(), 1), round(_maxrss_mb(), 1)))

    res = sts.track(spec["tiff"], reference=0, step=spec["step"], config=cfg,
                    device=spec["device"], progress=False, out=out_h5, overwrite=True,
                    callback=sample)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    out = {
        **_movie_rates(res, wall, cpu),
        "rss_after_import_mb": rss_import,
        "rss_peak_mb": _maxrss_mb(),
        "peak_mem_mb": _maxrss_mb(),
        "mem_kind": "ru_maxrss (absolute, whole process)",
        "converged_frac": float(res.ok.float().mean()),
        "info": {k: v for k, v in res.info.items() if isinstance(v, (int, float, str))},
        "tiff_mb": os.path.getsize(spec["tiff"]) / 2**20,
        "memory_mb_budget": cfg.budget_mb,
        "rss_trace": trace,
        "load_before": load0,
        "load_after": load1,
    }
    if spec["device"].startswith("cuda"):
        out["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def movie_tiff_path(n_frames: int, size: int = 1024) -> Path:
    return cache_dir() / f"movie_{n_frames}x{size}_v{MOVIE_VERSION}.tif"


def run_movie_case(spec: dict[str, Any]) -> dict[str, Any]:
    """A TIFF movie from disk through plan_run + HDF5 sink + run_plan (what ``sts.track``
    does), with every stage timed (see the module docstring)."""
    import torch

    import torch_stsdic as sts
    from torch_stsdic.movie import series as series_mod
    from torch_stsdic.movie.frames import default_ahead
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.sinks import open_sink

    dev = spec["device"]
    clock = _Clock(dev)
    size = spec["size"]
    side = max(2, round(math.sqrt(spec["points"])))  # a regular grid, like track's own
    step = min(10, (size - 1 - 2 * (spec["subset"] // 2 + 8)) // (side - 1))
    pts = poi_grid(size, side, spec["subset"], step=step)
    mem = spec.get("memory_mb") or (_cuda_budget_mb() if dev.startswith("cuda") else 512.0)
    cfg = sts.DICConfig(subset_size=spec["subset"], m=spec["m"], dtype="float32",
                        memory_mb=mem)
    t_solve = [0.0]
    t_write = [0.0]
    orig = series_mod.solve_block

    def timed_solve(*a, **kw):
        t0 = time.perf_counter()
        out = orig(*a, **kw)
        clock.sync()
        t_solve[0] += time.perf_counter() - t0
        return out

    t_finish = [0.0]

    def timed(fn, acc):
        def run(*a, **kw):
            clock.sync()
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                acc[0] += time.perf_counter() - t0
        return run

    series_mod.solve_block = timed_solve
    out_h5 = Path(spec["workdir"]) / "movie_result.h5"
    base_rss = _maxrss_mb()
    if dev.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    try:
        w0, c0 = clock.now()
        plan = plan_run(spec["tiff"], 0, None, pts, None, None, 10, cfg, dev, None,
                        spec.get("batch_frames"))
        if spec.get("single_reference"):  # the baseline: frame 0 as the reference image
            plan.options["single_reference"] = "asked for (--movie-single-reference)"
        sink = open_sink(plan, out_h5, overwrite=True)
        sink.write_rows = timed(sink.write_rows, t_write)
        sink.finish = timed(sink.finish, t_finish)
        res = series_mod.run_plan(plan, sink, progress=False)
        w1, c1 = clock.now()
    finally:
        series_mod.solve_block = orig
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    wall, cpu = w1 - w0, c1 - c0
    ft = res.info["frame_times_s"]
    solve = t_solve[0] - ft["wait_s"]
    split = {
        "read_s": ft["read_s"], "prefilter_s": ft["prefilter_s"],
        "ahead_read_s": ft["ahead_read_s"], "ahead_prefilter_s": ft["ahead_prefilter_s"],
        "wait_frames_s": ft["wait_s"], "solve_s": solve, "write_s": t_write[0] + t_finish[0],
        "write_rows_s": t_write[0], "finish_s": t_finish[0],
    }
    wt = res.info.get("writer_times_s")
    if wt is not None:  # the rows are written on the writer's thread, beside the solves:
        # what writing cost the run is the loop's wait for it (and the final strains)
        split["write_s"] = wt["waited_s"] + t_finish[0]
        split["writer_busy_s"] = wt["busy_s"]  # (overlapped: not part of the sum)
    # the rest: planning, the reference, carry, everything else in the loop
    split["other_s"] = wall - t_solve[0] - split["write_s"]  # the reference's read included
    # of which the run-level estimates: the template made from the series, the shared motion
    split["series_reference_s"] = float(
        (res.info.get("series_reference") or {}).get("seconds") or 0.0)
    split["shared_motion_s"] = float((res.info.get("shared_motion") or {}).get("seconds") or 0.0)
    # the TIFF moves by u = 0.01 t, v = -0.005 t px; a run on a GPU keeps its result there
    truth_u = 0.01 * res.times.cpu().view(-1, 1)
    ok = res.ok.cpu()
    out = {
        **_movie_rates(res, wall, cpu),
        "split_s": split,
        "overhead_share": (wall - solve) / wall,
        "cpu_over_wall": cpu / wall,
        "batch_frames": plan.batch_frames,
        "read_ahead": default_ahead(plan.batch_frames, cfg.m),
        "peak_mem_mb": _maxrss_mb() - base_rss,
        "rss_peak_mb": _maxrss_mb(),
        "mem_kind": "ru_maxrss rise" if not dev.startswith("cuda") else "cuda max allocated",
        "converged_frac": float(ok.float().mean()),
        "u_rmse_px": float(((res.u.cpu() - truth_u)[ok] ** 2).mean().sqrt()),
        "mean_iterations": float(res.iterations.float().mean()),
        "info": {k: v for k, v in res.info.items() if isinstance(v, (int, float, str))},
        "tiff_mb": os.path.getsize(spec["tiff"]) / 2**20,
        "load_before": load0,
        "load_after": load1,
    }
    if dev.startswith("cuda"):
        out["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
        out["peak_mem_mb"] = out["cuda_peak_mb"]
    return out


CASE_RUNNERS = {"solve": run_solve_case, "track": run_track_case, "memory": run_memory_case,
                "movie": run_movie_case}


def child_main(spec_json: str) -> None:
    spec = json.loads(spec_json)
    if spec.get("compile"):
        os.environ["TORCH_STSDIC_COMPILE"] = spec["compile"]
    if spec.get("native"):
        os.environ["TORCH_STSDIC_NATIVE"] = spec["native"]
    if spec.get("read_ahead") is not None:
        os.environ["TORCH_STSDIC_READ_AHEAD"] = str(spec["read_ahead"])
    if spec.get("per_point"):  # "0": the batched Gauss-Newton loop, not the per-point solver
        os.environ["TORCH_STSDIC_PER_POINT"] = spec["per_point"]
    importlib.import_module("torch_stsdic")  # first: its OpenMP defaults precede torch's load
    import torch

    torch.set_num_threads(spec["threads"])
    try:
        res = CASE_RUNNERS[spec["kind"]](spec)
        res["ok"] = True
    except Exception as exc:
        res = {"ok": False, "error": f"{type(exc).__name__}: {exc}",
               "traceback": traceback.format_exc()[-2000:]}
    res["omp_wait_policy"] = os.environ.get("OMP_WAIT_POLICY")
    print(CHILD_TAG + json.dumps(res, default=float), flush=True)


# ---------------------------------------------------------------------------------------
# cases (parent side)
# ---------------------------------------------------------------------------------------
def case_name(spec: dict[str, Any]) -> str:
    return f"{_case_name(spec)} {spec['threads']}t"


def _case_name(spec: dict[str, Any]) -> str:
    k = spec["kind"]
    stsname = "classical" if spec["m"] == 0 else f"STS({2 * spec['m'] + 1})"
    if k == "solve":
        n = spec["n"] ** 2 if spec.get("step") else spec["n"]
        return (f"solve {stsname} {spec['subset']}px N~{n} {spec['dtype']} {spec['device']}"
                + (f" step{spec['step']}" if spec.get("step") else "")
                + (f" compile={spec['compile']}" if spec.get("compile") else "")
                + (f" init={spec['initial_guess']}" if spec.get("initial_guess") else "")
                + (f" native={spec['native']}" if spec.get("native") else "")
                + (f" per_point={spec['per_point']}" if spec.get("per_point") else ""))
    comp = (f" compile={spec['compile']}" if spec.get("compile") else "") + (
        f" native={spec['native']}" if spec.get("native") else "")
    if k == "track":
        return (f"track {spec.get('label', '')} {stsname} {spec['dtype']} {spec['device']}"
                + comp)
    if k == "movie":
        ra = spec.get("read_ahead")
        return (f"movie {spec['frames']}x{spec['size']} {spec['points']} POIs {stsname} "
                f"{spec['device']}" + (f" batch_frames={spec['batch_frames']}"
                                       if spec.get("batch_frames") else "")
                + (f" read_ahead={ra}" if ra is not None else "")
                + (" single-reference" if spec.get("single_reference") else ""))
    return (f"memory track {stsname} {spec['device']} memory_mb="
            f"{spec.get('memory_mb') or 512:g}")


def run_case(spec: dict[str, Any], isolate: bool, timeout: float) -> dict[str, Any]:
    t0 = time.perf_counter()
    if not isolate:
        import torch

        old = torch.get_num_threads()
        torch.set_num_threads(spec["threads"])
        if spec.get("compile"):
            from torch_stsdic.core import interpolation

            if hasattr(interpolation, "set_compile"):
                interpolation.set_compile(spec["compile"])
        if spec.get("native"):
            from torch_stsdic.kernels import native

            native.set_native(spec["native"])
        try:
            res = CASE_RUNNERS[spec["kind"]](spec)
            res["ok"] = True
        except Exception as exc:
            res = {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                   "traceback": traceback.format_exc()[-2000:]}
        finally:
            torch.set_num_threads(old)
        res["isolated"] = False
    else:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--_child", json.dumps(spec)]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
            line = next((ln for ln in reversed(p.stdout.splitlines())
                         if ln.startswith(CHILD_TAG)), None)
            if line is None:
                res = {"ok": False, "error": f"child exited {p.returncode}",
                       "stderr": p.stderr[-2000:]}
            else:
                res = json.loads(line[len(CHILD_TAG):])
        except subprocess.TimeoutExpired:
            res = {"ok": False, "error": f"timeout after {timeout:.0f} s"}
        res["isolated"] = True
    res["case_wall_s"] = time.perf_counter() - t0
    res["date"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    res["code_sha1"] = _code_hash()
    return {"name": case_name(spec), "spec": spec, **res}


# ---------------------------------------------------------------------------------------
# presets
# ---------------------------------------------------------------------------------------
def _solve(m, subset, n, dtype, device, threads, repeats, *, size=1024, step=None, **kw):
    return {"kind": "solve", "m": m, "subset": subset, "n": n, "dtype": dtype,
            "device": device, "threads": threads, "repeats": repeats, "size": size,
            "movie": str(movie_path(size)), "step": step, **kw}


def preset_cases(args, device: str) -> list[dict[str, Any]]:
    """The preset's cases, repeated for every thread count of --threads."""
    base = _preset_cases(args, device, args.thread_list[0])
    return [{**c, "threads": t} for t in args.thread_list for c in base]


def _preset_cases(args, device: str, th: int) -> list[dict[str, Any]]:
    dev = device
    r = args.repeats
    cases: list[dict[str, Any]] = []
    if args.preset == "quick":
        r = r or 1
        for m in (0, 1):
            cases.append(_solve(m, 21, 144, "float32", dev, th, r, size=192))
        cases.append({"kind": "track", "label": "mini", "m": 1, "subset": 21, "dtype": "float32",
                      "device": dev, "threads": th, "repeats": r, "size": 96, "n_frames": 5,
                      "step": 20, "movie": str(table1_path(96, 5))})
        return cases
    if args.preset == "targets":
        r = r or 3
        t1 = {"kind": "track", "label": "table1", "subset": 21, "dtype": "float32",
              "device": dev, "threads": th, "repeats": r, "size": 301, "n_frames": 9,
              "step": 15, "movie": str(table1_path(301, 9)), "compile": args.compile}
        for m in (0, 2):
            cases.append({**t1, "m": m, "profile": args.profile})
        for m in (0, 2):  # for comparison: without the fused C++ kernels (torch code)
            cases.append({**t1, "m": m, "native": "0", "compare": True})
        rb = args.repeats or r
        for m in (0, 2):
            cases.append(_solve(m, 21, 197, "float32", dev, th, rb, step=5,
                                profile=args.profile, memory_mb=args.memory_mb,
                                compile=args.compile))
        for m in (0, 2):  # for comparison: FFT cross-correlation at every POI (OpenCorr's way)
            cases.append(_solve(m, 21, 197, "float32", dev, th, rb, step=5,
                                memory_mb=args.memory_mb, compile=args.compile,
                                initial_guess="fft", compare=True))
        if dev.startswith("cuda"):
            for m in (0, 2):
                for n in (100_000, 250_000):
                    cases.append(_solve(m, 21, n, "float32", dev, th, r,
                                        memory_mb=args.memory_mb, compile=args.compile))
            # for comparison: the batched Gauss-Newton loop (a Triton right-hand side and torch
            # ops per iteration) instead of the whole-stage Triton solver (kernels.triton_solve)
            for m in (0, 2):
                cases.append(_solve(m, 21, 197, "float32", dev, th, rb, step=5, per_point="0",
                                    memory_mb=args.memory_mb, compare=True))
                cases.append(_solve(m, 21, 250_000, "float32", dev, th, r, per_point="0",
                                    memory_mb=args.memory_mb, compare=True))
        return cases
    if args.preset == "full":
        r = r or 3
        for dtype in args.dtypes.split(","):
            for m in (0, 1, 2, 4):
                for subset in (21, 31, 41):
                    for n in (1_000, 10_000, 100_000):
                        cases.append(_solve(m, subset, n, dtype, dev, th, r,
                                            memory_mb=args.memory_mb, compile=args.compile))
        return cases
    raise ValueError(args.preset)


def run_solver_preset(args, device: str, checkpoint=None) -> list[dict[str, Any]]:
    cases = preset_cases(args, device)
    if args.only:
        cases = [c for c in cases if re.search(args.only, case_name(c))]
    for c in cases:
        if c["kind"] == "track" and "movie" in c:
            ensure_table1(c["size"], c["n_frames"])
    if any(c["kind"] == "solve" for c in cases):
        sizes = {c["size"] for c in cases if c["kind"] == "solve"}
        for s in sizes:
            t0 = time.perf_counter()
            ensure_movie(s)
            print(f"# movie {s}x{s}: {movie_path(s)} ({time.perf_counter() - t0:.1f} s)",
                  file=sys.stderr)
    results: list[dict[str, Any]] = []
    rate: dict[tuple, float] = {}  # (m, subset, dtype) -> seconds per POI (total)
    for spec in cases:
        key = (spec["kind"], spec["m"], spec["subset"], spec["dtype"])
        if spec["kind"] == "solve" and key in rate and args.max_case_seconds:
            est = rate[key] * spec["n"]
            if est * (spec["repeats"] + 1) > args.max_case_seconds:
                spec["repeats"] = 1
            if est * 1.2 > args.max_case_seconds:
                results.append({"name": case_name(spec), "spec": spec, "ok": False,
                                "skipped": True,
                                "error": f"skipped: estimated {est:.0f} s per run > "
                                         f"--max-case-seconds {args.max_case_seconds:.0f}"})
                print(f"{results[-1]['name']}: {results[-1]['error']}", file=sys.stderr)
                continue
        res = run_case(spec, args.isolate, args.case_timeout)
        results.append(res)
        if res.get("ok") and spec["kind"] == "solve":
            rate[key] = res["median_s"]["total"] / res["n_points"]
        print(_one_line(res), file=sys.stderr, flush=True)
        if checkpoint is not None:
            checkpoint(results)
    return results


def _one_line(res: dict[str, Any]) -> str:
    if not res.get("ok"):
        return f"{res['name']}: FAILED {res.get('error')}\n{res.get('traceback', '')}" \
               f"{res.get('stderr', '')}"
    med = res["median_s"]
    return (f"{res['name']}: total {med['total']:.3f} s, {res['poi_per_s']:,.0f} POI/s, "
            f"peak {res['peak_mem_mb']:.0f} MB, load {res.get('load_after')}")


# ---------------------------------------------------------------------------------------
# memory preset
# ---------------------------------------------------------------------------------------
def write_tiff_movie(path: Path, n_frames: int, size: int, seed: int = 3) -> None:
    """1000-frame-style uint8 stack: a rendered speckle moved by Fourier shifts
    (u = 0.01 t, v = -0.005 t px), page by page (never the whole movie in memory)."""
    import numpy as np
    import tifffile
    import torch

    from torch_stsdic.synth import make_speckle, render

    img = render(make_speckle((size, size), seed=seed), (size, size))
    spec = torch.fft.rfft2(img)
    ky = torch.fft.fftfreq(size, dtype=torch.float64).view(-1, 1)
    kx = torch.fft.rfftfreq(size, dtype=torch.float64).view(1, -1)
    gen = torch.Generator().manual_seed(seed)
    tmp = path.with_name(path.name + ".tmp")
    with tifffile.TiffWriter(tmp) as tw:
        for t in range(n_frames):
            u, v = 0.01 * t, -0.005 * t
            phase = torch.exp(-2j * math.pi * (kx * u + ky * v))
            frame = torch.fft.irfft2(spec * phase, s=(size, size))
            frame = frame + NOISE * torch.randn(frame.shape, generator=gen, dtype=frame.dtype)
            arr = frame.round().clamp(0, 255).numpy().astype(np.uint8)
            tw.write(arr, photometric="minisblack", contiguous=True)
    os.replace(tmp, path)


def run_memory_preset(args, device: str) -> list[dict[str, Any]]:
    n_frames, size = args.memory_frames, 1024
    need = n_frames * size * size * 1.05 + 200 * 2**20
    workdir = Path(args.tiff_dir) if args.tiff_dir else Path(tempfile.mkdtemp(prefix="stsbench"))
    workdir.mkdir(parents=True, exist_ok=True)
    tiff = workdir / f"movie_{n_frames}x{size}.tif"
    free = shutil.disk_usage(workdir).free
    if not tiff.exists() and free < need * 1.5:
        raise SystemExit(f"--memory: {free / 2**30:.1f} GiB free in {workdir}, need "
                         f"{need * 1.5 / 2**30:.1f} GiB (use --tiff-dir)")
    results = []
    try:
        if not tiff.exists():
            t0 = time.perf_counter()
            write_tiff_movie(tiff, n_frames, size)
            print(f"# wrote {tiff} ({tiff.stat().st_size / 2**20:.0f} MiB, "
                  f"{time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        for mem in (args.memory_mb, 256.0):  # the default budget (512), then a smaller one
            spec = {"kind": "memory", "m": 2, "subset": 21, "step": args.memory_step,
                    "dtype": "float32", "device": device, "threads": args.thread_list[0],
                    "tiff": str(tiff), "workdir": str(workdir), "frames": n_frames,
                    "memory_mb": mem}
            res = run_case(spec, True, args.case_timeout)
            results.append(res)
            print(_one_line(res), file=sys.stderr, flush=True)
    finally:
        if not args.keep_tiff and not args.tiff_dir:
            shutil.rmtree(workdir, ignore_errors=True)
    return results


def run_movie_preset(args, device: str) -> list[dict[str, Any]]:
    """The movie cases: with the read-ahead thread (default), and without it
    (``--movie-compare``) for the before/after comparison."""
    n_frames, size = args.movie_frames, 1024
    tiff = movie_tiff_path(n_frames, size)
    need = n_frames * size * size * 1.05
    if not tiff.exists():
        free = shutil.disk_usage(tiff.parent).free
        if free < need * 1.5:
            raise SystemExit(f"--movie: {free / 2**30:.1f} GiB free in {tiff.parent}, need "
                             f"{need * 1.5 / 2**30:.1f} GiB (set STSDIC_BENCH_CACHE)")
        t0 = time.perf_counter()
        write_tiff_movie(tiff, n_frames, size)
        print(f"# wrote {tiff} ({tiff.stat().st_size / 2**20:.0f} MiB, "
              f"{time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    workdir = Path(tempfile.mkdtemp(prefix="stsmovie"))
    results = []
    try:
        aheads = [args.movie_read_ahead]
        if args.movie_compare:
            aheads.append(0)
        runs: dict[str, list[dict[str, Any]]] = {}
        for _ in range(max(1, args.repeats or 1)):  # interleaved: load drifts alike
            for ra in aheads:
                spec = {"kind": "movie", "m": 2, "subset": 21, "size": size,
                        "points": args.movie_points, "frames": n_frames, "dtype": "float32",
                        "device": device, "threads": args.thread_list[0], "tiff": str(tiff),
                        "workdir": str(workdir), "batch_frames": args.movie_batch_frames,
                        "read_ahead": ra, "memory_mb": args.memory_mb,
                        "single_reference": args.movie_single_reference}
                res = run_case(spec, args.isolate, args.case_timeout)
                runs.setdefault(res["name"], []).append(res)
                print(_one_line(res), file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    for same in runs.values():  # per case: the run of median wall time, all walls listed
        ok = sorted((r for r in same if r.get("ok")), key=lambda r: r["median_s"]["total"])
        if not ok:
            results.append(same[0])
            continue
        med = dict(ok[(len(ok) - 1) // 2])
        med["repeat_walls_s"] = [r["median_s"]["total"] for r in same if r.get("ok")]
        med["repeat_overhead_shares"] = [r["overhead_share"] for r in same if r.get("ok")]
        results.append(med)
    return results


# ---------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------
def _fmt_rate(x: float | None) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:,.0f}" if x < 1e6 else f"{x / 1e6:.2f} M"


def _ms(x: float) -> str:
    return f"{1000 * x:.0f}" if x >= 0.1 else f"{1000 * x:.1f}"


def solve_table(results: list[dict[str, Any]]) -> str:
    head = ("| case | N | prefilter ms | FFT-CC ms | iterations ms | total ms | POI/s | "
            "iter POI/s | iters | conv. | err px | peak MB | cpu/wall | load |\n"
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    rows = []
    for r in results:
        if r["spec"]["kind"] != "solve":
            continue
        if not r.get("ok"):
            rows.append(f"| {r['name']} | | | | | | {r.get('error', 'failed')[:60]} "
                        "| | | | | | | |")
            continue
        md = r["median_s"]
        rows.append(
            f"| {r['name']} | {r['n_points']:,} | {_ms(md['prefilter'])} | "
            f"{_ms(md['initial_guess'])} | {_ms(md['iterations'])} | {_ms(md['total'])} | "
            f"{_fmt_rate(r['poi_per_s'])} | {_fmt_rate(r['poi_per_s_iterations'])} | "
            f"{r['mean_iterations']:.1f} | {100 * r['converged_frac']:.1f}% | "
            f"{r['median_err_px']:.4f} | {r['peak_mem_mb']:.0f} | {r['cpu_over_wall']:.2f} | "
            f"{r['load_after']:.1f} |")
    return head + "\n".join(rows) + "\n" if rows else ""


def track_table(results: list[dict[str, Any]]) -> str:
    head = ("| case | POIs x frames | median s | min s | POI-frames/s | iters | conv. | "
            "u RMSE px | peak MB | cpu/wall | load |\n"
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    rows = []
    for r in results:
        if r["spec"]["kind"] != "track":
            continue
        if not r.get("ok"):
            rows.append(f"| {r['name']} | {r.get('error', 'failed')[:60]} | | | | | | | | | |")
            continue
        t = r["times_s"]["total"]
        rows.append(
            f"| {r['name']} | {r['n_points']} x {r['n_frames']} | {t['median']:.3f} | "
            f"{t['min']:.3f} | {_fmt_rate(r['poi_per_s'])} | {r['mean_iterations']:.1f} | "
            f"{100 * r['converged_frac']:.1f}% | {r['u_rmse_px']:.4f} | "
            f"{r['peak_mem_mb']:.0f} | {r['cpu_over_wall']:.2f} | {r['load_after']:.1f} |")
    return head + "\n".join(rows) + "\n" if rows else ""


def memory_table(results: list[dict[str, Any]]) -> str:
    head = ("| case | frames x POIs | TIFF MiB | wall s | frames/s | RSS after import MB | "
            "RSS at 10 / 50 / 100 % of frames MB | peak RSS MB | conv. | load |\n"
            "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|\n")
    rows = []
    for r in results:
        if r["spec"]["kind"] != "memory":
            continue
        if not r.get("ok"):
            rows.append(f"| {r['name']} | {r.get('error', 'failed')[:60]} | | | | | | | | |")
            continue
        tr = r.get("rss_trace") or []
        at = []
        for frac in (0.1, 0.5, 1.0):
            hit = next((t for t in tr if t[0] >= frac * r["n_frames"]), None)
            at.append(f"{hit[1]:.0f}" if hit else "-")
        rows.append(
            f"| {r['name']} | {r['n_frames']} x {r['n_points']} | {r['tiff_mb']:.0f} | "
            f"{r['median_s']['total']:.0f} | {r['frames_per_s']:.1f} | "
            f"{r['rss_after_import_mb']:.0f} | {' / '.join(at)} | {r['rss_peak_mb']:.0f} | "
            f"{100 * r['converged_frac']:.1f}% | {r['load_after']:.1f} |")
    return head + "\n".join(rows) + "\n" if rows else ""


def movie_table(results: list[dict[str, Any]]) -> str:
    head = ("| case | frames x POIs | wall s (median) | frames/s | POI-frames/s | read ms/frame "
            "(ahead) | prefilter ms/frame (ahead) | wait for frames s | solve s | write s | "
            "other s | overhead | peak MB | conv. | u RMSE px | load |\n"
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    rows = []
    for r in results:
        if r["spec"]["kind"] != "movie":
            continue
        if not r.get("ok"):
            rows.append(f"| {r['name']} | {r.get('error', 'failed')[:60]} |" + " |" * 15)
            continue
        sp, nf = r["split_s"], r["n_frames"]
        rd = (f"{1000 * sp['read_s'] / nf:.1f} ({1000 * sp['ahead_read_s'] / nf:.1f})")
        pf = (f"{1000 * sp['prefilter_s'] / nf:.1f} "
              f"({1000 * sp['ahead_prefilter_s'] / nf:.1f})")
        walls = r.get("repeat_walls_s") or [r["median_s"]["total"]]
        wall = f"{r['median_s']['total']:.1f}" + (
            f" (runs: {', '.join(f'{w:.1f}' for w in walls)})" if len(walls) > 1 else "")
        rows.append(
            f"| {r['name']} | {nf} x {r['n_points']:,} | {wall} | "
            f"{r['frames_per_s']:.2f} | {_fmt_rate(r['poi_per_s'])} | {rd} | {pf} | "
            f"{sp['wait_frames_s']:.2f} | {sp['solve_s']:.1f} | {sp['write_s']:.2f} | "
            f"{sp['other_s']:.2f} | {100 * r['overhead_share']:.1f}% | "
            f"{r['peak_mem_mb']:.0f} | {100 * r['converged_frac']:.1f}% | "
            f"{r['u_rmse_px']:.4f} | {r['load_after']:.1f} |")
    return head + "\n".join(rows) + "\n" if rows else ""


def _find(results, **want):
    for r in results:
        s = r["spec"]
        if r.get("ok") and all(s.get(k) == v for k, v in want.items()):
            return r
    return None


def target_rows(records: list[dict[str, Any]]) -> list[tuple[str, str, str, str, str]]:
    """(target, goal, measured, verdict, source) for every target with data, per thread
    count (cases marked "compare" - e.g. the forced-compile run - are left out)."""
    rows = []
    for rec in records:
        mach = rec["machine"]
        src = f"{rec.get('_file', rec['preset'])}, {mach['date'][:10]}"
        dev = mach["device"]
        all_res = [r for r in rec["results"] if not r["spec"].get("compare")]
        for th in sorted({r["spec"].get("threads") for r in all_res}, key=str):
            res = [r for r in all_res if r["spec"].get("threads") == th]
            where = f"{dev}, {th} thread{'s' if th != 1 else ''}"
            if rec["preset"] == "targets":
                got = (_track_targets(res, where, src)
                       + _solve_targets(res, where, src, dev.startswith("cuda")))
                if not dev.startswith("cuda") and isinstance(th, int) and th < mach.get(
                        "cores", th):
                    # the CPU targets are for the whole machine: fewer threads are a reference
                    got = [(a, b, c, f"({d}: reference, {th} of {mach['cores']} cores)", e)
                           for a, b, c, d, e in got]
                rows += got
            for r in (res if rec["preset"] == "memory" else []):
                if r.get("ok") and r["spec"]["kind"] == "memory":
                    goal, ref = TARGETS["memory_rss_mb"]
                    mem = r["spec"].get("memory_mb") or 512
                    rows.append((f"{r['n_frames']}-frame 1024x1024 TIFF via sts.track, "
                                 f"{r['n_points']} POIs, STS(5), memory_mb={mem:g}, {where}",
                                 f"<= {goal:.0f} MB RAM ({ref})",
                                 f"{r['rss_peak_mb']:.0f} MB peak RSS, "
                                 f"{r['median_s']['total']:.0f} s",
                                 "PASS" if r["rss_peak_mb"] <= goal else "MISS", src))
            for r in (res if rec["preset"] == "movie" else []):
                if r.get("ok") and r["spec"].get("read_ahead") != 0 \
                        and r["n_points"] >= 10_000:  # the issue's size
                    rows += _movie_targets(r, where, src, dev.startswith("cuda"))
    return rows


def _movie_targets(r, where: str, src: str, gpu: bool) -> list[tuple[str, str, str, str, str]]:
    what = (f"{r['n_frames']}-frame 1024x1024 TIFF via sts.track, {r['n_points']:,} POIs, "
            f"STS(5), {r.get('batch_frames', '?')} targets a block, {where}")
    goal, ref = TARGETS["movie_overhead_share"]
    share = r["overhead_share"]
    rows = [(f"{what}: per-frame overhead (all but the solve)", f"<= {100 * goal:.0f} % of "
             f"the run ({ref})", f"{100 * share:.1f} % of {r['median_s']['total']:.0f} s "
             f"({r['frames_per_s']:.2f} frames/s)", "PASS" if share <= goal else "MISS", src)]
    if gpu:
        goal, ref = TARGETS["gpu_movie_frames_s"]
        fps = r["frames_per_s"]
        rows.append((f"{what}: throughput", f">= {goal:.0f} frames/s ({ref})",
                     f"{fps:.1f} frames/s", "PASS" if fps >= goal else "MISS", src))
    return rows


def _track_targets(res, where: str, src: str) -> list[tuple[str, str, str, str, str]]:
    rows = []
    sts5 = _find(res, kind="track", label="table1", m=2, dtype="float32")
    cl = _find(res, kind="track", label="table1", m=0, dtype="float32")
    if sts5:
        t = sts5["median_s"]["total"]
        goal, ref = TARGETS["table1_sts5_s"]
        rows.append((f"Table 1 via sts.track, STS(5), 361 POIs x 9 frames, {where}",
                     f"<= {goal:g} s ({ref})", f"{t:.2f} s",
                     "PASS" if t <= goal else "MISS", src))
    if sts5 and cl:
        ratio = sts5["median_s"]["total"] / cl["median_s"]["total"]
        goal, ref = TARGETS["table1_ratio"]
        rows.append((f"Table 1: STS(5) / classical time, {where}", f"<= {goal:g}x ({ref})",
                     f"{ratio:.2f}x ({cl['median_s']['total']:.2f} s classical)",
                     "PASS" if ratio <= goal else "MISS", src))
    return rows


def _solve_targets(res, where: str, src: str, gpu: bool):
    rows = []
    for m, key in ((0, "classical_poi_s"), (2, "sts5_poi_s")):
        goal, ref = TARGETS[("gpu_" if gpu else "cpu_") + key]
        cands = [r for r in res if r.get("ok") and r["spec"]["kind"] == "solve"
                 and r["spec"]["m"] == m and r["spec"]["dtype"] == "float32"]
        if not cands:
            continue
        best = max(cands, key=lambda r: r["poi_per_s"])
        label = "classical" if m == 0 else "STS(5)"
        how = best.get("initial_guess", {})
        init = (f"FFT-CC at {how['seeds']:,} seeds" if how.get("method") == "seeded"
                else "FFT-CC at every POI")
        rows.append((f"{label}, 21x21, {best['n_points']:,} POIs on 1024x1024, "
                     f"incl. prefilter + {init}, {where}",
                     f">= {_fmt_rate(goal)} POI/s" + (f" ({ref})" if ref else ""),
                     f"{_fmt_rate(best['poi_per_s'])} POI/s (iterations alone "
                     f"{_fmt_rate(best['poi_per_s_iterations'])})",
                     "PASS" if best["poi_per_s"] >= goal else "MISS", src))
    return rows


def scaling_tables(results: list[dict[str, Any]]) -> str:
    """POI/s (total) against m, N and subset size, per dtype."""
    ok = [r for r in results if r.get("ok") and r["spec"]["kind"] == "solve"]
    if not ok:
        return ""
    out = []
    for dtype in sorted({r["spec"]["dtype"] for r in ok}):
        sel = [r for r in ok if r["spec"]["dtype"] == dtype]
        ns = sorted({r["spec"]["n"] for r in sel})
        subs = sorted({r["spec"]["subset"] for r in sel})
        ms = sorted({r["spec"]["m"] for r in sel})
        out.append(f"\nPOI/s (total; iterations alone in brackets), {dtype}:\n")
        out.append("| m (frames) | subset | " + " | ".join(f"N~{n:,}" for n in ns) + " |")
        out.append("|---|---|" + "---:|" * len(ns))
        for m in ms:
            for s in subs:
                cells = []
                for n in ns:
                    r = _find(sel, m=m, subset=s, n=n)
                    cells.append(f"{_fmt_rate(r['poi_per_s'])} "
                                 f"({_fmt_rate(r['poi_per_s_iterations'])})" if r else "-")
                out.append(f"| {m} ({2 * m + 1}) | {s} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def profile_text(results: list[dict[str, Any]], top: int = 10) -> str:
    out = []
    for r in results:
        prof = r.get("profile")
        if not prof:
            continue
        out.append(f"\n{r['name']}: top Python functions by own time\n")
        out.append("| function | calls | own s | cum s |\n|---|---:|---:|---:|")
        for p in prof["python_top"][:top]:
            out.append(f"| `{p['function']}` | {p['calls']} | {p['own_s']:.3f} | "
                       f"{p['cum_s']:.3f} |")
        out.append("\ntop torch ops by self CPU time\n")
        out.append("| op | calls | self ms |\n|---|---:|---:|")
        for p in prof["ops_top"][:top]:
            out.append(f"| `{p['op']}` | {p['calls']} | {p['self_cpu_ms']:.1f} |")
    return "\n".join(out) + "\n" if out else ""


def machine_line(rec: dict[str, Any]) -> str:
    m = rec["machine"]
    la = m.get("load_average")
    la_s = ", ".join(f"{x:.2f}" for x in la) if la else "n/a"
    gpu = f", GPU {m['gpu']} ({m['gpu_memory_gb']} GB, CUDA {m['cuda']})" if m.get("gpu") else ""
    return (f"{m['cpu_model']}, {m['cores']} cores, {m.get('memory_gb', '?')} GB{gpu}; "
            f"torch {m['torch']}, threads {m['torch_threads']}; {m['date']}; load average "
            f"at start {la_s}; commit {m['git_commit']}"
            + (f" + uncommitted {', '.join(m['git_dirty_files'])}"
               if m.get("git_dirty_files") else "")
            + f"; code sha1 {m.get('code_sha1')}; `{m['command']}`")


def render_record(rec: dict[str, Any]) -> str:
    parts = [f"Machine: {machine_line(rec)}\n"]
    for fn in (track_table, solve_table, memory_table, movie_table):
        t = fn(rec["results"])
        if t:
            parts.append(t)
    if rec["preset"] == "full":
        parts.append(scaling_tables(rec["results"]))
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------
# docs/benchmarks.md
# ---------------------------------------------------------------------------------------
def load_records(directory: Path = BENCH_DIR) -> list[dict[str, Any]]:
    recs = []
    for p in sorted(directory.glob("*.json")):
        try:
            rec = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        # this script's presets only (bench_memory_length.py writes "memory-length" records
        # of another layout into the same folder)
        if (isinstance(rec, dict) and "results" in rec and "machine" in rec
                and rec.get("preset") in _PRESETS):
            rec["_file"] = p.name
            recs.append(rec)
    return recs


_PRESET_ORDER = {"targets": 0, "memory": 1, "movie": 2, "full": 3}
_PRESETS = frozenset(_PRESET_ORDER)


def _triton_kernel_row() -> tuple[str, str, str, str, str]:
    """The fused Triton step against the torch step, from ``kernels-cuda.json``
    (``scripts/benchmarks/bench_kernels.py --device cuda``)."""
    label, goal = "GPU, fused Triton IC-GN step vs the torch step (5 frames)", ">= 3x"
    path = BENCH_DIR / "kernels-cuda.json"
    if not path.exists():
        return (label, goal,
                "GPU not measured (run scripts/benchmarks/bench_kernels.py --device cuda)",
                "-", "-")
    rec = json.loads(path.read_text())
    ns = {(r["kernel"], r["impl"]): r["ns_per_sample"] for r in rec["results"]}
    key = "IC-GN step right-hand side, 5 frames"
    tri, tor = ns.get((key, "triton")), ns.get((key, "torch"))
    if not tri or not tor:
        return (label, goal, "no 5-frame rows in kernels-cuda.json", "-", "-")
    ratio = tor / tri
    return (f"{label}, {rec.get('device', 'GPU')}", goal,
            f"{ratio:.1f}x ({tri:.3g} against {tor:.3g} ns a sample)",
            "PASS" if ratio >= 3 else "MISS", f"kernels-cuda.json, {rec['date'][:10]}")


def autogen_sections(records: list[dict[str, Any]]) -> dict[str, str]:
    records = sorted(records, key=lambda r: (_PRESET_ORDER.get(r["preset"], 9), r["_file"]))
    rows = target_rows(records)
    if not any(r["machine"]["device"].startswith("cuda") and r["preset"] == "targets"
               for r in records):
        for k, label in (("gpu_classical_poi_s", "classical"), ("gpu_sts5_poi_s", "STS(5)")):
            rows.append((f"GPU (one H100), {label}, 21x21", f">= {_fmt_rate(TARGETS[k][0])} "
                         "POI/s", "not measured (no CUDA record: run --targets --device "
                         "cuda)", "-", "-"))
    if not any(r["machine"]["device"].startswith("cuda") and r["preset"] == "movie"
               for r in records):
        rows.append(("GPU (one H100), 500-frame 1024x1024 TIFF via sts.track, 10,000 POIs, "
                     "STS(5)", f">= {TARGETS['gpu_movie_frames_s'][0]:.0f} frames/s",
                     "GPU not measured (no CUDA record: run --movie --device cuda)", "-", "-"))
    rows.append(_triton_kernel_row())
    tgt = ["| target | goal | measured | verdict | record |", "|---|---|---|---|---|"]
    tgt += [f"| {a} | {b} | {c} | **{d}** | {e} |" for a, b, c, d, e in rows]
    sections = {"targets": "\n".join(tgt) + "\n"}
    details = []
    for rec in records:
        part = ", partial: still running or interrupted" if rec.get("partial") else ""
        details.append(f"\n#### `docs/bench/{rec['_file']}` ({rec['preset']}{part})\n")
        details.append(render_record(rec))
    sections["details"] = "\n".join(details)
    prof = [profile_text(rec["results"]) for rec in records if rec["preset"] == "targets"]
    sections["profile"] = "\n".join(p for p in prof if p) or "(run with --profile)\n"
    return sections


def update_doc(records: list[dict[str, Any]], doc: Path = DOC) -> bool:
    if not doc.exists():
        print(f"# {doc} does not exist: tables not written", file=sys.stderr)
        return False
    text = doc.read_text()
    for name, body in autogen_sections(records).items():
        pat = re.compile(rf"(<!-- BEGIN AUTOGEN {name} -->\n).*?(<!-- END AUTOGEN {name} -->)",
                         re.S)
        text, k = pat.subn(lambda mt, b=body: mt.group(1) + b + "\n" + mt.group(2), text)
        if not k:
            print(f"# {doc}: no AUTOGEN {name} markers", file=sys.stderr)
    doc.write_text(text)
    return True


# ---------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group()
    for name in ("quick", "targets", "full", "memory", "movie", "report"):
        g.add_argument(f"--{name}", dest="preset", action="store_const", const=name)
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto (default cpu)")
    p.add_argument("--threads", default=None,
                   help="torch.set_num_threads; a comma list runs every case with each "
                        "(e.g. 2,1; default: all cores)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats per case")
    p.add_argument("--memory-mb", type=float, default=None,
                   help="cfg.memory_mb (default: DICConfig's on CPU, 35%% of free GPU memory "
                   "on CUDA)")
    p.add_argument("--out", default=None, help="JSON record path (default docs/bench/"
                   "<preset>-<device>.json; --quick writes none unless given)")
    p.add_argument("--no-update-doc", dest="update_doc", action="store_false")
    p.add_argument("--no-isolate", dest="isolate", action="store_false",
                   help="run cases in this process (memory figures then are lower bounds)")
    p.add_argument("--only", default=None, help="run only the cases whose name matches "
                   "this regular expression (e.g. 'table1')")
    p.add_argument("--compile", default=None, choices=("0", "1", "auto"),
                   help="TORCH_STSDIC_COMPILE for the cases (default: the library's default)")
    p.add_argument("--dtypes", default="float32,float64", help="--full: dtypes to run")
    p.add_argument("--profile", action="store_true",
                   help="--targets: also record the top functions / torch ops")
    p.add_argument("--max-case-seconds", type=float, default=120.0,
                   help="--full: skip a case estimated to take longer per run (0: no limit)")
    p.add_argument("--case-timeout", type=float, default=3600.0)
    p.add_argument("--memory-frames", type=int, default=1000)
    p.add_argument("--memory-step", type=int, default=64, help="--memory: POI grid step, px")
    p.add_argument("--tiff-dir", default=None, help="--memory: where the TIFF is written/kept")
    p.add_argument("--keep-tiff", action="store_true")
    p.add_argument("--movie-frames", type=int, default=500,
                   help="--movie: frames of the TIFF movie, all tracked (default 500)")
    p.add_argument("--movie-points", type=int, default=10_000,
                   help="--movie: POIs (a regular square grid; default 10,000)")
    p.add_argument("--movie-batch-frames", type=int, default=None,
                   help="--movie: target frames per block (default: track's)")
    p.add_argument("--movie-read-ahead", type=int, default=None,
                   help="--movie: frames read ahead (default: track's; 0 = off)")
    p.add_argument("--movie-single-reference", action="store_true",
                   help="--movie: measure against frame 0 alone (no template made from the "
                        "series): the baseline of the default")
    p.add_argument("--movie-compare", action="store_true",
                   help="--movie: also run without read-ahead (before/after)")
    p.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    a.preset = a.preset or "quick"
    a.thread_list = [int(t) for t in (a.threads or str(_cores())).split(",")]
    if a.preset == "quick" and not any(x.startswith("--threads") for x in (argv or sys.argv)):
        a.thread_list = [1]  # small tensors: threads only add synchronisation
    if a.preset == "quick" and "--no-isolate" not in (argv or sys.argv):
        a.isolate = False  # seconds: no subprocess per case
    return a


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args._child is not None:
        child_main(args._child)
        return 0
    if args.preset == "report":
        recs = load_records()
        update_doc(recs)
        for rec in recs:
            print(f"\n## {rec['_file']}\n\n" + render_record(rec))
        return 0
    importlib.import_module("torch_stsdic")  # first: its OpenMP defaults precede torch's load
    import torch

    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available (torch.cuda.is_available() is "
                         "False)")
    torch.set_num_threads(args.thread_list[0])
    machine = machine_info(args.thread_list, device)
    t0 = time.perf_counter()
    out = args.out
    if out is None and args.preset != "quick":
        out = BENCH_DIR / f"{args.preset}-{device.split(':')[0]}.json"

    def save(results: list[dict[str, Any]], partial: bool) -> dict[str, Any]:
        rec = {"preset": args.preset, "machine": dict(machine), "partial": partial,
               "wall_s": time.perf_counter() - t0, "results": list(results)}
        if not partial:
            rec["machine"]["load_average_end"] = (list(os.getloadavg())
                                                  if hasattr(os, "getloadavg") else None)
        if out is not None and args.only and Path(out).exists():
            # a partial re-run (--only) replaces its cases in the existing record
            old = json.loads(Path(out).read_text())
            names = {r["name"] for r in results}
            merged = [r for r in old.get("results", []) if r["name"] not in names]
            order = {r["name"]: i for i, r in enumerate(old.get("results", []))}
            rec["results"] = sorted(merged + rec["results"],
                                    key=lambda r: order.get(r["name"], 1e9))
            before = old["machine"].get("merged_into", [])
            if old["machine"]["date"] != machine["date"]:
                before = [*before, old["machine"]["date"]]
            rec["machine"]["merged_into"] = before
        if out is not None:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
            Path(out).write_text(json.dumps(rec, indent=1, default=float) + "\n")
        return rec

    if args.preset == "memory":
        results = run_memory_preset(args, device)
    elif args.preset == "movie":
        results = run_movie_preset(args, device)
    else:
        results = run_solver_preset(args, device, checkpoint=lambda r: save(r, True))
    rec = save(results, False)
    if out is not None:
        print(f"# wrote {out}", file=sys.stderr)
    rec["_file"] = Path(out).name if out else "(not saved)"
    print(render_record(rec))
    rows = target_rows([rec])
    if rows:
        print("| target | goal | measured | verdict |\n|---|---|---|---|")
        for a, b, c, d, _ in rows:
            print(f"| {a} | {b} | {c} | {d} |")
    if args.profile:
        print(profile_text(results))
    if args.update_doc and args.preset != "quick" and out is not None \
            and Path(out).resolve().parent == BENCH_DIR.resolve():
        update_doc(load_records())
    return 0 if all(r.get("ok") or r.get("skipped") for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
