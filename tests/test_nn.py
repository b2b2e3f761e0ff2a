"""torch_stsdic.nn: the differentiable STSDIC module (implicit gradients) and dense helpers."""

from __future__ import annotations

import warnings

import pytest
import torch

from torch_stsdic import DICConfig, SubsetSolver, grid_points, solve_window
from torch_stsdic.core.status import Status
from torch_stsdic.nn import STSDIC, STSDICOutput, dense_to_points, points_to_dense
from torch_stsdic.synth import Translation, make_speckle, render_series

SIZE = (41, 41)
POINTS = [[15.0, 15.0], [25.0, 20.0], [20.0, 26.0]]


def _sequence(seed: int, u0=0.3, v0=-0.2, ut=0.1, vt=0.05, noise=2.0):
    pat = make_speckle(SIZE, seed=seed)
    motion = Translation(u0=u0, v0=v0, ut=ut, vt=vt)
    # reference = the undeformed pattern: truth u = u0 + ut t (centre frame t = 2)
    return render_series(pat, SIZE, motion, torch.tensor([1.0, 2.0, 3.0]),
                         noise_sigma=noise, seed=seed + 100, reference_time=None)


@pytest.fixture(scope="module")
def seq():
    ref, frames = _sequence(0)
    return ref, frames, torch.tensor(POINTS, dtype=torch.float64)


@pytest.fixture(scope="module")
def fields():
    g = torch.Generator().manual_seed(3)
    basis = torch.randn(1, 4, *SIZE, generator=g, dtype=torch.float64)
    return torch.nn.functional.avg_pool2d(basis, 5, 1, 2)[0] * 5.0  # smooth brightness fields


def _cfg(**kw) -> DICConfig:
    base = dict(subset_size=13, m=1, tol=1e-12, max_iter=300)
    base.update(kw)
    return DICConfig(**base)


# ------------------------------------------------------------------------------------------
def test_forward_matches_solve_window(seq):
    ref, frames, pts = seq
    for form in ("joint", "auto", "joint+average"):
        cfg = _cfg(formulation=form, tol=1e-6)
        out = STSDIC(cfg).forward_full(ref[None], frames[None], pts)
        sol = solve_window(ref, frames, pts, cfg)
        assert isinstance(out, STSDICOutput)
        assert out.disp.shape == (1, 3, 2) and out.vel.shape == (1, 3, 2)
        assert out.status.shape == (1, 3) and out.params.shape == (1, 3, 8)
        torch.testing.assert_close(out.disp[0, :, 0], sol.u, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.disp[0, :, 1], sol.v, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.vel[0, :, 0], sol.ut, rtol=0, atol=1e-12)
        torch.testing.assert_close(out.vel[0, :, 1], sol.vt, rtol=0, atol=1e-12)
        assert torch.equal(out.status[0], sol.status)
        # the truth at the centre frame (t = 2): u = 0.3 + 0.1 * 2, v = -0.2 + 0.05 * 2
        # measured at most 0.054 (u), 0.021 (v), 0.017 (ut), 0.0085 (vt); bands about 2x
        # (noise 2, subset 13, 3 points): v = 0 or a velocity of 0 fails
        assert (out.disp[0, :, 0] - 0.5).abs().max() < 0.1
        assert (out.disp[0, :, 1] + 0.1).abs().max() < 0.05
        assert (out.vel[0, :, 0] - 0.1).abs().max() < 0.04
        assert (out.vel[0, :, 1] - 0.05).abs().max() < 0.02


@pytest.mark.parametrize("form", ["joint", "average", "joint+average"])
def test_gradcheck_brightness_fields_and_points(seq, fields, form):
    """Implicit gradient == finite differences of the converged solver (float64)."""
    ref, frames, pts = seq
    mod = STSDIC(_cfg(formulation=form))

    def fn(theta, dpts):
        r = ref + (theta[:2, None, None] * fields[:2]).sum(0)
        f = frames + (theta[2:, None, None] * fields[2:]).sum(0)
        out = mod.forward_full(r[None], f[None], pts + dpts)
        return torch.cat([out.disp.reshape(-1), out.vel.reshape(-1)])

    theta = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    dpts = torch.zeros(2, dtype=torch.float64, requires_grad=True)  # moves all POIs
    assert torch.autograd.gradcheck(fn, (theta, dpts), eps=1e-6, atol=1e-6, rtol=1e-4)
    jac = torch.autograd.functional.jacobian(fn, (theta, dpts))
    assert jac[0].abs().max() > 1e-3  # a non-trivial dependence was checked


