"""Synthetic speckle images with exactly known motion (for testing and benchmarking DIC).

The speckle pattern is a sum of Gaussian spots on a constant background. Frames are rendered
*analytically*: no image is ever interpolated. For a motion ``U(X, t)`` each spot centre ``c``
moves to ``c' = c + U(c, t)`` and its shape is mapped by the local deformation gradient
``F = I + grad U(c, t)``::

    I(x) = background + sum_k a_k * exp(-|F_k^{-1} (x - c'_k)|^2 / (2 r_k^2))

This is exact for affine motion (translation, homogeneous strain) and a close approximation
(error of second order in the spot size) for smooth non-uniform fields. Every pixel value is the
*mean of I over the pixel area* (pixel ``(row i, col j)`` is the unit square centred on
``(x, y) = (j, i)``): the integral along x is done exactly with ``erf`` and, where ``F F^T`` is
diagonal (no motion, translation, normal strain without shear/rotation), along y too; otherwise
along y by Gauss-Legendre quadrature (``quadrature`` nodes per pixel, default 4; error
< 1e-6 grey levels for spots with r >= 1.2 px). The pixel integration is part of the known
truth. Spots are truncated at ``cutoff`` = 6 standard deviations (relative error ~1e-8).

Conventions: x = column (right), y = row (down), pixel centres at integer coordinates, 0-based;
``u`` along x, ``v`` along y. Motion is Lagrangian: ``g_t(X + U(X, t)) = f(X)``, where ``X`` are
coordinates of the undeformed pattern. Intensities are grey levels on an 8-bit scale (0..255),
stored as float64 (see :func:`quantize` for integer images).

Typical use::

    pattern = make_speckle((301, 301), seed=0)
    motion = Translation(ut=1 / 20)                     # u = t / 20 px, the paper's test
    times = torch.arange(1.0, 10.0)
    ref, frames = render_series(pattern, (301, 301), motion, times, noise_sigma=5.0, seed=1)
    truth = ground_truth(motion, points, times)         # dict of (T, N) tensors
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "SpecklePattern",
    "make_speckle",
    "Motion",
    "Translation",
    "HomogeneousStrain",
    "QuadraticInTime",
    "Sinusoidal",
    "Jump",
    "Custom",
    "Sum",
    "render",
    "add_noise",
    "quantize",
    "render_series",
    "ground_truth",
    "Movie",
    "synthetic_movie",
]

_DT = torch.float64
ArrayLike = Tensor | float | int | np.ndarray | Sequence[float]


def _t(a: ArrayLike) -> Tensor:
    """Convert to a float64 tensor (no copy if already float64)."""
    if isinstance(a, Tensor):
        return a.to(_DT)
    return torch.as_tensor(np.asarray(a, dtype=np.float64))


# --------------------------------------------------------------------------------------------
# Pattern
# --------------------------------------------------------------------------------------------


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
    u = torch.rand(4, n, generator=g, dtype=_DT)
    x = x0 + u[0] * (x1 - x0)
    y = y0 + u[1] * (y1 - y0)
    if min_distance > 0 and relax_iterations > 0:
        xr, yr = _relax(x.numpy(), y.numpy(), float(min_distance), bounds, int(relax_iterations))
        x, y = torch.from_numpy(xr), torch.from_numpy(yr)
    rad = radius * (1.0 + radius_spread * (2.0 * u[2] - 1.0))
    amp = amplitude * (1.0 + amplitude_spread * (2.0 * u[3] - 1.0))
    return SpecklePattern(x, y, rad, amp, float(background), bounds)


# --------------------------------------------------------------------------------------------
# Motions
# --------------------------------------------------------------------------------------------


class Motion:
    """Base class of analytic displacement fields ``U(X, t) = (u, v)`` in px.

    ``x, y`` are reference (Lagrangian) coordinates [px], ``t`` time [frame units or any unit
    consistent with the rates]; all are broadcast together (tensors or floats) and results are
    float64 tensors of the broadcast shape. Motions can be added: ``m1 + m2`` is ``Sum``.
    """

    def displacement(self, x: ArrayLike, y: ArrayLike, t: ArrayLike) -> tuple[Tensor, Tensor]:
        """``(u, v)`` [px]."""
        raise NotImplementedError

    def gradient(
        self, x: ArrayLike, y: ArrayLike, t: ArrayLike
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(du/dx, du/dy, dv/dx, dv/dy)`` [px/px]."""
        raise NotImplementedError

    def velocity(self, x: ArrayLike, y: ArrayLike, t: ArrayLike) -> tuple[Tensor, Tensor]:
        """``(du/dt, dv/dt)`` [px per time unit]."""
        raise NotImplementedError

    def __add__(self, other: Motion) -> Sum:
        if not isinstance(other, Motion):
            return NotImplemented
        return Sum(self, other)

    @staticmethod
    def _shape(x: ArrayLike, y: ArrayLike, t: ArrayLike) -> tuple[Tensor, Tensor, Tensor]:
        x, y, t = _t(x), _t(y), _t(t)
        return tuple(torch.broadcast_tensors(x, y, t))  # type: ignore[return-value]


