"""``stsdic run``: track points through an image series, write HDF5, add strains, summarise."""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.cli import options
from torch_stsdic.cli.common import check_device, check_folder
from torch_stsdic.cli.errors import CommandError, UsageError, one_line
from torch_stsdic.cli.run_summary import print_summary
from torch_stsdic.cli.signals import Interrupted, checkpoint

NAME = "run"
HELP = "measure displacement, velocity and strain in an image series -> HDF5"

DESCRIPTION = """\
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
3 outside, 4 low texture, 5 not computed, 6 poor fit, 7 inconsistent: only 0 and 1 are
used), m (the window half-width each result used: shorter where the motion is not
affine in time, 0 = classical), u_std, v_std, ut_std, vt_std (predicted standard
deviations), exx, eyy, exy [-]; see 'stsdic export'.
--scale 0.02 --unit mm records a calibration with them (the datasets stay in px):
'stsdic export' and 'stsdic plot' then give lengths in mm and velocities in mm per
time unit (--time-unit, e.g. s with --timestamps).
"""

EPILOG = """\
examples:
  stsdic run movie.tif --out result.h5                      # defaults: subset 21, m 2, step 10
  stsdic run frames/ --m 0 --out classical.h5               # classical DIC, frame by frame
  stsdic run 'img_*.tif' --roi 50 50 450 300 --step 5 --out r.h5
  stsdic run movie.tif --reference 0:5 --frames 5: --out r.h5   # averaged reference
  stsdic run movie.tif --points poi.csv --timestamps times.csv --out r.h5
  stsdic run movie.tif --out r.h5 --resume                  # continue a killed run
  stsdic run movie.tif --device cuda --dtype float32 --out r.h5
  stsdic run movie.tif --scale 0.02 --unit mm --timestamps t.csv --time-unit s --out r.h5
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic run``."""
    opt = options.add_option
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image series (see above)")
    p.add_argument(
        "--out", "-o", required=True, metavar="FILE.h5",
        help="result file (HDF5), required; missing folders are created"
    )
    _add_frames(p)
    options.add_points(p)
    options.add_solver(p)
    g = p.add_argument_group("strain")
    opt(g, "--strain-window", type=options.odd_int(3), default=5, metavar="N",
        help="plane fit over N x N grid points (odd)")  # fmt: skip
    opt(g, "--strain-kind", choices=("green", "small"), default="green",
        help="green: Green-Lagrange; small: infinitesimal strain")  # fmt: skip
    options.add_calibration(p.add_argument_group("calibration"))
    g = p.add_argument_group("computation and output")
    opt(g, "--dtype", choices=("float32", "float64"), default=None,
        help="computation precision",
        shown="float32 for integer images, else the image's")  # fmt: skip
    opt(g, "--no-checks", dest="checks", action="store_false", default=True,
        help="skip the trust checks (window against classical, fit, neighbours): every "
        "converged point is reported as such, as before the checks existed; faster",
        shown="checks on")  # fmt: skip
    ex = g.add_mutually_exclusive_group()
    ex.add_argument("--resume", action="store_true", help="continue the run that wrote --out "
                    "(same inputs and options); finished frames are kept")  # fmt: skip
    ex.add_argument("--overwrite", action="store_true", help="replace an existing --out (the "
                    "old file stays intact until the new run ends)")  # fmt: skip
    options.add_compute(g)
    _add_distributed(p)


def _add_distributed(p: argparse.ArgumentParser) -> None:
    """The 'beyond one machine' group: the run in frame chunks on Dask workers."""
    opt = options.add_option
    g = p.add_argument_group(
        "beyond one machine", "the targets in chunks of --chunk-frames, each on a Dask worker "
        "(pip install torch_stsdic[dist]); the shared motion, load steps and reference are "
        "measured once for the whole series, so the result equals the one-process run's to "
        "within --tol; not with --reference-update")
    ex = g.add_mutually_exclusive_group()
    opt(ex, "--workers", type=options.int_min(1), default=None, metavar="N",
        help="a local Dask cluster of N worker processes", shown="one process, no Dask")
    opt(ex, "--scheduler", default=None, metavar="ADDRESS",
        help="an existing Dask cluster: its scheduler's address (tcp://host:8786) or "
        "scheduler file (scheduler.json); the workers must see INPUT",
        shown="none")  # fmt: skip
    opt(g, "--chunk-frames", type=options.int_min(1), default=None, metavar="N",
        help="target frames per task, rounded up to whole blocks of the run (each chunk but "
        "the first also solves the 2 targets before it; docs/benchmarks.md sizes it)",
        shown="50")  # fmt: skip


