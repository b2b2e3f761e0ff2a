"""Motions with exact displacement, gradient and velocity: translation, homogeneous strain,
quadratic in time, sinusoidal, jump, custom, and sums of them."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torch_stsdic.synth.pattern import DTYPE, ArrayLike, as_float64

__all__ = ["Motion", "Translation", "HomogeneousStrain", "QuadraticInTime", "Sinusoidal", "Jump",
           "Custom", "Sum"]




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
        x, y, t = as_float64(x), as_float64(y), as_float64(t)
        return tuple(torch.broadcast_tensors(x, y, t))  # type: ignore[return-value]


def _broadcast(a: ArrayLike, like: Tensor) -> Tensor:
    return torch.broadcast_to(as_float64(a), like.shape)


def _zeros_like(x: Tensor) -> Tensor:
    return torch.zeros_like(x, dtype=DTYPE)


class _Uniform(Motion):
    """A motion the same at every point, ``(u(t), v(t))``: zero gradient. Subclasses give
    :meth:`_at` and :meth:`_rate` of the (broadcast) times."""

    def _at(self, t: Tensor) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def _rate(self, t: Tensor) -> tuple[Tensor | float, Tensor | float]:
        raise NotImplementedError

    def displacement(self, x, y, t):
        return self._at(self._shape(x, y, t)[2])

    def gradient(self, x, y, t):
        z = _zeros_like(self._shape(x, y, t)[0])
        return z, z.clone(), z.clone(), z.clone()

    def velocity(self, x, y, t):
        t = self._shape(x, y, t)[2]
        du, dv = self._rate(t)
        return _zeros_like(t) + du, _zeros_like(t) + dv


class Translation(_Uniform):
    """Rigid translation, optionally moving at constant speed.

    ``u = u0 + ut * t``, ``v = v0 + vt * t``; gradient 0; velocity ``(ut, vt)``.
    The paper's simulated test is ``Translation(ut=1 / 20)`` with t = 1..9.
    """

    def __init__(self, u0: float = 0.0, v0: float = 0.0, ut: float = 0.0, vt: float = 0.0):
        self.u0, self.v0, self.ut, self.vt = float(u0), float(v0), float(ut), float(vt)

    def _at(self, t):
        return self.u0 + self.ut * t, self.v0 + self.vt * t

    def _rate(self, t):
        return self.ut, self.vt

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


class Rotation(Motion):
    """Rigid rotation about ``center = (x0, y0)`` at ``rate`` degrees per time unit (finite,
    not small-angle: an exact arc), positive = clockwise on screen (x right, y down).

    With ``theta = rate * t`` (radians), ``d = X - center``:
    ``u = (cos theta - 1) dx - sin theta dy``, ``v = sin theta dx + (cos theta - 1) dy``;
    gradient ``(cos - 1, -sin, sin, cos - 1)``; velocity ``theta' (-sin dx - cos dy,
    cos dx - sin dy)``. Breaks the affine-in-time model of STS-DIC (the subset turns along
    an arc); used by the motion-family validation.
    """

    def __init__(self, rate: float, center: tuple[float, float] = (0.0, 0.0)):
        self.rate = float(rate)
        self.center = (float(center[0]), float(center[1]))

    def _angle(self, t: Tensor) -> Tensor:
        return t * (self.rate * math.pi / 180.0)

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        th = self._angle(t)
        dx, dy = x - self.center[0], y - self.center[1]
        c, s = torch.cos(th), torch.sin(th)
        return (c - 1) * dx - s * dy, s * dx + (c - 1) * dy

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        th = self._angle(t)
        c, s = torch.cos(th), torch.sin(th)
        return c - 1, -s, s.clone(), c - 1

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        th = self._angle(t)
        w = self.rate * math.pi / 180.0
        dx, dy = x - self.center[0], y - self.center[1]
        c, s = torch.cos(th), torch.sin(th)
        return w * (-s * dx - c * dy), w * (c * dx - s * dy)

    def __repr__(self) -> str:
        return f"Rotation(rate={self.rate}, center={self.center})"


class RigidJitter(Motion):
    """A rigid motion of the whole field of view per frame: the shake of a specimen (or a
    camera) between frames. At time ``times[k]`` the translation is ``(tx[k], ty[k])`` px and
    the rotation ``angle[k]`` rad about ``center`` (exact, not small-angle); at any other
    time that of the nearest listed time. Add it to a smooth deformation
    (``HomogeneousStrain(...) + RigidJitter.random(...)``) for a movie that jitters the way
    real ones do. Its velocity is reported as zero (a jitter has no smooth velocity).
    """

    def __init__(self, times: ArrayLike, tx: ArrayLike, ty: ArrayLike,
                 angle: ArrayLike | None = None, center: tuple[float, float] = (0.0, 0.0)):
        self.times = as_float64(times).reshape(-1)
        self.tx, self.ty = as_float64(tx).reshape(-1), as_float64(ty).reshape(-1)
        self.angle = (torch.zeros_like(self.tx) if angle is None
                      else as_float64(angle).reshape(-1))
        if not (self.times.numel() == self.tx.numel() == self.ty.numel()
                == self.angle.numel()) or self.times.numel() == 0:
            raise ValueError("RigidJitter: times, tx, ty, angle must have one value per frame")
        self.center = (float(center[0]), float(center[1]))

    @classmethod
    def random(cls, times: ArrayLike, shift_std: float, angle_std: float = 0.0,
               center: tuple[float, float] = (0.0, 0.0), seed: int = 0,
               still: float | None = 0.0) -> RigidJitter:
        """Independent Gaussian jitter per frame: translation std ``shift_std`` px per axis,
        rotation std ``angle_std`` rad; the frame at time ``still`` (default 0, the usual
        reference) does not move (None: every frame jitters)."""
        t = as_float64(times).reshape(-1)
        g = torch.Generator().manual_seed(int(seed))
        tx = torch.randn(t.numel(), generator=g, dtype=DTYPE) * shift_std
        ty = torch.randn(t.numel(), generator=g, dtype=DTYPE) * shift_std
        an = torch.randn(t.numel(), generator=g, dtype=DTYPE) * angle_std
        if still is not None:
            at = (t - float(still)).abs() < 1e-9
            tx[at], ty[at], an[at] = 0.0, 0.0, 0.0
        return cls(t, tx, ty, an, center)

    def _at(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        k = (t.unsqueeze(-1) - self.times).abs().argmin(-1)
        return self.tx[k], self.ty[k], self.angle[k]

    def displacement(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        tx, ty, th = self._at(t)
        dx, dy = x - self.center[0], y - self.center[1]
        c, s = torch.cos(th), torch.sin(th)
        return (c - 1) * dx - s * dy + tx, s * dx + (c - 1) * dy + ty

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        _, _, th = self._at(t)
        c, s = torch.cos(th), torch.sin(th)
        return c - 1, -s, s.clone(), c - 1

    def velocity(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        return _zeros_like(x), _zeros_like(x)

    def __repr__(self) -> str:
        return f"RigidJitter({self.times.numel()} frames, center={self.center})"


class QuadraticInTime(_Uniform):
    """Uniform motion, quadratic in time (constant acceleration).

    ``u = au * t + bu * t^2``, ``v = av * t + bv * t^2``; gradient 0;
    velocity ``(au + 2 bu t, av + 2 bv t)``. Breaks the linear-in-time assumption of STS-DIC.
    """

    def __init__(self, au: float = 0.0, bu: float = 0.0, av: float = 0.0, bv: float = 0.0):
        self.au, self.bu, self.av, self.bv = float(au), float(bu), float(av), float(bv)

    def _at(self, t):
        return self.au * t + self.bu * t * t, self.av * t + self.bv * t * t

    def _rate(self, t):
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
        on = ((x > self.x0) & (t >= self.t_jump)).to(DTYPE)
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
        return _broadcast(u, x), _broadcast(v, x)

    def gradient(self, x, y, t):
        x, y, t = self._shape(x, y, t)
        if self.gradient_fn is not None:
            return tuple(_broadcast(g, x) for g in self.gradient_fn(x, y, t))
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
            return _broadcast(ut, x), _broadcast(vt, x)
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



#: motion families that break the affine-in-time window of STS-DIC (:func:`motion_family`)
MOTION_FAMILIES = ("rotation4", "rotation1", "acceleration", "crack", "large_translation")


def motion_family(name: str, size: int, t_jump: float = 5.0) -> Motion:
    """A motion of one of the :data:`MOTION_FAMILIES` on a ``size`` x ``size`` image (frame
    units), as used by ``scripts/motion_families.py`` and the tests of the trust checks:
    rigid rotation about the image centre at 4 or 1 deg/frame; constant acceleration
    (u = 0.2 t + 0.05 t^2, v = -0.1 t + 0.03 t^2); a crack (the right half jumps by (1.5,
    0.8) px at ``t_jump`` on top of 0.3 px/frame); a large translation (12, -7) px/frame."""
    c = (size - 1) / 2
    if name == "rotation4":
        return Rotation(4.0, (c, c))
    if name == "rotation1":
        return Rotation(1.0, (c, c))
    if name == "acceleration":
        return QuadraticInTime(au=0.2, bu=0.05, av=-0.1, bv=0.03)
    if name == "crack":
        return Translation(ut=0.3) + Jump(c + 0.5, du=1.5, dv=0.8, t_jump=t_jump)
    if name == "large_translation":
        return Translation(ut=12.0, vt=-7.0)
    raise ValueError(f"unknown motion family {name!r}; one of {MOTION_FAMILIES}")
