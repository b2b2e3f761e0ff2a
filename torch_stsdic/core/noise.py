"""Noise floor of subset / STS-DIC: the predicted random error, and image-noise estimates.

Prediction (first-order error propagation through the Gauss-Newton solution)
-------------------------------------------------------------------------------

Near the solution every Gauss-Newton formulation of :mod:`torch_stsdic.core.solver` solves the
linear least-squares problem ``H dp = sum_t J_t^T W (n_f - n_t)`` where

* ``J_t`` (S, P) is the Jacobian of frame ``t``: the reference gradient times the shape
  basis, ``[f_x b_t, f_y b_t]`` with ``b_t = (spatial basis, dt_t)``; with the ZNSSD
  criterion its subset mean is removed (centred ``J``, which also makes the prediction
  insensitive to the noise's subset mean);
* ``H = sum_t J_t^T W J_t`` the Gauss-Newton Hessian (``W`` the window weights);
* ``n_f`` the reference noise at the subset pixels (shared by every frame of the window) and
  ``n_t`` the noise of frame ``t`` *interpolated* at the warped pixel positions.

So ``cov(p) = H^-1 cov(b) H^-1`` with

    cov(b) = sigma_ref^2 (sum_t J_t)^T W C_ref W (sum_t J_t)
           + sigma_def^2 sum_t J_t^T W C_t W J_t.

``C_t`` is the (S, S) correlation of B-spline-interpolated white noise at the sub-pixel
position of frame ``t`` (``C = I`` at integer positions). For a symmetric window
(``sum dt = 0``) and the affine shape this reduces to the textbook formula

    var(u) = (sigma_ref^2 + c_interp sigma_def^2 / (2m+1)) [H_s^-1]_uu,
    var(ut) = c_interp sigma_def^2 / sum(dt^2) [H_0^-1]_uu,

with ``H_s = J_s^T W J_s`` the classical (spatial) Hessian and ``H_0`` its translation block
(``c_interp`` is 1 at integer positions and, in effect, also at sub-pixel ones: see below).
The reference noise is never averaged away by the window (and does not enter the velocity of
a symmetric window); only the deformed frames' noise is divided by the number of frames.
A reference that is the mean of K still frames has ``sigma_ref = sigma / sqrt(K)``.

``interp`` selects ``C_t``:

* ``"exact"`` (default): the full correlation of the interpolated noise for the sub-pixel
  shift of each frame (``C = R_y (x) R_x``, the 1-D autocorrelations of the cardinal
  B-spline interpolation kernel at that shift). Needs the displacement (``displacement``);
  without it the frames are taken at integer positions, i.e. ``C = I``.
* ``"white"``: ``C = c_interp I`` with ``c_interp = r_x(0) r_y(0)`` the variance of the
  interpolated noise (ignores its spatial correlation). At a half-pixel shift in x the cubic
  B-spline gives ``c_interp`` ≈ 0.76 (quintic ≈ 0.84); at integer shifts 1.
* a number: ``C = interp * I`` (1.0: no interpolation effect).

The interpolation low-passes the frames' noise (its variance drops to 0.76 at a half-pixel
shift), but it passes the low spatial frequencies where a speckle's gradients, i.e. ``J``,
live almost unchanged: ``J^T C J`` stays within ~1 % of ``J^T J``. So ``"exact"`` gives
practically the same floor as ``interp=1.0`` on speckle images, and a Monte-Carlo test
(clean reference, sigma = 5 on the frame, 21 px subsets) measured the same error at shifts
0, 0.25 and 0.5 px (measured/predicted 1.02, 1.01, 1.02 with "exact"), whereas ``"white"``
under-predicts by 8 % at 0.25 px and 16 % at 0.5 px. Use ``"white"`` only as a bound.

Second order: the Jacobian is built from the *noisy* reference gradient. The product of
that gradient noise (variance ``kappa sigma_ref^2``, ``kappa`` = 1.39 for cubic splines) and
the frames' noise adds ``kappa sigma_ref^2 sigma_def^2 sum_t sum_s w^2 b_t b_t^T`` to
``cov(b)`` (the reference noise's product with its own derivative cancels); with
``sigma_ref = sigma_def = 5`` this is +3..4 % on the classical std of the paper's case and
brings the prediction to within 1 % of the Monte-Carlo value (``second_order=True``).

Caveats: random error only (no interpolation bias, no bias of the forward-additive
"average" formulation, no model error of the linear-in-time assumption). ``H`` must be
built from a clean reference: a noisy ``ref`` adds about ``kappa sigma^2`` per pixel to the
gradient energy and makes the prediction low (-13 % at sigma = 5 on the paper's case); when
only a noisy reference is available, pass its noise level as ``ref_noise`` to subtract the
expected gradient-noise energy (then within ~1 %). Only the displacement's translation terms
enter the sub-pixel shift (strain changes it across the subset by ``ux * 10 px``).

Noise estimates
---------------

:func:`estimate_noise_sigma` estimates the image noise ``sigma``: from two (or more) still
frames of the same scene (the frame differences, the best estimate), or from a single
image by Immerkaer's Laplacian method (robust variant restricted to the flattest pixels,
because speckle texture inflates the Laplacian). :func:`residual_noise_sigma` estimates the
noise that matters for the error, ``sigma_ref^2 + sigma_def^2``, from the converged DIC
residual of a reference/frame pair (not inflated by texture; on the DIC Challenge sample 5 it
predicts the measured std of u within a few per cent, where Immerkaer's single-image
estimate is texture-dominated and over-predicts it three times).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.formulations import Geometry, ic_hessian, ic_jacobian
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.shape import make_shape
from torch_stsdic.core.signatures import signature_like
from torch_stsdic.core.window import effective_pixels, make_window
from torch_stsdic.kernels import dispatch
from torch_stsdic.kernels import native as native_ops

__all__ = [
    "predicted_std",
    "predicted_covariance",
    "interpolated_noise_autocorrelation",
    "interpolation_variance_factor",
    "gradient_noise_factor",
    "estimate_noise_sigma",
    "residual_noise_sigma",
]

_L = 48  # half-size of the delta image used to tabulate the cardinal kernel
_D = 14  # autocorrelation lags kept (|lag| <= _D); beyond ~1e-8 for cubic and quintic


@lru_cache(maxsize=4)
def _delta_spline(order: int) -> BSplineImage:
    n = 2 * _L + 1
    img = torch.zeros(n, n, dtype=torch.float64)
    img[_L, _L] = 1.0
    return BSplineImage(img, order=order)


def _cardinal(y: torch.Tensor, order: int) -> torch.Tensor:
    """Cardinal B-spline interpolation kernel eta(y): the weight of a pixel at distance y."""
    spl = _delta_spline(order)
    yy = y.to(torch.float64)
    return spl.sample(_L + yy, torch.full_like(yy, float(_L)))


def interpolated_noise_autocorrelation(
    delta: Any, order: int = 3, max_lag: int = _D
) -> torch.Tensor:
    """Autocorrelation ``r_delta(d)``, ``d = -max_lag..max_lag``, of unit white noise
    interpolated by a B-spline at fractional shift ``delta`` (1-D; the 2-D correlation is the
    product of the x and y ones). ``delta`` any shape; returns ``delta.shape + (2 max_lag + 1,)``.
    ``r_delta(0)`` is the variance factor; ``r_0 = [.., 0, 1, 0, ..]``."""
    dl = torch.as_tensor(delta, dtype=torch.float64)
    k = torch.arange(-(max_lag + 16), max_lag + 17, dtype=torch.float64)
    eta = _cardinal((dl.unsqueeze(-1) + k).reshape(-1), order).reshape(*dl.shape, -1)
    lags = torch.arange(-max_lag, max_lag + 1)
    nk = k.numel()
    out = []
    for d in lags.tolist():
        # r(d) = sum_k eta(d + delta + k) eta(delta + k)
        if d >= 0:
            out.append((eta[..., d:] * eta[..., : nk - d]).sum(-1))
        else:
            out.append((eta[..., : nk + d] * eta[..., -d:]).sum(-1))
    return torch.stack(out, -1)


_TABLE = 128  # nodes per unit shift of the variance-factor table


@lru_cache(maxsize=4)
def _variance_table(order: int) -> torch.Tensor:
    """``r_delta(0)`` at delta = 0, 1/_TABLE, .., 1 (float64), for linear interpolation
    (relative error < 1e-6: the factor is smooth and 1-periodic)."""
    d = torch.linspace(0.0, 1.0, _TABLE + 1, dtype=torch.float64)
    return interpolated_noise_autocorrelation(d, order, 0)[..., 0]


def _variance_1d(f: torch.Tensor, order: int) -> torch.Tensor:
    tab = _variance_table(order).to(f.device)
    pos = (f - torch.floor(f)) * _TABLE
    i = pos.floor().long().clamp(0, _TABLE - 1)
    a = pos - i
    return tab[i] * (1 - a) + tab[i + 1] * a


def interpolation_variance_factor(dx: Any, dy: Any = 0.0, order: int = 3) -> torch.Tensor:
    """Variance of unit white noise after B-spline interpolation at the fractional shift
    (dx, dy): ``r_dx(0) r_dy(0)`` (1 at integer shifts; cubic at (0.5, 0): about 0.76), from a
    table of :func:`interpolated_noise_autocorrelation`."""
    fx = torch.as_tensor(dx, dtype=torch.float64)
    fy = torch.as_tensor(dy, dtype=torch.float64, device=fx.device)
    # both axes in one pass of the table (half the operations: launches on a GPU)
    r = _variance_1d(torch.stack(torch.broadcast_tensors(fx, fy)), order)
    return r[0] * r[1]


@lru_cache(maxsize=4)
def gradient_noise_factor(order: int = 3) -> float:
    """kappa: variance of the x-derivative of the B-spline interpolant of unit white noise at
    the pixels, ``sum_l eta'(l)^2`` (cubic 1.39, quintic 1.89)."""
    spl = _delta_spline(order)
    lags = torch.arange(-_L + 8, _L - 7, dtype=torch.float64)
    _, gx, _ = spl.sample(_L + lags, torch.full_like(lags, float(_L)), grad=True)
    return float((gx * gx).sum())


