"""``stsdic plot``: field maps at one frame and time histories of a result file, as PNG."""

from __future__ import annotations

import argparse
import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.cli import options
from torch_stsdic.cli.common import check_folder, span
from torch_stsdic.cli.errors import CommandError, UsageError, one_line
from torch_stsdic.cli.stereo_plots import stereo_frame_figures, stereo_shape_figure

NAME = "plot"
HELP = "draw fields over the image and time histories as PNG files"

DESCRIPTION = """\
Draw a result file as PNG files in DIR, in the units the run recorded ('stsdic run
--scale 0.02 --unit mm': lengths in mm; px without a scale):
  fields_frameNNNNN.png    maps of the chosen fields at one frame over the image
  quality_frameNNNNN.png   status of every point and its ZNCC at that frame
  history_mean.png         time history of u, v averaged over the usable points, with
                           how many points each frame's mean rests on (left out, a gap,
                           where fewer than 10 % of the points, or 20, are usable)
  history_xX_yY.png        ... or of the point nearest to (X, Y) with --point
  velocity_history_*.png   the same for ut, vt (STS-DIC results, m >= 1)
  strain_history_*.png     the same for exx, eyy, exy (when the file has strains)
  FIELD_movie.gif          with --animate FIELD: the field over the movie (MP4 with
                           --animate-format mp4 when ffmpeg is installed)
Every colour bar and axis names its quantity and unit. Displacements use a sequential
colour map with robust limits (0.5-99.5 percentiles of the usable points), strains,
gradients and errors a diverging one centred on 0 when their values have both signs (else
the sequential one on their range). Unusable points (status not converged/max-iter, or
ZNCC below --min-zncc) are not drawn: the image shows through. A file whose run has not
finished (stopped, killed, a full disk) says so in every figure's title and in the
summary; its 'last' frame is the last finished one other than the reference.

A stereo result file ('stsdic stereo', recognised from its content) gives, in mm:
  fields_frameNNNNN.png    maps of W (out-of-plane), U, V (or --fields) on the left
                           reference points
  shape_frameNNNNN.png     the 3D points (X, Y, Z) at that frame coloured by W, equal axes
  quality_frameNNNNN.png   status of every point and its reprojection error (px)
  history_mean.png         mean U, V, W over the usable points with how many points each
                           mean rests on (left out as above); history_xX_yY.png with --point
  velocity_history_*.png   the same for Ut, Vt, Wt (m >= 1)
Usable: status converged / max-iter; --image draws the left reference under the maps;
--animate and --min-zncc are for 2-D result files.
"""

EPILOG = """\
examples:
  stsdic plot result.h5 --out plots/                        # last frame, mean history
  stsdic plot result.h5 --frame 5 --fields u,exx --out plots/
  stsdic plot result.h5 --point 150 150 --image movie.tif --out plots/
  stsdic plot result.h5 --animate v --out plots/            # plots/v_movie.gif
  stsdic plot 3d.h5 --out plots/                            # a 'stsdic stereo' file
"""

#: (fields, quantity, file name prefix) of the time-history figures
HISTORIES = (
    (("u", "v"), "displacement", "history"),
    (("ut", "vt"), "velocity", "velocity_history"),
    (("exx", "eyy", "exy"), "strain", "strain_history"),
)

#: the time-history figures of a stereo result file
STEREO_HISTORIES = (
    (("U", "V", "W"), "displacement", "history"),
    (("Ut", "Vt", "Wt"), "velocity", "velocity_history"),
)

#: the fields mapped by default for a stereo result file
STEREO_MAPS = ("W", "U", "V")