def _runner(args: argparse.Namespace) -> Any:
    """``run_plan``, or its distributed twin with --workers/--scheduler (checked here)."""
    from torch_stsdic.movie.series import run_plan

    if args.workers is None and args.scheduler is None:
        if args.chunk_frames is not None:
            raise UsageError("--chunk-frames: only with --workers or --scheduler")
        return run_plan
    flag = "--workers" if args.workers is not None else "--scheduler"
    if args.reference_update is not None:
        raise UsageError(f"--reference-update: not with {flag} (the incremental reference "
                         "chains every frame to the previous ones)")
    from torch_stsdic.movie.distributed import DASK_HINT, run_plan_distributed

    try:
        import distributed  # noqa: F401
    except ImportError:
        raise UsageError(f"{flag} needs Dask distributed, which is not installed: "
                         f"{DASK_HINT}") from None

    def run(plan: Any, sink: Any, **kw: Any) -> Any:
        return run_plan_distributed(plan, sink, chunk_frames=args.chunk_frames or 50,
                                    client=args.scheduler, n_workers=args.workers or 1, **kw)

    return run


def _add_frames(p: argparse.ArgumentParser) -> None:
    """The 'frames and reference' group."""
    opt = options.add_option
    g = p.add_argument_group("frames and reference")
    g.add_argument(
        "--reference",
        default="0",
        metavar="SPEC",
        help="reference frame, or several frames averaged into the reference, e.g. 0:5 "
        "(frame numbers of the series, 0-based; default: %(default)s)",
    )
    opt(g, "--frames", default=None, metavar="SPEC", help="output frames: an index, slices "
        "and lists such as 5, -1, 10:100:2, 0:5,9, all", shown="every frame")  # fmt: skip
    opt(g, "--timestamps", default=None, metavar="FILE",
        help="frame times, one per frame (text/CSV: one number a line, or a column named "
        "'time'); velocities are then per this time unit", shown="0, 1, 2, ...")  # fmt: skip
    opt(g, "--reference-update", type=options.unit_open, default=None, metavar="THRESH",
        help="take a new reference (incremental DIC) when the mean ZNCC falls below THRESH, "
        "e.g. 0.9", shown="never, one fixed reference")  # fmt: skip
    g.add_argument(
        "--refine-reference",
        action="store_true",
        help="the template's zero displacement from the trajectories: classical DIC of the "
        "frames around the reference against it, a fit in time per point, its value at the "
        "reference time subtracted; pays on long smooth movies (docs/accuracy.md)",
    )
    opt(g, "--refine-frames", type=options.int_min(5), default=None, metavar="N",
        help="most frames of that fit",
        shown="41; fewer where the motion is not smooth")  # fmt: skip
    ref_mode = g.add_mutually_exclusive_group()
    rounds = options.int_min(1)
    opt(ref_mode, "--series-reference", type=lambda s: s if s == "auto" else rounds(s),
        nargs="?", const=2,
        default="auto", metavar="ROUNDS", help="measure against a template made from the "
        "series: up to --series-frames frames mapped back with their measured subset warps "
        "(smoothed by local planes) and averaged, ROUNDS rounds of template and classical "
        "measurement (2 without a number), zero displacement fixed by the reference frame's "
        "own measurement; less reference noise at the cost of a classical run of those frames "
        "per round (docs/validation/series_reference.md)",
        shown="on, 2 rounds, where the reference is one frame of the series and not "
        "updated")  # fmt: skip
    ref_mode.add_argument("--single-reference", action="store_true",
                          help="measure against the reference image alone (classical DIC's "
                          "baseline; the template's noise gain is lost)")
    opt(g, "--series-frames", type=options.int_min(2), default=None, metavar="N",
        help="most frames of the template, evenly spread", shown="21")  # fmt: skip
    g.add_argument("--keep-background", action="store_true",
                   help="keep the default grid's points whose subsets are not on speckle in the "
                   "reference image (background, holes, featureless or saturated areas: left "
                   "out by default)")
    opt(g, "--shared-motion", choices=("auto", "quadratic", "affine", "translation", "none"),
        default="auto", help="the specimen's per-frame motion (a shake, load steps), "
        "measured from all points and carried in every window; auto: with --m > 0, "
        "quadratic (affine under 500 points), carried where the shake is significant or "
        "the motion bends over the windows (docs/series.md)")  # fmt: skip


