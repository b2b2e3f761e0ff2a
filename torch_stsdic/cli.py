"""The ``stsdic`` command line: ``run``, ``export``, ``plot``, ``synth`` and ``demo``.

Every sub-command is a function ``cmd_<name>(args) -> int``; :func:`main` parses the
arguments, runs one of them and turns every error into one line on stderr
(``stsdic: error: ...``) and a non-zero exit code: 2 for usage errors (a bad option value,
an option that does not fit the images), 1 for everything else (missing or unreadable files,
failed runs). ``--debug`` shows the Python traceback instead.

Heavy modules (torch, the solver, matplotlib) are imported inside the commands, so that
``stsdic --help`` answers at once.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
import traceback
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .config import FORMULATIONS

__all__ = ["main", "build_parser", "UsageError", "CommandError"]

PROG = "stsdic"
MOTIONS = ("translation", "strain", "sinusoidal", "quadratic", "jump")
DEMO_DIR = "stsdic-demo"


class UsageError(Exception):
    """A bad command line (option value, option that does not fit the input): exit code 2."""


class CommandError(Exception):
    """A command that cannot be carried out (files, data): exit code 1."""


# ----------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------


def _err(msg: str) -> None:
    print(f"{PROG}: error: {msg}", file=sys.stderr, flush=True)


def _one_line(exc: BaseException) -> str:
    """The exception's message on one line (KeyError without its quotes)."""
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        msg = exc.args[0]
    else:
        msg = str(exc)
    msg = " ".join(part.strip() for part in msg.splitlines() if part.strip())
    return msg or type(exc).__name__


@contextlib.contextmanager
def _warnings_on_stderr() -> Iterator[None]:
    """Show Python warnings as single ``stsdic: warning: ...`` lines."""

    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        text = " ".join(str(message).split())
        print(f"{PROG}: warning: {text}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show
        yield


def _np(a: Any) -> np.ndarray:
    """numpy view of a tensor or array-like (detached, on the CPU)."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def _fmt_time(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    m, s = divmod(seconds, 60)
    if m < 60:
        return f"{int(m)} min {s:.0f} s"
    h, m = divmod(m, 60)
    return f"{int(h)} h {int(m)} min"


# ----------------------------------------------------------------------------------------
# argument types (each names the option in its error message)
# ----------------------------------------------------------------------------------------


def _odd_int(lo: int) -> Any:
    def conv(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an odd integer, got {s!r}") from None
        if v < lo or v % 2 == 0:
            raise argparse.ArgumentTypeError(f"must be an odd integer >= {lo}, got {v}")
        return v

    return conv


def _int_min(lo: int) -> Any:
    def conv(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        return v

    return conv


def _float_pos(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {s}")
    return v


def _float_nonneg(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {s}")
    return v


def _unit_open(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"must be a ZNCC threshold in (0, 1), got {s}")
    return v


def _finite(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {s}")
    return v


# ----------------------------------------------------------------------------------------
# the parser
# ----------------------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line (raised as UsageError, printed by main)."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        raise UsageError(f"{message} (see '{self.prog} --help')")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=32, width=100)


MAIN_DESCRIPTION = """\
STS-DIC: short-time-series digital image correlation (Wang & Ma) in PyTorch.

Each solve matches a subset of the reference image against 2m+1 consecutive frames at
once, with a displacement that is linear in time (u + ut*dt, v + vt*dt): the frames'
noise is averaged, and the velocity comes out directly. m = 0 is classical subset DIC.

commands:
  run      measure displacement, velocity and strain in an image series -> HDF5
  export   write a result file as CSV files, one per frame
  plot     draw fields over the image and time histories as PNG files
  synth    write a synthetic speckle movie with exactly known motion
  demo     classical DIC vs STS-DIC on the paper's synthetic movie (start here)
"""

MAIN_EPILOG = """\
examples:
  stsdic demo                                   # 1-minute comparison, plots in ./stsdic-demo
  stsdic synth --out movie --motion strain      # synthetic test movie + ground truth
  stsdic run movie/movie.tif --m 2 --step 10 --out result.h5
  stsdic export result.h5 --out csv/
  stsdic plot result.h5 --frame last --out plots/

Run 'stsdic COMMAND --help' for the options of a command. Coordinates are pixels with
x = column (right), y = row (down), 0-based; times are frame numbers unless --timestamps.
"""

RUN_DESCRIPTION = """\
Track points through an image series with (STS-)DIC and write the results to an HDF5
file as the run goes (a killed run keeps every finished frame; --resume continues it).

INPUT is a multi-page TIFF, a directory of images (natural order: img2 before img10),
a glob pattern ('frames/*.tif', quoted) or several image files in order. 8/16-bit and
float images are read in their native grey scale; colour is converted to grey.

Points: a regular grid every --step px inside --roi (default: the whole image, at least
half a subset from the border), minus the pixels outside --mask; or the points listed
in --points. For every output frame the window of 2m+1 frames around it is solved
(shifted at the ends of the series). At the end the strains exx, eyy, exy (and their
rates) are computed by local plane fits and added to the file.

The file holds points (N, 2), frames (F,), times (F,), and (F, N) datasets u, v [px],
ut, vt [px per time unit], zncc, status (0 converged, 1 max-iter, 2 diverged,
3 outside, 4 low texture, 5 not computed), exx, eyy, exy [-]; see 'stsdic export'.
"""

RUN_EPILOG = """\
examples:
  stsdic run movie.tif --out result.h5                      # defaults: subset 21, m 2, step 10
  stsdic run frames/ --m 0 --out classical.h5               # classical DIC, frame by frame
  stsdic run 'img_*.tif' --roi 50 50 450 300 --step 5 --out r.h5
  stsdic run movie.tif --reference 0:5 --frames 5: --out r.h5   # averaged reference
  stsdic run movie.tif --points poi.csv --timestamps times.csv --out r.h5
  stsdic run movie.tif --out r.h5 --resume                  # continue a killed run
  stsdic run movie.tif --device cuda --dtype float32 --out r.h5
"""

EXPORT_DESCRIPTION = """\
Write the frames of a result file as CSV files, one per frame, named
<result stem>_frame<NNNNN>.csv in DIR (or give a pattern with {frame}, e.g.
'csv/f{frame:04d}.csv'). Columns: x, y, u, v, ut, vt, exx, eyy, exy, zncc, status, then
any other stored field; NaN (failed points) are empty cells. A first comment line
'# torch_stsdic results ... frame=F time=T' precedes the header.
"""

EXPORT_EPILOG = """\
examples:
  stsdic export result.h5 --out csv/
  stsdic export result.h5 --out csv/ --frames 0:10
  stsdic export result.h5 --out 'csv/f{frame:04d}.csv' --frames -1
"""

PLOT_DESCRIPTION = """\
Draw a result file as PNG files in DIR:
  fields_frameNNNNN.png    maps of the chosen fields at one frame over the image
  history_mean.png         time history of u, v averaged over the valid points
  history_xX_yY.png        ... or of the point nearest to (X, Y) with --point
  velocity_history_*.png   the same for ut, vt (STS-DIC results, m >= 1)
  strain_history_*.png     the same for exx, eyy, exy (when the file has strains)
Displacements use a sequential colour map, strains a diverging one centred on 0;
failed points are transparent.
"""

PLOT_EPILOG = """\
examples:
  stsdic plot result.h5 --out plots/                        # last frame, mean history
  stsdic plot result.h5 --frame 5 --fields u,exx --out plots/
  stsdic plot result.h5 --point 150 150 --image movie.tif --out plots/
"""

SYNTH_DESCRIPTION = """\
Write a synthetic speckle movie with exactly known motion (analytic rendering with
pixel-area integration; no interpolation), and its ground truth.

Frame 0 is the reference (t = 0, no motion); frames 1..N are at t = 1..N. Gaussian
noise (sigma in 8-bit grey levels) is added to every frame, then the images are
quantised to --bits (16 bits: the 8-bit scale times 257; 0: float32, no quantisation).

Files in DIR: movie.tif (multi-page TIFF) or frame_00000.tif ... (--layout files);
times.csv (frame, time); truth.csv (frame, time, x, y, u, v, ut, vt, dudx, dudy, dvdx,
dvdy at a grid of points every --truth-step px); motion.json (the motion and all settings).

Motions (parameters; t in frames, lengths in px):
  translation  u = u0 + ut*t, v = v0 + vt*t                    (--u0 --v0 --ut --vt)
  strain       homogeneous strain about the image centre, growing linearly in time:
               strain(t) = (exx, eyy, exy) * t, rotation omega*t (--exx --eyy --exy --omega)
  sinusoidal   u = rate*t * amplitude_u * sin(2 pi q / wavelength), q = x or y, same for v
               (--amplitude-u --amplitude-v --wavelength --axis --rate)
  quadratic    u = au*t + bu*t^2, v = av*t + bv*t^2 (accelerating)  (--au --bu --av --bv)
  jump         material right of x = x0 jumps by (du, dv) at t >= t_jump (a crack)
               (--x0 --du --dv --t-jump)
"""

SYNTH_EPILOG = """\
examples:
  stsdic synth --out movie                                 # the paper's movie: u = t/20, noise 5
  stsdic synth --out movie --motion strain --exx 0.002 --noise 2 --bits 16
  stsdic synth --out movie --motion jump --x0 150 --du 0.5 --layout files
  stsdic synth --out small --size 81 --frames 8 --noise 0 --seed 3
"""

DEMO_DESCRIPTION = """\
Reproduce the paper's simulated test: a 301 x 301 px speckle movie (reference + 9
frames) translating by u = t/20 px with Gaussian noise sigma 5 on every image, measured
with classical DIC (m = 0) and with STS-DIC (m = 2, 5 frames per solve), both against
the reference image (which is not part of any STS window). Prints the RMS errors of u, v
and of the velocity ut against the exact motion, the run times and throughputs (POI/s),
and the error ratio; saves plots (error per frame, fields, histories) and the numbers
(demo.json) in DIR.
"""

DEMO_EPILOG = """\
examples:
  stsdic demo                         # writes ./stsdic-demo/*.png
  stsdic demo --noise 10 --m 3 --out demo10
  stsdic demo --quick                 # small and fast (a smoke test)
