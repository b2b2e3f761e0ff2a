"""``stsdic synth``: a synthetic speckle movie with exactly known motion, and its ground truth."""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.cli import options
from torch_stsdic.cli.common import check_folder, fmt_time, to_numpy
from torch_stsdic.cli.errors import CommandError, UsageError

NAME = "synth"
HELP = "write a synthetic speckle movie with exactly known motion"

MOTIONS = ("translation", "strain", "sinusoidal", "quadratic", "jump")

DESCRIPTION = """\
Write a synthetic speckle movie with exactly known motion (analytic rendering with
pixel-area integration; no interpolation), and its ground truth.

Frame 0 is the reference (t = 0, no motion); frames 1..N are at t = 1..N. Gaussian
noise (sigma in 8-bit grey levels) is added to every frame, then the images are
quantised to --bits (16 bits: the 8-bit scale times 257; 0: float32, no quantisation).

Files in DIR: movie.tif (multi-page TIFF) or frame_00000.tif ... (--layout files), or
a camera movie (--format mraw: movie.mraw + movie.cih, Photron; --format avi: movie.avi,
lossless FFV1) whose frame rate --fps makes the run's times k/fps s;
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

EPILOG = """\
examples:
  stsdic synth --out movie                                 # the paper's movie: u = t/20, noise 5
  stsdic synth --out movie --motion strain --exx 0.002 --noise 2 --bits 16
  stsdic synth --out movie --motion jump --x0 150 --du 0.5 --layout files
  stsdic synth --out small --size 81 --frames 8 --noise 0 --seed 3
  stsdic synth --out cam --format mraw --bits 12 --fps 5000   # a Photron movie (pyMRAW's layout)
"""

#: the motion parameters: option, unit (metavar), type, default, help
MOTION_PARAMETERS: tuple[tuple[str, str, Any, float | None, str], ...] = (
    ("--u0", "PX", options.finite, 0.0, "translation: u at t=0 (default: 0)"),
    ("--v0", "PX", options.finite, 0.0, "translation: v at t=0 (default: 0)"),
    ("--ut", "PX/FR", options.finite, 0.05, "translation: du/dt, px/frame (default: 0.05)"),
    ("--vt", "PX/FR", options.finite, 0.0, "translation: dv/dt (default: 0)"),
    ("--exx", "1/FR", options.finite, 0.002, "strain: exx per frame (default: 0.002)"),
    ("--eyy", "1/FR", options.finite, 0.0, "strain: eyy per frame (default: 0)"),
    ("--exy", "1/FR", options.finite, 0.0, "strain: tensor shear per frame (default: 0)"),
    ("--omega", "RAD/FR", options.finite, 0.0, "strain: rotation per frame, rad (default: 0)"),
    ("--amplitude-u", "PX", options.finite, 0.5, "sinusoidal: u amplitude (default: 0.5)"),
    ("--amplitude-v", "PX", options.finite, 0.0, "sinusoidal: v amplitude (default: 0)"),
    ("--wavelength", "PX", options.float_pos, 64.0, "sinusoidal: px (default: 64)"),
    ("--rate", "1/FR", options.finite, 0.1,
     "sinusoidal: amplitude factor per frame, rate*t (default: 0.1)"),
    ("--au", "PX/FR", options.finite, 0.05, "quadratic: px/frame (default: 0.05)"),
    ("--bu", "PX/FR2", options.finite, 0.005, "quadratic: px/frame^2 (default: 0.005)"),
    ("--av", "PX/FR", options.finite, 0.0, "quadratic: px/frame (default: 0)"),
    ("--bv", "PX/FR2", options.finite, 0.0, "quadratic: px/frame^2 (default: 0)"),
    ("--x0", "PX", options.finite, None, "jump: crack line x = X0 (default: centre)"),
    ("--du", "PX", options.finite, 0.5, "jump: u jump in px (default: 0.5)"),
    ("--dv", "PX", options.finite, 0.0, "jump: v jump in px (default: 0)"),
    ("--t-jump", "T", options.finite, None,
     "jump: time of the jump (default: the middle frame, N//2 + 1)"),
)  # fmt: skip

#: the ground-truth columns after frame, time, x, y
TRUTH_KEYS = ("u", "v", "ut", "vt", "dudx", "dudy", "dvdx", "dvdy")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic synth``."""
    opt = options.add_option
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    opt(p, "--size", type=options.int_min(16), nargs="+", default=[301], metavar="PX",
        help="image size: N (square) or W H, px", shown="301")  # fmt: skip
    opt(p, "--frames", type=options.int_min(1), default=9, metavar="N",
        help="deformed frames after the reference (t = 1..N)")  # fmt: skip
    opt(p, "--motion", choices=MOTIONS, default="translation", help="motion type, see above")
    options.add_speckle(p)
    opt(p, "--bits", type=int, choices=(0, 8, 10, 12, 14, 16), default=8,
        help="quantisation: 8 -> uint8, 10..16 -> uint16, 0 -> float32")  # fmt: skip
    opt(p, "--radius", type=options.float_pos, default=2.0, metavar="PX",
        help="mean speckle spot radius (Gaussian std) in px")  # fmt: skip
    opt(p, "--layout", choices=("multipage", "files"), default="multipage",
        help="one multi-page TIFF (movie.tif) or one TIFF per frame")  # fmt: skip
    opt(p, "--format", choices=("tiff", "mraw", "avi"), default="tiff",
        help="tiff (see --layout), mraw (Photron movie.mraw + movie.cih, 8 or 16-bit words) "
        "or avi (lossless FFV1; needs PyAV, the cameras extra)")  # fmt: skip
    opt(p, "--fps", type=options.float_pos, default=1000.0, metavar="RATE",
        help="mraw/avi: the frame rate written in the movie's header, frames/s")  # fmt: skip
    opt(p, "--truth-step", type=options.int_min(1), default=10, metavar="PX",
        help="grid spacing of the ground-truth points in truth.csv")  # fmt: skip
    p.add_argument("--overwrite", action="store_true", help="replace existing files in DIR")
    options.add_threads(p)
    g = p.add_argument_group("motion parameters (t in frames, lengths in px)")
    for flag, unit, kind, default, text in MOTION_PARAMETERS:
        g.add_argument(flag, metavar=unit, type=kind, default=default, help=text)
    opt(g, "--axis", choices=("x", "y"), default="x", help="sinusoidal: varies along")


