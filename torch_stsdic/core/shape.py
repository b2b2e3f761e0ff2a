"""Shape functions: the displacement of every subset pixel at every frame time.

All shape functions here are linear in their parameters and share one basis between the
two displacement components (the paper's Eq. 9 written as U = a [1, dx, dy, dt]^T):

    u(dx, dy, dt) = sum_k p_u[k] * basis_k(dx, dy, dt)
    v(dx, dy, dt) = sum_k p_v[k] * basis_k(dx, dy, dt)

with (dx, dy) the pixel's offset from the point of interest (px) and dt = t - t_c the frame
time minus the time the results refer to (frames). The parameter vector is
p = (p_u[0..K-1], p_v[0..K-1]), so the Jacobian dU/dp is block diagonal: the basis itself.

With a single frame (m = 0) the temporal basis terms vanish and are dropped, which gives
exactly the classical subset DIC shape function (6 or 12 unknowns).
"""

from __future__ import annotations

import torch
from torch import nn

from torch_stsdic.kernels.ic_step import linear_displacement

__all__ = ["ShapeFunction", "AffineShape", "QuadraticShape", "make_shape", "linear_displacement"]


class ShapeFunction(nn.Module):
    """Base class. Subclasses define ``basis_names`` (per component) and ``basis``."""

    basis_names: tuple[str, ...] = ()
    temporal: tuple[str, ...] = ("t",)

    def __init__(self, temporal: bool = True) -> None:
        super().__init__()
        self.use_temporal = temporal

    # ---- naming -------------------------------------------------------------------------
    @property
    def terms(self) -> tuple[str, ...]:
        if self.use_temporal:
            return self.basis_names
        return tuple(n for n in self.basis_names if n not in self.temporal)

    @property
    def n_basis(self) -> int:
        return len(self.terms)

    @property
    def n_params(self) -> int:
        """Number of unknowns P (2 x the basis size)."""
        return 2 * self.n_basis

    @property
    def param_names(self) -> tuple[str, ...]:
        """E.g. ('u', 'ux', 'uy', 'ut', 'v', 'vx', 'vy', 'vt') for the affine STS function."""
        names = []
        for comp in ("u", "v"):
            names += [comp if t == "1" else comp + t for t in self.terms]
        return tuple(names)

    def index(self, name: str) -> int:
        """Position of a parameter by name ('u', 'vt', 'uxx' ...)."""
        return self.param_names.index(name)

    def spatial(self) -> ShapeFunction:
        """The same shape function without temporal terms (classical DIC, m = 0)."""
        return type(self)(temporal=False)

    def temporal_mask(self) -> torch.Tensor:
        """(P,) bool, True for the velocity parameters."""
        is_t = [t in self.temporal for t in self.terms]
        return torch.tensor(is_t + is_t)

    # ---- geometry -------------------------------------------------------------------------
    def basis(self, dx: torch.Tensor, dy: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """Basis values (T, S, K) for offsets dx, dy (S,) and frame times dt (T,)."""
        raise NotImplementedError

    def spatial_basis(self, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
        """Spatial basis values (S, Ks) (the basis without its temporal term ``t``, which is
        always the last term and enters as p_t * dt)."""
        z = torch.zeros(1, dtype=dx.dtype, device=dx.device)
        b = type(self)(temporal=False).basis(dx, dy, z)
        return b[0]

    @property
    def has_time(self) -> bool:
        """True if the last basis term is the linear-in-time term ``t``."""
        return self.terms[-1] == "t"

    def displacement(self, params: torch.Tensor, spatial: torch.Tensor, dt: torch.Tensor):
        """(u, v) of every subset pixel at every frame time (Eq. 9): each (N, T, S), or
        (N, 1, S) without temporal terms.

        params (N, P); spatial (S, Ks) from :meth:`spatial_basis`; dt (N, T) or (T,) frame
        times minus the time the results refer to."""
        dt = dt.expand(params.shape[0], -1) if dt.dim() == 1 else dt
        return linear_displacement(params, spatial.T, dt, spatial.shape[1], self.n_basis,
                                   self.has_time)

    def warp(self, params: torch.Tensor, px: torch.Tensor, py: torch.Tensor,
             dx: torch.Tensor, dy: torch.Tensor, spatial: torch.Tensor, dt: torch.Tensor,
             motion: torch.Tensor | None = None):
        """Warped subset coordinates (x, y), each (N, T, S) px: the POI (px, py) (N, 1) plus
        the offsets (dx, dy) (S,) plus the displacement at every frame time dt (N, T), plus a
        known ``motion`` (N, T, 2) (u, v) px per frame (the shared motion; None: none)."""
        u, v = self.displacement(params, spatial, dt)
        t_count = dt.shape[-1]
        if motion is not None:
            u = u + motion[..., 0:1]
            v = v + motion[..., 1:2]
        xs = (px.unsqueeze(-1) + dx + u).expand(-1, t_count, -1)
        ys = (py.unsqueeze(-1) + dy + v).expand(-1, t_count, -1)
        return xs, ys

    def increment_scale(self, spatial: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """(N, P) bound of each parameter's effect: |dp * scale| bounds the displacement
        change of any subset pixel in any frame (the convergence test). spatial (S, Ks),
        dt (N, T)."""
        s = spatial.abs().amax(0)  # (Ks,)
        block = s.expand(dt.shape[0], -1)
        if self.has_time:
            block = torch.cat([block, dt.abs().amax(1, keepdim=True)], 1)
        return torch.cat([block, block], 1)

    @property
    def inverse_compositional(self) -> bool:
        """True if the family is closed under composition (:meth:`compose_inverse` exists),
        so the inverse-compositional Gauss-Newton applies."""
        return type(self).compose_inverse is not ShapeFunction.compose_inverse

    def compose_inverse(self, params: torch.Tensor, dp: torch.Tensor) -> torch.Tensor | None:
        """Inverse-compositional update W(p) o W(dp)^-1 in parameter form, or None if the
        family is not closed under composition (the solver then updates additively)."""
        return None

    def extra_repr(self) -> str:
        return f"params={self.param_names}"


class AffineShape(ShapeFunction):
    """First-order spatio-temporal shape function (Eqs. 9-10), 8 unknowns:
    u + ux dx + uy dy + ut dt (and the same for v). m = 0: classical first order (6)."""

    basis_names = ("1", "x", "y", "t")

    def basis(self, dx, dy, dt):
        s, t = dx.shape[0], dt.shape[0]
        one = torch.ones(t, s, dtype=dx.dtype, device=dx.device)
        cols = [one, dx.expand(t, s), dy.expand(t, s)]
        if self.use_temporal:
            cols.append(dt.view(t, 1).expand(t, s))
        return torch.stack(cols, dim=-1)

    def compose_inverse(self, params: torch.Tensor, dp: torch.Tensor) -> torch.Tensor:
        """Exact W(p) o W(dp)^-1 for the affine spatio-temporal warp.

        In local coordinates W_p(z, t) = (I + D) z + b + bt * dt; composing with the inverse of
        W_dp gives M = (I + D)(I + dD)^-1, b' = b - M db, bt' = bt - M dbt: still affine in
        space and linear in time, so the family is closed."""
        k = self.n_basis
        # (N, 2, k) views: row 0 the u coefficients (1, x, y[, t]), row 1 the v ones; D = the
        # x, y columns (the displacement gradient), the 1 and t columns (0::3) the offsets
        p3, dp3 = params.reshape(-1, 2, k), dp.reshape(-1, 2, k)
        eye = torch.eye(2, dtype=params.dtype, device=params.device)
        a = eye + dp3[:, :, 1:3]
        det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
        adj = torch.stack([a[:, 1, 1], -a[:, 0, 1], -a[:, 1, 0], a[:, 0, 0]], -1)
        m = (eye + p3[:, :, 1:3]) @ (adj.view(-1, 2, 2) / det.view(-1, 1, 1))
        out = torch.empty_like(p3)
        out[:, :, 1:3] = m - eye
        out[:, :, 0::3] = p3[:, :, 0::3] - m @ dp3[:, :, 0::3]  # b - M db (and bt - M dbt)
        return out.reshape(params.shape)


class QuadraticShape(ShapeFunction):
    """Second-order spatial + linear temporal shape function, 14 unknowns:
    u + ux dx + uy dy + uxx dx^2/2 + uxy dx dy + uyy dy^2/2 + ut dt (same for v).
    For strain gradients within a subset. m = 0: classical second order (12)."""

    basis_names = ("1", "x", "y", "xx", "xy", "yy", "t")

    def basis(self, dx, dy, dt):
        s, t = dx.shape[0], dt.shape[0]
        one = torch.ones(t, s, dtype=dx.dtype, device=dx.device)
        cols = [one, dx, dy, 0.5 * dx * dx, dx * dy, 0.5 * dy * dy]
        cols = [cols[0]] + [c.expand(t, s) for c in cols[1:]]
        if self.use_temporal:
            cols.append(dt.view(t, 1).expand(t, s))
        return torch.stack(cols, dim=-1)


_SHAPES = {"affine": AffineShape, "quadratic": QuadraticShape}


def make_shape(shape: str | ShapeFunction) -> ShapeFunction:
    """A shape-function module from a name ("affine", "quadratic") or pass-through."""
    if isinstance(shape, ShapeFunction):
        return shape
    try:
        return _SHAPES[str(shape).lower()]()
    except KeyError:
        raise ValueError(f"shape must be one of {sorted(_SHAPES)}, got {shape!r}") from None
