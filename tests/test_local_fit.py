"""Local polynomial fits over scattered POIs (analysis.local_fit): exact on fields of their
degree, the variance of a fitted value as the overlap of subset windows predicts it (checked
by Monte Carlo), and the plane test that finds curvature."""

from __future__ import annotations

import pytest
import torch

from torch_stsdic.analysis.local_fit import local_fit, local_fit_weights, overlap_correlation


def _grid(step: float = 10.0, n: int = 15) -> torch.Tensor:
    xs = torch.arange(n, dtype=torch.float64) * step
    return torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)


def test_fits_reproduce_fields_of_their_degree():
    pts = _grid()
    x, y = pts[:, 0], pts[:, 1]
    plane = 0.3 + 0.01 * x - 0.02 * y
    quad = plane + 1e-4 * x * x - 2e-4 * x * y + 3e-4 * y * y
    fit = local_fit_weights(pts, 25, 21)
    assert torch.allclose(fit.apply(1, plane), plane, atol=1e-10)
    slopes = fit.apply_slopes(1, plane)
    assert torch.allclose(slopes[:, 0], torch.full_like(x, 0.01), atol=1e-10)
    assert torch.allclose(slopes[:, 1], torch.full_like(x, -0.02), atol=1e-10)
    assert torch.allclose(fit.apply(2, quad), quad, atol=1e-9)
    # the plane misses curvature: its value is off where the quadratic's is not
    assert float((fit.apply(1, quad) - quad).abs().max()) > 1e-3


def test_invalid_points_get_no_weight():
    pts = _grid()
    valid = torch.ones(len(pts), dtype=torch.bool)
    valid[::7] = False
    fit = local_fit_weights(pts, 25, 21, valid=valid)
    bad = ~valid
    cols = bad[fit.index] & fit.posed[1][:, None]
    assert float(fit.weights[1][cols].abs().max()) < 1e-12
    vals = torch.where(valid, 1.0 + 0.01 * pts[:, 0], torch.nan)
    # NaN values of invalid neighbours do not leak into the fits (weight exactly 0 times NaN
    # would): the caller zeroes them first
    out = fit.apply(1, torch.nan_to_num(vals))
    assert torch.allclose(out[valid], vals[valid], atol=1e-9)


def test_overlap_correlation():
    off = torch.tensor([[0.0, 0.0], [10.5, 0.0], [21.0, 3.0], [5.25, 5.25]])
    want = torch.tensor([1.0, 0.5, 0.0, 0.75 * 0.75])
    assert torch.allclose(overlap_correlation(off, 21), want)


def test_variance_factor_matches_monte_carlo():
    """Values whose errors are window averages of white noise (correlated as the windows
    overlap): the empirical variance of the plane's value over one value's equals
    w^T R w (within 8 %, 1500 draws; it is 0.144 at step 10, subset 21, 25 neighbours,
    against 0.04 for independent values)."""
    pts = _grid(step=10.0, n=9)
    fit = local_fit_weights(pts, 25, 21)
    g = torch.Generator().manual_seed(1)
    size = 10 * 8 + 21 + 2
    noise = torch.randn(1500, 1, size, size, generator=g, dtype=torch.float64)
    box = torch.nn.functional.avg_pool2d(noise, 21, stride=1)[:, 0]  # (R, H', W')
    ij = pts.long()
    vals = box[:, ij[:, 1], ij[:, 0]]  # (R, N): each POI's window average
    centre = 4 * 9 + 4
    fitted = fit.apply(1, vals)[:, centre]
    measured = float(fitted.var() / vals[:, centre].var())
    predicted = float(fit.variance_factor(fit.weights[1])[centre])
    assert predicted == pytest.approx(0.144, abs=0.01)
    assert measured == pytest.approx(predicted, rel=0.08)


def _window_noise(pts: torch.Tensor, sigma: float, seed: int) -> torch.Tensor:
    """(2, N) errors of the POIs' 21 px windows averaging white noise (correlated as the
    windows overlap, like DIC's), scaled to std ``sigma``."""
    g = torch.Generator().manual_seed(seed)
    size = int(pts.max()) + 23
    box = torch.nn.functional.avg_pool2d(
        torch.randn(2, 1, size, size, generator=g, dtype=torch.float64), 21, stride=1)[:, 0]
    ij = pts.long()
    vals = box[:, ij[:, 1], ij[:, 0]]
    return sigma * vals / vals.std()