# ----------------------------------------------------------------------------------------
# inputs: every check before any output file is opened
# ----------------------------------------------------------------------------------------


def _open_series(inputs: Sequence[str], timestamps: np.ndarray | None,
                 times_file: str | None = None) -> Any:
    from torch_stsdic.io import InputError, load_series

    src: Any = inputs[0] if len(inputs) == 1 else list(inputs)
    try:
        return load_series(src, timestamps=timestamps)
    except InputError as exc:
        if timestamps is None or "timestamps" not in str(exc):
            raise
        n = len(load_series(src))  # the series itself opens: the times do not fit it
        if len(timestamps) != n:  # an option that does not fit the input: usage error
            raise UsageError(f"--timestamps {times_file}: {len(timestamps)} time(s) for the "
                             f"{n} frames of the series (one per frame)") from None
        raise CommandError(f"--timestamps {times_file}: {exc}") from exc


def _frame_spec(option: str, spec: str, n: int) -> list[int]:
    """Frame numbers of ``spec`` in a series of ``n`` frames; UsageError naming ``option``.
    A --reference range is not clipped to the series (it would average fewer frames)."""
    from torch_stsdic.io import InputError, parse_frame_spec
    from torch_stsdic.movie.plan import reference_frames

    try:
        return (reference_frames if option == "--reference" else parse_frame_spec)(spec, n)
    except InputError as exc:
        raise UsageError(f"{option} {spec}: {exc}") from None


def _side_file(read: Any, option: str, path: str, *args: Any) -> Any:
    """``read(path, *args, option)``; a file that does not fit the images (a mask of
    another size, points outside them) is a usage error, exit code 2."""
    from torch_stsdic.io.tables import MismatchError

    try:
        return read(path, *args, option)
    except MismatchError as exc:
        raise UsageError(str(exc)) from None


def _roi(args: argparse.Namespace, w: int, h: int, name: str) -> tuple[int, int, int, int] | None:
    if args.roi is None:
        return None
    x0, y0, x1, y1 = args.roi
    if not (0 <= x0 < x1 <= w - 1 and 0 <= y0 < y1 <= h - 1):
        raise UsageError(
            f"--roi {x0} {y0} {x1} {y1} is not inside the {w}x{h} (WxH) image of {name}: "
            f"need 0 <= X0 < X1 <= {w - 1} and 0 <= Y0 < Y1 <= {h - 1}"
        )
    return (x0, y0, x1, y1)