def _toeplitz(r: torch.Tensor, n: int) -> torch.Tensor:
    """(..., n, n) matrices R[i, j] = r(i - j) from lags r (..., 2D+1) centred at D."""
    d = (r.shape[-1] - 1) // 2
    i = torch.arange(n)
    lag = (i.view(-1, 1) - i.view(1, -1)).clamp(-d, d) + d
    mat = r[..., lag]
    far = (i.view(-1, 1) - i.view(1, -1)).abs() > d
    return mat.masked_fill(far, 0.0)


def _as_displacement(disp: Any, n: int, t_count: int, dt: torch.Tensor) -> torch.Tensor | None:
    """(T, N, 2) displacement of every POI in every frame, or None."""
    if disp is None:
        return None
    d = torch.as_tensor(np.asarray(disp, dtype=np.float64) if not isinstance(disp, torch.Tensor)
                        else disp, dtype=torch.float64)
    if d.dim() == 0:
        d = d.expand(n, 2) * torch.tensor([1.0, 0.0], dtype=torch.float64)
    if d.dim() == 1 and d.shape[0] in (2, 4):
        d = d.unsqueeze(0).expand(n, -1)
    if d.dim() == 2 and d.shape == (n, 2):
        return d.unsqueeze(0).expand(t_count, n, 2)
    if d.dim() == 2 and d.shape == (n, 4):
        u = d[:, 0].unsqueeze(0) + d[:, 2].unsqueeze(0) * dt.view(-1, 1)
        v = d[:, 1].unsqueeze(0) + d[:, 3].unsqueeze(0) * dt.view(-1, 1)
        return torch.stack([u, v], -1)
    if d.dim() == 3 and d.shape == (t_count, n, 2):
        return d
    raise ValueError(
        f"displacement: expected a scalar, (2,), (4,), (N, 2) (u, v), (N, 4) (u, v, ut, vt) "
        f"or (T, N, 2), got {tuple(d.shape)} for N = {n}, T = {t_count}"
    )


