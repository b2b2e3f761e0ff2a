"""DIC Challenge 1.0 sample 3 (11 images, rigid shift 0.1 px a frame in x and y, noise on
every image): classical DIC and STS-DIC m=2 against the single reference image and against
the reference made from the series (the default), as ``stsdic run
../shared/data/dic-challenge-sample3 --subset 21 --step 16 --roi 40 40 471 471 --m M``
runs them.

Per run: RMS of measured - truth over all points and frames 1..10 (u and v), its ratio to
classical DIC against image 000, the random error (the part every point shares in a frame
taken out), the RMS of the predicted u_std / v_std, their ratio, and the wall time (one
run; noisy on a shared machine). Skips with a message where ``../shared/data`` is absent.

    python scripts/validation/sample3_series.py [--data ../shared/data] [--out F.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic.io.images import load_series

sys.path.insert(0, str(Path(__file__).resolve().parent))
from series_reference_floor import errors  # noqa: E402  (the same statistics)

ROOT = Path(__file__).resolve().parents[2]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    folder = args.data / "dic-challenge-sample3"
    if not folder.is_dir():
        print(f"skipped: {folder} not found (the DIC Challenge images are not in the "
              "repository)")
        return 0
    series = load_series(str(folder))
    truth = 0.1 * torch.arange(len(series), dtype=torch.float64)[:, None]
    lines = ["| m | reference | RMS 1e-3 px | x classical | random 1e-3 px | predicted 1e-3 px "
             "| random / predicted | s |", "|---:|---|---:|---:|---:|---:|---:|---:|"]
    base = None
    for m in (0, 2):
        for ref in ("single", "series"):
            t0 = time.perf_counter()
            res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21), step=16,
                            roi=(40, 40, 471, 471), progress=False,
                            series_reference="auto" if ref == "series" else False)
            sec = time.perf_counter() - t0
            err = errors(res, {"u": truth.expand_as(res.u), "v": truth.expand_as(res.v)})
            rms, rand, p = err["rms"], err["random"], err["predicted"]
            base = rms if base is None else base
            lines.append(f"| {m} | {ref} | {rms * 1e3:.2f} | {rms / base:.3f} | "
                         f"{rand * 1e3:.2f} | {p * 1e3:.2f} | {rand / p:.2f} | {sec:.1f} |")
            print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
