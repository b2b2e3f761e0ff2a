"""Per-point uncertainty (uncertainty.py): the linear algebra against its definitions."""

import pytest
import torch

from torch_stsdic.core import uncertainty
from torch_stsdic.core.formulations import Geometry, SubsetData, centred_gram
from torch_stsdic.core.shape import make_shape
from torch_stsdic.core.window import make_window


def _data(n: int = 64, t: int = 5, seed: int = 0, window: str = "square"):
    g = torch.Generator().manual_seed(seed)
    geo = Geometry.make(make_shape("affine"), make_window(window, 11), "znssd", torch.float64,
                        "cpu")
    s = geo.w.numel()
    gx = torch.randn(n, s, generator=g, dtype=torch.float64) * 20
    gy = torch.randn(n, s, generator=g, dtype=torch.float64) * 20
    dt = (torch.arange(t, dtype=torch.float64) - t // 2).expand(n, t).clone()
    z = torch.zeros(n, 1, dtype=torch.float64)
    data = SubsetData(px=z, py=z, dt=dt, fidx=torch.zeros(n, t, dtype=torch.long),
                      ft=torch.zeros(n, s, dtype=torch.float64),
                      fnorm=torch.ones(n, dtype=torch.float64), gx=gx, gy=gy)
    data.gram = centred_gram(geo, gx, gy)
    return geo, data


@pytest.mark.parametrize("window", ["square", "gaussian"])
def test_std_is_the_diagonal_of_the_covariance(window):
    geo, data = _data(window=window)
    n = data.dt.shape[0]
    noise = uncertainty.NoiseModel(ref=torch.full((n,), 4.0, dtype=torch.float64),
                                   frame=torch.full((n,), 9.0, dtype=torch.float64))
    r = uncertainty.response(geo, data, noise, 3)
    cov = uncertainty.covariance(r)
    want = torch.diagonal(cov, dim1=-2, dim2=-1).sqrt()
    torch.testing.assert_close(uncertainty.std_of(r), want, rtol=1e-10, atol=0)


def test_inverse_is_the_inverse_of_the_corrected_hessian():
    geo, data = _data()
    n = data.dt.shape[0]
    noise = uncertainty.NoiseModel(ref=torch.full((n,), 4.0, dtype=torch.float64),
                                   frame=torch.full((n,), 4.0, dtype=torch.float64))
    r = uncertainty.response(geo, data, noise, 3)
    z = r.z
    zz = torch.einsum("ntp,ntq->npq", z, z)
    kappa = r.kappa
    bw = r.b2  # square window: w = w^2
    h = data.gram * zz - kappa * 4.0 * bw * zz
    torch.testing.assert_close(r.coef, torch.linalg.inv(h), rtol=1e-9, atol=1e-14)


def test_noise_as_large_as_the_texture_falls_back_to_the_first_order_hessian():
    """A noise estimate above the texture's signal makes the corrected Hessian indefinite: the
    std must stay finite and positive (the first-order Hessian's), not come from the inverse
    of an indefinite matrix (which inflated it without bound)."""
    geo, data = _data(n=8)
    n = 8
    huge = torch.full((n,), 1e6, dtype=torch.float64)
    r = uncertainty.response(geo, data, uncertainty.NoiseModel(ref=huge, frame=huge), 3)
    zz = torch.einsum("ntp,ntq->npq", r.z, r.z)
    torch.testing.assert_close(r.coef, torch.linalg.inv(data.gram * zz), rtol=1e-9, atol=1e-14)
    std = uncertainty.std_of(r)
    assert torch.isfinite(std).all() and (std > 0).all()


def test_rows_without_texture_give_nan_not_an_error():
    """A flat subset (zero gradients: a singular Hessian, corrected or not) among textured
    ones: NaN std for it, the others unchanged, no exception (a flat image region on real
    data raised from the Cholesky inverse)."""
    geo, data = _data(n=6)
    n = 6
    noise = uncertainty.NoiseModel(ref=torch.full((n,), 4.0, dtype=torch.float64),
                                   frame=torch.full((n,), 4.0, dtype=torch.float64))
    want = uncertainty.std_of(uncertainty.response(geo, data, noise, 3))
    data.gx[2] = 0.0
    data.gy[2] = 0.0
    data.gram = centred_gram(geo, data.gx, data.gy)
    std = uncertainty.std_of(uncertainty.response(geo, data, noise, 3))
    assert torch.isnan(std[2]).all()
    keep = [0, 1, 3, 4, 5]
    torch.testing.assert_close(std[keep], want[keep], rtol=1e-10, atol=0)


def test_flat_region_in_a_movie_is_low_texture_with_nan_std():
    """End to end: a flat patch in the images is LOW_TEXTURE (std NaN), the rest solves."""
    from torch_stsdic import DICConfig, Status, solve_window, synth

    mv = synth.synthetic_movie((96, 96), 4, noise_sigma=1.0, seed=2)
    ref, frames = mv.ref.clone(), mv.frames.clone()
    ref[:, :40] = 100.0
    frames[:, :, :40] = 100.0
    pts = torch.tensor([[20.0, 48.0], [70.0, 48.0]])
    sol = solve_window(ref, frames[:3], pts, DICConfig(subset_size=15, m=1))
    assert int(sol.status[0]) == int(Status.LOW_TEXTURE)
    assert torch.isnan(sol.std[0]).all()
    assert int(sol.status[1]) == int(Status.CONVERGED) and torch.isfinite(sol.std[1]).all()


def _shared_frame_case(seed: int):
    """A window of frames 2..8 of 10 (target 3: shifted), a template of frames 0..8
    (unequal weights) registered to frame 0."""
    g = torch.Generator().manual_seed(seed)
    n_series, win, target = 10, torch.arange(2, 9), 3
    a = torch.zeros(n_series, dtype=torch.float64)
    a[:9] = torch.rand(9, generator=g, dtype=torch.float64) + 0.5
    a /= a.sum()
    return n_series, win, target, a


@pytest.mark.parametrize("reg_points", [0, 4, 16])
def test_shared_frame_factors_match_a_monte_carlo_of_the_noise(reg_points):
    """The template averages frames of the window (and is registered to frame 0 by fits
    over ``reg_points`` points): simulated displacements' and velocities' variances against
    what the independent-noise prediction, with its noise estimated from the residuals,
    says times :func:`shared_frame_factors` (the prediction alone is off by 25-45 %)."""
    n_series, win, target, a = _shared_frame_case(0)
    trials, j = 40_000, max(reg_points, 1)
    g = torch.Generator().manual_seed(1)
    nu = torch.randn(trials, j, n_series, generator=g, dtype=torch.float64)  # point 0: own
    dt = (win - target).double()
    z = torch.stack([torch.ones_like(dt), dt], 1)  # (T, 2)
    w = torch.linalg.solve(z.T @ z, z.T)  # (2, T): intercept and slope weights
    tmpl = nu @ a  # (trials, J) the template's noise
    d = tmpl[:, :1] - nu[:, 0, win]  # (trials, T) each frame's displacement noise
    if reg_points:
        d = d + (nu[..., 0] - tmpl).mean(1, keepdim=True)  # registration to frame 0
    est = d @ w.T  # (trials, 2)
    rho = float((a * a).sum())
    # the old prediction: sigma^2 from the residuals' mean variance over (rho + 1)
    resid = (tmpl[:, :1] - nu[:, 0, win]).var(0).mean()
    s2 = resid / (rho + 1.0)
    old = torch.stack([s2 * (rho + (w[0] ** 2).sum()), s2 * (w[1] ** 2).sum()])
    fac = uncertainty.shared_frame_factors(
        dt[None], a[win][None], (a * a).sum()[None], rho,
        reference=(win == 0)[None], registration=torch.tensor([1.0 / j if reg_points else 0.0],
                                                              dtype=torch.float64))[0]
    measured = est.var(0)
    torch.testing.assert_close(old * fac, measured, rtol=0.04, atol=0)
    assert float((old[0] / measured[0] - 1).abs()) > 0.25
