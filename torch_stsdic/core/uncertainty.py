"""Per-point uncertainty of a solution: the image noise from its residual, the predicted
standard deviation of every parameter, and the covariance between two solutions of the same
point (for the model check of :mod:`torch_stsdic.analysis.quality`).

Linear error propagation through the joint formulation (see :mod:`torch_stsdic.core.noise` for the
derivation and its Monte-Carlo checks): near the solution ``H dp = sum_t J_t^T W (n_f - n_t)``
with ``J_t = J_aug z_t`` (``J_aug`` the (S, P') augmented steepest-descent images
``[f_x B, f_x, f_y B, f_y]`` of the reference, ``z_t = (1 .. 1, dt_t)`` per component), so a
solution responds to the reference noise with ``C_ref = (sum_t z_t) o H^-1`` and to frame
``t``'s noise with ``C_t = -z_t o H^-1`` (rows in the augmented basis), and

    cov(p) = sigma_f^2 C_ref^T G2 C_ref + sigma_g^2 sum_t C_t^T G2 C_t
             + kappa sigma_f^2 sigma_g^2 sum_t C_t^T B2 C_t,

``G2 = sum_s w_s^2 (J_aug,s - mean) (J_aug,s - mean)^T`` (ZNSSD: centred), ``B2`` the same
moments of the bare basis (the second-order term of the noisy reference gradient), and ``H``
the Hessian built from the noisy reference minus its expected noise-gradient energy
``kappa sigma_f^2 sum_t w b_t b_t^T``. Two solutions of one point that share the reference or
a frame are correlated through those sources; :func:`cross_covariance` gives that.

The noise comes from the solution itself: the weighted residual variance of frame ``t``,
``r_t = sum_s w e_t,s^2 / sum_s w``, estimates ``(sigma_f^2 + c_t sigma_g^2) (1 - dof)``
(``c_t`` the variance factor of the B-spline-interpolated frame noise at the frame's sub-pixel
position, ``dof`` the fitted share of the pixels); the split between reference and frame noise
is the reference protocol's ``rho = sigma_f^2 / sigma_g^2`` (1 for one frame, 1/K for a mean
of K frames).

A reference that averages frames of the window (a template made from the series) shares their
noise: :func:`shared_frame_factors` gives the factors of the predicted variances then.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torch_stsdic.core.formulations import Geometry, SubsetData, centred_gram, gram
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.noise import gradient_noise_factor, interpolation_variance_factor
from torch_stsdic.kernels import dispatch, native
from torch_stsdic.kernels.linalg import spd_inverse

__all__ = ["NoiseModel", "Response", "frame_residuals", "residual_from_zncc", "noise_model",
           "response", "covariance", "cross_covariance", "solution_noise", "solution_response",
           "std_of", "predicted_std", "intercept_weights", "shared_frame_factors"]


def frame_residuals(geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor
                    ) -> Tensor:
    """(N, T) weighted residual variance of every frame of the joint criterion at ``p``:
    ``sum_s w e_t,s^2 / sum_s w`` with ``e_t = f~ - (|f~| / |g~_t|) g~_t`` (ZNSSD) or
    ``f - g_t`` (SSD), grey levels^2."""
    xs, ys = geo.shape.warp(p, data.px, data.py, geo.dx, geo.dy, geo.spatial, data.dt,
                            data.motion)
    g = frames.sample(xs, ys, frame=data.fidx.unsqueeze(-1))
    w = geo.w
    if geo.znssd:
        g = geo.centred(g)
        gg = (g * g) @ w
        g = g * (data.fnorm.unsqueeze(1) / gg.clamp(min=1e-30).sqrt()).unsqueeze(-1)
    e = data.ft.unsqueeze(1) - g
    return (e * e) @ w / w.sum()


@dataclass
class NoiseModel:
    """Noise variances per point (grey levels^2): ``ref`` of the reference, ``frame`` of one
    deformed frame, each (N,)."""

    ref: Tensor
    frame: Tensor

    @property
    def total(self) -> Tensor:
        """(N,) ``ref + frame``: the noise variance of one reference/frame pair."""
        return self.ref + self.frame


def residual_from_zncc(geo: Geometry, data: SubsetData, zncc: Tensor) -> Tensor:
    """(N, 1) the frame-mean weighted residual variance of the ZNSSD criterion from the
    window's mean ZNCC, without sampling the frames again:
    ``sum_s w e_t^2 = 2 |f~|^2 (1 - ZNCC_t)`` (``|f~|^2 = sum_s w f~^2``), grey levels^2."""
    f2 = data.fnorm.double() ** 2
    return (2.0 * f2 * (1.0 - zncc.double()).clamp(min=0.0) / geo.w_sum).unsqueeze(1)


def noise_model(geo: Geometry, residual: Tensor, p: Tensor, data: SubsetData, rho: float,
                order: int) -> NoiseModel:
    """Noise variances from a solution's weighted residual variance ``residual`` (N, T) per
    frame, or (N, 1) its mean over the frames, at parameters ``p`` (N, P) (see the module
    docstring); ``rho`` = sigma_f^2 / sigma_g^2. Means over the frames in use
    (:meth:`SubsetData.in_use`)."""
    s_eff = geo.w_effective
    use = data.in_use()
    t = data.dt.shape[1] if use is None else use.sum(1).to(residual.dtype)  # (N,) each row's
    dof = 1.0 - (2.0 + p.shape[1] / t) / s_eff  # mean, scale and a share of P per frame
    zero = torch.zeros(1, dtype=geo.dx.dtype, device=geo.dx.device)
    u, v = geo.shape.displacement(p, geo.shape.spatial_basis(zero, zero), data.dt)
    x = (data.px + u[..., 0]).double()  # the POI centre in every frame, px
    y = (data.py + v[..., 0]).double()
    if data.motion is not None:
        x, y = x + data.motion[..., 0].double(), y + data.motion[..., 1].double()
    c = interpolation_variance_factor(x, y, order).to(residual)
    sig_g = _frame_mean(residual, use) / dof / (rho + _frame_mean(c, use))
    return NoiseModel(ref=rho * sig_g, frame=sig_g)


def _frame_mean(x: Tensor, use: Tensor | None) -> Tensor:
    """(N,) the mean of ``x`` (N, T) over the frames in use ``use`` (N, T) bool (None: all;
    an (N, 1) ``x``: that column)."""
    if use is None or x.shape[1] == 1:
        return x.mean(1)
    return torch.where(use, x, 0.0).sum(1) / use.sum(1)


def _aug_columns(geo: Geometry) -> Tensor:
    """Positions of the P parameters among the P' = 2 (Ks + 1) augmented columns."""
    ks = geo.ks
    if geo.shape.has_time:
        return torch.arange(2 * (ks + 1), device=geo.spatial.device)
    i = torch.arange(2 * ks, device=geo.spatial.device)  # 0 .. ks-1, ks+1 .. 2 ks (made on
    return i + (i >= ks)  # the device: a tensor from a Python list is a copy to it)