def _corr_form(jw: torch.Tensor, frac: torch.Tensor, sq_index: torch.Tensor, size: int,
               order: int, mode: Any) -> torch.Tensor:
    """J^T W C W J for every POI: jw (N, S, P) is W J; frac (N, 2) sub-pixel shifts."""
    n, s, p = jw.shape
    if not isinstance(mode, str):
        return float(mode) * torch.einsum("nsp,nsq->npq", jw, jw)
    if mode not in ("exact", "white"):
        raise ValueError(f"interp: must be 'exact', 'white' or a number, got {mode!r}")
    if mode == "white":
        c = interpolation_variance_factor(frac[:, 0], frac[:, 1], order)
        return c.view(n, 1, 1) * torch.einsum("nsp,nsq->npq", jw, jw)
    rx = interpolated_noise_autocorrelation(frac[:, 0], order)
    ry = interpolated_noise_autocorrelation(frac[:, 1], order)
    mx, my = _toeplitz(rx, size), _toeplitz(ry, size)  # (N, n, n)
    grid = torch.zeros(n, size * size, p, dtype=jw.dtype)
    grid[:, sq_index] = jw
    grid = grid.view(n, size, size, p)  # (N, row=y, col=x, P)
    cg = torch.einsum("nab,nbcp->nacp", my, grid)
    cg = torch.einsum("ncd,nadp->nacp", mx, cg)
    return torch.einsum("nap,naq->npq", grid.reshape(n, -1, p), cg.reshape(n, -1, p))


