"""Options shared by several sub-commands, each defined once, and the argument types.

Every ``add_*`` function adds a group of options to a parser or argument group; a
sub-command calls the ones it needs. The argument types name the rule a value breaks, and
argparse puts the option's name in front (``argument --subset: must be an odd ...``).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from torch_stsdic.core.config import CRITERIA, FORMULATION_HELP, FORMULATIONS, INITIAL_GUESSES

#: an ArgumentParser or one of its argument groups
Group = Any

# ----------------------------------------------------------------------------------------
# argument types
# ----------------------------------------------------------------------------------------


def _checked(
    cast: Callable[[str], Any], expected: str, test: Callable[[Any], bool], rule: str
) -> Callable[[str], Any]:
    """Argument type: ``cast`` the text, then require ``test`` (else 'rule, got TEXT')."""

    def conv(s: str) -> Any:
        try:
            v = cast(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {s!r}") from None
        if not test(v):
            raise argparse.ArgumentTypeError(f"{rule}, got {s}")
        return v

    return conv


def odd_int(lo: int) -> Callable[[str], int]:
    """Argument type: an odd integer >= ``lo``."""
    return _checked(int, "an odd integer", lambda v: v >= lo and v % 2 == 1,
                    f"must be an odd integer >= {lo}")  # fmt: skip


def int_min(lo: int) -> Callable[[str], int]:
    """Argument type: an integer >= ``lo``."""
    return _checked(int, "an integer", lambda v: v >= lo, f"must be >= {lo}")


float_pos = _checked(float, "a number", lambda v: math.isfinite(v) and v > 0,
                     "must be a finite number > 0")  # fmt: skip
float_nonneg = _checked(float, "a number", lambda v: math.isfinite(v) and v >= 0,
                        "must be a finite number >= 0")  # fmt: skip
unit_open = _checked(float, "a number", lambda v: 0.0 < v < 1.0,
                     "must be a ZNCC threshold in (0, 1)")  # fmt: skip
finite = _checked(float, "a number", math.isfinite, "must be finite")

# ----------------------------------------------------------------------------------------
# declaring an option
# ----------------------------------------------------------------------------------------


def add_option(g: Group, *flags: str, help: str, shown: str = "%(default)s", **kw: Any) -> None:
    """Add the option ``flags`` (argparse keywords ``kw``) to ``g``; its help ends with
    ``(default: SHOWN)``, so every command says its defaults the same way.

    ``shown`` is the value argparse fills in, or words where the default is None or depends
    on other options ('whole image', '20; 25 with --quick').
    """
    g.add_argument(*flags, help=f"{help} (default: {shown})", **kw)


# ----------------------------------------------------------------------------------------
# option groups
# ----------------------------------------------------------------------------------------


def add_debug(p: Group) -> None:
    """``--debug`` (every sub-command; also accepted before the sub-command)."""
    p.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show the Python traceback of an error",
    )


def add_threads(g: Group) -> None:
    """``--threads N``: torch's CPU threads."""
    add_option(g, "--threads", type=int_min(1), default=None, metavar="N",
               help="CPU threads for torch", shown="torch's choice; use 1 on a busy machine, "
               "where competing threads slow torch down badly")  # fmt: skip


def add_compute(g: Group) -> None:
    """``--device``, ``--no-progress``, ``--threads``: where and how a tracking run computes."""
    add_option(g, "--device", default="cpu", metavar="DEV",
               help="torch device: cpu, cuda, cuda:1, mps ...")  # fmt: skip
    g.add_argument("--no-progress", action="store_true", help="no progress bar (it goes to stderr)")
    add_threads(g)


def add_dic(g: Group, *, min_m: int = 0, auto_m: bool = False) -> None:
    """``--subset``, ``--m``, ``--formulation``: the settings every (STS-)DIC run has
    (``auto_m``: without ``--m`` each point's window is chosen from its motion)."""
    add_option(g, "--subset", type=odd_int(5), default=21, metavar="PX",
               help="subset width in px, odd")  # fmt: skip
    classical = "; 0 = classical DIC" if min_m == 0 else ""
    if auto_m:
        add_option(g, "--m", type=int_min(min_m), default=None,
                   help=f"half window: each solve uses 2m+1 frames{classical}; without it, "
                   "each point and frame gets the longest window its measured motion "
                   "supports, up to m = 6", shown="chosen per point and frame")  # fmt: skip
    else:
        add_option(g, "--m", type=int_min(min_m), default=2,
                   help=f"half window: each solve uses 2m+1 frames{classical}")  # fmt: skip
    add_option(g, "--formulation", choices=FORMULATIONS, default="auto", help=FORMULATION_HELP)


def add_step(g: Group, default: int | None = 10, shown: str = "%(default)s") -> None:
    """``--step PX``: grid spacing of the points of interest (``shown``: as in add_option)."""
    add_option(g, "--step", type=int_min(1), default=default, metavar="PX",
               help="grid spacing in px", shown=shown)  # fmt: skip