def test_plane_test_keeps_planes_and_finds_curvature():
    pts = _grid(n=21)
    x, y = pts[:, 0] - 100, pts[:, 1] - 100
    sigma = 0.01
    noise = _window_noise(pts, sigma, 2)
    fit = local_fit_weights(pts, 25, 21, degrees=(1, 2, 3))
    var = torch.full((2, len(pts)), sigma ** 2, dtype=torch.float64)
    flat = torch.stack([0.002 * x, -0.001 * y]) + noise
    keep, factor = local_fit(fit, flat, var, z_limit=5.0)
    assert float(keep.double().mean()) > 0.97
    assert float(factor[keep].median()) == pytest.approx(0.144, abs=0.02)
    bump = torch.exp(-(x ** 2 + y ** 2) / (2 * 30.0 ** 2))
    keep_b, _ = local_fit(fit, flat + torch.stack([bump, 0.5 * bump]), var, z_limit=5.0)
    centre = (x.abs() < 15) & (y.abs() < 15)
    assert not bool(keep_b[centre].any())
    assert bool(keep_b[(x.abs() > 90) | (y.abs() > 90)].double().mean() > 0.9)
    # the quadratic follows the bump's centre where the plane does not
    keep_q, _ = local_fit(fit, flat + torch.stack([bump, 0.5 * bump]), var, degree=2,
                          z_limit=5.0)
    assert float(keep_q.double().mean()) > float(keep_b.double().mean())


def test_residuals_find_a_jump_the_fitted_values_miss():
    """A step of 1.5 px (a crack) between two columns of POIs: the plane's and the
    quadratic's values at a POI next to it can agree (both average across the step), the
    residuals cannot (z about 80 next to the step, below 5 elsewhere)."""
    pts = _grid(n=15)
    sigma = 0.01
    vals = _window_noise(pts, sigma, 3) + torch.stack(
        [1.5 * (pts[:, 0] > 70).double(), 0.8 * (pts[:, 0] > 70).double()])
    fit = local_fit_weights(pts, 25, 21, degrees=(1, 2, 3))
    var = torch.full_like(vals, sigma ** 2)
    z = fit.residual_z(1, vals, var).amax(0)
    near = (pts[:, 0] >= 60) & (pts[:, 0] <= 90)  # neighbourhoods (+-20 px) across it
    far = (pts[:, 0] <= 40) | (pts[:, 0] >= 110)
    assert float(z[near].min()) > 20 and float(z[far].max()) < 5
    keep, _ = local_fit(fit, vals, var, z_limit=5.0)
    assert not bool(keep[near].any())


def _direct_z(fit, degree: int, vals: torch.Tensor, var: torch.Tensor):
    """The tests written out with the (k, k) matrices: the residual operator ``(I - H)``
    (rows of unused neighbours 0), its covariance's diagonal ``(I - H) R (I - H)^T``, the
    value difference's weights and their ``d^T R d``."""
    n, k = fit.index.shape
    scale = float(fit.offsets.norm(dim=-1).max())
    from torch_stsdic.analysis.local_fit import _design

    a = _design(fit.offsets / scale, degree) * fit.used[..., None]
    h = a @ torch.linalg.inv(a.transpose(1, 2) @ a) @ a.transpose(1, 2)
    op = (torch.eye(k, dtype=torch.float64) - h) * fit.used[..., None]
    r = overlap_correlation(fit.offsets[:, :, None] - fit.offsets[:, None], fit.subset_size)
    cov = torch.einsum("njk,nkl,njl->nj", op, r, op).clamp(min=1e-12)
    nb = var[:, fit.index].mean(-1)
    res = torch.einsum("njk,cnk->cnj", op, vals[:, fit.index])
    rz = torch.where(fit.used[None] > 0, res.abs() / (cov[None] * nb[..., None]).sqrt(),
                     0.0).amax(-1)
    d = fit.weights[degree] - fit.weights[degree + 1]
    var_d = torch.einsum("nj,njk,nk->n", d, r, d)
    vz = (fit.apply(degree, vals) - fit.apply(degree + 1, vals)).abs() / (var_d * nb).sqrt()
    return vz, rz, torch.einsum("nj,njk,nk->n", fit.weights[degree], r, fit.weights[degree])


