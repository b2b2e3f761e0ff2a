"""The plan of a run: validated inputs, points, reference, target frames and frame blocks.

:func:`plan_run` checks every argument of :func:`~torch_stsdic.track` once (errors name the
argument) and returns a :class:`RunPlan`; :func:`~torch_stsdic.movie.series.run_plan` executes it
block by block into a result sink, and the distributed runner splits the same plan into
chunks. A plan holds no solver state, so it can be inspected before anything is computed.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.points import filter_points, grid_points
from torch_stsdic.analysis.specimen import SpecimenReport, on_specimen
from torch_stsdic.core.config import DICConfig, gpu_budget_mb
from torch_stsdic.core.shape import make_shape
from torch_stsdic.core.shared_motion import SHARED_MOTION_KINDS
from torch_stsdic.core.validation import check_pixels
from torch_stsdic.io import DEFAULT_FIELDS, ImageSeries, InputError, load_series, parse_frame_spec
from torch_stsdic.io.units import check_calibration

__all__ = ["RunPlan", "plan_run", "reference_frames", "resolve_reference", "resolve_frames",
           "resolve_times", "default_batch_frames", "grid_margin", "set_shared_motion",
           "MAX_DEFAULT_BATCH", "MAX_DEFAULT_BATCH_GPU", "guessed_blocks"]

MAX_DEFAULT_BATCH = 8
#: on a GPU a block's host work (launches, checks, carry), not its arithmetic, sets the pace:
#: 32 target frames a block ran the 500-frame 1024^2 movie 1.31x faster than 8 on an H100,
#: with the same error (u RMSE 0.0083947 against 0.0083941 px; 2.50 against 2.13 iterations)
MAX_DEFAULT_BATCH_GPU = 32
_BASE = ("u", "v", "ut", "vt")


@dataclass
class RunPlan:
    """A validated run of :func:`~torch_stsdic.track` (see :func:`plan_run`).

    Attributes:
        series: the image series (read lazily).
        config: solver settings; ``config.m`` sets the window of 2m+1 frames.
        points: (N, 2) float64 POIs (x, y) px in the reference, on the CPU.
        targets: ascending series indices of the frames with a result row each.
        times: (T_series,) float64 time of every series frame.
        reference_image: (H, W) reference pixels when it is not a single series frame
            (a mean of frames, or an array), else None.
        reference_frame: series index of the reference, -1 for a mean/array.
        reference_desc: how the reference is recorded (frame index, "mean:0,1,2",
            "array:<digest>").
        dtype, device: of the computation.
        batch_frames: target frames solved together per block.
        first_alone: the first target in a block of its own (its rows started by FFT
            cross-correlation, the next blocks' carried from it); False where every block
            starts from an earlier round's solutions (:func:`guessed_blocks`).
        param_names: the shape function's parameter names for a window of 2m+1 frames.
        options: run options recorded with the results (step, roi, reference_update,
            lost_zncc, smoothing, checks, strain settings).
        units: the calibration recorded as file attributes (:mod:`torch_stsdic.io.units`):
            ``unit`` ("px" without ``scale``), ``scale`` (units per px, when given),
            ``time_unit``. Results stay in px; exports and figures convert.
    """

    series: ImageSeries
    config: DICConfig
    points: torch.Tensor
    targets: list[int]
    times: np.ndarray
    reference_image: torch.Tensor | None
    reference_frame: int
    reference_desc: Any
    dtype: torch.dtype
    device: torch.device
    batch_frames: int
    param_names: tuple[str, ...]
    options: dict[str, Any] = field(default_factory=dict)
    units: dict[str, Any] = field(default_factory=lambda: {"unit": "px", "time_unit": "frame"})
    first_alone: bool = True

    @property
    def n_rows(self) -> int:
        """F, the number of result rows (target frames)."""
        return len(self.targets)

    @property
    def n_points(self) -> int:
        """N, the number of POIs."""
        return int(self.points.shape[0])

    def info(self) -> dict[str, Any]:
        """The result's ``info`` entries the plan's choices make: the specimen found, the
        smoothing, why the reference image alone is used."""
        return {k: self.options[k] for k in ("specimen", "smoothing", "single_reference")
                if self.options.get(k)}

    @property
    def row_times(self) -> np.ndarray:
        """(F,) times of the target frames."""
        return self.times[self.targets]

    @property
    def gradients(self) -> tuple[str, ...]:
        """Parameter names other than u, v, ut, vt (displacement gradients ...)."""
        return tuple(nm for nm in self.param_names if nm not in _BASE)

    @property
    def fields(self) -> tuple[str, ...]:
        """(F, N) result fields: u, v, ut, vt, zncc, status, iterations, gradients, the
        window half-width used ``m`` and the predicted standard deviations ``u_std``,
        ``v_std`` (and ``ut_std``, ``vt_std`` for STS shapes)."""
        stds = tuple(f"{nm}_std" for nm in _BASE if nm in self.param_names)
        return (*DEFAULT_FIELDS, "iterations", *self.gradients, "m", *stds)

    @property
    def blocks(self) -> list[list[int]]:
        """Target frames per block: the first target alone (FFT start; not where
        ``first_alone`` is False), then ``batch_frames`` at a time."""
        tg, n, a = self.targets, self.batch_frames, int(self.first_alone)
        return [b for b in [tg[:a]] + [tg[i : i + n] for i in range(a, len(tg), n)] if b]

    def row_of(self) -> dict[int, int]:
        """Result row of every target frame."""
        return {k: r for r, k in enumerate(self.targets)}

    def record(self) -> dict[str, Any]:
        """The settings recorded with the results (and compared on resume)."""
        track_cfg = {"reference": self.reference_desc, "batch_frames": self.batch_frames,
                     "points": self.n_points, **self.options}
        return {**self.config.to_dict(), "track": track_cfg}


def plan_run(
    series: Any,
    reference: Any = 0,
    frames: Any = None,
    points: Any = None,
    roi: Sequence[float] | None = None,
    mask: Any = None,
    step: int = 10,
    config: DICConfig | None = None,
    device: str | torch.device = "cpu",
    times: Any = None,
    batch_frames: int | None = None,
    *,
    reference_update: float | None = None,
    smoothing: int | None = None,
    lost_zncc: float = 0.8,
    checks: bool = True,
    scale: float | None = None,
    unit: str | None = None,
    time_unit: str | None = None,
    shared_motion: str | None = "auto",
    find_specimen: bool = True,
) -> RunPlan:
    """Validate the arguments of :func:`~torch_stsdic.track` (same meaning) into a plan
    (``shared_motion`` as there: a plan run by :func:`~torch_stsdic.run_plan` gives what
    ``track`` gives).

    Raises:
        ValueError / InputError naming the argument: ROI off the image, subset larger than
        the image, fewer frames than 2m+1, mask of the wrong shape, no points inside
        ROI/mask, reference index out of range, bad times/frames/batch_frames/
        reference_update/smoothing/scale/unit.

    ``scale`` (length ``unit``s per px, e.g. 0.02 with ``unit="mm"``) and ``time_unit``
    (default "frame", "s" for a movie whose frame rate gives the times, with ``time_source``
    saying so, or "time unit" for timestamps) are recorded, not applied.

    ``find_specimen`` (default True): the default grid keeps only the points whose subsets lie
    on speckle in the reference image (:func:`torch_stsdic.analysis.specimen.on_specimen`:
    not on a saturated or dark background, a hole, a featureless area); given points are
    kept as given. Where no grid point is on speckle, all are kept.
    """
    cfg = config if config is not None else DICConfig()
    if not isinstance(cfg, DICConfig):
        raise TypeError(f"config: expected a DICConfig, got {type(cfg).__name__}")
    if smoothing is not None:
        if not isinstance(smoothing, (int, np.integer)) or smoothing < 1 or smoothing % 2 == 0:
            raise ValueError(f"smoothing: span must be an odd integer >= 1, got {smoothing!r}")
        cfg = cfg.replace(m=0)
    if reference_update is not None and not 0.0 < float(reference_update) < 1.0:
        raise ValueError(f"reference_update: ZNCC threshold must be in (0, 1), got "
                         f"{reference_update!r}")
    if batch_frames is not None and (not isinstance(batch_frames, (int, np.integer))
                                     or batch_frames < 1):
        raise ValueError(f"batch_frames: must be an integer >= 1, got {batch_frames!r}")
    units = check_calibration(scale, unit, time_unit)
    ser = _open(series)
    h, w = ser.shape
    n_series = len(ser)
    if cfg.subset_size > min(h, w):
        raise ValueError(f"config.subset_size: {cfg.subset_size} px is larger than the image "
                         f"({h}x{w} HxW)")
    n_win = cfg.n_frames
    if n_series < n_win:
        raise ValueError(f"series: {n_series} frames, fewer than the 2m+1 = {n_win} frames of "
                         f"one window (config.m = {cfg.m})")
    if n_series < 2 and not (isinstance(reference, (np.ndarray, torch.Tensor))
                             and np.ndim(reference) >= 2):
        raise ValueError(f"series: {n_series} frame, nothing to match against itself: give "
                         "at least 2 frames (or a reference image as an array)")
    ts_np = resolve_times(times, ser)
    if times is None and getattr(ser, "time_source", None):  # a movie's frame rate: seconds
        if units.setdefault("time_unit", ser.time_unit) != ser.time_unit:
            raise ValueError(f"time_unit: the times are in {ser.time_unit}, from the "
                             f"{ser.time_source}; give timestamps for another unit")
        units["time_source"] = ser.time_source
    if "time_unit" not in units:
        frames_as_time = np.array_equal(ts_np, np.arange(n_series, dtype=np.float64))
        units["time_unit"] = "frame" if frames_as_time else "time unit"
    targets = resolve_frames(frames, n_series)
    if smoothing is not None and smoothing > len(targets):
        raise ValueError(f"smoothing: span {smoothing} is longer than the {len(targets)} "
                         "target frames")
    dev = torch.device(device)
    if cfg.dtype is not None:
        dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    else:
        dtype = torch.float64 if ser.dtype_name == "float64" else torch.float32
    ref_raw, ref_frame, ref_desc = resolve_reference(reference, ser, dtype, torch.device("cpu"))
    if points is None:
        # the whole image: keep room for motion; a roi is the user's choice (subset/2 only)
        margin = grid_margin(cfg) if roi is None else 0
        pts0 = grid_points((h, w), step, roi, mask, cfg.subset_size, margin=margin)
        specimen = _on_specimen(pts0, ref_raw, ser, ref_frame, cfg) if find_specimen else None
        if specimen is not None:
            pts0 = specimen[0]
    else:
        pts0 = filter_points(points, (h, w), roi, mask)
    elem = torch.finfo(dtype).bits // 8
    n_batch = int(batch_frames) if batch_frames is not None else default_batch_frames(
        cfg, (h, w), elem, dev)
    shape = make_shape(cfg.shape)
    names = shape.param_names if n_win > 1 else shape.spatial().param_names
    options = {"step": int(step), "roi": None if roi is None else list(roi),
               "reference_update": reference_update, "lost_zncc": float(lost_zncc),
               "smoothing": smoothing, "checks": bool(checks)}
    if points is None and find_specimen and specimen is not None:
        options["specimen"] = specimen[1].summary()
    plan = RunPlan(series=ser, config=cfg, points=pts0.double(), targets=targets, times=ts_np,
                   reference_image=ref_raw, reference_frame=ref_frame, reference_desc=ref_desc,
                   dtype=dtype, device=dev, batch_frames=n_batch, param_names=names,
                   options=options, units=units)
    set_shared_motion(plan, shared_motion)
    return plan


def _on_specimen(pts: torch.Tensor, ref_raw: torch.Tensor | None, ser: ImageSeries,
                 ref_frame: int, cfg: DICConfig) -> tuple[torch.Tensor, SpecimenReport] | None:
    """The grid points on the specimen and the report, or None where none is (every point
    kept then: the solver gives them their status)."""
    # through the series' own frame cache: the run reads the reference frame again from it
    image = (ref_raw if ref_raw is not None
             else torch.from_numpy(np.asarray(ser.numpy(ref_frame, np.float64))))
    keep, report = on_specimen(pts, image.double().cpu(), cfg.subset_size)
    if report.kept == 0:
        return None
    return pts[keep], report


def grid_margin(cfg: DICConfig) -> int:
    """Px the default grid keeps beyond half a subset from the image border: the B-spline's
    support (2 px cubic, 3 px quintic) plus the expected motion, ``config.search_radius``
    (the largest motion the initial guess looks for), so that subsets stay inside the image
    over the first window, whose frames have already moved (sample 12 of the DIC Challenge:
    the first row of a plain subset/2 margin was OUTSIDE on the reference frame)."""
    support = (3 if cfg.interpolation == "quintic" else 2)
    return support + int(cfg.search_radius)


def _open(series: Any) -> ImageSeries:
    if isinstance(series, ImageSeries):
        return series
    try:
        return load_series(series)
    except InputError as exc:
        raise InputError(f"series: {exc}") from exc


def resolve_reference(reference: Any, series: ImageSeries, dtype, device):
    """(raw (H, W), frame index or -1, description for the config)."""
    n = len(series)
    if isinstance(reference, (np.ndarray, torch.Tensor)) and np.ndim(reference) >= 2:
        check_pixels(reference, "reference")
        arr = torch.as_tensor(np.asarray(reference.detach().cpu() if isinstance(
            reference, torch.Tensor) else reference)).to(dtype)
        if arr.dim() == 3 and arr.shape[0] == 1:
            arr = arr[0]
        if tuple(arr.shape) != tuple(series.shape):
            raise ValueError(f"reference: image shape {tuple(arr.shape)} differs from the "
                             f"series {tuple(series.shape)} (H, W)")
        if not bool(torch.isfinite(arr).all()):
            raise ValueError("reference: contains non-finite pixels")
        digest = hashlib.sha1(arr.to(torch.float64).numpy().tobytes()).hexdigest()[:16]
        return arr.to(device), -1, f"array:{digest}"
    if isinstance(reference, (int, np.integer)) and not isinstance(reference, bool):
        i = int(reference)
        if not -n <= i < n:
            raise ValueError(f"reference: frame index {i} out of range for {n} frames")
        return None, i % n, i % n
    try:
        if isinstance(reference, str):
            idx = reference_frames(reference, n)
        else:
            idx = series.resolve(list(reference))
    except (InputError, IndexError, TypeError, ValueError) as exc:
        raise ValueError(f"reference: {exc}") from None
    if len(idx) == 1:
        return None, idx[0], idx[0]
    raw = series.mean_of(idx, dtype=torch.float64).to(device=device, dtype=dtype)
    return raw, -1, f"mean:{','.join(map(str, idx))}"


def reference_frames(spec: str, n: int) -> list[int]:
    """The series frames of a reference spec ("0:5", "3", "0,2,4") in a series of ``n``
    frames: :func:`parse_frame_spec`, except that a range reaching past the series is an
    error (InputError naming the valid frames), not clipped: "10:20" on 12 frames would
    otherwise average 2 frames where 10 were asked for."""
    idx = parse_frame_spec(spec, n)
    for part in str(spec).split(","):
        bits = [b.strip() for b in part.split(":")]
        if len(bits) < 2:
            continue  # a single index: checked by parse_frame_spec
        start, stop = (int(b) if b else None for b in bits[:2])
        if (start is not None and not -n <= start < n) or (stop is not None
                                                           and not -n <= stop <= n):
            raise InputError(
                f"the range {part.strip()} reaches past the series of {n} frames: the "
                f"reference frames must be within 0..{n - 1} (a range a:b takes frames "
                f"a..b-1, e.g. 0:{min(n, 5)})")
    return idx


def resolve_frames(frames: Any, n: int) -> list[int]:
    if frames is None:
        return list(range(n))
    try:
        if isinstance(frames, (str, int, np.integer)):
            idx = parse_frame_spec(frames, n)
        else:
            vals = np.asarray(frames.detach().cpu() if isinstance(frames, torch.Tensor)
                              else list(frames))
            if vals.ndim != 1 or vals.size == 0 or vals.dtype.kind not in "iu":
                raise ValueError(f"expected a non-empty list of frame indices, got {frames!r}")
            bad = [int(i) for i in vals if not -n <= int(i) < n]
            if bad:
                raise ValueError(f"indices {bad} out of range for {n} frames")
            idx = [int(i) % n for i in vals]
    except (InputError, ValueError, TypeError) as exc:
        raise ValueError(f"frames: {exc}") from None
    return sorted(set(idx))


def resolve_times(times: Any, series: ImageSeries) -> np.ndarray:
    n = len(series)
    if times is None:
        return series.times.astype(np.float64)
    t = np.asarray(times.detach().cpu() if isinstance(times, torch.Tensor) else times,
                   dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"times: expected {n} values (one per series frame), got {t.shape[0]}")
    if not np.isfinite(t).all() or (n > 1 and not (np.diff(t) > 0).all()):
        raise ValueError("times: must be finite and strictly increasing")
    return t


def default_batch_frames(cfg: DICConfig, shape: tuple[int, int], elem: int,
                         device: torch.device | str = "cpu",
                         device_mb: float | None = None, carried: bool = True) -> int:
    """Target frames per block: the frames its targets add (raw + padded coefficients, ~3
    copies each) within half of ``memory_mb`` (not given: 256 MiB; the other half bounds
    the solver's batches; the 2m frames of the window come on top: any block holds them),
    at most 8 on the CPU (the carried guess is extrapolated over the block, so very long
    blocks start further from the solution). On a GPU (``device``; its memory
    ``device_mb`` MiB, read from the device where not given) at most
    ``MAX_DEFAULT_BATCH_GPU`` and, where ``memory_mb`` is not given, the frames' budget at
    least :func:`~torch_stsdic.core.config.gpu_budget_mb` (2 GiB within a tenth of the
    device's memory): a block's host work sets the pace there, and 256 MiB would hold 6
    megapixel frames. ``carried=False``: the blocks of a run whose every block starts from
    an earlier round's solutions (:func:`guessed_blocks`), not from the carry: no cap on the
    CPU but the budget. (Counting the window's
    frames too left the muDIC hourglass, 1.3 megapixel frames and windows of up to 13, one
    target a block: 17 s a run against 14 s with 8, the same results within 1.1e-3 px.)"""
    frame_bytes = 3.0 * shape[0] * shape[1] * elem
    budget = cfg.budget_mb * 2**20 / 2.0
    most = MAX_DEFAULT_BATCH if carried else None
    gpu_mb = gpu_budget_mb(device, device_mb)
    if gpu_mb is not None:
        if cfg.gpu_floor:
            budget = max(budget, gpu_mb * 2**20)
        most = MAX_DEFAULT_BATCH_GPU
    fit = int(budget / frame_bytes)
    return max(1, fit if most is None else min(most, fit))


def guessed_blocks(plan: RunPlan) -> RunPlan:
    """``plan`` for a run whose every block starts from an earlier round's solutions (a
    ``first_guess`` with ``guess_every_block``: the template's later rounds): no block
    extrapolates the carry, so the first target is not alone and a block holds as many
    targets as the memory budget allows (:func:`default_batch_frames` with
    ``carried=False``; never fewer than ``plan``'s): fewer blocks, each with its own fixed
    costs (the hourglass's template: 5 blocks -> 3, 3 % of its time)."""
    elem = torch.finfo(plan.dtype).bits // 8
    n = default_batch_frames(plan.config, plan.series.shape, elem, plan.device, carried=False)
    return dataclasses.replace(plan, first_alone=False, batch_frames=max(plan.batch_frames, n))


def set_shared_motion(plan: RunPlan, kind: str | None = "auto") -> None:
    """Choose a plan's shared motion (recorded in ``plan.options["shared_motion"]``).

    ``"auto"``: for STS windows (m > 0) without reference updates or smoothing a quadratic
    (affine with few points) motion is measured and applied where it is significant;
    otherwise none is measured. "quadratic" / "affine" / "translation": measured and
    applied whatever m (with m = 0 it is reported and
    changes no result). None or "none": not measured."""
    if kind is None or kind == "none":
        plan.options["shared_motion"] = None
        return
    if kind != "auto" and kind not in SHARED_MOTION_KINDS:
        raise ValueError(f"shared_motion: must be 'auto', 'none', None or one of "
                         f"{SHARED_MOTION_KINDS}, got {kind!r}")
    updating = plan.options.get("reference_update") is not None
    if kind == "auto":
        use = plan.config.m > 0 and not updating and not plan.options.get("smoothing")
        plan.options["shared_motion"] = "auto" if use else None
        return
    if updating:
        raise ValueError("shared_motion: cannot be combined with reference_update (the shared "
                         "motion is measured against one reference); pass shared_motion=None")
    plan.options["shared_motion"] = kind
