"""Why a reference averaged from the series does not lift the single-reference floor by itself:
the measurement behind the design note in docs/validation/series_reference.md.

A render (181 x 181, 21 images with noise sigma 2 on every one of them, the reference included;
a uniform motion decelerating in time) is measured classically against image 0. Every image is
then mapped back to the reference configuration with the measured displacements (bilinear
between the POIs) and averaged into a template, and the series is measured again against the
template; this is iterated. The same template built with the TRUE displacements shows what the
averaging alone would give. Error = measured - truth over all points and frames 1..20; "offset"
is each point's error averaged over the frames (the part common to every frame: the reference's
share), RMS over points.

    python scripts/validation/series_reference_gauge.py [--iterations 4] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core.interpolation import BSplineImage


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    n = args.frames
    mot = synth.QuadraticInTime(au=0.13, bu=-0.004, av=-0.07, bv=0.002)
    mv = synth.synthetic_movie((181, 181), n - 1, mot, noise_sigma=2.0, seed=5)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    kw = dict(step=8, progress=False, checks=False, shared_motion=None, times=times.numpy())
    truth = [torch.tensor([mot._at(t)[i] for t in times.tolist()]).double()[:, None]
             for i in (0, 1)]
    rows = []

    def run(ref):
        return sts.track(series, config=sts.DICConfig(m=0, subset_size=21), reference=ref,
                         **kw)

    def record(res, name):
        e = torch.cat([res.u.double()[1:] - truth[0][1:], res.v.double()[1:] - truth[1][1:]], 1)
        off = torch.nanmean(e, 0)
        rows.append((name, float(e[torch.isfinite(e)].pow(2).mean().sqrt()) * 1e3,
                     float(off.pow(2).nanmean().sqrt()) * 1e3))

    res = run(0)
    pts = res.points.double()
    xs, ys = torch.unique(pts[:, 0]), torch.unique(pts[:, 1])
    h, w = series.shape[-2:]
    gx, gy = torch.meshgrid(torch.arange(w, dtype=torch.float64),
                            torch.arange(h, dtype=torch.float64), indexing="xy")
    grid = torch.stack([(gx - xs[0]) / (xs[-1] - xs[0]) * 2 - 1,
                        (gy - ys[0]) / (ys[-1] - ys[0]) * 2 - 1], -1)[None]
    img = BSplineImage(series)

    def dense(vals):
        g = vals.reshape(len(ys), len(xs))[None, None]
        return F.grid_sample(g, grid, mode="bilinear", padding_mode="border",
                             align_corners=True)[0, 0]

    def template(u, v):
        return sum(img.sample(gx + dense(u[t]), gy + dense(v[t]), t) for t in range(n)) / n

    record(res, "classical against image 0")
    u, v = res.u.double().nan_to_num(0), res.v.double().nan_to_num(0)
    for k in range(1, args.iterations + 1):
        res = run(template(u, v).numpy())
        record(res, f"against the template, iteration {k}")
        u, v = res.u.double().nan_to_num(0), res.v.double().nan_to_num(0)
    true_t = template(truth[0].expand(n, pts.shape[0]), truth[1].expand(n, pts.shape[0]))
    record(run(true_t.numpy()), "against a template built with the TRUE motion")
    first = rows[0][2]
    lines = ["| measurement | RMS error 1e-3 px | offset 1e-3 px | offset x sqrt(k+1) |",
             "|---|---:|---:|---:|"]
    for i, (name, rms, off) in enumerate(rows):
        law = f"{off * (i + 1) ** 0.5:.2f}" if 0 < i <= args.iterations else ""
        lines.append(f"| {name} | {rms:.2f} | {off:.2f} | {law} |")
    text = "\n".join(lines)
    print(text)
    print(f"(offset of the single reference: {first:.2f}e-3 px)")
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