def test_one_pass_tests_equal_the_tests_written_out():
    """LocalFit.test_z (every degree from one pass: nested designs, the residuals' variance
    as diag(R - 2 H R + H R H) from A^T R, A^T R A) gives the z of the tests written out
    with the (k, k) matrices, an invalid POI among the neighbours included, and the
    fitted value's factor w^T R w; one value of variance (1, N) serves every row."""
    g = torch.Generator().manual_seed(4)
    pts = _grid(n=12) + torch.rand(144, 2, generator=g, dtype=torch.float64) * 4
    valid = torch.ones(144, dtype=torch.bool)
    valid[[30, 77]] = False
    fit = local_fit_weights(pts, 25, 21, valid=valid, degrees=(1, 2, 3))
    x, y = pts[:, 0] - 60, pts[:, 1] - 60
    vals = torch.stack([1e-4 * x * x, 0.01 * y, 1e-6 * x ** 3]) + 0.01 * torch.randn(
        3, 144, generator=g, dtype=torch.float64)
    var = 1e-4 * (1 + torch.rand(1, 144, generator=g, dtype=torch.float64))
    tests = fit.test_z(vals, var, (1, 2))
    for d in (1, 2):
        vz, rz, factor = _direct_z(fit, d, vals, var.expand(3, -1))
        ok = fit.posed[d] & fit.posed[d + 1]
        assert bool(ok.all())
        torch.testing.assert_close(tests[d].value_z, vz, rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(tests[d].residual_z, rz, rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(tests[d].factor, factor, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(fit.value_factors((d,))[d], factor, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(fit.residual_z(d, vals, var), rz, rtol=1e-7, atol=1e-9)
    # the curved rows fail the plane somewhere, the noise-only row passes nearly everywhere
    passes = tests[1].passes(5.0)
    assert float(passes[1].double().mean()) > 0.9 and not bool(passes[2].all())
    # the correlation made in place is overlap_correlation of the pairwise offsets
    off = fit.offsets[:5]
    torch.testing.assert_close(fit.correlation(slice(0, 5)),
                               overlap_correlation(off[:, :, None] - off[:, None], 21.0))


def test_fits_shared_by_neighbourhood_pattern_equal_the_fits_of_every_poi():
    """A grid's POIs whose neighbourhoods have one shape (the same offsets and used
    neighbours, listed alike) share one pattern, and the fits' geometry is worked out once
    a pattern: the tests, factors, map weights and stored weights equal those worked out at
    every POI (a fit without patterns), invalid POIs and the grid's edges included."""
    import dataclasses

    g = torch.Generator().manual_seed(9)
    pts = _grid(n=20)
    valid = torch.ones(400, dtype=torch.bool)
    valid[[42, 211, 305]] = False
    fit = local_fit_weights(pts, 25, 21, valid=valid, degrees=(1, 2, 3))
    # every POI lists its neighbours as its pattern's first POI does: equal offsets, used
    rep = fit.reps[fit.pattern]
    assert torch.equal(fit.offsets, fit.offsets[rep]) and torch.equal(fit.used, fit.used[rep])
    assert bool((fit.index[:, 0] == torch.arange(400)).all())  # itself first
    # the interior's 12 x 12 POIs minus those next to an invalid one: a handful of patterns
    assert fit.reps.numel() < 120
    plain = dataclasses.replace(fit, pattern=None, reps=None)
    x, y = pts[:, 0] - 100, pts[:, 1] - 100
    vals = torch.stack([1e-4 * x * x, 0.01 * y]) + 0.01 * torch.randn(
        2, 400, generator=g, dtype=torch.float64)
    var = 1e-4 * (1 + torch.rand(1, 400, generator=g, dtype=torch.float64))
    shared, each = fit.test_z(vals, var, (1, 2)), plain.test_z(vals, var, (1, 2))
    rows = torch.tensor([0, 5, 41, 42, 43, 200, 399])
    for d in (1, 2):
        torch.testing.assert_close(shared[d].value_z, each[d].value_z, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(shared[d].residual_z, each[d].residual_z, rtol=1e-9,
                                   atol=1e-12)
        torch.testing.assert_close(shared[d].factor, each[d].factor, rtol=1e-10, atol=1e-14)
        torch.testing.assert_close(fit.value_factors((d,))[d], plain.value_factors((d,))[d])
        torch.testing.assert_close(fit.map_weights(d, rows), plain.map_weights(d, rows))
        torch.testing.assert_close(fit.map_weights(d, slice(0, 400))[..., 0],
                                   plain.map_weights(d, slice(0, 400))[..., 0])
    # the stored weights (made once a pattern) are those of every POI's own fit
    torch.testing.assert_close(fit.weights[1], plain.map_weights(1, slice(0, 400))[..., 0])
    torch.testing.assert_close(fit.slopes[2], plain.map_weights(2, slice(0, 400))[..., 1:3])
    for d in (1, 2, 3):  # posed at the edges' shapes too
        assert torch.equal(fit.posed[d], fit.posed[d][rep])