def _z(geo: Geometry, dt: Tensor, use: Tensor | None = None) -> Tensor:
    """(N, T, P') column factors z_t = (1 .. 1, dt_t) per component (0 for the time columns
    of a shape without time; 0 at the frames not in ``use`` (N, T) bool, None: all)."""
    ks = geo.ks
    n, t = dt.shape
    z = torch.ones(n, t, 2 * (ks + 1), dtype=torch.float64, device=dt.device)
    d = dt.double() if geo.shape.has_time else torch.zeros_like(dt, dtype=torch.float64)
    z[..., ks] = d
    z[..., 2 * ks + 1] = d
    return z if use is None else z * use.unsqueeze(-1)


def _centred_gram(geo: Geometry, g: Tensor, m: Tensor, m1: Tensor, weights: Tensor) -> Tensor:
    """sum_s weights_s (J_s - Jbar)(J_s - Jbar)^T (N, P', P') of the augmented columns from
    their moments ``g, m`` = :func:`gram` with ``weights``, Jbar = ``m1`` / sum w the
    window-weighted (``geo.w``) mean for ZNSSD (no centring for SSD)."""
    if not geo.znssd:
        return g
    jbar = m1 / geo.w_sum
    return (g - m.unsqueeze(-1) * jbar.unsqueeze(-2) - jbar.unsqueeze(-1) * m.unsqueeze(-2)
            + weights.sum() * jbar.unsqueeze(-1) * jbar.unsqueeze(-2))  # (0-d: no read)


