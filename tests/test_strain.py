"""Tests of torch_stsdic.analysis.strain: plane-fit gradients, small / Green-Lagrange strain and
rates."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_stsdic.analysis.strain import (
    compute_strain,
    detect_grid,
    plane_fit_gradients,
    principal_strains,
)


def grid_points(nx: int = 12, ny: int = 9, step: float = 10.0, x0: float = 20.0, y0: float = 15.0):
    xs, ys = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def green(ux, uy, vx, vy):
    return (
        ux + 0.5 * (ux**2 + vx**2),
        vy + 0.5 * (uy**2 + vy**2),
        0.5 * (uy + vx + ux * uy + vx * vy),
    )


def ref_plane_fit(pts, vals, ok, i, h, step):
    """Reference slope at point i by np.linalg.lstsq over the square window of half-size h."""
    d = pts - pts[i]
    sel = ok & (np.abs(d[:, 0]) <= h * step + 1e-9) & (np.abs(d[:, 1]) <= h * step + 1e-9)
    a = np.stack([np.ones(sel.sum()), d[sel, 0], d[sel, 1]], axis=1)
    coef = np.linalg.lstsq(a, vals[sel], rcond=None)[0]
    return coef[1], coef[2]


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["small", "green"])
@pytest.mark.parametrize("method", ["grid", "knn"])
def test_homogeneous_exact_batched(kind, method):
    pts = grid_points()
    x, y = pts[:, 0], pts[:, 1]
    rng = np.random.default_rng(0)
    h = rng.normal(scale=0.05, size=(3, 4))  # 3 frames of (ux, uy, vx, vy)
    u = h[:, :1] * x + h[:, 1:2] * y + 5.0
    v = h[:, 2:3] * x + h[:, 3:4] * y - 2.0
    s = compute_strain(pts, u, v, kind=kind, method=method, return_gradients=True)
    assert isinstance(s["exx"], np.ndarray) and s["exx"].shape == (3, len(pts))
    for k, name in enumerate(["ux", "uy", "vx", "vy"]):
        np.testing.assert_allclose(s[name], np.broadcast_to(h[:, k : k + 1], u.shape), atol=1e-10)
    ux, uy, vx, vy = (h[:, k : k + 1] for k in range(4))
    if kind == "small":
        exp = (ux, vy, 0.5 * (uy + vx))
    else:
        exp = green(ux, uy, vx, vy)
    for name, e in zip(["exx", "eyy", "exy"], exp):
        np.testing.assert_allclose(s[name], np.broadcast_to(e, u.shape), atol=1e-10)


def test_rigid_rotation_has_zero_green_strain():
    pts = grid_points()
    th = 0.3
    x, y = pts[:, 0] - 50, pts[:, 1] - 40
    u = (np.cos(th) - 1) * x - np.sin(th) * y
    v = np.sin(th) * x + (np.cos(th) - 1) * y
    s = compute_strain(pts, u, v, kind="green")
    for k in ("exx", "eyy", "exy"):
        np.testing.assert_allclose(s[k], 0.0, atol=1e-12)
    small = compute_strain(pts, u, v, kind="small")
    assert np.allclose(small["exx"], np.cos(th) - 1)  # small strain is not rotation-invariant


@pytest.mark.parametrize("window", [3, 5, 7])
def test_quadratic_field_gradient_at_interior_points(window):
    pts = grid_points(nx=15, ny=13, step=4.0)
    x, y = pts[:, 0], pts[:, 1]
    u = 1e-3 * x**2 - 2e-3 * x * y + 5e-4 * y**2
    v = -3e-4 * x**2 + 1e-3 * x * y + 2e-3 * y**2
    gx, gy = plane_fit_gradients(pts, np.stack([u, v]), window=window)
    g = detect_grid(pts)
    h = window // 2
    inner = (g.ix >= h) & (g.ix < g.nx - h) & (g.iy >= h) & (g.iy < g.ny - h)
    np.testing.assert_allclose(gx[0, inner], (2e-3 * x - 2e-3 * y)[inner], atol=1e-12)
    np.testing.assert_allclose(gy[0, inner], (-2e-3 * x + 1e-3 * y)[inner], atol=1e-12)
    np.testing.assert_allclose(gx[1, inner], (-6e-4 * x + 1e-3 * y)[inner], atol=1e-12)
    np.testing.assert_allclose(gy[1, inner], (1e-3 * x + 4e-3 * y)[inner], atol=1e-12)
    # border points are finite (they use the neighbours that exist) but one-sided
    assert np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))


def test_holes_and_invalid_match_reference_lstsq():
    rng = np.random.default_rng(1)
    full = grid_points(nx=11, ny=10, step=5.0)
    keep = rng.random(len(full)) > 0.2  # holes in the grid (masked points)
    pts = full[keep]
    n = len(pts)
    vals = np.sin(pts[:, 0] / 13.0) + np.cos(pts[:, 1] / 7.0) * 0.5
    valid = rng.random(n) > 0.15
    vals_bad = vals.copy()
    vals_bad[~valid] = 1e6  # garbage at invalid points must not leak
    vals_bad[np.flatnonzero(valid)[:3]] = np.nan  # NaN counts as invalid too
    ok = valid & np.isfinite(vals_bad)
    for window in (3, 5):
        gx, gy = plane_fit_gradients(pts, vals_bad, window=window, valid=valid)
        assert detect_grid(pts) is not None
        n_checked = 0
        for i in range(n):
            if not ok[i]:
                assert np.isnan(gx[i]) and np.isnan(gy[i])
                continue
            if np.isnan(gx[i]):
                continue
            rx, ry = ref_plane_fit(pts, vals, ok, i, window // 2, 5.0)
            assert gx[i] == pytest.approx(rx, abs=1e-10)
            assert gy[i] == pytest.approx(ry, abs=1e-10)
            n_checked += 1
        assert n_checked > 0.5 * ok.sum()


def test_edges_use_existing_neighbours():
    pts = grid_points(nx=6, ny=5, step=3.0)
    vals = 0.1 * pts[:, 0] ** 2 + 0.3 * pts[:, 1]
    gx, gy = plane_fit_gradients(pts, vals, window=5)
    ok = np.ones(len(pts), bool)
    for i in (0, 5, 24, 29, 2):  # corners and an edge point
        rx, ry = ref_plane_fit(pts, vals, ok, i, 2, 3.0)
        assert gx[i] == pytest.approx(rx, abs=1e-10) and gy[i] == pytest.approx(ry, abs=1e-10)


@pytest.mark.parametrize("window", [3, 5])
def test_knn_path_matches_grid_path_on_grid(window):
    pts = grid_points(nx=14, ny=12, step=7.5, x0=3.2, y0=-4.0)
    frames = np.stack([np.sin(pts[:, 0] / (10 + f)) * np.cos(pts[:, 1] / 9) for f in range(3)])
    sg = compute_strain(pts, frames, 0.5 * frames[::-1], window=window, method="grid")
    sk = compute_strain(pts, frames, 0.5 * frames[::-1], window=window, method="knn")
    g = detect_grid(pts)
    h = window // 2
    inner = (g.ix >= h) & (g.ix < g.nx - h) & (g.iy >= h) & (g.iy < g.ny - h)
    for k in ("exx", "eyy", "exy"):
        np.testing.assert_allclose(sk[k][:, inner], sg[k][:, inner], atol=1e-10)


def test_scattered_points_linear_field_exact():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 300, size=(400, 2))
    assert detect_grid(pts) is None
    u = 0.02 * pts[:, 0] - 0.01 * pts[:, 1]
    v = 0.005 * pts[:, 0] + 0.03 * pts[:, 1]
    s = compute_strain(pts, u, v, kind="small", window=5)  # auto -> knn
    np.testing.assert_allclose(s["exx"], 0.02, atol=1e-10)
    np.testing.assert_allclose(s["eyy"], 0.03, atol=1e-10)
    np.testing.assert_allclose(s["exy"], -0.0025, atol=1e-10)


@pytest.mark.parametrize("kind", ["small", "green"])
def test_strain_rate_from_velocity(kind):
    pts = grid_points()
    x, y = pts[:, 0], pts[:, 1]
    h0 = np.array([0.02, -0.01, 0.015, 0.03])
    h1 = np.array([0.004, 0.002, -0.003, 0.001])  # dH/dt per frame

    def fields(t):
        hh = h0 + t * h1  # (F, 4)
        return hh[:, :1] * x + hh[:, 1:2] * y, hh[:, 2:3] * x + hh[:, 3:4] * y

    t = np.array([0.0, 1.0, 2.5])[:, None]
    u, v = fields(t)
    ut = np.broadcast_to(h1[0] * x + h1[1] * y, u.shape)
    vt = np.broadcast_to(h1[2] * x + h1[3] * y, u.shape)
    s = compute_strain(pts, u, v, ut=ut, vt=vt, kind=kind)
    dt = 1e-4  # E(t) is quadratic in t: the central difference is exact up to rounding
    sp = compute_strain(pts, *fields(t + dt), kind=kind)
    sm = compute_strain(pts, *fields(t - dt), kind=kind)
    for k in ("exx", "eyy", "exy"):
        fd = (sp[k] - sm[k]) / (2 * dt)
        np.testing.assert_allclose(s[k + "_rate"], fd, atol=1e-8)
    if kind == "small":
        np.testing.assert_allclose(s["exx_rate"], h1[0], atol=1e-12)
        np.testing.assert_allclose(s["exy_rate"], 0.5 * (h1[1] + h1[2]), atol=1e-12)


def test_too_few_neighbours_give_nan_without_crash():
    pts = grid_points(nx=8, ny=8, step=1.0)
    u = 0.1 * pts[:, 0]
    v = 0.2 * pts[:, 1]
    valid = np.zeros(len(pts), bool)
    valid[[0, 1]] = True  # two valid points: a line, no plane
    valid[[27, 28, 29]] = True  # three collinear points
    s = compute_strain(pts, u, v, valid=valid, window=3)
    assert np.all(np.isnan(s["exx"]))
    valid[35] = True  # (3, 4) makes (3,3),(4,3),(5,3),(3,4) non-collinear around (4,3)
    s = compute_strain(pts, u, v, valid=valid, window=3, kind="small")
    assert s["exx"][28] == pytest.approx(0.1) and s["eyy"][28] == pytest.approx(0.2)
    assert np.isnan(s["exx"][0]) and np.isnan(s["exx"][10])  # invalid centre -> NaN
    # a single row of points: collinear everywhere; tiny inputs
    row = np.stack([np.arange(6.0), np.zeros(6)], 1)
    assert np.all(np.isnan(compute_strain(row, row[:, 0], row[:, 0])["exx"]))
    for n in (1, 2):
        p = np.arange(2 * n, dtype=float).reshape(n, 2)
        assert np.all(np.isnan(compute_strain(p, np.zeros(n), np.zeros(n))["exy"]))
    s = compute_strain(pts, np.full((2, 64), np.nan), np.zeros((2, 64)))
    assert np.all(np.isnan(s["exx"]))


def test_min_points_and_require_center():
    pts = grid_points(nx=5, ny=5, step=2.0)
    u = 0.01 * pts[:, 0]
    valid = np.ones(25, bool)
    valid[12] = False  # centre point invalid
    s = compute_strain(pts, u, u * 0, valid=valid, window=3, kind="small")
    assert np.isnan(s["exx"][12])
    s = compute_strain(pts, u, u * 0, valid=valid, window=3, kind="small", require_center=False)
    assert s["exx"][12] == pytest.approx(0.01)
    s = compute_strain(pts, u, u * 0, window=3, min_points=4)
    assert np.isfinite(s["exx"][0])  # a corner has 4 points in its 3 x 3 window (itself included)
    s = compute_strain(pts, u, u * 0, window=3, min_points=5)
    assert np.isnan(s["exx"][0]) and np.isfinite(s["exx"][1])  # an edge point has 6


def test_torch_in_torch_out_dtype_and_autograd():
    pts = torch.as_tensor(grid_points(nx=6, ny=6, step=1.0))
    u = (0.01 * pts[:, 0]).float().repeat(2, 1).requires_grad_(True)
    v = torch.zeros(2, 36)
    s = compute_strain(pts, u, v, kind="green", valid=torch.ones(36, dtype=torch.bool))
    assert isinstance(s["exx"], torch.Tensor) and s["exx"].dtype == torch.float32
    assert s["exx"].shape == (2, 36)
    torch.testing.assert_close(s["exx"], torch.full((2, 36), 0.01 + 0.5e-4))
    s["exx"].sum().backward()
    assert u.grad is not None and torch.isfinite(u.grad).all()


def test_detect_grid():
    pts = grid_points(nx=7, ny=4, step=2.5, x0=1.25, y0=-3.0)
    g = detect_grid(pts)
    assert (g.nx, g.ny) == (7, 4) and g.sx == pytest.approx(2.5) and g.y0 == pytest.approx(-3.0)
    aniso = np.stack(np.meshgrid(np.arange(5) * 3.0, np.arange(4) * 8.0), -1).reshape(-1, 2)
    g = detect_grid(aniso[::-1])
    assert (g.sx, g.sy, g.nx, g.ny) == (3.0, 8.0, 5, 4)
    img = g.to_image(np.arange(20.0)[::-1])
    assert img.shape == (4, 5) and img[0, 0] == 0.0 and img[3, 4] == 19.0
    holed = pts[np.arange(len(pts)) % 3 != 0]
    assert detect_grid(holed) is not None
    assert detect_grid(np.concatenate([pts, pts[:1]])) is None  # duplicate point
    assert detect_grid(pts + np.random.default_rng(0).normal(0, 0.1, pts.shape)) is None


def test_principal_strains():
    e1, e2, th = principal_strains(np.array([0.0]), np.array([0.0]), np.array([0.01]))
    assert e1[0] == pytest.approx(0.01) and e2[0] == pytest.approx(-0.01)
    assert th[0] == pytest.approx(np.pi / 4)
    e1, e2, th = principal_strains(torch.tensor(0.02), torch.tensor(0.01), torch.tensor(0.0))
    assert float(e1) == pytest.approx(0.02) and float(th) == pytest.approx(0.0)


def test_argument_checks():
    pts = grid_points(nx=4, ny=4)
    z = np.zeros(16)
    with pytest.raises(ValueError, match="window"):
        compute_strain(pts, z, z, window=4)
    with pytest.raises(ValueError, match="kind"):
        compute_strain(pts, z, z, kind="log")
    with pytest.raises(ValueError, match="ut"):
        compute_strain(pts, z, z, ut=z)
    with pytest.raises(ValueError, match="N="):
        compute_strain(pts, np.zeros(15), np.zeros(15))
    with pytest.raises(ValueError, match="grid"):
        compute_strain(np.random.default_rng(0).random((16, 2)), z, z, method="grid")


def test_detect_grid_answers_again_from_the_points_bytes():
    ys, xs = np.meshgrid(np.arange(0.0, 50, 5), np.arange(3.0, 83, 8), indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel()], 1)
    g1 = detect_grid(pts)
    g2 = detect_grid(torch.from_numpy(pts.copy()))  # same points, another object: kept
    assert g1 is g2 and (g1.nx, g1.ny, g1.sx, g1.sy) == (10, 10, 8.0, 5.0)
    assert not g1.ix.flags.writeable and not g1.iy.flags.writeable
    moved = pts.copy()
    moved[0, 0] += 0.5  # off the grid now
    assert detect_grid(moved) is None
    assert detect_grid(pts[1:]) is not g1 and detect_grid(pts[1:]).nx == 10


def test_a_grid_is_found_again_from_the_same_tensor_without_a_copy(monkeypatch):
    """``detect_grid`` keeps its answer by the points' tensor (unchanged since): a block asks
    for its points' grid again without copying them to the host (a GPU waits for that); a
    tensor changed in place, or another one, is looked at again."""
    import torch_stsdic.analysis.strain as strain

    copies = []
    real = strain._as_numpy
    monkeypatch.setattr(strain, "_as_numpy", lambda a: copies.append(1) or real(a))
    ys, xs = torch.meshgrid(torch.arange(5.0) * 7 + 3, torch.arange(6.0) * 7 + 1,
                            indexing="ij")
    pts = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
    g = detect_grid(pts)
    assert g is not None and (g.nx, g.ny, g.sx) == (6, 5, 7.0) and len(copies) == 1
    assert detect_grid(pts) is g and len(copies) == 1
    pts[3, 0] += 2.5  # off the grid now
    assert detect_grid(pts) is None and len(copies) == 2
    assert detect_grid(pts.clone()) is None and len(copies) == 3
