"""What limits the relaxing stretch (issue 47, item 2): the windows' length, their shape in
time, or the template?

On the ``stretch`` render of ``window_length.py`` (31 images of 201 px, noise sigma 2 on every
image, subset 21, step 10, the template made from the series) it runs classical DIC against
the single reference image (the baseline), the template with every fixed half-width m = 0 ..
``--max-m`` and with the windows chosen from the data (``window_length="auto"``), and splits
each run's error (u, v against the truth over frames 1..) into

- ``constant``: each point's mean error over the frames (the template's registration, and
  the part of a time-model bias that does not change sign), RMS over the points;
- ``varying``: the rest (each frame's noise through its window, the bias that changes);

and reports the RMS error per band of frames. ``oracle``: per frame, the fixed m with the
least RMS error over the points, chosen with the truth (a bound on what any choice of
linear windows, one length per frame, reaches; its selection among ``max-m + 1`` runs on
~500 values a frame is only slightly optimistic). A second-order term in time can beat the
oracle only where the oracle's frames are limited by bias, not by noise.

    python scripts/validation/stretch_limits.py [--max-m 6]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic import synth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from series_reference_floor import motion as stretch  # noqa: E402
from window_length import render  # noqa: E402

BANDS = ((1, 5), (6, 10), (11, 20), (21, 30))


def error(res, truth: dict[str, torch.Tensor]) -> torch.Tensor:
    """(2, T - 1, N) u, v minus the truth over frames 1.. (NaN where not usable)."""
    e = torch.stack([res.u.double()[1:] - truth["u"][1:], res.v.double()[1:] - truth["v"][1:]])
    ok = (res.status[1:] <= 1)[None] & torch.isfinite(e)
    return torch.where(ok, e, torch.nan)


def rms(e: torch.Tensor) -> float:
    return float(torch.nanmean(e.pow(2)).sqrt())


def split(e: torch.Tensor) -> tuple[float, float]:
    """RMS of each point's mean error over the frames, and of the rest."""
    const = torch.nanmean(e, 1, keepdim=True)
    return rms(const), rms(e - const)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-m", type=int, default=6)
    args = ap.parse_args(argv)
    mot = stretch()
    series, times = render(mot)
    runs: dict[str, torch.Tensor] = {}
    cfg = {"subset_size": 21}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = sts.track(series, config=sts.DICConfig(m=0, **cfg), step=10, progress=False,
                         series_reference=False)
        truth = synth.ground_truth(mot, base.points.double(), times)
        b = rms(error(base, truth))
        for m in range(args.max_m + 1):
            res = sts.track(series, config=sts.DICConfig(m=m, **cfg), step=10, progress=False)
            runs[f"m = {m}"] = error(res, truth)
        res = sts.track(series, config=sts.DICConfig(m=args.max_m, **cfg), step=10,
                        progress=False, window_length="auto")
        runs[f"chosen (m <= {args.max_m})"] = error(res, truth)
    fixed = torch.stack([runs[f"m = {m}"] for m in range(args.max_m + 1)])  # (M, 2, T, N)
    per_frame = torch.nanmean(fixed.pow(2), (1, 3))  # (M, T)
    best = per_frame.argmin(0)  # (T,)
    runs["oracle (m per frame)"] = fixed[best, :, torch.arange(fixed.shape[2])].permute(1, 0, 2)
    print(f"classical DIC against the single reference: {b * 1e3:.2f}e-3 px; oracle's m per "
          f"frame 1..: {' '.join(str(int(k)) for k in best)}\n")
    print("| run | RMS 1e-3 px | x classical | constant 1e-3 px | varying 1e-3 px | "
          + " | ".join(f"frames {lo}-{hi}" for lo, hi in BANDS) + " |")
    print("|---|---:|---:|---:|---:|" + "---:|" * len(BANDS))
    for name, e in runs.items():
        c, v = split(e)
        bands = [rms(e[:, lo - 1:hi]) * 1e3 for lo, hi in BANDS]
        print(f"| {name} | {rms(e) * 1e3:.2f} | {rms(e) / b:.3f} | {c * 1e3:.2f} | "
              f"{v * 1e3:.2f} | " + " | ".join(f"{x:.2f}" for x in bands) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
