"""Frames of a movie held while they are in use: raw pixels and B-spline coefficients.

A sliding window reads every frame 2m+1 times; :class:`FrameCache` reads and prefilters each
frame once while consecutive blocks of windows overlap, and drops it after, so memory is
bounded by the block, not by the movie length.
"""

from __future__ import annotations

from collections import OrderedDict

import torch

from .interpolation import BSplineImage
from .io import ImageSeries
from .solver import SubsetSolver

__all__ = ["FrameCache"]


class FrameCache:
    """Frames of the current block: raw pixels and prefiltered coefficients, by index.

    ``load`` keeps exactly the frames asked for (older ones are dropped), so a frame is read
    and prefiltered once while consecutive blocks overlap."""

    def __init__(self, series: ImageSeries, solver: SubsetSolver, dtype, device) -> None:
        self.series, self.solver = series, solver
        self.dtype, self.device = dtype, device
        self.raw: OrderedDict[int, torch.Tensor] = OrderedDict()
        self.prep: dict[int, BSplineImage] = {}
        self.reads = 0
        self.prefiltered = 0
        self.max_cached = 0

    def read(self, i: int) -> torch.Tensor:
        """(H, W) frame ``i`` from the cache or the series (counted)."""
        if i in self.raw:
            return self.raw[i]
        self.reads += 1
        return self.series.get(i, dtype=self.dtype).to(self.device)

    def load(self, idx: list[int]) -> tuple[torch.Tensor, BSplineImage]:
        """Frames ``idx``: raw (L, H, W) and a prepared L-frame stack."""
        keep = set(idx)
        for k in [k for k in self.raw if k not in keep]:
            del self.raw[k]
            del self.prep[k]
        for i in idx:
            if i not in self.raw:
                raw = self.read(i)
                self.raw[i] = raw
                self.prep[i] = self.solver.prepare(raw)
                self.prefiltered += 1
        self.max_cached = max(self.max_cached, len(self.raw))
        raw = torch.stack([self.raw[i] for i in idx])
        return raw, BSplineImage.stack([self.prep[i] for i in idx])
