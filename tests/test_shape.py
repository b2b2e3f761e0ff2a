"""Shape functions and windows: basis, Jacobians against finite differences, IC composition."""

import pytest
import torch

from torch_stsdic.core.shape import AffineShape, QuadraticShape, make_shape
from torch_stsdic.core.window import make_window


def _grid(dtype=torch.float64):
    dx = torch.tensor([-3.0, 0.0, 2.0, 5.0], dtype=dtype)
    dy = torch.tensor([1.0, -4.0, 0.0, 2.0], dtype=dtype)
    dt = torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0], dtype=dtype)
    return dx, dy, dt


def test_affine_names_and_counts():
    s = AffineShape()
    assert s.param_names == ("u", "ux", "uy", "ut", "v", "vx", "vy", "vt")
    assert s.n_params == 8
    assert s.spatial().param_names == ("u", "ux", "uy", "v", "vx", "vy")
    q = QuadraticShape()
    assert q.n_params == 14 and q.spatial().n_params == 12
    assert q.index("vt") == 13


@pytest.mark.parametrize("name", ["affine", "quadratic"])
def test_displacement_formula(name):
    s = make_shape(name)
    dx, dy, dt = _grid()
    p = torch.randn(3, s.n_params, dtype=torch.float64)
    u, v = s.displacement(p, s.spatial_basis(dx, dy), dt)
    names = s.param_names
    P = {n: p[:, i].view(-1, 1, 1) for i, n in enumerate(names)}
    X, Y, T = dx.view(1, 1, -1), dy.view(1, 1, -1), dt.view(1, -1, 1)
    ue = P["u"] + P["ux"] * X + P["uy"] * Y + P["ut"] * T
    ve = P["v"] + P["vx"] * X + P["vy"] * Y + P["vt"] * T
    if name == "quadratic":
        ue = ue + 0.5 * P["uxx"] * X**2 + P["uxy"] * X * Y + 0.5 * P["uyy"] * Y**2
        ve = ve + 0.5 * P["vxx"] * X**2 + P["vxy"] * X * Y + 0.5 * P["vyy"] * Y**2
    assert torch.allclose(u, ue) and torch.allclose(v, ve)


@pytest.mark.parametrize("name", ["affine", "quadratic"])
def test_jacobian_against_finite_differences(name):
    # dU/dp is the basis (block diagonal): check by central differences
    s = make_shape(name)
    dx, dy, dt = _grid()
    b = s.basis(dx, dy, dt)
    sp = s.spatial_basis(dx, dy)
    p = torch.randn(1, s.n_params, dtype=torch.float64)
    k = s.n_basis
    e = 1e-6
    for j in range(s.n_params):
        dp = torch.zeros_like(p)
        dp[0, j] = e
        up, vp = s.displacement(p + dp, sp, dt)
        um, vm = s.displacement(p - dp, sp, dt)
        du, dv = (up - um) / (2 * e), (vp - vm) / (2 * e)
        exp_u = b[..., j] if j < k else torch.zeros_like(b[..., 0])
        exp_v = b[..., j - k] if j >= k else torch.zeros_like(b[..., 0])
        assert torch.allclose(du[0], exp_u, atol=1e-8)
        assert torch.allclose(dv[0], exp_v, atol=1e-8)


def test_affine_inverse_composition_is_exact():
    s = AffineShape()
    dx, dy, dt = _grid()
    sp = s.spatial_basis(dx, dy)
    g = torch.Generator().manual_seed(0)
    p = torch.randn(4, 8, generator=g, dtype=torch.float64) * 0.1
    dp = torch.randn(4, 8, generator=g, dtype=torch.float64) * 0.05
    new = s.compose_inverse(p, dp)
    # W_new(W_dp(z)) must equal W_p(z) for every subset pixel z and frame time
    ud, vd = s.displacement(dp, sp, dt)
    zx, zy = dx + ud, dy + vd  # W_dp(z) in local coordinates, (N, T, S)
    un, vn = [], []
    for t in range(dt.numel()):
        bt = s.basis(zx[:, t].reshape(-1), zy[:, t].reshape(-1), dt[t : t + 1])  # (1, N*S, K)
        bt = bt.reshape(4, -1, 4)
        un.append((new[:, :4].unsqueeze(1) * bt).sum(-1))
        vn.append((new[:, 4:].unsqueeze(1) * bt).sum(-1))
    xn = zx + torch.stack(un, 1)
    yn = zy + torch.stack(vn, 1)
    up, vp = s.displacement(p, sp, dt)
    assert torch.allclose(xn, dx + up, atol=1e-12)
    assert torch.allclose(yn, dy + vp, atol=1e-12)


def test_quadratic_has_no_exact_composition():
    assert QuadraticShape().compose_inverse(torch.zeros(1, 14), torch.zeros(1, 14)) is None
    assert not QuadraticShape().inverse_compositional and AffineShape().inverse_compositional


@pytest.mark.parametrize("name", ["affine", "quadratic"])
def test_warp_and_increment_scale(name):
    s = make_shape(name)
    dx, dy, dt = _grid()
    sp = s.spatial_basis(dx, dy)
    p = torch.randn(2, s.n_params, dtype=torch.float64)
    px = torch.tensor([[10.0], [20.5]], dtype=torch.float64)
    py = torch.tensor([[3.0], [-1.0]], dtype=torch.float64)
    xs, ys = s.warp(p, px, py, dx, dy, sp, dt.expand(2, -1))
    u, v = s.displacement(p, sp, dt)
    assert torch.allclose(xs, px.unsqueeze(-1) + dx + u)
    assert torch.allclose(ys, py.unsqueeze(-1) + dy + v)
    # |dp * scale| bounds the largest pixel displacement change over subset and window
    scale = s.increment_scale(sp, dt.expand(2, -1))
    for j in range(s.n_params):
        dp = torch.zeros(2, s.n_params, dtype=torch.float64)
        dp[:, j] = 1.0
        du, dv = s.displacement(dp, sp, dt)
        assert torch.allclose(torch.maximum(du.abs(), dv.abs()).amax(dim=(1, 2)), scale[:, j])


@pytest.mark.parametrize("name,count", [("square", 441), ("circular", None), ("gaussian", 441)])
def test_windows(name, count):
    w = make_window(name, 21)
    off, wt = w.offsets_and_weights()
    assert off.shape[1] == 2 and wt.shape[0] == off.shape[0]
    assert off.abs().max() == 10
    if count:
        assert off.shape[0] == count
    else:
        assert 300 < off.shape[0] < 441
        assert ((off**2).sum(-1) <= 10.5**2).all()
    if name == "gaussian":
        assert wt.max() == 1.0 and wt.min() < 0.1


def test_bad_window_and_shape_names():
    with pytest.raises(ValueError, match="window"):
        make_window("hexagon", 21)
    with pytest.raises(ValueError, match="odd"):
        make_window("square", 20)
    with pytest.raises(ValueError, match="shape"):
        make_shape("cubic")