def _config(args: argparse.Namespace) -> Any:
    from torch_stsdic.core.config import DICConfig

    try:
        return DICConfig(
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


def _track_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """Open and check every input; the keyword arguments of ``track`` (output excluded)."""
    from torch_stsdic.io import read_mask, read_points, read_timestamps

    times = read_timestamps(args.timestamps, "--timestamps") if args.timestamps else None
    series = _open_series(args.inputs, times, args.timestamps)
    name = args.inputs[0] if len(args.inputs) == 1 else f"{args.inputs[0]} .. {args.inputs[-1]}"
    h, w = series.shape
    n = len(series)
    if args.subset > min(h, w):
        raise UsageError(
            f"--subset {args.subset} is larger than the images of {name} ({w}x{h} px, WxH)"
        )
    if n < 2:
        raise UsageError(
            f"{name} holds {n} frame: a run needs a reference and at least one more frame "
            "(give a folder, a glob, several files or a multi-page TIFF)"
        )
    if args.m is None and args.reference_update is not None:
        args.m = 2  # windows are chosen for one reference configuration: the fixed default
    args.window_length = "auto" if args.m is None else "fixed"
    if args.m is None:  # the longest window tried: up to 6, as the movie allows
        from torch_stsdic.movie.window_length import auto_max_m

        args.m = auto_max_m(n)
    if n < 2 * args.m + 1:
        raise UsageError(
            f"--m {args.m} needs at least 2m+1 = {2 * args.m + 1} frames, but {name} has "
            f"{n} frame(s)"
        )
    frames = None if args.frames is None else _frame_spec("--frames", args.frames, n)
    refs = _frame_spec("--reference", args.reference, n)
    kwargs = {
        "series": series,
        "reference": refs[0] if len(refs) == 1 else args.reference,
        "frames": frames,
        "roi": _roi(args, w, h, name),
        "mask": _side_file(read_mask, "--mask", args.mask, (h, w)) if args.mask else None,
        "points": (_side_file(read_points, "--points", args.points, (h, w)) if args.points
                   else None),
        "config": _config(args),
    }
    # float images: NaN/inf anywhere is found now, before any output file is written
    if series.dtype_name.startswith("float"):
        for i in range(n):
            series.numpy(i)
    return kwargs


# ----------------------------------------------------------------------------------------
# the command
# ----------------------------------------------------------------------------------------


def execute(args: argparse.Namespace) -> int:
    """``stsdic run``: track points through a series, write HDF5, add strains, summarise."""
    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out}: is a directory; give a file name such as result.h5")
    _check_not_an_input(out, args)
    if out.exists() and not (args.overwrite or args.resume):
        raise CommandError(
            f"output file {out} exists: use --overwrite to replace it or --resume to continue it"
        )
    _check_writable(out)
    device = check_device(args.device)
    calibration = options.check_calibration(args)
    kwargs = _track_arguments(args)
    run = _runner(args)

    from torch_stsdic.io import InputError
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import set_reference_mode, set_window_length

    series = kwargs.pop("series")
    print(series.describe(), flush=True)
    t0 = time.perf_counter()
    plan = sink = None
    target = _written_file(out, args)
    existed = target.exists()
    try:
        try:
            plan = plan_run(series, **kwargs, step=args.step, device=str(device),
                            reference_update=args.reference_update, checks=args.checks,
                            scale=calibration.get("scale"), unit=calibration["unit"],
                            time_unit=calibration.get("time_unit"),
                            shared_motion=args.shared_motion,
                            find_specimen=not args.keep_background)
            set_reference_mode(plan, args.refine_reference, args.refine_frames,
                               False if args.single_reference else args.series_reference,
                               args.series_frames)
            set_window_length(plan, args.window_length)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        sink = _open_sink(plan, args, out)
        kept = len(sink.completed_rows()) if args.resume else 0
        try:
            res = run(plan, sink, progress=not args.no_progress,
                      callback=lambda done, total: checkpoint())
        except (OSError, InputError) as exc:  # a full disk, a frame gone or changed mid-run
            _discard_unfinished(sink, out, args)
            raise CommandError(f"{_text(exc)}; {_kept(out, args, plan)}") from exc
        except Exception:  # e.g. the refined reference's pre-pass: no empty file is left
            _discard_unfinished(sink, out, args)
            raise
        elapsed = time.perf_counter() - t0
        print_summary(res, args, elapsed, _reference_name(series, plan), kept)
        from torch_stsdic.io.results import field_names, open_results

        with open_results(out) as f:
            fields = [nm for nm in field_names(f)
                      if nm not in ("u", "v", "ut", "vt", "zncc", "status")]
        print(f"results: {out} (fields u, v, ut, vt, zncc, status, {', '.join(fields)})")
    except KeyboardInterrupt as exc:  # at any moment: say what is kept
        stop = exc if isinstance(exc, Interrupted) else Interrupted()
        if sink is not None:  # a file of no finished frame is not left behind
            _discard_unfinished(sink, out, args)
        elif not args.resume and not existed:  # stopped while the file was being made
            target.unlink(missing_ok=True)
        raise stop.with_detail(_kept(out, args, plan)) from None
    return 0