# ----------------------------------------------------------------------------------------
# the motion
# ----------------------------------------------------------------------------------------


def _make_motion(args: argparse.Namespace, w: int, h: int, n_frames: int) -> tuple[Any, dict]:
    """The ``synth`` motion that ``--motion`` names, and its parameters (for motion.json)."""
    from torch_stsdic import synth

    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    kind = args.motion
    if kind == "translation":
        params = {"u0": args.u0, "v0": args.v0, "ut": args.ut, "vt": args.vt}
        return synth.Translation(**params), params
    if kind == "strain":
        params = {"exx": args.exx, "eyy": args.eyy, "exy": args.exy, "omega": args.omega}
        motion = synth.HomogeneousStrain(**params, center=(cx, cy), rate=1.0)
        return motion, {**params, "center": [cx, cy], "rate": 1.0}
    if kind == "sinusoidal":
        params = {
            "amplitude_u": args.amplitude_u, "amplitude_v": args.amplitude_v,
            "wavelength": args.wavelength, "axis": args.axis, "rate": args.rate,
        }  # fmt: skip
        return synth.Sinusoidal(**params), params
    if kind == "quadratic":
        params = {"au": args.au, "bu": args.bu, "av": args.av, "bv": args.bv}
        return synth.QuadraticInTime(**params), params
    x0 = cx if args.x0 is None else args.x0
    tj = float(n_frames // 2 + 1) if args.t_jump is None else args.t_jump
    params = {"x0": x0, "du": args.du, "dv": args.dv, "t_jump": tj}
    return synth.Jump(**params), params


def _max_border_motion(motion: Any, w: int, h: int, times: np.ndarray) -> float:
    """Largest displacement (px) of the image border over ``times``."""
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


# ----------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------


def _image_files(layout: str, n: int, fmt: str = "tiff") -> list[str]:
    if fmt == "mraw":
        return ["movie.cih", "movie.mraw"]
    if fmt == "avi":
        return ["movie.avi"]
    return ["movie.tif"] if layout == "multipage" else [f"frame_{k:05d}.tif" for k in range(n)]


def _write_movie(out: Path, files: list[str], images: Iterable[np.ndarray], fmt: str,
                 fps: float) -> None:
    """The frames ``images`` (each (H, W), written as they come) as the camera movie
    ``files`` (``fmt`` "mraw" or "avi")."""
    from torch_stsdic.io.photron import write_mraw
    from torch_stsdic.io.video import write_video

    if fmt == "mraw":
        write_mraw(out / files[1], images, fps)
    else:
        tmp = out / "movie.partial.avi"
        write_video(tmp, images, fps)
        os.replace(tmp, out / files[0])


def _check_targets(out: Path, images: list[str], overwrite: bool) -> None:
    """CommandError if ``out`` is a file, or (without ``overwrite``) a file would be replaced."""
    if out.exists() and not out.is_dir():
        raise CommandError(f"--out {out}: exists and is not a directory")
    targets = [out / f for f in (*images, "truth.csv", "motion.json", "times.csv")]
    existing = [t for t in targets if t.exists()]
    if existing and not overwrite:
        raise CommandError(
            f"{existing[0]} exists ({len(existing)} file(s) would be replaced): "
            "use --overwrite or another --out"
        )


def _write_tiff_atomic(path: Path, data: np.ndarray) -> None:
    import tifffile

    tmp = path.with_name(path.name + ".partial")
    tifffile.imwrite(tmp, data, photometric="minisblack")
    os.replace(tmp, path)


def _write_multipage(path: Path, images: Iterable[np.ndarray]) -> None:
    """The frames ``images`` (each (H, W)) as one multi-page TIFF, page by page as they come
    (one series of shape (T, H, W), as ``tifffile.imwrite`` of the whole stack stores it)."""
    import tifffile

    tmp = path.with_name(path.name + ".partial")
    with tifffile.TiffWriter(tmp) as tw:
        for img in images:
            tw.write(img, photometric="minisblack", contiguous=True)
    os.replace(tmp, path)


def _to_dtype(img: Any, bits: int) -> np.ndarray:
    """Images quantised to ``bits`` (uint8 / uint16), or float32 for ``bits`` 0."""
    from torch_stsdic.synth import quantize

    if bits == 0:
        return to_numpy(img).astype(np.float32)
    q = to_numpy(quantize(img, bits))
    return q.astype(np.uint8 if bits == 8 else np.uint16)


#: (frame, point) entries of the ground truth computed at a time (truth.csv is written frame
#: chunk by frame chunk: a long movie's truth is never held whole)
TRUTH_CHUNK = 1 << 16


def _write_truth(path: Path, motion: Any, pts: np.ndarray, times: np.ndarray
                 ) -> tuple[float, float]:
    """truth.csv at ``pts`` (N, 2) px and ``times`` (F,), a few frames at a time; returns
    the largest |u| and |v| px."""
    from torch_stsdic.synth import ground_truth

    step = max(1, TRUTH_CHUNK // max(len(pts), 1))
    umax = vmax = 0.0
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("frame,time,x,y," + ",".join(TRUTH_KEYS) + "\n")
        for f0 in range(0, len(times), step):
            truth = ground_truth(motion, pts, times[f0:f0 + step])
            tr = {k: to_numpy(truth[k]) for k in TRUTH_KEYS}
            umax = max(umax, float(np.abs(tr["u"]).max(initial=0.0)))
            vmax = max(vmax, float(np.abs(tr["v"]).max(initial=0.0)))
            lines = []
            for i in range(tr["u"].shape[0]):
                f = f0 + i
                for j in range(len(pts)):
                    vals = ",".join(f"{tr[k][i, j]:.10g}" for k in TRUTH_KEYS)
                    lines.append(f"{f},{times[f]:g},{pts[j, 0]:g},{pts[j, 1]:g},{vals}\n")
            fh.write("".join(lines))
    return umax, vmax


def _metadata(args: argparse.Namespace, motion: Any, params: dict, extra: dict) -> dict:
    """The contents of motion.json: the motion, every setting and the files."""
    return {
        "generator": "torch_stsdic synth",
        "motion": {
            "type": args.motion,
            "class": type(motion).__name__,
            "params": params,
            "repr": repr(motion),
        },
        "size": extra["size"],
        "frames": extra["frames"],
        "reference_frame": 0,
        "times": extra["times"],
        "noise_sigma": args.noise,
        "noise_scale": "8-bit grey levels",
        "bits": args.bits,
        "dtype": extra["dtype"],
        "seed": args.seed,
        "speckle_radius": args.radius,
        "pattern_margin": extra["margin"],
        "layout": args.layout,
        "format": args.format,
        "fps": args.fps if args.format != "tiff" else None,
        "files": extra["files"],
        "truth": {
            "file": "truth.csv",
            "grid_step": args.truth_step,
            "points": extra["points"],
            "columns": ["frame", "time", "x", "y", *TRUTH_KEYS],
            "units": "px, px per frame, px/px; u along x (columns), v along y (rows)",
            "convention": "Lagrangian: displacement of reference-image point (x, y) at time t",
        },
        "conventions": "x = column, y = row, pixel centres at integers, 0-based",
    }


# ----------------------------------------------------------------------------------------
# the command
# ----------------------------------------------------------------------------------------


def execute(args: argparse.Namespace) -> int:
    """``stsdic synth``: synthetic speckle movie + ground truth."""
    from torch_stsdic import synth

    if len(args.size) > 2:
        raise UsageError(f"--size: give N or W H, got {len(args.size)} values")
    w, h = args.size if len(args.size) == 2 else args.size * 2
    n = args.frames
    out = Path(args.out)
    check_folder(out, f"--out {args.out}")
    if args.format != "tiff" and args.bits == 0:
        raise UsageError(f"--format {args.format} stores integer grey levels: give --bits 8 to "
                         "16 (float frames: --format tiff)")
    files = _image_files(args.layout, n + 1, args.format)
    _check_targets(out, files, args.overwrite)
    times = np.arange(0, n + 1, dtype=np.float64)
    motion, params = _make_motion(args, w, h, n)
    margin = max(16.0, 8.0 * args.radius) + math.ceil(_max_border_motion(motion, w, h, times))
    t0 = time.perf_counter()
    # the reference and every frame rendered, quantised and written one at a time: a long
    # movie is never held whole (2,001 frames of 512 x 512 took 23 GB as one stack)
    _, _, rendered = synth.synthetic_images(
        (h, w), n, motion, noise_sigma=args.noise, seed=args.seed, radius=args.radius,
        margin=margin,
    )  # fmt: skip
    images = (_to_dtype(img, args.bits) for img in rendered)
    out.mkdir(parents=True, exist_ok=True)
    if args.format != "tiff":
        from torch_stsdic.io import InputError

        try:
            _write_movie(out, files, images, args.format, args.fps)
        except (InputError, ValueError) as exc:  # PyAV missing, a rate AVI cannot store
            raise CommandError(str(exc)) from None
    elif args.layout == "multipage":
        _write_multipage(out / files[0], images)
    else:
        for name, img in zip(files, images):
            _write_tiff_atomic(out / name, img)

    # ground truth on a grid
    xs = np.arange(0, w, args.truth_step, dtype=np.float64)
    ys = np.arange(0, h, args.truth_step, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    umax, vmax = _write_truth(out / "truth.csv", motion, pts, times)
    (out / "times.csv").write_text(
        "frame,time\n" + "".join(f"{k},{t:g}\n" for k, t in enumerate(times)), encoding="utf-8"
    )
    dtype = {0: "float32", 8: "uint8"}.get(args.bits, "uint16")
    extra = {"size": {"width": w, "height": h}, "frames": n + 1, "times": times.tolist(),
             "dtype": dtype, "margin": margin, "files": files, "points": int(len(pts))}  # fmt: skip
    meta = _metadata(args, motion, params, extra)
    (out / "motion.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    el = time.perf_counter() - t0
    print(
        f"wrote {n + 1} frames of {w}x{h} px ({dtype}, noise {args.noise:g}) to "
        f"{out / files[0]}{' ..' if len(files) > 1 else ''} in {fmt_time(el)}"
    )
    print(f"motion: {motion!r}; max |u| {umax:.3g} px, max |v| {vmax:.3g} px on the truth grid")
    print(f"ground truth: {out / 'truth.csv'} ({len(pts)} points x {n + 1} frames), "
          f"{out / 'motion.json'}")  # fmt: skip
    return 0