def predicted_covariance(
    ref: Any,
    points: Any,
    config: DICConfig | None = None,
    sigma_ref: float = 1.0,
    sigma_def: float | None = None,
    n_frames: int | None = None,
    dt: Any = None,
    *,
    displacement: Any = None,
    interp: str | float = "exact",
    second_order: bool = True,
    ref_noise: float = 0.0,
) -> tuple[torch.Tensor, tuple[str, ...]]:
    """Predicted covariance (N, P, P) of the shape-function parameters and their names.

    See :func:`predicted_std` for the arguments."""
    cfg = config if config is not None else DICConfig()
    img = torch.as_tensor(np.asarray(ref, dtype=np.float64) if not isinstance(ref, torch.Tensor)
                          else ref, dtype=torch.float64)
    if img.dim() != 2:
        raise ValueError(f"ref: expected an (H, W) image, got {tuple(img.shape)}")
    pts = torch.as_tensor(np.asarray(points, dtype=np.float64) if not isinstance(
        points, torch.Tensor) else points, dtype=torch.float64).reshape(-1, 2)
    sd = float(sigma_ref if sigma_def is None else sigma_def)
    t_count = int(n_frames) if n_frames is not None else cfg.n_frames
    if dt is None:
        dtt = torch.arange(t_count, dtype=torch.float64) - (t_count - 1) / 2.0
    else:
        dtt = torch.as_tensor(np.asarray(dt, dtype=np.float64), dtype=torch.float64).reshape(-1)
        t_count = dtt.numel()
    if t_count < 1:
        raise ValueError("n_frames: must be >= 1")
    shape = make_shape(cfg.shape)
    use_t = t_count > 1 and float(dtt.abs().max()) > 0
    if not use_t:
        shape = shape.spatial()
    window = make_window(cfg.window, cfg.subset_size)
    geo = Geometry.make(shape, window, cfg.criterion, torch.float64, None)
    off, w = torch.stack([geo.dx, geo.dy], 1), geo.w
    half = window.half
    size = 2 * half + 1
    sq_index = ((off[:, 1] + half) * size + (off[:, 0] + half)).long()
    spline = BSplineImage(img, order=cfg.interpolation_order)
    _, gx, gy = spline.sample(pts[:, :1] + geo.dx, pts[:, 1:] + geo.dy, grad=True)  # (N, S)
    bs = geo.spatial  # (S, Ks)
    n = pts.shape[0]
    ks = bs.shape[1]
    k = shape.n_basis
    p_count = 2 * k
    # the joint formulation's Jacobian of every frame, (T, N, S, P), and its Hessian
    jac = ic_jacobian(geo, gx, gy, dtt.expand(n, t_count)).transpose(0, 1)
    wj = jac * w.view(1, 1, -1, 1)
    hess = ic_hessian(geo, gx, gy, dtt.expand(n, t_count))
    order = cfg.interpolation_order
    kap = gradient_noise_factor(order)
    bt = torch.zeros(t_count, bs.shape[0], k, dtype=torch.float64)
    bt[:, :, :ks] = bs
    if use_t:
        bt[:, :, k - 1] = dtt.view(-1, 1)

    def block(weights: torch.Tensor, summed: bool = False) -> torch.Tensor:
        """sum_t b_t^T diag(weights) b_t (or with sum_t b_t) in both u and v blocks.
        (The ZNSSD centring of the noise-gradient Jacobian is neglected: O(1/S).)"""
        btc = bt
        if summed:
            btc = btc.sum(0, keepdim=True)
        m2 = torch.einsum("tsk,tsl->kl", btc * weights.view(1, -1, 1), btc)
        out = torch.zeros(p_count, p_count, dtype=torch.float64)
        out[:k, :k] = m2
        out[k:, k:] = m2
        return out

    rn2 = kap * float(ref_noise) ** 2
    if rn2 > 0:
        # expected gradient energy of the noise contained in `ref` (white noise assumed)
        hess = hess - rn2 * block(w)
    frac_ref = pts - torch.floor(pts)
    cov_b = torch.zeros_like(hess)
    if sigma_ref > 0:
        cov_b = sigma_ref**2 * (_corr_form(wj.sum(0), frac_ref, sq_index, size, order, interp)
                                - rn2 * block(w * w, summed=True))
    if sd > 0:
        disp = _as_displacement(displacement, n, t_count, dtt)
        for i in range(t_count):
            pos = pts if disp is None else pts + disp[i]
            frac = pos - torch.floor(pos)
            cov_b = cov_b + sd**2 * _corr_form(wj[i], frac, sq_index, size, order, interp)
        cov_b = cov_b - sd**2 * rn2 * block(w * w)
    if second_order and sigma_ref > 0 and sd > 0:
        # the noise of the reference gradient (in J) times the frames' noise: both frames'
        # terms are independent of the first-order ones; kappa sigma_ref^2 is the variance of
        # the reference spline's derivative noise (the reference noise's own product with
        # its derivative cancels between the Jacobian and the residual, first order)
        cov_b = cov_b + kap * sigma_ref**2 * sd**2 * block(w * w)
    hinv = torch.linalg.inv(hess)
    cov = hinv @ cov_b @ hinv
    return cov, shape.param_names