#: default of --min-zncc (a stereo file has no ZNCC: any other value is refused there)
MIN_ZNCC = 0.8


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic plot``."""
    p.add_argument("result", metavar="RESULT.h5",
                   help="result file written by 'stsdic run' or 'stsdic stereo'")
    p.add_argument("--out", "-o", required=True, metavar="DIR",
                   help="output directory, created if missing")
    opt = options.add_option
    opt(p, "--frame", default="last", metavar="N|last",
        help="image frame number of the maps, or 'last' finished frame")  # fmt: skip
    opt(p, "--fields", default=None, metavar="LIST",
        help="comma-separated fields to map, e.g. u,v,exx,eyy,exy,ut,vt,zncc,status",
        shown="u,v,exx,eyy,exy, those in the file; stereo: W,U,V")  # fmt: skip
    opt(p, "--image", default=None, metavar="INPUT", help="image series for the background",
        shown="the inputs recorded in the file, if they still exist")  # fmt: skip
    opt(p, "--image-frame", default=None, metavar="N", help="frame of the background series",
        shown="the run's reference frame; stereo: 0")  # fmt: skip
    p.add_argument("--no-image", action="store_true", help="no background image")
    ex = p.add_mutually_exclusive_group()
    ex.add_argument(
        "--point",
        type=options.finite,
        nargs=2,
        default=None,
        metavar=("X", "Y"),
        help="time history of the point nearest to (X, Y) px (refused when that point is "
        "more than 2 grid steps away)",
    )
    ex.add_argument(
        "--mean",
        action="store_true",
        help="time history of the mean over the valid points (the default)",
    )
    opt(p, "--dpi", type=options.int_min(20), default=120, help="PNG resolution")
    p.add_argument("--animate", default=None, metavar="FIELD", help="also write "
                   "FIELD_movie.gif: the field at every frame over the moving images")  # fmt: skip
    opt(p, "--animate-format", choices=("gif", "mp4"), default="gif",
        help="mp4 needs ffmpeg (else a GIF is written)")  # fmt: skip
    opt(p, "--fps", type=options.float_pos, default=4.0, help="frames per second of --animate")
    opt(p, "--min-zncc", type=float, default=MIN_ZNCC, metavar="Z",
        help="hide points whose ZNCC is below Z in the maps, e.g. holes, edges, background",
        shown="%(default)s; -1 shows every converged point")  # fmt: skip


# ----------------------------------------------------------------------------------------
# what to draw: frame, fields, valid points, background
# ----------------------------------------------------------------------------------------


def _row(args: argparse.Namespace, res: Any) -> int:
    """Row of the result file that ``--frame`` names; 'last' is the last finished frame
    other than the reference (whose displacement is zero by definition)."""
    if args.frame == "last":
        done = np.flatnonzero(res.completed)
        if not done.size:
            raise CommandError(f"{args.result}: no finished frame to plot"
                               f"{_continue_hint(res)}")
        refs = _reference_frames(res)
        moved = [r for r in done if int(res.frames[r]) not in refs]
        if not moved and not res.completed.all():
            raise CommandError(
                f"{args.result}: only the reference frame is finished ({incomplete(res)}): "
                f"nothing to map yet{_continue_hint(res)}")
        return int(moved[-1] if moved else done[-1])
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
            f"(frames {span(res.frames.tolist())})"
        )
    return int(hits[0])


def _field_names(args: argparse.Namespace, res: Any,
                 default: tuple[str, ...] = ("u", "v", "exx", "eyy", "exy")) -> list[str]:
    """The fields to map: ``--fields``, checked against the file, or the ``default`` ones
    the file has."""
    if args.fields is None:
        return [f for f in default if f in res.fields]
    names = [s.strip() for s in args.fields.split(",") if s.strip()]
    bad = [s for s in names if s not in res.fields]
    if bad or not names:
        raise UsageError(
            f"--fields {args.fields}: unknown field(s) {', '.join(bad) or '(none)'} "
            f"(the file has {', '.join(res.fields)})"
        )
    return names


def _valid(args: argparse.Namespace, res: Any) -> np.ndarray:
    """(F, N) bool: usable points (converged or max-iter) with ZNCC >= ``--min-zncc``."""
    from torch_stsdic.core.status import usable

    status = res.fields.get("status")
    valid = (
        usable(np.asarray(status))
        if status is not None
        else np.isfinite(res.fields.get("u", np.zeros((res.n_frames, res.n_points))))
    )
    zn = res.fields.get("zncc")
    if zn is not None and args.min_zncc > -1.0:
        valid = valid & (np.nan_to_num(np.asarray(zn), nan=-1.0) >= args.min_zncc)
    return valid


def _reference_frames(res: Any) -> set[int]:
    """The series frames the run's reference is made of (one, or those averaged)."""
    ref = (res.config.get("track") or {}).get("reference", 0)
    try:
        return {int(ref)}
    except (TypeError, ValueError):  # "mean:0,1,2" or "array:..."
        if "mean:" not in str(ref):
            return set()
        return {int(k) for k in str(ref).split(":")[-1].split(",") if k.strip().isdigit()}


