"""Refined reference: the per-frame error profile, its decomposition, and the first-order
prediction (the study behind docs/accuracy.md, "Error per frame").

Renders (301x301, analytic speckle, 41 frames, frame 0 the reference, u = rate * t, v = 0,
19x19 points ``linspace(30, 270, 19)``, 21x21 subsets, float32) with Gaussian noise of std
``s_ref`` on the reference and ``s_frames`` on every other frame, then classical DIC (m = 0),
STS m = 2 and STS m = 2 with ``refine_reference=True``. Cases: noise on every image (sigma 5,
rate 1/20 px/frame) over several seeds; and, over the first two seeds, noise on the reference
only, on the frames only, and rates 1/80 and 1/5 px/frame.

Per scheme it reports

* the RMS error of u, v (together) at frames 0, 4, ..., 40;
* a per-point decomposition of the error over frames 3..37: ``e(t) = alpha + beta t + r``,
  as the RMS of alpha (the part constant in time), of 20 beta (the linear part, per 20 frames:
  1 px of motion at 1/20 px/frame) and of r (the rest);
* for the refined scheme, the first-order prediction of each frame's RMS (no fitted
  parameter): with ``c`` the reference's offset (std ``a_r``) and ``s_j`` the frames' errors
  (std ``a_f``), both measured from the classical run, and the fit's shrink factor, the
  refined error is ``c (1 - lam_t0 - sum om) + sum_j (lam_tj - om_j) s_j``
  (:func:`torch_stsdic.movie.refine.predicted_profile`; ``lam_t``: the window's line evaluated at t,
  ``om``: the subtracted intercept's weights on the frames).

    python scripts/validation/refine_drift.py            # ~2 min on 2 loaded cores
    python scripts/validation/refine_drift.py --quick    # one seed, no side cases
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch

import torch_stsdic as sts
from torch_stsdic.movie.refine import predicted_profile
from torch_stsdic.synth import Translation, make_speckle, render_series

REPO = Path(__file__).resolve().parents[2]
SIZE = (301, 301)
N_FRAMES = 41
M = 2
SHOW = list(range(0, N_FRAMES, 4))  # frames of the profile
ROWS = slice(3, N_FRAMES - 3)  # frames of the decomposition (full windows)


def movie(seed: int, rate: float, s_ref: float, s_frames: float) -> torch.Tensor:
    """(41, H, W) float32: the clean render plus noise s_ref on frame 0, s_frames on the rest."""
    pat = make_speckle(SIZE, radius=2.0, seed=seed)
    ref, frames = render_series(pat, SIZE, Translation(ut=rate), torch.arange(1, N_FRAMES),
                                noise_sigma=0.0)
    g = torch.Generator().manual_seed(1000 + seed)
    ref = ref + s_ref * torch.randn(ref.shape, generator=g, dtype=ref.dtype)
    frames = frames + s_frames * torch.randn(frames.shape, generator=g, dtype=frames.dtype)
    return torch.cat([ref[None], frames]).float()


def points() -> np.ndarray:
    g = np.linspace(30.0, 270.0, 19)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel()], 1)


def errors(res, rate: float) -> np.ndarray:
    """(2, T, N) errors of u and v (NaN where not usable)."""
    t = res.times.numpy()[:, None]
    ok = res.ok.numpy()
    e = np.stack([res.u.numpy() - rate * t, res.v.numpy()]).astype(np.float64)
    return np.where(ok[None], e, np.nan)


def profile(e: np.ndarray) -> list[float]:
    return [float(np.sqrt(np.nanmean(e[:, f] ** 2))) for f in SHOW]


def decompose(e: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    """RMS of alpha, 20 beta and r of the per-point fit e = alpha + beta t + r over ROWS."""
    tt = t[ROWS]
    x = np.stack([np.ones_like(tt), tt], 1)
    y = e[:, ROWS].transpose(1, 0, 2).reshape(len(tt), -1)
    y = y[:, np.isfinite(y).all(0)]
    coef = np.linalg.lstsq(x, y, rcond=None)[0]
    rest = y - x @ coef
    return (float(np.sqrt(np.mean(coef[0] ** 2))), float(np.sqrt(np.mean((20 * coef[1]) ** 2))),
            float(np.sqrt(np.mean(rest**2))))


def noise_split(e0: np.ndarray) -> tuple[float, float]:
    """(a_r, a_f) from classical errors (2, T, N): the frames' scatter and the offset's std."""
    e = e0[:, 1:]  # frame 0 (the reference against itself) is exactly 0
    n = e.shape[1]
    a_f2 = float(np.nanmean(np.nanvar(e, axis=1, ddof=1)))
    a_r2 = float(np.nanmean(np.nanmean(e, axis=1) ** 2)) - a_f2 / n
    return float(np.sqrt(max(a_r2, 0.0))), float(np.sqrt(a_f2))


def run_case(seed: int, rate: float, s_ref: float, s_frames: float) -> list[dict]:
    mv = movie(seed, rate, s_ref, s_frames)
    pts = points()
    rows, errs = [], {}
    for name, m, refine in (("classical", 0, False), ("STS m=2", 2, False),
                            ("STS m=2 refined", 2, True)):
        t0 = time.perf_counter()
        res = sts.track(mv, points=pts, config=sts.DICConfig(m=m, dtype="float32"),
                        progress=False, refine_reference=refine)
        sec = time.perf_counter() - t0
        e = errors(res, rate)
        errs[name] = e
        const, lin, rest = decompose(e, res.times.numpy())
        info = res.info.get("refine_reference") or {}
        row = {"seed": seed, "rate": rate, "s_ref": s_ref, "s_frames": s_frames,
               "scheme": name, "const": const, "lin20": lin, "rest": rest,
               "profile": profile(e), "shrink": info.get("shrink", float("nan")),
               "fit_frames": info.get("frames_median", 0), "run_s": round(sec, 2)}
        rows.append(row)
    a_r, a_f = noise_split(errs["classical"])
    ref_row = rows[-1]
    shrink = ref_row["shrink"] if np.isfinite(ref_row["shrink"]) else 1.0
    var = predicted_profile(np.arange(N_FRAMES, dtype=np.float64), 0, range(1, N_FRAMES), M,
                            (a_r / a_f) ** 2, shrink)
    ref_row["predicted"] = [float(a_f * np.sqrt(var[f])) for f in SHOW]
    for r in rows:
        r["a_r"], r["a_f"] = a_r, a_f
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "validation")
    ap.add_argument("--tag", default="", help="suffix of the output files")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = args.seeds[:1] if args.quick else args.seeds
    cases = [(s, 0.05, 5.0, 5.0) for s in seeds]
    if not args.quick:
        for s in seeds[:2]:
            cases += [(s, 0.05, 5.0, 0.0), (s, 0.05, 0.0, 5.0), (s, 0.0125, 5.0, 5.0),
                      (s, 0.2, 5.0, 5.0)]
    table = []
    for case in cases:
        rows = run_case(*case)
        table += rows
        for r in rows:
            print(case, r["scheme"], " ".join(f"{1e3 * x:5.1f}" for x in r["profile"]),
                  f"| const {1e3 * r['const']:.1f} lin20 {1e3 * r['lin20']:.1f} "
                  f"rest {1e3 * r['rest']:.1f}", flush=True)
    write(table, args.out, args.tag + ("_quick" if args.quick else ""))
    return 0


def write(table: list[dict], out: Path, suffix: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    head = ["seed", "rate", "s_ref", "s_frames", "scheme", "fit_frames", "shrink", "a_r", "a_f",
            "const", "lin20", "rest"] + [f"f{f}" for f in SHOW] + [f"pred_f{f}" for f in SHOW]
    recs = []
    for r in table:
        rec = {k: r[k] for k in head[:12]}
        rec.update({f"f{f}": v for f, v in zip(SHOW, r["profile"])})
        rec.update({f"pred_f{f}": v for f, v in zip(SHOW, r.get("predicted", [np.nan] * 11))})
        for k in head[7:]:
            rec[k] = round(1e3 * rec[k], 2)  # 1e-3 px
        recs.append(rec)
    with open(out / f"refine_drift{suffix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=head)
        w.writeheader()
        w.writerows(recs)
    md = ["Generated by `python scripts/validation/refine_drift.py` (301x301 renders, 41 frames, "
          "361 points, float32; errors in 1e-3 px, u and v together; 'pred': first-order "
          "prediction of the refined STS error, no fitted parameter).", ""]
    # median over seeds of each case and scheme
    keys = sorted({(r["rate"], r["s_ref"], r["s_frames"], r["scheme"]) for r in recs},
                  key=lambda k: (k[1] != 5.0 or k[2] != 5.0 or k[0] != 0.05, k))
    cols = ["const", "lin20", "rest"] + [f"f{f}" for f in SHOW]
    md.append("| rate px/frame | sigma ref | sigma frames | scheme | seeds | "
              + " | ".join(cols) + " |")
    md.append("|" + "---|" * (5 + len(cols)))
    for k in keys:
        sel = [r for r in recs if (r["rate"], r["s_ref"], r["s_frames"], r["scheme"]) == k]
        med = {c: float(np.median([r[c] for r in sel])) for c in cols}
        md.append(f"| {k[0]} | {k[1]} | {k[2]} | {k[3]} | {len(sel)} | "
                  + " | ".join(f"{med[c]:.1f}" for c in cols) + " |")
        if k[3].endswith("refined"):
            pred = {c: float(np.median([r["pred_" + c] for r in sel])) for c in cols[3:]}
            md.append(f"| | | | predicted | {len(sel)} | | | | "
                      + " | ".join(f"{pred[c]:.1f}" for c in cols[3:]) + " |")
    md.append("")
    md.append("const, lin20, rest: RMS over points of the per-point fit e(t) = alpha + beta t "
              "+ r over frames 3..37 (alpha; 20 beta, i.e. per 20 frames; r). f0 .. f40: RMS "
              "error at that frame (median over seeds).")
    (out / f"refine_drift{suffix}.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    raise SystemExit(main())
