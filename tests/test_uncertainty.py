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
