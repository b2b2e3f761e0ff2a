"""The error of classical DIC and STS-DIC against a single reference image and against the
reference made from the series, on renders with known motion, next to the theory line.

The render: a speckle of ``--size`` px, noise sigma 2 grey levels on every image (the
reference's too), ``N`` images whose motion is smooth but not linear in time: a stretch
that relaxes towards 0.4 % (x) and -0.12 % (y) with a time constant of 8 frames, a drift
that decelerates (0.2 px (1 - exp(-t / 5))) plus 0.03 px a frame. Subset 21, step 10, the
other options the defaults but ``series_reference`` (``single``: off; ``series``: on).

Theory (first order, white noise; one image's share of a classical displacement's variance
= 1): classical DIC against one image has 1 + 1 = 2; against the series' template 1 + 1/N_t
(N_t the template's images, its registration to the reference configuration fixed by the
local planes and the reference's own measurement); STS-DIC replaces the frame's 1 by the
window's intercept variance ``1/n + (t - t_mean)^2 / sum (t_i - t_mean)^2`` (1/5 inside the
movie at m = 2, up to 0.6 at its ends). The line is the square root of the ratio to 2,
averaged over the frames.

"random" is the error once the part every point shares in a frame (the time model's bias in
a uniform motion) is taken out: sqrt(mean over frames of the variance over points);
"predicted" the RMS of u_std and v_std.

    python scripts/validation/series_reference_floor.py [--frames 5 11 21 41] [--out F.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie.frames import window_frames
from torch_stsdic.movie.series_reference import DEFAULT_FRAMES


def motion() -> synth.Motion:
    """Relaxing stretch plus a decelerating drift (frame units, px)."""
    def fn(x, y, t):
        e = 0.004 * (1 - torch.exp(-t / 8.0))
        u = e * (x - 150) + 0.03 * t + 0.2 * (1 - torch.exp(-t / 5.0))
        v = -0.3 * e * (y - 150) - 0.02 * t
        return u, v
    return synth.Custom(fn)


def theory(n: int, m: int, template: bool) -> float:
    """First-order error over classical single-reference DIC's (see the module doc)."""
    targets = torch.arange(1, n)
    win = window_frames(targets, m, n).double()  # (T, 2m+1) frames of each row's window
    t = targets.double()[:, None]
    dev = win - win.mean(1, keepdim=True)
    frame = 1.0 / win.shape[1] + ((t - win.mean(1, keepdim=True)) ** 2).squeeze(1) / \
        dev.pow(2).sum(1).clamp(min=1e-12) if m else torch.ones(len(targets))
    ref = 1.0 / min(n, DEFAULT_FRAMES) if template else 1.0
    return float(((frame + ref) / 2).sqrt().mean())


def errors(res, truth: dict[str, torch.Tensor]) -> dict[str, float]:
    e = torch.stack([res.u.double()[1:] - truth["u"][1:], res.v.double()[1:] - truth["v"][1:]])
    pred = torch.stack([res.std["u"].double()[1:], res.std["v"].double()[1:]])
    ok = torch.isfinite(e) & torch.isfinite(pred)
    e = torch.where(ok, e, torch.nan)
    centred = e - torch.nanmean(e, -1, keepdim=True)
    return {"rms": float(e[ok].pow(2).mean().sqrt()),
            "random": float(torch.nanmean(centred.pow(2)).sqrt()),
            "predicted": float(pred[ok].pow(2).mean().sqrt())}


def run_case(n: int, size: int, seed: int) -> list[dict]:
    mot = motion()
    mv = synth.synthetic_movie((size, size), n - 1, mot, noise_sigma=2.0, seed=seed)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    rows, base = [], None
    for m in (0, 2):
        for template in (False, True):
            t0 = time.perf_counter()
            res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21), reference=0,
                            step=10, progress=False, series_reference=template)
            sec = time.perf_counter() - t0
            gt = synth.ground_truth(mot, res.points.double(), times)
            err = errors(res, gt)
            base = err["rms"] if base is None else base
            rows.append({"frames": n, "m": m, "reference": "series" if template else "single",
                         **err, "ratio": err["rms"] / base, "theory": theory(n, m, template),
                         "seconds": sec})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[5, 11, 21, 41])
    ap.add_argument("--size", type=int, default=301)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    lines = ["| N | m | reference | RMS 1e-3 px | x classical | theory | random 1e-3 px | "
             "random / predicted | s |", "|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for n in args.frames:
        for r in run_case(n, args.size, args.seed):
            lines.append(f"| {r['frames']} | {r['m']} | {r['reference']} | {r['rms'] * 1e3:.2f} | "
                         f"{r['ratio']:.3f} | {r['theory']:.3f} | {r['random'] * 1e3:.2f} | "
                         f"{r['random'] / r['predicted']:.2f} | {r['seconds']:.1f} |")
            print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
