"""``stsdic demo``: classical DIC vs STS-DIC on the paper's synthetic movie.

The experiment is :func:`torch_stsdic.demo.run_demo`; this module maps the options onto
it and prints its table.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict
from pathlib import Path

from torch_stsdic.cli import options
from torch_stsdic.cli.common import check_device, check_folder
from torch_stsdic.cli.errors import UsageError

NAME = "demo"
HELP = "classical DIC vs STS-DIC on the paper's synthetic movie (start here)"
DEMO_DIR = "stsdic-demo"
#: how long ``stsdic demo`` takes, quoted by the README, docs/cli.md and ``stsdic --help``
#: (scripts/regenerate_docs.py --check verifies that they all quote this text)
DEMO_TIME = "under 10 s on 2 CPU cores"

DESCRIPTION = """\
Reproduce the paper's simulated test: a 301 x 301 px speckle movie (reference + 9
frames) translating by u = t/20 px with Gaussian noise sigma 5 on every image, measured
with classical DIC (m = 0) and with STS-DIC (m = 2, 5 frames per solve), both against
the reference image (which is not part of any STS window). Prints the RMS errors of u, v
and of the velocity ut against the exact motion, the run times and throughputs (POI/s),
and the error ratios; saves figures and the numbers (demo.json) in DIR:
  error_per_frame.png  RMS error of u in every frame, per method
  fields.png           error maps of u and ut at the middle frame, classical DIC vs
                       STS-DIC on shared colour scales centred on 0
  history.png          error of u and ut against time per method: mean over the points
                       and +-1 std band
"""

EPILOG = f"""\
examples:
  stsdic demo                         # {DEMO_TIME}; writes ./stsdic-demo/*.png
  stsdic demo --noise 10 --m 3 --out demo10
  stsdic demo --quick                 # small and fast (a smoke test)
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic demo``."""
    opt = options.add_option
    opt(p, "--out", "-o", default=DEMO_DIR, metavar="DIR",
        help="directory for plots and numbers", shown="./%(default)s")  # fmt: skip
    opt(p, "--size", type=options.int_min(41), default=None, metavar="PX",
        help="image size in px", shown="301; 101 with --quick")  # fmt: skip
    opt(p, "--frames", type=options.int_min(1), default=None, metavar="N",
        help="deformed frames", shown="9; 7 with --quick")  # fmt: skip
    options.add_speckle(p)
    options.add_dic(p, min_m=1)
    options.add_step(p, default=None, shown="20; 25 with --quick")
    p.add_argument(
        "--still-frames", type=options.int_min(0), default=None, metavar="K",
        help="also run with the reference = mean of K noisy still frames taken before the "
        "motion (0: skip; default: 8; 0 with --quick). The reference's noise is shared by "
        "every frame, so no temporal window averages it away; averaging still frames does",
    )  # fmt: skip
    p.add_argument("--quick", action="store_true", help="small movie, few points: a smoke test")
    p.add_argument("--no-plots", action="store_true", help="print the table only")
    options.add_compute(p)


def execute(args: argparse.Namespace) -> int:
    """``stsdic demo``: run the experiment, print its table, say where the files are."""
    from torch_stsdic.demo import DemoSettings, check_settings, run_demo

    device = check_device(args.device)
    settings = DemoSettings.create(
        args.quick, size=args.size, frames=args.frames, noise=args.noise, m=args.m,
        subset=args.subset, step=args.step, formulation=args.formulation,
        still_frames=args.still_frames, seed=args.seed, device=str(device),
    )  # fmt: skip
    try:
        check_settings(settings, name=lambda field: "--" + field.replace("_", "-"))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = None if args.no_plots else args.out
    if out is not None:
        check_folder(Path(out), f"--out {out}")
    result = run_demo(out, progress=not args.no_progress, log=_say, **asdict(settings))
    print(result.table())
    if result.files:
        names = " ".join(p.name for p in result.files)
        print(f"plots and numbers in {result.files[0].parent}/: {names}")
    return 0


def _say(line: str) -> None:
    print(line, flush=True)
