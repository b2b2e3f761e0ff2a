"""Windows as long as the motion allows: the window half-width chosen per point and frame
(``stsdic run`` without ``--m``: ``track(..., window_length="auto")``, up to m = 6) against
classical DIC and the fixed windows, on renders with known motion and DIC Challenge sample 3.

Cases (noise sigma 2 grey levels on every image, the reference's too; subset 21, step 10,
every other option the default, the template made from the series included):

- ``stretch``: the relaxing stretch plus a decelerating drift of
  ``series_reference_floor.py`` (smooth, not linear in time), 31 images of 201 px;
- ``vibration A``: ``u = A (sin(2 pi t / 4 + ph) - sin(ph))``, ``v = -u / 2``, ``ph = (x +
  y) / 60`` (``time_model_bias.py``), 31 images of 201 px;
- ``steps``: load steps: a strain of 0.1 % added every 6 frames (held in between) plus a
  drift of 0.02 px a frame, 31 images of 201 px;
- ``linear``: a drift and a strain growing linearly in time (``u = 0.05 t + 0.0004 t (x -
  100)``, ``v = -0.03 t + 0.0002 t (y - 100)``), 31 images of 201 px;
- ``sample3``: DIC Challenge sample 3 (rigid 0.1 px a frame, 11 images; subset 21, step 16,
  ROI 40 40 471 471), where ``--data`` holds it.

Per run: RMS error of u, v against the truth over frames 1.. (and its ratio to classical DIC
against the single reference image), the random error (each frame's mean error taken out),
the RMS predicted u_std / v_std and their ratio, the RMS velocity error (rows with a
velocity) and its random part over the RMS of ut_std / vt_std, the share of trusted results
at each m, the wall time and its ratio to the ``--m 0`` run (one run each: noisy on a
shared machine).

    python scripts/validation/window_length.py [--cases stretch linear vibration0.03 ...]
        [--data ../shared/data] [--out docs/validation/window_length.md] [--seed 1]
        [--neighbourhoods 25 49 81]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.io.images import load_series
from torch_stsdic.movie import series_reference

sys.path.insert(0, str(Path(__file__).resolve().parent))
from series_reference_floor import errors  # noqa: E402
from series_reference_floor import motion as stretch  # noqa: E402
from time_model_bias import vibration  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: (label, m, window_length, series_reference)
RUNS = (("classical, single reference", 0, "fixed", False), ("classical", 0, "fixed", "auto"),
        ("m = 2", 2, "fixed", "auto"), ("chosen (m <= 6)", 6, "auto", "auto"))


def steps() -> synth.Motion:
    """Load steps: 0.1 % strain more every 6 frames, held between, plus a slow drift."""
    def fn(x, y, t):
        e = 0.001 * torch.floor(t / 6.0)
        return e * (x - 100) + 0.02 * t, -0.3 * e * (y - 100)
    return synth.Custom(fn)


def linear() -> synth.Motion:
    """A drift and a strain, both linear in time: the time model holds everywhere."""
    def fn(x, y, t):
        return 0.05 * t + 0.0004 * t * (x - 100), -0.03 * t + 0.0002 * t * (y - 100)
    return synth.Custom(fn)


def render(mot: synth.Motion, n: int = 31, size: int = 201, seed: int = 1):
    mv = synth.synthetic_movie((size, size), n - 1, mot, noise_sigma=2.0, seed=seed)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    return series, times


#: px per frame: a truth's velocity above this is its finite difference across a jump (a load
#: step: the velocity is not defined there); those rows are left out of the velocity columns
JUMP = 1.0


def _smooth_truth(truth: dict[str, torch.Tensor]) -> torch.Tensor:
    """(2, T-1, N) bool: frames 1.. where the truth's velocity is defined (no jump)."""
    t = torch.stack([truth["ut"][1:], truth["vt"][1:]])
    return (t.abs() < JUMP).all(0, keepdim=True).expand_as(t)


def velocity_rms(res, truth: dict[str, torch.Tensor]) -> float:
    """RMS of ut, vt minus the truth over frames 1.. where a velocity was measured (and the
    truth's is defined: :data:`JUMP`)."""
    e = torch.stack([res.ut.double()[1:] - truth["ut"][1:], res.vt.double()[1:] - truth["vt"][1:]])
    ok = torch.isfinite(e) & _smooth_truth(truth)
    return float(e[ok].pow(2).mean().sqrt()) if bool(ok.any()) else float("nan")


def velocity_honesty(res, truth: dict[str, torch.Tensor]) -> float:
    """The velocity's random error (each frame's mean error taken out) over the RMS of
    ut_std, vt_std, frames 1.. where a velocity was measured."""
    e = torch.stack([res.ut.double()[1:] - truth["ut"][1:], res.vt.double()[1:] - truth["vt"][1:]])
    p = torch.stack([res.std["ut"].double()[1:], res.std["vt"].double()[1:]])
    ok = torch.isfinite(e) & torch.isfinite(p) & _smooth_truth(truth)
    if not bool(ok.any()):
        return float("nan")
    e = torch.where(ok, e, torch.nan)
    e = e - torch.nanmean(e, -1, keepdim=True)
    return float(torch.nanmean(e.pow(2)).sqrt() / p[ok].pow(2).mean().sqrt())


