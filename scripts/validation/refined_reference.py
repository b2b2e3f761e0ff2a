"""Refined reference and off-grid points: measured error of each scheme next to its prediction.

Two movies with noise on every image (the reference too), frame 0 the reference, 41 frames,
u = t/20, v = t/40 px, 21x21 subsets, float32:

* ``render``: the analytic speckle renderer (torch_stsdic.synth), 161x161, sigma = 5;
* ``real``: a real camera speckle (DIC Challenge sample 5 reference, ``../shared/data``;
  skipped when absent), 256x256 crop shifted by Fourier interpolation, then cropped to
  200x200, sigma = 3 added to every image (the camera's own noise is common to all frames).

Schemes: classical (m = 0), STS m = 2, against the reference image alone
(``series_reference=False``), against the reference made from the series
(``series_reference=True``; predicted ``a sqrt(w + 1/N_t)``, N_t = min(frames, 21) the
template's images), and with ``refine_reference=True`` (the template, its gauge from the
trajectories: predicted as the template, whose registration neither prediction counts);
points on the pixel grid and the same grid moved by (+0.37, -0.41) px. Prediction (first
order, docs/accuracy.md): with ``a`` the frame-to-frame scatter of classical DIC (the
frames' share), classical sqrt(2) a, STS sqrt(1 + 1/5) a.

    python scripts/validation/refined_reference.py            # a few minutes on 2 loaded cores
    python scripts/validation/refined_reference.py --quick    # smoke run (21 frames)
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

import torch_stsdic as sts
from torch_stsdic.synth import Translation, make_speckle, render_series

REPO = Path(__file__).resolve().parents[2]
UT, VT = 0.05, 0.025


def render_movie(n: int, seed: int = 1) -> torch.Tensor:
    size = (161, 161)
    pat = make_speckle(size, radius=2.0, seed=seed)
    ref, frames = render_series(pat, size, Translation(ut=UT, vt=VT), torch.arange(1, n),
                                noise_sigma=5.0, seed=seed + 10)
    return torch.cat([ref[None], frames]).float()


def real_movie(n: int, data: Path, seed: int = 2) -> torch.Tensor | None:
    path = data / "dic-challenge-sample5" / "Sample5_Reference.tif"
    if not path.exists():
        return None
    img = torch.from_numpy(tifffile.imread(str(path)).astype(np.float64))[128:384, 128:384]
    ky = torch.fft.fftfreq(256, dtype=torch.float64)[:, None]
    kx = torch.fft.fftfreq(256, dtype=torch.float64)[None, :]
    spec = torch.fft.fft2(img)
    g = torch.Generator().manual_seed(seed)
    out = []
    for t in range(n):  # g(x + u) = f(x): shift the content by +u
        ph = torch.exp(-2j * math.pi * (kx * UT * t + ky * VT * t))
        fr = torch.fft.ifft2(spec * ph).real[28:228, 28:228]
        out.append(fr + 3.0 * torch.randn(fr.shape, generator=g, dtype=torch.float64))
    return torch.stack(out).float()


def grid(size: int, offset=(0.0, 0.0)) -> np.ndarray:
    g = np.arange(20.0, size - 20.0, 8.0)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel() + offset[0], y.ravel() + offset[1]], 1)


def errors(res, rows: slice) -> dict[str, float]:
    t = res.times.numpy()[:, None]
    eu = (res.u.numpy() - UT * t)[rows]
    ev = (res.v.numpy() - VT * t)[rows]
    e = np.concatenate([eu, ev], 1)
    off = e.mean(0)
    out = {"rms": float(np.sqrt(np.mean(e**2))), "mean": float(e.mean()),
           "offset": float(np.sqrt(np.mean(off**2))),
           "scatter": float(np.sqrt(np.mean((e - off) ** 2)))}
    if np.isfinite(res.ut.numpy()).any():
        eut = np.concatenate([res.ut.numpy() - UT, res.vt.numpy() - VT], 1)[rows]
        # rows the model check solved classically (m = 0) have no velocity (NaN)
        out["vel_rms"] = float(np.sqrt(np.nanmean(eut**2)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "validation")
    args = ap.parse_args(argv)
    n = 21 if args.quick else args.frames
    rows = slice(3, n - 3)
    torch.set_num_threads(1)
    movies = {"render": render_movie(n)}
    real = real_movie(n, args.data)
    if real is None:
        print(f"real: skipped ({args.data} has no dic-challenge-sample5)")
    else:
        movies["real"] = real
    table = []
    for name, mv in movies.items():
        size = mv.shape[-1]
        for grid_name, off in (("on grid", (0.0, 0.0)), ("off grid", (0.37, -0.41))):
            pts = grid(size, off)
            a = None
            for m, mode in ((0, "single"), (2, "single"), (0, "series"), (2, "series"),
                            (0, "refined"), (2, "refined")):
                refine = mode == "refined"
                if grid_name == "off grid" and refine:
                    continue
                cfg = sts.DICConfig(m=m, dtype="float32")
                t0 = time.perf_counter()
                res = sts.track(mv, points=pts, config=cfg, progress=False,
                                refine_reference=refine,
                                series_reference=mode in ("series", "refined"))
                sec = time.perf_counter() - t0
                err = errors(res, rows)
                if m == 0 and mode == "single":
                    a = err["scatter"]
                info = res.info.get("refine_reference") or {}
                frames_l = info.get("frames_median", 0)
                if mode in ("series", "refined"):  # the template's noise: 1/N of a frame's
                    pred = a * math.sqrt((1.0 if m == 0 else 0.2) + 1.0 / min(n, 21))
                else:
                    pred = a * math.sqrt(2.0 if m == 0 else 1.2)
                table.append({
                    "movie": name, "points": grid_name, "scheme": ("classical" if m == 0 else
                                                                   "STS m=2")
                    + {"single": "", "series": " series ref", "refined": " refined"}[mode],
                    "rms_1e-3px": round(err["rms"] * 1e3, 2),
                    "predicted_1e-3px": round(pred * 1e3, 2),
                    "offset_1e-3px": round(err["offset"] * 1e3, 2),
                    "scatter_1e-3px": round(err["scatter"] * 1e3, 2),
                    "mean_1e-3px": round(err["mean"] * 1e3, 2),
                    "vel_rms_1e-3px_per_frame": round(err.get("vel_rms", float("nan")) * 1e3, 2),
                    "fit_frames": frames_l, "refine_s": info.get("seconds", 0.0),
                    "run_s": round(sec, 2), "frames": n, "points_n": len(pts),
                })
                print(table[-1], flush=True)
    for r in table:  # ratio to classical at the same points (on grid)
        base = next(x for x in table if x["movie"] == r["movie"] and x["points"] == "on grid"
                    and x["scheme"] == "classical")  # against the reference image alone
        r["x_classical_on_grid"] = round(r["rms_1e-3px"] / base["rms_1e-3px"], 3)
    args.out.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    with open(args.out / f"refined_reference{suffix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(table)
    cols = ["movie", "points", "scheme", "rms_1e-3px", "predicted_1e-3px", "x_classical_on_grid",
            "offset_1e-3px", "scatter_1e-3px", "mean_1e-3px", "vel_rms_1e-3px_per_frame",
            "fit_frames", "refine_s", "run_s"]
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in table]
    (args.out / f"refined_reference{suffix}.md").write_text(
        "Generated by `python scripts/validation/refined_reference.py"
        f"{' --quick' if args.quick else ''}`"
        f" ({n} frames, errors over frames 3..{n - 4}, 2 loaded CPU cores, 1 thread).\n\n"
        + "\n".join(md) + "\n")
    print((args.out / f"refined_reference{suffix}.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
