"""Joint inverse-compositional formulation (the default): sum over frames of each frame's
residual against the reference.

Criterion: ``C(p) = sum_t sum_s w_s e_t,s(p)^2`` with, for ZNSSD, ``e_t = f~ - (|f~| / |g~_t|)
g~_t`` (f~, g~_t the zero-mean reference subset and frame ``t`` sampled at the warped subset
``W(x; p, t)``, Pan's normalisation) or ``e_t = f - g_t`` for SSD. Inverse compositional
Gauss-Newton (IC-GN): the Jacobian of frame ``t`` is the *reference* gradient times the shape
basis, ``J_t = [f_x b_t, f_y b_t]`` with ``b_t = (spatial basis, dt_t)`` (the paper's Eq. 16
evaluated on the reference), so the Hessian ``H = sum_t J_t^T W J_t`` (Eq. 18) is formed and
Cholesky-factored once per point, and every iteration only samples the frames' values:

    H dp = -F(p),   F(p) = sum_t J_t^T W e_t(p),   p <- p o dp^-1.

``F = 0`` is the stationarity condition (:meth:`JointIC.stationarity`); for a shape family
closed under composition (the affine spatio-temporal warp) the update is exact.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic import kernels
from torch_stsdic.core.formulations.base import Formulation, Geometry, SubsetData
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.kernels import dispatch, native
from torch_stsdic.kernels.compile import maybe_compiled
from torch_stsdic.kernels.ic_step import ic_rhs_compiled, ic_rhs_kernel
from torch_stsdic.kernels.linalg import spd_inverse

__all__ = ["JointIC", "ic_rhs_kernel", "gram", "centred_gram", "ic_hessian", "ic_jacobian"]


def gram(gx: Tensor, gy: Tensor, spatial: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted moments of the augmented steepest-descent images J_s = [gx B, gx, gy B, gy]
    (B the spatial basis (S, Ks), P' = 2 (Ks + 1) columns): G = sum_s w J_s J_s^T
    (N, P', P') and m = sum_s w J_s (N, P'), float64."""
    if dispatch.gram(gx, spatial) == "native":
        return native.gram(gx, gy, spatial, w)
    baug = torch.cat([spatial, torch.ones_like(spatial[:, :1])], 1)  # (S, Ks + 1)
    j = torch.cat([gx.unsqueeze(-1) * baug, gy.unsqueeze(-1) * baug], -1)
    wj = j * w.view(1, -1, 1)
    return (wj.transpose(1, 2) @ j).double(), wj.sum(1).double()


def ic_jacobian(geo: Geometry, gx: Tensor, gy: Tensor, dt: Tensor) -> Tensor:
    """J_t (N, T, S, P) of every frame: the reference gradient (gx, gy (N, S)) times the shape
    basis at frame times ``dt`` (N, T) (Eq. 16 on the reference); subset-mean removed for
    ZNSSD. The definition :func:`ic_hessian` computes ``sum_t J_t^T W J_t`` from, faster."""
    n, t = dt.shape
    ks, k = geo.ks, geo.k
    jac = gx.new_zeros(n, t, gx.shape[1], 2 * k)
    for comp, g in ((0, gx), (1, gy)):
        jac[..., comp * k : comp * k + ks] = (g.unsqueeze(-1) * geo.spatial).unsqueeze(1)
        if geo.shape.has_time:
            jac[..., comp * k + k - 1] = g.unsqueeze(1) * dt.unsqueeze(-1)
    if geo.znssd:
        jac = jac - (jac * geo.w.view(1, 1, -1, 1)).sum(2, keepdim=True) / geo.w.sum()
    return jac


def centred_gram(geo: Geometry, gx: Tensor, gy: Tensor) -> Tensor:
    """(N, P', P') float64 ``sum_s w (J_s - Jbar)(J_s - Jbar)^T`` of the augmented columns
    (:func:`gram`), Jbar their window mean for ZNSSD (``G - m m^T / sum w``; SSD: G)."""
    return gram_and_texture(geo, gx, gy)[0]