def test_gradcheck_pixels_quadratic_ssd(seq):
    """A few raw pixels of the reference and of each frame; quadratic shape (forward-additive
    joint stage) with the SSD criterion."""
    ref, frames, pts = seq
    mod = STSDIC(_cfg(formulation="joint+average", shape="quadratic", criterion="ssd"))
    rows = torch.tensor([14, 21])
    cols = torch.tensor([16, 24])

    def fn(ref_px, frame_px):
        r = ref.clone()
        r[rows, cols] = ref_px
        f = frames.clone()
        f[:, rows, cols] = frame_px
        return mod(r[None], f[None], pts).reshape(-1)

    ref_px = ref[rows, cols].clone().requires_grad_(True)
    frame_px = frames[:, rows, cols].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (ref_px, frame_px), eps=1e-5, atol=1e-6, rtol=1e-3)


def test_stationarity_at_solver_output(seq):
    """The backward's condition F(p) = 0 holds at the solver's output: no point rejected."""
    ref, frames, pts = seq
    for form in ("joint", "average", "joint+average"):
        mod = STSDIC(_cfg(formulation=form, tol=1e-4), residual_tol=1e-3)
        r = ref[None].clone().requires_grad_(True)
        out = mod.forward_full(r, frames[None], pts)
        out.disp.sum().backward()
        assert out.report["zero_grad"] == 0 and out.report["not_stationary"] == 0


