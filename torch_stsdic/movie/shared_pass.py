"""The measuring pass of a run's shared motion (:mod:`torch_stsdic.core.shared_motion`): which
kind a run uses (:func:`torch_stsdic.movie.plan.set_shared_motion`) and its measurement by a
classical pass at a
sample of the run's POIs (:func:`estimate_shared_motion`)."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable

import numpy as np
import torch

from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.shared_motion import (
    DEFAULT_MAX_POINTS,
    DEPARTURE,
    SIGNIFICANT,
    VELOCITY_M,
    SharedMotion,
    fit_frame_motion,
    frame_chunks,
    overlap_factor,
    sample_points,
    step_increments,
    steps_from_increments,
)
from torch_stsdic.movie.classical_pass import ClassicalPass, classical_subplan
from torch_stsdic.movie.frames import frames_in_order
from torch_stsdic.movie.plan import RunPlan
from torch_stsdic.movie.sample_guess import MeasuredSample
from torch_stsdic.movie.sinks import MemorySink

#: runs a plan to its result (the signature of :func:`torch_stsdic.movie.series.run_plan`)
RunFunction = Callable[..., TrackResult]

__all__ = ["estimate_shared_motion", "shared_frames"]


def _fill(params: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Frames without an estimate (NaN rows) linearly interpolated in time (constant at
    the ends; zero where no frame has one)."""
    out = params.copy()
    ok = np.isfinite(out).all(1)
    if not ok.any():
        return np.zeros_like(out)
    for j in range(out.shape[1]):
        out[~ok, j] = np.interp(times[~ok], times[ok], out[ok, j])
    return out


def _measured_sample(sink: MemorySink, pts: torch.Tensor, valid: torch.Tensor
                     ) -> MeasuredSample:
    """The pass's trusted solutions (``valid`` (F, n)) at its sample points ``pts`` (n, 2),
    at the rows ``sink`` holds its gradients (``sink.sparse_rows``)."""
    rows = sink.sparse_rows
    at = torch.from_numpy(rows)
    return MeasuredSample.from_fields(
        pts, torch.as_tensor(sink.plan.targets, dtype=torch.long)[at],
        torch.from_numpy(sink.values["u"][rows]), torch.from_numpy(sink.values["v"][rows]),
        {nm: torch.from_numpy(a) for nm, a in sink.sparse.items()}, valid[at])


#: "auto" fits the quadratic shared motion where the sample has at least this many points
#: (its estimate then adds at most ~0.2 of the classical noise to a window), else the affine
QUADRATIC_POINTS = 500


#: the fitted motion may leave the range of the points' measured displacements by this much
#: (px), or by a quarter of that range where it is wider, at a frame before the fit is refused
PLAUSIBLE_MARGIN = 1.0


def implausible(disp: torch.Tensor, fitted: torch.Tensor, valid: torch.Tensor,
                frames: list[int]) -> str | None:
    """Why a shared-motion fit does not describe the points, or None: at some frame the
    fitted displacement (F, n, 2) lies outside the range of the trusted points' measured
    displacements ``disp`` (1st-99th percentile, +- a quarter of that range and at least
    ``PLAUSIBLE_MARGIN`` px) at more than half
    of the points (a robust fit follows the majority; one that leaves them all, as a fit
    dragged by background points that froze or diverged, is not the specimen's motion)."""
    # every frame at once: the points not trusted there are NaN in the quantiles (one host
    # read: the first frame that fails, if any)
    ok = valid & torch.isfinite(disp).all(-1)  # (a point without a finite displacement: out)
    d = torch.where(ok.unsqueeze(-1), disp, torch.nan)
    q01, q99 = torch.nanquantile(d, 0.01, dim=1), torch.nanquantile(d, 0.99, dim=1)  # (F, 2)
    margin = torch.clamp(0.25 * (q99 - q01), min=PLAUSIBLE_MARGIN)
    lo, hi = q01 - margin, q99 + margin
    outside = ((fitted < lo.unsqueeze(1)) | (fitted > hi.unsqueeze(1))).any(-1) & ok
    share = outside.sum(1).double() / ok.sum(1).clamp(min=1)  # (F,)
    bad = torch.nonzero((ok.sum(1) >= 10) & (share > 0.5)).flatten()
    if bad.numel():
        f = int(bad[0])
        lo_f, hi_f, out = lo[f].tolist(), hi[f].tolist(), float(share[f])
        return (f"at frame {frames[f]} it puts {out:.0%} of the points outside "
                f"the measured displacements (u {lo_f[0]:.2f}..{hi_f[0]:.2f}, "
                f"v {lo_f[1]:.2f}..{hi_f[1]:.2f} px)")
    return None