"""


def _add_threads(p: argparse.ArgumentParser | Any) -> None:
    p.add_argument(
        "--threads",
        type=_int_min(1),
        default=None,
        metavar="N",
        help="CPU threads for torch (default: torch's choice; use 1 on a busy machine, "
        "where competing threads slow torch down badly)",
    )


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show the Python traceback of an error",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``stsdic`` argument parser (all sub-commands)."""
    parser = _Parser(
        prog=PROG,
        description=MAIN_DESCRIPTION,
        epilog=MAIN_EPILOG,
        formatter_class=_Formatter,
    )
    try:
        from importlib.metadata import version

        ver = version("torch_stsdic")
    except Exception:
        ver = "unknown"
    parser.add_argument("--version", action="version", version=f"%(prog)s {ver}")
    parser.add_argument(
        "--debug", action="store_true", default=False, help="show the Python traceback of an error"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    # -- run ------------------------------------------------------------------------------
    p = sub.add_parser(
        "run",
        help="measure displacement, velocity and strain -> HDF5",
        description=RUN_DESCRIPTION,
        epilog=RUN_EPILOG,
        formatter_class=_Formatter,
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image series (see above)")
    p.add_argument(
        "--out", "-o", required=True, metavar="FILE.h5", help="result file (HDF5), required"
    )
    g = p.add_argument_group("frames and reference")
    g.add_argument(
        "--reference",
        default="0",
        metavar="SPEC",
        help="reference frame, or several frames averaged into the reference, e.g. 0:5 "
        "(frame numbers of the series, 0-based; default: %(default)s)",
    )
    g.add_argument(
        "--frames",
        default=None,
        metavar="SPEC",
        help="output frames: an index, slices and lists such as 5, -1, 10:100:2, 0:5,9, all "
        "(default: every frame)",
    )
    g.add_argument(
        "--timestamps",
        default=None,
        metavar="FILE",
        help="frame times, one per frame (text/CSV: one number a line, or a column named "
        "'time'); velocities are then per this time unit (default: 0, 1, 2, ...)",
    )
    g.add_argument(
        "--reference-update",
        type=_unit_open,
        default=None,
        metavar="THRESH",
        help="take a new reference (incremental DIC) when the mean ZNCC falls below THRESH, "
        "e.g. 0.9 (default: never, one fixed reference)",
    )
    g = p.add_argument_group("points of interest")
    g.add_argument(
        "--step", type=_int_min(1), default=10, metavar="PX",
        help="grid spacing in px (default: %(default)s)",
    )  # fmt: skip
    g.add_argument(
        "--roi",
        type=int,
        nargs=4,
        default=None,
        metavar=("X0", "Y0", "X1", "Y1"),
        help="region of interest in px: columns X0..X1, rows Y0..Y1 (default: whole image)",
    )
    g.add_argument(
        "--mask",
        default=None,
        metavar="FILE",
        help="image (or .npy) of the image size; points on zero pixels are skipped",
    )
    g.add_argument(
        "--points",
        default=None,
        metavar="FILE.csv",
        help="explicit points: CSV with columns x, y in px (header optional); replaces the grid",
    )
    g = p.add_argument_group("solver")
    g.add_argument(
        "--subset", type=_odd_int(5), default=21, metavar="PX",
        help="subset width in px, odd (default: %(default)s)",
    )  # fmt: skip
    g.add_argument(
        "--m",
        type=_int_min(0),
        default=2,
        help="half window: each solve uses 2m+1 frames; 0 = classical DIC (default: %(default)s)",
    )
    g.add_argument(
        "--formulation",
        choices=FORMULATIONS,
        default="auto",
        help="joint: sum of per-frame residuals; average: the paper's averaged image; auto: "
        "joint, then refined on the average (default: %(default)s)",
    )
    g.add_argument(
        "--criterion",
        choices=("znssd", "ssd"),
        default="znssd",
        help="znssd: insensitive to brightness/contrast changes; ssd: plain sum of squared "
        "differences (default: %(default)s)",
    )
    g.add_argument(
        "--shape",
        choices=("affine", "quadratic"),
        default="affine",
        help="spatial shape function (both linear in time) (default: %(default)s)",
    )
    g.add_argument(
        "--window",
        choices=("square", "circular", "gaussian"),
        default="square",
        help="subset window (default: %(default)s)",
    )
    g.add_argument(
        "--interpolation",
        choices=("cubic", "quintic"),
        default="cubic",
        help="B-spline interpolation order (default: %(default)s)",
    )
    g.add_argument(
        "--search-radius",
        type=_int_min(0),
        default=10,
        metavar="PX",
        help="initial-guess search radius (FFT cross-correlation) in px; make it larger than "
        "the largest motion between neighbouring output frames (default: %(default)s)",
    )
    g.add_argument(
        "--initial-guess",
        choices=("auto", "fft", "seeded"),
        default="auto",
        help="where POIs without a previous result start: 'fft' = FFT cross-correlation at "
        "every POI; 'seeded' = FFT at one seed POI per cell of --seed-spacing px, the others "
        "start from their seed's solution (FFT again where that fails); 'auto' = seeded for "
        "dense POIs (default: %(default)s)",
    )
    g.add_argument(
        "--seed-spacing",
        type=_float_pos,
        default=None,
        metavar="PX",
        help="cell width for --initial-guess seeded, px (default: the subset size)",
    )
    g.add_argument(
        "--tol",
        type=_float_pos,
        default=1e-4,
        metavar="PX",
        help="convergence: largest subset-pixel motion of the last increment, px "
        "(default: %(default)s)",
    )
    g.add_argument(
        "--max-iter",
        type=_int_min(1),
        default=50,
        metavar="N",
        help="Gauss-Newton iterations per stage (default: %(default)s)",
    )
    g.add_argument(
        "--batch-points",
        type=_int_min(1),
        default=None,
        metavar="N",
        help="points solved together (default: from --memory-mb)",
    )
    g.add_argument(
        "--memory-mb",
        type=_float_pos,
        default=256.0,
        metavar="MB",
        help="working-memory budget per batch in MiB (default: %(default)s)",
    )
    g = p.add_argument_group("strain")
    g.add_argument(
        "--strain-window",
        type=_odd_int(3),
        default=5,
        metavar="N",
        help="plane fit over N x N grid points (odd) (default: %(default)s)",
    )
    g.add_argument(
        "--strain-kind",
        choices=("green", "small"),
        default="green",
        help="green: Green-Lagrange; small: infinitesimal strain (default: %(default)s)",
    )
    g = p.add_argument_group("computation and output")
    g.add_argument(
        "--device",
        default="cpu",
        metavar="DEV",
        help="torch device: cpu, cuda, cuda:1, mps ... (default: %(default)s)",
    )
    g.add_argument(
        "--dtype",
        choices=("float32", "float64"),
        default=None,
        help="computation precision (default: float32 for integer images, else the image's)",
    )
    ex = g.add_mutually_exclusive_group()
    ex.add_argument(
        "--resume",
        action="store_true",
        help="continue the run that wrote --out (same inputs and options); finished frames "
        "are kept",
    )
    ex.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out (the old file stays intact until the new run ends)",
    )
    g.add_argument("--no-progress", action="store_true", help="no progress bar (it goes to stderr)")
    _add_threads(g)
    _add_common(p)
    p.set_defaults(func=cmd_run)

    # -- export ---------------------------------------------------------------------------
    p = sub.add_parser(
        "export",
        help="write a result file as CSV files, one per frame",
        description=EXPORT_DESCRIPTION,
        epilog=EXPORT_EPILOG,
        formatter_class=_Formatter,
    )
    p.add_argument("result", metavar="RESULT.h5", help="result file written by 'stsdic run'")
    p.add_argument(
        "--out", "-o", required=True, metavar="DIR", help="output directory (or a {frame} pattern)"
    )
    p.add_argument(
        "--frames",
        default=None,
        metavar="SPEC",
        help="image frame numbers to export, e.g. 5, -1 (last), 0:10, 3,7 "
        "(default: every finished frame)",
    )
    p.add_argument("--no-comment", action="store_true", help="no '# torch_stsdic ...' first line")
    _add_common(p)
    p.set_defaults(func=cmd_export)

    # -- plot -----------------------------------------------------------------------------
    p = sub.add_parser(
        "plot",
        help="draw fields and time histories as PNG files",
        description=PLOT_DESCRIPTION,
        epilog=PLOT_EPILOG,
        formatter_class=_Formatter,
    )
    p.add_argument("result", metavar="RESULT.h5", help="result file written by 'stsdic run'")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--frame",
        default="last",
        metavar="N|last",
        help="image frame number of the maps, or 'last' finished frame (default: %(default)s)",
    )
    p.add_argument(
        "--fields",
        default=None,
        metavar="LIST",
        help="comma-separated fields to map, e.g. u,v,exx,eyy,exy,ut,vt,zncc,status "
        "(default: u,v,exx,eyy,exy, those in the file)",
    )
    p.add_argument(
        "--image",
        default=None,
        metavar="INPUT",
        help="image series for the background (default: the inputs recorded in the file, "
        "if they still exist)",
    )
    p.add_argument(
        "--image-frame",
        default=None,
        metavar="N",
        help="frame of the background series (default: the run's reference frame)",
    )
    p.add_argument("--no-image", action="store_true", help="no background image")
    ex = p.add_mutually_exclusive_group()
    ex.add_argument(
        "--point",
        type=_finite,
        nargs=2,
        default=None,
        metavar=("X", "Y"),
        help="time history of the point nearest to (X, Y) px",
    )
    ex.add_argument(
        "--mean",
        action="store_true",
        help="time history of the mean over the valid points (the default)",
    )
    p.add_argument(
        "--dpi", type=_int_min(20), default=120, help="PNG resolution (default: %(default)s)"
    )
    p.add_argument(
        "--min-zncc", type=float, default=0.8, metavar="Z",
        help="hide points whose ZNCC is below Z in the maps, e.g. holes, edges, background "
        "(default: %(default)s; -1 shows every converged point)",
    )
    _add_common(p)
    p.set_defaults(func=cmd_plot)

    # -- synth ----------------------------------------------------------------------------
    p = sub.add_parser(
        "synth",
        help="write a synthetic speckle movie with known motion",
        description=SYNTH_DESCRIPTION,
        epilog=SYNTH_EPILOG,
        formatter_class=_Formatter,
    )
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--size", type=_int_min(16), nargs="+", default=[301], metavar="PX",
        help="image size: N (square) or W H, px (default: 301)",
    )  # fmt: skip
    p.add_argument(
        "--frames",
        type=_int_min(1),
        default=9,
        metavar="N",
        help="deformed frames after the reference (t = 1..N) (default: %(default)s)",
    )
    p.add_argument(
        "--motion",
        choices=MOTIONS,
        default="translation",
        help="motion type, see above (default: %(default)s)",
    )
    p.add_argument(
        "--noise",
        type=_float_nonneg,
        default=5.0,
        metavar="SIGMA",
        help="Gaussian noise std in 8-bit grey levels (default: %(default)s)",
    )
    p.add_argument(
        "--bits",
        type=int,
        choices=(0, 8, 10, 12, 14, 16),
        default=8,
        help="quantisation: 8 -> uint8, 10..16 -> uint16, 0 -> float32 (default: %(default)s)",
    )
    p.add_argument("--seed", type=int, default=0, help="speckle and noise seed (default: 0)")
    p.add_argument(
        "--radius",
        type=_float_pos,
        default=2.0,
        metavar="PX",
        help="mean speckle spot radius (Gaussian std) in px (default: %(default)s)",
    )
    p.add_argument(
        "--layout",
        choices=("multipage", "files"),
        default="multipage",
        help="one multi-page TIFF (movie.tif) or one TIFF per frame (default: %(default)s)",
    )
    p.add_argument(
        "--truth-step",
        type=_int_min(1),
        default=10,
        metavar="PX",
        help="grid spacing of the ground-truth points in truth.csv (default: %(default)s)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing files in DIR")
    _add_threads(p)
    g = p.add_argument_group("motion parameters (t in frames, lengths in px)")
    g.add_argument(
        "--u0", metavar="PX", type=_finite, default=0.0, help="translation: u at t=0 (default: 0)"
    )
    g.add_argument(
        "--v0", metavar="PX", type=_finite, default=0.0, help="translation: v at t=0 (default: 0)"
    )
    g.add_argument(
        "--ut",
        metavar="PX/FR",
        type=_finite,
        default=0.05,
        help="translation: du/dt, px/frame (default: 0.05)",
    )
    g.add_argument(
        "--vt", metavar="PX/FR", type=_finite, default=0.0, help="translation: dv/dt (default: 0)"
    )
    g.add_argument(
        "--exx",
        metavar="1/FR",
        type=_finite,
        default=0.002,
        help="strain: exx per frame (default: 0.002)",
    )
    g.add_argument(
        "--eyy",
        metavar="1/FR",
        type=_finite,
        default=0.0,
        help="strain: eyy per frame (default: 0)",
    )
    g.add_argument(
        "--exy",
        metavar="1/FR",
        type=_finite,
        default=0.0,
        help="strain: tensor shear per frame (default: 0)",
    )
    g.add_argument(
        "--omega",
        metavar="RAD/FR",
        type=_finite,
        default=0.0,
        help="strain: rotation per frame, rad (default: 0)",
    )
    g.add_argument(
        "--amplitude-u",
        metavar="PX",
        type=_finite,
        default=0.5,
        help="sinusoidal: u amplitude (default: 0.5)",
    )
    g.add_argument(
        "--amplitude-v",
        metavar="PX",
        type=_finite,
        default=0.0,
        help="sinusoidal: v amplitude (default: 0)",
    )
    g.add_argument(
        "--wavelength",
        metavar="PX",
        type=_float_pos,
        default=64.0,
        help="sinusoidal: px (default: 64)",
    )
    g.add_argument(
        "--axis", choices=("x", "y"), default="x", help="sinusoidal: varies along (default: x)"
    )
    g.add_argument(
        "--rate",
        metavar="1/FR",
        type=_finite,
        default=0.1,
        help="sinusoidal: amplitude factor per frame, rate*t (default: 0.1)",
    )
    g.add_argument(
        "--au",
        metavar="PX/FR",
        type=_finite,
        default=0.05,
        help="quadratic: px/frame (default: 0.05)",
    )
    g.add_argument(
        "--bu",
        metavar="PX/FR2",
        type=_finite,
        default=0.005,
        help="quadratic: px/frame^2 (default: 0.005)",
    )
    g.add_argument(
        "--av", metavar="PX/FR", type=_finite, default=0.0, help="quadratic: px/frame (default: 0)"
    )
    g.add_argument(
        "--bv",
        metavar="PX/FR2",
        type=_finite,
        default=0.0,
        help="quadratic: px/frame^2 (default: 0)",
    )
    g.add_argument(
        "--x0",
        metavar="PX",
        type=_finite,
        default=None,
        help="jump: crack line x = X0 (default: centre)",
    )
    g.add_argument(
        "--du", metavar="PX", type=_finite, default=0.5, help="jump: u jump in px (default: 0.5)"
    )
    g.add_argument(
        "--dv", metavar="PX", type=_finite, default=0.0, help="jump: v jump in px (default: 0)"
    )
    g.add_argument(
        "--t-jump",
        metavar="T",
        type=_finite,
        default=None,
        help="jump: time of the jump (default: the middle frame, N//2 + 1)",
    )
    _add_common(p)
    p.set_defaults(func=cmd_synth)

    # -- demo -----------------------------------------------------------------------------
    p = sub.add_parser(
        "demo",
        help="classical DIC vs STS-DIC on the paper's synthetic movie",
        description=DEMO_DESCRIPTION,
        epilog=DEMO_EPILOG,
        formatter_class=_Formatter,
    )
    p.add_argument(
        "--out", "-o", default=DEMO_DIR, metavar="DIR",
        help="directory for plots and numbers (default: ./%(default)s)",
    )  # fmt: skip
    p.add_argument(
        "--noise", type=_float_nonneg, default=5.0, metavar="SIGMA",
        help="noise std in grey levels (default: %(default)s)",
    )  # fmt: skip
    p.add_argument(
        "--size", type=_int_min(41), default=None, metavar="PX",
        help="image size in px (default: 301; 101 with --quick)",
    )  # fmt: skip
    p.add_argument(
        "--frames", type=_int_min(1), default=None, metavar="N",
        help="deformed frames (default: 9; 7 with --quick)",
    )  # fmt: skip
    p.add_argument(
        "--m", type=_int_min(1), default=2, help="STS-DIC half window (default: %(default)s)"
    )
    p.add_argument(
        "--subset", type=_odd_int(5), default=21, metavar="PX",
        help="subset width in px (default: %(default)s)",
    )  # fmt: skip
    p.add_argument(
        "--step", type=_int_min(1), default=None, metavar="PX",
        help="grid spacing in px (default: 20; 25 with --quick)",
    )  # fmt: skip
    p.add_argument(
        "--formulation",
        choices=FORMULATIONS,
        default="auto",
        help="STS-DIC formulation (default: %(default)s)",
    )
    p.add_argument(
        "--still-frames", type=_int_min(0), default=8, metavar="K",
        help="also run with the reference = mean of K noisy still frames taken before the "
        "motion (0: skip; default: %(default)s). The reference's noise is shared by every "
        "frame, so no temporal window averages it away; averaging still frames does",
    )  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="speckle and noise seed (default: 0)")
    p.add_argument("--device", default="cpu", metavar="DEV", help="torch device (default: cpu)")
    p.add_argument("--quick", action="store_true", help="small movie, few points: a smoke test")
    p.add_argument("--no-plots", action="store_true", help="print the table only")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    _add_threads(p)
    _add_common(p)
    p.set_defaults(func=cmd_demo)
    return parser