def _reference_frame(res: Any, n: int) -> int:
    """The run's reference frame (the first one of an averaged reference), else 0."""
    k = min(_reference_frames(res), default=0)
    return k if 0 <= k < n else 0


def incomplete(res: Any) -> str | None:
    """'incomplete: 3 of 12 frames finished' for a file whose run has not finished (killed,
    stopped, a full disk), else None."""
    done, n = int(np.count_nonzero(res.completed)), len(res.completed)
    return None if done == n else f"incomplete: {done} of {n} frames finished"


def _continue_hint(res: Any) -> str:
    """How to finish an interrupted run."""
    return ("; finish the run with the same 'stsdic run' command and --resume"
            if incomplete(res) else "")


def _background(args: argparse.Namespace, res: Any) -> np.ndarray | None:
    """Background image for the maps, or None."""
    from torch_stsdic.io import parse_frame_spec

    series = _series(args, res)
    if series is None:
        return None
    try:
        if args.image_frame is not None:
            k = parse_frame_spec(args.image_frame, len(series))[0]
        else:
            k = _reference_frame(res, len(series))
        return series.numpy(k)
    except Exception as exc:
        if args.image is not None or args.image_frame is not None:
            raise CommandError(f"--image {args.image}: {one_line(exc)}") from exc
        warnings.warn(f"no background image ({one_line(exc)})", stacklevel=2)
        return None


def _series(args: argparse.Namespace, res: Any) -> Any:
    """The image series of ``--image`` or of the inputs the file records, or None."""
    from torch_stsdic.io import load_series

    if args.no_image:
        return None
    explicit = args.image is not None
    inputs = [args.image] if explicit else list(res.inputs)
    if not inputs or (not explicit and not all(Path(s).exists() for s in inputs)):
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return load_series(inputs[0] if len(inputs) == 1 else inputs)
    except Exception as exc:
        if explicit:
            raise CommandError(f"--image {args.image}: {one_line(exc)}") from exc
        warnings.warn(f"no background image ({one_line(exc)})", stacklevel=2)
        return None


# ----------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------


#: --point farther than this many grid steps from every point is refused
POINT_REACH = 2.0


def _point_spacing(points: np.ndarray) -> float:
    """The points' spacing in px: the grid step (the larger of x and y), else the median
    distance to the nearest neighbour; 1 for a single point."""
    from torch_stsdic.analysis.strain import detect_grid

    grid = detect_grid(points) if len(points) > 1 else None
    if grid is not None and max(grid.nx, grid.ny) > 1:
        return float(max(grid.sx if grid.nx > 1 else 0.0, grid.sy if grid.ny > 1 else 0.0))
    if len(points) < 2:
        return 1.0
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def _nearest_point(args: argparse.Namespace, res: Any) -> int:
    """Index of the point nearest to ``--point X Y``; UsageError when it is more than
    :data:`POINT_REACH` grid steps away (a point outside the measured region)."""
    x, y = args.point
    pts = np.asarray(res.points, dtype=np.float64)
    d2 = (pts[:, 0] - x) ** 2 + (pts[:, 1] - y) ** 2
    k = int(np.argmin(d2))
    dist, step = float(np.sqrt(d2[k])), _point_spacing(pts)
    if dist > POINT_REACH * step:
        lo, hi = pts.min(0), pts.max(0)
        raise UsageError(
            f"--point {x:g} {y:g}: the nearest measured point ({pts[k, 0]:g}, {pts[k, 1]:g}) is "
            f"{dist:.1f} px away, more than {POINT_REACH:g} grid steps ({step:g} px); the "
            f"points span x {lo[0]:g}..{hi[0]:g}, y {lo[1]:g}..{hi[1]:g} px (--point is in px)")
    return k


