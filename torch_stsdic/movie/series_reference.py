"""A reference made from the series: a sample of the movie's images mapped back to the reference
configuration with each point's measured subset warp and averaged into a template, the movie
then measured against the template.

Each POI's classical solution (u, v and the displacement gradients, the spatial part of the
shape function) maps the pixels of its subset window in the reference configuration to frame
t: ``X -> X + u + grad(u) (X - x_poi)``. Frame t sampled there (B-spline) is the reference
image as frame t saw it; every POI adds it to the pixels of its window with a tent weight (so
a pixel blends the warps of the POIs around it), for every sampled frame where the POI is
trusted, weighted by the inverse of the frame's noise variance. Pixels no trusted POI covers
keep the reference frame's value.

What it gains (docs/validation/series_reference.md, measured): the template's own noise falls
as 1/N, but its *registration* to the reference configuration comes from the measured warps,
which carry the single reference image's error; that error is averaged over the overlapping
windows of neighbouring points at each iteration (template, then a classical measurement
against it), so its variance falls as ``1 / (k + 1)`` after k iterations, not as 1/N. On a
render (21 images, noise on every image) classical DIC against the template reads 0.82x,
0.78x, 0.75x and 0.74x its error against the reference image after 1 to 4 iterations.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.noise import estimate_noise_sigma, interpolation_variance_factor
from torch_stsdic.movie.plan import RunPlan

__all__ = ["SeriesReference", "DEFAULT_FRAMES", "DEFAULT_ITERATIONS", "sample_frames",
           "build_series_reference", "registration_share", "set_series_reference"]

#: frames of the movie sampled for the template (evenly spread over the targets)
DEFAULT_FRAMES = 21
#: template / classical-measurement rounds
DEFAULT_ITERATIONS = 2
#: the points whose warps feed the template (grey levels of the pixels: memory per chunk)
_CHUNK_SAMPLES = 4_000_000


@dataclass
class SeriesReference:
    """The template and what it rests on."""

    image: torch.Tensor  # (H, W) the template, float64
    noise_ratio: float  # its pixels' noise variance over one frame's
    added_var: torch.Tensor | None  # (N,) px^2 its registration's variance (registration_share)
    frames: list[int]  # the sampled frames (series indices)
    iterations: int
    coverage: float  # share of the POIs' window pixels averaged over >= 2 frames
    seconds: float

    def summary(self) -> dict[str, Any]:
        return {"frames": list(self.frames), "iterations": self.iterations,
                "noise_ratio": round(self.noise_ratio, 4),
                "added_std_px": (None if self.added_var is None
                                 else round(float(self.added_var.mean().sqrt()), 6)),
                "coverage": round(self.coverage, 4), "seconds": round(self.seconds, 3)}


#: the registration share's fall per round and overlapping window (fitted: a render, subset
#: 21 px at step 8, 0.35 / 0.20 / 0.14 / 0.10 after 1-4 rounds; DIC Challenge sample 3, step
#: 16: 0.45 after 2 rounds; scripts/validation/series_reference_gauge.py)
SHARE_RATE = 0.27


def registration_share(iterations: int, subset_size: int, spacing: float) -> float:
    """The template's registration error variance over a single reference image's, after
    ``iterations`` rounds: every round averages it over the windows of the POIs that overlap
    a subset, ``o = (subset / spacing)^2`` of them, so ``1 / (1 + SHARE_RATE k o)``."""
    overlap = (float(subset_size) / max(float(spacing), 1.0)) ** 2
    return 1.0 / (1.0 + SHARE_RATE * int(iterations) * overlap)


def _unit_variance(res: TrackResult) -> torch.Tensor:
    """(N,) px^2 one image's share of a classical displacement's variance per POI, from a
    classical measurement's predicted std (both images noisy: half the variance when the
    reference is one frame; divided by 1 + its noise ratio otherwise)."""
    ratio = float(res.info.get("reference_noise_ratio") or 1.0)
    var = (res.std["u"].double().cpu().pow(2) + res.std["v"].double().cpu().pow(2)) / 2
    ok = res.status.cpu() <= USABLE
    var = torch.where(ok, var, torch.nan)
    per_point = torch.nanmean(var, 0) / (1.0 + ratio)
    return torch.nan_to_num(per_point, nan=float(torch.nanmean(per_point)))


def _spacing(points: torch.Tensor) -> float:
    """Median distance px of a POI to its nearest other POI."""
    p = points.double().cpu()
    if p.shape[0] < 2:
        return 1.0
    sel = p[torch.randperm(p.shape[0], generator=torch.Generator().manual_seed(0))[:2000]]
    d = torch.cdist(sel, p)
    d[d == 0] = float("inf")
    return float(d.min(1).values.median())


def sample_frames(plan: RunPlan, max_frames: int = DEFAULT_FRAMES) -> list[int]:
    """Up to ``max_frames`` frames evenly spread over the targets, the reference frame (when
    it is a frame of the series) always among them."""
    if int(max_frames) < 2:
        raise ValueError(f"series_reference: needs >= 2 frames, got {max_frames!r}")
    ks = sorted(set(plan.targets) | ({plan.reference_frame} if plan.reference_frame >= 0
                                     else set()))
    if len(ks) > max_frames:
        pick = np.unique(np.round(np.linspace(0, len(ks) - 1, int(max_frames))).astype(int))
        chosen = {ks[i] for i in pick}
        if plan.reference_frame >= 0:
            chosen.add(plan.reference_frame)
        ks = sorted(chosen)
    return ks


def _measure(plan: RunPlan, frames: list[int], image: torch.Tensor | None,
             run: Callable[..., TrackResult]) -> TrackResult:
    """Classical DIC (checks off) of ``frames`` at all the plan's POIs, against the plan's
    reference or against ``image``."""
    opts = {**plan.options, "smoothing": None, "reference_update": None, "checks": False,
            "shared_motion": None, "series_reference": None}
    opts.pop("refine_reference", None)
    names = tuple(nm for nm in plan.param_names if nm not in ("ut", "vt"))
    sub = dataclasses.replace(plan, config=plan.config.replace(m=0), targets=frames,
                              options=opts, param_names=names)
    if image is not None:
        sub = dataclasses.replace(sub, reference_image=image, reference_frame=-1,
                                  reference_desc="array:series-template")
    return run(sub, progress=False)


def _warps(res: TrackResult, j: int, lost_zncc: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 6) u, ux, uy, v, vx, vy of result row j (gradients 0 where not solved) and (N,)
    whether the row is trusted."""
    cols = []
    for nm in ("u", "ux", "uy", "v", "vx", "vy"):
        try:
            cols.append(res.field(nm)[j].double().cpu())
        except (KeyError, AttributeError):
            cols.append(torch.zeros(res.u.shape[1], dtype=torch.float64))
    w = torch.stack(cols, 1)
    ok = ((res.status[j].cpu() <= USABLE) & torch.isfinite(w).all(1)
          & (res.zncc[j].double().cpu() >= lost_zncc))
    return torch.nan_to_num(w), ok