def predicted_std(*args: Any, **kwargs: Any) -> dict[str, torch.Tensor]:
    """Predicted random error (standard deviation) of u, v, ut, vt at every POI.

    Args:
        ref: reference image (H, W); the cleanest available (its gradients build ``H``).
        points: (N, 2) POIs (x, y), px.
        config: the :class:`~torch_stsdic.DICConfig` of the measurement (subset size, shape,
            window, criterion, interpolation; ``m`` gives the default ``n_frames``).
        sigma_ref: noise std of the reference image (grey levels). A mean of K still frames
            has ``sigma / sqrt(K)``; a synthetic noise-free reference 0.
        sigma_def: noise std of each deformed frame (default ``sigma_ref``).
        n_frames: frames in the window, 2m+1 (default ``config.n_frames``); 1 = classical.
        dt: (T,) frame times minus the result's time (default centred: ``-m..m``); a shifted
            window at the ends of a series has e.g. ``0..2m``.
        displacement: for the sub-pixel interpolation correction: a scalar (u), (N, 2)
            (u, v) at every frame, (N, 4) (u, v, ut, vt: u + ut dt per frame) or (T, N, 2).
            None: integer positions (no correction).
        interp: "exact" (full correlation of the interpolated noise), "white" (variance
            factor only) or a number c (noise variance times c): see the module docstring.
        second_order: add the product term of the reference-gradient noise and the frames'
            noise, ``kappa sigma_ref^2 sigma_def^2 sum_t sum_s w^2 b_t b_t^T`` (only when
            both are noisy; +3..4 % std for classical DIC at sigma = 5 on the paper's case).
        ref_noise: noise std contained in ``ref`` itself (when only a noisy reference is
            available): its expected gradient energy ``kappa ref_noise^2 sum_s w b b^T`` is
            removed from ``H`` (without it the prediction is a few per cent low).

    Returns:
        dict of (N,) float64 tensors ``u, v, ut, vt`` (px, px per time unit of ``dt``; NaN
        velocities for one frame), plus ``cov`` (N, P, P) and ``names``.
    """
    cov, names = predicted_covariance(*args, **kwargs)
    std = torch.diagonal(cov, dim1=-2, dim2=-1).clamp(min=0).sqrt()
    out: dict[str, Any] = {}
    for nm in ("u", "v", "ut", "vt"):
        out[nm] = std[:, names.index(nm)] if nm in names else torch.full(
            (std.shape[0],), math.nan, dtype=torch.float64)
    out["cov"] = cov
    out["names"] = names
    return out


# the parameters are those of predicted_covariance, written once there
predicted_std.__signature__ = signature_like(  # type: ignore[attr-defined]
    predicted_covariance, returns="dict[str, torch.Tensor]")


def _quantiles(x: torch.Tensor, q: float) -> torch.Tensor:
    """(F,) ``torch.quantile(x, q, dim=1)`` of ``x`` (F, n) (linear interpolation, in x's
    dtype: :func:`_interpolated`) from its two order statistics about ``q`` in each row: on
    the CPU, where every value is a whole number in [0, ``_HISTOGRAM_BINS``) (the Sobel
    magnitudes of integer grey levels), from the rows' histograms (:func:`_histograms`: a
    megapixel in ~1 ms); else the lower by ``kthvalue``'s selection (O(n), where a
    megapixel's full sort takes 0.15 s), the next as the least value above it unless the
    lower one repeats."""
    counts = _histograms(x)
    if counts is not None:
        return _counted_quantiles(counts, x.shape[1], q, x.dtype)

    def selected(ranks: tuple[int, ...]) -> torch.Tensor:
        v_lo = x.kthvalue(ranks[0], dim=1).values
        if len(ranks) == 1:
            return v_lo.unsqueeze(1)
        above = torch.where(x > v_lo.unsqueeze(1), x, torch.inf).amin(1)
        v_hi = torch.where((x <= v_lo.unsqueeze(1)).sum(1) >= ranks[1], v_lo, above)
        return torch.stack([v_lo, v_hi], 1)
    return _interpolated(x.shape[1], q, selected)


def _counted_quantiles(counts: torch.Tensor, n: int, q: float, dtype: torch.dtype
                       ) -> torch.Tensor:
    """(F,) :func:`_quantiles` of rows of ``n`` whole numbers given as their histograms
    ``counts`` (F, bins) (value v counted at bin v), in ``dtype``: the same numbers."""
    return _interpolated(n, q, lambda ranks: _ranked(counts, ranks).to(dtype))


