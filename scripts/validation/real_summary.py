#!/usr/bin/env python
"""The columns of docs/real.md's comparison table from result files.

    python scripts/validation/real_summary.py s12_m2.h5 s12_m2_nochecks.h5 [--reference 0]

Per file: usable point-frames (status <= MAX_ITER) of all frames and of the last frame; of
the usable ones, those measured with the run's full window (m) and those with a velocity;
the median predicted random error (u_std and v_std) over the usable point-frames but the
reference frame's (``--reference``, default 0). With two or more files also the rows whose
status or window differ from the first file's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from torch_stsdic.io import read_results  # noqa: E402


def summary(path: str, reference: int = 0) -> dict[str, float]:
    r = read_results(path)
    f = r.fields
    ok = f["status"] <= 1
    # the run's window (its config; the file's largest m where none is recorded: a run whose
    # points were all solved classically has m = 0 everywhere)
    m_run = int(r.config.get("m", np.nanmax(f["m"]) if f["m"].size else 0))
    not_ref = (r.frames != reference)[:, None] & ok
    err = np.concatenate([f["u_std"][not_ref], f["v_std"][not_ref]])
    return {
        "usable_all": float(ok.mean()), "usable_last": float(ok[-1].mean()),
        "full_window": float(((f["m"] == m_run) & ok).sum() / max(ok.sum(), 1)),
        "velocity": float((np.isfinite(f["ut"]) & ok).sum() / max(ok.sum(), 1)),
        "pred_error_px": float(np.nanmedian(err)) if err.size else float("nan"),
        "m": m_run,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--reference", type=int, default=0)
    args = ap.parse_args()
    print(f"{'file':<28}{'usable':>8}{'last':>8}{'full m':>8}{'vel.':>8}{'pred. err px':>14}")
    for p in args.files:
        s = summary(p, args.reference)
        print(f"{Path(p).name:<28}{s['usable_all']:>8.1%}{s['usable_last']:>8.1%}"
              f"{s['full_window']:>8.1%}{s['velocity']:>8.1%}{s['pred_error_px']:>14.3e}")
    if len(args.files) > 1:
        first = read_results(args.files[0]).fields
        for p in args.files[1:]:
            other = read_results(p).fields
            if other["status"].shape != first["status"].shape:
                print(f"{Path(p).name}: other points or frames than {Path(args.files[0]).name}"
                      " (not compared row by row)")
                continue
            st = int((first["status"] != other["status"]).sum())
            mm = int((first["m"] != other["m"]).sum())
            du = np.nanmax(np.abs(first["u"] - other["u"]))
            print(f"{Path(p).name}: status differs at {st}, window at {mm} of "
                  f"{first['status'].size} rows; max |du| {du:.2e} px")


if __name__ == "__main__":
    main()
