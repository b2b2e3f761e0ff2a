"""Local polynomial fits of a field sampled at scattered POIs, with a test of the fit's order.

Every POI's value is replaced by the value at the POI of a least-squares polynomial in
(x, y) (degree 1: a plane; 2: a quadratic) fitted to its ``k`` nearest POIs. The fit is
linear in the values, ``fitted_i = sum_j w_ij y_j``, so one set of weights serves any number
of frames or components, and the fitted value's variance follows from the weights and the
covariance of the values.

Neighbouring subsets share pixels, so their errors are correlated: two square windows of
side ``S`` offset by (dx, dy) share ``(1 - |dx|/S)(1 - |dy|/S)`` of their pixels, which is
the correlation of their noise-induced errors for a uniform speckle
(:func:`overlap_correlation`). The fitted value's variance is then ``w^T R w`` times one
value's, not ``|w|^2``.

Where the field is not a plane over the neighbourhood the plane's value is biased; the test
(:func:`local_fit`) compares it with the quadratic's value: the difference is zero-mean under
a plane with a variance ``d^T R d`` (``d`` the difference of the two weight vectors), so a
difference beyond ``z_limit`` of its standard deviation says the plane does not hold there.
A jump inside the neighbourhood (a crack) can leave the two values alike; the residuals
show it (:meth:`LocalFit.residual_z`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torch_stsdic.analysis.points import nearest_points

__all__ = ["LocalFit", "local_fit_weights", "overlap_correlation", "local_fit",
           "local_fit_passes"]

_CHUNK = 1 << 22  # elements of the (n, k, k) work arrays per chunk of POIs


@dataclass
class LocalFit:
    """Weights of the local fits of a set of POIs.

    Attributes:
        index: (N, k) long, the neighbours of every POI (itself first).
        weights: degree -> (N, k) float64 weights of the fitted value at the POI (rows of
            POIs whose fit is ill-posed: the POI itself, weight 1).
        slopes: degree -> (N, k, 2) weights of the fitted d/dx, d/dy at the POI (0 where
            ill-posed).
        quadratic: degree -> (N, k, 3) weights of the fit's coefficients of dx^2, dx dy, dy^2
            (px offsets from the POI; 0 for a plane and where ill-posed).
        posed: degree -> (N,) bool, whether the fit was well posed.
        offsets: (N, k, 2) px, the neighbours' offsets from the POI.
        used: (N, k) float64, 1 where a neighbour may be used.
        subset_size: px, for the neighbours' error correlation (:func:`overlap_correlation`,
            computed by chunks of POIs where needed: (k, k) per POI).
    """

    index: torch.Tensor
    weights: dict[int, torch.Tensor]
    slopes: dict[int, torch.Tensor]
    quadratic: dict[int, torch.Tensor]
    posed: dict[int, torch.Tensor]
    offsets: torch.Tensor
    used: torch.Tensor
    subset_size: float
    #: (N, k, k) the neighbours' correlations, kept while :meth:`keep_correlation` asks
    _corr: torch.Tensor | None = field(default=None, repr=False)

    def _chunks(self, rows: int = 1) -> range:
        """Chunks of POIs whose (n, k, k) and (rows, n, k) work arrays hold ~_CHUNK each."""
        k = self.index.shape[1]
        return range(0, self.index.shape[0], max(1, _CHUNK // (k * max(k, rows))))

    def correlation(self, sl: slice) -> torch.Tensor:
        """(n, k, k) the error correlation of the neighbours of the POIs ``sl``."""
        if self._corr is not None:
            return self._corr[sl]
        d = self.offsets[sl]
        return overlap_correlation(d[:, :, None, :] - d[:, None, :, :], self.subset_size)

    def keep_correlation(self, keep: bool = True, budget_mb: float = 128.0) -> None:
        """Keep every POI's (k, k) correlation (float64) between calls, where they fit
        in ``budget_mb``: several tests of one fit then make them once, not per call;
        ``keep=False`` lets them go."""
        n, k = self.index.shape
        self._corr = None
        if keep and n * k * k * 8 <= budget_mb * 2**20:
            self._corr = self.correlation(slice(0, n))

    def apply(self, degree: int, values: torch.Tensor) -> torch.Tensor:
        """(..., N) values -> (..., N) fitted values at the POIs."""
        return (values[..., self.index] * self.weights[degree]).sum(-1)

    def apply_slopes(self, degree: int, values: torch.Tensor) -> torch.Tensor:
        """(..., N) values -> (..., N, 2) fitted d/dx, d/dy (value units per px)."""
        return (values[..., self.index, None] * self.slopes[degree]).sum(-2)

    def apply_quadratic(self, degree: int, values: torch.Tensor) -> torch.Tensor:
        """(..., N) values -> (..., N, 3) the fit's coefficients of dx^2, dx dy, dy^2."""
        return (values[..., self.index, None] * self.quadratic[degree]).sum(-2)

    def variance_factor(self, w: torch.Tensor) -> torch.Tensor:
        """(N, k) weights -> (N,) ``w^T R w``: the variance of ``sum_j w_j y_j`` over one
        value's, for values whose errors correlate as the windows overlap."""
        out = torch.empty(w.shape[0], dtype=torch.float64)
        for s0 in self._chunks():
            sl = slice(s0, s0 + self._chunks().step)
            out[sl] = torch.einsum("nj,njk,nk->n", w[sl], self.correlation(sl), w[sl])
        return out

    def residual_z(self, degree: int, values: torch.Tensor, variance: torch.Tensor
                   ) -> torch.Tensor:
        """(C, N) the largest |residual| / its standard deviation of the fit of ``degree``
        over each POI's neighbours: the residuals ``(I - H) y`` (``H`` the fit's hat matrix)
        have the covariance ``(I - H) R (I - H)^T`` times the values' variance (C, N) (the
        neighbourhood's mean). A jump (a crack, a lost subset) inside the neighbourhood
        stands out here, where the fitted value alone may not show it."""
        c, n = values.shape
        k = self.index.shape[1]
        out = torch.zeros(c, n, dtype=torch.float64)
        nb_var = variance[:, self.index].mean(-1).clamp(min=1e-30)  # (C, N)
        eye = torch.eye(k, dtype=torch.float64)
        scale = float(self.offsets.norm(dim=-1).max().clamp(min=1.0))
        chunks = self._chunks(c)
        for s0 in chunks:
            sl = slice(s0, s0 + chunks.step)
            u = self.used[sl]
            a = _design(self.offsets[sl] / scale, degree) * u[..., None]  # (n, k, P)
            ata = a.transpose(1, 2) @ a
            good = self.posed[degree][sl]
            p = a.shape[-1]
            inv = torch.linalg.inv(torch.where(good[:, None, None], ata,
                                               torch.eye(p, dtype=torch.float64)))
            resid_op = (eye - a @ inv @ a.transpose(1, 2)) * u[:, :, None]  # (n, k, k)
            cov = torch.einsum("njk,nkl,njl->nj", resid_op, self.correlation(sl), resid_op)
            y = values[:, self.index[sl]]  # (C, n, k)
            r = torch.einsum("njk,cnk->cnj", resid_op, y)
            sd = (cov.clamp(min=1e-12)[None] * nb_var[:, sl, None]).sqrt()
            z = torch.where(u[None] > 0, r.abs() / sd, 0.0).amax(-1)
            out[:, sl] = torch.where(good[None], z, torch.inf)
        return out