#: the choices of the 'solver' group: option, choices (the first is the default), help
SOLVER_CHOICES: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("--criterion", CRITERIA, "znssd: insensitive to brightness/contrast changes; ssd: plain "
     "sum of squared differences"),
    ("--shape", ("affine", "quadratic"), "spatial shape function (both linear in time)"),
    ("--window", ("square", "circular", "gaussian"), "subset window"),
    ("--interpolation", ("cubic", "quintic"), "B-spline interpolation order"),
)  # fmt: skip


def add_solver(p: argparse.ArgumentParser) -> None:
    """The 'solver' group: subset, window, formulation, criterion, shape ... batch size."""
    g = p.add_argument_group("solver")
    add_dic(g, auto_m=True)
    for flag, choices, text in SOLVER_CHOICES:
        add_option(g, flag, choices=choices, default=choices[0], help=text)
    _add_initial_guess(g)
    add_option(g, "--tol", type=float_pos, default=1e-4, metavar="PX", help="convergence: "
               "largest subset-pixel motion of the last increment, px")  # fmt: skip
    add_option(g, "--max-iter", type=int_min(1), default=50, metavar="N",
               help="Gauss-Newton iterations per stage")  # fmt: skip
    add_option(g, "--batch-points", type=int_min(1), default=None, metavar="N",
               help="points solved together", shown="from --memory-mb")  # fmt: skip
    add_option(g, "--memory-mb", type=float_pos, default=None, metavar="MB",
               help="working-memory budget per batch in MiB, kept to on every device (a GPU "
                    "shared with other work)",
               shown="256; a GPU takes at least 2048, within a tenth of its memory")  # fmt: skip


def _add_initial_guess(g: Group) -> None:
    """``--search-radius``, ``--initial-guess``, ``--seed-spacing``."""
    add_option(g, "--search-radius", type=int_min(0), default=10, metavar="PX",
               help="initial-guess search radius (FFT cross-correlation) in px; make it larger "
               "than the largest motion between neighbouring output frames")  # fmt: skip
    add_option(g, "--initial-guess", choices=INITIAL_GUESSES, default="auto",
               help="where POIs without a previous result start: 'fft' = FFT cross-correlation "
               "at every POI; 'seeded' = FFT at one seed POI per cell of --seed-spacing px, the "
               "others start from their seed's solution (FFT again where that fails); 'auto' = "
               "seeded for dense POIs")  # fmt: skip
    add_option(g, "--seed-spacing", type=float_pos, default=None, metavar="PX",
               help="cell width for --initial-guess seeded, px",
               shown="the subset size")  # fmt: skip


def add_points(p: argparse.ArgumentParser) -> None:
    """The 'points of interest' group: a grid (--step, --roi, --mask) or --points."""
    g = p.add_argument_group("points of interest")
    add_step(g)
    add_option(g, "--roi", type=int, nargs=4, default=None, metavar=("X0", "Y0", "X1", "Y1"),
               help="region of interest in px: columns X0..X1, rows Y0..Y1",
               shown="whole image")  # fmt: skip
    g.add_argument("--mask", default=None, metavar="FILE", help="image (or .npy) of the "
                   "image size; points on zero pixels are skipped")  # fmt: skip
    g.add_argument("--points", default=None, metavar="FILE.csv",
                   help="explicit points: CSV with columns x, y in px (header optional); "
                   "replaces the grid")  # fmt: skip


def add_speckle(g: Group) -> None:
    """``--noise``, ``--seed``: the synthetic speckle movie's noise and random seed."""
    add_option(g, "--noise", type=float_nonneg, default=5.0, metavar="SIGMA",
               help="Gaussian noise std in 8-bit grey levels")  # fmt: skip
    add_option(g, "--seed", type=int, default=0, help="speckle and noise seed")


def add_calibration(g: Group) -> None:
    """``--scale``, ``--unit``, ``--time-unit``: the calibration a run records (values stay
    in px; exports and plots convert)."""
    add_option(g, "--scale", type=float_pos, default=None, metavar="UNIT_PER_PX",
               help="length of one pixel in --unit, e.g. 0.02 (mm per px); recorded in the "
               "result file, whose values stay in px; exports and plots are then in --unit",
               shown="none, everything in px")  # fmt: skip
    g.add_argument("--unit", default=None, metavar="NAME",
                   help="length unit of --scale, e.g. mm or um (required with --scale)")
    add_option(g, "--time-unit", default=None, metavar="NAME",
               help="unit of the times, e.g. s or ms",
               shown="frame; 'time unit' with --timestamps")  # fmt: skip


def check_calibration(args: argparse.Namespace) -> dict[str, Any]:
    """The calibration of ``--scale``, ``--unit``, ``--time-unit`` (UsageError naming them)."""
    from torch_stsdic.cli.errors import UsageError
    from torch_stsdic.io.units import check_calibration as check

    try:
        return check(args.scale, args.unit, args.time_unit)
    except ValueError as exc:
        msg = str(exc)
        for name in ("time_unit", "scale", "unit"):
            msg = msg.replace(f"{name}:", f"--{name.replace('_', '-')}:", 1)
        raise UsageError(msg.replace("unit='mm'", "--unit mm")) from None


def add_result(p: argparse.ArgumentParser) -> None:
    """The positional ``RESULT.h5``: a file written by ``stsdic run``."""
    p.add_argument("result", metavar="RESULT.h5", help="result file written by 'stsdic run'")
