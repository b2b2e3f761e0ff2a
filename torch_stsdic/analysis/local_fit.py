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

:meth:`LocalFit.test_z` makes both tests of several degrees in one pass over the POIs (the
designs of the degrees are nested; the residuals' variances come from ``A^T R`` and
``A^T R A``, O(k^2 P) a POI). That geometry depends only on the neighbours' offsets: POIs
whose neighbourhoods have one shape (a grid's interior; the neighbours listed by distance,
then angle) share it, worked out once a pattern. On the hourglass's 1,666 POIs (149, 288 and
412 patterns over 25, 49 and 81 neighbours) and 42 rows the tests take ~0.15 s instead of
~0.3 s (docs/validation/window_length.md, "Cost").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_stsdic.analysis.points import nearest_points

__all__ = ["LocalFit", "local_fit_weights", "overlap_correlation", "local_fit",
           "local_fit_passes", "passing_fits", "FitTest"]

_CHUNK = 1 << 22  # elements of the (n, k, k) work arrays per chunk of POIs


@dataclass
class FitTest:
    """One degree's tests of a local fit (:meth:`LocalFit.test_z`) for C rows of values.

    Attributes:
        value_z: (C, N) |fitted value - the next degree's| / its standard deviation (inf
            where either fit is ill-posed; None: not tested).
        residual_z: (C, N) the largest |residual| / its standard deviation over the
            neighbours (inf where ill-posed).
        factor: (N,) the fitted value's variance over one value's, ``w^T R w`` (1 where
            ill-posed).
    """

    value_z: torch.Tensor | None
    residual_z: torch.Tensor
    factor: torch.Tensor

    def passes(self, z_limit: float) -> torch.Tensor:
        """(C, N) bool: both tests within ``z_limit`` (both fits well posed)."""
        if self.value_z is None:
            raise ValueError("FitTest.passes: the fitted value was not tested (value=False)")
        return (self.value_z < z_limit) & (self.residual_z < z_limit)