def overlap_correlation(offsets: torch.Tensor, subset_size: float) -> torch.Tensor:
    """(..., 2) offsets (px) between two square subset windows of side ``subset_size`` ->
    (...) the share of pixels they have in common."""
    s = float(subset_size)
    share = (1.0 - offsets.abs() / s).clamp(min=0.0)
    return share[..., 0] * share[..., 1]


def _design(d: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, k, 2) offsets in units of the spacing -> (N, k, P) monomials up to ``degree``."""
    x, y = d[..., 0], d[..., 1]
    cols = [torch.ones_like(x), x, y]
    if degree >= 2:
        cols += [x * x, x * y, y * y]
    if degree >= 3:
        cols += [x ** 3, x * x * y, x * y * y, y ** 3]
    if degree >= 4:
        cols += [x ** 4, x ** 3 * y, x * x * y * y, x * y ** 3, y ** 4]
    return torch.stack(cols, -1)


def local_fit_weights(points: torch.Tensor, k: int, subset_size: float,
                      valid: torch.Tensor | None = None,
                      degrees: tuple[int, ...] = (1, 2)) -> LocalFit:
    """The local fits of degree ``degrees`` of every POI over its ``k`` nearest POIs.

    Args:
        points: (N, 2) POIs (x, y) px.
        k: neighbours per fit (the POI itself included); a 5 x 5 block of a grid: 25.
        subset_size: the subset width px (for the errors' correlation).
        valid: (N,) bool, the POIs whose values may be used (default all); an invalid POI
            gets weight 0 in its neighbours' fits.
        degrees: polynomial degrees to fit.
    """
    pts = points.double().cpu()
    n = pts.shape[0]
    k = max(1, min(int(k), n))
    idx = nearest_points(pts, k)[1]
    d = pts[idx] - pts[:, None]  # (N, k, 2) px
    scale = float(d.norm(dim=-1).max().clamp(min=1.0))
    ok = torch.ones(n, dtype=torch.bool) if valid is None else valid.cpu().bool()
    wk = ok[idx].double()  # (N, k)
    weights, slopes, quadratic, posed = {}, {}, {}, {}
    own = torch.zeros(n, k, dtype=torch.float64)
    own[:, 0] = 1.0
    for deg in degrees:
        a = _design(d / scale, deg) * wk[..., None]  # (N, k, P)
        ata = a.transpose(1, 2) @ a
        p = a.shape[-1]
        eye = torch.eye(p, dtype=torch.float64)
        cond = torch.linalg.cond(ata)
        good = (wk.sum(1) > p) & torch.isfinite(cond) & (cond < 1e8)
        inv = torch.linalg.inv(torch.where(good[:, None, None], ata, eye))
        rows = inv @ a.transpose(1, 2)  # (N, P, k): coefficients = rows @ y
        w0 = torch.where(good[:, None], rows[:, 0], own)
        sl = torch.where(good[:, None, None], rows[:, 1:3].transpose(1, 2) / scale,
                         torch.zeros(n, k, 2, dtype=torch.float64))
        quad = torch.zeros(n, k, 3, dtype=torch.float64)
        if deg >= 2:
            quad = torch.where(good[:, None, None], rows[:, 3:6].transpose(1, 2) / scale ** 2,
                               quad)
        weights[deg], slopes[deg], quadratic[deg], posed[deg] = w0, sl, quad, good
    return LocalFit(index=idx, weights=weights, slopes=slopes, quadratic=quadratic,
                    posed=posed, offsets=d, used=wk, subset_size=float(subset_size))


def local_fit_passes(fit: LocalFit, values: torch.Tensor, variance: torch.Tensor, *,
                     degree: int = 1, z_limit: float = 3.0) -> torch.Tensor:
    """(C, N) bool: where the fit of ``degree`` holds for each component of ``values``
    (C, N) (error variances ``variance``: (C, N) px^2): its value within ``z_limit``
    standard deviations of the next degree's, every residual within ``z_limit`` of its own
    (:meth:`LocalFit.residual_z`), and both fits well posed. The weights' geometry is worked
    out once for all C components, so the C rows (every frame's u and v) cost about one."""
    d = fit.weights[degree] - fit.weights[degree + 1]
    var_d = fit.variance_factor(d).clamp(min=1e-12)  # (N,)
    nb_var = variance[:, fit.index].mean(-1)  # (C, N) the neighbourhood's mean variance
    diff = fit.apply(degree, values) - fit.apply(degree + 1, values)
    z = diff.abs() / (var_d * nb_var).sqrt()
    resid = fit.residual_z(degree, values, variance)
    return (z < z_limit) & (resid < z_limit) & fit.posed[degree] & fit.posed[degree + 1]


def local_fit(fit: LocalFit, values: torch.Tensor, variance: torch.Tensor, *,
              degree: int = 1, z_limit: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the fit of ``degree`` holds (its value does not differ significantly from the
    next degree's), and its value's variance factor.

    Args:
        fit: :func:`local_fit_weights` with ``degree`` and ``degree + 1``.
        values: (C, N) the values to test together (e.g. u and v): the fit is kept where
            every component passes (:func:`local_fit_passes`).
        variance: (C, N) each value's error variance (px^2).
        degree: the degree tested (1: the plane against the quadratic).
        z_limit: the largest |value - next degree's value| / its standard deviation accepted.

    Returns:
        (N,) bool whether the fit is kept; (N,) its value's variance over one value's
        (``w^T R w``; 1 where it is not kept).
    """
    keep = local_fit_passes(fit, values, variance, degree=degree, z_limit=z_limit).all(0)
    factor = torch.where(keep, fit.variance_factor(fit.weights[degree]),
                         torch.ones(keep.shape, dtype=torch.float64))
    return keep, factor
