"""Checks that decide whether a solved point is trusted: the model check of a window, the fit
check against the image noise, and the neighbour (normalised median) test.

A number marked CONVERGED is a promise. The Gauss-Newton iteration converging only says the
criterion is at a minimum; these checks say whether that minimum is the motion:

- **Model check** (:func:`model_mismatch`): a window of 2m+1 frames assumes the motion is
  affine in time over the window. The classical (m = 0) solution at the window's target frame
  needs no such assumption. Under the model both estimate the same displacement, and the STS one
  is the more efficient, so their difference has variance ``var_classical - var_sts`` (the
  Hausman test; both variances are predicted per point by :mod:`torch_stsdic.core.uncertainty` from
  the point's own residual). A difference beyond ``MODEL_Z`` standard deviations (plus a
  tolerance ``MODEL_TOL`` px for what the noise model leaves out: interpolation bias) means the
  window does not fit; the tracker then shortens it (m - 1, ..., 0) for that point. So it
  does where the window's residual is clearly above the classical one
  (:func:`residual_mismatch`): a line through a step in time can pass through the right
  displacement at the target frame, but its residual shows the misfit.
- **Fit check** (:func:`poor_fit`): the residual of a right answer is the image noise. A point
  whose noise estimate (residual std) is more than ``FIT_RATIO`` times the median of the points
  solved with it (unless its ZNCC is at least ``FIT_ZNCC_GOOD``), or whose ZNCC is below the
  run's floor, did not find its subset: POOR_FIT.
- **Neighbour check** (:func:`median_test`): the normalised median test of PIV (Westerweel &
  Scarano 2005, Exp. Fluids 39:1096) on u and v among the nearest grid neighbours, each
  neighbour's value first carried to the point by the measured gradients (the trapezoid rule of
  :func:`carried_neighbours`, so linear and quadratic fields pass, at edges and beside holes
  too), iterated so that a bad point does not condemn its good neighbours: residual ``|u_i -
  med_j c_j| / (med_j |c_j - med| + eps)`` above ``MEDIAN_THRESHOLD`` is an outlier:
  INCONSISTENT. ``eps`` is ``MEDIAN_EPS_STD`` times the median predicted std, at least
  ``MEDIAN_EPS_MIN`` px, combined with the neighbours' gradient noise carried over their
  distance (:func:`neighbour_tolerance`; never the judged point's own precision): the test
  catches gross outliers (a wrong peak, off by more than ~0.1 px), never the noise or the
  noise of the gradients used to carry the neighbours. The test
  normalises by the neighbours' own scatter, so it cannot judge a point whose neighbours scatter
  as wildly as it does (subsets across a specimen's edge, where half the subset is background:
  each finds some peak, px to tens of px apart). A point whose carried neighbours scatter by
  more than ``MEDIAN_SCATTER`` times ``eps`` (median absolute residual) is therefore
  INCONSISTENT too: a smooth field, even a strongly strained one, carried by its gradients
  scatters by the noise; a crack's jump moves the median residual of the points beside it by at
  most half the jump.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.analysis.points import nearest_points
from torch_stsdic.analysis.strain import detect_grid
from torch_stsdic.kernels import dispatch, native

__all__ = [
    "MODEL_Z", "MODEL_TOL", "RESIDUAL_Z", "RESIDUAL_ZNCC", "FIT_RATIO", "FIT_ZNCC_GOOD",
    "FIT_GROWTH",
    "MEDIAN_THRESHOLD", "MEDIAN_EPS_STD", "MEDIAN_EPS_MIN", "MEDIAN_SCATTER", "MEDIAN_ROUNDS",
    "LINE_Z", "difference_std", "model_mismatch", "line_offset", "line_mismatch",
    "residual_mismatch", "poor_fit",
    "neighbours", "carried_neighbours", "median_test", "nanmedian_rows",
]

MODEL_Z = 3.0  #: model check: standard deviations of the STS - classical difference allowed
MODEL_TOL = 0.005  #: model check: px added in quadrature to that standard deviation
RESIDUAL_Z = 6.0  #: model check: the window's residual std may exceed the classical one by
#: a factor 1 + RESIDUAL_Z / sqrt(subset pixels) (measured spread: 1 +- 0.03 at 21x21)
RESIDUAL_ZNCC = 0.9999  #: model check: above this window ZNCC the residual test is not made
#: shorter windows: one whose frames' classical displacements miss a line by the check's
#: limit plus this many standard deviations of that prediction is not solved (it would fail)
LINE_Z = 4.0
FIT_RATIO = 2.0  #: fit check: residual std above this times the median is POOR_FIT
FIT_ZNCC_GOOD = 0.999  #: fit check: a ZNCC at least this is a good fit whatever the median
#: fit check: a point whose misfit (1 - ZNCC) grew by at most this factor since its last
#: trusted row keeps its trust (a residual growing with the strain, not a jump to a wrong peak)
FIT_GROWTH = 2.25
MEDIAN_THRESHOLD = 2.0  #: neighbour check: normalised median residual above this is an outlier
MEDIAN_EPS_STD = 3.0  #: neighbour check: eps in units of the median predicted std
MEDIAN_EPS_MIN = 0.05  #: neighbour check: smallest eps, px (half the 0.1 px a user notices)
#: neighbour check: neighbours (carried by their gradients) whose median absolute residual
#: exceeds this times eps are no smooth field: the point is INCONSISTENT (1 px at eps 0.05)
MEDIAN_SCATTER = 20.0
#: neighbour check: a point's own gradient is used to carry its neighbours where it is
#: within 3 median absolute deviations of theirs plus this
GRADIENT_TOL = 0.005
#: neighbour check: rounds of the test (each flags the worst outliers of their neighbourhood)
MEDIAN_ROUNDS = 4


def difference_std(std_sts: Tensor, std_cls: Tensor) -> Tensor:
    """(N, 2) px the predicted standard deviation of the window's displacement minus the
    classical one (Hausman: ``var_classical - var_sts``, at least a fifth of the classical
    variance), with ``MODEL_TOL`` added in quadrature; from their (N, 2) predicted
    standard deviations (NaN: 0)."""
    vs = torch.nan_to_num(std_sts.double(), nan=0.0) ** 2
    vc = torch.nan_to_num(std_cls.double(), nan=0.0) ** 2
    return (torch.maximum(vc - vs, 0.2 * vc) + MODEL_TOL**2).sqrt()


def model_mismatch(d_sts: Tensor, d_cls: Tensor, std_sts: Tensor, std_cls: Tensor,
                   slack: Tensor | None = None) -> Tensor:
    """(N,) bool: the window's displacement disagrees with the classical one.

    Args:
        d_sts, d_cls: (N, 2) displacement (u, v) at the target frame, px: the window's and
            the classical solution's.
        std_sts, std_cls: (N, 2) their predicted standard deviations, px (NaN: unknown, then
            only ``MODEL_TOL`` is allowed beyond ``MODEL_Z`` times the classical std).
        slack: (N,) px by which ``d_cls`` may miss the classical solution (an estimate of
            it: the difference must pass however it lies within that), or None: 0.
    """
    diff = (d_sts.double() - d_cls.double()).abs()
    if slack is not None:
        diff = diff + slack.double().unsqueeze(1)
    z = diff / difference_std(std_sts, std_cls)
    return ~(z <= MODEL_Z).all(1)  # NaN differences fail


def line_offset(disp: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
    """The least-squares line through a window's classical displacements, evaluated at the
    target (dt = 0), minus the target's own displacement: to within its noise, how far the
    window's solution (affine in time) lands from the classical one.

    Args:
        disp: (R, T, 2) classical (u, v) at the window's frames, px (any leading dims).
        dt: (R, T) the frames' times minus the target's (the target's own frame: the one
            nearest 0); any leading dims that broadcast with ``disp``'s (one row of times
            for all the points of a target: (K, 1, T) against (K, N, T, 2)).

    Returns:
        (R, 2) the offset px; (R, 1) ``sum_k c_k^2``, the offset's noise variance over one
        frame's (``c``: the offset's weights of the frames, which sum to 0: a displacement
        error every frame shares, the reference image's, cancels), of ``dt``'s leading dims.
    """
    d, t = disp.double(), dt.double()
    n = t.shape[-1]
    tm = t.mean(-1, keepdim=True)
    sxx = ((t - tm) ** 2).sum(-1, keepdim=True)
    a = 1.0 / n - tm * (t - tm) / sxx.clamp(min=1e-12)  # (R, T) weights of the line at 0
    at = t.abs().argmin(-1, keepdim=True)  # the target's own frame in the window
    c = a - torch.zeros_like(a).scatter_(-1, at, 1.0)
    return (c.unsqueeze(-1) * d).sum(-2), (c * c).sum(-1, keepdim=True)


def line_mismatch(disp: Tensor, dt: Tensor, own: Tensor, std_cls: Tensor,
                  line: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(R,) bool: a window whose frames' classical displacements are this far off a line
    cannot pass the model check (:func:`model_mismatch`), so it need not be solved.

    The window's displacement at the target is, to within its noise, the least-squares line
    through its frames' displacements evaluated at dt = 0 (:func:`line_offset`). Where that
    line misses the classical displacement ``own`` by more than the check's limit
    (``MODEL_Z`` standard deviations of the difference, the window's variance taken as the
    classical one over T) plus ``LINE_Z`` standard deviations of the prediction's own noise,
    the window fails.

    Args:
        disp: (R, T, 2) classical (u, v) at the window's frames, px, any known motion the
            window carries (the shared motion's offsets) removed; NaN: unknown (then False).
        dt: (R, T) the frames' times minus the target's (leading dims that broadcast, as
            :func:`line_offset`'s).
        own: (R, 2) the classical (u, v) at the target.
        std_cls: (R, 2) its predicted standard deviation, px (taken for every frame).
        line: :func:`line_offset` of (disp, dt), where the caller has it already.
    """
    n = dt.shape[-1]
    at = dt.abs().argmin(-1)[..., None, None]  # the target's frame in the window
    # the line at 0 minus the target frame's displacement
    off, csq = line_offset(disp, dt) if line is None else line
    off = off + torch.take_along_dim(disp.double(), at, -2).squeeze(-2) - own.double()
    vc = torch.nan_to_num(std_cls.double(), nan=float("inf")) ** 2
    sd_pred = (vc * csq).sqrt()
    sd_diff = (torch.maximum(vc * (1.0 - 1.0 / n), 0.2 * vc) + MODEL_TOL**2).sqrt()
    off = off.abs()
    return ((off > MODEL_Z * sd_diff + LINE_Z * sd_pred) & torch.isfinite(off)).any(-1)