# ----------------------------------------------------------------------------------------
# main
# ----------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``stsdic`` with ``argv`` (default ``sys.argv[1:]``); return the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except UsageError as exc:
        _err(_one_line(exc))
        return 2
    if args.command is None:
        _err("a command is required: run, export, plot, synth or demo (see 'stsdic --help')")
        return 2
    debug = debug or bool(getattr(args, "debug", False))
    threads = None
    try:
        if getattr(args, "threads", None):
            import torch

            threads = torch.get_num_threads()
            torch.set_num_threads(args.threads)
        with _warnings_on_stderr():
            return int(args.func(args) or 0)
    except UsageError as exc:
        if debug:
            traceback.print_exc()
        _err(_one_line(exc))
        return 2
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        _err("interrupted")
        return 130
    except Exception as exc:
        if debug:
            traceback.print_exc()
        known = (CommandError, ValueError, TypeError, OSError, KeyError, IndexError)
        msg = _one_line(exc)
        if not isinstance(exc, known):
            msg = f"{type(exc).__name__}: {msg} (run with --debug for the traceback)"
        _err(msg)
        return 1
    finally:
        if threads is not None:  # main() may be called in-process: leave torch as it was
            import torch

            torch.set_num_threads(threads)


# ----------------------------------------------------------------------------------------
# input files for run: timestamps, points, mask
# ----------------------------------------------------------------------------------------