def shared_frames(plan: RunPlan) -> list[int]:
    """The series frames the shared-motion pass measures: every frame a window of the run
    uses."""
    return sorted(set(frames_in_order(plan.blocks, plan.config.m, len(plan.series))))


def estimate_shared_motion(plan: RunPlan, kind: str = "auto",
                           max_points: int = DEFAULT_MAX_POINTS,
                           auto: bool = False, *, run: RunFunction,
                           guess_blocks: list[list[int]] | None = None,
                           measured: ClassicalPass | None = None) -> SharedMotion:
    """Measure the shared motion of a run: classical DIC (checks off) of every series frame
    that a window of the run uses, at up to ``max_points`` of the run's POIs, then
    :func:`fit_frame_motion` over the series (one motion per frame, its robust weights from
    statistics over all frames; worked frame chunk by frame chunk). The reference frame's
    motion is exactly zero. With
    ``auto`` it is applied (``SharedMotion.applied``) only where its departure from a line in
    time is significant (:meth:`SharedMotion.significance` above ``SIGNIFICANT``), or where
    it departs from a line over the run's windows (:meth:`SharedMotion.departure` above
    ``DEPARTURE``): where neither, carrying it would only add its estimation noise to every
    window. ``kind`` "auto":
    "quadratic" where the sample holds ``QUADRATIC_POINTS`` points, else "affine" (sample 12:
    full windows at 77 % of the trusted results with the quadratic kind, 71 % with the
    affine one; the hourglass: 94.5 % and 94.9 %). ``run``: the runner of a plan
    (:func:`torch_stsdic.movie.series.run_plan`, which calls this function).
    ``guess_blocks``: the blocks that start without a carry, from the pass's solutions
    (``sample``, kept at their frames only: :meth:`MeasuredSample.near_frames`); default the
    plan's first block (classical windows, m = 0: every frame, a block after the reference
    frame's own row starts so too). ``measured``: the run's shared classical pass (its rows
    where it holds the pass's frames, at the sample points)."""

    t0 = time.perf_counter()
    n_series = len(plan.series)
    frames = shared_frames(plan)
    sel = sample_points(plan.points, max_points)
    if kind == "auto":
        kind = "quadratic" if sel.numel() >= QUADRATIC_POINTS else "affine"
    sub = classical_subplan(plan, frames, sel)
    # only what the fit uses, at the run's precision (a long movie: the pass measures every
    # frame), and the gradients of the first guess only where blocks start from it
    if guess_blocks is None and plan.config.m > 0:
        guess_blocks = plan.blocks[:1]
    near = torch.ones(len(frames), dtype=torch.bool) if guess_blocks is None else \
        MeasuredSample.near_frames(torch.as_tensor(frames, dtype=torch.long), guess_blocks,
                                   plan.config.m)
    pts = plan.points[sel].double().cpu()
    res = None if measured is None else measured.result(frames, sel)
    if res is None:
        grads = tuple(nm for nm in ("ux", "uy", "vx", "vy") if nm in sub.param_names)
        keep = ("u", "v", "zncc", "status", *(("u_std",) if "u_std" in sub.fields else ()))
        sink = MemorySink(sub, keep=keep, pair=("u", "v"),
                          at_rows=(grads, torch.nonzero(near).flatten().numpy()))
        res = run(sub, sink, progress=False)
    else:
        sink = None
    # (F, n, 2) at the pass's precision (float32: exact in the fit's float64, frame chunk by
    # frame chunk), the sink's own array where it measured them
    disp = (torch.from_numpy(sink.paired) if sink is not None and sink.paired is not None
            else torch.stack([res.u, res.v], -1).cpu())
    valid = (res.status <= USABLE).cpu() & (res.zncc.cpu() >= float(
        plan.options.get("lost_zncc", 0.8)))
    origin = plan.points.double().mean(0).cpu()
    # (F, n) at the pass's precision: made float64 frame chunk by frame chunk where used
    noise = res.std["u"].cpu() if "u" in res.std else None
    # the first guess: near the blocks' frames
    sample = (_measured_sample(sink, pts, valid) if sink is not None else
              MeasuredSample.from_result(res.select(res.frames[near].tolist()), pts,
                                         valid[near]))
    del res, sink  # the pass's fields: only what the fit uses is kept
    par, scat, used, se_t = fit_frame_motion(pts, disp, valid, kind, origin=origin,
                                             noise=noise)
    se_t = se_t * overlap_factor(pts, plan.config.subset_size)
    params = np.full((n_series, par.shape[1]), np.nan)
    scatter, se = np.full(n_series, np.nan), np.full(n_series, np.nan)
    count = np.zeros(n_series, dtype=np.int64)
    params[frames] = par.numpy()
    scatter[frames], se[frames] = scat.numpy(), se_t.numpy()
    count[frames] = used.numpy()
    if 0 <= plan.reference_frame < n_series:  # the reference against itself: exactly 0
        params[plan.reference_frame] = 0.0
        se[plan.reference_frame] = 0.0
    measured = np.isfinite(params).all(1)
    params = _fill(params, np.asarray(plan.times, dtype=np.float64))
    out = SharedMotion(kind=kind, params=params, origin=origin.numpy(), scatter=scatter,
                       points=count, measured=measured, se=se,
                       times=np.asarray(plan.times, dtype=np.float64))
    # the fitted motion at the sample, the residual from it, the typical noise of each
    # frame, the fit's plausibility and the increments the load steps are found from: frame
    # chunk by frame chunk (each with one frame more, the increment into the next chunk), a
    # long movie's pass holds no (F, n) array besides its measurements
    fidx, f = torch.as_tensor(frames), len(frames)
    sigma = torch.zeros(f, dtype=torch.float64)
    incs = torch.empty(max(f - 1, 0), dtype=torch.float64)
    reason = None
    for sl in frame_chunks(*valid.shape):
        a, b = sl.start, min(sl.stop + 1, f)
        g = out.displacement(pts, fidx[a:b]).double()
        d = disp[a:b].double()
        if reason is None:
            reason = implausible(d[:sl.stop - a], g[:sl.stop - a], valid[sl], frames[sl])
        if noise is not None:
            sigma[sl] = torch.nanmedian(torch.where(valid[sl], noise[sl].double(), torch.nan),
                                        dim=1).values
        incs[a:b - 1] = step_increments(d - g, valid[a:b])
    del disp
    out.steps = steps_from_increments(incs, sigma, frames)
    out.sample = sample
    if auto:
        z = out.significance()
        out.applied = bool(np.isfinite(z) and z > SIGNIFICANT)
        if plan.config.m > 0 and reason is None:  # smooth, not affine in time over windows
            dep = out.departure(pts, plan.config.m)
            out.extra["departure"] = None if not np.isfinite(dep) else round(dep, 3)
            if not out.applied and np.isfinite(dep) and dep > DEPARTURE:
                # its velocity at a target: over a few frames about it, not across a jump
                out.applied, out.velocity_m, out.jumps = True, VELOCITY_M, out.find_jumps(pts)
                out.extra["smoothed_frames"] = out.smooth(pts)  # its noise: in every window
    if reason is not None:
        out.applied, out.velocity_m = False, None
        out.steps, out.jumps = [], []
        out.extra["refused"] = reason
        warnings.warn(f"shared motion: not carried, the fit is implausible: {reason}; the "
                      "points may include background or a second body (choose them with "
                      "roi/mask)", RuntimeWarning, stacklevel=3)
    out.seconds = time.perf_counter() - t0
    return out
