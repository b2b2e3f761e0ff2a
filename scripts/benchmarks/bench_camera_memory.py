"""Peak resident memory of camera-movie reading against the movie's length.

Writes Photron MRAW movies of ``--sizes`` frames (``stsdic synth --format mraw``, small
frames) and measures, each in a fresh process (peak RSS from ``os.wait4``):

- ``reader``: open the movie with ``load_series`` and read every frame once;
- ``run``: ``stsdic run movie.cih`` (few points) to its end, writing a result file.

The reader must not grow with the movie's length; a run also holds its own per-frame
results (the (frames, points) result arrays), which do grow with it.

    python scripts/benchmarks/bench_camera_memory.py --sizes 500 5000 \
        --json docs/bench/camera-memory-cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

READ_ALL = """
import sys
from torch_stsdic.io import load_series
s = load_series(sys.argv[1])
total = 0.0
for i in range(len(s)):
    total += float(s.numpy(i)[0, 0])
print(len(s), total)
"""


def _peak_mb(cmd: list[str]) -> tuple[float, float]:
    """(peak RSS in MiB, seconds) of the command ``cmd`` run as a child process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed: {proc.stderr.read().decode()[-2000:]}")
    return usage.ru_maxrss / 1024.0, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[500, 5000])
    ap.add_argument("--size", type=int, default=64, help="frame size, px (square)")
    ap.add_argument("--step", type=int, default=20, help="grid step of the run, px")
    ap.add_argument("--reader-sizes", type=int, nargs="*", default=[],
                    help="also: the reader alone on movies of these frame counts of "
                    "--reader-px square random 16-bit frames (no run)")
    ap.add_argument("--reader-px", type=int, default=512)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    stsdic = [sys.executable, "-m", "torch_stsdic"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.reader_sizes:
            import numpy as np

            from torch_stsdic.io.photron import write_mraw

            d = Path(tmp) / f"big{n}"
            d.mkdir()
            px = args.reader_px
            frame = np.random.default_rng(0).integers(0, 4096, (1, px, px), dtype=np.uint16)
            _, cih = write_mraw(d / "movie.mraw", frame, 1000.0)
            with open(d / "movie.mraw", "ab") as fh:  # the same frame n times
                for _ in range(n - 1):
                    frame.tofile(fh)
            text = cih.read_text().replace("Total Frame : 1\n", f"Total Frame : {n}\n")
            cih.write_text(text)
            mb, sec = _peak_mb([sys.executable, "-c", READ_ALL, str(cih)])
            row = {"frames": n, "size": px, "mraw_mb": round(n * px * px * 2 / 2**20, 1),
                   "reader_peak_rss_mb": round(mb, 1), "reader_s": round(sec, 1)}
            print(json.dumps(row), flush=True)
            rows.append(row)
            (d / "movie.mraw").unlink()
        for n in args.sizes:
            d = Path(tmp) / f"m{n}"
            subprocess.run([*stsdic, "synth", "--out", str(d), "--format", "mraw", "--bits",
                            "12", "--size", str(args.size), "--frames", str(n - 1), "--noise",
                            "1", "--fps", "10000", "--threads", "1"], check=True,
                           stdout=subprocess.DEVNULL)
            movie = d / "movie.cih"
            reader_mb, reader_s = _peak_mb([sys.executable, "-c", READ_ALL, str(movie)])
            run_mb, run_s = _peak_mb([*stsdic, "run", str(movie), "--step", str(args.step),
                                      "--out", str(d / "r.h5"), "--threads", "1",
                                      "--no-progress"])
            import h5py

            with h5py.File(d / "r.h5") as f:
                points = len(f["points"])
            row = {"frames": n, "size": args.size, "points": points,
                   "mraw_mb": round((d / "movie.mraw").stat().st_size / 2**20, 1),
                   "reader_peak_rss_mb": round(reader_mb, 1), "reader_s": round(reader_s, 1),
                   "run_peak_rss_mb": round(run_mb, 1), "run_s": round(run_s, 1)}
            print(json.dumps(row), flush=True)
            rows.append(row)
    if args.json:
        out = {"what": "peak RSS of reading / running a Photron MRAW movie vs its length",
               "command": "python " + " ".join(sys.argv),
               "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                           "load_average": os.getloadavg(), "platform": platform.platform(),
                           "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())},
               "rows": rows}
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
