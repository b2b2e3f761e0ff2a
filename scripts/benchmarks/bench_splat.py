#!/usr/bin/env python
"""The template's C++ splat on one chunk of samples: ``native.splat`` (each (frame, POI)
row's window mapped into a frame, sampled, matched to the reference's grey levels and
weighted) and ``native.splat_add`` (the rows added to the covered pixels' sums in row order),
as ``movie/template_image.splat`` calls them on the hourglass (1,000 rows of 31 x 31
samples: its 1M-sample chunk; a 754 x 1273 float32 frame).

    python scripts/benchmarks/bench_splat.py --repeats 25
    PYTHONPATH=/path/to/old/checkout python scripts/benchmarks/bench_splat.py   # another version

Prints the median and the least time of each over ``--repeats`` calls (ms); compare
versions in interleaved runs (this VM's speed swings by 20 % between minutes)."""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.kernels import native


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=25)
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    a = ap.parse_args(argv)
    if not native.available():
        print("no native kernels: nothing to time")
        return 1
    torch.manual_seed(0)
    h, w, half, n, n_poi, n_px = 754, 1273, 15, 1000, 1666, 600_000
    img = BSplineImage((torch.rand(1, h, w) * 200).float(), 3)
    ka = img.kernel_args()
    d = torch.arange(-half, half + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    dx, dy = dx.reshape(-1), dy.reshape(-1)
    ns = dx.numel()
    cx = torch.randint(40, w - 40, (n,)).double()
    cy = torch.randint(40, h - 40, (n,)).double()
    maps = torch.zeros(n, 12, dtype=torch.float64)  # a small stretch about each centre
    maps[:, 0], maps[:, 1], maps[:, 6], maps[:, 8] = cx + 0.3, 1.001, cy - 0.2, 0.999
    one = torch.ones(n, dtype=torch.float64)
    ref = torch.rand(h * w, dtype=torch.float64) * 200
    local = torch.randint(0, n_px, (n_poi, ns))
    poi, frame = torch.randint(0, n_poi, (n,)), torch.zeros(n, dtype=torch.long)
    sums = [torch.zeros(n_px, dtype=torch.float64) for _ in range(3)]
    t_splat, t_add = [], []
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        out = native.splat(ka, 3, dx, dy, torch.ones(ns, dtype=torch.float64), maps,
                           torch.stack([cx, cy], 1), torch.zeros(n, dtype=torch.long), one,
                           one, one, (one * 100, one * 50), ref, w, h)
        t1 = time.perf_counter()
        native.splat_add(*sums, *out, poi, frame, local)
        t_splat.append(t1 - t0)
        t_add.append(time.perf_counter() - t1)
    rec = {"rows": n, "samples_per_row": ns, "repeats": a.repeats,
           "splat_ms_median": 1e3 * statistics.median(t_splat),
           "splat_ms_min": 1e3 * min(t_splat),
           "splat_add_ms_median": 1e3 * statistics.median(t_add),
           "splat_add_ms_min": 1e3 * min(t_add), "threads": torch.get_num_threads()}
    print(f"splat {rec['splat_ms_median']:.2f} ms (least {rec['splat_ms_min']:.2f}), "
          f"splat_add {rec['splat_add_ms_median']:.2f} ms (least {rec['splat_add_ms_min']:.2f})"
          f" a chunk of {n} x {ns} samples")
    if a.out is not None:
        a.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