def _basis_moments(geo: Geometry, weights: Tensor) -> Tensor:
    """(P', P') sum_s weights_s b_s b_s^T of the augmented bare basis (B, 1) in both
    components (no gradient): the noise-gradient moments."""
    baug = torch.cat([geo.spatial, torch.ones_like(geo.spatial[:, :1])], 1).double()
    m = (baug * weights.double().unsqueeze(1)).T @ baug
    return torch.block_diag(m, m)


@dataclass
class Response:
    """Linear response of the solutions of N points to the images' noise.

    Attributes:
        coef: (N, P', P) H^-1 in the augmented basis (rows), per parameter (columns).
        z: (N, T, P') column factors of the frames.
        zz: (N, P', P') ``sum_t z_t z_t^T``.
        g2: (N, P', P') the centred w^2-moments of the reference's augmented columns.
        b2: (P', P') the w^2-moments of the bare basis.
        noise: the noise variances.
        kappa: gradient noise factor of the interpolation.
    """

    coef: Tensor
    z: Tensor
    zz: Tensor
    g2: Tensor
    b2: Tensor
    noise: NoiseModel
    kappa: float


def _moments(geo: Geometry, data: SubsetData
             ) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
    """(g1, g2, bw, b2): the centred gram (N, P', P') of the reference's augmented columns,
    their w^2-moments (None where the window is 0/1: then they are g1), and the bare basis's
    w- and w^2-moments (P', P')."""
    w = geo.w
    g1 = data.gram if data.gram is not None else centred_gram(geo, data.gx, data.gy)
    # the bare basis's moments: the geometry's alone, kept with it (a solver keeps its
    # geometries from solve to solve)
    held = geo.__dict__.get("_basis_moments")
    if held is None:
        bw = _basis_moments(geo, w)
        held = (bw, bw if geo.w_binary else _basis_moments(geo, w * w))
        geo.__dict__["_basis_moments"] = held
    bw, b2 = held
    if geo.w_binary:  # a 0/1 window: the w^2-moments are the w-moments
        return g1, None, bw, b2
    _, mw = gram(data.gx, data.gy, geo.spatial, w)
    gww, mww = gram(data.gx, data.gy, geo.spatial, w * w)
    return g1, _centred_gram(geo, gww, mww, mw, w * w), bw, b2


def response(geo: Geometry, data: SubsetData, noise: NoiseModel, order: int) -> Response:
    """The noise response of solutions with geometry ``geo`` at the points and frame times of
    ``data`` (reference gradients ``gx, gy`` (N, S) or their ``gram``, ``dt`` (N, T))."""
    kappa = gradient_noise_factor(order)
    z = _z(geo, data.dt, data.in_use())
    zz = z.transpose(1, 2) @ z
    g1, g2, bw, b2 = _moments(geo, data)
    g2 = g1 if g2 is None else g2
    h, bias = g1 * zz, kappa * noise.ref.double().view(-1, 1, 1) * bw * zz
    if geo.shape.has_time:
        coef = _corrected_inverse(h, bias)
    else:  # the time columns are not parameters: invert without them, put back as zeros
        cols = _aug_columns(geo)
        coef = h.new_zeros(h.shape[0], z.shape[-1], len(cols))
        coef[:, cols] = _corrected_inverse(h[:, cols][:, :, cols], bias[:, cols][:, :, cols])
    return Response(coef=coef, z=z, zz=zz, g2=g2, b2=b2, noise=noise, kappa=kappa)


def _corrected_inverse(h: Tensor, bias: Tensor) -> Tensor:
    """(N, P, P) inverse of the Hessian ``h`` minus its expected noise-gradient energy
    ``bias`` (both (N, P, P)), by Cholesky (:func:`~torch_stsdic.kernels.linalg.spd_inverse`). Where
    the corrected matrix is not positive definite (a noise estimate as large as the texture's
    signal, e.g. a subset that does not fit), the correction is not valid: ``h`` itself (the
    first-order Hessian the solver factored) is inverted instead; where that is singular too
    (no texture) the inverse is NaN."""
    inv, bad = spd_inverse(h - bias)
    # every row's plain inverse too (a batch of small ones), blended in: no host read of
    # whether any row needs it
    return torch.where(bad.view(-1, 1, 1), spd_inverse(h)[0], inv)