def _zeros_like(x: Tensor) -> Tensor:
    return torch.zeros_like(x, dtype=_DT)


class Translation(Motion):
    """Rigid translation, optionally moving at constant speed.

    ``u = u0 + ut * t``, ``v = v0 + vt * t``; gradient 0; velocity ``(ut, vt)``.
    The paper's simulated test is ``Translation(ut=1 / 20)`` with t = 1..9.
    """

    def __init__(self, u0: float = 0.0, v0: float = 0.0, ut: float = 0.0, vt: float = 0.0):
        self.u0, self.v0, self.ut, self.vt = float(u0), float(v0), float(ut), float(vt)

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        return self.u0 + self.ut * t, self.v0 + self.vt * t

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        z = _zeros_like(x)
        return z, z.clone(), z.clone(), z.clone()

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        return _zeros_like(x) + self.ut, _zeros_like(x) + self.vt

    def __repr__(self) -> str:
        return f"Translation(u0={self.u0}, v0={self.v0}, ut={self.ut}, vt={self.vt})"


class HomogeneousStrain(Motion):
    """Homogeneous (affine) deformation about a fixed point ``center = (x0, y0)``.

    ``u = s(t) * [exx (x - x0) + (exy - omega) (y - y0)]``
    ``v = s(t) * [(exy + omega) (x - x0) + eyy (y - y0)]``

    with ``s(t) = 1`` if ``rate is None`` (static, also at t = 0) else ``s(t) = rate * t``
    (strain growing linearly in time: the strain at time t is ``exx * rate * t``...).
    ``exy`` is the tensor shear strain (engineering shear = 2 exy), ``omega`` a small rotation
    [rad]. The gradient is constant in space: ``(s exx, s (exy - omega), s (exy + omega), s eyy)``.
    """

    def __init__(
        self,
        exx: float = 0.0,
        eyy: float = 0.0,
        exy: float = 0.0,
        center: tuple[float, float] = (0.0, 0.0),
        rate: float | None = None,
        omega: float = 0.0,
    ):
        self.exx, self.eyy, self.exy, self.omega = float(exx), float(eyy), float(exy), float(omega)
        self.center = (float(center[0]), float(center[1]))
        self.rate = None if rate is None else float(rate)

    def _s(self, t: Tensor) -> Tensor:
        return torch.ones_like(t) if self.rate is None else self.rate * t

    def _ds(self, t: Tensor) -> Tensor:
        return torch.zeros_like(t) if self.rate is None else torch.full_like(t, self.rate)

    def _lin(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        dx, dy = x - self.center[0], y - self.center[1]
        u = self.exx * dx + (self.exy - self.omega) * dy
        v = (self.exy + self.omega) * dx + self.eyy * dy
        return u, v

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        u, v = self._lin(x, y)
        s = self._s(t)
        return s * u, s * v

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        s = self._s(t)
        return (s * self.exx, s * (self.exy - self.omega), s * (self.exy + self.omega),
                s * self.eyy)

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        u, v = self._lin(x, y)
        ds = self._ds(t)
        return ds * u, ds * v

    def __repr__(self) -> str:
        return (f"HomogeneousStrain(exx={self.exx}, eyy={self.eyy}, exy={self.exy}, "
                f"center={self.center}, rate={self.rate}, omega={self.omega})")


class QuadraticInTime(Motion):
    """Uniform motion, quadratic in time (constant acceleration).

    ``u = au * t + bu * t^2``, ``v = av * t + bv * t^2``; gradient 0;
    velocity ``(au + 2 bu t, av + 2 bv t)``. Breaks the linear-in-time assumption of STS-DIC.
    """

    def __init__(self, au: float = 0.0, bu: float = 0.0, av: float = 0.0, bv: float = 0.0):
        self.au, self.bu, self.av, self.bv = float(au), float(bu), float(av), float(bv)

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        return self.au * t + self.bu * t * t, self.av * t + self.bv * t * t

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        z = _zeros_like(x)
        return z, z.clone(), z.clone(), z.clone()

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        return self.au + 2.0 * self.bu * t, self.av + 2.0 * self.bv * t

    def __repr__(self) -> str:
        return f"QuadraticInTime(au={self.au}, bu={self.bu}, av={self.av}, bv={self.bv})"


class Sinusoidal(Motion):
    """Sinusoidal displacement field (non-uniform strain), optionally growing in time.

    With ``q = x`` (``axis="x"``) or ``q = y`` (``axis="y"``) and
    ``phi = 2 pi q / wavelength + phase``:

    ``u = s(t) * amplitude_u * sin(phi)``, ``v = s(t) * amplitude_v * sin(phi)``

    with ``s(t) = 1`` if ``rate is None`` else ``rate * t``. E.g. ``Sinusoidal(0.5, 0, 64)`` is
    ``u = 0.5 sin(2 pi x / 64)``, a strain ``du/dx`` of amplitude ``0.5 * 2 pi / 64 = 0.049``.
    """

    def __init__(
        self,
        amplitude_u: float = 0.5,
        amplitude_v: float = 0.0,
        wavelength: float = 64.0,
        axis: str = "x",
        phase: float = 0.0,
        rate: float | None = None,
    ):
        if axis not in ("x", "y"):
            raise ValueError("axis must be 'x' or 'y'")
        if wavelength <= 0:
            raise ValueError("wavelength must be positive")
        self.au, self.av = float(amplitude_u), float(amplitude_v)
        self.wavelength, self.axis, self.phase = float(wavelength), axis, float(phase)
        self.rate = None if rate is None else float(rate)

    def _phi(self, x: Tensor, y: Tensor) -> Tensor:
        q = x if self.axis == "x" else y
        return 2.0 * math.pi * q / self.wavelength + self.phase

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        s = torch.ones_like(t) if self.rate is None else self.rate * t
        sn = torch.sin(self._phi(x, y)) * s
        return self.au * sn, self.av * sn

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        s = torch.ones_like(t) if self.rate is None else self.rate * t
        d = torch.cos(self._phi(x, y)) * (2.0 * math.pi / self.wavelength) * s
        z = _zeros_like(x)
        if self.axis == "x":
            return self.au * d, z, self.av * d, z.clone()
        return z, self.au * d, z.clone(), self.av * d

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        if self.rate is None:
            z = _zeros_like(x)
            return z, z.clone()
        sn = torch.sin(self._phi(x, y)) * self.rate
        return self.au * sn, self.av * sn

    def __repr__(self) -> str:
        return (f"Sinusoidal(amplitude_u={self.au}, amplitude_v={self.av}, "
                f"wavelength={self.wavelength}, axis={self.axis!r}, phase={self.phase}, "
                f"rate={self.rate})")


class Jump(Motion):
    """Crack-like sudden jump: material right of the line ``x = x0`` jumps at ``t_jump``.

    ``(u, v) = (du, dv)`` where ``x > x0`` and ``t >= t_jump``, else 0 (discontinuous in space
    and time). Gradient and velocity are 0 (the Dirac parts at ``x0`` / ``t_jump`` are ignored).
    In :func:`render` each spot moves with its centre, so a spot straddling ``x0`` moves as a
    whole: the crack is resolved to the spot scale.
    """

    def __init__(self, x0: float, du: float = 1.0, dv: float = 0.0, t_jump: float = 0.0):
        self.x0, self.du, self.dv, self.t_jump = float(x0), float(du), float(dv), float(t_jump)

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        on = ((x > self.x0) & (t >= self.t_jump)).to(_DT)
        return on * self.du, on * self.dv

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        z = _zeros_like(x)
        return z, z.clone(), z.clone(), z.clone()

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        z = _zeros_like(x)
        return z, z.clone()

    def __repr__(self) -> str:
        return f"Jump(x0={self.x0}, du={self.du}, dv={self.dv}, t_jump={self.t_jump})"


class Custom(Motion):
    """User-defined motion from a callable ``fn(x, y, t) -> (u, v)`` (float64 tensors).

    ``gradient`` and ``velocity`` use the given callables if any, else central finite
    differences with steps ``h`` [px] and ``ht`` [time] (accurate to ~1e-8 for smooth fields).
    """

    def __init__(
        self,
        fn: Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]],
        gradient_fn: Callable[[Tensor, Tensor, Tensor], tuple[Tensor, ...]] | None = None,
        velocity_fn: Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]] | None = None,
        h: float = 1e-4,
        ht: float = 1e-4,
    ):
        self.fn, self.gradient_fn, self.velocity_fn = fn, gradient_fn, velocity_fn
        self.h, self.ht = float(h), float(ht)

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        u, v = self.fn(x, y, t)
        return torch.broadcast_to(_t(u), x.shape), torch.broadcast_to(_t(v), x.shape)

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        if self.gradient_fn is not None:
            return tuple(torch.broadcast_to(_t(g), x.shape) for g in self.gradient_fn(x, y, t))
        h = self.h
        up, vp = self.displacement(x + h, y, t)
        um, vm = self.displacement(x - h, y, t)
        uq, vq = self.displacement(x, y + h, t)
        un, vn = self.displacement(x, y - h, t)
        return (up - um) / (2 * h), (uq - un) / (2 * h), (vp - vm) / (2 * h), (vq - vn) / (2 * h)

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        if self.velocity_fn is not None:
            ut, vt = self.velocity_fn(x, y, t)
            return torch.broadcast_to(_t(ut), x.shape), torch.broadcast_to(_t(vt), x.shape)
        up, vp = self.displacement(x, y, t + self.ht)
        um, vm = self.displacement(x, y, t - self.ht)
        return (up - um) / (2 * self.ht), (vp - vm) / (2 * self.ht)


