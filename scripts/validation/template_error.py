"""What the template's own error is made of (issue 47, round 4): on the ``stretch`` render of
``window_length.py`` (31 images of 201 px, subset 21, step 10) made noise-free and given noise
of its own (sigma 2 grey levels, or 0.05: "none") on the reference image only, on the other
frames only, on neither or on all, classical DIC against the template (m = 0; every other
option the default) and its error (u, v against the truth over frames 1..) split into each
point's mean over the frames ("constant": what the template puts into every row) and the
rest, over all points and over the inner ones (more than 40 px from the grid's edge).

The reference image's noise alone makes nearly all of the constant: the template is
registered to the reference configuration through the frames' warps measured against the
reference image, so that image's noise, seen through the local fits of the warps, is in
every row (``NEIGHBOURHOODS``: fits over larger neighbourhoods where the field allows).

    python scripts/validation/template_error.py [--neighbourhoods 25 49 81] [--noise-seed 7]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie import series_reference

sys.path.insert(0, str(Path(__file__).resolve().parent))
from series_reference_floor import motion as stretch  # noqa: E402
from stretch_limits import error, split  # noqa: E402

#: (name, noise sigma of the reference image, of the other frames)
CASES = (("none", 0.05, 0.05), ("reference only", 2.0, 0.05), ("frames only", 0.05, 2.0),
         ("all", 2.0, 2.0))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--neighbourhoods", nargs="+", type=int,
                    default=list(series_reference.NEIGHBOURHOODS))
    ap.add_argument("--noise-seed", type=int, default=7)
    args = ap.parse_args(argv)
    series_reference.NEIGHBOURHOODS = tuple(args.neighbourhoods)
    mot = stretch()
    mv = synth.synthetic_movie((201, 201), 30, mot, noise_sigma=0.0, seed=1)
    clean = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    gen = torch.Generator().manual_seed(args.noise_seed)
    unit = torch.randn(clean.shape, generator=gen, dtype=torch.float64)
    print(f"neighbourhoods {args.neighbourhoods}\n\n| noise on | RMS 1e-3 px | constant 1e-3 px"
          " | varying 1e-3 px | inner: constant | inner: varying |\n|---|---:|---:|---:|---:|---:|")
    for name, s_ref, s_frames in CASES:
        scale = torch.full((len(clean), 1, 1), s_frames, dtype=torch.float64)
        scale[0] = s_ref
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = sts.track(clean + unit * scale, config=sts.DICConfig(m=0, subset_size=21),
                            step=10, progress=False, series_reference=True)
        e = error(res, synth.ground_truth(mot, res.points.double(), times))
        p = res.points.double()
        inner = (p - p.amin(0) > 40).all(1) & (p.amax(0) - p > 40).all(1)
        c, v = split(e)
        ci, vi = split(e[..., inner])
        rms = float(torch.nanmean(e ** 2).sqrt())
        print(f"| {name} | {rms * 1e3:.2f} | {c * 1e3:.2f} | {v * 1e3:.2f} | {ci * 1e3:.2f} | "
              f"{vi * 1e3:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
