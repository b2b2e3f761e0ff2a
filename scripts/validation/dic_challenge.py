"""DIC Challenge 1.0 samples 5 and 14 (real / synthetic speckle with known truth).

Reads ``../shared/data`` (relative to the repository root; ``--data`` to change) and skips
with a clear message when it is absent (the images are not part of the repository).

Sample 5 (real speckle, rigid shift with contrast changes): the reference and two images,
``000`` (shift 0.0 px, contrast 75 %) and ``001`` (shift 0.1 px in x and y, contrast 100 %).
Every state is a single image, so only **classical DIC** (m = 0) is possible: STS-DIC needs
2m+1 >= 3 frames of one continuous motion, and two images at different, unrelated states
are not a time series. The error of u and v against the truth (bias, std, RMS) is reported,
with the noise floor predicted from the images' noise (estimated by Immerkaer's method on
each image) by :mod:`torch_stsdic.core.noise`. Note that the truth of sample 5 is only 0.0 and 0.1
px: the errors are dominated by noise and contrast change, not by large-motion effects.

Sample 14 (synthetic, sinusoidal u(x) with frequency growing along x, amplitude 0.1 px;
v = 0): the reference and L1, L3, L5 (three frequency ramps). u is averaged over y per
column x and compared with ``ground_truth.csv``, as is exx (from the subset shape
function's du/dx, averaged over y; microstrain). Classical DIC only: L1, L3, L5 are three
*different* displacement fields (different frequency ramps, the same amplitude), not three
instants of one motion, so the linear-in-time model of STS-DIC (u(L3) = mean of u(L1),
u(L5)) does not hold and a 3-frame "series" would be meaningless.

Outputs (``--out``, default docs/validation): dic_challenge.csv, dic_challenge.md,
dic_challenge_sample14.png, dic_challenge_sample14_profiles.csv.

    python scripts/validation/dic_challenge.py             # about a minute on 2 cores
    python scripts/validation/dic_challenge.py --quick     # smoke run
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np
import tifffile
import torch
from matplotlib.figure import Figure

import torch_stsdic as sts
from torch_stsdic.core.noise import estimate_noise_sigma, predicted_std, residual_noise_sigma
from torch_stsdic.plot import save_figure

REPO = Path(__file__).resolve().parents[2]


def _read_tiff(path: Path) -> np.ndarray:
    return tifffile.imread(str(path)).astype(np.float64)


def local_slope(x: np.ndarray, y: np.ndarray, span: int) -> np.ndarray:
    """Least-squares slope of y(x) over a centred window of ``span`` samples (shrunk at the
    ends; NaN samples skipped): the strain of a 1-D "virtual strain gauge"."""
    h = span // 2
    out = np.full_like(y, np.nan)
    for i in range(len(x)):
        sl = slice(max(0, i - h), min(len(x), i + h + 1))
        xx, yy = x[sl], y[sl]
        ok = np.isfinite(yy)
        if ok.sum() >= 2:
            xc = xx[ok] - xx[ok].mean()
            out[i] = float((xc * (yy[ok] - yy[ok].mean())).sum() / (xc * xc).sum())
    return out


def stats(e: torch.Tensor) -> dict[str, float]:
    e = e[torch.isfinite(e)]
    return {"bias": float(e.mean()), "std": float(e.std()), "rms": float(e.pow(2).mean().sqrt())}


def sample5(folder: Path, args, rows: list[dict], lines: list[str]) -> None:
    truth = {}
    with open(folder / "ground_truth.csv") as fh:
        for r in csv.DictReader(fh):
            truth[r["filename"]] = (float(r["u_x_px"]), float(r["u_y_px"]))
    ref = _read_tiff(folder / "Sample5_Reference.tif")
    h, w = ref.shape
    margin = 20
    step = 50 if args.quick else 10
    lines += ["## Sample 5 (classical DIC; one image per state)", "",
              f"Grid step {step} px, {margin} px from the border; errors in px. σ res: noise "
              "from the converged DIC residual (sqrt(σ_ref² + σ_img²) in reference grey "
              "levels, torch_stsdic.core.noise.residual_noise_sigma); σ Imm.: Immerkaer single-"
              "image estimates of the reference / image (texture-inflated on real speckle); "
              "pred: the noise floor (std) predicted from σ res.", "",
              "| image | subset | points ok | u bias | u std | u RMS | v bias | v std | v RMS "
              "| σ res | σ Imm. ref / img | pred std u, v | std/pred u, v | time (s) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    s_ref = estimate_noise_sigma(ref)
    for name, (tu, tv) in truth.items():
        img = _read_tiff(folder / name)
        s_img = estimate_noise_sigma(img)
        for size in args.subsets:
            cfg = sts.DICConfig(subset_size=size, m=0)
            pts = sts.grid_points(ref.shape, step=step, subset_size=size,
                                  roi=(margin, margin, w - 1 - margin, h - 1 - margin))
            t0 = time.perf_counter()
            sol = sts.solve_window(ref, img, pts, config=cfg)
            sec = time.perf_counter() - t0
            su, sv = stats(sol.u - tu), stats(sol.v - tv)
            # total noise seen by the ZNSSD residual, in the reference's grey levels; the
            # split between reference and image is unknown: assume equal halves for the
            # reference-gradient correction (a ~2 % effect here)
            s_res = residual_noise_sigma(ref, img, pts, sol.params, cfg)
            pr = predicted_std(ref, pts, cfg, sigma_ref=s_res, sigma_def=0.0,
                               ref_noise=s_res / math.sqrt(2.0))
            pu = float(pr["u"].pow(2).mean().sqrt())
            pv = float(pr["v"].pow(2).mean().sqrt())
            ok = int(sol.ok.sum())
            rows.append({"sample": 5, "image": name, "subset": size, "points": len(pts),
                         "ok": ok, "u_bias": su["bias"], "u_std": su["std"],
                         "u_rms": su["rms"], "v_bias": sv["bias"], "v_std": sv["std"],
                         "v_rms": sv["rms"], "sigma_residual": s_res,
                         "sigma_immerkaer_ref": s_ref, "sigma_immerkaer_img": s_img,
                         "pred_u": pu, "pred_v": pv, "exx_rms": math.nan,
                         "exx_fit_rms": math.nan, "time_s": sec})
            lines.append(
                f"| {name} | {size} | {ok}/{len(pts)} | {su['bias']:+.4f} | {su['std']:.4f} "
                f"| {su['rms']:.4f} | {sv['bias']:+.4f} | {sv['std']:.4f} | {sv['rms']:.4f} "
                f"| {s_res:.2f} | {s_ref:.2f} / {s_img:.2f} | {pu:.4f}, {pv:.4f} | "
                f"{su['std'] / pu:.2f}, {sv['std'] / pv:.2f} | {sec:.1f} |")
            print(f"sample 5 {name} subset {size}: u {su} v {sv} sigma_res {s_res:.3f} "
                  f"pred ({pu:.4f}, {pv:.4f})", flush=True)
    lines.append("")


def sample14(folder: Path, args, rows: list[dict], lines: list[str], out: Path) -> None:
    gt = np.genfromtxt(folder / "ground_truth.csv", delimiter=",", names=True)
    ref = _read_tiff(folder / "Sample14_Reference.tif")
    h, w = ref.shape
    xstep = 64 if args.quick else 4
    ystep = 200 if args.quick else 20
    lines += ["## Sample 14 (classical DIC; L1, L3, L5 are different fields, not a series)",
              "", f"Grid: every {xstep} px in x, every {ystep} px in y; u averaged over y per "
              "column. exx two ways: `subset` = the subset shape function's du/dx averaged "
              f"over y; `fit` = least-squares slope of the averaged u(x) over "
              f"{args.strain_window} columns ({(args.strain_window - 1) * xstep} px). RMS "
              "over the columns where the subset fits (px and microstrain); `x<1024` / "
              "`x>=1024`: the low- and high-frequency halves.", "",
              "| level | subset | u RMS | u RMS x<1024 | u RMS x>=1024 | exx subset RMS (µε) "
              "| exx fit RMS | exx fit RMS x<1024 | exx fit RMS x>=1024 | max abs exx truth "
              "| time (s) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    fig = Figure(figsize=(11.0, 7.5), layout="constrained")
    axes = fig.subplots(3, 2)
    profiles: dict[str, np.ndarray] = {}
    per_point: dict[str, tuple[int, float]] = {}  # level -> (points per column, u RMS)
    for li, level in enumerate(("L1", "L3", "L5")):
        img = _read_tiff(folder / f"Sample14_{level}_Amp0.1b.tif")
        tu = gt[f"u_{level}_px"]
        te = gt[f"exx_{level}_microstrain"]
        axes[li, 0].plot(gt["x_px"], tu, "k-", lw=1, label="truth")
        axes[li, 1].plot(gt["x_px"], te, "k-", lw=1, label="truth")
        for size in args.subsets:
            half = size // 2
            xs = np.arange(half + 2, w - half - 2, xstep, dtype=np.float64)
            ys = np.arange(max(half + 2, 20), h - max(half + 2, 20), ystep, dtype=np.float64)
            gx, gy = np.meshgrid(xs, ys)
            pts = torch.tensor(np.stack([gx.ravel(), gy.ravel()], 1))
            cfg = sts.DICConfig(subset_size=size, m=0)
            t0 = time.perf_counter()
            sol = sts.solve_window(ref, img, pts, config=cfg)
            sec = time.perf_counter() - t0
            u = sol.u.numpy().reshape(len(ys), len(xs))
            ux = sol.params[:, sol.param_names.index("ux")].numpy().reshape(len(ys), len(xs))
            ok = sol.ok.numpy().reshape(len(ys), len(xs))
            u = np.where(ok, u, np.nan)
            ux = np.where(ok, ux, np.nan)
            u_prof = np.nanmean(u, 0)
            per_point[f"{level}"] = (len(ys), float(np.sqrt(np.nanmean(
                (u - tu[xs.astype(int)][None, :]) ** 2))))
            e_prof = 1e6 * np.nanmean(ux, 0)
            xi = xs.astype(int)
            eu = u_prof - tu[xi]
            ee = e_prof - te[xi]
            ef_prof = 1e6 * local_slope(xs, u_prof, args.strain_window)
            ef = ef_prof - te[xi]
            lo = xs < 1024

            def r(a):
                a = a[np.isfinite(a)]
                return float(np.sqrt(np.mean(a * a))) if a.size else math.nan

            rows.append({"sample": 14, "image": level, "subset": size,
                         "points": len(pts), "ok": int(ok.sum()), "u_bias": float(
                             np.nanmean(eu)), "u_std": float(np.nanstd(eu)), "u_rms": r(eu),
                         "v_bias": float(np.nanmean(sol.v.numpy())), "v_std": float(
                             np.nanstd(sol.v.numpy())), "v_rms": r(sol.v.numpy()),
                         "sigma_residual": math.nan, "sigma_immerkaer_ref": math.nan,
                         "sigma_immerkaer_img": math.nan, "pred_u": math.nan,
                         "pred_v": math.nan, "exx_rms": r(ee), "exx_fit_rms": r(ef),
                         "time_s": sec})
            lines.append(
                f"| {level} | {size} | {r(eu):.4f} | {r(eu[lo]):.4f} | {r(eu[~lo]):.4f} | "
                f"{r(ee):.0f} | {r(ef):.0f} | {r(ef[lo]):.0f} | {r(ef[~lo]):.0f} | "
                f"{np.abs(te).max():.0f} | {sec:.1f} |")
            print(f"sample 14 {level} subset {size}: u RMS {r(eu):.4f} px, exx RMS "
                  f"{r(ee):.0f} (subset) / {r(ef):.0f} (fit) microstrain "
                  f"({int(ok.sum())}/{len(pts)} ok, {sec:.1f} s)", flush=True)
            axes[li, 0].plot(xs, u_prof, lw=1, label=f"DIC, subset {size}")
            axes[li, 1].plot(xs, e_prof, lw=0.6, alpha=0.6,
                             label=f"DIC subset du/dx, subset {size}")
            axes[li, 1].plot(xs, ef_prof, lw=1,
                             label=f"DIC fit over {args.strain_window} columns, subset {size}")
            profiles[f"x_{level}_{size}"] = xs
            profiles[f"u_{level}_{size}"] = u_prof
            profiles[f"exx_subset_{level}_{size}"] = e_prof
            profiles[f"exx_fit_{level}_{size}"] = ef_prof
        axes[li, 0].set_ylabel(f"{level}: u (px)")
        axes[li, 1].set_ylabel(f"{level}: exx (µε)")
        for ax in axes[li]:
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7)
    axes[2, 0].set_xlabel("x (px)")
    axes[2, 1].set_xlabel("x (px)")
    n_col = max(n for n, _ in per_point.values())
    one = ", ".join(f"{lv} {e:.3f}" for lv, (_, e) in per_point.items())
    fig.suptitle(f"DIC Challenge sample 14: u(x) and exx(x), each the mean of the {n_col} "
                 f"points of a column (classical DIC)\na single point's u RMS error: {one} px")
    lines += ["", f"Per point (before the column mean of {n_col} points): u RMS {one} px."]
    sfx = "_quick" if args.quick else ""
    save_figure(fig, out / f"dic_challenge_sample14{sfx}.png")
    n = max(len(v) for v in profiles.values())
    with open(out / f"dic_challenge_sample14_profiles{sfx}.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        keys = list(profiles)
        wr.writerow(keys)
        for i in range(n):
            wr.writerow([f"{profiles[k][i]:.6g}" if i < len(profiles[k]) else "" for k in keys])
    lines.append("")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared" / "data"),
                    help="folder with dic-challenge-sample5 and -sample14 (../shared/data)")
    ap.add_argument("--quick", action="store_true", help="smoke run (few points)")
    ap.add_argument("--subsets", default="21", help="subset sizes, comma separated")
    ap.add_argument("--samples", default="5,14")
    ap.add_argument("--strain-window", type=int, default=5,
                    help="columns of the sample-14 strain fit (default 5)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="docs/validation")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.subsets = [int(s) for s in args.subsets.split(",") if s.strip()]
    data = Path(args.data)
    samples = [s.strip() for s in args.samples.split(",") if s.strip()]
    folders = {"5": data / "dic-challenge-sample5", "14": data / "dic-challenge-sample14"}
    missing = [str(folders[s]) for s in samples if not folders[s].is_dir()]
    if missing:
        print(f"SKIPPED: DIC Challenge data not found ({', '.join(missing)}); the images are "
              "not part of the repository (see ../shared/data/README.md)")
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    lines = ["DIC Challenge 1.0 (classical DIC, ZNSSD, affine subsets, cubic B-splines).", ""]
    if "5" in samples:
        sample5(folders["5"], args, rows, lines)
    if "14" in samples:
        sample14(folders["14"], args, rows, lines, out)
    sfx = "_quick" if args.quick else ""
    with open(out / f"dic_challenge{sfx}.csv", "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    (out / f"dic_challenge{sfx}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {out / f'dic_challenge{sfx}.csv'} and {out / f'dic_challenge{sfx}.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
