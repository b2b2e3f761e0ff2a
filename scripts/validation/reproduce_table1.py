"""Reproduce Table 1 of Wang & Ma (STS-DIC): error of u against the number of averaged frames.

The paper's simulated experiment: a 301 x 301 speckle reference, nine frames translated by
u = t / 20 px (t = 1..9), 19 x 19 POIs (spacing 10 px), 21 x 21 subsets, Gaussian noise of
sigma = 0 and 5 grey levels, windows of 1 (classical DIC), 3, 5, 7 and 9 frames.

How it is run here: **per centre window**. Every window is centred on frame t = 5 (the only
frame where all five window sizes fit centred), i.e. frames 5-m .. 5+m, solved by
``sts.solve_window`` (FFT initial guess, then Gauss-Newton) for the 361 POIs; the error is the
RMS over the POIs (Eq. 20) of u - 0.25 px, pooled over ``--seeds`` noise realisations. The
time column is the wall time of one ``solve_window`` call (361 POIs, prefilter + FFT +
Gauss-Newton) on this machine with ``--threads`` torch threads. ``--mode track`` instead runs
``sts.track`` over the nine frames (shifted windows at the ends) and pools all frames.

Reference-noise protocols (sigma > 0):

* ``noisy``: independent noise on every image, reference included (the paper's stated protocol);
* ``clean``: a noise-free reference, noisy frames;
* ``mean8``: the reference is the mean of 8 still noisy frames (sigma / sqrt(8));

(The ``refined`` protocol, the single-reference refinement of ``refine_reference=True``,
was removed on 2026-11-28: ``refine_reference`` is now a setting of the template made from the
series, which needs 25 points and 3 frames; docs/accuracy.md.)

The ``average`` formulation is retired (it runs as ``joint+average``) and not in the table.

The frames' noise is the same realisation in all three protocols. Beside the measured error,
the noise floor predicted by :func:`torch_stsdic.core.noise.predicted_std` (from the clean
reference's gradients) and the ratio of the measured *random* error (RMS of u minus the
noise-free solution of the same formulation) to it are reported.

Outputs (``--out``, default docs/validation): table1.csv, table1.md.

    python scripts/validation/reproduce_table1.py --seeds 2        # as in docs (~15 min, 2 cores)
    python scripts/validation/reproduce_table1.py --formulations auto --protocols noisy,clean
    python scripts/validation/reproduce_table1.py --quick          # tiny smoke run (seconds)
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic.core.noise import predicted_std
from torch_stsdic.synth import Translation, make_speckle, render_series

PAPER_SIGMA5 = {1: 10.7272, 3: 5.5453, 5: 4.7422, 7: 4.4291, 9: 3.7261}  # e-3 px
PAPER_SIGMA0 = {1: 1.1779, 3: 1.6364, 5: 1.6434, 7: 1.8627, 9: 1.7438}
PAPER_TIME = {1: 2.9742, 3: 53.2310, 5: 95.7100, 7: 120.7580, 9: 143.8548}  # s
VELOCITY = 1.0 / 20.0
PROTOCOLS = ("noisy", "clean", "mean8")
FORM_LABEL = {"auto": "auto (joint)", "joint": "joint", "joint+average": "joint+average"}


def grid(size: int, n: int, step: float = 10.0) -> torch.Tensor:
    """n x n POIs (x, y), spacing ``step``, centred in a size x size image."""
    c = (size - 1) / 2.0
    g = c + (torch.arange(n, dtype=torch.float64) - (n - 1) / 2.0) * step
    ys, xs = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)


def noisy_inputs(ref, frames, sigma, seed, protocol, n_still=8):
    """(reference, frames) of one noise realisation; the frames' noise does not depend on the
    protocol (one generator: frames first, then the reference, then the still frames)."""
    if sigma == 0:
        return ref, frames
    gen = torch.Generator().manual_seed(1000 + seed)
    nf = sigma * torch.randn(frames.shape, generator=gen, dtype=torch.float64)
    nr = sigma * torch.randn(ref.shape, generator=gen, dtype=torch.float64)
    still = sigma * torch.randn((n_still, *ref.shape), generator=gen, dtype=torch.float64)
    if protocol == "noisy":
        r = ref + nr
    elif protocol == "clean":
        r = ref
    elif protocol == "mean8":
        r = ref + still.mean(0)
    else:
        raise ValueError(f"unknown protocol {protocol!r}")
    return r, frames + nf


def sigma_ref_of(protocol: str, sigma: float, n_still: int = 8) -> float:
    return {"noisy": sigma, "clean": 0.0, "mean8": sigma / math.sqrt(n_still)}[protocol]


def rms(x: torch.Tensor) -> float:
    x = x[torch.isfinite(x)]
    return float(x.pow(2).mean().sqrt()) if x.numel() else math.nan


def run_window(ref, frames, times, pts, cfg, centre, mode):
    """Solve and return (u, ut, truth_u, truth_ut, seconds, mean iterations)."""
    m = cfg.m
    t0 = time.perf_counter()
    if mode == "centre":
        sl = slice(centre - m, centre + m + 1)
        sol = sts.solve_window(ref, frames[sl], pts, config=cfg, times=times[sl])
        dt = time.perf_counter() - t0
        tc = float(times[centre])
        return (sol.u, sol.ut, torch.full_like(sol.u, tc * VELOCITY),
                torch.full_like(sol.u, VELOCITY), dt, float(sol.iterations.float().mean()))
    res = sts.track(frames, reference=ref, points=pts, config=cfg, times=times, progress=False)
    dt = time.perf_counter() - t0
    tt = res.times.view(-1, 1).expand_as(res.u)
    return (res.u.reshape(-1), res.ut.reshape(-1), (tt * VELOCITY).reshape(-1),
            torch.full_like(res.u.reshape(-1), VELOCITY), dt,
            float(res.iterations.float().mean()))


def predict(ref0, pts, cfg, protocol, sigma, times, centre, mode) -> tuple[float, float]:
    """Predicted RMS noise floor of u and ut over the rows that are measured: the centre
    window, or (track) every target frame with its (shifted at the ends) window."""
    n = cfg.n_frames
    targets = [centre] if mode == "centre" else list(range(len(times)))
    pu, put = [], []
    for k in targets:
        lo = min(max(k - cfg.m, 0), len(times) - n)
        dt = times[lo: lo + n] - times[k]
        u_k = float(times[k]) * VELOCITY
        disp = torch.tensor([u_k, 0.0, VELOCITY, 0.0]) if cfg.m else u_k
        pr = predicted_std(ref0, pts, cfg, sigma_ref=sigma_ref_of(protocol, sigma),
                           sigma_def=sigma, n_frames=n, dt=dt, displacement=disp)
        pu.append(pr["u"])
        put.append(pr["ut"])
    return rms(torch.cat(pu)), rms(torch.cat(put))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny smoke run (seconds)")
    ap.add_argument("--sigma", default="0,5", help="noise levels, comma separated (default 0,5)")
    ap.add_argument("--formulations", default="auto,joint+average",
                    help="solver formulations (auto = joint)")
    ap.add_argument("--protocols", default=",".join(PROTOCOLS),
                    help="reference-noise protocols: noisy, clean, mean8")
    ap.add_argument("--max-m", type=int, default=4, help="largest half window (4: 9 frames)")
    ap.add_argument("--seeds", type=int, default=1, help="noise realisations pooled")
    ap.add_argument("--mode", choices=("centre", "track"), default="centre")
    ap.add_argument("--size", type=int, default=301)
    ap.add_argument("--grid", type=int, default=19, help="POIs per side (spacing 10 px)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--seed", type=int, default=0, help="speckle pattern seed")
    ap.add_argument("--out", default="docs/validation", help="output folder")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.grid, args.max_m, args.seeds = 81, 3, 1, 1
        if args.sigma == "0,5":
            args.sigma = "5"
    torch.set_num_threads(args.threads)
    sigmas = [float(s) for s in args.sigma.split(",") if s.strip()]
    forms = [f.strip() for f in args.formulations.split(",") if f.strip()]
    protocols = [p.strip() for p in args.protocols.split(",") if p.strip()]
    for p in protocols:
        if p not in PROTOCOLS:
            ap.error(f"--protocols: unknown {p!r} (choose from {PROTOCOLS})")
    n_frames = 9
    centre = 4  # frame index of t = 5
    if args.max_m > centre:
        ap.error("--max-m: at most 4 with nine frames")
    shape = (args.size, args.size)
    pattern = make_speckle(shape, seed=args.seed)
    times = torch.arange(1.0, n_frames + 1.0, dtype=torch.float64)
    ref0, frames0 = render_series(pattern, shape, Translation(ut=VELOCITY), times)
    pts = grid(args.size, args.grid)
    print(f"Table 1: {args.size}x{args.size}, {pts.shape[0]} POIs, subsets 21, mode "
          f"{args.mode}, {args.seeds} seed(s), {args.threads} thread(s)")

    rows = []
    clean_cache: dict[tuple[str, int], torch.Tensor] = {}
    for sigma in sigmas:
        for protocol in (protocols if sigma > 0 else ["noisy"]):
            for form in forms:
                for m in range(args.max_m + 1):
                    if m == 0 and form != forms[0]:
                        # one frame: every formulation is classical DIC: reuse
                        prev = [r for r in rows if r["sigma"] == sigma and r["m"] == 0
                                and r["protocol"] == (protocol if sigma > 0 else "-")]
                        if prev:
                            rows.append({**prev[0], "formulation": FORM_LABEL[form]})
                            continue
                    cfg = sts.DICConfig(subset_size=21, m=m, formulation=form)
                    key = (form if m else "classical", m)
                    if key not in clean_cache:
                        u0, *_ = run_window(ref0, frames0, times, pts, cfg, centre, args.mode)
                        clean_cache[key] = u0
                    errs, errt, rand, secs, its = [], [], [], [], []
                    for s in range(args.seeds):
                        r, f = noisy_inputs(ref0, frames0, sigma, s, protocol)
                        u, ut, tu, tut, sec, it = run_window(r, f, times, pts, cfg, centre,
                                                             args.mode)
                        errs.append(u - tu)
                        errt.append(ut - tut)
                        rand.append(u - clean_cache[key])
                        secs.append(sec)
                        its.append(it)
                    e, et, rr = torch.cat(errs), torch.cat(errt), torch.cat(rand)
                    if sigma > 0:
                        pred_u, pred_ut = predict(ref0, pts, cfg, protocol, sigma, times,
                                                  centre, args.mode)
                    else:
                        pred_u = pred_ut = 0.0
                    row = {
                        "sigma": sigma,
                        "protocol": protocol if sigma > 0 else "-",
                        "formulation": FORM_LABEL[form],
                        "frames": 2 * m + 1,
                        "m": m,
                        "rms_u": rms(e),
                        "bias_u": float(e[torch.isfinite(e)].mean()),
                        "rms_ut": rms(et) if m else math.nan,
                        "random_u": rms(rr),
                        "random_std_u": float(rr[torch.isfinite(rr)].std()),
                        "pred_u": pred_u,
                        "ratio_u": rms(rr) / pred_u if pred_u > 0 else math.nan,
                        "pred_ut": pred_ut if m else math.nan,
                        "time_s": min(secs),
                        "iterations": sum(its) / len(its),
                        "ok_fraction": float(torch.isfinite(e).float().mean()),
                        "paper_e": (PAPER_SIGMA5 if sigma == 5 else PAPER_SIGMA0).get(2 * m + 1)
                        if sigma in (0, 5) else math.nan,
                        "paper_time": PAPER_TIME.get(2 * m + 1),
                    }
                    rows.append(row)
                    print(f"sigma={sigma:g} {row['protocol']:6s} {row['formulation']:14s} "
                          f"frames={2 * m + 1}: e={1e3 * row['rms_u']:.4f}e-3 px "
                          f"(bias {1e3 * row['bias_u']:+.4f}e-3, paper {row['paper_e']}) "
                          f"ut={_f(row['rms_ut'], fmt='.4f')}e-3 pred={1e3 * pred_u:.4f}e-3 "
                          f"random/pred={row['ratio_u']:.3f} t={row['time_s']:.2f}s", flush=True)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ("_track" if args.mode == "track" else "")
    with open(out / f"table1{suffix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (out / f"table1{suffix}.md").write_text(markdown(rows, args))
    print(f"wrote {out / f'table1{suffix}.csv'} and {out / f'table1{suffix}.md'}")
    return 0


def _f(x: float, scale: float = 1e3, fmt: str = ".3f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else \
        format(x * scale, fmt)


def markdown(rows, args) -> str:
    lines = [f"Table 1 reproduction ({args.mode} windows, {args.size}x{args.size}, "
             f"{args.grid}x{args.grid} POIs, {args.seeds} seed(s), {args.threads} thread(s)). "
             "Errors in 1e-3 px; `random` = RMS of u minus the noise-free solution; `pred` = "
             "predicted noise floor (torch_stsdic.core.noise); time = "
             + ("one solve_window call (s)." if args.mode == "centre" else
                "the whole sts.track run over the 9 frames (s)."), ""]
    sig = sorted({r["sigma"] for r in rows})
    # headline: the default formulation, all protocols, beside the paper
    head = [r for r in rows if r["formulation"] == rows[0]["formulation"]]
    cols = []
    for s in sig:
        for p in sorted({r["protocol"] for r in head if r["sigma"] == s},
                        key=lambda p: (PROTOCOLS + ("-",)).index(p)):
            cols.append((s, p))
    lines.append("| frames | " + " | ".join(
        f"e σ={s:g} {p if p != '-' else ''}".strip() for s, p in cols)
        + " | paper σ=5 | paper σ=0 | time (s) | paper time (s) |")
    lines.append("|" + "---|" * (len(cols) + 5))
    for n in sorted({r["frames"] for r in head}):
        cells = []
        for s, p in cols:
            hit = [r for r in head if r["sigma"] == s and r["protocol"] == p
                   and r["frames"] == n]
            cells.append(_f(hit[0]["rms_u"]) if hit else "-")
        t = [r["time_s"] for r in head if r["frames"] == n]
        lines.append(f"| {n} | " + " | ".join(cells)
                     + f" | {PAPER_SIGMA5.get(n, '-')} | {PAPER_SIGMA0.get(n, '-')} | "
                     f"{min(t):.2f} | {PAPER_TIME.get(n, '-')} |")
    lines += ["", f"Headline formulation: {rows[0]['formulation']}.", "",
              "All rows:", "",
              "| σ | reference | formulation | frames | e (RMS u) | bias u | e(ut) | random "
              "| random std | pred | random/pred | pred ut | time (s) | iters |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['sigma']:g} | {r['protocol']} | {r['formulation']} | {r['frames']} | "
            f"{_f(r['rms_u'])} | {_f(r['bias_u'], fmt='+.3f')} | {_f(r['rms_ut'])} | "
            f"{_f(r['random_u'])} | {_f(r['random_std_u'])} | {_f(r['pred_u'])} | "
            f"{_f(r['ratio_u'], 1, '.3f')} | "
            f"{_f(r['pred_ut'])} | {r['time_s']:.2f} | {r['iterations']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
