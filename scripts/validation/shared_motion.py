"""The shared-motion model on movies that shake: renders with known motion, and the real
series of ../shared/data (classical vs STS vs STS with the shared motion).

Render study: a smooth homogeneous deformation growing linearly in time plus a rigid shake
of the whole field of view per frame (translation std ``--shake`` px per axis, rotation std
``--angle`` rad), Gaussian noise on every image (reference included). For each seed:
classical DIC, STS m=2 without the shared motion, with it, and with it and the refined
reference; RMS error of u, v over all point-frames but the reference's, as a fraction of
classical, and the share of point-frames measured with the full window and converged.

Real series (skipped with a reason where ../shared/data is absent): the muDIC hourglass and
DIC Challenge sample 12 with the commands of docs/real.md: usable points at the last frame,
full windows, velocities present, time.

    python scripts/validation/shared_motion.py                # render study, 3 seeds (~3 min)
    python scripts/validation/shared_motion.py --real         # plus the real series (~15 min)
    python scripts/validation/shared_motion.py --only-real    # the real series alone
    python scripts/validation/shared_motion.py --quick        # smoke test (small render, 1 seed)

Writes docs/validation/shared_motion.csv and shared_motion_real.csv (unless --quick).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import torch_stsdic as sts  # noqa: E402
from torch_stsdic.synth import (  # noqa: E402
    HomogeneousStrain,
    RigidJitter,
    ground_truth,
    make_speckle,
    render_series,
)

DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "docs" / "validation"


def jittery_movie(size: int, frames: int, shake: float, angle: float, noise: float, seed: int):
    """(movie (T, H, W) with the reference first, motion, times)."""
    times = torch.arange(0.0, frames)
    c = ((size - 1) / 2, (size - 1) / 2)
    smooth = HomogeneousStrain(exx=0.002, eyy=-0.001, exy=0.0005, center=c, rate=1.0)
    motion = smooth + RigidJitter.random(times, shake, angle, center=c, seed=seed)
    ref, fr = render_series(make_speckle((size, size), seed=seed + 100), (size, size), motion,
                            times[1:], noise_sigma=noise, seed=seed + 200)
    return torch.cat([ref[None], fr]), motion, times


def rms_error(res, motion, times) -> float:
    """RMS of the u, v errors over the usable point-frames but the reference's, px."""
    gt = ground_truth(motion, res.points.double(), times)
    ok = (res.status <= 1)[1:]
    e2 = ((res.u.double() - gt["u"]) ** 2 + (res.v.double() - gt["v"]) ** 2)[1:] / 2
    return float(e2[ok].mean().sqrt())


def full_windows(res, m: int) -> float:
    """Share of point-frames (reference's excluded) with the full window, converged."""
    return float(((res.m == m) & (res.status == 0))[1:].float().mean())


def render_study(seeds: list[int], size: int, frames: int, shake: float, angle: float,
                 noise: float) -> list[dict]:
    rows = []
    cases = [("classical", 0, None, False), ("STS m=2", 2, None, False),
             ("STS m=2, shared motion", 2, "auto", False),
             ("STS m=2, shared motion, refined", 2, "auto", True)]
    for seed in seeds:
        movie, motion, times = jittery_movie(size, frames, shake, angle, noise, seed)
        e0 = None
        for name, m, shared, refine in cases:
            t0 = time.perf_counter()
            res = sts.track(movie, config=sts.DICConfig(m=m), step=10, progress=False,
                            shared_motion=shared, refine_reference=refine)
            sec = time.perf_counter() - t0
            e = rms_error(res, motion, times)
            e0 = e if e0 is None else e0
            rec = res.info.get("shared_motion") or {}
            rows.append({"seed": seed, "case": name, "rms_px": round(e, 5),
                         "vs_classical": round(e / e0, 3),
                         "full_window_converged": round(full_windows(res, m), 4) if m else "",
                         "shake_applied": rec.get("applied", ""), "seconds": round(sec, 2)})
            print(rows[-1], flush=True)
    return rows


def real_study() -> list[dict]:
    if not DATA.is_dir():
        print(f"skipped: {DATA} is absent (the real series are not shipped)")
        return []
    y, x = np.mgrid[:1040, :400]
    s12_mask = (x - 192.7) ** 2 + (y - 541.2) ** 2 > 68 ** 2
    series = {
        "hourglass": (DATA / "mudic-hourglass", dict(roi=(150, 20, 1120, 734), step=20)),
        "sample 12": (DATA / "dic-challenge-sample12",
                      dict(roi=(58, 60, 334, 1020), step=10, mask=s12_mask)),
    }
    rows = []
    for name, (path, kw) in series.items():
        for case, m, shared in (("classical", 0, None), ("STS m=2", 2, None),
                                ("STS m=2, shared motion", 2, "auto")):
            t0 = time.perf_counter()
            res = sts.track(str(path), config=sts.DICConfig(m=m, subset_size=31),
                            progress=False, shared_motion=shared, **kw)
            sec = time.perf_counter() - t0
            ok = (res.status <= 1).numpy()
            rec = res.info.get("shared_motion") or {}
            row = {"series": name, "case": case, "usable_last": round(float(ok[-1].mean()), 4),
                   "usable_all": round(float(ok.mean()), 4),
                   "full_window": (round(float(((res.m.numpy() == m) & ok).mean()), 4)
                                   if m else ""),
                   "velocity_present": (round(float(np.isfinite(res.ut.numpy()).mean()), 4)
                                        if m else ""),
                   "shake_median_px": rec.get("jitter_px_median", ""),
                   "steps": " ".join(str(s) for s in rec.get("steps", [])),
                   "seconds": round(sec, 1)}
            rows.append(row)
            print(row, flush=True)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small render, one seed, no files")
    ap.add_argument("--real", action="store_true", help="also the real series")
    ap.add_argument("--only-real", action="store_true", help="the real series alone")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--shake", type=float, default=0.25, help="px per axis (std)")
    ap.add_argument("--angle", type=float, default=5e-4, help="rad (std)")
    ap.add_argument("--noise", type=float, default=3.0, help="grey levels (std)")
    args = ap.parse_args(argv)
    torch.set_num_threads(min(2, torch.get_num_threads()))
    if args.quick:
        rows = render_study([0], 91, 9, args.shake, args.angle, args.noise)
        return 0 if rows else 1
    if args.only_real:
        write_csv(OUT / "shared_motion_real.csv", real_study())
        return 0
    rows = render_study(list(range(args.seeds)), 201, 24, args.shake, args.angle, args.noise)
    write_csv(OUT / "shared_motion.csv", rows)
    for case in dict.fromkeys(r["case"] for r in rows):
        sel = [r for r in rows if r["case"] == case]
        print(f"{case:34s} median {np.median([r['vs_classical'] for r in sel]):.3f}x classical"
              + (f", full windows {np.median([r['full_window_converged'] for r in sel]):.3f}"
                 if sel[0]["full_window_converged"] != "" else ""))
    if args.real:
        write_csv(OUT / "shared_motion_real.csv", real_study())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