def _read_timestamps(path: str) -> np.ndarray:
    from .io import read_timestamps

    return read_timestamps(path, "--timestamps")


def _read_points(path: str, shape: tuple[int, int]) -> np.ndarray:
    from .io import read_points

    return read_points(path, shape, "--points")


def _read_mask(path: str, shape: tuple[int, int]) -> np.ndarray:
    from .io import read_mask

    return read_mask(path, shape, "--mask")


def _open_series(inputs: Sequence[str], timestamps: np.ndarray | None) -> Any:
    from .io import InputError, load_series

    src: Any = inputs[0] if len(inputs) == 1 else list(inputs)
    try:
        return load_series(src, timestamps=timestamps)
    except InputError as exc:
        if timestamps is not None and "timestamps" in str(exc):
            raise CommandError(f"--timestamps: {exc}") from exc
        raise


def _series_name(inputs: Sequence[str]) -> str:
    return inputs[0] if len(inputs) == 1 else f"{inputs[0]} .. {inputs[-1]}"


def _check_device(device: str) -> Any:
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError) as exc:
        raise UsageError(f"--device {device}: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {device}: CUDA is not available on this machine")
    if dev.type == "mps" and not (
        getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()
    ):
        raise UsageError(f"--device {device}: MPS is not available on this machine")
    return dev