def test_batch_equals_separate_calls(seq, monkeypatch):
    ref0, frames0, pts = seq
    ref1, frames1 = _sequence(1, u0=-0.5, ut=-0.2, vt=0.1)
    ref2, frames2 = _sequence(2, v0=0.4, ut=0.05, vt=-0.15)
    refs = torch.stack([ref0, ref1, ref2])
    frames = torch.stack([frames0, frames1, frames2])
    mod = STSDIC(_cfg(tol=1e-10))
    calls = []
    orig = SubsetSolver.solve

    def counting(self, *a, **k):
        calls.append(1)
        return orig(self, *a, **k)

    monkeypatch.setattr(SubsetSolver, "solve", counting)
    r = refs.clone().requires_grad_(True)
    f = frames.clone().requires_grad_(True)
    out = mod.forward_full(r, f, pts)
    assert len(calls) == 1  # the batch is one solve, not a loop over B
    w = torch.linspace(0.5, 2.0, 12, dtype=torch.float64).view(1, 3, 4)
    loss_terms = torch.cat([out.disp, out.vel], -1) * w
    loss_terms.sum().backward()
    for b in range(3):
        rb = refs[b : b + 1].clone().requires_grad_(True)
        fb = frames[b : b + 1].clone().requires_grad_(True)
        ob = mod.forward_full(rb, fb, pts)
        torch.testing.assert_close(ob.disp[0], out.disp[b], rtol=0, atol=1e-9)
        torch.testing.assert_close(ob.vel[0], out.vel[b], rtol=0, atol=1e-9)
        assert torch.equal(ob.status[0], out.status[b])
        (torch.cat([ob.disp, ob.vel], -1) * w).sum().backward()
        torch.testing.assert_close(rb.grad[0], r.grad[b], rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(fb.grad[0], f.grad[b], rtol=1e-6, atol=1e-9)
    # per-sequence points (B, N, 2) give the same as shared points
    out2 = mod.forward_full(refs, frames, pts.expand(3, -1, -1))
    torch.testing.assert_close(out2.disp, out.disp.detach(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_output_dtype_and_device(seq, dtype):
    ref, frames, pts = seq
    mod = STSDIC(_cfg(tol=1e-4))
    r = ref[None].to(dtype).requires_grad_(True)
    f = frames[None].to(dtype).requires_grad_(True)
    out = mod.forward_full(r, f, pts.to(dtype))
    for t in (out.disp, out.vel, out.params, out.zncc):
        assert t.dtype == dtype and t.device == ref.device
    assert out.status.dtype == torch.int8
    (out.disp.sum() + out.vel.sum()).backward()
    assert r.grad.dtype == dtype and f.grad.dtype == dtype
    assert torch.isfinite(r.grad).all() and torch.isfinite(f.grad).all()
    ref64 = STSDIC(_cfg(tol=1e-4)).forward_full(ref[None], frames[None], pts)
    assert (out.disp.double() - ref64.disp).abs().max() < 1e-3
    # the (B, 1, H, W) layout is accepted
    d = mod(r.detach().unsqueeze(1), f.detach().unsqueeze(2), pts)
    assert d.shape == (1, 3, 2) and d.dtype == dtype


def test_failed_points_get_zero_gradient(seq):
    ref, frames, pts = seq
    ref = ref.clone()
    frames = frames.clone()
    ref[0:14, 27:41] = 100.0  # a flat patch: LOW_TEXTURE at (34, 7)
    frames[:, 0:14, 27:41] = 100.0
    bad_pts = torch.cat([pts, torch.tensor([[3.0, 20.0], [34.0, 7.0]], dtype=pts.dtype)])
    mod = STSDIC(_cfg(tol=1e-8))
    r = ref[None].clone().requires_grad_(True)
    f = frames[None].clone().requires_grad_(True)
    out = mod.forward_full(r, f, bad_pts)
    st = out.status[0].tolist()
    assert st[:3] == [int(Status.CONVERGED)] * 3
    assert st[3] == int(Status.OUTSIDE) and st[4] == int(Status.LOW_TEXTURE)
    assert torch.isnan(out.disp[0, 3:]).all()
    assert out.converged.tolist() == [[True, True, True, False, False]]
    loss = out.disp[out.converged].sum()
    loss.backward()
    assert out.report["not_converged"] == 2 and out.report["zero_grad"] == 2
    assert torch.isfinite(r.grad).all() and torch.isfinite(f.grad).all()
    # the gradient is exactly that of the converged points alone
    r2 = ref[None].clone().requires_grad_(True)
    f2 = frames[None].clone().requires_grad_(True)
    mod(r2, f2, pts).sum().backward()
    torch.testing.assert_close(r.grad, r2.grad, rtol=1e-6, atol=1e-10)
    # a loss that touches the NaN outputs still yields finite, zero-padded gradients
    r3 = ref[None].clone().requires_grad_(True)
    mod(r3, frames[None], bad_pts).nansum().backward()
    torch.testing.assert_close(r3.grad, r2.grad, rtol=1e-6, atol=1e-10)


def test_max_iter_points_get_zero_gradient(seq):
    ref, frames, pts = seq
    mod = STSDIC(_cfg(max_iter=1, tol=1e-12))
    r = ref[None].clone().requires_grad_(True)
    out = mod.forward_full(r, frames[None], pts)
    assert (out.status == int(Status.MAX_ITER)).all()
    out.disp.sum().backward()
    assert out.report["zero_grad"] == 3
    assert torch.equal(r.grad, torch.zeros_like(r))


def test_not_stationary_points_are_rejected(seq):
    ref, frames, pts = seq
    mod = STSDIC(_cfg(tol=1e-2), residual_tol=1e-9)
    r = ref[None].clone().requires_grad_(True)
    out = mod.forward_full(r, frames[None], pts)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out.disp.sum().backward()
    assert out.report["not_stationary"] > 0
    assert any("not stationary" in str(x.message) for x in rec)
    assert torch.isfinite(r.grad).all()


def test_init_is_used_and_gets_zero_gradient(seq):
    ref, frames, pts = seq
    mod = STSDIC(_cfg(tol=1e-10, search_radius=0))
    flow = torch.zeros(1, 2, *SIZE, dtype=torch.float64)
    flow[:, 0] = 0.9  # a rough guess of the centre-frame displacement (truth 0.5, -0.1)
    flow.requires_grad_(True)
    init = dense_to_points(flow, pts)
    assert init.shape == (1, 3, 2)
    out = mod.forward_full(ref[None], frames[None], pts, init=init)
    free = STSDIC(_cfg(tol=1e-10)).forward_full(ref[None], frames[None], pts)
    torch.testing.assert_close(out.disp, free.disp, rtol=0, atol=1e-8)
    assert torch.equal(out.solution.info["initial_params"][:, 0], init[0, :, 0].detach())
    out.disp.sum().backward()
    assert flow.grad is not None and torch.equal(flow.grad, torch.zeros_like(flow))


# ------------------------------------------------------------------------------------------
def _linear_field(h, w, b=2):
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                            torch.arange(w, dtype=torch.float64), indexing="ij")
    f = torch.stack([0.3 + 0.01 * xx - 0.02 * yy, -1.0 + 0.005 * xx + 0.03 * yy])
    return f.unsqueeze(0) * torch.arange(1, b + 1, dtype=torch.float64).view(b, 1, 1, 1)


@pytest.mark.parametrize("mode", ["bilinear", "bicubic"])
def test_dense_points_round_trip_linear_field(mode):
    h, w = 37, 45
    flow = _linear_field(h, w)
    pts = grid_points((h, w), 6, subset_size=11)  # x = 7..37, y = 6..30
    assert pts.shape == (6 * 5, 2)
    vals = dense_to_points(flow, pts, mode="bilinear")
    assert vals.shape == (2, 30, 2)
    exact = torch.stack([0.3 + 0.01 * pts[:, 0] - 0.02 * pts[:, 1],
                         -1.0 + 0.005 * pts[:, 0] + 0.03 * pts[:, 1]], -1)
    torch.testing.assert_close(vals[0], exact, rtol=0, atol=1e-12)
    perm = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))
    dense = points_to_dense(pts[perm], vals[:, perm], (h, w), mode=mode)
    assert dense.shape == (2, 2, h, w)
    torch.testing.assert_close(dense, flow, rtol=0, atol=1e-12)  # incl. linear extrapolation
    # off-grid points sampled back from the dense field
    q = torch.tensor([[3.3, 7.9], [40.25, 30.5]], dtype=torch.float64)
    torch.testing.assert_close(dense_to_points(dense, q), dense_to_points(flow, q),
                               rtol=0, atol=1e-12)


