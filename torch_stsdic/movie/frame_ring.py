"""The frames a block reads, as one stack that consecutive blocks share.

The solver reads a block's frames from one stack: pixels (C, H, W) and B-spline coefficients
(C, H', W'), each frame a plane of it. Consecutive blocks of a sliding window share all but a
frame or two, so :class:`FrameRing` keeps the stack between blocks and writes only the frames
that are new into the planes that frames no longer needed leave free: a frame is copied into
the stack once while it stays in use, instead of every block copying all of its 2m+1 (or
more) frames again (on a 754 x 1273 movie with 13-frame windows that was 100 MB a block).
A frame's pixels are copied into their plane only when a block asks for them
(:attr:`RingView.raw`: the FFT initial guess, a noise estimate), not with its coefficients,
which every solve reads (the hourglass's defaults: 102 frames copied, the pixels of most
never read).

A block then addresses its frames by *plane* (:attr:`RingView.planes`), not by position in its
list of frames.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import torch

from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.pyramid import ImagePyramid, PyramidStack

__all__ = ["FrameRing", "RingView"]


class _Prepared(Protocol):  # movie.frames.PreparedFrame (not imported: no cycle)
    raw: torch.Tensor
    prep: BSplineImage

    def pyramid(self) -> ImagePyramid: ...


@dataclass(frozen=True)
class RingView:
    """A block's frames in the ring: ``img`` the C-plane coefficient stack (every plane,
    those of other frames or empty ones included), ``planes`` the plane of each frame asked
    for (in the order asked), ``pyramids`` the Gaussian pyramids by plane (an empty plane's
    is None), and :attr:`raw` the pixels (C, H, W), the planes asked for filled on first
    use."""

    ring: FrameRing
    img: BSplineImage
    planes: list[int]
    pyramids: PyramidStack

    @property
    def raw(self) -> torch.Tensor:
        """(C, H, W) the pixel stack, the planes of the frames asked for filled (copied
        from the prepared frames where not yet: once while a frame stays in its plane)."""
        return self.ring.pixels(self.planes)

    def frames_raw(self) -> torch.Tensor:
        """(L, H, W) the pixels of the frames asked for, in their order (a copy)."""
        return self.raw[torch.as_tensor(self.planes, device=self.raw.device)]


class FrameRing:
    """Planes of a stack kept from block to block (see the module docstring). ``fill``
    gives a block its frames; the stack grows (and is rebuilt) only when a block needs more
    frames than it has planes, or when the frames' size, type or device change."""

    def __init__(self) -> None:
        self.slot: dict[int, int] = {}  # frame index -> plane
        self.raw: torch.Tensor | None = None  # (C, H, W)
        self.coeffs: torch.Tensor | None = None  # (C, H', W')
        self.by_plane: list[_Prepared | None] = []
        self.has_pixels: list[bool] = []  # the plane's pixels copied (:meth:`pixels`)
        self.copies = 0  # frames copied into a plane (a test counts them)
        self.pixel_copies = 0  # and their pixels (:meth:`pixels`)

    @property
    def capacity(self) -> int:
        return 0 if self.raw is None else int(self.raw.shape[0])

    def _same_kind(self, first: _Prepared) -> bool:
        raw, co = first.raw, first.prep.coeffs
        return (self.raw is not None and self.coeffs is not None
                and self.raw.shape[1:] == raw.shape and self.raw.dtype == raw.dtype
                and self.raw.device == raw.device and self.coeffs.shape[1:] == co.shape[1:]
                and self.coeffs.dtype == co.dtype and self.coeffs.device == co.device)

    def _allocate(self, first: _Prepared, n: int) -> None:
        """``n`` planes for frames like ``first``: the planes held kept where they are when
        the frames are of the same kind (the stack grows), else all freed."""
        raw, co = first.raw, first.prep.coeffs
        new_raw = torch.empty((n, *raw.shape), dtype=raw.dtype, device=raw.device)
        new_co = torch.empty((n, *co.shape[1:]), dtype=co.dtype, device=co.device)
        if self._same_kind(first):
            c = self.capacity
            held = [p for p in range(c) if self.has_pixels[p]]
            if held:
                new_raw[held] = self.raw[held]
            new_co[:c].copy_(self.coeffs)
            self.by_plane += [None] * (n - c)
            self.has_pixels += [False] * (n - c)
        else:
            self.slot, self.by_plane, self.has_pixels = {}, [None] * n, [False] * n
        self.raw, self.coeffs = new_raw, new_co

    def fill(self, entries: Mapping[int, _Prepared], idx: Sequence[int]) -> RingView:
        """The frames ``idx`` (each in ``entries``, prepared single-frame images of one size)
        in the ring: the planes of frames not in ``idx`` are freed, the new ones copied in."""
        idx = [int(i) for i in idx]
        first = entries[idx[0]]
        if not self._same_kind(first) or len(idx) > self.capacity:
            self._allocate(first, len(idx))
        keep = set(idx)
        for i in [i for i in self.slot if i not in keep]:
            self.by_plane[self.slot.pop(i)] = None
        free = iter([p for p, e in enumerate(self.by_plane) if e is None])
        for i in idx:
            if i in self.slot:
                continue
            p = next(free)
            entry = entries[i]
            self.coeffs[p].copy_(entry.prep.coeffs[0])
            self.slot[i], self.by_plane[p], self.has_pixels[p] = p, entry, False
            self.copies += 1
        img = first.prep.with_coeffs(self.coeffs)  # every plane, no copy
        pyramids = PyramidStack([None if e is None else e.pyramid() for e in self.by_plane])
        return RingView(self, img, [self.slot[i] for i in idx], pyramids)

    def pixels(self, planes: Sequence[int]) -> torch.Tensor:
        """(C, H, W) the pixel stack with the frames of ``planes`` in it (each copied from
        its prepared frame the first time it is asked for while it holds that plane)."""
        for p in planes:
            if not self.has_pixels[p]:
                self.raw[p].copy_(self.by_plane[p].raw)
                self.has_pixels[p] = True
                self.pixel_copies += 1
        return self.raw