@dataclass
class LocalFit:
    """Weights of the local fits of a set of POIs.

    Attributes:
        index: (N, k) long, the neighbours of every POI (itself first).
        weights: degree -> (N, k) float64 weights of the fitted value at the POI (rows of
            POIs whose fit is ill-posed: the POI itself, weight 1), for the degrees kept
            (``keep`` of :func:`local_fit_weights`; any degree by chunks of POIs:
            :meth:`map_weights`).
        slopes: degree -> (N, k, 2) weights of the fitted d/dx, d/dy at the POI (0 where
            ill-posed), the degrees kept.
        quadratic: degree -> (N, k, 3) weights of the fit's coefficients of dx^2, dx dy, dy^2
            (px offsets from the POI; 0 for a plane and where ill-posed), the degrees kept.
        posed: degree -> (N,) bool, whether the fit was well posed (every degree fitted).
        offsets: (N, k, 2) px, the neighbours' offsets from the POI.
        used: (N, k) float64, 1 where a neighbour may be used.
        subset_size: px, for the neighbours' error correlation (:func:`overlap_correlation`,
            computed by chunks of POIs where needed: (k, k) per POI).
        scale: px, the offsets' unit in the designs (the largest neighbour distance).
    """

    index: torch.Tensor
    weights: dict[int, torch.Tensor]
    slopes: dict[int, torch.Tensor]
    quadratic: dict[int, torch.Tensor]
    posed: dict[int, torch.Tensor]
    offsets: torch.Tensor
    used: torch.Tensor
    subset_size: float
    scale: float
    #: (N,) long each POI's neighbourhood pattern (the same offsets and used neighbours, in
    #: the same order: every POI inside a grid shares one) and (U,) a POI of each pattern:
    #: the fits' geometry is worked out once a pattern (None: at every POI)
    pattern: torch.Tensor | None = None
    reps: torch.Tensor | None = None

    def _geometry_rows(self, sl: slice | torch.Tensor
                       ) -> tuple[torch.Tensor | slice, torch.Tensor | None]:
        """The POIs whose geometry stands for the POIs ``sl`` (a slice or indices; one of
        each pattern among them) and (n,) each POI's row among those (None: ``sl`` itself,
        no gather)."""
        if self.pattern is None or self.reps is None:
            return sl, None
        pats, back = torch.unique(self.pattern[sl], return_inverse=True)
        return self.reps[pats], back

    def map_weights(self, degree: int, rows: torch.Tensor | slice) -> torch.Tensor:
        """(n, k, 6) the weights of the fitted value, d/dx, d/dy and the coefficients of
        dx^2, dx dy, dy^2 of the fit of ``degree`` at the POIs ``rows`` (indices or a slice),
        worked out there (the stored ``weights``, ``slopes``, ``quadratic`` of a kept degree
        are these, column by column): O(n k) memory for any number of POIs."""
        geo, back = self._geometry_rows(rows)  # once a neighbourhood pattern
        rows_ = _fit_rows(self.offsets[geo], self.used[geo], degree, self.scale,
                          self.posed[degree][geo])[0]
        out = _map_columns(rows_, self.posed[degree][geo], self.scale, degree)
        return out if back is None else out[back]

    def _chunks(self, rows: int = 1) -> range:
        """Chunks of POIs whose (n, k, k) and (rows, n, k) work arrays hold ~_CHUNK each."""
        k = self.index.shape[1]
        return range(0, self.index.shape[0], max(1, _CHUNK // (k * max(k, rows))))

    def correlation(self, sl: slice | torch.Tensor) -> torch.Tensor:
        """(n, k, k) the error correlation of the neighbours of the POIs ``sl``: the
        :func:`overlap_correlation` of their pairwise offsets, one axis at a time in place
        (no (n, k, k, 2) temporaries: this is most of a fit test's work)."""
        d = self.offsets[sl]
        scale = -1.0 / float(self.subset_size)

        def share(a: torch.Tensor) -> torch.Tensor:
            return (a[:, :, None] - a[:, None, :]).abs_().mul_(scale).add_(1.0).clamp_(min=0.0)
        return share(d[..., 0]).mul_(share(d[..., 1]))

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
        stands out here, where the fitted value alone may not show it. inf where the fit is
        ill-posed."""
        return self.test_z(values, variance, (degree,), value=False)[degree].residual_z

    def value_factors(self, degrees: tuple[int, ...]) -> dict[int, torch.Tensor]:
        """degree -> (N,) ``w^T R w`` of the fitted value's weights ``w`` (1 where the fit is
        ill-posed: the POI's own value), as :meth:`variance_factor` of ``weights[degree]``,
        every degree from one pass over the correlations (``A^T R A``, P x P a POI)."""
        n = self.index.shape[0]
        out = {d: torch.ones(n, dtype=torch.float64) for d in degrees}
        scale = self.scale
        chunks = self._chunks()
        for s0 in chunks:
            sl = slice(s0, s0 + chunks.step)
            geo, back = self._geometry_rows(sl)  # once a neighbourhood pattern
            a, _, _, gram = self._moments(geo, max(degrees), scale)
            for d in degrees:
                w = self._inverse(a[..., :_n_terms(d)], geo, d)[:, 0]
                f = self._factor(w, gram, geo, d)
                out[d][sl] = f if back is None else f[back]
        return out

    def test_z(self, values: torch.Tensor, variance: torch.Tensor, degrees: tuple[int, ...],
               value: bool = True) -> dict[int, FitTest]:
        """degree -> :class:`FitTest` of the fits of ``degrees`` for the values (C, N) of
        error variances ``variance`` (C, N), or (1, N) for all rows, px^2 (the
        neighbourhood's mean counts); ``value=False``: the residuals only.

        All the degrees from one pass over each chunk of POIs: the neighbours' values
        gathered once, the fits' coefficients ``(A^T A)^-1 A^T y`` of nested designs ``A``
        (the degree's monomials are the first columns of the highest's), and the
        residuals' variances as the diagonal ``R - 2 H R + H R H`` from ``A^T R`` and
        ``A^T R A`` (O(k^2 P) a POI, not the (k, k) products' O(k^3)); the value
        difference's variance ``delta^T (A^T R A) delta`` with ``delta`` the two fits'
        value rows of their inverses (the weights' difference is ``A delta``)."""
        c, n = values.shape
        top = max(degrees) + (1 if value else 0)
        scale = self.scale
        out = {d: FitTest(value_z=(torch.full((c, n), torch.inf, dtype=torch.float64)
                                   if value else None),
                          residual_z=torch.full((c, n), torch.inf, dtype=torch.float64),
                          factor=torch.ones(n, dtype=torch.float64)) for d in degrees}
        need = sorted(set(degrees) | ({d + 1 for d in degrees} if value else set()))
        # POI-major: every product below is one batched matrix product over the POIs
        vals_t, var_t = values.T.contiguous(), variance.T.contiguous()  # (N, C), (N, C | 1)
        chunks = self._chunks(c)
        for s0 in chunks:
            sl = slice(s0, s0 + chunks.step)
            # the geometry (designs, correlations, inverses: O(k^2 P) a POI, most of the
            # work) once a neighbourhood pattern among the chunk's POIs, then gathered
            geo, back = self._geometry_rows(sl)

            def each(t: torch.Tensor, back: torch.Tensor | None = back) -> torch.Tensor:
                return t if back is None else t[back]
            u = self.used[geo]
            idx = self.index[sl]
            a_g, rdiag, ar, gram = self._moments(geo, top, scale)
            a = each(a_g)
            y = vals_t[idx]  # (n, k, C)
            nb_var = var_t[idx].mean(1).clamp(min=1e-30)  # (n, C | 1)
            aty = a.transpose(1, 2) @ y  # (n, P, C) A^T y
            inv = {d: self._inverse(a_g[..., :_n_terms(d)], geo, d) for d in need}
            for d in degrees:
                p = _n_terms(d)
                coef = each(inv[d]) @ aty[:, :p]  # (n, P, C) the fit's coefficients
                resid = torch.baddbmm(y, a[..., :p], coef, alpha=-1.0)  # (n, k, C)
                am = a_g[..., :p] @ inv[d]  # (U, k, P): H = am A^T
                hr = (am * ar[:, :p].transpose(1, 2)).sum(-1)  # (U, k) diag(H R)
                hrh = ((am @ gram[:, :p, :p]) * am).sum(-1)  # diag(H R H)
                # 1 / the residuals' variance factors, 0 at unused neighbours
                icov = each(torch.where(u > 0, 1.0 / (rdiag - 2.0 * hr + hrh).clamp(min=1e-12),
                                        0.0))
                z = (resid.square_().mul_(icov[..., None]).amax(1) / nb_var).sqrt()  # (n, C)
                out[d].residual_z[:, sl] = torch.where(self.posed[d][sl][:, None], z,
                                                       torch.inf).T
                out[d].factor[sl] = each(self._factor(inv[d][:, 0], gram, geo, d))
                if value:
                    q = _n_terms(d + 1)
                    nxt = inv[d + 1][:, 0]  # (U, Q)
                    delta = -nxt
                    delta[:, :p] += inv[d][:, 0]
                    var_d = each(torch.einsum("np,npq,nq->n", delta, gram[:, :q, :q],
                                              delta).clamp(min=1e-12))
                    diff = coef[:, 0] - (each(nxt)[:, None] @ aty[:, :q])[:, 0]  # (n, C)
                    vz = diff.abs() / (var_d[:, None] * nb_var).sqrt()
                    posed = self.posed[d][sl] & self.posed[d + 1][sl]
                    out[d].value_z[:, sl] = torch.where(posed[:, None], vz, torch.inf).T
        return out

    def _factor(self, w: torch.Tensor, gram: torch.Tensor, sl: slice | torch.Tensor,
                degree: int) -> torch.Tensor:
        """(n,) ``w^T (A^T R A) w`` for the value rows ``w`` (n, P) of the inverses of the
        fit of ``degree`` (its weights are ``A w``); 1 where it is ill-posed."""
        p = w.shape[-1]
        f = torch.einsum("np,npq,nq->n", w, gram[:, :p, :p], w)
        return torch.where(self.posed[degree][sl], f, 1.0)

    def _moments(self, sl: slice | torch.Tensor, degree: int, scale: float
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """For the POIs ``sl``: the design ``A`` (n, k, P) of ``degree`` (offsets / ``scale``,
        unused neighbours' rows 0), the correlations' diagonal (n, k), ``A^T R`` (n, P, k)
        and ``A^T R A`` (n, P, P)."""
        a = _design(self.offsets[sl] / scale, degree) * self.used[sl][..., None]
        r = self.correlation(sl)
        ar = a.transpose(1, 2) @ r
        return a, r.diagonal(dim1=1, dim2=2).clone(), ar, ar @ a  # r itself goes now

    def _inverse(self, a: torch.Tensor, sl: slice | torch.Tensor, degree: int
                 ) -> torch.Tensor:
        """(n, P, P) ``(A^T A)^-1`` of the design ``a`` (n, k, P) of ``degree`` (the identity
        where the fit is ill-posed)."""
        p = a.shape[-1]
        ata = a.transpose(1, 2) @ a
        good = self.posed[degree][sl]
        return torch.linalg.inv(torch.where(good[:, None, None], ata,
                                            torch.eye(p, dtype=torch.float64)))


def _n_terms(degree: int) -> int:
    """Monomials of a polynomial in (x, y) up to ``degree``."""
    return (degree + 1) * (degree + 2) // 2


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
                      degrees: tuple[int, ...] = (1, 2),
                      keep: tuple[int, ...] | None = None) -> LocalFit:
    """The local fits of degree ``degrees`` of every POI over its ``k`` nearest POIs.

    Args:
        points: (N, 2) POIs (x, y) px.
        k: neighbours per fit (the POI itself included); a 5 x 5 block of a grid: 25.
        subset_size: the subset width px (for the errors' correlation).
        valid: (N,) bool, the POIs whose values may be used (default all); an invalid POI
            gets weight 0 in its neighbours' fits.
        degrees: polynomial degrees to fit.
        keep: the degrees whose weights are stored (default all ``degrees``; the others
            only whether they are well posed, their weights by chunks where needed:
            :meth:`LocalFit.map_weights`): N k 48 bytes a kept degree.
    """
    pts = points.double().cpu()
    n = pts.shape[0]
    k = max(1, min(int(k), n))
    idx = _canonical(pts, nearest_points(pts, k)[1])
    d = pts[idx] - pts[:, None]  # (N, k, 2) px
    scale = float(d.norm(dim=-1).max().clamp(min=1.0))
    ok = torch.ones(n, dtype=torch.bool) if valid is None else valid.cpu().bool()
    wk = ok[idx].double()  # (N, k)
    pattern, reps = _patterns(d, wk)
    kept = tuple(degrees) if keep is None else tuple(keep)
    weights, slopes, quadratic, posed = {}, {}, {}, {}
    step = max(1, _CHUNK // (k * 16))  # POIs a chunk: (n, k, P) designs of up to 15 terms
    good: dict[int, list[torch.Tensor]] = {deg: [] for deg in degrees}
    cols: dict[int, list[torch.Tensor]] = {deg: [] for deg in kept if deg in degrees}
    d_r, wk_r = d[reps], wk[reps]  # one POI a pattern: the fits depend on nothing else
    for s0 in range(0, reps.numel(), step):
        sl = slice(s0, s0 + step)
        # the degrees not kept: only whether posed, from the highest design's first columns
        top = _design(d_r[sl] / scale, max(degrees)) * wk_r[sl][..., None]
        for deg in degrees:
            if deg in cols:
                rows, g = _fit_rows(d_r[sl], wk_r[sl], deg, scale, None)
                cols[deg].append(_map_columns(rows, g, scale, deg))
            else:
                g = _posed(top[..., :_n_terms(deg)], wk_r[sl])
            good[deg].append(g)
    for deg in degrees:
        posed[deg] = torch.cat(good[deg])[pattern]
        if deg in cols:
            m = torch.cat(cols[deg])[pattern]  # (N, k, 6)
            weights[deg] = m[..., 0].clone()
            slopes[deg] = m[..., 1:3].clone()
            quadratic[deg] = m[..., 3:6].clone()
    return LocalFit(index=idx, weights=weights, slopes=slopes, quadratic=quadratic,
                    posed=posed, offsets=d, used=wk, subset_size=float(subset_size),
                    scale=scale, pattern=pattern, reps=reps)


def _canonical(pts: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """The neighbours ``idx`` (N, k) of the POIs ``pts`` (N, 2) in an order set by their
    offsets alone: by distance, then angle (the POI itself first): POIs whose neighbourhoods
    have the same shape list them alike (a nearest-point search breaks distance ties by
    index, which differs between POIs)."""
    d = pts[idx] - pts[:, None]  # (N, k, 2)
    angle = torch.atan2(d[..., 1], d[..., 0])
    dist = d.square().sum(-1)
    # distance first, to 1e-9 of the largest (equal offsets of a grid are equal here)
    ticks = (dist / dist.amax().clamp(min=1e-300) * 1e9).round()
    order = torch.sort(angle, dim=1, stable=True).indices
    order = order.gather(1, torch.sort(ticks.gather(1, order), dim=1, stable=True).indices)
    return idx.gather(1, order)


def _patterns(d: torch.Tensor, used: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) the pattern of each POI's neighbourhood (offsets ``d`` (N, k, 2) and ``used``
    (N, k) equal, in order) and (U,) the first POI of each pattern. Rows are told apart by
    a random projection, and every POI is checked against its pattern's first: a POI that
    differs (a projection's collision) is a pattern of its own."""
    n = d.shape[0]
    rows = torch.cat([d.reshape(n, -1), used], 1)  # (N, 3k)
    gen = torch.Generator().manual_seed(0)
    key = rows @ torch.rand(rows.shape[1], 2, dtype=torch.float64, generator=gen)  # (N, 2)
    _, pattern = torch.unique(key, dim=0, return_inverse=True)
    first = torch.full((int(pattern.max()) + 1 if n else 0,), n, dtype=torch.long)
    first.scatter_reduce_(0, pattern, torch.arange(n), reduce="amin")
    odd = (rows != rows[first[pattern]]).any(1)
    if bool(odd.any()):  # its own pattern each
        pattern = pattern.clone()
        pattern[odd] = first.numel() + torch.arange(int(odd.sum()))
        first = torch.cat([first, torch.nonzero(odd).flatten()])
    return pattern, first


def _fit_rows(offsets: torch.Tensor, used: torch.Tensor, degree: int, scale: float,
              good: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The fits of ``degree`` of some POIs from their neighbours' ``offsets`` (n, k, 2) px and
    ``used`` (n, k): the rows (n, P, k) of ``(A^T A)^-1 A^T`` (the coefficients are these
    times the values) and (n,) whether each fit is well posed
    (``good``: known; None: from the condition number of ``A^T A``, below 1e8, and more
    used neighbours than terms)."""
    a = _design(offsets / scale, degree) * used[..., None]  # (n, k, P)
    ata = a.transpose(1, 2) @ a
    p = a.shape[-1]
    if good is None:
        good = _posed(a, used, ata)
    inv = torch.linalg.inv(torch.where(good[:, None, None], ata,
                                       torch.eye(p, dtype=torch.float64)))
    return inv @ a.transpose(1, 2), good


def _posed(a: torch.Tensor, used: torch.Tensor, ata: torch.Tensor | None = None
           ) -> torch.Tensor:
    """(n,) whether the fits of the designs ``a`` (n, k, P) (``ata``: their ``A^T A`` where
    known) are well posed: more used neighbours (``used`` (n, k)) than terms and the
    condition number of ``A^T A`` below 1e8."""
    if ata is None:
        ata = a.transpose(1, 2) @ a
    ev = torch.linalg.eigvalsh(ata)  # symmetric: its eigenvalues are its singular values
    cond = torch.where(ev[..., 0] > 0, ev[..., -1] / ev[..., 0], torch.inf)
    return (used.sum(1) > a.shape[-1]) & torch.isfinite(cond) & (cond < 1e8)


def _map_columns(rows: torch.Tensor, good: torch.Tensor, scale: float, degree: int
                 ) -> torch.Tensor:
    """(n, P, k) rows of the fits of ``degree`` (:func:`_fit_rows`) -> (n, k, 6) the weights of
    the value (the POI's own value where ill-posed), d/dx, d/dy (px^-1) and the coefficients
    of dx^2, dx dy, dy^2 (px^-2; 0 for a plane and where ill-posed)."""
    n, _, k = rows.shape
    own = torch.zeros(n, k, dtype=torch.float64)
    own[:, 0] = 1.0
    w0 = torch.where(good[:, None], rows[:, 0], own)
    sl = torch.where(good[:, None, None], rows[:, 1:3].transpose(1, 2) / scale,
                     torch.zeros(n, k, 2, dtype=torch.float64))
    quad = torch.zeros(n, k, 3, dtype=torch.float64)
    if degree >= 2:
        quad = torch.where(good[:, None, None], rows[:, 3:6].transpose(1, 2) / scale ** 2, quad)
    return torch.cat([w0[..., None], sl, quad], -1)


def passing_fits(fit: LocalFit, values: torch.Tensor, variance: torch.Tensor, *,
                 degrees: tuple[int, ...] = (1,), z_limit: float = 3.0
                 ) -> dict[int, torch.Tensor]:
    """degree -> (C, N) bool: where the fit of that degree holds for each component of
    ``values`` (C, N) (error variances ``variance``: (C, N) or (1, N) px^2): its value within
    ``z_limit`` standard deviations of the next degree's, every residual within ``z_limit``
    of its own (:meth:`LocalFit.residual_z`), and both fits well posed
    (:meth:`FitTest.passes`). The weights' geometry and the neighbours' values are worked
    out once for all C components and all ``degrees`` (:meth:`LocalFit.test_z`), so the C
    rows (every frame's u and v) and the degrees cost about one."""
    return {d: t.passes(z_limit) for d, t in fit.test_z(values, variance, degrees).items()}


def local_fit_passes(fit: LocalFit, values: torch.Tensor, variance: torch.Tensor, *,
                     degree: int = 1, z_limit: float = 3.0) -> torch.Tensor:
    """(C, N) bool: where the fit of ``degree`` holds for each component of ``values``
    (:func:`passing_fits` of the one degree)."""
    return passing_fits(fit, values, variance, degrees=(degree,), z_limit=z_limit)[degree]


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
