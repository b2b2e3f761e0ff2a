"""How fast ``stsdic view`` opens a long result: the server's open, and the first frame drawn
in headless Chromium (issue 49: a 10,000-frame file opens at once; the first frame of a
1,000-frame file shows within 2 s).

Makes, in --workdir, a 1,000-frame result (a 40 x 30 grid, every row finished) with its
1,000-frame 420 x 320 TIFF movie, and a 10,000-frame result without images; then, --repeats
times, interleaved: builds the viewer's source for each file (:func:`open_source`: what
``stsdic view`` does before it serves) and times a fresh browser page from ``goto`` to its
first frame drawn (image and field: ``body[data-ready]``); and the command's own start, from
``python -m torch_stsdic view`` to its address printed, next to ``stsdic --version`` (Python
and torch's import, which every command pays). Writes docs/bench/view.json::

    python scripts/benchmarks/bench_view.py                 # -> docs/bench/view.json
    python scripts/benchmarks/bench_view.py --repeats 2 --out /tmp/view.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def make_result(path: Path, frames: int, nx: int, ny: int, inputs: list[str]) -> None:
    """A finished result file of ``frames`` rows on an nx x ny grid (a smooth made-up
    motion), written in blocks of 500 rows."""
    from torch_stsdic.io.results import ResultWriter

    xs, ys = np.meshgrid(20.0 + 10 * np.arange(nx), 20.0 + 10 * np.arange(ny))
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    fields = ("u", "v", "ut", "vt", "zncc", "status", "u_std", "v_std")
    with ResultWriter(path, points=pts, frames=np.arange(frames), times=np.arange(float(frames)),
                      config={"m": 2, "subset_size": 21, "track": {"step": 10}}, inputs=inputs,
                      fields=fields[:6], extra_fields=fields[6:]) as w:
        for a in range(0, frames, 500):
            t = np.arange(a, min(frames, a + 500), dtype=np.float64)[:, None]
            u = 1e-3 * t * (pts[None, :, 0] - 200) / 10
            vals = {"u": u, "v": 0.5 * u, "ut": np.broadcast_to(u[:1] / np.maximum(t[:1], 1),
                                                                  u.shape),
                    "vt": np.zeros_like(u), "zncc": np.full_like(u, 0.99),
                    "status": np.zeros_like(u), "u_std": np.full_like(u, 0.01),
                    "v_std": np.full_like(u, 0.01)}
            w.write_rows(np.arange(a, a + len(t)), vals)


def make_movie(path: Path, frames: int, shape: tuple[int, int]) -> None:
    """A ``frames``-page 8-bit TIFF: a speckle pattern shifted by one px every 50 frames."""
    import tifffile

    rng = np.random.default_rng(0)
    base = rng.random((shape[0] + 64, shape[1] + 64))
    k = np.ones(5) / 5
    for ax in (0, 1):
        base = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), ax, base)
    base = (255 * (base - base.min()) / np.ptp(base)).astype(np.uint8)
    with tifffile.TiffWriter(path) as tw:
        for f in range(frames):
            s = f // 50
            tw.write(base[s: s + shape[0], s: s + shape[1]], contiguous=True)


def first_frame_seconds(browser, url: str) -> float:
    """Seconds from a fresh page's goto to its first frame drawn."""
    ctx = browser.new_context(viewport={"width": 1400, "height": 860})
    page = ctx.new_page()
    t0 = time.perf_counter()
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']", timeout=120_000)
    dt = time.perf_counter() - t0
    ctx.close()
    return dt


def command_start_seconds(args: list[str]) -> float:
    """Seconds from starting ``python -m torch_stsdic ARGS`` to the page's address printed
    (then it is stopped with Ctrl-C); for ``view``. With ``--version``: to its exit."""
    import signal

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "torch_stsdic", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    if "--version" in args:
        proc.communicate()
        return time.perf_counter() - t0
    for line in proc.stdout:
        if "http://127.0.0.1:" in line:
            break
    dt = time.perf_counter() - t0
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=60)
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="/tmp/stsdic-bench-view")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "view.json"))
    args = ap.parse_args()

    from playwright.sync_api import sync_playwright
    from view_support import chromium, serving

    from torch_stsdic.view.server import result_api
    from torch_stsdic.view.source import open_source

    wd = Path(args.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    movie, r1k, r10k = wd / "movie1000.tif", wd / "r1000.h5", wd / "r10000.h5"
    if not movie.exists():
        make_movie(movie, 1000, (320, 420))
    if not r1k.exists():
        make_result(r1k, 1000, 40, 30, [str(movie)])
    if not r10k.exists():
        make_result(r10k, 10_000, 40, 30, [])
    sizes = {p.name: p.stat().st_size for p in (movie, r1k, r10k)}
    runs: list[dict] = []
    exe = chromium()
    if exe is None:
        raise SystemExit("no Chromium: apt-get install chromium")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=["--no-sandbox", "--disable-gpu"])
        for rep in range(args.repeats):
            for name, path in (("1000 frames, with images", r1k),
                               ("10000 frames, no images", r10k)):
                t0 = time.perf_counter()
                src = open_source(path, no_image=path == r10k)
                t_open = time.perf_counter() - t0
                with serving(result_api(src)) as server:
                    t_page = first_frame_seconds(browser, server.url)
                runs.append({"file": name, "repeat": rep, "open_s": round(t_open, 4),
                             "first_frame_s": round(t_page, 4)})
                print(runs[-1], flush=True)
            # the command's own start (Python, torch), next to 'stsdic --version'
            t_cmd = command_start_seconds(["view", str(r1k), "--no-browser"])
            t_ver = command_start_seconds(["--version"])
            runs.append({"file": "command start", "repeat": rep,
                         "view_address_printed_s": round(t_cmd, 3),
                         "version_s": round(t_ver, 3)})
            print(runs[-1], flush=True)
        browser.close()
    summary = {}
    for name in {r["file"] for r in runs} - {"command start"}:
        rs = [r for r in runs if r["file"] == name]
        summary[name] = {"open_s_median": statistics.median(r["open_s"] for r in rs),
                         "first_frame_s_median": statistics.median(r["first_frame_s"]
                                                                   for r in rs),
                         "first_frame_s_max": max(r["first_frame_s"] for r in rs)}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    record = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
              "machine": f"{platform.machine()} {os.cpu_count()} cores",
              "load_avg": os.getloadavg(), "commit": commit,
              "chromium": subprocess.run([exe, "--version"], capture_output=True,
                                         text=True).stdout.strip(),
              "points": 1200, "file_bytes": sizes, "summary": summary, "runs": runs}
    starts = [r for r in runs if r["file"] == "command start"]
    summary["command start"] = {
        "view_address_printed_s_median": statistics.median(r["view_address_printed_s"]
                                                          for r in starts),
        "version_s_median": statistics.median(r["version_s"] for r in starts)}
    Path(args.out).write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
