"""The classical pass that a run's pre-passes share: classical DIC (checks off) of series
frames at the run's POIs against its reference image, measured once.

The shared-motion pass (:mod:`.shared_pass`), the template's first round
(:mod:`.series_reference`), the window-length pass (:mod:`.window_length`) and, without a
template, the time-model pass (:func:`.series_reference.measure_time_model`) each measured
the same thing, each for its own frames (and the shared-motion pass at a sample of the
points): on the muDIC hourglass (40 frames, 1,666 POIs) three classical passes over the
movie before its first block. :class:`ClassicalPass` measures the union of the frames they
will ask for once, at every POI, and hands each its rows (and points): what a pass asks
for outside that union, or a union too large to hold (more than ``memory_mb / 4`` MiB of
rows), it measures itself as before (:meth:`ClassicalPass.result` returns None).

A point's classical solution does not depend on the other points or frames of the pass
but through its initial guess; the passes' results equal their own measurements within the
solver's tolerance (``DICConfig.tol``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import torch

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.movie.plan import RunPlan

__all__ = ["ClassicalPass", "classical_subplan", "ROW_BYTES"]

#: bytes a held row of the pass takes per point (its ~16 float64 fields)
ROW_BYTES = 16 * 8


def classical_subplan(plan: RunPlan, frames: list[int], points: torch.Tensor | None = None
                      ) -> RunPlan:
    """The sub-plan of a classical measurement of series ``frames`` against ``plan``'s
    reference image: m = 0, checks, smoothing, reference updates, shared motion and
    template off, no velocity fields; at ``points`` (indices into the plan's POIs; None:
    all)."""
    opts = {**plan.options, "smoothing": None, "reference_update": None, "checks": False,
            "shared_motion": None, "series_reference": None}
    opts.pop("refine_reference", None)
    names = tuple(nm for nm in plan.param_names if nm not in ("ut", "vt"))
    sub = dataclasses.replace(plan, config=plan.config.replace(m=0), targets=list(frames),
                              options=opts, param_names=names)
    if points is not None:
        sub = dataclasses.replace(sub, points=plan.points[points])
    return sub


class ClassicalPass:
    """Classical DIC of the frames ``wanted`` (the union the pre-passes will ask for) at
    every POI of ``plan``, measured on the first :meth:`result` that it covers and kept
    for the others. ``run``: the runner of a plan
    (:func:`torch_stsdic.movie.series.run_plan`)."""

    def __init__(self, plan: RunPlan, run: Callable[..., TrackResult],
                 wanted: Iterable[int]) -> None:
        self.plan, self.run = plan, run
        self.frames = sorted({int(k) for k in wanted})
        budget = plan.config.budget_mb * 2**20 / 4
        self.enabled = 0 < len(self.frames) * plan.n_points * ROW_BYTES <= budget
        self._res: TrackResult | None = None
        #: how many of the pre-passes' requests it answered (the passes not measured again)
        self.served = 0

    def covers(self, frames: Iterable[int]) -> bool:
        """Whether :meth:`result` answers a request for ``frames``."""
        return self.enabled and set(int(k) for k in frames) <= set(self.frames)

    def result(self, frames: list[int], points: torch.Tensor | None = None
               ) -> TrackResult | None:
        """The rows of series ``frames`` (in that order) at ``points`` (indices into the
        plan's POIs; None: all), or None where not covered (the caller measures)."""
        if not self.covers(frames):
            return None
        if self._res is None:
            self._res = self.run(classical_subplan(self.plan, self.frames), progress=False)
        self.served += 1
        return self._res.select(frames, points)
