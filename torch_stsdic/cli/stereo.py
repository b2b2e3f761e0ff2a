"""``stsdic stereo``: stereo STS-DIC of a left and a right image series with a calibration.

A command module (``NAME``, ``HELP``, ``DESCRIPTION``, ``EPILOG``, ``add_arguments(parser)``,
``execute(args) -> int``), registered in ``COMMANDS`` of ``torch_stsdic/cli/app.py``. Errors
are ``ValueError`` / ``OSError`` with one line, which ``stsdic``'s main turns into ``stsdic:
error: ...``. The method is in
:mod:`torch_stsdic.stereo`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from torch_stsdic.cli import options
from torch_stsdic.cli.signals import Interrupted
from torch_stsdic.core.config import DICConfig

NAME = "stereo"
HELP = "3D shape, displacement and velocity from two cameras (stereo STS-DIC)"

DESCRIPTION = """\
Stereo STS-DIC: the left reference points are matched into the right reference along their
epipolar lines (no seed needed), both series are tracked with the same STS-DIC options, and
every frame's pixel pair is triangulated with the calibration (lens distortion removed).

The calibration is read from OpenCV FileStorage YAML/XML, a VIC-3D project XML, a DICe
camera-system XML, JSON/NPZ (this package's keys) or MATLAB stereoParameters (toStruct, .mat
or .json), and converted to one convention: the left camera is the world frame, X_R = R X_L +
T (mm), distortion k1 k2 p1 p2 k3 (OpenCV order), pixel centres at integers, 0-based.

The result file (HDF5) holds points (N, 2 left reference px), right_points, frames, times,
X, Y, Z, U, V, W (F, N; mm), Ut, Vt, Wt (mm per time unit, NaN for --m 0), their *_std
(predicted), reprojection_error (px), status, X0 (N, 3 reference shape), each with a units
attribute, and the calibration summary.
"""

EPILOG = """\
examples:
  stsdic stereo --left 'cam0/*.tif' --right 'cam1/*.tif' --calibration cal.xml --out 3d.h5
  stsdic stereo --left L.tif --right R.tif --calibration stereo.yml --m 2 --subset 25 \\
      --step 20 --roi 100 100 900 700 --refine-reference --out 3d.h5
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--left", nargs="+", required=True, metavar="L",
                   help="left series: a TIFF stack, a folder, a glob or files in time order")
    p.add_argument("--right", nargs="+", required=True, metavar="R",
                   help="right series, frame k taken with left frame k")
    p.add_argument("--calibration", required=True, metavar="FILE",
                   help="stereo calibration (OpenCV YAML/XML, VIC-3D XML, DICe XML, JSON, "
                        "NPZ, MATLAB .mat/.json)")
    p.add_argument("--out", required=True, metavar="FILE.h5", help="result file (HDF5)")
    options.add_option(p, "--m", type=int, default=2,
                       help="window half-width: 2m+1 frames per solve (0 = classical DIC)")
    options.add_option(p, "--subset", type=int, default=21, help="subset size px (odd)")
    options.add_option(p, "--step", type=int, default=10, help="grid spacing px")
    p.add_argument("--roi", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="region of the left reference, px inclusive")
    options.add_option(p, "--reference", default="0",
                       help="reference frame or frame spec of both series, e.g. 0 or 0:5 (mean)")
    p.add_argument("--refine-reference", action="store_true",
                   help="remove the noisy reference's offset (as in 'stsdic run')")
    options.add_option(p, "--cross-shape", choices=("affine", "quadratic"), default="affine",
                       help="subset warp of the left -> right match")
    options.add_option(p, "--max-reprojection", type=float, default=1.0,
                       help="px; points beyond are flagged INCONSISTENT")
    options.add_option(p, "--coordinates", choices=("camera", "plane"), default="camera",
                       help="frame of X..W in the file: the left camera's, or the best-fit "
                       "plane of the reference shape (X, Y in the plane, Z its normal; the "
                       "plane's origin and rotation are stored)")
    options.add_option(p, "--device", default="cpu", help="torch device")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run: the frames its two cameras finished "
                   "(in <out>.left.h5, <out>.right.h5, written as the run goes and removed "
                   "once --out is written) are kept")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _series(items: list[str]):
    return items[0] if len(items) == 1 else list(items)


def execute(args: argparse.Namespace) -> int:
    from torch_stsdic.stereo.calibration import load_calibration
    from torch_stsdic.stereo.run import work_files, write_stereo

    if os.path.exists(args.out) and not args.overwrite:
        raise ValueError(f"--out: {args.out} exists (use --overwrite to replace it)"
                         + (": that run is complete" if args.resume else ""))
    if args.subset < 3 or args.subset % 2 == 0:
        raise ValueError(f"--subset must be an odd number >= 3, got {args.subset}")
    if args.m < 0:
        raise ValueError(f"--m must be >= 0, got {args.m}")
    if args.step < 1:
        raise ValueError(f"--step must be >= 1, got {args.step}")
    rig = load_calibration(args.calibration)
    print(rig.describe(), file=sys.stderr)
    ref = int(args.reference) if args.reference.lstrip("-").isdigit() else args.reference
    t0 = time.perf_counter()
    try:
        info = _track(args, rig, ref, write_stereo)
    except KeyboardInterrupt as exc:  # say what the cameras' files keep
        stop = exc if isinstance(exc, Interrupted) else Interrupted()
        raise stop.with_detail(_kept(args.out, work_files)) from None
    for f in work_files(args.out):  # the cameras' files: the result now holds what they did
        f.unlink(missing_ok=True)
    print(f"stereo: {info['points']} points x {info['frames']} frames, "
          f"{int(info['cross_ok'])} matched left -> right, {info['usable']:.1%} "
          f"usable, reference reprojection {info['reference_reprojection_px']:.3f} px "
          f"(median), {time.perf_counter() - t0:.1f} s -> {args.out}", file=sys.stderr)
    return 0


def _track(args: argparse.Namespace, rig, ref, write_stereo):
    """The stereo run of the command's options into ``--out`` (its cameras' files beside it;
    the 3-D stage a few frames at a time: :func:`~torch_stsdic.stereo.run.write_stereo`)."""
    return write_stereo(args.out, _series(args.left), _series(args.right), rig,
                        coordinates=args.coordinates, overwrite=args.overwrite,
                        roi=args.roi, step=args.step,
                        config=DICConfig(subset_size=args.subset, m=args.m),
                        reference=ref, device=args.device, progress=not args.no_progress,
                        cross_shape=args.cross_shape, max_reprojection=args.max_reprojection,
                        refine_reference=args.refine_reference, work=args.out,
                        resume=args.resume)


def _kept(out: str, work_files) -> str:
    """What an interrupted run keeps: the finished frames of each camera's file."""
    import h5py

    parts = []
    for name, f in zip(("left", "right"), work_files(out)):
        done = 0
        if f.exists():
            try:
                with h5py.File(f, "r", locking=False) as h:
                    done = int(h["completed"][()].sum()) if "completed" in h else 0
            except OSError:
                done = 0
        parts.append(f"{name} camera {done} frame(s) in {f.name}")
    return ", ".join(parts) + "; continue with the same command and --resume"
