"""Reproduce Fig. 6 of Wang & Ma: error of u against image noise, sigma = 0..10.

Three methods on the paper's simulated series (301 x 301, nine frames, u = t / 20 px,
19 x 19 POIs, 21 x 21 subsets), evaluated at the centre frame t = 5:

* classical DIC (one frame, m = 0);
* STS-DIC with five frames (m = 2, frames t = 3..7, the default "auto" = joint formulation);
* direct temporal smoothing of the classical results over the same five frames
  (``sts.smooth_in_time``, span 5: a least-squares line in time per POI, value at t = 5).

Two reference-noise protocols: ``noisy`` (noise on every image, the paper's protocol) and
``clean`` (noise-free reference). The frames' noise is the same realisation in both. The
dashed lines are the noise floors predicted by :mod:`torch_stsdic.core.noise`; for the symmetric
window the smoothing floor equals the STS floor (to first order both average the five
frames' noise and neither averages the reference's).

Outputs (``--out``, default docs/validation): fig6.csv, fig6.png, fig6.md.

    python scripts/validation/reproduce_fig6.py            # full run (a few minutes on 2 cores)
    python scripts/validation/reproduce_fig6.py --quick    # tiny smoke run
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import torch
from matplotlib.figure import Figure

import torch_stsdic as sts
from torch_stsdic.core.noise import predicted_std
from torch_stsdic.plot import plot_xy, save_figure
from torch_stsdic.synth import Translation, make_speckle, render_series

VELOCITY = 1.0 / 20.0
PROTOCOLS = ("noisy", "clean")
METHODS = ("classical", "STS m=2", "smoothed classical")


def grid(size: int, n: int, step: float = 10.0) -> torch.Tensor:
    c = (size - 1) / 2.0
    g = c + (torch.arange(n, dtype=torch.float64) - (n - 1) / 2.0) * step
    ys, xs = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)


def rms(x: torch.Tensor) -> float:
    x = x[torch.isfinite(x)]
    return float(x.pow(2).mean().sqrt()) if x.numel() else math.nan


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny smoke run (seconds)")
    ap.add_argument("--sigmas", default="0,1,2,3,4,5,6,7,8,9,10")
    ap.add_argument("--protocols", default=",".join(PROTOCOLS))
    ap.add_argument("--span", type=int, default=5, help="frames of STS and of the smoothing")
    ap.add_argument("--formulation", default="auto")
    ap.add_argument("--seeds", type=int, default=1, help="noise realisations pooled")
    ap.add_argument("--size", type=int, default=301)
    ap.add_argument("--grid", type=int, default=19)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0, help="speckle pattern seed")
    ap.add_argument("--out", default="docs/validation")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.grid, args.seeds = 81, 3, 1
        if args.sigmas == "0,1,2,3,4,5,6,7,8,9,10":
            args.sigmas = "0,5"
    torch.set_num_threads(args.threads)
    if args.span < 1 or args.span % 2 == 0 or args.span > 9:
        ap.error("--span: odd, 1..9")
    m = args.span // 2
    sigmas = [float(s) for s in args.sigmas.split(",") if s.strip()]
    protocols = [p.strip() for p in args.protocols.split(",") if p.strip()]
    shape = (args.size, args.size)
    times = torch.arange(1.0, 10.0, dtype=torch.float64)
    centre = 4
    ref0, frames0 = render_series(make_speckle(shape, seed=args.seed), shape,
                                  Translation(ut=VELOCITY), times)
    pts = grid(args.size, args.grid)
    truth = float(times[centre]) * VELOCITY
    sl = slice(centre - m, centre + m + 1)
    cfg0 = sts.DICConfig(subset_size=21, m=0)
    cfg = sts.DICConfig(subset_size=21, m=m, formulation=args.formulation)
    disp = torch.tensor([truth, 0.0, VELOCITY, 0.0])
    print(f"Fig. 6: {args.size}x{args.size}, {pts.shape[0]} POIs, span {args.span}, "
          f"{args.seeds} seed(s)")
    rows = []
    t_start = time.perf_counter()
    for protocol in protocols:
        for sigma in sigmas:
            err = {k: [] for k in METHODS}
            for s in range(args.seeds):
                gen = torch.Generator().manual_seed(2000 + 7919 * s + int(round(sigma * 1000)))
                nf = sigma * torch.randn(frames0.shape, generator=gen, dtype=torch.float64)
                nr = sigma * torch.randn(ref0.shape, generator=gen, dtype=torch.float64)
                ref = ref0 + nr if protocol == "noisy" else ref0
                frames = frames0 + nf
                cl = torch.stack([
                    sts.solve_window(ref, frames[k], pts, config=cfg0).u
                    for k in range(sl.start, sl.stop)])  # (span, N) classical
                st = sts.solve_window(ref, frames[sl], pts, config=cfg, times=times[sl])
                sm = sts.smooth_in_time(cl, args.span, times[sl])
                err["classical"].append(cl[m] - truth)
                err["STS m=2"].append(st.u - truth)
                err["smoothed classical"].append(sm[m] - truth)
            sr = sigma if protocol == "noisy" else 0.0
            if sigma > 0:
                p_cl = rms(predicted_std(ref0, pts, cfg0, sigma_ref=sr, sigma_def=sigma,
                                         displacement=truth)["u"])
                p_st = rms(predicted_std(ref0, pts, cfg, sigma_ref=sr, sigma_def=sigma,
                                         displacement=disp)["u"])
                # LS line through 2m+1 classical results at the centre = their mean: the
                # reference noise is shared, the frames' noise is averaged
                p_sm = rms(predicted_std(ref0, pts, cfg0, sigma_ref=sr,
                                         sigma_def=sigma / math.sqrt(args.span),
                                         displacement=truth)["u"])
            else:
                p_cl = p_st = p_sm = 0.0
            for meth, pred in zip(METHODS, (p_cl, p_st, p_sm)):
                e = torch.cat(err[meth])
                rows.append({"protocol": protocol, "sigma": sigma, "method": meth,
                             "rms_u": rms(e), "bias_u": float(e[torch.isfinite(e)].mean()),
                             "pred_u": pred})
            last = rows[-3:]
            print(f"{protocol:5s} sigma={sigma:4.1f}: " + "  ".join(
                f"{r['method']}={1e3 * r['rms_u']:.3f}e-3 (pred {1e3 * r['pred_u']:.3f})"
                for r in last) + f"  [{time.perf_counter() - t_start:.0f} s]", flush=True)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sfx = "_quick" if args.quick else ""
    with open(out / f"fig6{sfx}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    fig = Figure(figsize=(6.0 * len(protocols), 4.2), layout="constrained")
    axes = fig.subplots(1, len(protocols), squeeze=False)[0]
    for ax, protocol in zip(axes, protocols):
        series = {}
        for meth in METHODS:
            series[meth] = [1e3 * r["rms_u"] for r in rows
                            if r["protocol"] == protocol and r["method"] == meth]
        plot_xy(sigmas, series, ax=ax, xlabel="noise sigma (grey levels)",
                ylabel="RMS error of u (1e-3 px)",
                title=f"{'noisy' if protocol == 'noisy' else 'noise-free'} reference")
        sts_line = ax.get_lines()[-2]  # STS drawn as open squares: it hides under smoothing
        sts_line.set_marker("s")
        sts_line.set_markersize(9)
        sts_line.set_markerfacecolor("none")
        sts_line.set_zorder(3)
        for meth, style in (("classical", "C0--"), ("STS m=2", "C1--")):
            pr = [1e3 * r["pred_u"] for r in rows
                  if r["protocol"] == protocol and r["method"] == meth]
            label = "predicted floor, classical" if meth == "classical" else \
                "predicted floor, STS = smoothing"
            ax.plot(sigmas, pr, style, lw=1, label=label)
        ax.legend(fontsize=8)
    save_figure(fig, out / f"fig6{sfx}.png")
    md = markdown(rows, sigmas, protocols, args)
    (out / f"fig6{sfx}.md").write_text(md)
    print(md)
    print(f"wrote {out / f'fig6{sfx}.csv'}, {out / f'fig6{sfx}.png'}, {out / f'fig6{sfx}.md'}")
    return 0


def markdown(rows, sigmas, protocols, args) -> str:
    lines = [f"Fig. 6 reproduction ({args.size}x{args.size}, {args.grid}x{args.grid} POIs, "
             f"span {args.span}, {args.seeds} seed(s)); RMS error of u in 1e-3 px "
             "(predicted floor in brackets).", ""]
    for protocol in protocols:
        lines += [f"Reference: {protocol}", "",
                  "| σ | classical | STS m=2 | smoothed classical | STS/classical | "
                  "STS/smoothed |", "|---|---|---|---|---|---|"]
        ratios = {"cl": [], "sm": []}
        for s in sigmas:
            r = {x["method"]: x for x in rows if x["protocol"] == protocol and x["sigma"] == s}
            a, b, c = (r[k]["rms_u"] for k in METHODS)
            if s >= 2:
                ratios["cl"].append(b / a)
                ratios["sm"].append(b / c)
            lines.append(
                f"| {s:g} | " + " | ".join(
                    f"{1e3 * r[k]['rms_u']:.3f} ({1e3 * r[k]['pred_u']:.3f})" for k in METHODS)
                + f" | {b / a:.3f} | {b / c:.3f} |")
        if ratios["cl"]:
            mc = sum(ratios["cl"]) / len(ratios["cl"])
            ms = sum(ratios["sm"]) / len(ratios["sm"])
            lines += ["", f"Mean ratios for σ >= 2: STS/classical = {mc:.3f}, "
                      f"STS/smoothed = {ms:.3f}."]
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