def _middle(r: Response) -> Tensor:
    """(N, P', P') the noise moments between ``coef^T`` and ``coef`` (module docstring)."""
    zs = r.z.sum(1)
    f2 = r.noise.ref.double().view(-1, 1, 1)
    g2n = r.noise.frame.double().view(-1, 1, 1)
    return (f2 * r.g2 * zs.unsqueeze(-1) * zs.unsqueeze(-2) + g2n * r.g2 * r.zz
            + r.kappa * f2 * g2n * r.b2 * r.zz)


def covariance(r: Response) -> Tensor:
    """(N, P, P) predicted covariance of the parameters (module docstring)."""
    return r.coef.transpose(1, 2) @ _middle(r) @ r.coef


def cross_covariance(a: Response, b: Response, shared: Tensor) -> Tensor:
    """(N, Pa, Pb) covariance between two solutions of the same points against the same
    reference: through the reference noise, and through the frames they share: ``shared``
    (N, Ta, Tb) bool, True where frame ``i`` of ``a`` is frame ``j`` of ``b``."""
    za, zb = a.z.sum(1), b.z.sum(1)
    f2 = a.noise.ref.double().view(-1, 1, 1)
    g2n = a.noise.frame.double().view(-1, 1, 1)
    zab = torch.einsum("nip,nij,njq->npq", a.z, shared.double(), b.z)
    mid = f2 * a.g2 * za.unsqueeze(-1) * zb.unsqueeze(-2) + g2n * a.g2 * zab
    return a.coef.transpose(1, 2) @ mid @ b.coef


def solution_noise(geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
                   rho: float, order: int, zncc: Tensor | None = None
                   ) -> tuple[NoiseModel, Tensor]:
    """The noise of the solutions ``p`` (N, P) of the points in ``data``, estimated from their
    own residuals, and those residuals ((N, T) per frame, or (N, 1) from the window's mean
    ``zncc`` (N,) when given, for ZNSSD: no new sampling)."""
    if zncc is not None and geo.znssd:
        res = residual_from_zncc(geo, data, zncc)
    else:
        res = frame_residuals(geo, frames, data, p)
    return noise_model(geo, res, p, data, rho, order), res


def solution_response(geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
                      rho: float, order: int, zncc: Tensor | None = None
                      ) -> tuple[Response, Tensor]:
    """The noise response of the solutions ``p`` (N, P) of the points in ``data``, with the
    noise estimated from their own residuals (:func:`solution_noise`), and those residuals."""
    noise, res = solution_noise(geo, frames, data, p, rho, order, zncc)
    return response(geo, data, noise, order), res


def std_of(r: Response) -> Tensor:
    """(N, P) predicted standard deviation of every parameter (the diagonal of
    :func:`covariance` alone)."""
    var = ((_middle(r) @ r.coef) * r.coef).sum(1)
    return var.clamp(min=0).sqrt()


def predicted_std(geo: Geometry, data: SubsetData, noise: NoiseModel, order: int) -> Tensor:
    """(N, P) :func:`std_of` of :func:`response`: row by row in the native kernel where it
    can run (CPU, no autograd graph; no (N, P', P') temporaries: 38,809 classical rows in
    ~3 instead of ~30 ms), else through the response."""
    cols = _aug_columns(geo)
    grads = [t for t in (data.gram, data.gx, data.gy) if t is not None]
    if dispatch.param_std(cols.numel(), *grads, data.dt, noise.ref, noise.frame) == "native":
        g1, g2, bw, b2 = _moments(geo, data)
        return native.param_std(cols, data.dt, geo.shape.has_time, geo.ks, g1, g2, bw, b2,
                                noise.ref.double(), noise.frame.double(),
                                gradient_noise_factor(order), count=data.count)
    return std_of(response(geo, data, noise, order))