def _splat(acc: torch.Tensor, img: BSplineImage, pts: torch.Tensor, warp: torch.Tensor,
           ok: torch.Tensor, half: int, weight: float) -> None:
    """Add frame ``img`` mapped back by each trusted POI's warp to ``acc`` (3, H*W): weighted
    values, weights, squared weights times the interpolated noise's variance factor."""
    h, w = img.height, img.width
    d = torch.arange(-half, half + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    dx, dy = dx.reshape(-1), dy.reshape(-1)
    tent = ((1.0 - dx.abs() / (half + 1)) * (1.0 - dy.abs() / (half + 1)))
    sel = torch.nonzero(ok).flatten()
    chunk = max(1, _CHUNK_SAMPLES // dx.numel())
    for s0 in range(0, sel.numel(), chunk):
        i = sel[s0: s0 + chunk]
        c = pts[i].round()
        x = c[:, :1] + dx  # (n, S) reference-configuration pixels
        y = c[:, 1:] + dy
        ox, oy = x - pts[i, :1], y - pts[i, 1:]
        wp = warp[i]
        xs = x + wp[:, 0:1] + wp[:, 1:2] * ox + wp[:, 2:3] * oy
        ys = y + wp[:, 3:4] + wp[:, 4:5] * ox + wp[:, 5:6] * oy
        inside = ((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & (xs >= 0)
                  & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1))
        vals = img.sample(xs.to(img.dtype), ys.to(img.dtype)).double()
        fac = interpolation_variance_factor(xs - xs.floor(), ys - ys.floor())
        wt = (tent * weight).expand_as(x)[inside]
        idx = (y[inside] * w + x[inside]).long()
        acc[0].index_add_(0, idx, wt * vals[inside])
        acc[1].index_add_(0, idx, wt)
        acc[2].index_add_(0, idx, wt * wt * fac[inside] / weight)


def _frame_noise(plan: RunPlan, frames: list[int]) -> list[float]:
    """The image noise sigma (grey levels) of each of ``frames`` (Immerkaer's estimate)."""
    return [max(float(estimate_noise_sigma(plan.series.get(k, dtype=torch.float64))), 1e-6)
            for k in frames]


def _template(plan: RunPlan, res: TrackResult, frames: list[int], sigmas: list[float],
              ref_raw: torch.Tensor) -> tuple[torch.Tensor, float, float]:
    """The template from the measured warps of ``res`` (rows = ``frames``, noise ``sigmas``):
    image (H, W), its noise variance over one frame's (median over the covered pixels),
    coverage."""
    h, w = plan.series.shape
    pts = plan.points.double().cpu()
    half = (plan.config.subset_size - 1) // 2
    lost = float(plan.options.get("lost_zncc", 0.8))
    acc = torch.zeros(3, h * w, dtype=torch.float64)
    for j, (k, sigma) in enumerate(zip(frames, sigmas)):
        raw = plan.series.get(k, dtype=torch.float64)
        warp, ok = _warps(res, j, lost)
        _splat(acc, BSplineImage(raw), pts, warp, ok, half, 1.0 / sigma ** 2)
    ref = ref_raw.double().cpu().reshape(-1)
    covered = acc[1] > 0
    image = torch.where(covered, acc[0] / acc[1].clamp(min=1e-300), ref).reshape(h, w)
    # noise variance of a pixel: sum w^2 s^2 f / (sum w)^2 with w = 1/s^2 (acc[2] holds
    # sum w^2 f / w = sum w f), over one frame's median s^2
    var = acc[2][covered] / acc[1][covered] ** 2
    s2 = float(np.median(sigmas)) ** 2
    ratio = float(var.median()) / s2 if bool(covered.any()) else 1.0
    wmax = acc[1][covered].max() if bool(covered.any()) else torch.tensor(1.0)
    multi = (acc[1][covered] > 1.5 * wmax / max(len(frames), 1)).double()
    coverage = float(multi.mean()) if multi.numel() else 0.0
    return image, ratio, coverage


def build_series_reference(plan: RunPlan, ref_raw: torch.Tensor, *,
                           run: Callable[..., TrackResult],
                           max_frames: int = DEFAULT_FRAMES,
                           iterations: int = DEFAULT_ITERATIONS) -> SeriesReference:
    """The template of ``plan``: ``iterations`` rounds of a classical measurement of the
    sampled frames (:func:`sample_frames`; the first against the plan's reference image
    ``ref_raw`` (H, W), the others against the last template) and a template from its warps.
    ``run``: the runner of a plan (:func:`torch_stsdic.movie.series.run_plan`)."""
    if int(iterations) < 1:
        raise ValueError(f"series_reference: iterations must be >= 1, got {iterations!r}")
    t0 = time.perf_counter()
    frames = sample_frames(plan, max_frames)
    sigmas = _frame_noise(plan, frames)  # the same in every round
    image = None
    ratio = coverage = 1.0
    for i in range(int(iterations)):
        res = _measure(plan, frames, image, run)
        if i == 0 and "u" in res.std:
            unit = _unit_variance(res)
        image, ratio, coverage = _template(plan, res, frames, sigmas, ref_raw)
    added = None
    if "u" in res.std:
        share = registration_share(int(iterations), plan.config.subset_size,
                                   _spacing(plan.points))
        added = share * unit
    return SeriesReference(image=image, noise_ratio=ratio, added_var=added, frames=frames,
                           iterations=int(iterations), coverage=coverage,
                           seconds=time.perf_counter() - t0)


def set_series_reference(plan: RunPlan, iterations: int | bool = True,
                         max_frames: int | None = None) -> None:
    """Switch a plan to the reference made from the series (checked; recorded in
    ``plan.options["series_reference"]``). ``iterations``: True for the default rounds."""
    if plan.options.get("reference_update") is not None:
        raise ValueError("series_reference: cannot be combined with reference_update (the "
                         "template is made for one reference configuration)")
    if plan.options.get("refine_reference"):
        raise ValueError("series_reference: cannot be combined with refine_reference; choose "
                         "one")
    k = DEFAULT_ITERATIONS if iterations is True else iterations
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"series_reference: iterations must be an integer >= 1 or True, got "
                         f"{iterations!r}")
    n = DEFAULT_FRAMES if max_frames is None else max_frames
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"series_frames: must be an integer >= 2, got {max_frames!r}")
    plan.options["series_reference"] = {"iterations": int(k), "frames": int(n)}
