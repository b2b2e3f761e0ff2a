#!/usr/bin/env python
"""Peak memory and time of the FFT search (``core.initial.fft_cross_correlation``) against
its search radius: POIs x frames of random images, the process's resident memory sampled
every 10 ms during the call (psutil), over what it held before.

    python scripts/benchmarks/bench_fft_memory.py --radius 10 16 32 [--points 1444 --frames 13]
"""

from __future__ import annotations

import argparse
import threading
import time

import psutil
import torch

from torch_stsdic.core.initial import FFT_MEMORY_MB, fft_cross_correlation
from torch_stsdic.kernels.native.rows import own_threads


def _watch(proc: psutil.Process, peak: list[int], stop: list[bool]) -> None:
    while not stop[0]:
        peak[0] = max(peak[0], proc.memory_info().rss)
        time.sleep(0.01)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radius", type=int, nargs="+", default=[10, 16, 32])
    ap.add_argument("--points", type=int, default=1444)
    ap.add_argument("--frames", type=int, default=13)
    ap.add_argument("--size", type=int, default=420, help="image side, px")
    ap.add_argument("--subset", type=int, default=21)
    ap.add_argument("--memory-mb", type=float, default=FFT_MEMORY_MB)
    a = ap.parse_args()
    gen = torch.Generator().manual_seed(0)
    imgs = torch.rand(a.frames, a.size, a.size, generator=gen)
    ref = torch.rand(a.size, a.size, generator=gen)
    lo, hi = 40, a.size - 40
    pts = torch.randint(lo, hi, (a.points, 2), generator=gen).float()
    index = torch.arange(a.frames).expand(a.points, -1)
    proc = psutil.Process()
    for rad in a.radius:
        base, peak, stop = proc.memory_info().rss, [0], [False]

        th = threading.Thread(target=_watch, args=(proc, peak, stop), daemon=True)
        th.start()
        t0 = time.perf_counter()
        with own_threads():
            d, _ = fft_cross_correlation(ref, imgs, pts, a.subset, rad, frame_index=index,
                                         memory_mb=a.memory_mb)
        sec = time.perf_counter() - t0
        stop[0] = True
        th.join()
        print(f"radius {rad}: {sec:.2f} s, peak {(peak[0] - base) / 2**20:.0f} MB over the "
              f"process ({a.points} POIs x {a.frames} frames, budget {a.memory_mb:g} MiB; "
              f"checksum {float(d.sum()):.4f})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