def residual_mismatch(sigma_window: Tensor, sigma_classical: Tensor, n_pixels: float,
                      zncc_window: Tensor, margin: float = 1.0) -> Tensor:
    """(N,) bool: the window's residual is not the image noise that the classical solution
    of the same point leaves: ``sigma_window > (1 + RESIDUAL_Z / sqrt(n_pixels)) *
    sigma_classical`` (both (N,) noise std estimates, grey levels). Under the model the two
    estimate the same noise (ratio 1 +- 0.03 for 21 x 21 subsets, measured); a window across
    a jump in time or an arc can still put its displacement right at the target frame (the
    line through a step can pass through it), but not its residual. Not judged where the
    window matches at ZNCC >= ``RESIDUAL_ZNCC`` (noise-free images: both residuals are
    interpolation round-off, and their ratio means nothing). ``margin`` < 1 tightens the
    limit by that factor (``sigma_classical`` an estimate)."""
    limit = margin * (1.0 + RESIDUAL_Z / max(float(n_pixels), 1.0) ** 0.5)
    misfit = sigma_window.double() > limit * sigma_classical.double()
    return misfit & ~(zncc_window.double() >= RESIDUAL_ZNCC)


def poor_fit(sigma: Tensor, zncc: Tensor, solved: Tensor, zncc_floor: float,
             min_points: int = 16, group: Tensor | None = None,
             baseline_zncc: Tensor | None = None) -> Tensor:
    """(N,) bool: solved points whose fit is not the image noise.

    Args:
        sigma: (N,) noise std estimated from each point's residual, grey levels.
        zncc: (N,) ZNCC of each point.
        solved: (N,) bool, the points to judge (the median is taken over them).
        zncc_floor: ZNCC below this is a poor fit.
        min_points: the residual test needs at least this many solved points (a median).
        group: (N,) int >= 0: points are compared with the median of their own group only
            (e.g. one target frame each). Default: one group.
        baseline_zncc: (N,) each point's ZNCC at its last trusted row (NaN: none). A point
            whose misfit energy (1 - ZNCC, proportional to its residual variance) grew by
            at most ``FIT_GROWTH`` since then is not POOR_FIT for its residual: it fits as it
            did, only worse as the speckles deform (the hourglass's neck at 50 % strain, ZNCC
            0.89-0.97, residual 2x the frame's median); a wrong peak or a crack opening
            under the subset makes it jump.

    The median is taken over the points that are not noise-free matches (ZNCC below
    ``RESIDUAL_ZNCC``): a classical solution at the reference frame matches the reference
    itself, to round-off, and where most rows of that frame had fallen back to classical
    (sample 12: load steps) their ~0 median made a third of the window rows POOR_FIT.
    """
    bad = solved & ~(zncc >= zncc_floor)
    have = solved & torch.isfinite(sigma) & ~(zncc >= RESIDUAL_ZNCC)
    g = torch.zeros_like(sigma, dtype=torch.long) if group is None else group.long()
    if group is None and sigma.numel() == 0:
        return bad
    if group is None:  # one group: its lower middle value, with no host synchronisation
        counts = have.sum().reshape(1)
        ranked = torch.where(have, sigma, torch.inf).sort().values  # the judged ones first
        med = ranked.gather(0, ((counts - 1) // 2).clamp(min=0))  # none: not enough
    elif not bool(have.any()):
        return bad
    else:
        s, gs = sigma[have], g[have]
        counts = torch.bincount(gs, minlength=int(g.max()) + 1)
        order = torch.argsort(s, stable=True)
        order = order[torch.argsort(gs[order], stable=True)]  # by group, then by sigma
        first = torch.cumsum(counts, 0) - counts
        med = s[order][(first + (counts - 1).clamp(min=0) // 2).clamp(max=s.numel() - 1)]
    enough = (counts >= min_points)[g]
    # a match at ZNCC >= FIT_ZNCC_GOOD is never poor (e.g. a frame against itself, where
    # the "noise" is round-off and its median ~0)
    high = solved & enough & (sigma > FIT_RATIO * med[g]) & ~(zncc >= FIT_ZNCC_GOOD)
    if baseline_zncc is not None:
        base = (1.0 - baseline_zncc.to(zncc.dtype)).clamp(min=0.0)
        high &= ~((1.0 - zncc) <= FIT_GROWTH * base)  # NaN baseline: judged as before
    return bad | high


def neighbours(points: Tensor, k: int = 8, reach: float = 2.5, chunk: int = 2048) -> Tensor:
    """(N, k) indices of the ``k`` nearest other points within ``reach`` times the median
    nearest-neighbour distance (-1 where fewer), from (N, 2) positions px. Points on a
    regular grid (holes allowed) are looked up in the grid; others searched
    (:func:`~torch_stsdic.analysis.points.nearest_points`)."""
    p = points.double()
    n = p.shape[0]
    k_eff = min(k, n - 1)
    if k_eff <= 0:
        return torch.full((n, k), -1, dtype=torch.long, device=points.device)
    grid = detect_grid(p.cpu().numpy()) if n > 64 else None
    if grid is not None:
        idx_t = _grid_neighbours(grid, k_eff, reach).to(points.device)
    else:
        dist_t, idx_t = nearest_points(p, k_eff + 1, chunk)
        dist_t, idx_t = dist_t[:, 1:], idx_t[:, 1:]  # not itself
        limit = reach * dist_t[:, 0].median()
        idx_t = torch.where(dist_t <= limit, idx_t, torch.full_like(idx_t, -1))
    if k_eff < k:
        pad = torch.full((n, k - k_eff), -1, dtype=torch.long, device=idx_t.device)
        idx_t = torch.cat([idx_t, pad], 1)
    return idx_t.to(points.device)


def neighbour_tolerance(std_uv: Tensor, grad_std: Tensor | None, ok: Tensor, nb: Tensor,
                        reach: float) -> Tensor:
    """(B, N) eps px of the neighbour test (:func:`median_test`): ``MEDIAN_EPS_STD`` times
    the median predicted std of u, v of the ``ok`` (B, N) rows of each target (``std_uv``
    (B, N, 2)), at least ``MEDIAN_EPS_MIN``; with ``grad_std`` (B, N) (the largest predicted
    std of a point's gradients), combined with ``MEDIAN_EPS_STD`` times the median gradient
    noise of the point's ``ok`` neighbours ``nb`` (N, k) carried over ``reach`` px (the
    neighbours' gradients carry their values to the point). The judged point's own precision
    does not widen its tolerance: a point whose subset does not determine its motion (a
    predicted std of thousands of px) would otherwise never be an outlier."""
    sd = torch.where(ok.unsqueeze(-1), std_uv.double(), torch.nan).flatten(1)
    eps = (MEDIAN_EPS_STD * torch.nanmedian(sd, dim=1).values).nan_to_num(0.0)
    eps = eps.clamp(min=MEDIAN_EPS_MIN).unsqueeze(1).expand(ok.shape)
    if grad_std is None:
        return eps
    safe, has = nb.clamp(min=0), (nb >= 0).unsqueeze(0)
    g = torch.where(ok, grad_std.double(), torch.nan)[:, safe]  # (B, N, k)
    g = torch.where(has & ok[:, safe], g, torch.nan)
    g_nb = nanmedian_rows(g).nan_to_num(0.0)
    return torch.hypot(eps, MEDIAN_EPS_STD * g_nb * reach)


def _grid_neighbours(grid, k: int, reach: float) -> Tensor:
    """(N, k) the nearest ``k`` other points of a regular grid (:func:`detect_grid`) within
    ``reach`` times the grid's smaller step, nearest first (-1 where fewer)."""
    ix, iy = torch.tensor(grid.ix, dtype=torch.long), torch.tensor(grid.iy, dtype=torch.long)
    n = ix.shape[0]
    table = torch.full((grid.ny, grid.nx), -1, dtype=torch.long)
    table[iy, ix] = torch.arange(n)
    step = min(grid.sx, grid.sy)
    rx, ry = int(reach * step / grid.sx), int(reach * step / grid.sy)
    dy, dx = torch.meshgrid(torch.arange(-ry, ry + 1), torch.arange(-rx, rx + 1), indexing="ij")
    dist = torch.hypot(dx * grid.sx, dy * grid.sy).flatten()
    keep = (dist > 0) & (dist <= reach * step * (1 + 1e-9))
    order = torch.argsort(dist[keep], stable=True)
    ox, oy = dx.flatten()[keep][order], dy.flatten()[keep][order]  # nearest first

    def candidates(rows, m):  # (R, m) the points at the nearest m offsets, -1: none
        cx, cy = ix[rows].unsqueeze(1) + ox[:m], iy[rows].unsqueeze(1) + oy[:m]
        inside = (cx >= 0) & (cx < grid.nx) & (cy >= 0) & (cy < grid.ny)
        return torch.where(inside, table[cy.clamp(0, grid.ny - 1), cx.clamp(0, grid.nx - 1)],
                           -1)

    # where the nearest k offsets all hold a point (the grid's interior) they are the answer
    if ox.shape[0] >= k:
        out = candidates(slice(None), k)
        short = torch.nonzero((out < 0).any(1)).flatten()
        if short.numel() == 0:
            return out
    else:
        out, short = torch.full((n, k), -1, dtype=torch.long), torch.arange(n)
    cand = candidates(short, ox.shape[0])
    # the valid ones, nearest first: each to its place among the valid ones of its row (a
    # cumulative count, not a sort), the rest and those beyond k to a spare column
    valid = cand >= 0
    pos = torch.cumsum(valid, 1) - 1
    pos = torch.where(valid & (pos < k), pos, k)
    some = torch.full((short.numel(), k + 1), -1, dtype=torch.long)
    some.scatter_(1, pos, torch.where(valid, cand, -1))
    out[short] = some[:, :k]
    return out


def nanmedian_rows(x: Tensor) -> Tensor:
    """The median along the last dim over the values that are not NaN (the lower middle one
    for an even count; NaN where none): ``torch.nanmedian``'s, natively on the CPU for the
    short rows of the neighbour tests (~6x faster: 1.5 against 9 ms for 155,000 rows of 8)."""
    if dispatch.nanmedian(x) == "native":
        return native.nanmedian(x)
    return torch.nanmedian(x, dim=-1).values


#: :func:`carried_neighbours` fits the plane of the neighbours' gradients at every row where
#: it has at most this many (B x N: a lost point's guess), not only where it is needed (one
#: host read fewer; a row's plane does not depend on the others); beyond, where its caller
#: asks for no read (``every_row``: a GPU's rounds)
PLANE_EVERY_ROW = 4096


def carried_neighbours(values: Tensor, valid: Tensor, nb: Tensor, points: Tensor | None = None,
                       gradients: Tensor | None = None, at: Tensor | None = None,
                       every_row: bool = False) -> Tensor:
    """(B, N, k, C): the ``valid`` (B, N) neighbours ``nb`` (N, k) of every point, their
    (B, N, C) ``values`` carried to the point by ``gradients`` (B, N, C, 2) (d/dx, d/dy of
    each component; positions ``points`` (N, 2) px), NaN where there is no valid neighbour.
    Without gradients the neighbours' values as they are. ``at`` (M,) long: only those
    points, (B, M, k, C) (the same numbers as the rows ``at`` of the whole answer).

    The carry is the trapezoid rule: the mean of the neighbour's gradient and the gradient at
    the point, so a quadratic field (a strain that changes along the specimen) is carried
    exactly; carried by its own gradient alone, every neighbour misses the point by half the
    curvature times the squared distance, all to the same side (hourglass neck: 0.2-0.3 px,
    far above the noise). The gradient at the point is its own where that is like its
    neighbours' (the point being judged, or a lost one, may be wrong), else the plane fitted
    to its valid neighbours' gradients (:func:`_gradient_at`): fitted at every row where there
    are at most :data:`PLANE_EVERY_ROW` or with ``every_row`` (no host read; the same
    numbers), else only at the rows that need it (one read)."""
    if at is not None:
        nb = nb[at]
    n = nb.shape[0]
    safe, has = nb.clamp(min=0), (nb >= 0).view(1, n, -1)
    use = valid[:, safe] & has  # (B, N, k)
    v = torch.where(valid.unsqueeze(-1), values.double(), torch.nan)
    vn = v[:, safe]  # (B, N, k, C)
    if points is not None and gradients is not None:
        p = points.double()
        d = (p[at if at is not None else slice(None)].unsqueeze(1) - p[safe]).view(1, n, -1, 1, 2)
        g = gradients.double()
        gs = g[:, safe]  # (B, N, k, C, 2)
        if at is not None:
            g, valid = g[:, at], valid[:, at]
        use5 = use.view(*use.shape, 1, 1)
        gn = torch.where(use5, gs, 0.0)
        # the point's own gradient where it is one of its neighbours' (within 3 of their
        # median absolute deviations from their median, + GRADIENT_TOL): no extrapolation
        # noise at edges and corners, and a wrong point's wrong gradient is not used
        gm = torch.where(use5, gs, torch.nan).permute(0, 1, 3, 4, 2).contiguous()  # (B,N,C,2,k)
        med = nanmedian_rows(gm)
        mad = nanmedian_rows((gm - med.unsqueeze(-1)).abs_())
        own = valid.view(*valid.shape, 1, 1) & ((g - med).abs() <= 3.0 * mad + GRADIENT_TOL)
        g_at = g.clone(memory_format=torch.contiguous_format)  # the gradient at each point
        fit = ~own.flatten(-2).all(-1)  # (B, N): the plane fit of the neighbours is needed
        if every_row or fit.numel() <= PLANE_EVERY_ROW:  # the plane at all (no host read)
            g_at = torch.where(own, g, _gradient_at(gn, use, d.view(1, n, -1, 2)))
            at_fit = fit.new_empty(0)
        else:
            at_fit = torch.nonzero(fit.reshape(-1)).flatten()  # one index for all (one read)
        if at_fit.numel():

            def rows(t: Tensor) -> Tensor:  # (M, ...) the (B, N, ...) rows that need it
                return t.reshape(-1, *t.shape[2:])[at_fit]
            dd = rows(d.view(1, n, -1, 2).expand(g.shape[0], -1, -1, -1))  # (M, k, 2)
            plane = _gradient_at(rows(gn).unsqueeze(0), rows(use).unsqueeze(0),
                                 dd.unsqueeze(0))[0]
            g_at.view(-1, *g_at.shape[2:])[at_fit] = torch.where(rows(own), rows(g), plane)
        vn = vn + (0.5 * (torch.nan_to_num(gn) + g_at.unsqueeze(2)) * d).sum(-1)
    return torch.where(use.unsqueeze(-1), vn, torch.nan)


def _gradient_at(gn: Tensor, use: Tensor, d: Tensor) -> Tensor:
    """(B, N, C, 2) the gradients at the points: a plane in position fitted by least squares
    to the neighbours' gradients ``gn`` (B, N, k, C, 2) where ``use`` (B, N, k), at offsets
    ``-d`` (1, N, k, 2) px from the point (exact for a linear gradient field, at edges too);
    its slopes are damped (by 1e-3 of the mean squared offset) so that neighbours on one
    line, or a single one, give their mean."""
    w = use.double()
    a = torch.cat([torch.ones_like(d[..., :1]), -d], -1).expand(w.shape[0], -1, -1, -1)
    m = torch.einsum("bnk,bnki,bnkj->bnij", w, a, a)  # (B, N, 3, 3)
    scale = (w * d.square().sum(-1)).sum(-1) / w.sum(-1).clamp(min=1.0)
    damp = torch.ones(3, dtype=m.dtype, device=m.device)  # (0, 1, 1), made on the device
    damp[0] = 0.0
    m = m + torch.diag_embed(1e-3 * scale.clamp(min=1e-12).unsqueeze(-1) * damp)
    m = m + torch.diag_embed((w.sum(-1) == 0).double().unsqueeze(-1) * (1.0 - damp))
    rhs = torch.einsum("bnk,bnki,bnkf->bnif", w, a, gn.flatten(-2))  # (B, N, 3, 2C)
    # (regular by its damping: solved without the error check, which waits for a GPU)
    coef = torch.linalg.solve_ex(m, rhs).result
    return coef[..., 0, :].view(gn.shape[0], gn.shape[1], *gn.shape[3:])


def _round_torch(v: Tensor, valid: Tensor, nb: Tensor, points: Tensor | None,
                 gradients: Tensor | None, eps: Tensor, every_row: bool = False
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """One round of :func:`median_test` on ``valid`` (B, N) points, eps (B, N) px: the
    normalised residual r (B, N) (NaN: no neighbour), the neighbours' scatter rm (B, N, C)
    (median absolute residual) and the number of neighbours (B, N) (``every_row``: as
    :func:`carried_neighbours`)."""
    vn = carried_neighbours(v, valid, nb, points, gradients, every_row=every_row)
    med = nanmedian_rows(vn.transpose(-1, -2))  # (B, N, C)
    rm = nanmedian_rows((vn - med.unsqueeze(2)).abs().transpose(-1, -2))  # (B, N, C)
    r = ((v - med).abs() / (rm + eps.unsqueeze(-1))).amax(-1)
    return r, rm, (~torch.isnan(vn[..., 0])).sum(-1)


def _round_native(v: Tensor, valid: Tensor, nb: Tensor, points: Tensor | None,
                  gradients: Tensor | None, eps: Tensor, every_row: bool = False
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_round_torch` by the native kernels (CPU): the same numbers at the ``valid``
    points (the others are never judged; their gradient is not fitted here). The
    gradient at each point is its own where the kernel finds it like its neighbours', else
    the plane fitted by :func:`_gradient_at` here (few points: edges, corners, outliers;
    the CPU's: reads, whatever ``every_row``)."""
    n = v.shape[1]
    if points is None or gradients is None:
        return native.neighbour_test(nb, valid, v, torch.zeros(n, 2, dtype=v.dtype), eps,
                                     None, None)
    g = gradients.double().contiguous()
    own = native.neighbour_own_gradient(nb, valid, g, GRADIENT_TOL)
    at = g
    fit = valid & ~own.flatten(-2).all(-1)
    if bool(fit.any()):
        at = g.clone()
        bi, ii = fit.nonzero(as_tuple=True)
        q = nb[ii].clamp(min=0)  # (M, k)
        use = (nb[ii] >= 0) & valid[bi.unsqueeze(1), q]
        gn = torch.where(use[..., None, None], g[bi.unsqueeze(1), q], 0.0)  # (M, k, C, 2)
        p = points.double()
        d = p[ii].unsqueeze(1) - p[q]  # (M, k, 2) to the point
        plane = _gradient_at(gn.unsqueeze(0), use.unsqueeze(0), d.unsqueeze(0))[0]
        at[bi, ii] = torch.where(own[bi, ii], g[bi, ii], plane)
    return native.neighbour_test(nb, valid, v, points.double(), eps, g, at)


def median_test(values: Tensor, valid: Tensor, nb: Tensor, eps: float | Tensor,
                points: Tensor | None = None, gradients: Tensor | None = None,
                min_neighbours: int = 3, rounds: int = MEDIAN_ROUNDS,
                until_done: bool = True) -> Tensor:
    """Normalised median test (module docstring) of (B, N, C) ``values`` (C components, e.g.
    u and v) over the neighbours ``nb`` (N, k); only ``valid`` (B, N) points count as
    neighbours or are judged. ``eps`` px: a number, (B,) one per row of ``values`` or (B, N)
    one per point (the noise of u plus that of the gradients carried over the neighbours'
    distance). With ``points`` (N, 2) px and ``gradients`` (B, N, C, 2) (d/dx, d/dy of each
    component), each neighbour's value is carried to the point first
    (:func:`carried_neighbours`), so linear and quadratic fields pass.

    A bad point must not condemn its good neighbours: the test is iterated (at most
    ``rounds`` times): each round flags only the outliers that are the worst of the outliers
    among their neighbours, and the next round judges the others again without the points
    flagged so far. A point whose carried neighbours (outliers excluded) scatter (median
    absolute residual) by more than ``MEDIAN_SCATTER`` times ``eps`` is an outlier too: no
    smooth field to judge it by. ``until_done``: the rounds stop at the first that flags
    no point (one host read a round); False: all ``rounds`` run, no read (a round that
    flags none changes nothing: the same answer; the gradients' planes fitted at every
    point, :func:`carried_neighbours`'s ``every_row``). Returns (B, N) bool outliers (never a
    point with fewer than ``min_neighbours`` valid neighbours)."""
    b = values.shape[0]
    v = values.double()
    eps_t = torch.as_tensor(eps, dtype=torch.float64, device=values.device)
    if eps_t.dim() == 1:  # per row of values
        eps_t = eps_t.view(b, 1, 1)
    elif eps_t.dim() == 2:  # per point
        eps_t = eps_t.unsqueeze(-1)
    safe, has = nb.clamp(min=0), (nb >= 0).unsqueeze(0)
    out = torch.zeros_like(valid)
    fast = dispatch.neighbour_test(v, eps_t, nb.shape[1], points, gradients) == "native"
    round_ = _round_native if fast else _round_torch  # the same numbers (native ~4x faster)
    eps_bn = (eps_t if eps_t.dim() else eps_t.view(1, 1, 1)).expand(b, v.shape[1], 1)[..., 0]
    for i in range(max(1, rounds)):
        r, rm, count = round_(v, valid & ~out, nb, points, gradients, eps_bn,
                              every_row=not until_done)
        judged = valid & ~out & (count >= min_neighbours)
        cand = judged & (r > MEDIAN_THRESHOLD)
        if i == rounds - 1 or (until_done and not bool(cand.any())):
            out |= cand
            break
        score = torch.where(cand, r, -torch.inf)
        worst = torch.where(has, score[:, safe], -torch.inf).amax(-1)  # (B, N)
        out |= cand & (score >= worst)  # the worst among its neighbours
    wild = judged & ~out & (rm > MEDIAN_SCATTER * eps_t).any(-1)
    return out | wild
