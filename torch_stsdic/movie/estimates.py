"""Run-level estimates: what a run measures once, before its first block, for the whole movie.

A run measures, from the whole movie, a few things every block then uses: the specimen's
shared motion and its load steps with the measuring pass's solutions (the first block's
guess; :func:`~torch_stsdic.movie.shared_pass.estimate_shared_motion`), the reference made
from the series (:func:`~torch_stsdic.movie.series_reference.build_series_reference`), the
template's gauge from the trajectories (:func:`~torch_stsdic.movie.refine.measure_trajectory_gauge`)
and, for a reference given as an image, its noise ratio. :func:`measure_run` measures them
(:class:`RunEstimates`); :func:`~torch_stsdic.movie.series.run_plan` does so itself, or takes
them measured already: the distributed runner (:mod:`torch_stsdic.movie.distributed`)
measures them once on the whole movie and hands them to every chunk, so that a chunk's
windows and decisions are those of the one-process run.

A run with a result file records them there (:func:`record_estimates`: the shared motion and
the template as the file's run-level arrays, everything else a run uses in its group
``run_estimates``, exactly: float64, int64, bool), and a resumed run reads them back
(:func:`stored_or_measured`) instead of measuring them again: the pending blocks get the
very numbers the interrupted run had. A file written before they were recorded, or one
whose first block is unfinished where the shared motion's first guess (not stored) is
needed, is measured again, as the run's ``info["run_estimates"]`` says.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.classical_pass import ClassicalPass
from torch_stsdic.movie.frames import FrameStore, segment_bounds, window_frames
from torch_stsdic.movie.plan import RunPlan
from torch_stsdic.movie.reference import noise_ratio
from torch_stsdic.movie.refine import ReferenceOffsets, measure_trajectory_gauge
from torch_stsdic.movie.series_reference import (
    SeriesReference,
    build_series_reference,
    measure_time_model,
    sample_frames,
    wants_time_model,
)
from torch_stsdic.movie.shared_pass import estimate_shared_motion, shared_frames
from torch_stsdic.movie.sinks import MemorySink
from torch_stsdic.movie.window_length import (
    measure_window_lengths,
    measured_frames,
    wants_window_lengths,
)

__all__ = ["RunEstimates", "measure_run", "reference_pixels", "record_estimates",
           "stored_or_measured", "FROM_FILE"]

#: runs a plan to its result (the signature of :func:`torch_stsdic.movie.series.run_plan`)
RunFunction = Callable[..., TrackResult]

#: the shared-motion pass takes its rows from the run's shared classical pass where it
#: measures at most this many frames (twice the window-length pass's: a short movie)
SHARED_FRAMES_HELD = 128


@dataclass(eq=False)
class RunEstimates:
    """The run-level estimates of a plan (:func:`measure_run`); None where not used.

    Attributes:
        shared: the shared motion (:class:`~torch_stsdic.core.shared_motion.SharedMotion`):
            per-frame motion, load ``steps`` and the measuring pass's ``sample`` (the guess
            of a block without a carry); carried in the windows where ``applied``.
        series_reference: the reference made from the series (its image, noise ratio and
            added variance).
        offsets: the template's gauge from the trajectories (``refine_reference``), which
            every row has subtracted in place of the template's own.
        noise_ratio: the reference's noise variance over a frame's (None: the first block
            measures it, as a one-process run does).
        time_model: (N,) bool, where the time model holds, for an STS run against its
            reference image alone (:func:`~torch_stsdic.movie.series_reference.
            measure_time_model`; with a template its ``model_holds`` says it).
        window_m: (T_series, N) int8, the longest window half-width the measured motion
            supports at each point with each frame as target, for a run that chooses its
            windows' lengths (:mod:`~torch_stsdic.movie.window_length`; it then decides
            where the time model holds: ``model_holds`` is None).
        source: where a resumed run took them (:data:`FROM_FILE`, or why they were measured
            again); None: measured for a new run, or handed over.
    """

    shared: SharedMotion | None = None
    series_reference: SeriesReference | None = None
    offsets: ReferenceOffsets | None = None
    noise_ratio: float | None = None
    time_model: torch.Tensor | None = None
    source: str | None = None
    window_m: torch.Tensor | None = None

    @property
    def model_holds(self) -> torch.Tensor | None:
        """(N,) bool where the time model holds (None: everywhere): the template's decision,
        or the single reference's own; None where the windows' lengths decide it."""
        if self.window_m is not None:
            return None
        if self.series_reference is not None:
            return self.series_reference.model_holds
        return self.time_model

    @property
    def row_offsets(self) -> ReferenceOffsets | None:
        """The per-point offsets every stored row has subtracted: the refined reference's, or
        the series reference's gauge (its template's registration as the reference frame
        measured it)."""
        if self.offsets is not None:
            return self.offsets
        return None if self.series_reference is None else self.series_reference.gauge

    def summary(self) -> dict[str, Any]:
        """The result's ``info`` entries of these estimates, as a one-process run has them."""
        info: dict[str, Any] = {}
        if self.offsets is not None:
            info["refine_reference"] = self.offsets.summary()
        if self.series_reference is not None:
            info["series_reference"] = self.series_reference.summary()
        if self.shared is not None:
            info["shared_motion"] = self.shared.summary()
        if self.time_model is not None:
            info["time_model"] = {"classical_points": int((~self.time_model).sum()),
                                  "points": int(self.time_model.numel())}
        if self.window_m is not None:
            info["window_length"] = _window_share(self.window_m)
        if self.source is not None:
            info["run_estimates"] = self.source
        return info