def gram_and_texture(geo: Geometry, gx: Tensor, gy: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`centred_gram` and the texture (N,) of each subset: the window-weighted mean of
    ``gx^2 + gy^2`` (the texture test), read off the gram before centring (the diagonal
    entries of the augmented constant columns are ``sum_s w gx^2`` and ``sum_s w gy^2``)."""
    g, m = gram(gx, gy, geo.spatial, geo.w)
    ks, wsum = geo.ks, geo.w_sum  # (a host number: no read of the device)
    texture = ((g[:, ks, ks] + g[:, 2 * ks + 1, 2 * ks + 1]) / wsum).to(gx.dtype)
    if geo.znssd:
        g = g - m.unsqueeze(-1) * m.unsqueeze(-2) / wsum
    return g, texture


def ic_hessian(geo: Geometry, gx: Tensor, gy: Tensor, dt: Tensor,
               g: Tensor | None = None, use: Tensor | None = None) -> Tensor:
    """Gauss-Newton Hessian ``sum_t J_t^T W J_t`` of the joint IC problem, (N, P, P) float64.

    With the moments of :func:`gram` this is H = (G - m m^T / sum w) o sum_t z_t z_t^T,
    z_t = (1 .. 1, dt_t) per component (o: element-wise product), so no (N, T, S, P) Jacobian
    is formed (equal to the brute-force sum over :func:`ic_jacobian`; tested). ``g``: the
    :func:`centred_gram` when already computed; ``use`` (N, T) bool the frames in use
    (:meth:`SubsetData.in_use`; None: all)."""
    if g is None:
        g = centred_gram(geo, gx, gy)
    n, t = dt.shape
    ks = geo.ks
    if not geo.shape.has_time:  # drop the augmented constant columns; sum over T frames
        keep = [*range(ks), *range(ks + 1, 2 * ks + 1)]
        frames = t if use is None else use.sum(1).to(g.dtype).view(-1, 1, 1)
        return g[:, keep][:, :, keep] * frames
    z = torch.ones(n, t, 2 * (ks + 1), dtype=torch.float64, device=g.device)
    dtd = dt.double()
    z[..., ks] = dtd
    z[..., 2 * ks + 1] = dtd
    if use is not None:
        z = z * use.unsqueeze(-1)
    return g * torch.einsum("ntp,ntq->npq", z, z)


class JointIC(Formulation):
    """Joint inverse-compositional Gauss-Newton (see the module docstring). Needs a shape
    function closed under composition (``shape.inverse_compositional``)."""

    name = "joint_ic"
    inverse_compositional = True

    def prepare(self, geo: Geometry, data: SubsetData) -> Tensor:
        d = data if data.gram is not None else data.direct()
        # the inverse once per point: a batched product per step is ~7x cheaper than a
        # batched Cholesky solve of (N, 8, 8) systems (singular points are dropped)
        data.hinv, singular = spd_inverse(ic_hessian(geo, d.gx, d.gy, d.dt, g=d.gram,
                                                     use=d.in_use()))
        return singular

    def uses_fused_kernel(self, frames: BSplineImage, data: SubsetData, p: Tensor) -> bool:
        return self._backend(frames, data, p) != "torch"

    @staticmethod
    def _backend(frames: BSplineImage, data: SubsetData, p: Tensor) -> str:
        """Which kernel runs this call's step (:func:`torch_stsdic.kernels.dispatch.ic_step`:
        C++ on the CPU, Triton on CUDA, else torch)."""
        return dispatch.ic_step(frames.kernel_args(), frames.order, p, data.ft, data.gx,
                                data.gy)

    def _args(self, geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor) -> tuple:
        flat, wp, x_lo, x_hi, y_lo, y_hi, shift, plane = frames.kernel_args()
        return (flat, p, data.px, data.py, geo.dx, geo.dy, geo.spatial.T.contiguous(), data.dt,
                data.fidx * plane, data.ft, data.fnorm, data.gx, data.gy, geo.w, wp, x_lo,
                x_hi, y_lo, y_hi, shift, frames.width, frames.height, geo.ks, geo.k,
                geo.shape.has_time, geo.znssd, frames.order, data.motion, data.count)

    def gives_frame_rhs(self, frames: BSplineImage, data: SubsetData, p: Tensor) -> bool:
        # the native and Triton steps do; the torch step does not
        return self._backend(frames, data, p) != "torch"

    def step(self, geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
             work: int, sel: Tensor | None = None, frame_rhs: Tensor | None = None
             ) -> tuple[Tensor, Tensor, Tensor]:
        if sel is not None:
            ka = frames.kernel_args()
            extra = {}
            if self._backend(frames, data, p) == "native":
                fused, extra = native.ic_rhs, {"motion": data.motion, "ref_rows": data.ref_rows,
                                               "frame_rhs": frame_rhs, "count": data.count}
            else:  # Triton: reference subsets row by row (no ref_rows), the motion by data row
                fused, data = kernels.ic_rhs, data.direct()
                extra = {"motion": data.motion, "count": data.count}
                if frame_rhs is not None:
                    extra["frame_rhs"] = frame_rhs
            b, zn, outside = fused(
                ka, frames.order, p, data.px, data.py, geo.dx, geo.dy, geo.spatial, data.dt,
                data.fidx * ka[-1], data.ft, data.fnorm, data.gx, data.gy, geo.w, frames.width,
                frames.height, geo.k, geo.shape.has_time, geo.znssd, rows=sel, **extra,
            )
            dp = -(data.hinv[sel] @ b.unsqueeze(-1)).squeeze(-1)
            return dp.to(p.dtype), zn, outside
        fn = maybe_compiled(ic_rhs_compiled, ("ic_rhs",), work, device=p.device)
        b, zn, outside = fn(*self._args(geo, frames, data.direct(), p))
        dp = -(data.hinv @ b.double().unsqueeze(-1)).squeeze(-1)
        return dp.to(p.dtype), zn, outside

    def update(self, geo: Geometry, p: Tensor, dp: Tensor) -> Tensor:
        return geo.shape.compose_inverse(p, dp)

    def stationarity(self, geo: Geometry, frames: BSplineImage, data: SubsetData,
                     p: Tensor) -> Tensor:
        return ic_rhs_kernel(*self._args(geo, frames, data.direct(), p))[0]