class Sum(Motion):
    """Superposition ``U = U_1 + U_2 + ...`` (displacements, gradients, velocities add).

    Also available as ``m1 + m2``. E.g. ``Translation(ut=0.05) + Jump(150, du=0.3, t_jump=5)``.
    """

    def __init__(self, *motions: Motion):
        flat: list[Motion] = []
        for m in motions:
            if not isinstance(m, Motion):
                raise TypeError(f"not a Motion: {m!r}")
            flat.extend(m.motions if isinstance(m, Sum) else [m])
        if not flat:
            raise ValueError("Sum needs at least one motion")
        self.motions = flat

    def _acc(self, name: str, x, y, t) -> tuple[Tensor, ...]:
        out = None
        for m in self.motions:
            r = getattr(m, name)(x, y, t)
            out = list(r) if out is None else [a + b for a, b in zip(out, r)]
        return tuple(out)  # type: ignore[arg-type]

    def displacement(self, x, y, t):
        return self._acc("displacement", x, y, t)

    def gradient(self, x, y, t):
        return self._acc("gradient", x, y, t)

    def velocity(self, x, y, t):
        return self._acc("velocity", x, y, t)

    def __repr__(self) -> str:
        return " + ".join(repr(m) for m in self.motions)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------

_SQRT2 = math.sqrt(2.0)
_SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_CHUNK = 1 << 20  # max elements of the largest temporary per chunk (8 MiB in float64)