def test_points_to_dense_nan_and_grad():
    h, w = 37, 45
    flow = _linear_field(h, w, b=1)
    pts = grid_points((h, w), 6, subset_size=11)
    vals = dense_to_points(flow, pts).clone()
    vals[0, 7] = float("nan")  # node (x=13, y=12)
    kept = points_to_dense(pts, vals, (h, w))
    nan_px = torch.isnan(kept[0, 0])
    assert nan_px.any() and nan_px[12, 13] and not nan_px[6, 7]
    assert torch.equal(nan_px, torch.isnan(kept[0, 1]))
    ok = ~nan_px
    torch.testing.assert_close(kept[0, 0][ok], flow[0, 0][ok], rtol=0, atol=1e-12)
    filled = points_to_dense(pts, vals, (h, w), nan="fill")
    assert torch.isfinite(filled).all()
    v = vals.clone().nan_to_num(0.0).requires_grad_(True)
    points_to_dense(pts, v, (h, w), mode="bicubic").sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="regular grid"):
        points_to_dense(pts[:-1], vals[:, :-1], (h, w))


def test_input_validation(seq):
    ref, frames, pts = seq
    mod = STSDIC(_cfg())
    with pytest.raises(ValueError, match="2m\\+1"):
        mod(ref[None], frames[None, :2], pts)
    with pytest.raises(ValueError, match="points"):
        mod(ref[None], frames[None], pts[:, :1])
    with pytest.raises(ValueError, match="init"):
        mod(ref[None], frames[None], pts, init=torch.zeros(3, 2))
