"""``stsdic export``: a result file as CSV files (one per frame), VTK for ParaView or MATLAB."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from torch_stsdic.cli import options
from torch_stsdic.cli.common import check_folder, span
from torch_stsdic.cli.errors import CommandError, UsageError, one_line

NAME = "export"
HELP = "write a result file as CSV (one file per frame), VTK (ParaView) or MATLAB .mat"

DESCRIPTION = """\
Write the frames of a result file for other tools, in the units the run recorded
('stsdic run --scale 0.02 --unit mm': lengths in mm, velocities in mm per time unit,
strains dimensionless; px without a scale). Every field of the file is written.

  --format csv  one CSV per frame, <result stem>_frame<NNNNN>.csv in DIR (or a pattern
                with {frame}, e.g. 'csv/f{frame:04d}.csv'). The first line is the header:
                x, y, u, v, ut, vt, exx, eyy, exy, zncc, status, then any other field;
                NaN (failed points) are empty cells. Units, calibration and the frame and
                time of every file are in <result stem>_csv.json (--comment adds a
                '# torch_stsdic ...' line before the header instead).
  --format vtk  ParaView: <stem>_frame<NNNNN>.vtu per frame (points joined into quads on a
                grid; point data: every field, plus the vectors displacement and velocity)
                and the time series <stem>.pvd (open this one).
  --format mat  MATLAB: <stem>.mat with (frames, points) arrays u, v, ut, vt, ..., and x, y,
                frames, times, completed, unit, scale, time_unit, units, status_codes.

A stereo result file ('stsdic stereo', recognised from its content) is written the same way,
in mm: CSV columns x, y (left reference px), X, Y, Z, U, V, W (mm), Ut, Vt, Wt (mm per
time unit), their _std, reprojection_error (px), status; VTK points at their 3D position of
the frame (a point not usable there at its reference position X0 with NaN fields; points
never triangulated left out), point data every field and the vectors displacement (U, V,
W), velocity (Ut, Vt, Wt) and reference_position (X0); MATLAB (frames, points) arrays and
x, y, X0, X0_std, right_points, frames, times, units, status_codes, calibration (JSON).
"""

EPILOG = """\
examples:
  stsdic export result.h5 --out csv/
  stsdic export result.h5 --out csv/ --frames 0:10
  stsdic export result.h5 --out 'csv/f{frame:04d}.csv' --frames -1
  stsdic export result.h5 --format vtk --out vtk/        # then open vtk/result.pvd
  stsdic export result.h5 --format mat --out mat/        # load('mat/result.mat')
  stsdic export 3d.h5 --format vtk --out vtk/            # a 'stsdic stereo' file: 3D points
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic export``."""
    from torch_stsdic.analysis.export import FORMATS

    p.add_argument("result", metavar="RESULT.h5",
                   help="result file written by 'stsdic run' or 'stsdic stereo'")
    p.add_argument(
        "--out", "-o", required=True, metavar="DIR",
        help="output directory, created if missing (csv: or a {frame} pattern)",
    )  # fmt: skip
    options.add_option(p, "--format", "-f", choices=FORMATS, default="csv",
                       help="csv: one file per frame; vtk: ParaView .vtu per frame + .pvd; "
                       "mat: MATLAB")  # fmt: skip
    options.add_option(p, "--frames", default=None, metavar="SPEC",
                       help="image frame numbers to export, e.g. 5, -1 (last), 0:10, 3,7",
                       shown="every finished frame")  # fmt: skip
    ex = p.add_mutually_exclusive_group()
    ex.add_argument(
        "--comment", action="store_true",
        help="csv: a '# torch_stsdic ... frame=F time=T unit=U' line before the header",
    )  # fmt: skip
    ex.add_argument("--no-comment", action="store_true", help=argparse.SUPPRESS)  # the default


def _read_frames(path: str) -> tuple[np.ndarray, bool]:
    """The image frame numbers a result file holds, and whether it is a stereo result
    (CommandError if it is no result file)."""
    import h5py

    from torch_stsdic.stereo.result import is_stereo_file

    p = Path(path)
    if not p.exists():
        raise CommandError(f"result file not found: {path}")
    try:
        with h5py.File(p, "r", locking=False) as f:
            if "frames" not in f:
                raise CommandError(f"{path} is not a torch_stsdic result file")
            return f["frames"][()], is_stereo_file(f)
    except OSError as exc:
        raise CommandError(f"{path} is not a readable HDF5 result file: {exc}") from exc


def _select_frames(spec: str, frames: np.ndarray, path: str) -> list[int]:
    """Image frame numbers from ``--frames spec`` that the result file holds."""
    from torch_stsdic.io import InputError, parse_frame_spec

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
    """``stsdic export``: CSV per frame, VTK per frame + .pvd, or one .mat (2-D or stereo
    result files)."""
    from torch_stsdic.analysis.export import export_results
    from torch_stsdic.stereo.export import export_stereo

    frames = None
    stored, stereo = _read_frames(args.result)
    if args.frames is not None:
        frames = _select_frames(args.frames, stored, args.result)
    if args.format != "csv" and "{" in args.out:
        raise UsageError(f"--out {args.out}: a {{frame}} pattern is for --format csv; give a "
                         "directory")
    folder = Path(args.out).parent if "{" in args.out else Path(args.out)
    check_folder(folder, f"--out {args.out}")
    kw = {"comment": args.comment} if args.format == "csv" else {}
    try:
        export = export_stereo if stereo else export_results
        written = export(args.result, args.out, args.format, frames, **kw)
    except OSError as exc:  # a full disk: the file named, none left half-written
        done = getattr(exc, "written", None)
        kept = (f"; the {len(done)} file(s) finished before it are whole ({done[0].name} ..)"
                if done else "; no file was left half-written")
        raise CommandError(f"{one_line(exc)}{kept}") from None
    frame_files = [w for w in written if w.suffix in (".csv", ".vtu")]
    if args.format != "mat" and not frame_files:
        print(f"no finished frame in {args.result}: nothing written")
        return 0
    where = Path(written[0]).parent
    (_say_stereo_units if stereo else _say_units)(args.result)
    what = {"csv": "CSV", "vtk": "VTK"}.get(args.format)
    if what:
        extra = f"; open {written[-1].name} in ParaView" if args.format == "vtk" else ""
        print(f"wrote {len(frame_files)} {what} file(s) to {where} ({frame_files[0].name} ..)"
              f"{extra}")
    else:
        print(f"wrote {written[0]}")
    return 0


def _say_units(path: str) -> None:
    """One line: the units of the export (the calibration the run recorded)."""
    from torch_stsdic.io.results import open_results
    from torch_stsdic.io.units import units_of

    with open_results(Path(path)) as f:
        u = units_of(f.attrs)
    scale = f" ({u.scale:g} {u.unit}/px)" if u.scale is not None else " (no --scale in the run)"
    print(f"units: lengths in {u.unit}{scale}, velocities in {u.unit}/{u.time_unit}, "
          "strains dimensionless")


def _say_stereo_units(path: str) -> None:
    """One line: the units of a stereo export."""
    from torch_stsdic.stereo.export import time_unit
    from torch_stsdic.stereo.result import open_stereo

    with open_stereo(path) as f:
        tu = time_unit(f)
        frame = str(f.attrs.get("frame", "left camera")).split(":")[0]
    print(f"units: X, Y, Z, U, V, W in mm ({frame} frame), velocities in mm/{tu}, "
          "reprojection error in px, x, y in left reference px")
