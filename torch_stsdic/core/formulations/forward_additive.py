"""Forward-additive Gauss-Newton formulations: the paper's averaged image, and the joint sum
for shape functions without an inverse composition.

Both sample the deformed frames *with gradients* at the warped subset every iteration and
build the Jacobian from them (the paper's Eq. 16), then solve ``H dp = F`` with the
Gauss-Newton Hessian ``H = J^T W J`` (Eq. 18) and ``p <- p + dp``.

* :class:`AverageFA`, the paper's own model (Eqs. 2, 3, 11, 14): the reference against the
  average ``G`` of the 2m+1 warped frames; ``J = mean_t grad g_t dU/dp``.
* :class:`JointFA`: the sum over frames of each frame's residual against the reference (the
  joint criterion of :mod:`.joint_ic`) solved forward-additively, for the quadratic shape.

With ZNSSD the criterion is written in its variable-projection form: the residual is
``f~ - a g~`` with f~, g~ zero-mean and ``a`` the least-squares scale, so the fixed point is
exactly the ZNCC maximum; the stationarity condition is ``F = J~^T W (f~ - a g~) / a``
(average) or ``sum_t a_t J~_t^T W (f~ - a_t g~_t)`` (joint).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.core.formulations.base import Formulation, Geometry, SubsetData, wsum
from torch_stsdic.core.interpolation import BSplineImage

__all__ = ["AverageFA", "JointFA"]


def _sample_warped(geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
                   work: int | None = None):
    """Values and gradients (each (N, T, S)) of the frames at the warped subsets, and the
    outside flag (N,)."""
    xs, ys = geo.shape.warp(p, data.px, data.py, geo.dx, geo.dy, geo.spatial, data.dt,
                            data.motion)
    outside = (
        (xs.amin(dim=(1, 2)) < 0) | (xs.amax(dim=(1, 2)) > frames.width - 1)
        | (ys.amin(dim=(1, 2)) < 0) | (ys.amax(dim=(1, 2)) > frames.height - 1)
    )
    out = frames.sample(xs, ys, frame=data.fidx.unsqueeze(-1), grad=True, work=work)
    return out, outside


def _mean_zncc(geo: Geometry, data: SubsetData, g: Tensor) -> Tensor:
    """(N,) ZNCC of every frame (N, T, S) against the reference, mean over the frames."""
    gc = geo.centred(g)
    gg = wsum(gc * gc, geo.w)
    fg = wsum(data.ft.unsqueeze(1) * gc, geo.w)
    return (fg / (data.fnorm.unsqueeze(1) * gg.clamp(min=1e-30).sqrt())).mean(1)


def _steepest_descent(geo: Geometry, gxs: Tensor, gxt: Tensor, gys: Tensor,
                      gyt: Tensor) -> Tensor:
    """(..., S, P) Jacobian [gx B, gx dt, gy B, gy dt] from the gradient factors of the
    spatial (gxs, gys) and temporal (gxt, gyt) columns, each (..., S)."""
    parts = []
    for gs, gt in ((gxs, gxt), (gys, gyt)):
        parts.append(gs.unsqueeze(-1) * geo.spatial)
        if geo.shape.has_time:
            parts.append(gt.unsqueeze(-1))
    return torch.cat(parts, -1)


def _criterion(geo: Geometry, ft: Tensor, g: Tensor, jac: Tensor):
    """(Jacobian, scale a, residual) of the criterion: ZNSSD in variable-projection form
    (centred g and J, least-squares scale a) or SSD (a = 1). g (..., S), jac (..., S, P)."""
    w = geo.w
    if not geo.znssd:
        return jac, torch.ones_like(g[..., 0]), ft - g
    gt = geo.centred(g)
    jac = jac - ((jac * w.view(-1, 1)).sum(-2) / w.sum()).unsqueeze(-2)
    a = wsum(ft * gt, w) / wsum(gt * gt, w).clamp(min=1e-30)
    return jac, a, ft - a.unsqueeze(-1) * gt


class _ForwardAdditive(Formulation):
    def system(self, geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
               work: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(F (N, P), H (N, P, P), mean ZNCC (N,), outside (N,)) at ``p``."""
        raise NotImplementedError

    def step(self, geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
             work: int, sel: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        rhs, hess, zn, outside = self.system(geo, frames, data, p, work)
        free = (torch.arange(p.shape[1], device=p.device) if self.free is None
                else torch.nonzero(self.free.to(p.device))[:, 0])
        hess = hess[:, free][:, :, free]
        chol, info = torch.linalg.cholesky_ex(hess.double())
        dp_free = torch.cholesky_solve(rhs[:, free].double().unsqueeze(-1), chol).squeeze(-1)
        dp_free = torch.where((info > 0).unsqueeze(-1), torch.full_like(dp_free, float("nan")),
                              dp_free)
        dp = torch.zeros_like(p)
        dp[:, free] = dp_free.to(p.dtype)
        return dp, zn, outside

    def stationarity(self, geo: Geometry, frames: BSplineImage, data: SubsetData,
                     p: Tensor) -> Tensor:
        return self.system(geo, frames, data, p)[0]


class AverageFA(_ForwardAdditive):
    """The paper's averaged-image model (Eqs. 2-3, 11, 14-18), forward additive."""

    name = "average"

    def system(self, geo, frames, data, p, work=None):
        (g, gx, gy), outside = _sample_warped(geo, frames, data, p, work)
        dt = data.dt.unsqueeze(-1)  # (N, T, 1)
        big_g = g.mean(1)  # (N, S): G of Eq. 3
        # Eq. 16: dG/dp = mean_t grad g_t * dU/dp
        jac = _steepest_descent(geo, gx.mean(1), (gx * dt).mean(1), gy.mean(1), (gy * dt).mean(1))
        jac, a, r = _criterion(geo, data.ft, big_g, jac)  # jac (N, S, P)
        wj = jac * geo.w.view(1, -1, 1)
        hess = wj.transpose(1, 2) @ jac  # Eq. 18
        rhs = (wj * r.unsqueeze(-1)).sum(1) / a.clamp(min=1e-12).unsqueeze(-1)  # Eq. 15
        return rhs, hess, _mean_zncc(geo, data, g), outside


class JointFA(_ForwardAdditive):
    """The joint criterion (sum over frames) solved forward additively, for shape functions
    without an inverse composition (quadratic)."""

    name = "joint_fa"

    def system(self, geo, frames, data, p, work=None):
        (g, gx, gy), outside = _sample_warped(geo, frames, data, p, work)
        dt = data.dt.unsqueeze(-1)
        jac = _steepest_descent(geo, gx, gx * dt, gy, gy * dt)  # (N, T, S, P)
        jac, a, r = _criterion(geo, data.ft.unsqueeze(1), g, jac)  # a (N, T)
        wj = jac * (geo.w.view(1, 1, -1, 1) * a.view(*a.shape, 1, 1))
        hess = torch.einsum("ntsp,ntsq->npq", wj * a.view(*a.shape, 1, 1), jac)
        rhs = torch.einsum("ntsp,nts->np", wj, r)
        return rhs, hess, _mean_zncc(geo, data, g), outside
