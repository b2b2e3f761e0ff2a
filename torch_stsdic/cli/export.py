"""``stsdic export``: write the frames of a result file as CSV files, one per frame."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from . import options
from .common import span
from .errors import CommandError, UsageError

NAME = "export"
HELP = "write a result file as CSV files, one per frame"

DESCRIPTION = """\
Write the frames of a result file as CSV files, one per frame, named
<result stem>_frame<NNNNN>.csv in DIR (or give a pattern with {frame}, e.g.
'csv/f{frame:04d}.csv'). Columns: x, y, u, v, ut, vt, exx, eyy, exy, zncc, status, then
any other stored field; NaN (failed points) are empty cells. A first comment line
'# torch_stsdic results ... frame=F time=T' precedes the header.
"""

EPILOG = """\
examples:
  stsdic export result.h5 --out csv/
  stsdic export result.h5 --out csv/ --frames 0:10
  stsdic export result.h5 --out 'csv/f{frame:04d}.csv' --frames -1
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic export``."""
    options.add_result(p)
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


def _read_frames(path: str) -> np.ndarray:
    """The image frame numbers a result file holds (CommandError if it is no result file)."""
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


def _select_frames(spec: str, frames: np.ndarray, path: str) -> list[int]:
    """Image frame numbers from ``--frames spec`` that the result file holds."""
    from ..io import InputError, parse_frame_spec

    if len(frames) == 0:
        raise CommandError(f"{path}: the result file holds no frame")
    stored = [int(f) for f in frames]
    try:
        wanted = parse_frame_spec(spec, max(stored) + 1)
    except InputError as exc:
        raise UsageError(f"--frames {spec}: {exc} (the file holds frames {span(stored)})") from None
    have = set(stored)
    keep = [f for f in wanted if f in have]
    if not keep:
        raise UsageError(f"--frames {spec}: no such frame in {path} (frames {span(stored)})")
    return keep


def execute(args: argparse.Namespace) -> int:
    """``stsdic export``: one CSV per frame."""
    from ..io import export_csv

    frames = None
    stored = _read_frames(args.result)
    if args.frames is not None:
        frames = _select_frames(args.frames, stored, args.result)
    written = export_csv(args.result, args.out, frames, comment=not args.no_comment)
    if not written:
        print(f"no finished frame in {args.result}: nothing written")
        return 0
    where = Path(written[0]).parent
    print(f"wrote {len(written)} CSV file(s) to {where} ({written[0].name} ..)")
    return 0
