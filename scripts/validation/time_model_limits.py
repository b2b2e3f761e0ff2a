"""Where the linear-in-time model of STS-DIC breaks: acceleration and sudden jumps.

STS-DIC fits u(t) = u + ut dt over the 2m+1 frames of a window. Three experiments on
synthetic speckle (``torch_stsdic.synth``, 21 px subsets, the default "auto" = joint
formulation):

1. **Quadratic motion** u = a t^2 (``QuadraticInTime(bu=a)``), noise-free, window centred on
   t = 10, m = 0..4. The least-squares line through a parabola sampled at the symmetric
   offsets dt = -m..m has the intercept error a mean(dt^2) = a m (m+1) / 3 and an *exact*
   slope (dt^2 is even, so it does not project on dt): the displacement is biased by
   a m(m+1)/3, the velocity is not. The measured bias is compared with this formula.
2. **Trade-off with noise** (sigma = 5 on the frames; noisy or noise-free reference): the
   total RMS error against the prediction sqrt((a m(m+1)/3)^2 + floor(m)^2), with floor(m)
   from :func:`torch_stsdic.core.noise.predicted_std`. The best m is where the two balance.
3. **Sudden jump** (crack-like, ``Jump``: +du for x > x0 from t_jump on, on top of a uniform
   velocity), tracked with ``sts.track`` for m = 0..4: a window that straddles the jump
   returns the mean of the step over its frames, so the 2m frames nearest to the jump are
   wrong by up to du m/(2m+1); the window's mean ZNCC drops there (a usable detector). Run
   with ``checks=False`` to show the bare model: by default ``track`` detects these windows
   and shortens them (``scripts/validation/motion_families.py``).

Outputs (``--out``, default docs/validation): time_model_limits.csv,
time_model_limits_jump.csv, time_model_limits.png, time_model_limits.md.

    python scripts/validation/time_model_limits.py            # about 1-3 minutes on 2 cores
    python scripts/validation/time_model_limits.py --quick    # smoke run
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
from torch_stsdic.synth import Jump, QuadraticInTime, Translation, make_speckle, render_series


def grid(size: int, n: int, step: float) -> torch.Tensor:
    c = (size - 1) / 2.0
    g = c + (torch.arange(n, dtype=torch.float64) - (n - 1) / 2.0) * step
    ys, xs = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)


def rms(x: torch.Tensor) -> float:
    x = x[torch.isfinite(x)]
    return float(x.pow(2).mean().sqrt()) if x.numel() else math.nan


def line_bias(a: float, m: int) -> float:
    """Intercept error of the LS line through a*dt^2 at dt = -m..m: a * mean(dt^2)."""
    dt = torch.arange(-m, m + 1, dtype=torch.float64)
    return float(a * (dt * dt).mean())


def quadratic(args, rows, pattern, shape, pts) -> None:
    tc = 10.0
    mmax = args.max_m
    times = torch.arange(tc - mmax, tc + mmax + 1, dtype=torch.float64)
    for a in args.accelerations:
        motion = QuadraticInTime(bu=a)
        ref0, frames0 = render_series(pattern, shape, motion, times)
        truth_u, truth_ut = a * tc * tc, 2.0 * a * tc
        for protocol in ["none"] + args.protocols:
            sigma = 0.0 if protocol == "none" else args.sigma
            if sigma > 0:
                gen = torch.Generator().manual_seed(3000 + int(a * 1e6))
                nf = sigma * torch.randn(frames0.shape, generator=gen, dtype=torch.float64)
                nr = sigma * torch.randn(ref0.shape, generator=gen, dtype=torch.float64)
                ref = ref0 + nr if protocol == "noisy" else ref0
                frames = frames0 + nf
            else:
                ref, frames = ref0, frames0
            for m in range(mmax + 1):
                cfg = sts.DICConfig(subset_size=21, m=m)
                c = mmax
                sl = slice(c - m, c + m + 1)
                t0 = time.perf_counter()
                sol = sts.solve_window(ref, frames[sl], pts, config=cfg, times=times[sl])
                sec = time.perf_counter() - t0
                e = sol.u - truth_u
                et = sol.ut - truth_ut
                theory = line_bias(a, m)
                floor = 0.0
                if sigma > 0:
                    floor = rms(predicted_std(
                        ref0, pts, cfg, sigma_ref=sigma if protocol == "noisy" else 0.0,
                        sigma_def=sigma,
                        displacement=torch.tensor([truth_u, 0.0, truth_ut, 0.0]) if m
                        else truth_u)["u"])
                rows.append({
                    "a": a, "reference_noise": protocol, "sigma": sigma, "m": m,
                    "frames": 2 * m + 1, "bias_u": float(e[torch.isfinite(e)].mean()),
                    "theory_bias_u": theory, "rms_u": rms(e),
                    "predicted_rms_u": math.hypot(theory, floor), "floor_u": floor,
                    "bias_ut": float(et[torch.isfinite(et)].mean()) if m else math.nan,
                    "rms_ut": rms(et) if m else math.nan,
                    "zncc": float(sol.zncc[torch.isfinite(sol.zncc)].mean()), "time_s": sec,
                })
                r = rows[-1]
                print(f"a={a:g} ref={protocol:5s} m={m}: bias {1e3 * r['bias_u']:+.3f}e-3 "
                      f"(theory {1e3 * theory:+.3f}e-3) rms {1e3 * r['rms_u']:.3f}e-3 "
                      f"(pred {1e3 * r['predicted_rms_u']:.3f}e-3) ut bias "
                      f"{1e3 * r['bias_ut']:+.4f}e-3", flush=True)


def jump(args, jrows, pattern, shape) -> None:
    x0, du, vel = (shape[1] - 1) / 2.0 + 0.5, args.jump, 0.02
    t_jump = 9.5
    n_frames = 10 if args.quick else 19
    times = torch.arange(1.0, n_frames + 1.0, dtype=torch.float64)
    if args.quick:
        t_jump = 5.5
    motion = Translation(ut=vel) + Jump(x0=x0, du=du, t_jump=t_jump)
    ref, frames = render_series(pattern, shape, motion, times)
    if args.sigma > 0 and args.jump_noise:
        gen = torch.Generator().manual_seed(77)
        frames = frames + args.sigma * torch.randn(frames.shape, generator=gen,
                                                   dtype=torch.float64)
    off = 12.0 + 21.0 * torch.arange(2 if args.quick else 3, dtype=torch.float64)
    xs = torch.cat([x0 - 0.5 - off.flip(0), x0 - 0.5 + off])
    ys = torch.arange(25.0, shape[0] - 25.0, 40.0 if args.quick else 20.0, dtype=torch.float64)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)
    moving = pts[:, 0] > x0
    for m in range(min(args.max_m, (n_frames - 1) // 2) + 1):
        cfg = sts.DICConfig(subset_size=21, m=m)
        # checks=False: the bare model's error (track's model check would shorten these
        # windows; that is measured by scripts/validation/motion_families.py)
        res = sts.track(frames, reference=ref, points=pts, config=cfg, times=times,
                        progress=False, checks=False, shared_motion=None)  # the bare model
        for k in range(res.n_frames):
            t = float(res.times[k])
            true_u = vel * t + (du * moving.double() if t >= t_jump else 0.0)
            e = res.u[k] - true_u
            # the LS-line prediction: the window's frames are k-m..k+m (shifted at the ends)
            lo = min(max(k - m, 0), n_frames - (2 * m + 1))
            wt = times[lo: lo + 2 * m + 1]
            step = (wt >= t_jump).double() * du
            dt = wt - t
            if m:
                A = torch.stack([torch.ones_like(dt), dt], 1)
                coef = torch.linalg.lstsq(A, step.unsqueeze(1)).solution[:, 0]
                pred = float(coef[0]) - (du if t >= t_jump else 0.0)
            else:
                pred = 0.0
            jrows.append({"m": m, "frame": k, "t": t, "t_jump": t_jump,
                          "error_u_moving": float(e[moving].mean()),
                          "theory_error_u_moving": pred,
                          "error_u_static": float(e[~moving].mean()),
                          "zncc_moving": float(res.zncc[k][moving].mean()),
                          "zncc_static": float(res.zncc[k][~moving].mean())})
        errs = [r["error_u_moving"] for r in jrows if r["m"] == m]
        print(f"jump m={m}: max |error| moving side {max(abs(x) for x in errs):.3f} px "
              f"(theory {du * m / (2 * m + 1):.3f}), frames with |error| > 0.05 px: "
              f"{sum(abs(x) > 0.05 for x in errs)}", flush=True)


def best_m(rows, a, protocol):
    sel = [r for r in rows if r["a"] == a and r["reference_noise"] == protocol]
    if not sel:
        return None, None
    meas = min(sel, key=lambda r: r["rms_u"])["m"]
    pred = min(sel, key=lambda r: r["predicted_rms_u"])["m"]
    return meas, pred


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--accelerations", default="0.0005,0.002,0.005,0.02",
                    help="a in u = a t^2 (px / frame^2)")
    ap.add_argument("--sigma", type=float, default=5.0)
    ap.add_argument("--protocols", default="noisy,clean", help="reference noise: noisy, clean")
    ap.add_argument("--max-m", type=int, default=4)
    ap.add_argument("--jump", type=float, default=0.5, help="jump height du (px)")
    ap.add_argument("--jump-noise", action="store_true", help="add sigma to the jump frames")
    ap.add_argument("--size", type=int, default=201)
    ap.add_argument("--grid", type=int, default=15, help="POIs per side (spacing 10 px)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="docs/validation")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.grid, args.max_m = 121, 3, 2
        args.accelerations = "0.005"
    torch.set_num_threads(args.threads)
    args.accelerations = [float(a) for a in args.accelerations.split(",") if a.strip()]
    args.protocols = [p.strip() for p in args.protocols.split(",") if p.strip()]
    shape = (args.size, args.size)
    pattern = make_speckle(shape, seed=5, margin=40)
    pts = grid(args.size, args.grid, 10.0)
    rows: list[dict] = []
    jrows: list[dict] = []
    t0 = time.perf_counter()
    quadratic(args, rows, pattern, shape, pts)
    jump(args, jrows, pattern, shape)
    print(f"done in {time.perf_counter() - t0:.0f} s")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sfx = "_quick" if args.quick else ""
    for name, data in ((f"time_model_limits{sfx}.csv", rows),
                       (f"time_model_limits_jump{sfx}.csv", jrows)):
        with open(out / name, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(data[0]))
            w.writeheader()
            w.writerows(data)
    plot(args, rows, jrows, out / f"time_model_limits{sfx}.png")
    md = markdown(args, rows, jrows)
    (out / f"time_model_limits{sfx}.md").write_text(md)
    print(md)
    return 0


def plot(args, rows, jrows, path) -> None:
    fig = Figure(figsize=(12.0, 8.0), layout="constrained")
    ax = fig.subplots(2, 2)
    ms = list(range(args.max_m + 1))
    for i, a in enumerate(args.accelerations):
        sel = [r for r in rows if r["a"] == a and r["reference_noise"] == "none"]
        ax[0, 0].plot(ms, [abs(r["bias_u"]) for r in sel], f"C{i}o", label=f"a = {a:g}")
        ax[0, 0].plot(ms[1:], [r["theory_bias_u"] for r in sel][1:], f"C{i}-", lw=1)
    ax[0, 0].set_yscale("log")
    ax[0, 0].set_ylim(bottom=1e-5)
    ax[0, 0].set_xlabel("m (window 2m+1 frames)")
    ax[0, 0].set_ylabel("|bias of u| (px)")
    ax[0, 0].set_title("u = a t²: measured (dots) vs a m(m+1)/3 (lines), noise-free")
    for protocol, axis in zip(args.protocols, (ax[0, 1], ax[1, 0])):
        for i, a in enumerate(args.accelerations):
            sel = [r for r in rows if r["a"] == a and r["reference_noise"] == protocol]
            axis.plot(ms, [r["rms_u"] for r in sel], f"C{i}o", label=f"a = {a:g}")
            axis.plot(ms, [r["predicted_rms_u"] for r in sel], f"C{i}-", lw=1)
        axis.set_yscale("log")
        axis.set_xlabel("m")
        axis.set_ylabel("RMS error of u (px)")
        axis.set_title(f"σ = {args.sigma:g}, {protocol} reference: measured (dots), "
                       "sqrt(bias² + floor²) (lines)", fontsize=9)
    for m in sorted({r["m"] for r in jrows}):
        sel = [r for r in jrows if r["m"] == m]
        ax[1, 1].plot([r["t"] for r in sel], [r["error_u_moving"] for r in sel], f"C{m}o-",
                      ms=3, lw=1, label=f"m = {m}")
        ax[1, 1].plot([r["t"] for r in sel], [r["theory_error_u_moving"] for r in sel],
                      f"C{m}:", lw=1)
    ax[1, 1].axvline(jrows[0]["t_jump"], color="k", lw=0.5)
    ax[1, 1].set_xlabel("frame time t")
    ax[1, 1].set_ylabel("error of u, moving side (px)")
    ax[1, 1].set_title(f"jump of {args.jump:g} px at t = {jrows[0]['t_jump']:g}: measured "
                       "(solid), LS line through the step (dotted)", fontsize=9)
    for axis in ax.flat:
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=7)
    from torch_stsdic.plot import save_figure

    save_figure(fig, path)


def markdown(args, rows, jrows) -> str:
    lines = ["Limits of the linear-in-time model (21 px subsets, joint formulation).", "",
             "Quadratic motion u = a t², window centred on t = 10 (bias in 1e-3 px; theory "
             "a m(m+1)/3; velocity bias in 1e-3 px/frame):", "",
             "| a (px/frame²) | m | bias u | theory | bias ut | mean ZNCC |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        if r["reference_noise"] == "none":
            but = "-" if math.isnan(r["bias_ut"]) else format(1e3 * r["bias_ut"], "+.4f")
            lines.append(f"| {r['a']:g} | {r['m']} | {1e3 * r['bias_u']:+.3f} | "
                         f"{1e3 * r['theory_bias_u']:.3f} | {but} | {r['zncc']:.6f} |")
    for protocol in args.protocols:
        lines += ["", f"Total RMS error of u (1e-3 px) with σ = {args.sigma:g} on the frames, "
                  f"{protocol} reference: measured / predicted sqrt(bias² + floor²):", "",
                  "| a | " + " | ".join(f"m={m}" for m in range(args.max_m + 1))
                  + " | best m measured / predicted |",
                  "|---|" + "---|" * (args.max_m + 2)]
        for a in args.accelerations:
            sel = [r for r in rows if r["a"] == a and r["reference_noise"] == protocol]
            bm, bp = best_m(rows, a, protocol)
            lines.append(f"| {a:g} | " + " | ".join(
                f"{1e3 * r['rms_u']:.2f} / {1e3 * r['predicted_rms_u']:.2f}" for r in sel)
                + f" | {bm} / {bp} |")
    lines += ["", f"Jump of {args.jump:g} px at t = {jrows[0]['t_jump']:g} (moving side; "
              "error in px, mean ZNCC of the window):", "",
              "| m | max abs error | theory du m/(2m+1) | frames with abs error > 0.05 px | "
              "min ZNCC (moving side) | ZNCC away from the jump |", "|---|---|---|---|---|---|"]
    for m in sorted({r["m"] for r in jrows}):
        sel = [r for r in jrows if r["m"] == m]
        far = [r["zncc_moving"] for r in sel if abs(r["t"] - r["t_jump"]) > m + 1]
        lines.append(
            f"| {m} | {max(abs(r['error_u_moving']) for r in sel):.3f} | "
            f"{args.jump * m / (2 * m + 1):.3f} | "
            f"{sum(abs(r['error_u_moving']) > 0.05 for r in sel)} | "
            f"{min(r['zncc_moving'] for r in sel):.4f} | "
            f"{(sum(far) / len(far)) if far else math.nan:.4f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
