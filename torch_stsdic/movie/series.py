"""Track a whole movie with STS-DIC: sliding 2m+1 windows, carried-forward guesses, batching.

For every target frame ``k`` the window ``k-m .. k+m`` (2m+1 frames) is solved against the
reference; the result refers to the time of frame ``k`` (``dt = t_j - t_k``, the paper's
Eqs. 1-10 with the expansion time at the target frame). At the ends of the series the
window is **shifted, not shrunk**: frames ``0 .. 2m`` for the first ``m`` targets (and the
last ``2m+1`` frames at the end), so every result averages the same number of frames.

A run is a :class:`~torch_stsdic.movie.plan.RunPlan` (validated inputs, points, reference, frame
blocks; :func:`~torch_stsdic.movie.plan.plan_run`) executed by :func:`run_plan` block by block into
a sink (:mod:`torch_stsdic.movie.sinks`: memory or an HDF5 file). :func:`track` does both.

Target frames are processed in time order, in fixed *blocks* of consecutive targets
(``batch_frames``). The first block is the first target alone, initialised by FFT
cross-correlation; every later block is initialised from the last row of the block before,
moved on by its velocity: ``u + ut (t_k - t_last)``, ``v + vt (t_k - t_last)``, gradients
carried (classical DIC, m = 0, uses the finite-difference velocity of the last two rows).
All POIs of all targets of a block go through **one** call of
:meth:`~torch_stsdic.core.solver.SubsetSolver.solve` (each row has its own frames and ``dt``).
Lost points (not converged, or ZNCC below ``lost_zncc``) are solved again with an FFT
initial guess, and the better of the two results is kept.

Frames are read lazily (:class:`~torch_stsdic.movie.frames.FrameCache`): only the frames of the
current block's windows are held, so memory is bounded by ``batch_frames + 2m`` frames (plus
the few read ahead by a background thread: :func:`~torch_stsdic.movie.frames.default_ahead`), not by
the movie length.

Determinism and resume: the carried state is always taken from the rows *as stored*
(float32, like the HDF5 file), and blocks are fixed by the target list and
``batch_frames``. A run resumed from a result file replays the finished blocks from the
file (carry, reference updates) and recomputes exactly the same pending blocks, so it ends
with the same numbers as an uninterrupted run.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.analysis.smoothing import smooth_in_time
from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.gauss_newton import ReferenceCache
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.core.status import Status
from torch_stsdic.io.run_record import as_numpy
from torch_stsdic.kernels.allocator import release_freed_memory
from torch_stsdic.movie.block import BlockContext, solve_block
from torch_stsdic.movie.carry import Carry, make_carry
from torch_stsdic.movie.estimates import (
    RunEstimates,
    measure_run,
    record_estimates,
    stored_or_measured,
)
from torch_stsdic.movie.frames import (
    FrameCache,
    FrameStore,
    default_ahead,
    frames_in_order,
    segment_bounds,
)
from torch_stsdic.movie.plan import RunPlan, plan_run
from torch_stsdic.movie.reference import Reference, maybe_update
from torch_stsdic.movie.refine import ReferenceOffsets, set_refinement
from torch_stsdic.movie.row_writer import RowWriter, carried_rows, replayed_rows
from torch_stsdic.movie.sample_guess import MeasuredSample
from torch_stsdic.movie.series_reference import SeriesReference, set_series_reference
from torch_stsdic.movie.sinks import MemorySink, open_sink
from torch_stsdic.movie.template_noise import TemplateShares

__all__ = ["track", "run_plan", "classical_smoothed", "set_reference_mode", "series_template",
           "set_window_length"]

#: the prepared frames a run keeps across its passes: up to this many times ``memory_mb``
#: (512 MiB by default: the 40 frames of the hourglass, 754 x 1273, each with its
#: coefficients and pyramid, or a 21-frame template's sample of a 1024 x 1024 movie) ...
STORE_BUDGETS = 2.0
#: ... for a movie of at most this many frames beyond two blocks' windows (the template's
#: and the window-length pass's samples); a longer movie keeps none beyond its blocks (its
#: passes read mostly other frames, and frames kept and dropped over a long run grow the
#: process's heap: a 1,200-frame 256 x 256 run peaked at 820 MB with them, 489 MB without)
STORE_FRAMES = 64


# ---------------------------------------------------------------------------------------
# running a plan
# ---------------------------------------------------------------------------------------
def run_plan(plan: RunPlan, sink: MemorySink | None = None, *, progress: bool = True,
             callback: Callable[[int, int], None] | None = None,
             estimates: RunEstimates | None = None, warm_up: bool = False,
             frames: FrameStore | None = None,
             first_guess: MeasuredSample | None = None,
             guess_every_block: bool = False) -> TrackResult:
    """Execute ``plan`` block by block into ``sink`` (default: memory) and return the result.

    Blocks the sink already holds (an interrupted run being resumed) are replayed from it, not
    recomputed. On any error or interruption the sink is closed without committing, so an
    HDF5 file keeps every finished block and can be resumed. ``estimates``: the run-level
    estimates (:class:`~torch_stsdic.movie.estimates.RunEstimates`: shared motion, load
    steps, first guess, reference made from the series, refined reference's offsets)
    measured already, e.g. on the whole movie of which ``plan`` is a piece; default: those
    ``sink``'s file recorded (a resumed run), else measured here
    (:func:`~torch_stsdic.movie.estimates.stored_or_measured`). ``warm_up``: the first block
    only seeds the carry of the next (the distributed runner's rows before a chunk): the rows
    its fit check made POOR_FIT without their point's history (the last trusted row's ZNCC)
    are carried on as trusted, as the one-process run carries a point whose fit worsens
    gradually. ``frames``: the prepared frames of the run of which ``plan`` is a pass
    (:class:`~torch_stsdic.movie.frames.FrameStore`; default: a new store, within the
    plan's ``memory_mb``). ``first_guess``: solutions of an earlier measurement of the plan's
    frames (:class:`~torch_stsdic.movie.sample_guess.MeasuredSample`) that the first block
    starts from instead of FFT cross-correlation (a template's later rounds, its gauge);
    default: the shared-motion pass's, where there is one. ``guess_every_block``: every
    block starts from ``first_guess`` where it has the row's solution (an earlier round of
    the same frames), not only the first."""
    sink = sink if sink is not None else MemorySink(plan)
    cfg = plan.config
    solver = SubsetSolver(cfg)
    if cfg.m > 0 or sum(k != plan.reference_frame for k in plan.targets) > 1:
        # the points are solved again (windows and their checks, later blocks): their
        # reference subsets are sampled once, within the working-memory budget
        solver.reference_cache = ReferenceCache(cfg.budget_mb, expected=len(plan.points))
    # the prepared frames of this run, kept across its passes (the shared-motion pass, the
    # template's rounds, the time-model pass: the sub-runs given ``frames``) and its blocks
    most = 2 * (plan.batch_frames + 2 * cfg.m) + STORE_FRAMES
    store = frames if frames is not None else FrameStore(
        STORE_BUDGETS * cfg.budget_mb if len(plan.series) <= most else 0.0, max_frames=most,
        keep_mb=STORE_BUDGETS * cfg.budget_mb)  # (the passes' samples: measure_run)
    cache = FrameCache(plan.series, solver, plan.dtype, plan.device,
                       ahead=default_ahead(plan.batch_frames, cfg.m), store=store)
    run = BlockContext(solver=solver, cache=cache,
               ts=torch.from_numpy(plan.times).to(device=plan.device, dtype=torch.float64),
               times=np.asarray(plan.times, dtype=np.float64),
               n_series=len(plan.series), m=cfg.m, dtype=plan.dtype, device=plan.device,
               lost_zncc=float(plan.options.get("lost_zncc", 0.8)), names=plan.param_names,
               checks=bool(plan.options.get("checks", True)),
               stats={"fft_rows": 0, "redone_rows": 0})
    pts = plan.points.to(device=plan.device, dtype=plan.dtype)
    if plan.reference_image is None:  # a frame of the series: read and prepared once
        held = cache.hold(plan.reference_frame)
        ref = Reference(frame=plan.reference_frame, raw=held.raw, img=held.prep, points=pts,
                        pyramid=held.pyramid())
    else:
        ref_raw = plan.reference_image.to(device=plan.device, dtype=plan.dtype)
        ref = Reference(frame=plan.reference_frame, raw=ref_raw, img=solver.prepare(ref_raw),
                        points=pts)
    run.reference_desc = plan.reference_desc  # its noise ratio is measured on the 1st block
    # ... unless the plan knows it (a template's own rounds: made from frames of known noise)
    run.noise_ratio = plan.options.get("reference_noise_ratio")
    updates: list[dict[str, Any]] = []
    if "series_reference" not in plan.options and "single_reference" not in plan.options:
        set_series_reference(plan, "auto")  # the default of a plan no one chose a reference for
    # with a result file, the noise ratio is measured now (on the first block's frames, as
    # that block would) and recorded: a resumed run reads it back, not measuring it anew on
    # its first pending block
    est = estimates if estimates is not None else stored_or_measured(
        plan, sink, ref.raw, run=functools.partial(run_plan, frames=store),
        first_noise=sink.path is not None, frames=store)
    record_estimates(est, sink)  # for a resumed run (not where they were read from the file)
    # the passes before the blocks freed what they held: its pages back to the system, so
    # that what a long movie's passes left fragmented does not stay resident under the blocks
    if estimates is None and (est.shared is not None or est.series_reference is not None
                              or est.window_m is not None or est.time_model is not None):
        release_freed_memory()  # (not after a sub-run's nothing: a few ms each)
    ref = _apply_estimates(run, est, plan, ref, first_guess, guess_every_block)
    offsets = est.row_offsets
    bar = tqdm(total=plan.n_rows, unit="frame", file=sys.stderr, disable=not progress,
               desc="STS-DIC" if cfg.m else "DIC", dynamic_ncols=True)
    try:
        try:
            writer_times = _run_blocks(plan, sink, run, ref, updates, bar, callback, offsets,
                                       warm_up)
        finally:
            frame_times = cache.finish()
        run.read_counts()  # the blocks' counters, kept on the device until now
        if plan.options.get("smoothing"):
            _smooth(plan, sink)
        info: dict[str, Any] = {
            "batch_frames": plan.batch_frames, "blocks": len(plan.blocks),
            # over the whole run, its passes included (they share the store)
            "frames_read": sum(store.reads.values()),
            "prefiltered": sum(store.prefiltered.values()),
            "pyramid_levels": sum(store.pyramid_builds.values()),
            "max_cached_frames": cache.max_cached, "reference": plan.reference_desc,
            "frame_times_s": frame_times, "writer_times_s": writer_times,
            "reference_updates": updates, "reference_noise_ratio": run.noise_ratio,
            **run.stats,
        }
        info.update(est.summary())
        info.update(plan.info())
        result = sink.result(info)
        sink.finish(result)
    except BaseException:
        bar.close()
        sink.close(commit=False)
        raise
    bar.close()
    sink.close()
    return result


def _apply_estimates(run: BlockContext, est: RunEstimates, plan: RunPlan, ref: Reference,
                     first_guess: MeasuredSample | None, guess_every_block: bool) -> Reference:
    """Set the run-level estimates ``est`` on the blocks' context ``run`` (shared motion,
    load segments, first guesses, the template's variance and shares, the time model, the
    window lengths, the noise ratio); returns the reference the blocks measure against (the
    template made from the series, where there is one)."""
    solver = run.solver
    if est.shared is not None:
        shared = est.shared
        run.shared = shared if shared.applied else None
        run.first_guess = shared.sample  # the first block starts from the pass's solutions
        if shared.steps:
            run.segments_host = segment_bounds(shared.steps, len(plan.series))
            run.segments = run.segments_host.to(plan.device)
        if run.shared is not None and shared.jumps:
            run.velocity_segments = segment_bounds(sorted(set(shared.steps) | set(
                shared.jumps)), len(plan.series)).to(plan.device)
    if first_guess is not None:
        run.first_guess = first_guess
        run.guess_every_block = bool(guess_every_block)
    if est.series_reference is not None:
        img = est.series_reference.image.to(device=plan.device, dtype=plan.dtype)
        ref = Reference(frame=-1, raw=img, img=solver.prepare(img), points=ref.points)
        if est.series_reference.added_var is not None:
            run.reference_var = est.series_reference.added_var.to(device=plan.device)
        if est.series_reference.shares is not None:
            sref = est.series_reference
            run.template_shares = TemplateShares.make(sref.frames, sref.shares,
                                                      len(plan.series), plan.reference_frame,
                                                      sref.registration, device=plan.device)
    if est.model_holds is not None:  # the time model failed at the other points
        run.classical_points = ~est.model_holds.to(device=plan.device)
    if est.window_m is not None:  # each point's window as long as its motion allows
        run.window_lengths = est.window_m.to(device=plan.device)
    if est.noise_ratio is not None:
        run.noise_ratio = est.noise_ratio
    return ref


def _run_blocks(plan: RunPlan, sink: MemorySink, run: BlockContext, ref: Reference,
                updates: list, bar: tqdm, callback,
                offsets: ReferenceOffsets | None = None, warm_up: bool = False
                ) -> dict[str, float]:
    """Solve (or replay) every block, carrying guesses and reference updates along
    (``offsets``: the refined reference's per-point offsets, subtracted before storing).
    Returns the writer's seconds (:meth:`~torch_stsdic.movie.row_writer.RowWriter.times`)."""
    row_of = plan.row_of()
    done = sink.completed_rows()
    run.cache.schedule(frames_in_order(  # read ahead the frames of the blocks to solve
        [b for b in plan.blocks if not all(row_of[k] in done for k in b)], plan.config.m,
        len(plan.series), run.host_segments()))
    carry: Carry | None = None
    rows_done = 0
    thr = plan.options.get("reference_update")
    pts0 = plan.points.to(device=plan.device, dtype=plan.dtype)
    blocks = plan.blocks  # (a property: made anew on every read)
    writer = RowWriter(sink, plan.fields, offsets)
    try:
        for b_i, block in enumerate(blocks):
            rs = [row_of[k] for k in block]
            last = b_i == len(blocks) - 1  # the last block carries nothing on
            replay = all(r in done for r in rs)
            if replay:
                writer.wait()  # (the file is the writer's until then)
                stored = sink.read_rows(rs)  # replay a finished block from the file
                sink.reference_frames[rs] = ref.frame
                seed = replayed_rows(stored, plan.param_names, offsets, plan.device)
            else:
                solved = solve_block(run, block, ref, carry)
                writer.put(rs, solved, block, ref.frame)  # written while the next is solved
                # the next carry from the same rows as stored, on the device (no host copy)
                seed = None if last and thr is None else carried_rows(
                    solved, plan.param_names, offsets, block)
            if not last:
                # in the solves' own terms: the stored rows with the offsets added back (the
                # template's gauge on the hourglass, ~0.01 px a point: every block started
                # that far off); made from the stored rows, so a resumed run carries the same
                if warm_up and b_i == 0:  # poor for the residual, judged without
                    # its history: trusted
                    seed = _warm_start(seed, float(plan.options.get("lost_zncc", 0.8)))
                carry = make_carry(seed, plan.times[block], plan.param_names, carry,
                                   plan.dtype, plan.device, frames=block)
            if thr is not None:  # (no refined reference with reference updates: the
                # seed is the stored rows)
                stored = {nm: as_numpy(v) for nm, v in seed.items()}
                ref = maybe_update(ref, stored, block[-1], float(thr), pts0, plan.param_names,
                                   run.cache, plan.dtype, plan.device, updates, rs[-1])
                if updates:  # the reference is now a frame of the series
                    run.noise_ratio = 1.0
            rows_done += len(block)  # handed over: written before the run ends, or stops
            bar.update(len(block))
            if callback is not None:
                callback(rows_done, plan.n_rows)
    finally:
        writer.close()
    return writer.times()


def _warm_start(seed: dict[str, torch.Tensor], lost_zncc: float) -> dict[str, torch.Tensor]:
    """``seed`` with its rows made POOR_FIT by their residual alone (ZNCC at least
    ``lost_zncc``) trusted: a first block judged without its points' history."""
    st, z = seed["status"], seed["zncc"]
    poor = (st == int(Status.POOR_FIT)) & (z >= lost_zncc)
    return {**seed, "status": torch.where(poor, int(Status.CONVERGED), st).to(torch.int8)}


def _smooth(plan: RunPlan, sink: MemorySink) -> None:
    """The "direct smoothing" baseline: u, v of the classical rows smoothed in time."""
    span = plan.options["smoothing"]
    t_rows = plan.row_times
    su, sut = smooth_in_time(sink.field_values("u"), span, t_rows, return_rate=True)
    sv, svt = smooth_in_time(sink.field_values("v"), span, t_rows, return_rate=True)
    sink.write_smoothed({"u": su, "v": sv, "ut": sut, "vt": svt})


# ---------------------------------------------------------------------------------------
# track
# ---------------------------------------------------------------------------------------
def track(
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
    progress: bool = True,
    out: str | os.PathLike[str] | None = None,
    resume: bool = False,
    batch_frames: int | None = None,
    reference_update: float | None = None,
    smoothing: int | None = None,
    *,
    lost_zncc: float = 0.8,
    checks: bool = True,
    overwrite: bool = False,
    callback: Callable[[int, int], None] | None = None,
    refine_reference: bool = False,
    series_reference: bool | int | str = "auto",
    series_frames: int | None = None,
    refine_frames: int | None = None,
    shared_motion: str | None = "auto",
    find_specimen: bool = True,
    strain_window: int | None = 5,
    strain_kind: str = "green",
    scale: float | None = None,
    unit: str | None = None,
    time_unit: str | None = None,
    run_estimates: RunEstimates | None = None, window_length: str = "fixed",
) -> TrackResult:
    """Track POIs through a movie with STS-DIC (sliding windows of 2m+1 frames).

    Args:
        series: anything :func:`~torch_stsdic.io.load_series` accepts (TIFF stack, directory,
            glob, list of files, (T, H, W) array/tensor) or an ImageSeries; read lazily.
        reference: frame index (int), a frame spec / list ("0:5", [0, 1, 2]) whose pixel-wise
            MEAN is the reference (less reference noise), or an (H, W) image.
        frames: target frames (spec string, int or list; default all frames of the series,
            the reference frame included). Sorted ascending; one result row each.
        points: (N, 2) POIs (x, y) px; default a grid of spacing ``step`` px inside ``roi``
            and ``mask`` (see :func:`~torch_stsdic.analysis.points.grid_points`). Given points are
            filtered by roi/mask.
        roi: (x0, y0, x1, y1) px, inclusive. mask: (H, W) array or image path, 0 = drop.
        step: grid spacing, px.
        config: :class:`DICConfig` (default DICConfig()); ``config.m`` sets the window.
        device: torch device of the computation.
        times: (T,) time of every series frame (uneven frame rates); default the series'
            timestamps, else frame indices. Velocities are px per this time unit.
        progress: tqdm progress bar on stderr (frames/s, ETA).
        out: HDF5 result path, written block by block (:class:`~torch_stsdic.movie.sinks.HDF5Sink`;
            fields u, v, ut, vt, zncc, status, iterations, ux, uy, vx, vy, and with every
            block its strains exx, eyy, exy and their rates).
        resume: continue the run recorded in ``out`` (same settings); the result equals
            an uninterrupted run. overwrite: replace an existing ``out``.
        batch_frames: target frames solved together per block (default: at most 8, 32 on a
            GPU: :func:`~torch_stsdic.movie.plan.default_batch_frames`).
        reference_update: ZNCC threshold in (0, 1): when the mean ZNCC of a block's last
            frame drops below it, that frame becomes the new reference (see docs).
        smoothing: odd span (frames): run classical DIC (config.m = 0) and smooth u, v in
            time with :func:`~torch_stsdic.analysis.smoothing.smooth_in_time` (the paper's "direct
            smoothing" baseline).
        lost_zncc: points whose ZNCC falls below this are re-solved with an FFT guess, and a
            solved point still below it is POOR_FIT.
        checks: the trust checks of :mod:`torch_stsdic.analysis.quality` (model check of every
            window against the classical solution, shorter windows where the motion is not affine
            in time, fit and neighbour checks). False: every converged point is reported so.
        callback: ``callback(rows_done, n_rows)`` after each block (all written if it raises).
        refine_reference: the template's zero displacement from the trajectories: classical
            DIC of up to ``refine_frames`` (41) frames against the template, a fit in time per
            point, its (shrunk) value at the reference time subtracted from every row
            (:mod:`~torch_stsdic.movie.refine`; pays on long movies smooth in time).
        series_reference: measure against a template of up to ``series_frames`` frames
            (default 21) mapped back by local fits of their measured warps and averaged
            (:mod:`torch_stsdic.movie.series_reference`). "auto" (default): 2 rounds where
            the reference is a frame of the series, without ``reference_update``; an
            integer: that many rounds; False: the single reference image (classical DIC's
            baseline).
        find_specimen: the default grid keeps only points whose subsets lie on speckle in the
            reference image (not on background, holes, featureless or saturated areas;
            :mod:`torch_stsdic.analysis.specimen`); False: the whole grid.
        shared_motion: the specimen's per-frame motion carried as a known term in every
            window (:mod:`torch_stsdic.core.shared_motion`): "quadratic", "affine" or
            "translation" per frame, measured by a classical pass at up to 1,000 POIs and
            fitted robustly, so a specimen that shakes or steps as a whole keeps its full
            windows. "auto" (default): for STS windows (m > 0) without ``reference_update``,
            quadratic (affine under 500 points), carried where it shakes or bends over the
            windows; None: off. The per-frame motion: ``result.shared_motion``, the file.
        strain_window, strain_kind: strains written to ``out`` (grid points per side of the
            plane fit; "green" or "small"); ``strain_window=None``: none.
        scale, unit, time_unit: calibration recorded with the results (``out`` attributes,
            ``result.info["units"]``): ``scale`` length ``unit``s per px (e.g. 0.02, "mm"),
            ``time_unit`` of ``times`` (default "frame", "time unit" with timestamps). The
            values stay in px; exports and figures convert (:mod:`torch_stsdic.io.units`).
        run_estimates: the distributed runner's hook: the whole movie's run-level estimates
            (:func:`~torch_stsdic.movie.estimates.measure_run`), not measured on its frames.
        window_length: "fixed" or "auto" (``config.m`` the longest): :func:`set_window_length`.

    Returns:
        :class:`TrackResult` with (F, N) fields; with ``out`` those of the file (float32),
        read when first used (:class:`~torch_stsdic.analysis.stored_result.StoredTrackResult`).

    Raises:
        ValueError naming the argument (see :func:`~torch_stsdic.movie.plan.plan_run`).
    """
    if resume and out is None:
        raise ValueError("resume: needs out (the result file to continue)")
    plan = plan_run(series, reference, frames, points, roi, mask, step, config, device, times,
                    batch_frames, reference_update=reference_update, smoothing=smoothing,
                    lost_zncc=lost_zncc, checks=checks, scale=scale, unit=unit,
                    time_unit=time_unit, shared_motion=shared_motion, find_specimen=find_specimen)
    set_reference_mode(plan, refine_reference, refine_frames, series_reference, series_frames)
    set_window_length(plan, window_length)
    sink = open_sink(plan, out, resume=resume, overwrite=overwrite,
                     strain_window=strain_window, strain_kind=strain_kind)
    return run_plan(plan, sink, progress=progress, callback=callback, estimates=run_estimates)


def set_reference_mode(plan: RunPlan, refine_reference: bool, refine_frames: int | None,
                       series_reference: bool | int | str, series_frames: int | None) -> None:
    """Record the reference made from the series (and its gauge from the trajectories,
    ``refine_reference``) in ``plan``."""
    if refine_reference:
        if series_reference is None or series_reference is False:
            raise ValueError("refine_reference: sets the gauge of the template made from the "
                             "series; not with series_reference=False (--single-reference)")
        set_refinement(plan, refine_frames)
    elif refine_frames is not None:
        raise ValueError("refine_frames: only with refine_reference=True")
    if series_reference is not None and series_reference is not False:
        set_series_reference(plan, series_reference, series_frames)
        if refine_reference and "series_reference" not in plan.options:
            raise ValueError(f"refine_reference: sets the gauge of the template made from the "
                             f"series, which does not apply here "
                             f"({plan.options['single_reference']})")
        if series_frames is not None and "series_reference" not in plan.options:
            raise ValueError(f"series_frames: the reference made from the series does not "
                             f"apply here ({plan.options['single_reference']})")
    elif series_frames is not None:
        raise ValueError("series_frames: only with series_reference")
    else:
        plan.options["single_reference"] = "asked for"


def set_window_length(plan: RunPlan, window_length: str) -> None:
    """Record how ``plan``'s windows get their lengths: "fixed" (default): every window of
    half-width ``config.m`` (shorter only where the model check rejects it); "auto":
    ``config.m`` is the longest, and each point and target gets the longest half-width up to
    it that its measured motion supports (:mod:`~torch_stsdic.movie.window_length`; in
    ``result.m``). Recorded in ``plan.options["window_length"]`` for STS windows."""
    if window_length not in ("fixed", "auto"):
        raise ValueError(f"window_length: must be 'fixed' or 'auto', got {window_length!r}")
    if window_length == "auto" and plan.options.get("reference_update") is not None:
        raise ValueError("window_length: 'auto' chooses windows for one reference "
                         "configuration; not with reference_update")
    if window_length == "auto" and plan.config.m > 0:
        plan.options["window_length"] = "auto"


def classical_smoothed(series: Any, span: int = 5, **kwargs: Any) -> TrackResult:
    """Classical DIC (m = 0) of ``series`` smoothed in time over ``span`` frames: shorthand
    for ``track(series, smoothing=span, **kwargs)``."""
    return track(series, smoothing=span, **kwargs)


def series_template(series: Any, points: Any = None, *, reference: int = 0, roi=None,
                    mask=None, step: int = 10, config: DICConfig | None = None,
                    device: str | torch.device = "cpu", rounds: int = 2,
                    series_frames: int | None = None, find_specimen: bool = True
                    ) -> SeriesReference:
    """The reference made from the series, for a pipeline of its own (e.g.
    :class:`torch_stsdic.nn.STSDIC`, whose ``ref`` it can be): tensors in, tensors out.

    Args:
        series: (T, H, W) tensor or array, or anything :func:`~torch_stsdic.load_series`
            reads; ``reference``: the frame whose configuration is zero displacement.
        points, roi, mask, step, config, device, find_specimen: as :func:`track`.
        rounds, series_frames: the template's rounds and most frames (2, 21).

    Returns:
        :class:`~torch_stsdic.movie.series_reference.SeriesReference`: ``image`` (H, W)
        float64, the template; ``gauge.values["u"]``, ``["v"]`` (N,) px to subtract from
        displacements measured against it at ``points`` (the template's registration as the
        reference frame reads it); ``added_var`` (N,) px^2 its share of their variance;
        ``noise_ratio`` its noise variance over a frame's.
    """
    plan = plan_run(series, reference, None, points, roi, mask, step, config, device, None,
                    None, find_specimen=find_specimen, shared_motion=None)
    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 1:
        raise ValueError(f"rounds: must be an integer >= 1, got {rounds!r}")
    set_reference_mode(plan, False, None, int(rounds), series_frames)
    est = measure_run(plan, run=run_plan)
    if est.series_reference is None:  # pragma: no cover - set_reference_mode asked for it
        raise RuntimeError("series_template: no template was made")
    return est.series_reference
