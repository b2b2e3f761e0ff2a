#!/usr/bin/env python
"""What the template's registering fits cost (``movie/series_reference.py``: the fits'
construction, ``_fit_choice``, and per round the guard band and ``_smooth``), on the warps a
real run hands them: ``stsdic run`` is run once with ``_fit_choice`` wrapped to keep its
inputs (the first round's warps against the reference image), then the fits' work is timed
``--repeats`` times, interleaved: today's neighbourhoods (``NEIGHBOURHOODS``) and fits over
the smallest neighbourhood only (``--neighbourhoods 25``'s: planes, quadratics and the cubic
over 25 POIs). Medians.

    python scripts/benchmarks/registration_fits.py [--repeats 7] \\
        [--out docs/bench/registration-fits-hourglass-cpu.json] [-- stsdic run's arguments]

Default: the muDIC hourglass with its documented region (1666 POIs, 21 sampled frames)."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
HOURGLASS = [str(REPO.parent / "shared/data/mudic-hourglass"), "--roi", "150", "20", "1120",
             "734", "--subset", "31", "--step", "20"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("run_args", nargs="*", help="stsdic run's arguments (after --)")
    args = ap.parse_args()
    from torch_stsdic.cli.app import main as cli_main
    from torch_stsdic.movie import series_reference as sr

    kept: dict = {}
    choose, make = sr._fit_choice, sr.RegistrationFits.make

    def keep_make(cls, pts, neighbours, subset_size):
        kept.setdefault("make", (pts, neighbours, subset_size))
        return make(pts, neighbours, subset_size)

    def keep_choice(reg, warps, ok, unit):
        kept.setdefault("choice", (warps, ok, unit))
        return choose(reg, warps, ok, unit)
    sr.RegistrationFits.make = classmethod(keep_make)
    sr._fit_choice = keep_choice
    run_args = args.run_args or HOURGLASS
    if not Path(run_args[0]).exists():
        print(f"registration_fits: no data at {run_args[0]}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        cli_main(["run", *run_args, "--out", str(Path(tmp) / "r.h5"), "--no-progress"])
    sr.RegistrationFits.make, sr._fit_choice = make, choose
    pts, neighbours, subset = kept["make"]
    warps, ok, unit = kept["choice"]
    default = sr.NEIGHBOURHOODS

    def once(sizes: tuple[int, ...]) -> list[float]:
        sr.NEIGHBOURHOODS = sizes
        try:
            t = [time.perf_counter()]
            reg = sr.RegistrationFits.make(pts, neighbours, subset)
            t.append(time.perf_counter())
            choice = sr._fit_choice(reg, warps, ok, unit)
            t.append(time.perf_counter())
            for _ in range(sr.DEFAULT_ITERATIONS):  # each round: the guard band, the maps
                reg.guard(choice, ok)
                sr._smooth(reg, warps, ok, choice)
            t.append(time.perf_counter())
        finally:
            sr.NEIGHBOURHOODS = default
        return [b - a for a, b in zip(t, t[1:])]
    cases = {f"neighbourhoods {' '.join(map(str, default))}": default,
             f"neighbourhoods {neighbours}": (neighbours,)}
    times: dict[str, list[list[float]]] = {k: [] for k in cases}
    for _ in range(max(1, args.repeats)):
        for name, sizes in cases.items():
            times[name].append(once(sizes))
    rec = {"points": int(pts.shape[0]), "frames": int(warps.shape[0]),
           "threads": torch.get_num_threads(), "repeats": args.repeats, "cases": {}}
    for name, ts in times.items():
        med = [statistics.median(x[i] for x in ts) for i in range(3)]
        rec["cases"][name] = {"fits_s": round(med[0], 3), "choice_s": round(med[1], 3),
                              "guard_and_maps_s": round(med[2], 3),
                              "total_s": round(statistics.median(sum(x) for x in ts), 3)}
    rec["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(rec, indent=1))
    if args.out:
        args.out.write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
