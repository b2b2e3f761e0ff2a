"""The window's length chosen from the data: per point and target frame, the longest
half-width m (up to the run's ``config.m``) whose window the measured motion supports.

A window of 2m + 1 frames lands, to within its noise, on the least-squares line through its
frames' displacements evaluated at the target (:func:`~torch_stsdic.analysis.quality.
line_offset`). Measured classically at every frame (against the reference image: its error
is common to the frames and cancels in the offset), that line minus the target's own
displacement has the mean square ``b^2 + v (1 - h)``: ``b`` the window's time-model bias,
``v`` one frame's share of a classical displacement's variance, ``h`` the window's
intercept variance factor (``1 / (2m + 1)`` at its centre, more where it is shifted at the
movie's ends or a load step). Pooled over a point's ``POOL_POINTS`` nearest POIs (the bias
is smooth in space) and the targets within m frames of it in the same load state, the
excess ``off^2 - v (1 - h)`` estimates ``b^2`` with a standard error ``se`` (the pooled
terms' scatter times the root of ``DESIGN``: neighbouring subsets share pixels, so the
terms are not independent).

A window of half-width m is accepted at a point and target where

- its estimated squared bias is at most ``GAMMA`` times the window's own noise variance
  ``v h`` (the optimum of ``b^2 + v h`` over m, for a bias growing like m^4 under a constant
  acceleration, lies at ``b^2 = v h / 4``) and at most what the window takes off (``v (1 -
  h)``: beyond, classical DIC is better), or below ``Z`` standard errors of its estimate
  (too small to tell from noise);
- fewer than half of its pooled windows miss the line by more than the model check could
  ever allow (:func:`~torch_stsdic.analysis.quality.line_mismatch`: a vibration, a jump).

The point's half-width at that target is the longest m whose shorter windows are all
accepted too (0: classical DIC). Measured from one classical pass over the frames the
windows use (at most ``TEST_FRAMES``; in a longer movie, runs of adjacent frames spread over
it, each target taking the decision of the nearest measured one).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from torch_stsdic.analysis.points import nearest_points
from torch_stsdic.analysis.quality import line_mismatch, line_offset
from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.classical_pass import ClassicalPass
from torch_stsdic.movie.frames import segment_bounds, window_frames
from torch_stsdic.movie.plan import RunPlan
from torch_stsdic.movie.series_reference import (
    BIAS_FLOOR_PX,
    POOL_CLIP,
    POOL_POINTS,
    measure_classical,
)

__all__ = ["DEFAULT_MAX_M", "TEST_FRAMES", "wants_window_lengths", "measured_frames",
           "measure_window_lengths", "window_lengths", "auto_max_m"]

#: the longest half-width a run without ``--m`` tries (2m + 1 = 13 frames)
DEFAULT_MAX_M = 6
#: the most frames the classical pass measures (beyond: runs of adjacent frames)
TEST_FRAMES = 64
#: the squared bias accepted, in units of the window's own noise variance
GAMMA = 0.5
#: standard errors of the pooled bias estimate below which a bias is not told from noise
Z = 3.0
#: the pooled mean offset's noise variance over that of independent offsets (neighbouring
#: subsets share pixels, windows of adjacent targets frames); the pooled squared offsets'
#: standard error from their scatter is too small by about its root too (measured: the
#: null's bias / standard error spread 1.7-2.0 on a linear render, window_length.md)
DESIGN = 3.0


def auto_max_m(n_frames: int, max_m: int = DEFAULT_MAX_M) -> int:
    """The longest half-width a movie of ``n_frames`` frames allows, at most ``max_m``."""
    return max(0, min(int(max_m), (int(n_frames) - 1) // 2))


def wants_window_lengths(plan: RunPlan) -> bool:
    """Whether ``plan`` chooses its windows' lengths from the data: asked for
    (``options["window_length"] == "auto"``), STS windows, one reference configuration."""
    return (plan.options.get("window_length") == "auto" and plan.config.m > 0
            and plan.options.get("reference_update") is None)


def _segments(plan: RunPlan, shared: SharedMotion | None) -> torch.Tensor | None:
    if shared is None or not shared.steps:
        return None
    return segment_bounds(shared.steps, len(plan.series))


def measured_frames(plan: RunPlan, segments: torch.Tensor | None = None,
                max_frames: int = TEST_FRAMES) -> list[int]:
    """The series frames the classical pass measures: every frame of the targets' windows
    (half-width ``config.m``), or, where those are more than ``max_frames``, runs of
    ``2 config.m + 3`` adjacent ones spread over the targets."""
    m, n_series = plan.config.m, len(plan.series)
    ks = torch.tensor(sorted(plan.targets))
    every = sorted(set(torch.unique(window_frames(ks, m, n_series, segments)).tolist())
                   | set(ks.tolist()))
    if len(every) <= max_frames:
        return every
    run = 2 * m + 3
    starts = np.unique(np.round(np.linspace(0, len(every) - run, max(1, max_frames // run))))
    return sorted({every[int(s) + j] for s in starts for j in range(run)})


def window_lengths(plan: RunPlan, res: TrackResult, frames: list[int],
                   shared: SharedMotion | None = None) -> torch.Tensor:
    """(T_series, N) int8: the half-width of each series frame's window (as a target) at each
    point, from the classical measurement ``res`` of ``frames`` against the reference image
    (module docstring). ``shared``: the shared motion carried in the windows (taken out, its
    load steps respected)."""
    max_m, n_series = plan.config.m, len(plan.series)
    pts = plan.points.double().cpu()
    n = pts.shape[0]
    seg = _segments(plan, shared)
    d = torch.stack([res.u.double().cpu(), res.v.double().cpu()], -1)  # (F, N, 2)
    if shared is not None and shared.applied:
        d = d - shared.displacement(pts, torch.as_tensor(frames)).double()
    sd = torch.stack([res.std["u"].double().cpu(), res.std["v"].double().cpu()],
                     -1).clamp(min=BIAS_FLOOR_PX)
    ok = (res.status.cpu() <= USABLE) & torch.isfinite(d).all(-1) & torch.isfinite(sd).all(-1)
    d = torch.where(ok[..., None], d, torch.nan)
    # one frame's share of a classical displacement's variance (N, 2) (as time_model_holds)
    own_var = torch.nanmedian(torch.where(ok[..., None], sd ** 2, torch.nan), 0).values / (
        1.0 + float(res.info.get("reference_noise_ratio") or 1.0))
    own_var = torch.nan_to_num(own_var, nan=float(torch.nanmedian(own_var)))
    vsum = own_var.sum(-1)  # (N,)
    t = torch.as_tensor(plan.times, dtype=torch.float64)
    pos = torch.full((n_series,), -1, dtype=torch.long)
    pos[torch.as_tensor(frames)] = torch.arange(len(frames))
    ks = torch.as_tensor(frames)  # every measured frame is a target of the test
    pool = _pooling(nearest_points(pts, min(POOL_POINTS, n))[1])  # (N, N) sparse
    seg_of = (seg[ks, 0] if seg is not None else torch.zeros_like(ks))  # (K,)
    own = d[pos[ks]]  # (K, N, 2) the targets' own displacements
    own_sd = sd[pos[ks]]
    accepted = torch.ones(len(frames), n, dtype=torch.bool)
    out = torch.zeros(len(frames), n, dtype=torch.int8)
    for m in range(1, max_m + 1):
        win = window_frames(ks, m, n_series, seg)  # (K, T)
        at = pos[win]  # (K, T) the windows' rows in res, -1: not measured
        have = (at >= 0).all(1)  # (K,)
        disp = d[at.clamp(min=0)].permute(0, 2, 1, 3)  # (K, N, T, 2) (a view)
        dt = (t[win] - t[ks][:, None]).unsqueeze(1)  # (K, 1, T): the same for all points
        off, csq = line_offset(disp, dt)  # (K, N, 2), (K, 1, 1)
        miss = line_mismatch(disp, dt, own, own_sd, line=(off, csq))  # (K, N)
        csq = csq.view(-1, 1)  # (K, 1)
        valid = torch.isfinite(off).all(-1) & have[:, None]  # (K, N)
        noise = own_var[None] * csq[..., None]  # (K, N, 2) the offset's noise variance
        term = (off.nan_to_num() ** 2 - noise).sum(-1)  # (K, N) squared bias, unbiased
        term = torch.minimum(term, POOL_CLIP * noise.sum(-1))  # a wrong peak: limited
        use = valid & ~miss
        term = torch.where(use, term, 0.0)
        # pooled over the nearest POIs, then over the targets within m frames (same state)
        near_t = ((ks[:, None] - ks[None, :]).abs() <= m) & (seg_of[:, None] == seg_of[None])
        wt = near_t.double()  # (K, K)
        # the signed offsets pooled too: a bias smooth over the pool adds up, the noise
        # averages out (far more power where the field is smooth; none where the bias
        # changes sign within the pool, which the squares above catch)
        offs = torch.where(use[..., None], off.nan_to_num(), 0.0)
        s1, s2, cnt, mu, mv, nsum = _pooled(pool, wt, torch.stack(
            [term, term ** 2, use.double(), offs[..., 0], offs[..., 1],
             torch.where(use, noise.sum(-1), 0.0)], -1))  # (K, N) each
        bias2 = s1 / cnt.clamp(min=1)
        se = ((s2 / cnt.clamp(min=1) - bias2 ** 2).clamp(min=0) / cnt.clamp(min=1)).sqrt()
        mean_off2 = (mu.pow(2) + mv.pow(2)) / cnt.clamp(min=1) ** 2
        noise_mean = nsum / cnt.clamp(min=1) ** 2 * DESIGN  # (K, N) its noise variance
        signed = mean_off2 - noise_mean
        h = (1.0 - csq)  # (K, N) the window's intercept variance over one frame's
        fails = wt @ (miss & valid).double()  # the point's own windows
        tests = wt @ valid.double()
        limit = torch.minimum(GAMMA * h, 1.0 - h) * vsum
        good = ((bias2 <= torch.maximum(limit, Z * DESIGN ** 0.5 * se))  # (correlated)
                & (signed <= torch.maximum(limit, Z * 2 ** 0.5 * noise_mean))
                & (2 * fails < tests)
                & have[:, None] & (cnt > 0))
        accepted &= good
        out = torch.where(accepted, m, out).to(torch.int8)
    # every series frame: the decision of the nearest measured target
    near = (t[:, None] - t[ks][None, :]).abs().argmin(1)  # (T_series,)
    return out[near]


def _pooling(nb: torch.Tensor) -> torch.Tensor:
    """(N, N) sparse float64: row i holds a 1 at each of point i's pool ``nb[i]`` (N, P)
    (its nearest POIs, itself included): ``pool @ x`` sums x (N, C) over every pool."""
    n, p = nb.shape
    rows = torch.arange(n, dtype=torch.int64).repeat_interleave(p)
    return torch.sparse_coo_tensor(torch.stack([rows, nb.reshape(-1).to(torch.int64)]),
                                   torch.ones(n * p, dtype=torch.float64), (n, n),
                                   check_invariants=True).coalesce()


def _pooled(pool: torch.Tensor, wt: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """x (K, N, C) summed over each point's pool (``pool``: :func:`_pooling`), then over the
    targets ``wt`` (K, K) weights: C tensors (K, N)."""
    k, n, c = x.shape
    by_point = (pool @ x.permute(1, 0, 2).reshape(n, k * c)).view(n, k, c)
    return torch.einsum("kj,njc->ckn", wt, by_point).unbind(0)


def measure_window_lengths(plan: RunPlan, run: Callable[..., TrackResult],
                           shared: SharedMotion | None = None,
                           measured: ClassicalPass | None = None) -> torch.Tensor:
    """(T_series, N) int8 the window half-widths of ``plan`` (:func:`window_lengths`) from a
    classical pass over :func:`measured_frames` against the plan's reference image (the
    run's shared one, ``measured``, where it holds those frames)."""
    seg = _segments(plan, shared)
    frames = measured_frames(plan, seg)
    res = None if measured is None else measured.result(frames)
    if res is None:
        res = measure_classical(plan, frames, run)
    return window_lengths(plan, res, frames, shared)


def distribution(m_used: np.ndarray, ok: np.ndarray, max_m: int) -> dict[int, float]:
    """The share of trusted results (``ok``) at each half-width 0 .. ``max_m``."""
    mu = np.asarray(m_used)[np.asarray(ok, dtype=bool)]
    if mu.size == 0:
        return {}
    return {m: float((mu == m).mean()) for m in range(int(max_m) + 1)}
