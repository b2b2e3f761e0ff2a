"""One reference mechanism: the template made from the series (the default) against the same
with its zero displacement from the trajectories (``refine_reference=True``: each point's
classical trajectory against the template fitted in time, its shrunk value at the reference
time subtracted with the template's gauge; until 2026-11-28 a mechanism of its own against
the single reference image), on DIC Challenge sample 3, the relaxing-stretch render of
``window_length.py`` (noise sigma 2 on every image, 31 frames) and ``linear41``, the render
of ``refined_reference.py`` (161 px, 41 frames, u = t/20, v = t/40, noise sigma 5 on every
image: where the old refined reference beat the template at m = 2), with m = 2 and the
windows chosen from the data (``window_length="auto"``).

Per run: RMS error of u, v against the truth over frames 1.. and its ratio to classical DIC
against the single reference image, the random error (each frame's mean error taken out),
the RMS predicted u_std / v_std and the ratio, the RMS velocity error.

    python scripts/validation/reference_mechanism.py [--cases sample3 stretch linear41]
        [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.io.images import load_series

sys.path.insert(0, str(Path(__file__).resolve().parent))
from series_reference_floor import errors  # noqa: E402
from series_reference_floor import motion as stretch  # noqa: E402
from window_length import render, velocity_rms  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: (label, m, window_length, keyword arguments)
RUNS = (("classical, single reference", 0, "fixed", {"series_reference": False}),
        ("template, m = 2", 2, "fixed", {}),
        ("trajectory gauge, m = 2", 2, "fixed", {"refine_reference": True}),
        ("template, chosen", 6, "auto", {}),
        ("trajectory gauge, chosen", 6, "auto", {"refine_reference": True}))


def case(name: str, data: Path):
    """(series, times or None, keyword arguments, truth(res))."""
    if name == "sample3":
        series = load_series(str(data / "dic-challenge-sample3"))
        t = torch.arange(len(series), dtype=torch.float64)[:, None]

        def truth(res):
            z = (0.1 * t).expand_as(res.u)
            return {"u": z, "v": z, "ut": torch.full_like(z, 0.1), "vt": torch.full_like(z, 0.1)}
        return series, {"step": 16, "roi": (40, 40, 471, 471)}, truth
    if name == "linear41":
        mv = synth.synthetic_movie((161, 161), 40, synth.Translation(ut=1 / 20, vt=1 / 40),
                                   noise_sigma=5.0, seed=1)
        series = torch.cat([mv.ref[None], mv.frames]).double()
        t = torch.arange(len(series), dtype=torch.float64)[:, None]

        def truth(res):
            u, v = (t / 20).expand_as(res.u), (t / 40).expand_as(res.u)
            return {"u": u, "v": v, "ut": torch.full_like(u, 1 / 20),
                    "vt": torch.full_like(u, 1 / 40)}
        return series, {"step": 10}, truth
    mot = stretch()
    series, times = render(mot)

    def truth(res):
        return synth.ground_truth(mot, res.points.double(), times)
    return series, {"step": 10}, truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["sample3", "stretch", "linear41"])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--runs", nargs="*", type=int, default=None,
                    help="indices into RUNS (default all; 0, the baseline, always runs)")
    args = ap.parse_args(argv)
    runs = RUNS if args.runs is None else tuple(RUNS[i] for i in sorted({0, *args.runs}))
    print("| case | run | RMS 1e-3 px | x classical | random 1e-3 px | predicted 1e-3 px | "
          "random / predicted | velocity RMS 1e-3 px/frame | s |\n"
          "|---|---|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    for name in args.cases:
        if name == "sample3" and not (args.data / "dic-challenge-sample3").is_dir():
            print(f"skipped {name}: no data")
            continue
        series, kw, truth = case(name, args.data)
        base = None
        for label, m, wl, extra in runs:
            m = min(m, (len(series) - 1) // 2)
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21),
                                progress=False, window_length=wl, **kw, **extra)
            sec = time.perf_counter() - t0
            gt = truth(res)
            err = errors(res, gt)
            base = err["rms"] if base is None else base
            vel = velocity_rms(res, gt) if m else float("nan")
            print(f"| {name} | {label} | {err['rms'] * 1e3:.2f} | {err['rms'] / base:.3f} | "
                  f"{err['random'] * 1e3:.2f} | {err['predicted'] * 1e3:.2f} | "
                  f"{err['random'] / err['predicted']:.2f} | "
                  + ("-" if vel != vel else f"{vel * 1e3:.2f}") + f" | {sec:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
