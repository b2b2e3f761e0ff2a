"""Run-level estimates: what a run measures once, before its first block, for the whole movie.

A run measures, from the whole movie, a few things every block then uses: the specimen's
shared motion and its load steps with the measuring pass's solutions (the first block's
guess; :func:`~torch_stsdic.movie.shared_pass.estimate_shared_motion`), the reference made
from the series (:func:`~torch_stsdic.movie.series_reference.build_series_reference`), the
refined reference's per-point offsets (:func:`~torch_stsdic.movie.refine.measure_offsets`)
and, for a reference given as an image, its noise ratio. :func:`measure_run` measures them
(:class:`RunEstimates`); :func:`~torch_stsdic.movie.series.run_plan` does so itself, or takes
them measured already: the distributed runner (:mod:`torch_stsdic.movie.distributed`)
measures them once on the whole movie and hands them to every chunk, so that a chunk's
windows and decisions are those of the one-process run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.frames import segment_bounds, window_frames
from torch_stsdic.movie.plan import RunPlan
from torch_stsdic.movie.reference import noise_ratio
from torch_stsdic.movie.refine import ReferenceOffsets, measure_offsets
from torch_stsdic.movie.series_reference import SeriesReference, build_series_reference
from torch_stsdic.movie.shared_pass import estimate_shared_motion

__all__ = ["RunEstimates", "measure_run", "reference_pixels"]

#: runs a plan to its result (the signature of :func:`torch_stsdic.movie.series.run_plan`)
RunFunction = Callable[..., TrackResult]


@dataclass(eq=False)
class RunEstimates:
    """The run-level estimates of a plan (:func:`measure_run`); None where not used.

    Attributes:
        shared: the shared motion (:class:`~torch_stsdic.core.shared_motion.SharedMotion`):
            per-frame motion, load ``steps`` and the measuring pass's ``sample`` (the guess
            of a block without a carry); carried in the windows where ``applied``.
        series_reference: the reference made from the series (its image, noise ratio and
            added variance).
        offsets: the refined reference's per-point offsets.
        noise_ratio: the reference's noise variance over a frame's (None: the first block
            measures it, as a one-process run does).
    """

    shared: SharedMotion | None = None
    series_reference: SeriesReference | None = None
    offsets: ReferenceOffsets | None = None
    noise_ratio: float | None = None

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
        return info


def reference_pixels(plan: RunPlan) -> torch.Tensor:
    """(H, W) the plan's reference image as a run reads it (plan dtype and device)."""
    if plan.reference_image is not None:
        return plan.reference_image.to(device=plan.device, dtype=plan.dtype)
    return plan.series.get(plan.reference_frame, dtype=plan.dtype).to(plan.device)


def measure_run(plan: RunPlan, ref_raw: torch.Tensor | None = None, *, run: RunFunction,
                first_noise: bool = False) -> RunEstimates:
    """Measure the run-level estimates of ``plan`` (those its options ask for) on the whole
    movie. ``ref_raw``: the reference image (default :func:`reference_pixels`); ``run``: the
    runner of a plan (:func:`torch_stsdic.movie.series.run_plan`, which calls this
    function). ``first_noise``: also the reference's noise ratio, on the frames of the plan's
    first block as that block measures it (a runner whose pieces start elsewhere)."""
    shared = None
    if plan.options.get("shared_motion"):
        kind = plan.options["shared_motion"]
        shared = estimate_shared_motion(plan, kind, auto=kind == "auto", run=run)
    series_ref = None
    if plan.options.get("series_reference"):
        opt = plan.options["series_reference"]
        raw = reference_pixels(plan) if ref_raw is None else ref_raw
        series_ref = build_series_reference(
            plan, raw, run=run, max_frames=opt["frames"], iterations=opt["iterations"],
            shared=shared if shared is not None and shared.applied else None)
    offsets = None
    if plan.options.get("refine_reference"):
        offsets = measure_offsets(plan, int(plan.options["refine_reference"]),
                                  shared if shared is not None and shared.applied else None,
                                  run=run)
    est = RunEstimates(shared=shared, series_reference=series_ref, offsets=offsets,
                       noise_ratio=None if series_ref is None else series_ref.noise_ratio)
    if first_noise and est.noise_ratio is None:
        est.noise_ratio = _first_block_noise(plan, ref_raw, shared)
    return est


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