def _window_share(window_m: torch.Tensor) -> dict[str, Any]:
    """The longest half-width of ``window_m`` (T_series, N) and the share of each, counted a
    few rows at a time (a long movie's (T_series, N) array is not copied whole)."""
    n = window_m.numel()
    if n == 0:
        return {"max_m": 0, "chosen_m": {}}
    lo, hi = int(window_m.min()), int(window_m.max())
    counts = torch.zeros(hi - lo + 1, dtype=torch.int64)
    step = max(1, (1 << 16) // max(window_m.shape[-1], 1))
    for r0 in range(0, window_m.shape[0], step):
        part = window_m[r0:r0 + step].flatten().to(torch.int64) - lo
        counts += torch.bincount(part, minlength=hi - lo + 1)
    return {"max_m": hi, "chosen_m": {lo + i: round(int(c) / n, 4)
                                      for i, c in enumerate(counts.tolist()) if c}}


def reference_pixels(plan: RunPlan) -> torch.Tensor:
    """(H, W) the plan's reference image as a run reads it (plan dtype and device)."""
    if plan.reference_image is not None:
        return plan.reference_image.to(device=plan.device, dtype=plan.dtype)
    return plan.series.get(plan.reference_frame, dtype=plan.dtype).to(plan.device)


def measure_run(plan: RunPlan, ref_raw: torch.Tensor | None = None, *, run: RunFunction,
                first_noise: bool = False, guess_blocks: list[list[int]] | None = None,
                frames: FrameStore | None = None) -> RunEstimates:
    """Measure the run-level estimates of ``plan`` (those its options ask for) on the whole
    movie. ``ref_raw``: the reference image (default :func:`reference_pixels`); ``run``: the
    runner of a plan (:func:`torch_stsdic.movie.series.run_plan`, which calls this
    function). ``first_noise``: also the reference's noise ratio, on the frames of the plan's
    first block as that block measures it (a runner whose pieces start elsewhere, or a run
    that records it in its result file for a resumed run to read). ``guess_blocks``: the
    blocks that start from the shared motion's first guess (default the plan's first;
    :func:`~torch_stsdic.movie.shared_pass.estimate_shared_motion`). ``frames``: the run's
    prepared frames (:class:`~torch_stsdic.movie.frames.FrameStore`), which the template's
    images are taken from and added to (None: its own)."""
    measured = _classical_pass(plan, run)
    # the frames that several passes read (the template's sample, the window-length pass's)
    # prepared once, where the store keeps nothing else (a long movie)
    with frames.keeping(pass_frames(plan, shared=False)[1]) if frames is not None \
            else nullcontext():
        return _measure_passes(plan, ref_raw, run, first_noise, guess_blocks, frames, measured)


def _measure_passes(plan: RunPlan, ref_raw: torch.Tensor | None, run: RunFunction,
                    first_noise: bool, guess_blocks: list[list[int]] | None,
                    frames: FrameStore | None, measured: ClassicalPass | None
                    ) -> RunEstimates:
    """:func:`measure_run`'s passes, given the run's shared classical pass ``measured``."""
    shared = None
    if plan.options.get("shared_motion"):
        kind = plan.options["shared_motion"]
        shared = estimate_shared_motion(plan, kind, auto=kind == "auto", run=run,
                                        guess_blocks=guess_blocks, measured=measured)
    series_ref = None
    if plan.options.get("series_reference"):
        opt = plan.options["series_reference"]
        raw = reference_pixels(plan) if ref_raw is None else ref_raw
        series_ref = build_series_reference(
            plan, raw, run=run, max_frames=opt["frames"], iterations=opt["iterations"],
            shared=shared if shared is not None and shared.applied else None,
            measured=measured, frames=frames)
    offsets = None
    if plan.options.get("refine_reference") and series_ref is not None:
        offsets = measure_trajectory_gauge(
            plan, series_ref, int(plan.options["refine_reference"]),
            shared if shared is not None and shared.applied else None, run=run)
    window_m = None
    if wants_window_lengths(plan):
        window_m = measure_window_lengths(plan, run, shared if shared is not None
                                          and shared.applied else None, measured=measured)
        if series_ref is not None:  # its test was of the longest window alone
            series_ref.model_holds = None
    holds = None
    if series_ref is None and window_m is None and wants_time_model(plan):
        holds = measure_time_model(plan, run, shared if shared is not None and shared.applied
                                   else None, measured=measured)
        if holds is None:  # no point had three windows: decided, the model everywhere
            holds = torch.ones(plan.n_points, dtype=torch.bool)
    est = RunEstimates(shared=shared, series_reference=series_ref, offsets=offsets,
                       noise_ratio=None if series_ref is None else series_ref.noise_ratio,
                       time_model=holds, window_m=window_m)
    if first_noise and est.noise_ratio is None:
        est.noise_ratio = _first_block_noise(plan, ref_raw, shared)
    return est


def _classical_pass(plan: RunPlan, run: RunFunction) -> ClassicalPass | None:
    """The classical pass that the shared-motion pass, the template's first round, the
    window-length pass and the time-model pass share
    (:mod:`~torch_stsdic.movie.classical_pass`), over the frames they will ask for
    (:func:`pass_frames`); None where fewer than two of them run."""
    users, frames = pass_frames(plan)
    return ClassicalPass(plan, run, frames) if users >= 2 else None


def pass_frames(plan: RunPlan, shared: bool = True) -> tuple[int, set[int]]:
    """How many of the passes that measure frames classically run for ``plan`` (the
    shared-motion pass, the template's, the window-length pass, the time-model pass) and
    the frames they read: the shared-motion pass's only where they are at most
    ``SHARED_FRAMES_HELD`` (a long movie's pass measures every frame, at a sample of the
    points, and holds only what its fit needs) and ``shared``, the others' samples."""
    users, frames = 0, set()
    if plan.options.get("shared_motion"):
        users += 1
        own = shared_frames(plan)
        if len(own) <= SHARED_FRAMES_HELD and shared:
            frames |= set(own)
    if plan.options.get("series_reference"):
        users += 1
        frames |= set(sample_frames(plan, plan.options["series_reference"]["frames"]))
    if wants_window_lengths(plan):
        users += 1
        frames |= set(measured_frames(plan))
    elif not plan.options.get("series_reference") and wants_time_model(plan):
        users += 1  # the time model decided from its own classical pass
        frames |= set(sample_frames(plan))
    return users, frames


def _first_block_noise(plan: RunPlan, ref_raw: torch.Tensor | None,
                       shared: SharedMotion | None) -> float:
    """The reference's noise ratio as the plan's first block measures it
    (:func:`~torch_stsdic.movie.reference.noise_ratio` on its windows' frames)."""
    desc = plan.reference_desc
    if isinstance(desc, (int, np.integer)) or str(desc).startswith("mean:"):
        return noise_ratio(desc, torch.zeros(1, 1), torch.zeros(1, 1, 1))  # no pixels needed
    raw = reference_pixels(plan) if ref_raw is None else ref_raw
    n_series = len(plan.series)
    seg = None if shared is None or not shared.steps else segment_bounds(shared.steps, n_series)
    win = window_frames(torch.tensor(plan.blocks[0]), plan.config.m, n_series, seg)
    frames = torch.stack([plan.series.get(int(i), dtype=plan.dtype).to(plan.device)
                          for i in torch.unique(win).tolist()])
    return noise_ratio(desc, raw, frames)


# ---------------------------------------------------------------------------------------
# in the result file
# ---------------------------------------------------------------------------------------
#: ``source`` of the estimates a resumed run read from its result file
FROM_FILE = "read from the result file"
#: the layout of the group ``run_estimates`` (its ``meta`` attribute's ``version``)
LAYOUT_VERSION = 1
#: the group of the result file that holds them (besides its run-level arrays)
GROUP = "run_estimates"
#: fields not stored: the measuring pass's sample (only the first block's guess: a resumed
#: run whose first block is finished replays it) and the provenance
_SKIP = {"SharedMotion": ("sample",), "RunEstimates": ("source",)}
#: fields that the file's run-level arrays hold (not stored twice): field -> array
_ROOT = {("SharedMotion", "params"): "shared_motion",
         ("SeriesReference", "image"): "series_reference"}
_CLASSES = {c.__name__: c for c in (RunEstimates, SharedMotion, SeriesReference,
                                    ReferenceOffsets)}


def record_estimates(est: RunEstimates, sink: MemorySink) -> None:
    """Record ``est`` in ``sink``'s file as soon as they are measured: the shared motion and
    the template as its run-level arrays (``shared_motion``, ``series_reference``), every
    other field a run uses in the group ``run_estimates`` (:func:`_flatten`); nothing where
    they were read from that file."""
    if est.source == FROM_FILE:
        return
    if est.shared is not None:
        sink.write_shared_motion(est.shared)
    if est.series_reference is not None:
        sink.write_series_reference(est.series_reference)
    if sink.path is not None:
        arrays: dict[str, np.ndarray] = {}
        desc = {"version": LAYOUT_VERSION, "estimates": _flatten(est, "", arrays)}
        sink.write_run_estimates(arrays, json.dumps(desc, default=_plain))


def stored_or_measured(plan: RunPlan, sink: MemorySink, ref_raw: torch.Tensor | None = None,
                       *, run: RunFunction, first_noise: bool = False,
                       guess_needed: bool | None = None,
                       guess_blocks: list[list[int]] | None = None,
                       frames: FrameStore | None = None) -> RunEstimates:
    """The run-level estimates of ``plan``: those an earlier run of it recorded in ``sink``'s
    file (:func:`record_estimates`; a resumed run), where it holds all that ``plan`` asks
    for, else measured (:func:`measure_run`). On a resumed run ``source`` says which.

    ``first_noise``: the reference's noise ratio too, as the plan's first block measures it
    (:func:`measure_run`; read back like the rest, and measured so where a file recorded
    none), so that a resumed run's blocks scale their predicted std as the interrupted
    run's did, not by a ratio measured on its first pending block. ``guess_needed``: whether
    work still to do starts from the shared motion's first guess, which the file does not
    hold (default: where the plan's first block is unfinished; the distributed runner: where
    any chunk is pending, each starting from it); ``guess_blocks``: the blocks that start
    from it (:func:`measure_run`); ``frames``: the run's prepared frames (:func:`measure_run`)."""
    stored, done = sink.read_run(GROUP), sink.completed_rows()
    if stored is None and not done:
        return measure_run(plan, ref_raw, run=run, first_noise=first_noise,  # a new run
                           guess_blocks=guess_blocks, frames=frames)
    why = "the result file holds none (written before they were recorded)"
    if stored is not None:
        try:
            est = _from_file(stored, sink)
            why = _unusable(plan, est, done, guess_needed)
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            why = f"the result file's could not be read ({type(exc).__name__}: {exc})"
        if why is None:
            est.source = FROM_FILE
            if first_noise and est.noise_ratio is None:  # recorded before it was
                est.noise_ratio = _first_block_noise(plan, ref_raw, est.shared)
            return est
    est = measure_run(plan, ref_raw, run=run, first_noise=first_noise,
                      guess_blocks=guess_blocks, frames=frames)
    est.source = f"measured again: {why}"
    return est


def _unusable(plan: RunPlan, est: RunEstimates, done: set[int],
              guess_needed: bool | None = None) -> str | None:
    """Why the file's estimates ``est`` cannot stand for ``plan``'s (None: they can);
    ``guess_needed`` as for :func:`stored_or_measured`."""
    asked = {"shared motion": (plan.options.get("shared_motion"), est.shared),
             "reference made from the series": (plan.options.get("series_reference"),
                                                est.series_reference),
             "refined reference": (plan.options.get("refine_reference"), est.offsets)}
    for what, (want, have) in asked.items():
        if bool(want) != (have is not None):
            return f"the file's {what} is not this run's"
    if wants_window_lengths(plan) != (est.window_m is not None) or (
            est.window_m is not None and tuple(est.window_m.shape) != (len(plan.series),
                                                                     plan.n_points)):
        return "the file's window lengths are not this run's"
    if est.series_reference is None and not wants_window_lengths(plan) and wants_time_model(
            plan) and (
            est.time_model is None or len(est.time_model) != plan.n_points):
        return "the file holds no time-model decision for this run"
    ref = est.series_reference
    if ref is not None and (tuple(ref.image.shape) != tuple(plan.series.shape) or any(
            a is not None and len(a) != plan.n_points for a in (ref.added_var, ref.model_holds))):
        return "the file's reference made from the series is not this run's"
    if est.shared is None:
        return None
    if guess_needed is None:
        row_of = plan.row_of()
        if not all(row_of[k] in done for k in plan.blocks[0]):
            return ("its first block is unfinished (the shared motion's first guess is not "
                    "stored)")
    elif guess_needed:
        return "chunks still to run start from the shared motion's first guess (not stored)"
    return None


def _flatten(obj: Any, prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """The description (JSON) of dataclass ``obj``: its class and, per field, ``["value",
    v]``, ``["array"]`` / ``["tensor"]`` (stored at ``prefix + name``), ``["arrays", keys]``
    (a dict of arrays, at ``prefix + name/key``), ``["dataclass", description]`` or
    ``["root", array, kind]`` (a run-level array of the file); its arrays put in ``arrays``
    as they are (exact: float64, int64, bool)."""
    cls = type(obj).__name__
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v, path = getattr(obj, f.name), prefix + f.name
        if f.name in _SKIP.get(cls, ()):
            continue
        if (cls, f.name) in _ROOT:
            fields[f.name] = ["root", _ROOT[cls, f.name],
                              "tensor" if isinstance(v, torch.Tensor) else "array"]
        elif isinstance(v, torch.Tensor):
            arrays[path] = v.detach().cpu().numpy()
            fields[f.name] = ["tensor"]
        elif isinstance(v, np.ndarray):
            arrays[path] = v
            fields[f.name] = ["array"]
        elif dataclasses.is_dataclass(v):
            fields[f.name] = ["dataclass", _flatten(v, path + "/", arrays)]
        elif isinstance(v, dict) and v and all(isinstance(a, np.ndarray) for a in v.values()):
            arrays.update({f"{path}/{k}": a for k, a in v.items()})
            fields[f.name] = ["arrays", list(v)]
        else:
            fields[f.name] = ["value", v]
    return {"class": cls, "fields": fields}


def _unflatten(desc: dict[str, Any], prefix: str, arrays: dict[str, np.ndarray],
               root: dict[str, np.ndarray]) -> Any:
    """The dataclass that :func:`_flatten` described as ``desc``."""
    kw: dict[str, Any] = {}
    for name, (kind, *rest) in desc["fields"].items():
        path = prefix + name
        if kind == "value":
            kw[name] = rest[0]
        elif kind in ("array", "tensor"):
            kw[name] = arrays[path] if kind == "array" else torch.from_numpy(arrays[path])
        elif kind == "arrays":
            kw[name] = {k: arrays[f"{path}/{k}"] for k in rest[0]}
        elif kind == "dataclass":
            kw[name] = _unflatten(rest[0], path + "/", arrays, root)
        elif kind == "root":
            a = root[rest[0]]
            kw[name] = torch.from_numpy(a) if rest[1] == "tensor" else a
        else:
            raise ValueError(f"unknown kind {kind!r} of {path}")
    return _CLASSES[desc["class"]](**kw)


def _from_file(stored: tuple[dict[str, np.ndarray], dict[str, Any]],
               sink: MemorySink) -> RunEstimates:
    """The estimates of the group ``run_estimates`` (``stored``: its arrays and attributes)
    and of the run-level arrays of ``sink``'s file."""
    arrays, attrs = stored
    desc = json.loads(attrs["meta"])
    if desc.get("version") != LAYOUT_VERSION:
        raise ValueError(f"layout version {desc.get('version')!r}, not {LAYOUT_VERSION}")
    root = {}
    for name in set(_ROOT.values()):
        item = sink.read_run(name)
        if item is not None:
            root[name] = item[0]
    est = _unflatten(desc["estimates"], "", arrays, root)
    if not isinstance(est, RunEstimates):
        raise TypeError(f"{type(est).__name__}, not RunEstimates")
    return est


def _plain(obj: Any) -> Any:
    """A numpy scalar as a Python number, for JSON."""
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")