def _erf_profile(edges: Tensor, c: Tensor, s: Tensor) -> Tensor:
    """Integrals of ``exp(-(x - c)^2 / (2 s^2))`` over consecutive intervals of ``edges``.

    edges (K, P+1), c and s (K,) -> (K, P).
    """
    e = torch.erf((edges - c[:, None]) / (_SQRT2 * s[:, None]))
    return (e[:, 1:] - e[:, :-1]) * (_SQRT_PI_2 * s[:, None])


def _check_coverage(pattern: SpecklePattern, shape: tuple[int, int], motion: Motion | None,
                    t: float) -> None:
    if pattern.bounds is None or motion is None:
        return
    H, W = shape
    rmax = float(pattern.radius.max()) if len(pattern) else 0.0
    xs = torch.linspace(-0.5, W - 0.5, max(2, W // 16 + 2), dtype=_DT)
    ys = torch.linspace(-0.5, H - 0.5, max(2, H // 16 + 2), dtype=_DT)
    bx = torch.cat([xs, xs, torch.full_like(ys, -0.5), torch.full_like(ys, W - 0.5)])
    by = torch.cat([torch.full_like(xs, -0.5), torch.full_like(xs, H - 0.5), ys, ys])
    u, v = motion.displacement(bx, by, t)
    px, py = bx - u, by - v  # first-order inverse: material point seen at the image border
    x0, x1, y0, y1 = pattern.bounds
    m = 2.0 * rmax
    if bool(((px < x0 + m) | (px > x1 - m) | (py < y0 + m) | (py > y1 - m)).any()):
        warnings.warn(
            f"synth.render: at t={t} the motion moves the pattern's edge into the image "
            f"(max |u|={float(u.abs().max()):.3g}, |v|={float(v.abs().max()):.3g} px); "
            "use a larger margin in make_speckle", stacklevel=3)


def render(
    pattern: SpecklePattern,
    shape: tuple[int, int],
    motion: Motion | None = None,
    t: float = 0.0,
    *,
    quadrature: int = 4,
    cutoff: float = 6.0,
    check_coverage: bool = True,
) -> Tensor:
    """Render the pattern deformed by ``motion`` at time ``t``; exact pixel-area integration.

    Each spot centre ``c`` is moved to ``c + U(c, t)`` and its shape mapped by
    ``F = I + grad U(c, t)`` (exact for affine motion). Pixel values are means over the unit
    pixel square: exact (``erf``) along x; along y exact where ``F F^T`` is diagonal, else
    Gauss-Legendre with ``quadrature`` nodes. Vectorised over spots (``index_add_`` of local
    patches of half-width ``ceil(cutoff * sigma)``, spots grouped by patch size).

    Args:
        pattern: the speckle pattern (undeformed configuration).
        shape: (H, W) of the image [px].
        motion: displacement field; None = undeformed.
        t: time at which the motion is evaluated.
        quadrature: Gauss-Legendre nodes per pixel along y for sheared/rotated spots.
        cutoff: spots are truncated beyond ``cutoff`` standard deviations (6: relative
            truncation error < 2e-8 of the spot amplitude).
        check_coverage: warn if the motion pulls the pattern's margin into the image.

    Returns:
        (H, W) float64 tensor of grey levels.

    Raises:
        ValueError: if ``det F <= 0`` for some spot (folding motion).
    """
    H, W = int(shape[0]), int(shape[1])
    if quadrature < 1:
        raise ValueError("quadrature must be >= 1")
    dev = pattern.x.device
    img = torch.full((H, W), float(pattern.background), dtype=_DT, device=dev)
    if len(pattern) == 0:
        return img
    cx, cy = pattern.x.to(_DT), pattern.y.to(_DT)
    r, a = pattern.radius.to(_DT), pattern.amplitude.to(_DT)
    n = cx.shape[0]
    if motion is None:
        f00 = torch.ones(n, dtype=_DT, device=dev)
        f11 = f00.clone()
        f01 = torch.zeros(n, dtype=_DT, device=dev)
        f10 = f01.clone()
    else:
        if check_coverage:
            _check_coverage(pattern, (H, W), motion, t)
        u, v = motion.displacement(cx, cy, t)
        g = motion.gradient(cx, cy, t)
        u, v = torch.broadcast_to(u, (n,)).to(dev), torch.broadcast_to(v, (n,)).to(dev)
        dudx, dudy, dvdx, dvdy = (torch.broadcast_to(q, (n,)).to(dev) for q in g)
        cx, cy = cx + u, cy + v
        f00, f01, f10, f11 = 1.0 + dudx, dudy, dvdx, 1.0 + dvdy
    det = f00 * f11 - f01 * f10
    if bool((det <= 0).any()) or not bool(torch.isfinite(det).all()):
        raise ValueError("motion folds the material (det F <= 0) or is not finite at some spot")
    # Covariance of the deformed spot: r^2 F F^T.
    sxx = r * r * (f00 * f00 + f01 * f01)
    syy = r * r * (f10 * f10 + f11 * f11)
    sxy = r * r * (f00 * f10 + f01 * f11)
    sx, sy = torch.sqrt(sxx), torch.sqrt(syy)
    h = torch.ceil(cutoff * torch.maximum(sx, sy)).clamp(min=1).to(torch.long)
    jc = torch.floor(cx + 0.5).to(torch.long)
    ic = torch.floor(cy + 0.5).to(torch.long)
    keep = (jc + h >= 0) & (jc - h <= W - 1) & (ic + h >= 0) & (ic - h <= H - 1)
    if not bool(keep.any()):
        return img
    hmax = int(h[keep].max())
    pad = 2 * hmax + 1  # patch rows span ic +- h with ic in [-h, H - 1 + h]
    Wp = W + 2 * pad
    canvas = torch.zeros((H + 2 * pad) * Wp, dtype=_DT, device=dev)
    sep = sxy == 0
    xi_np, wq_np = np.polynomial.legendre.leggauss(int(quadrature))
    xi = torch.as_tensor(xi_np * 0.5, dtype=_DT, device=dev)  # nodes on [-1/2, 1/2]
    wq = torch.as_tensor(wq_np * 0.5, dtype=_DT, device=dev)  # weights sum to 1

    for separable in (True, False):
        sel_mask = keep & (sep if separable else ~sep)
        if not bool(sel_mask.any()):
            continue
        for hv in torch.unique(h[sel_mask]).tolist():
            idx = torch.nonzero(sel_mask & (h == hv)).squeeze(1)
            P = 2 * hv + 1
            per_spot = P * (P + 1) * (1 if separable else quadrature)
            step = max(1, _CHUNK // per_spot)
            off = torch.arange(-hv, hv + 1, device=dev)
            edge_off = torch.arange(-hv, hv + 2, device=dev, dtype=_DT) - 0.5
            for s0 in range(0, idx.numel(), step):
                k = idx[s0:s0 + step]
                jk, ik = jc[k], ic[k]
                xe = jk[:, None].to(_DT) + edge_off  # (K, P+1) pixel column edges
                if separable:
                    px = _erf_profile(xe, cx[k], sx[k])
                    ye = ik[:, None].to(_DT) + edge_off
                    py = _erf_profile(ye, cy[k], sy[k])
                    patch = (a[k][:, None] * py)[:, :, None] * px[:, None, :]
                else:
                    patch = _sheared_patch(xe, ik, off, xi, wq, cx[k], cy[k], sxx[k], syy[k],
                                           sxy[k], a[k])
                rows = ik[:, None] + off + pad  # (K, P)
                cols = jk[:, None] + off + pad
                flat = (rows[:, :, None] * Wp + cols[:, None, :]).reshape(-1)
                canvas.index_add_(0, flat, patch.reshape(-1))
    img += canvas.view(H + 2 * pad, Wp)[pad:pad + H, pad:pad + W]
    return img


def _sheared_patch(xe: Tensor, ik: Tensor, off: Tensor, xi: Tensor, wq: Tensor, cx: Tensor,
                   cy: Tensor, sxx: Tensor, syy: Tensor, sxy: Tensor, a: Tensor) -> Tensor:
    """Pixel integrals of general (correlated) Gaussian spots -> (K, P, P).

    With ``M = Sigma^{-1} = [[A, B], [B, C]]`` the exponent is
    ``A (dx + B/A dy)^2 + (C - B^2/A) dy^2``: for every y node the x-profile is a 1-D Gaussian
    of std ``1/sqrt(A)`` centred at ``cx - B/A dy``, integrated exactly with erf.
    """
    det = sxx * syy - sxy * sxy
    A, B, C = syy / det, -sxy / det, sxx / det
    sa = 1.0 / torch.sqrt(A)  # conditional std along x
    cyy = C - B * B / A  # = 1 / syy
    yn = (ik[:, None].to(_DT) + off.to(_DT))[:, :, None] + xi  # (K, P, Q) y nodes
    dy = yn - cy[:, None, None]
    mu = cx[:, None, None] - (B / A)[:, None, None] * dy  # (K, P, Q)
    e = torch.erf((xe[:, None, None, :] - mu[..., None]) / (_SQRT2 * sa)[:, None, None, None])
    ix = (e[..., 1:] - e[..., :-1]) * (_SQRT_PI_2 * sa)[:, None, None, None]  # (K, P, Q, P)
    wy = wq * torch.exp(-0.5 * cyy[:, None, None] * dy * dy) * a[:, None, None]  # (K, P, Q)
    return (wy[..., None] * ix).sum(2)


# --------------------------------------------------------------------------------------------
# Noise, quantisation, series
# --------------------------------------------------------------------------------------------


def _generator(seed: int | torch.Generator | None) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        return seed
    g = torch.Generator()
    if seed is None:
        g.seed()
    else:
        g.manual_seed(int(seed))
    return g


def add_noise(
    img: Tensor,
    sigma: float,
    seed: int | torch.Generator | None = None,
    *,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Return ``img`` plus i.i.d. zero-mean Gaussian noise of std ``sigma`` [grey levels].

    ``seed`` may be an int or a ``torch.Generator`` (``generator=`` is an alias); None draws a
    random seed. The input is not modified. Output float64, same shape.
    """
    img = img.to(_DT)
    if sigma < 0:
        raise ValueError("sigma must be >= 0")
    if sigma == 0:
        return img.clone()
    g = generator if generator is not None else _generator(seed)
    noise = torch.randn(img.shape, generator=g, dtype=_DT)
    return img + float(sigma) * noise.to(img.device)


def quantize(img: Tensor, bits: int = 8, *, dtype: torch.dtype | None = None) -> Tensor:
    """Digitise an 8-bit-scale image to ``bits`` bits: scale, round, clip.

    The image is multiplied by ``(2^bits - 1) / 255`` (1 for 8 bits, 257 for 16 bits, so the
    same pattern fills the same fraction of the range), rounded to integers and clipped to
    ``0 .. 2^bits - 1``. Returns float64 (integer values) unless ``dtype`` is given.
    """
    if not 1 <= int(bits) <= 32:
        raise ValueError("bits must be in 1..32")
    top = float(2 ** int(bits) - 1)
    out = torch.clamp(torch.round(img.to(_DT) * (top / 255.0)), 0.0, top)
    return out if dtype is None else out.to(dtype)


def render_series(
    pattern: SpecklePattern,
    shape: tuple[int, int],
    motion: Motion | None,
    times: ArrayLike,
    *,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int | torch.Generator | None = 0,
    reference_time: float | None = 0.0,
    quadrature: int = 4,
) -> tuple[Tensor, Tensor]:
    """Render a reference image and a time series of deformed frames.

    The reference is rendered at ``reference_time`` (None: the undeformed pattern, i.e. no
    motion), every frame at its time; then independent Gaussian noise of std ``noise_sigma``
    [8-bit grey levels] is added to *all* images (reference first, then frames in order, from
    one generator seeded with ``seed``), and finally, if ``bits`` is given, they are quantised
    with :func:`quantize` (16 bits: values scaled by 257).

    The ground truth relative to the reference is ``ground_truth(motion, X, times)`` when
    ``U(X, reference_time) = 0`` (true at t = 0 for every time-dependent motion here); otherwise
    pass ``reference_time`` to :func:`ground_truth` as well (or use ``reference_time=None``).

    Returns:
        ``(ref, frames)``: ``(H, W)`` and ``(T, H, W)`` float64.
    """
    tt = _t(times).reshape(-1)
    if reference_time is None:
        ref = render(pattern, shape, None, quadrature=quadrature)
    else:
        if motion is not None:
            H, W = shape
            gy, gx = torch.meshgrid(torch.linspace(0, H - 1, 5, dtype=_DT),
                                    torch.linspace(0, W - 1, 5, dtype=_DT), indexing="ij")
            u0, v0 = motion.displacement(gx, gy, float(reference_time))
            if float(torch.maximum(u0.abs(), v0.abs()).max()) > 1e-12:
                warnings.warn(
                    f"synth.render_series: U(X, reference_time={reference_time}) != 0, so the "
                    "reference image is itself deformed; the truth relative to it is "
                    f"ground_truth(..., reference_time={reference_time}) (or pass "
                    "reference_time=None to use the undeformed pattern as reference)",
                    stacklevel=2)
        ref = render(pattern, shape, motion, float(reference_time), quadrature=quadrature)
    frames = torch.stack([render(pattern, shape, motion, float(ti), quadrature=quadrature)
                          for ti in tt]) if tt.numel() else torch.empty((0, *shape), dtype=_DT)
    if noise_sigma > 0:
        g = _generator(seed)
        ref = add_noise(ref, noise_sigma, generator=g)
        frames = torch.stack([add_noise(f, noise_sigma, generator=g) for f in frames]) \
            if tt.numel() else frames
    if bits is not None:
        ref, frames = quantize(ref, bits), quantize(frames, bits)
    return ref, frames


def ground_truth(
    motion: Motion,
    points: ArrayLike,
    times: ArrayLike,
    *,
    reference_time: float | None = None,
    iterations: int = 20,
) -> dict[str, Tensor]:
    """Exact displacements, velocities and gradients at reference points.

    Args:
        motion: the motion used to render the frames.
        points: (N, 2) reference-image coordinates ``(x, y)`` [px].
        times: (T,) frame times.
        reference_time: None (default): the reference image is the undeformed pattern (or
            ``U(X, reference_time) = 0``), so the truth is ``U(X, t)``. A float: the
            reference was rendered at that time; points are then mapped back to the material
            (solve ``X = C + U(C, t_ref)`` by Newton) and displacements are relative:
            ``U(C, t) - U(C, t_ref)``, gradients w.r.t. reference-image coordinates.
        iterations: Newton iterations for the inversion.

    Returns:
        dict of float64 tensors, each (T, N): ``u, v`` [px], ``ut, vt`` [px / time unit],
        ``dudx, dudy, dvdx, dvdy`` [-].
    """
    pts = _t(points).reshape(-1, 2)
    tt = _t(times).reshape(-1)
    x, y = pts[:, 0], pts[:, 1]
    T, N = tt.numel(), x.numel()
    grad_ref = None
    if reference_time is not None:
        t0 = float(reference_time)
        cx, cy = x.clone(), y.clone()
        for _ in range(int(iterations)):
            u0, v0 = motion.displacement(cx, cy, t0)
            a, b, c, d = motion.gradient(cx, cy, t0)
            rx, ry = cx + u0 - x, cy + v0 - y
            a, b, c, d = 1.0 + a, b, c, 1.0 + d
            det = a * d - b * c
            cx, cy = cx - (d * rx - b * ry) / det, cy - (-c * rx + a * ry) / det
        u0, v0 = motion.displacement(cx, cy, t0)
        grad_ref = motion.gradient(cx, cy, t0)
        x, y = cx, cy
    X, Y, TT = x[None, :].expand(T, N), y[None, :].expand(T, N), tt[:, None].expand(T, N)
    u, v = motion.displacement(X, Y, TT)
    ut, vt = motion.velocity(X, Y, TT)
    g = motion.gradient(X, Y, TT)
    if grad_ref is not None:
        u, v = u - u0, v - v0
        # d(U(C,t) - U(C,t0))/dX = (G(t) - G(t0)) (I + G(t0))^-1
        a0, b0, c0, d0 = (torch.broadcast_to(q, (N,)) for q in grad_ref)
        e00, e01, e10, e11 = g[0] - a0, g[1] - b0, g[2] - c0, g[3] - d0
        f00, f01, f10, f11 = 1.0 + a0, b0, c0, 1.0 + d0
        det = f00 * f11 - f01 * f10
        i00, i01, i10, i11 = f11 / det, -f01 / det, -f10 / det, f00 / det
        g = (e00 * i00 + e01 * i10, e00 * i01 + e01 * i11,
             e10 * i00 + e11 * i10, e10 * i01 + e11 * i11)
    out = {"u": u, "v": v, "ut": ut, "vt": vt,
           "dudx": g[0], "dudy": g[1], "dvdx": g[2], "dvdy": g[3]}
    return {k: torch.broadcast_to(val.to(_DT), (T, N)).clone() for k, val in out.items()}


class Movie(NamedTuple):
    """Result of :func:`synthetic_movie` (unpacks as ``ref, frames, times, motion``)."""

    ref: Tensor  #: (H, W) reference image
    frames: Tensor  #: (T, H, W) deformed frames
    times: Tensor  #: (T,) frame times
    motion: Motion  #: the motion, for :func:`ground_truth`


def synthetic_movie(
    shape: tuple[int, int] = (301, 301),
    n_frames: int = 9,
    motion: Motion | None = None,
    *,
    times: ArrayLike | None = None,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int = 0,
    radius: float = 2.0,
    density: float | None = None,
    margin: float | None = None,
) -> Movie:
    """One-call demo series; defaults reproduce the paper's simulated experiment.

    Default: a 301 x 301 speckle, reference at t = 0 and 9 frames at t = 1..9 moving by
    ``u = t / 20`` px (``Translation(ut=0.05)``), noise ``noise_sigma`` on all 10 images.
    The pattern uses ``seed``; the noise uses an independent seed derived from it.

    Returns:
        ``Movie(ref, frames, times, motion)``; truth via ``ground_truth(movie.motion, pts,
        movie.times)``.
    """
    if motion is None:
        motion = Translation(ut=1.0 / 20.0)
    tt = torch.arange(1, n_frames + 1, dtype=_DT) if times is None else _t(times).reshape(-1)
    pattern = make_speckle(shape, density=density, radius=radius, seed=seed, margin=margin)
    noise_seed = (int(seed) * 1_000_003 + 7_919) % (2**63)
    ref, frames = render_series(pattern, shape, motion, tt, noise_sigma=noise_sigma, bits=bits,
                                seed=noise_seed)
    return Movie(ref, frames, tt, motion)
