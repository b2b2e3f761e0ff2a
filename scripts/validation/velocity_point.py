"""Velocities referred to their POIs (``movie/velocity_point.py``) against the windows' raw
velocities (the subset's gradient-weighted centroid), on renders whose velocity varies in
space: each case tracked with the defaults (windows chosen up to m = 6) both ways.

    python scripts/validation/velocity_point.py [--cases shear sine120 sine60] [--seeds 1 2]

Renders as ``window_length.py``'s (201 px, 31 frames, noise sigma 2 on every image,
subset 21, step 10). Prints the velocity RMS error and its random part over the predicted
std, referred and not."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie import velocity_point

sys.path.insert(0, str(Path(__file__).resolve().parent))
import window_length as wl  # noqa: E402

CASES = {
    "linear": lambda x, y, t: (0.05 * t + 4e-4 * t * (x - 100), -0.03 * t + 2e-4 * t * (y - 100)),
    "shear": lambda x, y, t: (0.03 * t + 5e-4 * t * (y - 100), 3e-4 * t * (x - 100)),
    "sine120": lambda x, y, t: (0.02 * t * torch.sin(2 * math.pi * x / 120),
                                -0.01 * t * torch.cos(2 * math.pi * y / 150)),
    "sine60": lambda x, y, t: (0.01 * t * torch.sin(2 * math.pi * x / 60),
                               0.005 * t * torch.sin(2 * math.pi * (x + y) / 80)),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["shear", "sine120", "sine60"],
                    choices=sorted(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    a = ap.parse_args(argv)
    refer = velocity_point.refer_to_points
    print("| case | seed | referred: velocity RMS 1e-3 px/frame | random / predicted | "
          "raw: velocity RMS | random / predicted |\n|---|---:|---:|---:|---:|---:|")
    for name in a.cases:
        mot = synth.Custom(CASES[name])
        for seed in a.seeds:
            series, times = wl.render(mot, seed=seed)
            row = []
            for on in (True, False):
                velocity_point.refer_to_points = refer if on else (
                    lambda pts, maps, ut, vt, *args, **kw: (ut, vt))
                try:
                    res = sts.track(series, config=sts.DICConfig(m=6, subset_size=21),
                                    progress=False, window_length="auto", step=10)
                finally:
                    velocity_point.refer_to_points = refer
                gt = synth.ground_truth(mot, res.points.double(), times)
                row += [wl.velocity_rms(res, gt) * 1e3, wl.velocity_honesty(res, gt)]
            print(f"| {name} | {seed} | {row[0]:.3f} | {row[1]:.2f} | {row[2]:.3f} | "
                  f"{row[3]:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
