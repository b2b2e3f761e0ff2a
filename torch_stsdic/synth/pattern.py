"""Speckle patterns: Gaussian spots on a constant background (positions relaxed to a
minimum distance)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["SpecklePattern", "make_speckle", "ArrayLike", "DTYPE", "as_float64"]

DTYPE = torch.float64
ArrayLike = Tensor | float | int | np.ndarray | Sequence[float]


def as_float64(a: ArrayLike) -> Tensor:
    """Convert to a float64 tensor (no copy if already float64)."""
    if isinstance(a, Tensor):
        return a.to(DTYPE)
    return torch.as_tensor(np.asarray(a, dtype=np.float64))






@dataclass(frozen=True)
class SpecklePattern:
    """A speckle pattern: Gaussian spots on a constant background.

    Attributes:
        x, y: (N,) float64 spot centres in the undeformed configuration [px].
        radius: (N,) float64 Gaussian standard deviation ``r`` of each spot [px]
            (``a * exp(-d^2 / (2 r^2))``; full width at half maximum = 2.355 r).
        amplitude: (N,) float64 signed peak amplitude ``a`` [grey levels]; negative = dark spot.
        background: constant background level [grey levels].
        bounds: ``(x_min, x_max, y_min, y_max)`` of the region in which centres were drawn [px]
            (the image plus a margin); used to warn when motion uncovers the image.
    """

    x: Tensor
    y: Tensor
    radius: Tensor
    amplitude: Tensor
    background: float = 0.0
    bounds: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        n = self.x.shape
        for name in ("y", "radius", "amplitude"):
            if getattr(self, name).shape != n:
                raise ValueError(f"SpecklePattern.{name} has shape "
                                 f"{tuple(getattr(self, name).shape)}, expected {tuple(n)}")
        if self.x.ndim != 1:
            raise ValueError("SpecklePattern fields must be 1-D tensors")
        if len(self.radius) and float(self.radius.min()) <= 0:
            raise ValueError("spot radii must be positive")

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def shifted(self, dx: float, dy: float) -> SpecklePattern:
        """The same pattern with every centre moved by ``(dx, dy)`` px (bounds move too)."""
        b = self.bounds
        nb = None if b is None else (b[0] + dx, b[1] + dx, b[2] + dy, b[3] + dy)
        return SpecklePattern(self.x + dx, self.y + dy, self.radius, self.amplitude,
                              self.background, nb)


def _relax(x: np.ndarray, y: np.ndarray, dmin: float, bounds: tuple[float, float, float, float],
           iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Push apart points closer than ``dmin`` (soft hard-core repulsion), vectorised.

    Neighbours are found by binning into cells of size >= ``dmin`` (a padded cell table,
    3 x 3 neighbourhood). Each close pair is separated by half its overlap per iteration.
    NumPy (single-threaded): many small operations, which are slow with an oversubscribed
    torch thread pool.
    """
    x0, x1, y0, y1 = bounds
    ncx = max(1, math.floor((x1 - x0) / dmin))
    ncy = max(1, math.floor((y1 - y0) / dmin))
    cw, ch = (x1 - x0) / ncx, (y1 - y0) / ncy  # >= dmin
    n = x.size
    ar = np.arange(n)
    for _ in range(iterations):
        ci = np.clip(np.floor((x - x0) / cw).astype(np.int64), 0, ncx - 1)
        cj = np.clip(np.floor((y - y0) / ch).astype(np.int64), 0, ncy - 1)
        cid = cj * ncx + ci
        order = np.argsort(cid, kind="stable")
        counts = np.bincount(cid, minlength=ncx * ncy)
        start = np.cumsum(counts) - counts
        rank = np.empty(n, dtype=np.int64)
        rank[order] = ar - start[cid[order]]
        table = np.full((ncy + 2, ncx + 2, int(counts.max())), n, dtype=np.int64)  # n: dummy
        table[cj + 1, ci + 1, rank] = ar
        xs, ys = np.append(x, 1e12), np.append(y, 1e12)
        dx, dy = np.zeros_like(x), np.zeros_like(y)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                nb = table[cj + 1 + di, ci + 1 + dj]  # (n, k)
                ex, ey = x[:, None] - xs[nb], y[:, None] - ys[nb]
                d = np.sqrt(ex * ex + ey * ey)
                f = 0.5 * np.maximum(dmin - d, 0.0) / np.maximum(d, 1e-12)
                f[nb == ar[:, None]] = 0.0
                dx += (f * ex).sum(1)
                dy += (f * ey).sum(1)
        x = np.clip(x + dx, x0, x1)
        y = np.clip(y + dy, y0, y1)
    return x, y