def intercept_weights(dt: Tensor) -> Tensor:
    """(N, T) the weights ``c_t`` of the least-squares line through a window's frames at
    times ``dt`` (N, T) evaluated at ``dt = 0`` (``sum_t c_t = 1``; ``1 / T`` where the frames
    do not fix a slope, e.g. one frame): ``c_t = [Z^-1 z_t]_0``, ``z_t = (1, dt_t)``,
    ``Z = sum_t z_t z_t^T``."""
    d = dt.double()
    t = float(d.shape[1])
    s1, s2 = d.sum(1, keepdim=True), (d * d).sum(1, keepdim=True)
    det = t * s2 - s1 * s1
    flat = det <= 1e-12 * t * s2.clamp(min=1e-300)
    c = (s2 - s1 * d) / torch.where(flat, 1.0, det)
    return torch.where(flat, 1.0 / t, c)


def shared_frame_factors(dt: Tensor, share: Tensor, share_sq: Tensor, rho: float | Tensor,
                         reference: Tensor | None = None, registration: Tensor | None = None
                         ) -> Tensor:
    """(N, 2) the factors of the predicted variances of the displacement (u, v) and of the
    velocity (ut, vt) of windows at frame times ``dt`` (N, T) measured against a template
    that averages frames of the series: ``share`` (N, T) the weight of each window frame in
    the template (0: not in it), ``share_sq`` (N,) the sum of all its frames' squared
    weights, ``rho`` the template's noise variance over a frame's as the solver was told it
    (the prediction's ``sigma_f^2 / sigma_g^2``); ``reference`` (N, T) bool where a window
    frame is the frame the template was registered to and ``registration`` (N,) ``phi``,
    the variance factor of the local fits that registered the frames (None: no
    registration noise).

    Derivation (per component; ``nu_k`` the noise of frame k as a classical displacement
    sees it, variance ``s^2`` each, independent): the window's displacement is its frames'
    least-squares line at ``dt = 0`` (:func:`intercept_weights` ``c_t``), its noise
    ``sum_k (a_k - c_k) nu_k`` (``a_k`` the template's weights, ``c_k`` = 0 off the window)
    where :func:`covariance` takes ``rho nu_R - sum_t c_t nu_t`` with ``nu_R`` independent of
    the frames: ``s^2 (rho + sum c^2)``. The template's registration adds the local fits of
    the frames' classical warps against the reference frame 0, ``phi``-smoothed
    ``sum_k (delta_k0 - a_k) nu_k``, correlated with the former at the point by ``phi``. So
    the displacement's variance is

        s^2 [sum a^2 + sum c^2 - 2 sum a c + phi (1 - 2 c_0 - sum a^2 + 2 sum a c)]

    (``phi = 1``: ``sum_k (delta_k0 - c_k)^2``, the line's error against frame 0, as
    classical DIC against it). Neither enters the velocity (common to every frame). Both
    predictions rest on ``s^2`` estimated from the residuals ``n_R - n_t``, whose mean
    variance is ``s^2 (rho + 1 - 2 mean_t a_t)``, not ``s^2 (rho + 1)`` (interpolation
    factors taken as 1): low by that ratio. So

        var(u) *= [...] / (rho + sum c^2) * (rho + 1) / (rho + 1 - 2 mean a),
        var(ut) *= (rho + 1) / (rho + 1 - 2 mean a).

    A template of the K frames of a window of K frames centred on its target (``a = c =
    1/K``) leaves only the registration's noise in the displacement."""
    a = share.double()
    c = intercept_weights(dt)
    # a number as it is (a tensor made of it would be a copy to the device, which waits)
    r = float(rho) if isinstance(rho, (int, float)) else rho.to(device=a.device,
                                                                 dtype=torch.float64)
    csq, ac, asq = (c * c).sum(1), (c * a).sum(1), share_sq.double()
    noise = (r + 1.0) / (r + 1.0 - 2.0 * a.mean(1)).clamp(min=1e-3 * (r + 1.0))
    var = asq + csq - 2.0 * ac
    if registration is not None and reference is not None:
        c0 = (c * reference.double()).sum(1)
        var = var + registration.double() * (1.0 - 2.0 * c0 - asq + 2.0 * ac)
    disp = var.clamp(min=0.0) / (r + csq)
    return torch.stack([disp * noise, noise], 1)