def _interpolated(n: int, q: float, ranked: Callable[[tuple[int, ...]], torch.Tensor]
                  ) -> torch.Tensor:
    """(F,) ``torch.quantile``'s linear rule at ``q`` over rows of ``n`` values, given
    ``ranked(ranks)`` (F, R) their ``ranks``-th smallest values (1-based; one rank or two
    adjacent ones): ``v_lo + (v_hi - v_lo) * frac`` (torch's ``lerp`` may round the last
    bit otherwise), the last value alone at the top."""
    pos = q * (n - 1)
    lo = int(math.floor(pos))
    if lo + 1 >= n:
        return ranked((lo + 1,))[:, 0]
    v_lo, v_hi = ranked((lo + 1, lo + 2)).unbind(1)
    return v_lo + (v_hi - v_lo) * (pos - lo)


#: whole-number values below this are counted in histograms by :func:`_quantiles` (8 MiB a
#: row of counts; the Sobel magnitudes of 16-bit grey levels stay below 2^19)
_HISTOGRAM_BINS = 1 << 20


def _histograms(x: torch.Tensor) -> torch.Tensor | None:
    """(F, bins) int64 each row's histogram of ``x`` (F, n) (value v counted at bin v); None
    where that does not apply: not on the CPU (the checks below read the values on the
    host), or a value not a whole number in [0, ``_HISTOGRAM_BINS``) (NaN included)."""
    if x.device.type != "cpu" or x.numel() == 0 or x.is_complex():
        return None
    lo, hi = torch.aminmax(x)
    if not (float(lo) >= 0.0 and float(hi) < _HISTOGRAM_BINS):
        return None
    if x.is_floating_point() and not bool(torch.equal(x, x.trunc())):
        return None
    f, bins = x.shape[0], int(hi) + 1
    at = x.to(torch.int64) + torch.arange(f).view(-1, 1) * bins  # each row its own bins
    return torch.bincount(at.reshape(-1), minlength=f * bins).view(f, bins)


def _ranked(counts: torch.Tensor, ranks: tuple[int, ...]) -> torch.Tensor:
    """(F, R) int64 the ``ranks``-th smallest values (1-based) of rows of whole numbers given
    as their histograms ``counts`` (F, bins): the first bin whose running count reaches each
    rank."""
    below = counts.cumsum(1)  # values <= each bin
    want = torch.tensor(ranks, dtype=below.dtype).expand(counts.shape[0], -1).contiguous()
    return torch.searchsorted(below, want)