def run_case(name: str, data: Path, runs=RUNS, save: Path | None = None, seed: int = 1
             ) -> list[dict]:
    kw: dict = {"step": 10}
    if name == "sample3":
        folder = data / "dic-challenge-sample3"
        if not folder.is_dir():
            print(f"skipped: {folder} not found")
            return []
        series = load_series(str(folder))
        n = len(series)
        t = torch.arange(n, dtype=torch.float64)[:, None]
        kw = {"step": 16, "roi": (40, 40, 471, 471)}

        def truth(res):
            z = (0.1 * t).expand_as(res.u)
            return {"u": z, "v": z, "ut": torch.full_like(z, 0.1), "vt": torch.full_like(z, 0.1)}
    else:
        mot = {"stretch": stretch, "steps": steps, "linear": linear}.get(name)
        mot = mot() if mot is not None else vibration(float(name.removeprefix("vibration")))
        series, times = render(mot, seed=seed)
        n = len(series)

        def truth(res):
            return synth.ground_truth(mot, res.points.double(), times)
    rows, base, t_cls = [], None, None
    for label, m, wl, ref in runs:
        m = min(m, (n - 1) // 2)
        t0 = time.perf_counter()
        res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21), progress=False,
                        series_reference=ref, window_length=wl, **kw)
        sec = time.perf_counter() - t0
        gt = truth(res)
        err = errors(res, gt)
        if save is not None:
            np.savez(save / f"{name}_{m}_{wl}_{ref}.npz", m=res.m.numpy(),
                     status=res.status.numpy(), points=res.points.numpy(),
                     **{k: getattr(res, k).double().numpy() for k in ("u", "v", "ut", "vt")},
                     **{f"{k}_std": res.std[k].double().numpy() for k in res.std},
                     **{f"true_{k}": gt[k].numpy() for k in ("u", "v", "ut", "vt")})
        base = err["rms"] if base is None else base
        if label == "classical":
            t_cls = sec
        mu, ok = res.m.numpy()[1:], res.status.numpy()[1:] <= 1
        share = " ".join(f"{k}:{(mu[ok] == k).mean():.2f}" for k in range(m + 1)
                         if (mu[ok] == k).any())
        rows.append({"case": name, "run": label, "rms": err["rms"], "ratio": err["rms"] / base,
                     "random": err["random"], "predicted": err["predicted"],
                     "vel": velocity_rms(res, gt) if m else float("nan"), "m": share,
                     "vel_honesty": velocity_honesty(res, gt) if m else float("nan"),
                     "s": sec, "time": sec / t_cls if t_cls else float("nan")})
        r = rows[-1]
        print(f"| {name} | {label} | {r['rms'] * 1e3:.2f} | {r['ratio']:.3f} | "
              f"{r['random'] * 1e3:.2f} | {r['predicted'] * 1e3:.2f} | "
              f"{r['random'] / r['predicted']:.2f} | {r['vel'] * 1e3:.2f} | "
              f"{r['vel_honesty']:.2f} | {share} | "
              f"{sec:.1f} | {r['time']:.2f} |", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+",
                    default=["sample3", "stretch", "steps", "vibration0.03", "vibration0.25"])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--runs", nargs="*", type=int, default=None,
                    help="indices into RUNS (default all)")
    ap.add_argument("--save", type=Path, default=None, help="folder for each run's fields")
    ap.add_argument("--seed", type=int, default=1, help="the renders' noise and speckle seed")
    ap.add_argument("--neighbourhoods", nargs="+", type=int, default=None,
                    help="the template's fits' neighbourhoods (series_reference.NEIGHBOURHOODS)")
    args = ap.parse_args(argv)
    if args.neighbourhoods:
        series_reference.NEIGHBOURHOODS = tuple(args.neighbourhoods)
    head = ["| case | run | RMS 1e-3 px | x classical | random 1e-3 px | predicted 1e-3 px | "
            "random / predicted | velocity RMS 1e-3 px/frame | velocity random / predicted | "
            "share of trusted results at m | s | time / classical |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    print("\n".join(head), flush=True)
    lines = list(head)
    for case in args.cases:
        runs = RUNS if args.runs is None else tuple(RUNS[i] for i in args.runs)
        for r in run_case(case, args.data, runs, args.save, args.seed):
            lines.append(f"| {r['case']} | {r['run']} | {r['rms'] * 1e3:.2f} | {r['ratio']:.3f} | "
                         f"{r['random'] * 1e3:.2f} | {r['predicted'] * 1e3:.2f} | "
                         f"{r['random'] / r['predicted']:.2f} | "
                         + ("-" if np.isnan(r["vel"]) else f"{r['vel'] * 1e3:.2f}") + " | "
                         + ("-" if np.isnan(r["vel_honesty"]) else f"{r['vel_honesty']:.2f}")
                         + f" | {r['m']} | {r['s']:.1f} | {r['time']:.2f} |")
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
