"""Motion families that break the affine-in-time window: how many results are trusted, and how
good the trusted ones are.

For each family (rigid rotation 4 and 1 degrees per frame, constant acceleration, a crack
opening, a large translation of tens of px per frame) a speckle movie is rendered
(:mod:`torch_stsdic.synth`, noise on every image, the reference included) and tracked with
``sts.track`` with the defaults (except ``subset_size`` and ``m``), classical (m = 0) and STS
(m = 2). Counted over the point-frames whose subset stays inside the image at the true motion:

- ``usable``: the share reported CONVERGED / MAX_ITER (trusted);
- ``bad``: the share of the trusted results off by more than 0.1 px (the promise broken);
- ``rms``: RMS error of the trusted results, px; ``m_mean``: the mean window half-width used.

Outputs (``--out``, default docs/validation): motion_families.csv, motion_families.md,
motion_families.png.

    python scripts/validation/motion_families.py            # a few minutes on 2 cores
    python scripts/validation/motion_families.py --quick    # smaller images, smoke run
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch

import torch_stsdic as sts
from torch_stsdic.core.status import usable
from torch_stsdic.synth import (
    MOTION_FAMILIES,
    ground_truth,
    make_speckle,
    motion_family,
    render_series,
)

FAMILIES = MOTION_FAMILIES


def render_family(name: str, size: int = 401, n_frames: int = 10, noise: float = 2.0,
                  seed: int = 0):
    """(series (T+1, H, W) float32 with the reference first, times (T,), motion)."""
    motion = motion_family(name, size)
    times = torch.arange(1.0, n_frames + 1.0)
    pattern = make_speckle((size, size), seed=seed, margin=size)
    ref, frames = render_series(pattern, (size, size), motion, times, noise_sigma=noise,
                                seed=seed + 1)
    return torch.cat([ref[None], frames]).float(), times, motion


def evaluate(res, motion, times, size: int, subset: int) -> dict[str, float]:
    """Usable share, bad share and RMS over truly-inside point-frames (frames 1..T)."""
    pts = res.points.double()
    truth = ground_truth(motion, pts, times)
    u, v = res.u[1:].double(), res.v[1:].double()
    st = res.status[1:]
    half = subset // 2 + 2
    xd = pts[:, 0] + truth["u"]
    yd = pts[:, 1] + truth["v"]
    r = half * 1.5  # a rotated subset reaches sqrt(2) further along its corners
    inside = (xd - r >= 0) & (xd + r <= size - 1) & (yd - r >= 0) & (yd + r <= size - 1)
    ok = torch.as_tensor(usable(st)) & inside
    err = torch.hypot(u - truth["u"], v - truth["v"])
    n_in = int(inside.sum())
    n_ok = int(ok.sum())
    bad = int((ok & (err > 0.1)).sum())
    mm = res.m
    return {
        "points_inside": n_in,
        "usable": n_ok / max(n_in, 1),
        "bad": bad / max(n_ok, 1),
        "rms": float(err[ok].pow(2).mean().sqrt()) if n_ok else float("nan"),
        "m_mean": float(mm[1:][ok].float().mean()) if mm is not None and n_ok else float("nan"),
    }


VARIANTS = ((0, True), (2, True), (0, False), (2, False))  # (m, checks)


def run_family(name: str, m: int, size: int, n_frames: int, subset: int, step: int,
               noise: float, seed: int = 0, checks: bool = True) -> dict[str, float]:
    series, times, motion = render_family(name, size, n_frames, noise, seed)
    cfg = sts.DICConfig(m=m, subset_size=subset)
    t0 = time.perf_counter()
    res = sts.track(series, reference=0, config=cfg, step=step, progress=False,
                    checks=checks)
    out = evaluate(res, motion, times, size, subset)
    out["seconds"] = time.perf_counter() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs/validation"))
    ap.add_argument("--quick", action="store_true", help="201 px images, 6 frames")
    ap.add_argument("--families", nargs="*", default=list(FAMILIES))
    args = ap.parse_args()
    size, n_frames, subset, step = (201, 6, 31, 20) if args.quick else (401, 10, 31, 20)
    noise = 2.0
    rows = []
    for fam in args.families:
        for m, checks in VARIANTS:
            r = run_family(fam, m, size, n_frames, subset, step, noise, checks=checks)
            r.update(family=fam, m=m, checks=checks)
            rows.append(r)
            print(f"{fam:18s} m={m} checks={checks!s:5s}  usable {r['usable']:6.1%}  "
                  f"bad {r['bad']:6.2%}  "
                  f"rms {r['rms']:.4f} px  m_mean {r['m_mean']:.2f}  ({r['seconds']:.1f} s)",
                  flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    keys = ["family", "m", "checks", "points_inside", "usable", "bad", "rms", "m_mean", "seconds"]
    with open(args.out / "motion_families.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in keys})
    _figure(rows, args.out / "motion_families.png")
    _markdown(rows, args.out / "motion_families.md", size, n_frames, subset, step, noise)


LABELS = {"rotation4": "rotation\n4°/frame", "rotation1": "rotation\n1°/frame",
          "acceleration": "acceleration", "crack": "crack",
          "large_translation": "translation\n12 px/frame"}


def _figure(rows, path: Path) -> None:
    from matplotlib.figure import Figure

    fams = list(dict.fromkeys(r["family"] for r in rows))
    fig = Figure(figsize=(13, 3.9), layout="constrained")
    axs = fig.subplots(1, 3)
    x = np.arange(len(fams))
    styles = {(0, False): ("classical, no checks", "#9ecae1", "//"),
              (2, False): ("STS m=2, no checks", "#fdae6b", "//"),
              (0, True): ("classical, checked", "#3182bd", None),
              (2, True): ("STS m=2, checked + adaptive m", "#e6550d", None)}
    order = [(0, False), (2, False), (0, True), (2, True)]
    width = 0.2
    for j, (key, label) in enumerate([("usable", "trusted share of point-frames"),
                                      ("bad", "trusted results off by > 0.1 px"),
                                      ("rms", "RMS error of trusted results (px)")]):
        ax = axs[j]
        for k, var in enumerate(order):
            vals = [next((r[key] for r in rows if r["family"] == f and
                          (r["m"], r["checks"]) == var), np.nan) for f in fams]
            name, colour, hatch = styles[var]
            ax.bar(x + (k - 1.5) * width, vals, width, label=name, color=colour, hatch=hatch,
                   edgecolor="white" if hatch is None else "grey", linewidth=0.5)
        ax.set_xticks(x, [LABELS.get(f, f) for f in fams], fontsize=8)
        ax.set_title(label, fontsize=10)
        if key == "bad":
            ax.axhline(0.01, color="k", lw=0.8, ls="--")
            ax.set_yscale("symlog", linthresh=0.01)
            ax.set_ylim(0, 1.0)
        if key in ("usable", "bad"):
            ax.yaxis.set_major_formatter(lambda v, _: f"{v:.0%}" if v >= 0.01 or v == 0
                                         else f"{v:.1%}")
        if key == "rms":
            ax.set_yscale("log")
    axs[0].set_ylim(0, 1.05)
    fig.legend(*axs[0].get_legend_handles_labels(), loc="outside lower center", ncols=4,
               fontsize=8)
    fig.savefig(path, dpi=120)


def _markdown(rows, path: Path, size, n_frames, subset, step, noise) -> None:
    lines = [
        "# Motion families: trusted results and their errors",
        "",
        f"Generated by `python scripts/validation/motion_families.py`: {size} x {size} px renders, "
        f"{n_frames} frames after the reference, noise sigma {noise} grey levels on every "
        f"image, subset {subset} px, grid step {step} px, float32, `sts.track` defaults "
        "otherwise. Counted over point-frames whose subset stays inside the image.",
        "",
        "`checks` False is the tracker without the trust checks of `torch_stsdic.analysis.quality` "
        "(every converged point reported as such, fixed m): how it behaved before they "
        "existed.",
        "",
        "| family | m | checks | point-frames | trusted | trusted off by > 0.1 px "
        "| RMS (px) | mean m used | time (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['family']} | {r['m']} | {r['checks']} | {r['points_inside']} | "
                     f"{r['usable']:.1%} | {r['bad']:.2%} | {r['rms']:.4f} | "
                     f"{r['m_mean']:.2f} | {r['seconds']:.1f} |")
    lines += ["", "![motion families](motion_families.png)", ""]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
