"""A reference made from the series: a sample of the movie's images mapped back to the reference
configuration and averaged into a template, the movie then measured against the template.

Each sampled frame is first measured classically against the reference image. Its warps (u,
v, their gradients) are replaced at every POI by a local plane or quadratic fitted over the
POI's neighbours (:mod:`torch_stsdic.analysis.local_fit`): the measured warps carry the
reference image's noise, which averaging frames cannot remove, while the fit averages it
over the neighbourhood. A frame enters the template at a POI only where its fit passes its
tests, its subset matched as well as its texture allows, and every neighbour is trusted (a
guard band around cracks and lost regions). Each POI maps the pixels of its window by its
fit, samples the frame there (B-spline of the run's order), brings it to the reference's
grey levels over the window, and adds it with a tent weight and the inverse of the frame's
noise variance; pixels no frame covers keep the reference frame's value. Rounds of
"measure against the template, make it again" follow. The reference frame, whose
displacement is zero by definition, is finally measured against the template: what it reads
(smoothed by the same planes, shrunk where below its noise) is the template's registration
error, subtracted from every row (the gauge). The first round also decides where the STS
window cannot help (:func:`time_model_holds`).

Measured (docs/validation/series_reference.md): STS m=2 at 0.37x classical DIC on DIC
Challenge sample 3 and 0.40x on renders of 11-41 frames (theory sqrt((1/5 + 1/N) / 2)).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.local_fit import LocalFit, local_fit_weights
from torch_stsdic.analysis.points import nearest_points
from torch_stsdic.analysis.quality import line_mismatch, line_offset
from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.noise import immerkaer_sigmas
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.movie.classical_pass import ClassicalPass, classical_subplan
from torch_stsdic.movie.frames import FrameCache, FrameStore
from torch_stsdic.movie.plan import RunPlan, guessed_blocks
from torch_stsdic.movie.refine import ReferenceOffsets
from torch_stsdic.movie.sample_guess import MeasuredSample
from torch_stsdic.movie.template_image import TemplateWindows, template_image

__all__ = ["SeriesReference", "DEFAULT_FRAMES", "DEFAULT_ITERATIONS", "sample_frames",
           "build_series_reference", "set_series_reference", "single_reason",
           "time_model_holds", "measure_classical"]

#: frames of the movie sampled for the template (evenly spread over the targets)
DEFAULT_FRAMES = 21
#: template / classical-measurement rounds
DEFAULT_ITERATIONS = 2
#: POIs of each local plane that registers the template (a 5 x 5 block of the grid; 0: none)
DEFAULT_NEIGHBOURS = 25
#: a frame's 1 - ZNCC at a POI beyond this many times the POI's best, or MISFIT_SPREAD times
#: the frame's median, leaves it out of the template there (:func:`_matched`)
MISFIT_RATIO, MISFIT_SPREAD = 3.0, 20.0
#: POIs over which a point's time-model bias is pooled (:func:`time_model_holds`)
POOL_POINTS = 25
#: the most a point's own excess counts in its neighbours' pools, in units of its own gain
POOL_CLIP = 3.0
#: px: the least standard deviation the time-model test grants a classical displacement:
#: the interpolation bias every solution carries alike (a cubic B-spline on a noise-free
#: speckle moving 0.3 px a frame: 3.7e-4 px RMS, 2.7x its u_std) is no time-model failure
BIAS_FLOOR_PX = 1e-3
#: |plane - quadratic| / its std beyond which a frame is left out of the template at a POI
PLANE_Z = 5.0
#: the neighbourhoods (POIs: 5 x 5, 7 x 7, 9 x 9 blocks of a grid) whose local fits may
#: register a frame at a POI, beyond the run's ``neighbours`` (the smallest): at each frame
#: and POI the passing fit of least variance (:class:`RegistrationFits`). The template's
#: registration error, common to every row, is the reference image's noise through the
#: fits (docs/validation/window_length.md): a plane over 81 POIs passes a third of a plane
#: over 25's variance where the field allows it
NEIGHBOURHOODS = (25, 49, 81)
#: relative difference below which two fits' variance factors are equal (:func:`_fit_choice`)
TIE = 1e-9
#: (frame, POI) pairs x neighbours of :func:`_smooth`'s work arrays per chunk of POIs (its
#: weights worked out there: memory bounded for any number of POIs and frames)
MAP_CHUNK = 1 << 19
#: pixels a frame's noise is estimated over (:func:`_frame_noise`: the middle of the POIs'
#: box; Immerkaer's estimate over 2^18 pixels has a relative error of ~0.3 %, far below the
#: frames' differences it weighs)
NOISE_PIXELS = 1 << 18
NOISE_CHUNK_PIXELS = 1 << 20  # pixels of the frames' boxes whose noise is estimated at once
WINDOW_CHUNK = 1 << 22  # displacements (windows x points x frames x 2) judged at once


@dataclass
class SeriesReference:
    """The template and what it rests on."""

    image: torch.Tensor  # (H, W) the template, float64
    noise_ratio: float  # its pixels' noise variance over one frame's
    added_var: torch.Tensor | None  # (N,) px^2 added to u_std^2, v_std^2: registration, noise
    frames: list[int]  # the sampled frames (series indices)
    iterations: int
    coverage: float  # share of the POIs' window pixels averaged over >= 2 frames
    seconds: float
    plane_share: float | None = None  # share of the frames x POIs registered by a plane
    fit_share: float | None = None  # ... by a plane or a quadratic (the rest left out)
    gauge: ReferenceOffsets | None = None  # the template's registration as the reference saw it
    #: (N,) bool where the STS window's time model held in the sampled frames (None: not
    #: tested); the run solves the other points classically (:func:`time_model_holds`)
    model_holds: torch.Tensor | None = None
    #: (F, N) each sampled frame's weight in the template at each POI (summing to 1): the
    #: noise it shares with the windows' frames (:mod:`~torch_stsdic.movie.template_noise`)
    shares: torch.Tensor | None = None
    #: (N,) the variance factor of the local fits that registered the frames to the
    #: reference frame (0 where none did; None: no reference frame, ``added_var`` holds it)
    registration: torch.Tensor | None = None

    def summary(self) -> dict[str, Any]:
        return {"frames": list(self.frames), "iterations": self.iterations,
                "noise_ratio": round(self.noise_ratio, 4),
                "added_std_px": (None if self.added_var is None
                                 else round(float(self.added_var.mean().sqrt()), 6)),
                "coverage": round(self.coverage, 4), "seconds": round(self.seconds, 3),
                "plane_share": (None if self.plane_share is None
                                else round(self.plane_share, 4)),
                "fit_share": None if self.fit_share is None else round(self.fit_share, 4),
                "classical_points": (None if self.model_holds is None
                                     else int((~self.model_holds).sum())),
                "gauge_rho": None if self.gauge is None else round(float(self.gauge.rho), 4),
                "gauge_rms_px": (None if self.gauge is None else round(float(np.sqrt(np.mean(
                    self.gauge.values["u"] ** 2 + self.gauge.values["v"] ** 2) / 2)), 6))}


def _unit_variance(res: TrackResult) -> torch.Tensor:
    """(N,) px^2 one image's share of a classical displacement's variance per POI, from a
    classical measurement's predicted std (both images noisy: half the variance when the
    reference is one frame; divided by 1 + its noise ratio otherwise): the median over the
    frames (a frame whose solve was nearly singular there predicts thousands of px^2; the
    mean made u_std 21 px at a well-matched point of the hourglass without a region)."""
    ratio = float(res.info.get("reference_noise_ratio") or 1.0)
    var = (res.std["u"].double().cpu().pow(2) + res.std["v"].double().cpu().pow(2)) / 2
    ok = res.status.cpu() <= USABLE
    var = torch.where(ok, var, torch.nan)
    per_point = torch.nanmedian(var, 0).values / (1.0 + ratio)
    return torch.nan_to_num(per_point, nan=float(torch.nanmean(per_point)))


def sample_frames(plan: RunPlan, max_frames: int = DEFAULT_FRAMES) -> list[int]:
    """About ``max_frames`` frames spread over the targets, the reference frame (in the series)
    among them: for STS windows in runs of 2m + 3 adjacent targets (three windows each,
    :func:`time_model_holds`), at least two, at the targets' start and end (21 frames: 22, 26,
    30 at m = 4, 5, 6); else, and where two runs do not fit, one by one."""
    if int(max_frames) < 2:
        raise ValueError(f"series_reference: needs >= 2 frames, got {max_frames!r}")
    ks = sorted(set(plan.targets) | ({plan.reference_frame} if plan.reference_frame >= 0
                                     else set()))
    run = 2 * plan.config.m + 3
    n_runs = min(max(2, round(int(max_frames) / run)), len(ks) // run)
    auto = plan.options.get("window_length") == "auto"  # its own test: evenly spread
    if len(ks) <= max_frames:
        return ks
    if plan.config.m > 0 and n_runs >= 2 and int(max_frames) >= run and not auto:
        starts = np.unique(np.round(np.linspace(0, len(ks) - run, n_runs)))
        chosen = {ks[int(s) + j] for s in starts for j in range(run)}
    else:
        pick = np.unique(np.round(np.linspace(0, len(ks) - 1, int(max_frames))).astype(int))
        chosen = {ks[i] for i in pick}
    if plan.reference_frame >= 0:
        chosen.add(plan.reference_frame)
    return sorted(chosen)


def _measure(plan: RunPlan, frames: list[int], image: torch.Tensor | None,
             run: Callable[..., TrackResult], guess: MeasuredSample | None = None,
             ratio: float | None = None) -> TrackResult:
    """Classical DIC (checks off) of ``frames`` at all the plan's POIs, against the plan's
    reference or against ``image`` (a template of noise variance ``ratio`` times a
    frame's, as :func:`template_image` made it: not estimated from its pixels again);
    every block starts from ``guess`` (an earlier round's solutions, in blocks as long as
    the memory budget allows: :func:`~torch_stsdic.movie.plan.guessed_blocks`; None: FFT
    cross-correlation, then the carry)."""
    sub = classical_subplan(plan, frames)
    if image is not None:
        sub = dataclasses.replace(sub, reference_image=image, reference_frame=-1,
                                  reference_desc="array:series-template",
                                  options={**sub.options, "reference_noise_ratio": ratio})
    if guess is None:
        return run(sub, progress=False)
    return run(guessed_blocks(sub), progress=False, first_guess=guess, guess_every_block=True)


def _round_guess(plan: RunPlan, res: TrackResult) -> MeasuredSample:
    """A round's trusted solutions at all the plan's POIs, where the next round (against the
    template, which the fits registered to the reference configuration: the same warps but
    for the noise) and the gauge start."""
    # a TrackResult holds its integer fields on the CPU, the others on the run's device
    ok = (res.status.cpu() <= USABLE) & (res.zncc.cpu() >= float(plan.options.get("lost_zncc",
                                                                                   0.8)))
    return MeasuredSample.from_result(res, plan.points.double().cpu(), ok)


def measure_classical(plan: RunPlan, frames: list[int], run: Callable[..., TrackResult]
                      ) -> TrackResult:
    """Classical DIC (checks off) of ``frames`` at all the plan's POIs against its reference
    image: the template's first-round measurement (:func:`_measure`)."""
    return _measure(plan, frames, None, run)


def _all_warps(plan: RunPlan, res: TrackResult) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, N, 6) u, ux, uy, v, vx, vy of every row of ``res`` (gradients 0 where not solved)
    and (F, N) whether each is trusted (usable, ZNCC at least ``plan``'s ``lost_zncc``), on
    the host: every row at once (a field copied to the host once, not once a frame)."""
    lost_zncc = float(plan.options.get("lost_zncc", 0.8))
    f, n = res.u.shape
    cols = []
    for nm in ("u", "ux", "uy", "v", "vx", "vy"):
        try:
            cols.append(res.field(nm).double().cpu())
        except (KeyError, AttributeError):
            cols.append(torch.zeros(f, n, dtype=torch.float64))
    w = torch.stack(cols, -1)
    ok = ((res.status.cpu() <= USABLE) & torch.isfinite(w).all(-1)
          & (res.zncc.double().cpu() >= lost_zncc))
    return torch.nan_to_num(w), ok


def _frame_noise(plan: RunPlan, frames: list[int], cache: FrameCache) -> list[float]:
    """The image noise sigma (grey levels) of each of ``frames`` (Immerkaer's estimate) over
    the box that the POIs' subsets cover (the pixels the template is made of; a background
    or a frame's border would only add work, and its own noise), its middle
    ``NOISE_PIXELS`` where larger; the frames read by ``cache`` (the run's)."""
    h, w = plan.series.shape
    pts = plan.points.double().cpu()
    pad = (plan.config.subset_size - 1) // 2 + 2
    x0, y0 = (pts.amin(0).floor() - pad).long().clamp(min=0).tolist()
    x1, y1 = (pts.amax(0).ceil() + pad + 1).long().tolist()
    x1, y1 = min(max(x1, x0 + 8), w), min(max(y1, y0 + 8), h)
    x0, y0 = min(x0, max(w - 8, 0)), min(y0, max(h - 8, 0))
    shrink = math.sqrt(NOISE_PIXELS / max((x1 - x0) * (y1 - y0), 1))
    if shrink < 1.0:  # the box's middle, its shape kept
        bw, bh = max(8, int((x1 - x0) * shrink)), max(8, int((y1 - y0) * shrink))
        x0, y0 = (x0 + x1 - bw) // 2, (y0 + y1 - bh) // 2
        x1, y1 = x0 + bw, y0 + bh
    per = max(1, NOISE_CHUNK_PIXELS // ((y1 - y0) * (x1 - x0)))  # (a chunk stays in cache)
    sig = [immerkaer_sigmas(torch.stack([cache.read(k)[y0:y1, x0:x1] for k in frames[i:i + per]]))
           for i in range(0, len(frames), per)]
    return torch.cat(sig).clamp(min=1e-6).tolist() if sig else []


def time_model_holds(plan: RunPlan, res: TrackResult, frames: list[int],
                     shared: SharedMotion | None = None) -> torch.Tensor | None:
    """(N,) bool: the points where the STS window helps, from the classical measurement
    ``res`` of the sampled ``frames`` against the reference image. Every 2m + 1 adjacent
    sampled frames (not across a load step of ``shared``, the shared motion taken out) make
    a window; the least-squares line through their classical displacements, at the target,
    minus the target's own (:func:`~torch_stsdic.analysis.quality.line_offset`) is where the
    window's solution lands from the classical one.

    A point is solved classically in the run (no window solve, no check: what a classical
    run costs there) where either

    - half or more of at least three windows miss the line by more than the model check
      could ever allow (:func:`~torch_stsdic.analysis.quality.line_mismatch`), or
    - the windows that would pass it carry a time-model bias that costs more than the
      window saves: over the point's ``POOL_POINTS`` nearest POIs (a smooth field: the bias
      varies slowly), the offsets' mean square less its noise (one frame's variance times
      ``sum c^2``) exceeds the variance the window takes off the target's displacement
      (one frame's times 2m / (2m + 1)); each point's own excess counts up to
      ``POOL_CLIP`` times its own gain, so that one gross mismatch (a wrong peak in a few
      frames) does not turn its neighbours classical. Such windows pass the model check,
      whose limit is some standard deviations, and would leave the point less accurate
      than a classical solve (a load series whose steps are not even: DIC Challenge
      sample 12).

    A displacement's standard deviation counts as at least ``BIAS_FLOOR_PX`` here: on
    noise-free images the interpolation bias, which the classical solution carries too,
    would otherwise pass for a time-model failure.

    None where no point had three windows (m = 0, checks off, too few adjacent frames)."""
    m = plan.config.m
    if m == 0 or not plan.options.get("checks", True) or "u" not in res.std:
        return None
    pts = plan.points.double().cpu()
    d = torch.stack([res.u.double().cpu(), res.v.double().cpu()], -1)  # (F, N, 2)
    if shared is not None and shared.applied:
        d = d - shared.displacement(pts, torch.as_tensor(frames)).double()
    sd = torch.stack([res.std["u"].double().cpu(), res.std["v"].double().cpu()],
                     -1).clamp(min=BIAS_FLOOR_PX)
    ok = (res.status.cpu() <= USABLE) & torch.isfinite(d).all(-1)
    # one frame's share of a classical displacement's variance (both images noisy), (N, 2):
    # the median over the frames (:func:`_unit_variance`: a nearly singular solve in one
    # frame must not set the point's noise, nor its neighbourhood's pooled sums)
    own_var = torch.nanmedian(torch.where(ok[..., None], sd ** 2, torch.nan), 0).values / (
        1.0 + float(res.info.get("reference_noise_ratio") or 1.0))
    t = torch.as_tensor(plan.times[frames], dtype=torch.float64)
    steps = list(shared.steps) if shared is not None and shared.steps else []
    n = pts.shape[0]
    fails = torch.zeros(n, dtype=torch.int64)
    tests = torch.zeros(n, dtype=torch.int64)
    excess = torch.zeros(n, dtype=torch.float64)  # sum over passing windows: off^2 - noise
    gain = torch.zeros(n, dtype=torch.float64)  # ... the variance the window takes off
    # the windows of 2m + 1 adjacent sampled frames within one load state, at once
    starts = [j0 for j0 in range(len(frames) - 2 * m) if frames[j0 + 2 * m] - frames[j0] == 2 * m
              and not any(frames[j0] < s <= frames[j0 + 2 * m] for s in steps)]
    per = max(1, WINDOW_CHUNK // (2 * n * (2 * m + 1)))
    for c0 in range(0, len(starts), per):
        j0 = torch.as_tensor(starts[c0:c0 + per])
        idx = j0.unsqueeze(1) + torch.arange(2 * m + 1)  # (W, T) rows of the sampled frames
        disp = d[idx].permute(0, 2, 1, 3)  # (W, N, T, 2)
        dt = (t[idx] - t[j0 + m].unsqueeze(1)).unsqueeze(1)  # (W, 1, T)
        off, csq = line_offset(disp, dt)
        miss = line_mismatch(disp, dt, d[j0 + m], sd[j0 + m], line=(off, csq))  # (W, N)
        valid = ok[idx].all(1)
        fails += (miss & valid).long().sum(0)
        tests += valid.long().sum(0)
        kept = valid & ~miss & torch.isfinite(own_var).all(-1)
        v = torch.where(kept[..., None], own_var, 0.0)
        excess += torch.where(kept, (off.nan_to_num() ** 2 - v * csq).sum(-1), 0.0).sum(0)
        gain += (v * (2 * m / (2 * m + 1))).sum(-1).sum(0)
    if int(tests.max()) < 3:
        return None
    nb = nearest_points(pts, min(POOL_POINTS, n))[1]
    # a point's own excess counts up to POOL_CLIP times its own gain: a gross mismatch at one
    # point (a wrong peak in a few frames) must not decide for all its neighbours
    excess = torch.minimum(excess, POOL_CLIP * gain)
    biased = excess[nb].sum(1) > gain[nb].sum(1)
    return ~(((tests >= 3) & (2 * fails >= tests)) | biased)


def _matched(res: TrackResult, frames: list[int], reference_frame: int) -> torch.Tensor:
    """(F, N) whether each frame's subset matched the reference as well as the subset's
    texture allows: its misfit ``1 - ZNCC`` at most ``MISFIT_RATIO`` times the point's best
    over the frames (a subset that straddles a crack or a lost region after it opened) and
    ``MISFIT_SPREAD`` times the frame's median over the points (one that straddles it in
    every frame; subsets of poor contrast have up to 10x the median's misfit). Such a
    subset's warp is a compromise of two motions that the local fits can take for a strain."""
    misfit = (1.0 - res.zncc.double().cpu()).clamp(min=1e-6)
    own = torch.tensor([k != reference_frame for k in frames])
    if not bool(own.any()):
        return torch.ones_like(misfit, dtype=torch.bool)
    others = torch.where(own[:, None], misfit, torch.inf)
    best = torch.nan_to_num(others, nan=torch.inf).amin(0)  # (N,)
    typical = torch.nanmedian(torch.where(own[:, None], misfit, torch.nan), 1).values  # (F,)
    ok = (misfit <= MISFIT_RATIO * best[None, :]) & (misfit <= MISFIT_SPREAD * typical[:, None])
    return ~own[:, None] | ok


@dataclass
class RegistrationFits:
    """The local fits that may register a frame at a POI (:func:`_fit_choice`): every
    (neighbourhood, degree) of ``NEIGHBOURHOODS`` (from the run's ``neighbours`` up; a plane
    or a quadratic, tested against the next degree) and a cubic over the smallest (against
    the quartic: a field that bends more than a quadratic over it, as a specimen's load
    grows), with each one's variance factor at each POI (``w^T R w``: the share of one
    POI's noise its fitted value keeps). Memory linear in N with a small constant: the
    fits keep their neighbours, whether each degree is posed and the smallest
    neighbourhood's plane weights (the gauge's), 6.2 kB a POI over 25, 49, 81 POIs; the
    maps' weights are made by chunks of POIs where chosen (:func:`_smooth`)."""

    fits: list[LocalFit]  # one per neighbourhood, degrees 1 .. 3 (the smallest: .. 4)
    candidates: list[tuple[int, int]]  # (index into fits, degree)
    #: (C, N) float64 each candidate's variance factor, from the fits' tests
    #: (:func:`_fit_choice`, which works them out in the same pass) or on first use
    _factor: torch.Tensor | None = None

    @property
    def factor(self) -> torch.Tensor:
        """(C, N) float64 each candidate's variance factor ``w^T R w``."""
        if self._factor is None:
            per_fit = [fit.value_factors(self.degrees(i)) for i, fit in enumerate(self.fits)]
            self._factor = torch.stack([per_fit[i][d] for i, d in self.candidates])
        return self._factor

    @classmethod
    def make(cls, pts: torch.Tensor, neighbours: int, subset_size: float) -> RegistrationFits:
        """The fits of the POIs ``pts`` (N, 2) over ``neighbours`` POIs and the larger
        ``NEIGHBOURHOODS`` of at most N / 3 POIs."""
        n = pts.shape[0]
        small = max(int(neighbours), 10)
        # a larger neighbourhood only where it is local: at most a third of the POIs (over
        # nearly all, every POI's registration error would be one and the same field)
        sizes = [small] + [k for k in NEIGHBOURHOODS if small < k <= n // 3]
        # weights kept: the smallest's planes (the gauge's); the maps' by chunks (_smooth)
        fits = [local_fit_weights(pts, k, subset_size, degrees=(1, 2, 3, 4) if i == 0
                                  else (1, 2, 3), keep=(1,) if i == 0 else ())
                for i, k in enumerate(sizes)]
        candidates = [(i, d) for i in range(len(fits)) for d in (1, 2)] + [(0, 3)]
        return cls(fits=fits, candidates=candidates)

    def degrees(self, i: int) -> tuple[int, ...]:
        """The degrees of the candidates over the neighbourhood ``fits[i]``."""
        return tuple(d for j, d in self.candidates if j == i)

    def degree(self, choice: torch.Tensor) -> torch.Tensor:
        """(F, N) the degree (1 .. 3; 0: none) of the fits ``choice`` (F, N) (0: none, c + 1:
        candidate c)."""
        deg = torch.tensor([0] + [d for _, d in self.candidates])
        return deg[choice]

    def variance(self, choice: torch.Tensor) -> torch.Tensor:
        """(F, N) the variance factor of the fits ``choice`` (0 where none)."""
        f = torch.cat([torch.zeros(1, self.factor.shape[1], dtype=torch.float64),
                       self.factor])  # (C + 1, N)
        return f.gather(0, choice.long())

    def guard(self, choice: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
        """(F, N) where the fit ``choice`` was made and every one of its neighbours is
        trusted (``ok`` (F, N)): a guard band around cracks and lost regions."""
        out = torch.zeros_like(choice, dtype=torch.bool)
        for i, fit in enumerate(self.fits):
            cs = [c + 1 for c, (j, _) in enumerate(self.candidates) if j == i]
            here = torch.isin(choice, torch.tensor(cs))
            if bool(here.any()):
                out |= here & ok[:, fit.index].all(-1)
        return out


def _fit_choice(reg: RegistrationFits, warps: torch.Tensor, ok: torch.Tensor,
                unit: torch.Tensor) -> torch.Tensor:
    """(F, N) the local fit that registers each frame at each POI (0: none, c + 1: candidate
    c of ``reg``): of the fits that pass their tests against the next degree
    (:meth:`~torch_stsdic.analysis.local_fit.LocalFit.test_z`, every degree of a
    neighbourhood in one pass, on u and v of that frame measured against the reference
    image: both images' noise, ``unit``: (N,) one image's share of a classical
    displacement's variance) and whose neighbours are all trusted (``ok``: a guard band
    around a crack, a lost region, the points that straddle them), the one of least
    variance factor (equal to ``TIE``: the one listed first): a larger neighbourhood where
    the field allows it, a plane before a quadratic over the same POIs; none: the frame is
    left out of the template there. Fills ``reg``'s factors from the same pass."""
    f, n = ok.shape
    # every frame's u and v as the rows of one test: (2F, N), rows u_0, v_0, u_1, v_1, ...
    vals = torch.where(ok[..., None], warps[..., [0, 3]], 0.0).transpose(1, 2).reshape(2 * f, n)
    var = (2.0 * unit)[None]  # (1, N): every row's
    passes, factor = [], {}  # per neighbourhood: degree -> (F, N); (i, degree) -> (N,)
    for i, fit in enumerate(reg.fits):  # every degree of a neighbourhood in one pass
        tests = fit.test_z(vals, var, reg.degrees(i))
        trusted = ok[:, fit.index].all(-1)
        passes.append({d: t.passes(PLANE_Z).view(f, 2, n).all(1) & trusted
                       for d, t in tests.items()})
        factor.update({(i, d): t.factor for d, t in tests.items()})
    if reg._factor is None:
        reg._factor = torch.stack([factor[c] for c in reg.candidates])
    best = torch.full((f, n), torch.inf, dtype=torch.float64)
    choice = torch.zeros(f, n, dtype=torch.long)
    for c, (i, d) in enumerate(reg.candidates):
        # an equal factor (the cubic's value weights are the quadratic's at a POI whose
        # neighbours lie symmetric about it) keeps the candidate listed first
        better = passes[i][d] & (reg.factor[c][None] < best * (1.0 - TIE))
        best = torch.where(better, reg.factor[c][None], best)
        choice = torch.where(better, c + 1, choice)
    return choice


def _smooth(reg: RegistrationFits, warps: torch.Tensor, ok: torch.Tensor,
            choice: torch.Tensor) -> torch.Tensor:
    """(F, N, 12) the maps of the frames at the POIs: u, its gradient and its coefficients
    of dx^2, dx dy, dy^2 (px offsets from the POI), then the same of v; the local fit
    ``choice`` (F, N) of ``reg`` (:func:`_fit_choice`; its neighbours trusted, ``ok``),
    elsewhere the POI's own warp (no second-order terms). The second-order terms matter
    where the field curves: a gradient of 10 % over 200 px moves a pixel 15 px from the POI
    by 0.06 px."""
    f, n = warps.shape[:2]
    out = torch.zeros(f, n, 12, dtype=torch.float64)
    out[..., 0:3], out[..., 6:9] = warps[..., 0:3], warps[..., 3:6]
    vals = torch.where(ok[..., None], warps[..., [0, 3]], 0.0)  # (F, N, 2) u, v
    for k, (i, d) in enumerate(reg.candidates):
        fit = reg.fits[i]
        chosen = (choice == k + 1) & fit.posed[d][None]  # (F, N)
        where = torch.nonzero(chosen.any(0)).flatten()  # POIs where it registers a frame
        step = max(1, MAP_CHUNK // (fit.index.shape[1] * f))
        for s0 in range(0, where.numel(), step):
            rows = where[s0:s0 + step]
            # (n, k, 6) the weights of the value, the slopes, the second-order coefficients
            weights = fit.map_weights(d, rows)
            at, fr = torch.nonzero(chosen[:, rows].T, as_tuple=True)
            pt = rows[at]
            nb = vals[fr[:, None], fit.index[pt]]  # (M, k, 2) only where chosen
            terms = torch.einsum("mkc,mkq->mcq", nb, weights[at])  # (M, 2, 6)
            here = out[fr, pt].view(-1, 2, 6)
            out[fr, pt] = torch.where(torch.isfinite(terms).all(-1, keepdim=True), terms,
                                      here).reshape(-1, 12)
    return out


def build_series_reference(plan: RunPlan, ref_raw: torch.Tensor, *,
                           run: Callable[..., TrackResult],
                           max_frames: int = DEFAULT_FRAMES,
                           iterations: int = DEFAULT_ITERATIONS,
                           neighbours: int = DEFAULT_NEIGHBOURS,
                           shared: SharedMotion | None = None,
                           measured: ClassicalPass | None = None,
                           frames: FrameStore | None = None) -> SeriesReference:
    """The template of ``plan``: ``iterations`` rounds of a classical measurement of the
    sampled frames (:func:`sample_frames`; the first against the plan's reference image
    ``ref_raw`` (H, W), the others against the last template) and a template from their
    warps, replaced by each POI's local fit over its ``neighbours`` nearest POIs; a frame
    enters the template at a POI only where its first-round warp matched
    (:func:`_matched`), one of its fits passed (:func:`_fit_choice`: over ``neighbours`` POIs
    or a larger neighbourhood of ``NEIGHBOURHOODS``) and every neighbour of it is trusted.
    The first round also decides where the time model holds (:func:`time_model_holds`,
    with the ``shared`` motion taken out). Then the template's registration as the
    reference frame measures it (:func:`_gauge`), where the reference is a frame of the
    series.
    ``run``: the runner of a plan (:func:`torch_stsdic.movie.series.run_plan`);
    ``measured``: the run's shared classical pass (the first round's rows where it has
    them); ``frames``: the run's prepared frames (the sampled frames' pixels and B-spline
    coefficients are taken from there, and put there: each frame is prepared once per
    run)."""
    if int(iterations) < 1:
        raise ValueError(f"series_reference: iterations must be >= 1, got {iterations!r}")
    t0 = time.perf_counter()
    cache = FrameCache(plan.series, SubsetSolver(plan.config), plan.dtype, plan.device,
                       store=frames)
    frames = sample_frames(plan, max_frames)
    sigmas = _frame_noise(plan, frames, cache)  # the same in every round
    pts = plan.points.double().cpu()
    reg = RegistrationFits.make(pts, neighbours, plan.config.subset_size)
    fit = reg.fits[0]  # the smallest neighbourhood: the gauge's planes
    image = choice = unit = matched = guess = ratio = None
    windows = TemplateWindows.make(plan, ref_raw)  # the same in every round
    for _ in range(int(iterations)):
        res = measured.result(frames) if image is None and measured is not None else None
        if res is None:
            res = _measure(plan, frames, image, run, guess, ratio)
        guess = _round_guess(plan, res)
        warps, trusted = _all_warps(plan, res)
        if choice is None:  # tested once, against the reference image (a known null)
            holds = time_model_holds(plan, res, frames, shared)
            unit = _unit_variance(res)
            matched = _matched(res, frames, plan.reference_frame)
            choice = _fit_choice(reg, warps, trusted & matched, unit)
        trusted = trusted & matched
        # a frame enters at a POI whose fit passed and whose fit's neighbours are all trusted
        splat = reg.guard(choice, trusted)
        image, ratio, coverage, point_ratio = template_image(
            plan, _smooth(reg, warps, trusted, choice), splat, frames, sigmas, ref_raw, cache,
            windows)
    degree = reg.degree(choice)
    use = degree > 0
    own = torch.tensor([k != plan.reference_frame for k in frames])
    counts = (use & own[:, None]).sum(0)  # (N,) frames besides the reference in the template
    registered = counts > 0
    # the template's registration: the fits' error (the reference image's, common to the
    # frames, and theirs averaged; the mean variance factor of the frames' fits), none
    # where only the reference image is there
    factor = reg.variance(choice).sum(0) / use.double().sum(0).clamp(min=1)
    prior = factor * (1.0 + 1.0 / counts.clamp(min=1)) * unit
    added = torch.where(registered, prior, 0.0)
    gauge = None
    if plan.reference_frame >= 0:
        gauge, left = _gauge(plan, fit, image, registered, run, guess, ratio)
        added = torch.where(registered, left, 0.0)
    # the template's noise beyond the median the solver is told, where fewer frames cover it
    added = added + (point_ratio - ratio).clamp(min=0.0) * unit
    return SeriesReference(image=image, noise_ratio=ratio, added_var=added, frames=frames,
                           iterations=int(iterations), coverage=coverage,
                           seconds=time.perf_counter() - t0,
                           plane_share=float((degree[own] == 1).double().mean())
                           if bool(own.any()) else 0.0,
                           fit_share=float(use[own].double().mean()) if bool(own.any())
                           else 0.0, gauge=gauge, model_holds=holds,
                           shares=_shares(splat, sigmas, frames, plan.reference_frame),
                           registration=(torch.where(registered, factor, 0.0)
                                         if plan.reference_frame >= 0 else None))


def _shares(splat: torch.Tensor, sigmas: list[float], frames: list[int], reference_frame: int
            ) -> torch.Tensor:
    """(F, N) each frame's weight in the template at each POI: its inverse noise variance
    where it entered there (``splat`` (F, N)), normalised; where none did, the reference
    frame's pixels (weight 1 where it is a sampled frame)."""
    w = splat.double() / torch.tensor(sigmas, dtype=torch.float64)[:, None] ** 2
    tot = w.sum(0, keepdim=True)
    own = torch.tensor([k == reference_frame for k in frames], dtype=torch.float64)[:, None]
    return torch.where(tot > 0, w / tot.clamp(min=1e-300), own.expand_as(w))


def _gauge(plan: RunPlan, fit: LocalFit, image: torch.Tensor, keep: torch.Tensor,
           run: Callable[..., TrackResult], guess: MeasuredSample | None = None,
           ratio: float | None = None) -> tuple[ReferenceOffsets, torch.Tensor]:
    """The template's registration error as the reference frame (zero displacement by
    definition) measures it against the template, and the variance (N,) px^2 left after
    subtracting it.

    Classical DIC of the reference frame against the template; its u, v and gradients
    smoothed by each POI's local plane, 0 where not trusted. The plane value's noise is the
    reference's own noise through the plane's weights, at the level its plane residuals show
    (the template's error is smooth: the rough part of the measurement is noise). Where the
    template was registered by the fits (``keep``) its error is small and smooth, partly
    below that noise: the measured error is shrunk by ``e / (e + noise)``, ``e`` its variance
    beyond the noise averaged over the POI's neighbourhood (the least-squares weight of a
    zero-mean error seen through noise; large where a field the fits missed biased the
    template there); elsewhere (the reference image's own pixels) nothing is subtracted.
    Subtracted from every row like the refined reference's offsets
    (:func:`~torch_stsdic.movie.refine.apply_offsets`); ``rho``: the median of ``e / noise``.
    ``guess``: where the solve starts (the last round's solutions; None: FFT); ``ratio``:
    the template's noise variance over a frame's (None: estimated from its pixels)."""
    res = _measure(plan, [plan.reference_frame], image, run, guess, ratio)
    warp, ok = (a[0] for a in _all_warps(plan, res))
    vals = torch.where(ok[:, None], warp, torch.nan).T  # (6, N)
    smooth = torch.nan_to_num(fit.apply(1, vals), nan=0.0)
    # the reference's own noise through the plane, scaled to the noise its plane residuals
    # show (the template's error is smooth: the rough part of the measurement is noise)
    resid = (vals[[0, 3]] - smooth[[0, 3]]).pow(2).nanmean(0)  # (N,)
    own = torch.zeros_like(fit.weights[1])
    own[:, 0] = 1.0
    level = float((resid / fit.variance_factor(own - fit.weights[1]).clamp(min=1e-12))
                  [keep & torch.isfinite(resid)].median()) if bool(keep.any()) else 0.0
    noise = level * fit.variance_factor(fit.weights[1])
    # the error's variance beyond the noise, over each POI's neighbourhood (where the
    # template's registration is biased, by a field its planes missed, it is large there)
    seen = (smooth[0] ** 2 + smooth[3] ** 2) / 2
    excess = (seen[fit.index].mean(1) - noise[fit.index].mean(1)).clamp(min=0.0)
    shrink = torch.where(keep, excess / (excess + noise).clamp(min=1e-30), 0.0)
    left = torch.where(keep, noise * shrink, 0.0)
    rho = float((excess[keep] / noise[keep].clamp(min=1e-30)).median()) if bool(keep.any()) \
        else 0.0
    names = ("u", "ux", "uy", "v", "vx", "vy")
    values = {nm: (smooth[i] * shrink).numpy() for i, nm in enumerate(names)
              if nm in ("u", "v") or nm in plan.param_names}
    n = smooth.shape[1]
    return ReferenceOffsets(values=values, frames=np.ones(n, dtype=np.int64),
                            degree=np.ones(n, dtype=np.int64), sigma=np.zeros(n), seconds=0.0,
                            shrink=shrink.numpy(), rho=rho,
                            reference_frame=int(plan.reference_frame)), left


def wants_time_model(plan: RunPlan) -> bool:
    """Whether a run without a template decides its time model from its own classical
    measurement (:func:`measure_time_model`): STS windows with the trust checks, one
    reference configuration, no refined reference (which models the motion next to the
    reference itself) and at least ``POOL_POINTS`` points (the pooled bias test's
    neighbourhood; fewer, as with the template, keep their windows and the model check)."""
    return (plan.config.m > 0 and bool(plan.options.get("checks", True))
            and plan.n_points >= POOL_POINTS
            and plan.options.get("reference_update") is None
            and not plan.options.get("refine_reference")
            and not plan.options.get("series_reference"))


def measure_time_model(plan: RunPlan, run: Callable[..., TrackResult],
                       shared: SharedMotion | None = None,
                       max_frames: int = DEFAULT_FRAMES,
                       measured: ClassicalPass | None = None) -> torch.Tensor | None:
    """(N,) bool: where the time model holds (:func:`time_model_holds`) for a run against
    its reference image alone: the same classical measurement of the sampled frames
    (:func:`sample_frames`) that a template's first round makes, against the plan's
    reference (the run's shared one, ``measured``, where it holds them). None where no
    point had three windows."""
    frames = sample_frames(plan, max_frames)
    res = None if measured is None else measured.result(frames)
    if res is None:
        res = _measure(plan, frames, None, run)
    return time_model_holds(plan, res, frames, shared)


def single_reason(plan: RunPlan) -> str | None:
    """Why the reference made from the series does not apply to ``plan`` by default (None:
    it does): it needs the reference to be one frame of the series (that frame's own
    measurement against the template fixes where zero displacement is), one reference
    configuration, other frames of the series to average, and enough points for the local
    fits of their warps."""
    if plan.options.get("reference_update") is not None:
        return "the reference is updated during the run"
    if plan.reference_frame < 0:
        return "the reference is not one frame of the series"
    if len(set(plan.targets) | {plan.reference_frame}) < 3:
        return "fewer than 3 frames to average"
    if plan.n_points < DEFAULT_NEIGHBOURS:
        return f"fewer than {DEFAULT_NEIGHBOURS} points for the local fits that register it"
    return None


def set_series_reference(plan: RunPlan, iterations: int | bool | str = True,
                         max_frames: int | None = None) -> None:
    """Switch a plan to the reference made from the series (checked; recorded in
    ``plan.options["series_reference"]``). ``iterations``: True for the default rounds;
    "auto": those, where :func:`single_reason` finds nothing against it (else the reason is
    recorded in ``plan.options["single_reference"]``)."""
    if isinstance(iterations, str):
        if iterations != "auto":
            raise ValueError(f"series_reference: must be True, False, 'auto' or a number of "
                             f"rounds, got {iterations!r}")
        reason = single_reason(plan)
        if reason is not None:
            plan.options["single_reference"] = reason
            return
        iterations = True
    if plan.options.get("reference_update") is not None:
        raise ValueError("series_reference: cannot be combined with reference_update (the "
                         "template is made for one reference configuration)")
    k = DEFAULT_ITERATIONS if iterations is True else iterations
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"series_reference: iterations must be an integer >= 1 or True, got "
                         f"{iterations!r}")
    n = DEFAULT_FRAMES if max_frames is None else max_frames
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"series_frames: must be an integer >= 2, got {max_frames!r}")
    plan.options["series_reference"] = {"iterations": int(k), "frames": int(n)}