def make_speckle(
    shape: tuple[int, int],
    *,
    density: float | None = None,
    radius: float = 2.0,
    seed: int = 0,
    margin: float | None = None,
    background: float = 215.0,
    amplitude: float = -100.0,
    radius_spread: float = 0.25,
    amplitude_spread: float = 0.25,
    min_distance: float | None = None,
    relax_iterations: int = 20,
) -> SpecklePattern:
    """Random DIC-like speckle pattern covering an image of ``shape = (H, W)`` plus a margin.

    Spot centres are uniform random (Poisson-like, a fixed count ``density * area``), then
    pushed apart to a soft minimum distance ``min_distance`` (blue-noise, isotropic, no lattice
    peaks). The repulsion removes the heavy overlaps of pure Poisson spots, which would
    otherwise saturate the image, so the pattern keeps good contrast over the whole range.
    With the defaults (dark spots on a light background, radius 2): mean grey ~143, standard
    deviation ~42, mean intensity gradient ~16 grey/px, ~47 % of the area darker than
    mid-range, values within ~5..215 (no saturation at 8 bits, even with moderate noise).

    Args:
        shape: (H, W) of the images the pattern is meant for [px].
        density: spots per px^2; default ``0.7 / (2 pi radius^2)`` (~0.028 for radius 2).
        radius: mean Gaussian standard deviation ``r`` of the spots [px] (FWHM = 2.355 r).
        seed: seed of the torch generator (patterns are reproducible across platforms).
        margin: extra border around the image in which spots are drawn, so that moved spots
            enter from outside [px]; default ``max(16, 8 * radius)``. Make it larger than the
            largest displacement you render (:func:`render` warns otherwise).
        background: background grey level.
        amplitude: mean signed spot peak amplitude [grey levels] (negative: dark spots).
        radius_spread: radii are uniform in ``radius * [1 - s, 1 + s]``.
        amplitude_spread: amplitudes are uniform in ``amplitude * [1 - s, 1 + s]``.
        min_distance: soft minimum centre distance [px]; default ``0.75 / sqrt(density)``;
            0 gives plain uniform random centres.
        relax_iterations: iterations of the repulsion.

    Returns:
        SpecklePattern with float64 tensors on the CPU.
    """
    H, W = int(shape[0]), int(shape[1])
    if radius <= 0:
        raise ValueError("radius must be positive")
    if density is None:
        density = 0.7 / (2.0 * math.pi * radius**2)
    if density <= 0:
        raise ValueError("density must be positive")
    if margin is None:
        margin = max(16.0, 8.0 * radius)
    if min_distance is None:
        min_distance = 0.75 / math.sqrt(density)
    x0, x1 = -0.5 - margin, W - 0.5 + margin
    y0, y1 = -0.5 - margin, H - 0.5 + margin
    bounds = (x0, x1, y0, y1)
    n = max(1, round(density * (x1 - x0) * (y1 - y0)))
    g = torch.Generator().manual_seed(int(seed))
    u = torch.rand(4, n, generator=g, dtype=DTYPE)
    x = x0 + u[0] * (x1 - x0)
    y = y0 + u[1] * (y1 - y0)
    if min_distance > 0 and relax_iterations > 0:
        xr, yr = _relax(x.numpy(), y.numpy(), float(min_distance), bounds, int(relax_iterations))
        x, y = torch.from_numpy(xr), torch.from_numpy(yr)
    rad = radius * (1.0 + radius_spread * (2.0 * u[2] - 1.0))
    amp = amplitude * (1.0 + amplitude_spread * (2.0 * u[3] - 1.0))
    return SpecklePattern(x, y, rad, amp, float(background), bounds)