def _text(exc: BaseException) -> str:
    """An error's message on one line, without the '[Errno N]' of an OSError."""
    if isinstance(exc, OSError) and exc.strerror and not exc.filename:
        return " ".join(exc.strerror.split())
    return one_line(exc)


def _reference_name(series: Any, plan: Any) -> str:
    """The reference as the user knows it: its file name (and page), or how it was made."""
    if plan.reference_frame < 0:
        return str(plan.reference_desc)
    path, sep, page = series.frame_name(plan.reference_frame).partition(" (page ")
    return Path(path).name + (f", page {page.rstrip(')')}" if sep else "")


def _input_files(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """Every file the run reads, with the option that names it: the frames of each INPUT
    (a folder or glob expanded as the series will), --points, --mask, --timestamps."""
    from torch_stsdic.io.images import InputError, expand_source

    files: list[tuple[str, Path]] = []
    for src in args.inputs:
        try:
            files += [("INPUT", p) for p in expand_source(src)]
        except InputError:
            continue  # refused with its reason when the series is opened
    for flag in ("points", "mask", "timestamps"):
        if getattr(args, flag, None):
            files.append((f"--{flag}", Path(getattr(args, flag))))
    return files


def _check_not_an_input(out: Path, args: argparse.Namespace) -> None:
    """--out is none of the files the run reads, whatever --overwrite/--resume say."""
    if not out.exists():
        return
    for flag, path in _input_files(args):
        try:
            same = os.path.samefile(path, out)
        except OSError:
            continue
        if same:
            raise UsageError(f"--out {out} is {path}, an input of the run ({flag}): it would be "
                             "overwritten; give another --out")


def _check_writable(out: Path) -> None:
    """--out's folder exists (or can be made) and takes files: checked before any work."""
    check_folder(out.absolute().parent, f"--out {out}")


def _open_sink(plan: Any, args: argparse.Namespace, out: Path) -> Any:
    """The HDF5 result file of the run; its problems in the words of the command line."""
    from torch_stsdic.io.results import ResultFileError
    from torch_stsdic.movie.sinks import open_sink

    try:
        return open_sink(plan, str(out), resume=args.resume, overwrite=args.overwrite,
                         strain_window=args.strain_window, strain_kind=args.strain_kind)
    except ResultFileError as exc:
        raise CommandError(resume_problem(exc)) from None
    except OSError as exc:  # read-only filesystem, no permission, full disk at creation
        text = _text(exc)  # said once: 'cannot create the result file OUT: reason'
        raise CommandError(text if str(out) in text else f"--out {out}: {text}") from None


#: result-file settings (dotted keys of the recorded config) -> the option that sets them
CONFIG_FLAGS: dict[str, str] = {
    "subset_size": "--subset", "m": "--m", "shape": "--shape", "window": "--window",
    "criterion": "--criterion", "formulation": "--formulation",
    "interpolation": "--interpolation", "max_iter": "--max-iter", "tol": "--tol",
    "search_radius": "--search-radius", "initial_guess": "--initial-guess",
    "seed_spacing": "--seed-spacing", "batch_points": "--batch-points",
    "memory_mb": "--memory-mb", "dtype": "--dtype", "track.reference": "--reference",
    "track.step": "--step", "track.roi": "--roi", "track.reference_update": "--reference-update",
    "track.checks": "--no-checks",
    "track.points": "--step/--roi/--mask/--points", "track.batch_frames": "--memory-mb",
    "points": "--step/--roi/--mask/--points", "frames": "--frames", "times": "--timestamps",
}


def resume_problem(exc: Any) -> str:
    """A :class:`~torch_stsdic.io.ResultFileError` met by ``--resume``, naming the options."""
    path = exc.path
    kinds = {what for what, _ in exc.problems}
    if "open" in kinds:
        return (f"--resume: {path} cannot be read as HDF5 (corrupt or truncated); nothing was "
                "changed; give another --out, or --overwrite to replace it")
    if "format" in kinds:
        return (f"--resume: {path} is not a result file of 'stsdic run' (an HDF5 file of "
                "another program); nothing was changed; give another --out, or --overwrite "
                "to replace it")
    if "missing" in kinds:
        what = "; ".join(t for k, t in exc.problems if k == "missing")
        return (f"--resume: {path} lacks what this run writes ({what}: written by another "
                "version, or with other --strain-window/--m options); nothing was changed; "
                "use --overwrite to start again")
    parts = []
    for what, text in exc.problems:
        if what == "config:track.points" and "points" in kinds:
            continue  # said once, by the points themselves
        key = what.split(":", 1)[1] if what.startswith("config:") else what
        flag = CONFIG_FLAGS.get(key, CONFIG_FLAGS.get(key.split(".")[-1], ""))
        parts.append(f"{flag} ({text})" if flag else text)
    return (f"--resume: {path} was written with other options: {'; '.join(parts)}; repeat "
            "the first run's options to continue it, or use --overwrite to start again")


def _written_file(out: Path, args: argparse.Namespace) -> Path:
    """The file a new run writes: ``out``, or ``<out>.partial`` (renamed over ``out`` when
    the run finishes) with ``--overwrite``."""
    return out.with_name(out.name + ".partial") if args.overwrite else out


def _holds_estimates(f: Any) -> bool:
    """Whether the open result file ``f`` holds measured run-level estimates (a template, a
    shared motion, a time model: its group ``run_estimates`` has arrays), not only a ratio."""
    from torch_stsdic.movie.estimates import GROUP

    return GROUP in f and len(f[GROUP]) > 0


def _discard_unfinished(sink: Any, out: Path, args: argparse.Namespace) -> None:
    """After a failed run: close the result file and remove it if this run created it, no
    frame was finished and it holds no run-level estimates (a file of 0 frames only invites
    a --resume that fails again; one with the estimates saves a --resume their time)."""
    import h5py

    sink.close(commit=False)
    if args.resume:  # the user's file: kept as it was
        return
    path = _written_file(out, args)
    try:
        with h5py.File(path, "r", locking=False) as f:
            done = int(np.asarray(f["completed"][()]).sum())
            estimates = _holds_estimates(f)
    except Exception:  # noqa: BLE001 - not ours or not there: leave it
        return
    if done == 0 and not estimates:
        path.unlink(missing_ok=True)


def _kept(out: Path, args: argparse.Namespace, plan: Any) -> str:
    """What an interrupted or failed run left: the finished frames and how to continue."""
    from torch_stsdic.io.results import RESULTS_FORMAT, open_results

    partial = out.with_name(out.name + ".partial")
    path = partial if (args.overwrite or args.resume) and partial.exists() else out
    if args.overwrite and path == out:  # the new file was not made yet: the old one stays
        return f"{out} is unchanged" if out.exists() else "nothing was written yet"
    try:
        with open_results(path) as f:
            done = f["completed"][()]
            ours = f.attrs.get("format") == RESULTS_FORMAT
            estimates = _holds_estimates(f)
    except Exception:  # noqa: BLE001 - only for the message
        return "nothing was written yet"
    if not ours or (plan is not None and len(done) != plan.n_rows):
        return f"{path} is unchanged"
    n, k = len(done), int(done.sum())
    if k == 0 and estimates:
        return (f"no frame finished; the run's estimates (template, shared motion, time "
                f"model) are kept in {path}: continue with the same command and --resume")
    if k == n:
        return (f"all {n} frames are finished in {path}; run the same command with --resume "
                "to complete what may be missing (strains)")
    return (f"{k} of {n} frames finished, kept in {path}; continue with the same command "
            "and --resume")