#: a frame's mean over points is left out (a gap) where it rests on fewer than this share of
#: the file's points or fewer than MIN_POINTS (half the points in a file of fewer than 40)
MIN_SHARE, MIN_POINTS = 0.10, 20


def min_points(n_points: int) -> int:
    """The fewest usable points a frame's mean rests on before it is drawn."""
    return max(1, math.ceil(MIN_SHARE * n_points), min(MIN_POINTS, math.ceil(n_points / 2)))


def _history_pick(args: argparse.Namespace, res: Any, valid: np.ndarray
                  ) -> tuple[Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]], str,
                             str]:
    """(F, N) values -> ((F,) history of ``--point`` or of the mean, (F,) points it rests
    on or None); its title and file tag."""
    if args.point is None:

        def mean(a: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
            vals = np.where(valid, np.asarray(a, dtype=np.float64), np.nan)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return np.nanmean(vals, axis=1), np.isfinite(vals).sum(axis=1)

        return mean, "mean over usable points", "mean"
    k = _nearest_point(args, res)
    px, py = res.points[k]

    def point(a: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return np.where(valid[:, k], np.asarray(a[:, k], dtype=np.float64), np.nan), None

    return point, f"point {k} at ({px:g}, {py:g})", f"x{px:g}_y{py:g}"


def _plot_histories(args: argparse.Namespace, res: Any, valid: np.ndarray, out: Path,
                    groups: tuple[tuple[tuple[str, ...], str, str], ...] = HISTORIES, *,
                    convert: Callable[[str, np.ndarray], np.ndarray] | None = None,
                    label: Callable[[str, str], str] | None = None,
                    time_label: str | None = None) -> tuple[list[Path], list[str]]:
    """The time-history PNGs (``groups``: (fields, quantity, file prefix)) that have data,
    their paths, and what the summary says of the frames left out of the means. ``convert``
    (name, values) -> values in the figure's unit, ``label`` (name, quantity) -> axis label
    and ``time_label``: by default those of the file's calibration (``res.units``)."""
    from torch_stsdic.plot import plot_history

    if convert is None or label is None or time_label is None:
        units = res.units
        convert, label, time_label = units.convert, units.label, units.time_label
    pick, what, tag = _history_pick(args, res, valid)
    done = res.completed.astype(bool)
    need = min_points(res.n_points)
    name, note = Path(args.result).name, incomplete(res)
    written, lines = [], []
    for keys, quantity, prefix in groups:
        curves, counts = {}, None
        for key in (k for k in keys if k in res.fields):
            vals, n = pick(convert(key, res.fields[key]))
            if np.isfinite(vals[done]).any():
                curves[key] = np.where(done, vals, np.nan)
                counts = n if counts is None else np.minimum(counts, n)
        if not curves:
            continue
        path = out / f"{prefix}_{tag}.png"
        title = f"{name}: {what}" + (f" ({note})" if note else "")
        kw = {}
        if counts is not None:
            kw = {"counts": np.where(done, counts, np.nan), "min_count": need,
                  "count_label": f"usable points\n(of {res.n_points})"}
            gone = [int(f) for f, c in zip(res.frames[done], counts[done]) if c < need]
            if gone:
                lines.append(f"{path.name}: frame(s) {span(gone)} left out, the mean there "
                             f"resting on fewer than {need} of {res.n_points} points")
        plot_history(res.times, curves, ylabel=label(next(iter(curves)), quantity),
                     xlabel=time_label, title=title, path=path, dpi=args.dpi, **kw)
        written.append(path)
    return written, lines


def _plot_shared_motion(args: argparse.Namespace, res: Any, out: Path) -> list[Path]:
    """``shared_motion.png`` where the file holds the run's shared motion."""
    from torch_stsdic.plot import plot_shared_motion

    if "shared_motion" not in res.arrays:
        return []
    params, attrs = res.arrays["shared_motion"]

    def value(key: str) -> Any:  # an attribute the writer stored as JSON (None: "null")
        v = attrs.get(key)
        return json.loads(v) if isinstance(v, str) else v
    times = value("times")
    times = np.arange(len(params)) if times is None else np.asarray(times)
    units = res.units
    path = out / "shared_motion.png"
    plot_shared_motion(times, params, applied=bool(attrs.get("applied", True)),
                       velocity_m=value("velocity_m"), smoothed_frames=value("smoothed_frames"),
                       jumps=value("jumps"),
                       title=f"{Path(args.result).name}: shared motion of the specimen",
                       time_label=units.time_label, length_unit=units.unit,
                       scale=units.scale or 1.0, path=path, dpi=args.dpi)
    return [path]


def velocity_note(m_row: np.ndarray, valid_row: np.ndarray) -> str | None:
    """Why a velocity map has holes: the share of usable points measured classically (m = 0:
    no window, so no velocity), or None where every usable point has one."""
    ok = np.asarray(valid_row, dtype=bool)
    if not ok.any():
        return None
    share = 100.0 * float((np.asarray(m_row)[ok] == 0).mean())
    if share == 0.0:
        return None
    pct = f"{share:.0f}" if share >= 1.0 else f"{share:.1f}"
    return f"blank at {pct} %: classical there (no window fits the motion or stays in view)"


def _velocity_notes(res: Any, row: int, valid: np.ndarray, names: list[str]) -> dict[str, str]:
    """Notes for the velocity panels (ut, vt, strain rates) of one row."""
    if "m" not in res.fields:
        return {}
    note = velocity_note(res.fields["m"][row], valid[row])
    rates = [nm for nm in names if nm in ("ut", "vt") or nm.endswith("_rate")]
    return {nm: note for nm in rates} if note else {}


def _calibration(res: Any) -> str:
    """'lengths in mm (0.02 mm/px)' or 'lengths in px' for the figures' titles."""
    u = res.units
    return "lengths in px" if u.scale is None else f"lengths in {u.unit} ({u.scale:g} {u.unit}/px)"


def _flag(res: Any) -> str:
    """A second title line for a file whose run has not finished, else ''."""
    note = incomplete(res)
    return f"\n{note.upper()} (the run was interrupted)" if note else ""


def _when(res: Any, row: int) -> str:
    """'frame 7', or 'frame 7 (t = 0.35 s)' when the times are not frame numbers."""
    units = res.units
    text = f"frame {int(res.frames[row])}"
    if units.time_unit != "frame":
        text += f" (t = {res.times[row]:g} {units.time_unit})"
    return text


def _plot_frame(args: argparse.Namespace, res: Any, row: int, valid: np.ndarray,
                image: np.ndarray | None, out: Path) -> list[Path]:
    """The field maps and the quality map of one row; their paths."""
    from torch_stsdic.plot import plot_fields, plot_status

    frame, units, name = int(res.frames[row]), res.units, Path(args.result).name
    when = _when(res, row)
    written = []
    names = _field_names(args, res)
    if names:
        maps = {}
        for nm in names:
            vals = units.convert(nm, np.asarray(res.fields[nm][row], dtype=np.float64))
            maps[nm] = vals if nm == "status" else np.where(valid[row], vals, np.nan)
        path = out / f"fields_frame{frame:05d}.png"
        plot_fields(image, res.points, maps, path, dpi=args.dpi, units=units,
                    suptitle=f"{name}: {when}, {_calibration(res)}; unusable points not drawn"
                    + _flag(res), notes=_velocity_notes(res, row, valid, names))
        written.append(path)
    if "status" in res.fields:
        from matplotlib.figure import Figure

        from torch_stsdic.plot import panel_extent, panel_layout, plot_field, save_figure

        zn = res.fields.get("zncc")
        w, h = panel_extent(image, res.points)
        n = 2 if zn is not None else 1
        _, _, (fw, fh) = panel_layout(n, w / h, n, height=4.2 if w <= h else 3.2)
        fig = Figure(figsize=(fw + 1.3, fh), layout="constrained")  # + the status names
        axes = fig.subplots(1, 2 if zn is not None else 1, squeeze=False).ravel()
        plot_status(image, res.points, res.fields["status"][row], ax=axes[0],
                    title="status (usable: converged, max_iter)", units=units)  # fmt: skip
        if zn is not None:
            z = np.where(np.isfinite(zn[row]), zn[row], np.nan)
            plot_field(image, res.points, z, ax=axes[1], title="ZNCC", label="ZNCC (-)",
                       vmax=1.0, units=units)  # fmt: skip
        fig.suptitle(f"{name}: quality at {when}{_flag(res)}")
        path = out / f"quality_frame{frame:05d}.png"
        save_figure(fig, path, dpi=args.dpi)
        written.append(path)
    return written


def _animate(args: argparse.Namespace, res: Any, valid: np.ndarray, out: Path) -> Path:
    """``--animate FIELD``: the field over the movie."""
    from torch_stsdic.plot import animate_field, is_diverging

    nm = args.animate
    if nm not in res.fields:
        raise UsageError(f"--animate {nm}: no such field (the file has {', '.join(res.fields)})")
    units = res.units
    rows = np.flatnonzero(res.completed)
    if not rows.size:
        raise CommandError(f"{args.result}: no finished frame to animate")
    series = _series(args, res)
    frames = res.frames[rows]
    if series is not None and int(frames.max()) >= len(series):
        series = None
    vals = np.where(valid[rows], units.convert(nm, res.fields[nm][rows].astype(np.float64)),
                    np.nan)  # fmt: skip
    disp = None
    if "u" in res.fields and "v" in res.fields:
        disp = (res.fields["u"][rows], res.fields["v"][rows])
    return animate_field(
        None if series is None else (lambda k: series.numpy(int(frames[k]))),
        res.points, vals, out / f"{nm}_movie.{args.animate_format}",
        stamps=[_when(res, r) for r in rows], displacement=disp, label=units.label(nm),
        symmetric=is_diverging(nm), title=f"{Path(args.result).name}: {nm} at", fps=args.fps,
        dpi=args.dpi, units=units,
    )  # fmt: skip


def execute(args: argparse.Namespace) -> int:
    """``stsdic plot``: field maps at one frame and time histories as PNG."""
    from torch_stsdic.io import read_results

    p = Path(args.result)
    if not p.exists():
        raise CommandError(f"result file not found: {args.result}")
    if _is_stereo(p):
        return _execute_stereo(args, p)
    res = read_results(p, lazy=True)  # the fields drawn are read, not all of them
    if res.n_frames == 0 or res.n_points == 0:
        raise CommandError(f"{args.result}: the result file holds no frame or no point")
    row = _row(args, res)
    _field_names(args, res)  # a bad --fields is a usage error before anything is written
    if args.animate is not None and args.animate not in res.fields:
        raise UsageError(f"--animate {args.animate}: no such field (the file has "
                         f"{', '.join(res.fields)})")
    out = Path(args.out)
    check_folder(out, f"--out {args.out}")
    if args.point is not None:
        _nearest_point(args, res)  # a point far outside is refused before anything is drawn
    valid = _valid(args, res)
    image = _background(args, res)
    out.mkdir(parents=True, exist_ok=True)
    note = incomplete(res)
    if note:
        print(f"{args.result}: {note} (the run was interrupted){_continue_hint(res)}; the "
              "figures say so")
    written = _plot_frame(args, res, row, valid, image, out)
    paths, lines = _plot_histories(args, res, valid, out)
    written += paths + _plot_shared_motion(args, res, out)
    if args.animate is not None:
        written.append(_animate(args, res, valid, out))
    for path in written:
        print(f"wrote {path}")
    for line in lines:
        print(line)
    return 0


# ----------------------------------------------------------------------------------------
# stereo result files ('stsdic stereo')
# ----------------------------------------------------------------------------------------


def _is_stereo(path: Path) -> bool:
    """Whether ``path`` is a stereo result file (False for anything else: the 2-D reader
    then says what it is)."""
    import h5py

    from torch_stsdic.stereo.result import is_stereo_file

    try:
        with h5py.File(path, "r", locking=False) as f:
            return is_stereo_file(f)
    except OSError:
        return False


class _Stereo:
    """A stereo result file, shaped as the 2-D figures read a file: ``points`` (N, 2) left
    reference px, ``frames``, ``times`` (F,), ``fields`` name -> (F, N) (mm, mm per time
    unit, px, status), every row finished, no reference frame recorded (row 0 is taken)."""

    def __init__(self, path: Path) -> None:
        from torch_stsdic.stereo.export import COLUMNS, stereo_units, time_unit
        from torch_stsdic.stereo.result import PLANE_FRAME, open_stereo

        with open_stereo(path) as f:
            self.points = f["points"][()]
            self.frames = f["frames"][()]
            self.times = f["times"][()]
            names = [c for c in COLUMNS if c not in ("x", "y") and c in f]
            self.fields = {nm: f[nm][()] for nm in names}
            self.unit = stereo_units(f, names)
            self.time_unit = time_unit(f)
            self.plane_frame = f.attrs.get("frame") == PLANE_FRAME
        self.path = path
        self.completed = np.ones(len(self.frames), dtype=bool)
        self.config: dict[str, Any] = {}
        self.inputs: list[str] = []

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def label(self, name: str, quantity: str | None = None) -> str:
        """'W (mm)', 'displacement (mm)', 'status', 'exx' (dimensionless: no unit)."""
        u = self.unit.get(name, "")
        return f"{quantity or name} ({u})" if u and u != "1" else (quantity or name)

    def when(self, row: int) -> str:
        """'frame 7', or 'frame 7 (t = 0.35)' when the times are not frame numbers."""
        text = f"frame {int(self.frames[row])}"
        return text if self.time_unit == "frame" else f"{text} (t = {self.times[row]:g})"


def _execute_stereo(args: argparse.Namespace, path: Path) -> int:
    """``stsdic plot`` of a stereo result file: U, V, W maps, the 3D shape and the status at
    one frame, mean (or --point) histories of U, V, W and Ut, Vt, Wt."""
    from torch_stsdic.core.status import usable

    if args.animate is not None:
        raise UsageError(f"--animate {args.animate}: for 2-D result files ('stsdic run'); "
                         f"{args.result} is a stereo result ('stsdic stereo')")
    if args.min_zncc != MIN_ZNCC:
        raise UsageError(f"--min-zncc: {args.result} is a stereo result, which has no ZNCC "
                         "(points are shown where their status is converged or max-iter)")
    res = _Stereo(path)
    if res.n_frames == 0 or res.n_points == 0:
        raise CommandError(f"{args.result}: the result file holds no frame or no point")
    row = _row(args, res)
    names = _field_names(args, res, STEREO_MAPS)
    out = Path(args.out)
    check_folder(out, f"--out {args.out}")
    if args.point is not None:
        _nearest_point(args, res)
    pos = np.stack([res.fields[k] for k in ("X", "Y", "Z")], -1)
    valid = usable(res.fields["status"]) & np.isfinite(pos).all(-1)
    image = _background(args, res)
    out.mkdir(parents=True, exist_ok=True)
    written = stereo_frame_figures(args, res, row, names, valid, image, out)
    written.append(stereo_shape_figure(args, res, row, valid, out))
    paths, lines = _plot_histories(
        args, res, valid, out, STEREO_HISTORIES, convert=lambda _k, a: np.asarray(a),
        label=res.label, time_label=f"time ({res.time_unit})")
    for p in written + paths:
        print(f"wrote {p}")
    for line in lines:
        print(line)
    return 0