# ----------------------------------------------------------------------------------------
# result-file helpers
# ----------------------------------------------------------------------------------------


def _status_summary(status: np.ndarray) -> dict[str, float]:
    from .status import Status

    s = np.asarray(status).astype(np.int64)
    total = max(1, s.size)
    return {st.name.lower(): 100.0 * float((s == int(st)).sum()) / total for st in Status}


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def _reference_arg(spec: str, n: int) -> tuple[Any, list[int]]:
    from .io import InputError, parse_frame_spec

    try:
        refs = parse_frame_spec(spec, n)
    except InputError as exc:
        raise UsageError(f"--reference {spec}: {exc}") from None
    if len(refs) == 1:
        return refs[0], refs
    return spec, refs


def cmd_run(args: argparse.Namespace) -> int:
    """``stsdic run``: track points through a series, write HDF5, add strains, summarise."""
    from .config import DICConfig
    from .io import InputError, parse_frame_spec

    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out}: is a directory; give a file name such as result.h5")
    if out.exists() and not (args.overwrite or args.resume):
        raise CommandError(
            f"output file {out} exists: use --overwrite to replace it or --resume to continue it"
        )
    device = _check_device(args.device)

    # inputs
    times = _read_timestamps(args.timestamps) if args.timestamps else None
    series = _open_series(args.inputs, times)
    name = _series_name(args.inputs)
    h, w = series.shape
    n = len(series)
    if args.subset > min(h, w):
        raise UsageError(
            f"--subset {args.subset} is larger than the images of {name} ({w}x{h} px, WxH)"
        )
    need = 2 * args.m + 1
    if n < need:
        raise UsageError(
            f"--m {args.m} needs at least 2m+1 = {need} frames, but {name} has {n} frame(s)"
        )
    frames = None
    if args.frames is not None:
        try:
            frames = parse_frame_spec(args.frames, n)
        except InputError as exc:
            raise UsageError(f"--frames {args.frames}: {exc}") from None
    reference, ref_frames = _reference_arg(args.reference, n)
    roi = None
    if args.roi is not None:
        x0, y0, x1, y1 = args.roi
        if not (0 <= x0 < x1 <= w - 1 and 0 <= y0 < y1 <= h - 1):
            raise UsageError(
                f"--roi {x0} {y0} {x1} {y1} is not inside the {w}x{h} (WxH) image of {name}: "
                f"need 0 <= X0 < X1 <= {w - 1} and 0 <= Y0 < Y1 <= {h - 1}"
            )
        roi = (x0, y0, x1, y1)
    mask = _read_mask(args.mask, (h, w)) if args.mask else None
    points = _read_points(args.points, (h, w)) if args.points else None
    try:
        cfg = DICConfig(
            subset_size=args.subset,
            m=args.m,
            shape=args.shape,
            window=args.window,
            criterion=args.criterion,
            formulation=args.formulation,
            interpolation=args.interpolation,
            max_iter=args.max_iter,
            tol=args.tol,
            search_radius=args.search_radius,
            initial_guess=args.initial_guess,
            seed_spacing=args.seed_spacing,
            batch_points=args.batch_points,
            memory_mb=args.memory_mb,
            dtype=args.dtype,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None

    # float images: NaN/inf anywhere is found now, before any output file is written
    if series.dtype_name.startswith("float"):
        for i in range(n):
            series.numpy(i)

    from .series import track

    print(series.describe(), flush=True)
    t0 = time.perf_counter()
    try:
        res = track(
            series,
            reference=reference,
            frames=frames,
            points=points,
            roi=roi,
            mask=mask,
            step=args.step,
            config=cfg,
            device=str(device),
            progress=not args.no_progress,
            out=str(out),
            resume=args.resume,
            overwrite=args.overwrite,
            reference_update=args.reference_update,
        )
    except KeyboardInterrupt:
        print(
            f"{PROG}: interrupted: the finished frames are kept in {out} (or {out}.partial); "
            "continue with the same command and --resume",
            file=sys.stderr,
        )
        raise
    elapsed = time.perf_counter() - t0
    return _finish_run(res, out, args, elapsed, t0)


def _finish_run(res: Any, out: Path, args: argparse.Namespace, elapsed: float, t0: float) -> int:
    from .io import add_fields

    # strains, added to the finished file
    strain = res.strain(window=args.strain_window, kind=args.strain_kind)
    fields = {k: _np(v) for k, v in strain.items() if _np(v).shape == _np(res.u).shape}
    add_fields(
        out,
        fields,
        {"strain": json.dumps({"window": args.strain_window, "kind": args.strain_kind})},
    )
    elapsed_total = time.perf_counter() - t0

    status = _np(res.status)
    n_f, n_p = status.shape
    st = _status_summary(status)
    poi = n_f * n_p
    print(f"points: {n_p}   frames: {n_f}   reference: {args.reference}   m: {args.m}")
    print(
        f"converged: {st['converged']:.1f} %   max-iter: {st['max_iter']:.1f} %   "
        f"failed: {100.0 - st['converged'] - st['max_iter']:.1f} % "
        f"(diverged {st['diverged']:.1f}, outside {st['outside']:.1f}, "
        f"low texture {st['low_texture']:.1f}, not computed {st['not_computed']:.1f})"
    )
    import torch

    from . import native

    device = args.device
    on_cpu = str(device).startswith("cpu")
    kernels = "fused C++ kernels" if on_cpu and native.available() else "torch kernels"
    threads = f", {torch.get_num_threads()} threads" if on_cpu else ""
    print(
        f"time: {_fmt_time(elapsed)} (strain included: {_fmt_time(elapsed_total)})   "
        f"{poi / max(elapsed, 1e-9):.0f} POI/s   ({device}, {kernels}{threads})"
    )
    print(f"results: {out} (fields u, v, ut, vt, zncc, status, {', '.join(fields)})")
    return 0


# ----------------------------------------------------------------------------------------
# export
# ----------------------------------------------------------------------------------------


def _select_frames(spec: str, frames: np.ndarray, path: str, option: str) -> list[int]:
    """Image frame numbers from ``spec`` that the result file holds."""
    from .io import InputError, parse_frame_spec

    if len(frames) == 0:
        raise CommandError(f"{path}: the result file holds no frame")
    stored = [int(f) for f in frames]
    n = max(stored) + 1
    try:
        wanted = parse_frame_spec(spec, n)
    except InputError as exc:
        msg = f"{option} {spec}: {exc} (the file holds frames {_span(stored)})"
        raise UsageError(msg) from None
    have = set(stored)
    keep = [f for f in wanted if f in have]
    if not keep:
        raise UsageError(f"{option} {spec}: no such frame in {path} (frames {_span(stored)})")
    return keep


def _span(frames: Sequence[int]) -> str:
    f = list(frames)
    if len(f) > 6:
        return f"{f[0]}, {f[1]}, {f[2]}, ..., {f[-1]} ({len(f)} frames)"
    return ", ".join(str(x) for x in f)


def _read_frames(path: str) -> np.ndarray:
    import h5py

    p = Path(path)
    if not p.exists():
        raise CommandError(f"result file not found: {path}")
    try:
        with h5py.File(p, "r", locking=False) as f:
            if "frames" not in f:
                raise CommandError(f"{path} is not a torch_stsdic result file")
            return f["frames"][()]
    except OSError as exc:
        raise CommandError(f"{path} is not a readable HDF5 result file: {exc}") from exc


def cmd_export(args: argparse.Namespace) -> int:
    """``stsdic export``: one CSV per frame."""
    from .io import export_csv

    frames = None
    stored = _read_frames(args.result)
    if args.frames is not None:
        frames = _select_frames(args.frames, stored, args.result, "--frames")
    written = export_csv(args.result, args.out, frames, comment=not args.no_comment)
    if not written:
        print(f"no finished frame in {args.result}: nothing written")
        return 0
    where = Path(written[0]).parent
    print(f"wrote {len(written)} CSV file(s) to {where} ({written[0].name} ..)")
    return 0


# ----------------------------------------------------------------------------------------
# plot
# ----------------------------------------------------------------------------------------


def _background(args: argparse.Namespace, res: Any) -> np.ndarray | None:
    """Background image for the maps, or None."""
    from .io import load_series

    if args.no_image:
        return None
    explicit = args.image is not None
    inputs = [args.image] if explicit else list(res.inputs)
    if not inputs or (not explicit and not all(Path(s).exists() for s in inputs)):
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            series = load_series(inputs[0] if len(inputs) == 1 else inputs)
        if args.image_frame is not None:
            from .io import parse_frame_spec

            k = parse_frame_spec(args.image_frame, len(series))[0]
        else:
            ref = (res.config.get("track") or {}).get("reference", 0)
            try:
                k = int(ref)
            except (TypeError, ValueError):  # "mean:0,1,2" or "array:..."
                k = int(str(ref).split(":")[-1].split(",")[0]) if "mean:" in str(ref) else 0
            k = k if 0 <= k < len(series) else 0
        return series.numpy(k)
    except Exception as exc:
        if explicit:
            raise CommandError(f"--image {args.image}: {_one_line(exc)}") from exc
        warnings.warn(f"no background image ({_one_line(exc)})", stacklevel=2)
        return None


def cmd_plot(args: argparse.Namespace) -> int:
    """``stsdic plot``: field maps at one frame and time histories as PNG."""
    from .io import read_results
    from .plot import plot_fields, plot_history
    from .status import Status

    p = Path(args.result)
    if not p.exists():
        raise CommandError(f"result file not found: {args.result}")
    res = read_results(p)
    if res.n_frames == 0 or res.n_points == 0:
        raise CommandError(f"{args.result}: the result file holds no frame or no point")
    # frame
    done = np.flatnonzero(res.completed)
    if args.frame == "last":
        if not done.size:
            raise CommandError(f"{args.result}: no finished frame to plot")
        row = int(done[-1])
    else:
        try:
            fr = int(args.frame)
        except ValueError:
            raise UsageError(f"--frame {args.frame}: expected a frame number or 'last'") from None
        hits = np.flatnonzero(res.frames == fr)
        if fr < 0 and not hits.size and -len(res.frames) <= fr:
            hits = np.array([len(res.frames) + fr])
        if not hits.size:
            raise UsageError(
                f"--frame {args.frame}: no such frame in {args.result} "
                f"(frames {_span(res.frames.tolist())})"
            )
        row = int(hits[0])
    frame = int(res.frames[row])
    # fields
    avail = list(res.fields)
    if args.fields is None:
        names = [f for f in ("u", "v", "exx", "eyy", "exy") if f in res.fields]
    else:
        names = [s.strip() for s in args.fields.split(",") if s.strip()]
        bad = [s for s in names if s not in res.fields]
        if bad or not names:
            raise UsageError(
                f"--fields {args.fields}: unknown field(s) {', '.join(bad) or '(none)'} "
                f"(the file has {', '.join(avail)})"
            )
    status = res.fields.get("status")
    valid = (
        np.asarray(status) <= int(Status.MAX_ITER)
        if status is not None
        else np.isfinite(res.fields.get("u", np.zeros((res.n_frames, res.n_points))))
    )
    zn = res.fields.get("zncc")
    if zn is not None and args.min_zncc > -1.0:
        valid = valid & (np.nan_to_num(np.asarray(zn), nan=-1.0) >= args.min_zncc)
    image = _background(args, res)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if names:
        maps = {}
        for nm in names:
            vals = np.asarray(res.fields[nm][row], dtype=np.float64)
            if nm != "status":
                vals = np.where(valid[row], vals, np.nan)
            maps[nm] = vals
        path = out / f"fields_frame{frame:05d}.png"
        plot_fields(
            image,
            res.points,
            maps,
            path,
            suptitle=f"{p.name}: frame {frame} (t = {res.times[row]:g})",
            dpi=args.dpi,
        )
        written.append(path)

    # histories
    if args.point is not None:
        x, y = args.point
        d2 = (res.points[:, 0] - x) ** 2 + (res.points[:, 1] - y) ** 2
        k = int(np.argmin(d2))
        px, py = res.points[k]

        def pick(a: np.ndarray) -> np.ndarray:
            return np.where(valid[:, k], np.asarray(a[:, k], dtype=np.float64), np.nan)

        what = f"point {k} at ({px:g}, {py:g})"
        tag = f"x{px:g}_y{py:g}"
    else:

        def pick(a: np.ndarray) -> np.ndarray:
            vals = np.where(valid, np.asarray(a, dtype=np.float64), np.nan)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return np.nanmean(vals, axis=1)

        what = "mean over valid points"
        tag = "mean"
    done_mask = res.completed.astype(bool)
    t = res.times

    def hist(keys: Sequence[str], ylabel: str, fname: str) -> None:
        series = {}
        for key in keys:
            if key in res.fields:
                vals = pick(res.fields[key])
                vals = np.where(done_mask, vals, np.nan)
                if np.isfinite(vals).any():
                    series[key] = vals
        if series:
            path = out / fname
            plot_history(t, series, ylabel=ylabel, title=f"{p.name}: {what}", path=path,
                         dpi=args.dpi)  # fmt: skip
            written.append(path)

    hist(("u", "v"), "displacement (px)", f"history_{tag}.png")
    hist(("ut", "vt"), "velocity (px / time unit)", f"velocity_history_{tag}.png")
    hist(("exx", "eyy", "exy"), "strain (-)", f"strain_history_{tag}.png")
    for path in written:
        print(f"wrote {path}")
    return 0


# ----------------------------------------------------------------------------------------
# synth
# ----------------------------------------------------------------------------------------


def _make_motion(args: argparse.Namespace, w: int, h: int, n_frames: int) -> tuple[Any, dict]:
    from . import synth

    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    kind = args.motion
    if kind == "translation":
        params = {"u0": args.u0, "v0": args.v0, "ut": args.ut, "vt": args.vt}
        motion = synth.Translation(**params)
    elif kind == "strain":
        params = {
            "exx": args.exx, "eyy": args.eyy, "exy": args.exy, "omega": args.omega,
            "center": [cx, cy], "rate": 1.0,
        }  # fmt: skip
        motion = synth.HomogeneousStrain(
            exx=args.exx, eyy=args.eyy, exy=args.exy, omega=args.omega, center=(cx, cy), rate=1.0
        )
    elif kind == "sinusoidal":
        params = {
            "amplitude_u": args.amplitude_u, "amplitude_v": args.amplitude_v,
            "wavelength": args.wavelength, "axis": args.axis, "rate": args.rate,
        }  # fmt: skip
        motion = synth.Sinusoidal(**params)
    elif kind == "quadratic":
        params = {"au": args.au, "bu": args.bu, "av": args.av, "bv": args.bv}
        motion = synth.QuadraticInTime(**params)
    else:  # jump
        x0 = cx if args.x0 is None else args.x0
        tj = float(n_frames // 2 + 1) if args.t_jump is None else args.t_jump
        params = {"x0": x0, "du": args.du, "dv": args.dv, "t_jump": tj}
        motion = synth.Jump(**params)
    return motion, params


def _max_border_motion(motion: Any, w: int, h: int, times: np.ndarray) -> float:
    import torch

    xs = torch.linspace(-0.5, w - 0.5, 64, dtype=torch.float64)
    ys = torch.linspace(-0.5, h - 0.5, 64, dtype=torch.float64)
    bx = torch.cat([xs, xs, torch.full_like(ys, -0.5), torch.full_like(ys, w - 0.5)])
    by = torch.cat([torch.full_like(xs, -0.5), torch.full_like(xs, h - 0.5), ys, ys])
    best = 0.0
    for t in times:
        u, v = motion.displacement(bx, by, float(t))
        best = max(best, float(torch.sqrt(u * u + v * v).max()))
    return best


def _write_tiff_atomic(path: Path, data: np.ndarray) -> None:
    import tifffile

    tmp = path.with_name(path.name + ".partial")
    tifffile.imwrite(tmp, data, photometric="minisblack")
    os.replace(tmp, path)


def _to_dtype(img: Any, bits: int) -> np.ndarray:
    from .synth import quantize

    if bits == 0:
        return _np(img).astype(np.float32)
    q = _np(quantize(img, bits))
    return q.astype(np.uint8 if bits == 8 else np.uint16)


def cmd_synth(args: argparse.Namespace) -> int:
    """``stsdic synth``: synthetic speckle movie + ground truth."""
    import torch

    from . import synth

    if len(args.size) == 1:
        w = h = args.size[0]
    elif len(args.size) == 2:
        w, h = args.size
    else:
        raise UsageError(f"--size: give N or W H, got {len(args.size)} values")
    n = args.frames
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CommandError(f"--out {out}: exists and is not a directory")
    times = np.arange(0, n + 1, dtype=np.float64)
    targets = (
        [out / "movie.tif"]
        if args.layout == "multipage"
        else [out / f"frame_{k:05d}.tif" for k in range(n + 1)]
    )
    targets += [out / "truth.csv", out / "motion.json", out / "times.csv"]
    existing = [t for t in targets if t.exists()]
    if existing and not args.overwrite:
        raise CommandError(
            f"{existing[0]} exists ({len(existing)} file(s) would be replaced): "
            "use --overwrite or another --out"
        )
    motion, params = _make_motion(args, w, h, n)
    margin = max(16.0, 8.0 * args.radius) + math.ceil(_max_border_motion(motion, w, h, times))
    t0 = time.perf_counter()
    movie = synth.synthetic_movie(
        (h, w),
        n,
        motion,
        noise_sigma=args.noise,
        seed=args.seed,
        radius=args.radius,
        margin=margin,
    )
    stack = torch.cat([movie.ref[None], movie.frames], 0)
    data = _to_dtype(stack, args.bits)
    out.mkdir(parents=True, exist_ok=True)
    if args.layout == "multipage":
        _write_tiff_atomic(out / "movie.tif", data)
        files = ["movie.tif"]
    else:
        files = []
        for k in range(n + 1):
            _write_tiff_atomic(out / f"frame_{k:05d}.tif", data[k])
            files.append(f"frame_{k:05d}.tif")

    # ground truth on a grid
    xs = np.arange(0, w, args.truth_step, dtype=np.float64)
    ys = np.arange(0, h, args.truth_step, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    truth = synth.ground_truth(motion, pts, times)
    keys = ("u", "v", "ut", "vt", "dudx", "dudy", "dvdx", "dvdy")
    tr = {k: _np(truth[k]) for k in keys}
    lines = ["frame,time,x,y," + ",".join(keys)]
    for f in range(n + 1):
        for j in range(len(pts)):
            vals = ",".join(f"{tr[k][f, j]:.10g}" for k in keys)
            lines.append(f"{f},{times[f]:g},{pts[j, 0]:g},{pts[j, 1]:g},{vals}")
    (out / "truth.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out / "times.csv").write_text(
        "frame,time\n" + "".join(f"{k},{t:g}\n" for k, t in enumerate(times)), encoding="utf-8"
    )
    dtype = {0: "float32", 8: "uint8"}.get(args.bits, "uint16")
    meta = {
        "generator": "torch_stsdic synth",
        "motion": {
            "type": args.motion,
            "class": type(motion).__name__,
            "params": params,
            "repr": repr(motion),
        },  # fmt: skip
        "size": {"width": w, "height": h},
        "frames": n + 1,
        "reference_frame": 0,
        "times": times.tolist(),
        "noise_sigma": args.noise,
        "noise_scale": "8-bit grey levels",
        "bits": args.bits,
        "dtype": dtype,
        "seed": args.seed,
        "speckle_radius": args.radius,
        "pattern_margin": margin,
        "layout": args.layout,
        "files": files,
        "truth": {
            "file": "truth.csv",
            "grid_step": args.truth_step,
            "points": int(len(pts)),
            "columns": ["frame", "time", "x", "y", *keys],
            "units": "px, px per frame, px/px; u along x (columns), v along y (rows)",
            "convention": "Lagrangian: displacement of reference-image point (x, y) at time t",
        },
        "conventions": "x = column, y = row, pixel centres at integers, 0-based",
    }
    (out / "motion.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    el = time.perf_counter() - t0
    umax = float(np.abs(tr["u"]).max())
    vmax = float(np.abs(tr["v"]).max())
    print(
        f"wrote {n + 1} frames of {w}x{h} px ({dtype}, noise {args.noise:g}) to "
        f"{out / files[0]}{' ..' if len(files) > 1 else ''} in {_fmt_time(el)}"
    )
    print(f"motion: {motion!r}; max |u| {umax:.3g} px, max |v| {vmax:.3g} px on the truth grid")
    print(f"ground truth: {out / 'truth.csv'} ({len(pts)} points x {n + 1} frames), "
          f"{out / 'motion.json'}")  # fmt: skip
    return 0


# ----------------------------------------------------------------------------------------
# demo
# ----------------------------------------------------------------------------------------


def _rms(err: np.ndarray) -> float:
    e = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


def cmd_demo(args: argparse.Namespace) -> int:
    """``stsdic demo``: classical DIC vs STS-DIC on the paper's synthetic movie."""
    import torch

    from . import synth
    from .config import DICConfig
    from .io import load_series
    from .series import track
    from .status import Status

    size = args.size or (101 if args.quick else 301)
    n = args.frames or (7 if args.quick else 9)
    step = args.step or (25 if args.quick else 20)
    m = args.m
    if n < 2 * m + 1:
        raise UsageError(f"--frames {n}: STS-DIC with --m {m} needs at least {2 * m + 1} frames")
    if args.subset > size:
        raise UsageError(f"--subset {args.subset} is larger than the image ({size} px)")
    device = _check_device(args.device)
    ut_true = 1.0 / 20.0

    t0 = time.perf_counter()
    motion = synth.Translation(ut=ut_true)
    movie = synth.synthetic_movie((size, size), n, motion, noise_sigma=args.noise, seed=args.seed)
    times = np.arange(0, n + 1, dtype=np.float64)
    # the deformed frames only: the reference image is given apart, so that no STS window
    # contains the reference itself (whose noise would match exactly)
    series = load_series(movie.frames.float(), timestamps=times[1:])
    reference = movie.ref.float()
    references = [("", reference)]
    k_still = 0 if args.quick else args.still_frames
    if k_still:
        clean = synth.synthetic_movie((size, size), 1, motion, seed=args.seed).ref
        stills = torch.stack([
            synth.add_noise(clean, args.noise, seed=10_000 + args.seed * 100 + k)
            for k in range(k_still)
        ])
        references.append((f", ref=mean of {k_still}", stills.mean(0).float()))
    t_synth = time.perf_counter() - t0

    margin = args.subset // 2 + 3
    xs = np.arange(margin, size - margin, step, dtype=np.float64)
    if xs.size == 0:
        raise UsageError(f"--size {size} is too small for --subset {args.subset}")
    xs = xs + np.floor(((size - 1 - margin) - xs[-1]) / 2.0)  # centre the grid
    gx, gy = np.meshgrid(xs, xs)
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    frames = list(range(n))
    truth = synth.ground_truth(motion, pts, times[1:])
    u_true, v_true = _np(truth["u"]), _np(truth["v"])

    print(
        f"STS-DIC demo: {size}x{size} px speckle, reference + {n} frames, u = t/20 px, "
        f"noise sigma {args.noise:g}, subset {args.subset}, {len(pts)} points "
        f"(synthesised in {_fmt_time(t_synth)})",
        flush=True,
    )
    rows = []
    runs = [(f"{name}{tag}", mm, ref) for tag, ref in references
            for name, mm in (("classical DIC", 0), ("STS-DIC", m))]
    for label, mm, reference in runs:
        cfg = DICConfig(
            subset_size=args.subset,
            m=mm,
            formulation=args.formulation,
            search_radius=2,
        )
        t1 = time.perf_counter()
        res = track(
            series,
            reference=reference,
            frames=frames,
            points=pts,
            config=cfg,
            device=str(device),
            progress=not args.no_progress,
        )
        el = time.perf_counter() - t1
        status = _np(res.status)
        ok = status <= int(Status.MAX_ITER)
        u = np.where(ok, _np(res.u).astype(np.float64), np.nan)
        v = np.where(ok, _np(res.v).astype(np.float64), np.nan)
        ut = np.where(ok, _np(res.ut).astype(np.float64), np.nan)
        fd = False
        if mm == 0 or not np.isfinite(ut).any():
            ut = np.gradient(u, times[1:], axis=0) if len(frames) > 1 else ut
            fd = True
        eu = u - u_true
        rows.append(
            {
                "method": label,
                "m": mm,
                "rms_u": _rms(eu),
                "rms_v": _rms(v - v_true),
                "rms_ut": _rms(ut - ut_true),
                "ut_from_finite_differences": fd,
                "bias_u": float(np.nanmean(eu)),
                "std_u": float(np.nanstd(eu)),
                "valid_percent": 100.0 * float(ok.mean()),
                "time_s": el,
                "poi_per_s": ok.size / max(el, 1e-9),
                "rms_u_per_frame": [_rms(eu[k]) for k in range(len(frames))],
                "mean_u_per_frame": np.nanmean(u, axis=1).tolist(),
                "_u": u,
                "_eu": eu,
            }
        )

    c, s = rows[0], rows[1]
    width = max(16, max(len(r["method"]) for r in rows) + 1)
    hdr = (
        f"{'method':<{width}}{'m':>3}{'RMS u err':>12}{'RMS v err':>12}{'RMS ut err':>13}"
        f"{'valid':>8}{'time':>9}{'POI/s':>9}"
    )
    units = (
        f"{'':<{width}}{'':>3}{'(px)':>12}{'(px)':>12}{'(px/frame)':>13}{'(%)':>8}{'(s)':>9}"
        f"{'':>9}"
    )
    print()
    print(hdr)
    print(units)
    print("-" * len(hdr))
    for r in rows:
        star = "*" if r["ut_from_finite_differences"] else " "
        print(
            f"{r['method']:<{width}}{r['m']:>3}{r['rms_u']:>12.4f}{r['rms_v']:>12.4f}"
            f"{r['rms_ut']:>12.4f}{star}{r['valid_percent']:>8.1f}{r['time_s']:>9.2f}"
            f"{r['poi_per_s']:>9.0f}"
        )
    print("-" * len(hdr))

    def ratio(a: float, b: float) -> float:
        return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")

    r_u, r_v, r_ut = (
        ratio(c["rms_u"], s["rms_u"]),
        ratio(c["rms_v"], s["rms_v"]),
        ratio(c["rms_ut"], s["rms_ut"]),
    )
    rat = [f"{x:.2f}x" for x in (r_u, r_v, r_ut)]
    lab = "ratio classical / STS-DIC"
    print(f"{lab:<{width + 3}}{rat[0]:>12}{rat[1]:>12}{rat[2]:>12}")
    if len(rows) == 4:
        ca, sa = rows[2], rows[3]
        r_ua = ratio(ca["rms_u"], sa["rms_u"])
        r_ca = ratio(c["rms_u"], sa["rms_u"])
        print(f"{lab + ', averaged ref':<{width + 3}}{r_ua:>11.2f}x")
        print(f"{'classical / STS-DIC averaged ref':<{width + 3}}{r_ca:>11.2f}x")
        print(
            "STS-DIC averages the deformed frames' noise; the reference's noise is shared by "
            "every frame,\nso with one noisy reference the gain in u is bounded by "
            f"sqrt((1 + 1/{2 * m + 1}) / 2) = {math.sqrt((1 + 1 / (2 * m + 1)) / 2):.2f}; "
            "averaging still frames into the reference lifts that bound."
        )
    if c["ut_from_finite_differences"]:
        print("* classical DIC measures no velocity: ut from finite differences of u")

    if not args.no_plots:
        from .plot import plot_fields, plot_history, plot_xy

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        tt = times[1:]
        plot_xy(
            tt,
            {f"{r['method']} (m={r['m']})": r["rms_u_per_frame"] for r in rows},
            xlabel="time (frame)",
            ylabel="RMS error of u (px)",
            title=f"error per frame, noise sigma {args.noise:g}",
            path=out / "error_per_frame.png",
        )
        mid = len(frames) // 2
        plot_fields(
            _np(movie.ref),
            pts,
            {
                f"u classical, t={tt[mid]:g}": c["_u"][mid],
                f"u STS-DIC m={m}, t={tt[mid]:g}": s["_u"][mid],
                "u error classical": c["_eu"][mid],
                f"u error STS-DIC m={m}": s["_eu"][mid],
            },
            out / "fields.png",
            ncols=2,
            suptitle=f"true u = {tt[mid] * ut_true:g} px",
        )
        plot_history(
            tt,
            {
                "truth": u_true[:, 0],
                "classical DIC (mean)": c["mean_u_per_frame"],
                f"STS-DIC m={m} (mean)": s["mean_u_per_frame"],
            },
            ylabel="u (px)",
            title="mean displacement",
            path=out / "history.png",
        )
        summary = {
            "settings": {
                "size": size, "frames": n, "noise_sigma": args.noise, "m": m,
                "subset": args.subset, "step": step, "points": len(pts),
                "formulation": args.formulation, "seed": args.seed, "device": str(device),
                "motion": repr(motion),
            },
            "results": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows],
            "ratio_classical_over_sts": {"u": r_u, "v": r_v, "ut": r_ut},
        }  # fmt: skip
        (out / "demo.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        print(f"plots and numbers in {out}/: error_per_frame.png fields.png history.png demo.json")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
