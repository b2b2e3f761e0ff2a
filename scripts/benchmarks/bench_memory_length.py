#!/usr/bin/env python
"""Peak memory of ``stsdic run`` against the movie's length (issue 50: it must not grow).

    python scripts/benchmarks/bench_memory_length.py                 # the issue's cases
    python scripts/benchmarks/bench_memory_length.py --cases 256:120,256:1200 \\
        --json docs/bench/memory-length-cpu.json
    # cases run side by side (one process each), then one record:
    python scripts/benchmarks/bench_memory_length.py --cases 256:120 --json /tmp/a.json &
    ...
    python scripts/benchmarks/bench_memory_length.py --merge /tmp/a.json /tmp/b.json \\
        --json docs/bench/memory-length-cpu.json

Each case ``SIZE:FRAMES`` is a translation movie rendered as ``stsdic synth`` renders it
(SIZE x SIZE px, FRAMES frames, its defaults: u = 0.05 t px, noise 5, 8 bits; written a
few frames at a time: :func:`write_movie`) tracked by ``stsdic run movie.tif
--out r.h5`` with the defaults (step 10, m 2, subset 21, strains), ``--threads`` torch
threads, in a fresh process. Its peak resident memory comes from ``wait4`` (the kernel's
high-water mark, ``ru_maxrss``); its resident memory is also sampled every
``--interval`` s (psutil) for the timeline. The record holds, per case, the peak, the
timeline (at most 200 samples), the wall time and the command's summary; and the ratios
of the peaks of the cases of one image size (the longest over the shortest). The movies
are written once into ``--data`` and reused.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts" / "benchmarks"))

import benchmark as bench  # noqa: E402  (the machine record)

DEFAULT_CASES = "256:120,256:1200,512:200,512:2000,256:10000"


def write_movie(movie: Path, size: int, frames: int, ut: float, noise: float = 5.0,
                seed: int = 0) -> None:
    """A translation movie, u = ``ut`` t px, v = 0, ``frames`` frames of ``size`` x ``size``
    px, written page by page (8 bits, Gaussian noise ``noise`` grey levels, speckle radius
    2 px: the defaults of ``stsdic synth``). A strip of speckle as wide as the motion is
    rendered once by :mod:`torch_stsdic.synth`; every frame is its window at the frame's
    whole-pixel offset moved by the fraction of a pixel with a Fourier shift (exact for the
    band-limited speckle). ``stsdic synth`` writes a frame at a time too, but renders each
    one analytically (~0.25 s a frame here): too slow for 10,000 frames."""
    import numpy as np
    import tifffile

    from torch_stsdic import synth

    pad = 16  # px of the window on each side, beyond the image (the shift's wrap-around)
    reach = int(np.ceil(abs(ut) * frames)) + 2 * pad + 2
    strip = synth.make_speckle((size + 2 * pad, size + reach), radius=2.0, seed=seed,
                               margin=16.0)
    img = synth.render(strip, (size + 2 * pad, size + reach), None).numpy()  # (H', W')
    kx = np.fft.fftfreq(size + 2 * pad)[None, :]
    rng = np.random.default_rng(seed + 1)
    movie.parent.mkdir(parents=True, exist_ok=True)
    tmp = movie.with_name(movie.name + ".partial")
    with tifffile.TiffWriter(tmp) as tw:
        for t in range(frames):
            u = ut * t  # the pattern moves by +u: the frame shows the strip at x - u
            whole = int(np.floor(u))
            frac = u - whole
            x0 = reach - 2 * pad - 2 - whole if ut >= 0 else -whole
            win = img[:, x0:x0 + size + 2 * pad]
            f = np.fft.ifft2(np.fft.fft2(win) * np.exp(-2j * np.pi * kx * frac)).real
            f = f[pad:pad + size, pad:pad + size] + rng.normal(0.0, noise, (size, size))
            tw.write(np.clip(np.rint(f), 0, 255).astype(np.uint8), contiguous=True,
                     photometric="minisblack")
    (movie.parent / "motion.json").write_text(json.dumps(
        {"motion": "translation", "ut": ut, "vt": 0.0, "frames": frames, "size": size,
         "noise": noise, "seed": seed, "writer": "bench_memory_length.write_movie"}) + "\n")
    tmp.replace(movie)


def ensure_movie(data: Path, size: int, frames: int, ut: float) -> Path:
    """The movie of a case (written once)."""
    movie = data / f"translation_{size}_{frames}_ut{ut:g}" / "movie.tif"
    if not movie.exists():
        write_movie(movie, size, frames, ut)
    return movie


def run_case(movie: Path, out: Path, threads: int, interval: float,
             run_args: list[str], max_seconds: float | None = None) -> dict[str, Any]:
    """``stsdic run`` of ``movie`` in a fresh process: its peak RSS (wait4), sampled RSS
    timeline, wall time and printed summary. After ``max_seconds`` the run is interrupted
    (SIGINT: it keeps its finished frames) and the record says how many frames it
    finished (``complete`` False)."""
    import psutil

    cmd = [sys.executable, "-m", "torch_stsdic", "run", str(movie), "--out", str(out),
           "--overwrite", "--no-progress", "--threads", str(threads), *run_args]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    samples: list[tuple[float, float]] = []
    output: list[str] = []
    reader = threading.Thread(target=lambda: output.extend(proc.stdout), daemon=True)
    reader.start()
    ps = psutil.Process(proc.pid)
    stopped = False
    while True:
        if max_seconds is not None and not stopped and time.perf_counter() - t0 > max_seconds:
            proc.send_signal(signal.SIGINT)
            stopped = True
        try:
            rss = ps.memory_info().rss
        except psutil.Error:
            break
        samples.append((round(time.perf_counter() - t0, 2), round(rss / 2**20, 1)))
        try:
            if ps.status() == psutil.STATUS_ZOMBIE:
                break
        except psutil.Error:
            break
        time.sleep(interval)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    reader.join(timeout=10)
    code = os.waitstatus_to_exitcode(status)
    if code != 0 and not stopped:
        raise RuntimeError(f"{' '.join(cmd)} failed ({code}):\n{''.join(output)[-2000:]}")
    step = max(1, len(samples) // 200)
    done = None
    if stopped:
        import h5py

        for f in (out, out.with_name(out.name + ".partial")):
            if f.exists():
                with h5py.File(f, "r") as h:
                    done = int(h["completed"][()].sum())
    return {
        "complete": not stopped, "frames_finished": done,
        "tail": [ln.rstrip() for ln in output[-3:]] if stopped else [],
        "command": " ".join(["stsdic", *cmd[3:]]),
        "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),  # kB on Linux
        "sampled_peak_mb": max((s[1] for s in samples), default=None),
        "wall_s": round(wall, 1),
        "result_file_mb": round(out.stat().st_size / 1e6, 1) if out.exists() else None,
        "summary": [ln.rstrip() for ln in output if ln.startswith(("points:", "time:",
                                                                    "converged:"))],
        "timeline_s_mb": samples[::step],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=DEFAULT_CASES,
                    help="comma-separated SIZE:FRAMES (default: %(default)s)")
    ap.add_argument("--data", type=Path, default=Path("/tmp/stsdic-memory-movies"),
                    help="folder of the movies (written once)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--interval", type=float, default=0.5, help="RSS sampling period, s")
    ap.add_argument("--ut", type=float, default=0.05,
                    help="the movie's velocity along x, px per frame (default: stsdic synth's)")
    ap.add_argument("--run-args", default="", help="extra stsdic run options")
    ap.add_argument("--json", type=Path, default=REPO / "docs/bench/memory-length-cpu.json")
    ap.add_argument("--max-seconds", type=float,
                    help="interrupt a run after this long (the record says how far it got)")
    ap.add_argument("--merge", type=Path, nargs="+",
                    help="records of this script to merge into --json (nothing is run)")
    ap.add_argument("--note", help="a note recorded with a merged record")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge, args.json, args.note)
        return
    cases = [tuple(int(x) for x in c.split(":")) for c in args.cases.split(",") if c]
    args.data.mkdir(parents=True, exist_ok=True)
    machine = bench.machine_info([args.threads], "cpu")  # the code as the runs start
    results = []
    for size, frames in cases:
        movie = ensure_movie(args.data, size, frames, args.ut)
        out = Path(tempfile.mkdtemp(dir=args.data)) / f"r_{size}_{frames}.h5"
        rec = run_case(movie, out, args.threads, args.interval, args.run_args.split(),
                       args.max_seconds)
        rec.update({"size": size, "frames": frames})
        print(f"{size}x{size} {frames:6d} frames: peak {rec['peak_rss_mb']:7.1f} MB, "
              f"{rec['wall_s']:7.1f} s  {rec['summary'][:1]}", flush=True)
        results.append(rec)
        shutil.rmtree(out.parent, ignore_errors=True)
    machine["load_average_end"] = list(os.getloadavg())
    write_record(args.json, results, machine)


def ratios_of(results: list[dict[str, Any]]) -> dict[str, float]:
    """Per image size, the peak of every longer finished case over that of the shortest
    (an interrupted run has no ratio: its peak is of the part it ran)."""
    out = {}
    done = [r for r in results if r.get("complete", True)]
    for size in sorted({r["size"] for r in done}):
        same = sorted((r for r in done if r["size"] == size), key=lambda r: r["frames"])
        for r in same[1:]:
            out[f"{size}: {r['frames']} / {same[0]['frames']} frames"] = round(
                r["peak_rss_mb"] / same[0]["peak_rss_mb"], 3)
    return out


def write_record(path: Path, results: list[dict[str, Any]], machine: dict[str, Any],
                 note: str | None = None) -> None:
    """The record (cases, ratios, machine) as JSON at ``path``, and the ratios printed."""
    record = {"preset": "memory-length", "machine": machine, "ratios": ratios_of(results),
              "results": results}
    if note:
        record["note"] = note
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    for k, v in record["ratios"].items():
        print(f"peak ratio {k}: {v}")
    print(f"-> {path}")


def merge(paths: list[Path], out: Path, note: str | None) -> None:
    """One record of the cases of several (e.g. run side by side, one case each): the
    machine of the first, each case keeping its own start time and load."""
    results, machine = [], None
    for p in paths:
        rec = json.loads(p.read_text())
        machine = machine or rec["machine"]
        for r in rec["results"]:
            r.setdefault("load_average", rec["machine"].get("load_average"))
            r.setdefault("started", rec["machine"].get("date"))
            results.append(r)
    results.sort(key=lambda r: (r["size"], r["frames"]))
    write_record(out, results, machine or {}, note)


if __name__ == "__main__":
    main()