def _second_difference(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``[1, -2, 1]`` along ``dim`` of ``x`` ("valid": 2 shorter there)."""
    n = x.shape[dim]
    return x.narrow(dim, 0, n - 2) - 2.0 * x.narrow(dim, 1, n - 2) + x.narrow(dim, 2, n - 2)


def _central_difference(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``[-1, 0, 1]`` along ``dim`` of ``x`` ("valid")."""
    n = x.shape[dim]
    return x.narrow(dim, 2, n - 2) - x.narrow(dim, 0, n - 2)


def _smoothing(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``[1, 2, 1]`` along ``dim`` of ``x`` ("valid")."""
    n = x.shape[dim]
    return x.narrow(dim, 0, n - 2) + 2.0 * x.narrow(dim, 1, n - 2) + x.narrow(dim, 2, n - 2)


def _immerkaer(img: torch.Tensor, flat_fraction: float | None) -> float:
    """Immerkaer's estimate of an (H, W) image (:func:`immerkaer_sigmas`)."""
    return float(immerkaer_sigmas(img.unsqueeze(0), flat_fraction)[0])


def immerkaer_sigmas(frames: torch.Tensor, flat_fraction: float | None = 0.5) -> torch.Tensor:
    """(F,) float64 Immerkaer's noise estimate (grey levels) of every frame of ``frames``
    (F, H, W) (float32 or float64, H, W >= 3; :func:`estimate_noise_sigma`), on the frames'
    device with no host read: the 3x3 kernels (the Laplacian difference, Sobel's) applied
    as their separable 1-D factors ("valid": a megapixel in tens of ms, where a float64
    ``conv2d`` on the CPU takes 0.15 s a kernel), each frame's flat pixels (Sobel's
    gradient at most its ``flat_fraction`` quantile; None: every pixel) averaged in
    float64. (In float32 the kernels of integer grey levels up to 16 bits are exact: sums
    of at most 16 of them.)"""
    if flat_fraction is not None:
        mean = _native_flat_mean(frames, float(flat_fraction))
        if mean is not None:
            return math.sqrt(math.pi / 2.0) * mean / 6.0
    a = _second_difference(_second_difference(frames, -1), -2).abs_()  # the Laplacian
    if flat_fraction is None:
        mean = a.mean((-2, -1), dtype=torch.float64)
    else:
        # Sobel's |d/dx| + |d/dy|, below each frame's quantile of it
        g = _smoothing(_central_difference(frames, -1), -2).abs_().add_(
            _smoothing(_central_difference(frames, -2), -1).abs_())
        flat = g.reshape(g.shape[0], -1)
        cut = _quantiles(flat[:, :: _cut_step(flat.shape[1])], float(flat_fraction))
        keep = g <= cut.view(-1, 1, 1)
        # the kept pixels' mean, without gathering them
        mean = torch.where(keep, a, 0.0).sum((-2, -1), dtype=torch.float64) / keep.sum(
            (-2, -1)).clamp(min=1)
    # E|N * noise| = sigma sqrt(36) sqrt(2/pi): sum of squared weights is 36
    return math.sqrt(math.pi / 2.0) * mean / 6.0


#: whole-number grey levels up to this magnitude take the C++ path (:func:`_native_flat_mean`)
_WHOLE_LEVELS = float(1 << 20)


def _cut_step(n: int) -> int:
    """The stride of the Sobel magnitudes (n a frame) whose quantile sets the flat cut."""
    return max(1, n // 2_000_000)


def _native_flat_mean(frames: torch.Tensor, q: float) -> torch.Tensor | None:
    """(F,) float64 :func:`immerkaer_sigmas`' mean of the flat pixels' Laplacian magnitudes,
    by the C++ kernels in two passes a frame and no (F, H, W) arrays
    (:func:`~torch_stsdic.kernels.native.sobel_counts`, ``flat_sums``), where they give the
    torch code's numbers to the bit: on the CPU, frames of whole-number grey levels (every
    stencil, cut and sum exact) whose Sobel magnitudes fit the histogram
    (``_HISTOGRAM_BINS``); else None (the torch code)."""
    if dispatch.noise(frames) != dispatch.NATIVE or frames.numel() == 0:
        return None
    lo, hi = (float(v) for v in torch.aminmax(frames))
    span = hi - lo  # (grey levels of up to 20 bits: every stencil's sums below 2^24, exact)
    if not (math.isfinite(span) and 8.0 * span < _HISTOGRAM_BINS
            and max(-lo, hi) <= _WHOLE_LEVELS and bool(torch.equal(frames, frames.trunc()))):
        return None
    f, h, w = frames.shape
    n_valid = (h - 2) * (w - 2)
    step = _cut_step(n_valid)
    counts = native_ops.sobel_counts(frames, step, int(8.0 * span) + 1)
    cut = _counted_quantiles(counts, -(-n_valid // step), q, frames.dtype)
    sums, kept = native_ops.flat_sums(frames, cut)
    return sums / kept.clamp(min=1)


def estimate_noise_sigma(
    image: Any,
    other: Any = None,
    *,
    method: str = "auto",
    flat_fraction: float | None = 0.5,
    robust: bool = False,
) -> float:
    """Estimate the image noise std (grey levels).

    * ``other`` given (a second still frame of the same scene): ``std(image - other) /
      sqrt(2)`` (``robust=True``: 1.4826 MAD instead of the std). Exact for independent
      noise of equal level; the two frames must not move (a 0.01 px shift of a speckle
      with 20 grey/px gradients adds ~0.2 grey levels).
    * ``image`` a stack (K, H, W) of K >= 2 still frames: the pooled per-pixel std over the
      stack (ddof = 1).
    * a single (H, W) image: Immerkaer (1996), ``sigma = sqrt(pi/2) / 6 * mean |I * N|``
      with ``N`` the 3x3 Laplacian-difference kernel ``[[1,-2,1],[-2,4,-2],[1,-2,1]]``.
      Image texture inflates it: on the synthetic speckle (``synth.make_speckle``) a
      noise-free image reads 0.4 grey levels, so the estimate is +10 % at sigma = 1, +2 % at
      sigma = 2 and within 1 % for sigma >= 5. ``flat_fraction`` (default 0.5) keeps only
      the pixels with the lowest Sobel gradient (Tai & Yang 2008), which helps on images
      with strong edges; ``None`` uses all pixels (plain Immerkaer).

    ``method`` "auto" picks by the inputs; "pair", "stack" or "immerkaer" force one.
    """
    if isinstance(image, torch.Tensor) and image.dtype == torch.float32 and other is None \
            and image.dim() == 2 and method in ("auto", "immerkaer"):
        a = image  # Immerkaer's on a float32 image as it is (no float64 copy)
    else:
        a = torch.as_tensor(np.asarray(image, dtype=np.float64) if not isinstance(
            image, torch.Tensor) else image, dtype=torch.float64)
    if method == "auto":
        method = "pair" if other is not None else ("stack" if a.dim() == 3 else "immerkaer")
    if method == "pair":
        if other is None:
            raise ValueError("method 'pair' needs `other` (a second still frame)")
        b = torch.as_tensor(np.asarray(other, dtype=np.float64) if not isinstance(
            other, torch.Tensor) else other, dtype=torch.float64)
        if a.shape != b.shape:
            raise ValueError(f"other: shape {tuple(b.shape)} differs from {tuple(a.shape)}")
        d = (a - b).reshape(-1)
        if robust:
            med = d.median()
            return float(1.4826 * (d - med).abs().median() / math.sqrt(2.0))
        return float(d.std() / math.sqrt(2.0))
    if method == "stack":
        if a.dim() != 3 or a.shape[0] < 2:
            raise ValueError(f"method 'stack' needs (K >= 2, H, W) frames, got {tuple(a.shape)}")
        return float(a.var(0, unbiased=True).mean().sqrt())
    if method == "immerkaer":
        if a.dim() != 2 or min(a.shape) < 3:
            raise ValueError(f"image: expected an (H, W) image of at least 3x3, got "
                             f"{tuple(a.shape)}")
        return _immerkaer(a, flat_fraction)
    raise ValueError(f"method: must be 'auto', 'pair', 'stack' or 'immerkaer', got {method!r}")


def residual_noise_sigma(
    ref: Any,
    frame: Any,
    points: Any,
    params: Any,
    config: DICConfig | None = None,
) -> float:
    """Noise estimate from the converged classical DIC residual, in the reference's grey levels.

    For every POI the frame is sampled at the warped subset (affine or quadratic parameters
    ``params`` (N, P) of a classical solution, e.g. ``sol.params`` of ``solve_window`` with
    m = 0) and compared with the reference subset after the ZNSSD normalisation (offset and
    least-squares scale). The pooled residual variance, corrected for the fitted parameters,
    estimates ``sigma_ref^2 + a^2 sigma_def^2`` (``a`` the contrast ratio): exactly the noise
    variance that enters the classical random error, ``var(u) = that * [H^-1]_uu``. Unlike
    a single-image estimate it is not inflated by texture. Two caveats: the frame's noise is
    seen after interpolation at the sub-pixel position, i.e. times ``c_interp`` (1 at integer
    shifts, 0.87 at 0.25 px, 0.76 at 0.5 px for cubic splines; measured on synthetic images:
    4.6 instead of 5 at a 0.25 px shift), and any shape-function mismatch or interpolation
    error adds to it. Non-finite rows (failed points) are skipped.
    """
    cfg = config if config is not None else DICConfig(m=0)
    f = torch.as_tensor(np.asarray(ref, dtype=np.float64) if not isinstance(
        ref, torch.Tensor) else ref, dtype=torch.float64)
    g = torch.as_tensor(np.asarray(frame, dtype=np.float64) if not isinstance(
        frame, torch.Tensor) else frame, dtype=torch.float64)
    pts = torch.as_tensor(np.asarray(points, dtype=np.float64) if not isinstance(
        points, torch.Tensor) else points, dtype=torch.float64).reshape(-1, 2)
    p = torch.as_tensor(np.asarray(params, dtype=np.float64) if not isinstance(
        params, torch.Tensor) else params, dtype=torch.float64)
    shape = make_shape(cfg.shape).spatial()
    if p.shape != (pts.shape[0], shape.n_params):
        raise ValueError(f"params: expected ({pts.shape[0]}, {shape.n_params}) classical "
                         f"parameters {shape.param_names}, got {tuple(p.shape)}")
    keep = torch.isfinite(p).all(1)
    pts, p = pts[keep], p[keep]
    if pts.shape[0] == 0:
        raise ValueError("params: no finite rows")
    window = make_window(cfg.window, cfg.subset_size)
    off, w = window.offsets_and_weights(torch.float64)
    bs = shape.spatial_basis(off[:, 0], off[:, 1])  # (S, K)
    k = shape.n_basis
    u = p[:, :k] @ bs.T
    v = p[:, k:] @ bs.T
    fs = BSplineImage(f, cfg.interpolation_order).sample(pts[:, :1] + off[:, 0],
                                                         pts[:, 1:] + off[:, 1])
    gs = BSplineImage(g, cfg.interpolation_order).sample(pts[:, :1] + off[:, 0] + u,
                                                         pts[:, 1:] + off[:, 1] + v)
    wsum = w.sum()
    fc = fs - (fs * w).sum(1, keepdim=True) / wsum
    gc = gs - (gs * w).sum(1, keepdim=True) / wsum
    a = (fc * gc * w).sum(1, keepdim=True) / (gc * gc * w).sum(1, keepdim=True).clamp(min=1e-30)
    r = fc - a * gc
    s_eff = effective_pixels(w)
    dof = max(s_eff - shape.n_params - 2.0, 1.0)
    var = (r * r * w).sum(1) / wsum * s_eff / dof
    return float(var.mean().sqrt())
