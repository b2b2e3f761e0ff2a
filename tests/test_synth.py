"""Tests of the synthetic speckle generator (torch_stsdic.synth)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torch_stsdic.synth import (
    Custom,
    HomogeneousStrain,
    Jump,
    Movie,
    QuadraticInTime,
    Sinusoidal,
    SpecklePattern,
    Sum,
    Translation,
    add_noise,
    ground_truth,
    make_speckle,
    quantize,
    render,
    render_series,
    synthetic_movie,
)

SHAPE = (64, 80)


@pytest.fixture(scope="module")
def pattern() -> SpecklePattern:
    return make_speckle(SHAPE, seed=7)


def _spots(xs, ys, r=1.7, a=50.0) -> SpecklePattern:
    xs = torch.as_tensor(xs, dtype=torch.float64)
    ys = torch.as_tensor(ys, dtype=torch.float64)
    n = xs.numel()
    return SpecklePattern(xs, ys, torch.full((n,), r, dtype=torch.float64),
                          torch.full((n,), a, dtype=torch.float64), 0.0, None)


def _bruteforce(p: SpecklePattern, shape, F: np.ndarray, shift=(0.0, 0.0), n=12) -> np.ndarray:
    """Independent 2-D Gauss-Legendre integration of the deformed spots over each pixel."""
    H, W = shape
    xi, w = np.polynomial.legendre.leggauss(n)
    xi, w = xi / 2, w / 2
    ys = (np.arange(H)[:, None] + xi[None, :]).reshape(-1)  # (H*n,)
    xs = (np.arange(W)[:, None] + xi[None, :]).reshape(-1)
    Y, X = np.meshgrid(ys, xs, indexing="ij")
    G = np.linalg.inv(F)
    val = np.full(X.shape, p.background)
    for cx, cy, r, a in zip(p.x.numpy(), p.y.numpy(), p.radius.numpy(), p.amplitude.numpy()):
        dx, dy = X - cx - shift[0], Y - cy - shift[1]
        qx, qy = G[0, 0] * dx + G[0, 1] * dy, G[1, 0] * dx + G[1, 1] * dy
        val += a * np.exp(-(qx * qx + qy * qy) / (2 * r * r))
    ww = np.outer(w, w)
    return np.einsum("iajb,ab->ij", val.reshape(H, n, W, n), ww)


# ------------------------------------------------------------------------------------------
# pattern and rendering
# ------------------------------------------------------------------------------------------


def test_pattern_statistics(pattern):
    img = render(make_speckle((128, 128), seed=3), (128, 128))
    assert img.dtype == torch.float64 and img.shape == (128, 128)
    assert 100 < float(img.mean()) < 160
    assert float(img.std()) > 30  # good contrast
    assert float(img.min()) > 0 and float(img.max()) < 255  # not saturated
    lo, hi = float(img.quantile(0.01)), float(img.quantile(0.99))
    cov = float((img < (lo + hi) / 2).double().mean())
    assert 0.3 < cov < 0.7
    # spots cover a margin around the image
    assert float(pattern.x.min()) < -5 and float(pattern.x.max()) > SHAPE[1] + 4
    assert float(pattern.y.min()) < -5 and float(pattern.y.max()) > SHAPE[0] + 4
    for f in (pattern.x, pattern.y, pattern.radius, pattern.amplitude):
        assert f.dtype == torch.float64


def test_translation_equals_shifted_centres(pattern):
    for m, t, (dx, dy) in [(Translation(0.37, -0.21), 0.0, (0.37, -0.21)),
                           (Translation(ut=0.05, vt=-0.125), 3.0, (0.15, -0.375))]:
        a = render(pattern, SHAPE, m, t)
        b = render(pattern.shifted(dx, dy), SHAPE)
        assert float((a - b).abs().max()) < 1e-10
        assert float((a - render(pattern, SHAPE)).abs().max()) > 1.0  # it did move


def test_integer_translation_is_roll(pattern):
    ref = render(pattern, SHAPE).numpy()
    g = render(pattern, SHAPE, Translation(1.0, 0.0)).numpy()
    np.testing.assert_allclose(g[:, 1:], np.roll(ref, 1, axis=1)[:, 1:], rtol=0, atol=1e-9)
    g = render(pattern, SHAPE, Translation(-2.0, 3.0)).numpy()
    rolled = np.roll(np.roll(ref, -2, axis=1), 3, axis=0)
    np.testing.assert_allclose(g[3:, :-2], rolled[3:, :-2], rtol=0, atol=1e-9)


def test_render_matches_independent_integration():
    p = _spots([10.3, 21.8, 16.2], [9.6, 14.1, 22.7], r=1.6, a=-80.0)
    p = SpecklePattern(p.x, p.y, torch.tensor([1.6, 2.3, 1.2], dtype=torch.float64),
                       p.amplitude, 100.0, None)
    shape = (32, 34)
    # undeformed and translated: separable erf path, exact up to the spot truncation
    img = render(p, shape, Translation(0.43, -0.29)).numpy()
    ref = _bruteforce(p, shape, np.eye(2), shift=(0.43, -0.29), n=16)
    assert np.abs(img - ref).max() < 1e-6  # cutoff = 6 standard deviations
    img = render(p, shape, Translation(0.43, -0.29), cutoff=9.0).numpy()
    assert np.abs(img - ref).max() < 1e-10
    # sheared + rotated affine field: Gauss-Legendre path (no strain at the centre point)
    m = HomogeneousStrain(exx=0.04, eyy=-0.03, exy=0.05, omega=0.1, center=(16.0, 16.0))
    g = m.gradient(0.0, 0.0, 0.0)
    F = np.eye(2) + np.array([[float(g[0]), float(g[1])], [float(g[2]), float(g[3])]])
    u, v = m.displacement(p.x, p.y, 0.0)
    moved = SpecklePattern(p.x + u, p.y + v, p.radius, p.amplitude, p.background, None)
    ref = _bruteforce(moved, shape, F, n=16)
    img4 = render(p, shape, m).numpy()
    img12 = render(p, shape, m, quadrature=12, cutoff=9.0).numpy()
    assert np.abs(img12 - ref).max() < 1e-10
    assert np.abs(img4 - ref).max() < 1e-5
    # pure normal strain: separable path with different x/y widths, exact
    m2 = HomogeneousStrain(exx=0.05, eyy=-0.04, center=(16.0, 16.0))
    u, v = m2.displacement(p.x, p.y, 0.0)
    moved = SpecklePattern(p.x + u, p.y + v, p.radius, p.amplitude, p.background, None)
    ref = _bruteforce(moved, shape, np.diag([1.05, 0.96]), n=16)
    assert np.abs(render(p, shape, m2, cutoff=9.0).numpy() - ref).max() < 1e-10


def test_homogeneous_strain_moves_spot_centres():
    shape = (96, 128)  # isolated spots, >= 30 px apart and >= 15 px from the border
    xs, ys = [18.2, 64.7, 110.4, 64.1, 33.5], [48.3, 16.6, 49.1, 80.2, 79.9]
    p = _spots(xs, ys, r=1.8, a=50.0)
    m = HomogeneousStrain(exx=0.02, eyy=-0.01, exy=0.004, center=(64.0, 48.0))
    img = render(p, shape, m).numpy()
    u, v = m.displacement(p.x, p.y, 0.0)
    g = m.gradient(0.0, 0.0, 0.0)
    F = np.eye(2) + np.array([[float(g[0]), float(g[1])], [float(g[2]), float(g[3])]])
    cov_true = 1.8**2 * F @ F.T + np.eye(2) / 12  # + Sheppard's correction of pixel binning
    Y, X = np.mgrid[0:shape[0], 0:shape[1]]
    for k in range(len(xs)):
        px, py = xs[k] + float(u[k]), ys[k] + float(v[k])
        win = (np.abs(X - px) < 11) & (np.abs(Y - py) < 11)
        w = img * win
        mx, my = (w * X).sum() / w.sum(), (w * Y).sum() / w.sum()
        assert abs(mx - px) < 1e-6 and abs(my - py) < 1e-6
        cxx = (w * (X - mx) ** 2).sum() / w.sum()
        cyy = (w * (Y - my) ** 2).sum() / w.sum()
        cxy = (w * (X - mx) * (Y - my)).sum() / w.sum()
        np.testing.assert_allclose([cxx, cyy, cxy], cov_true[[0, 1, 0], [0, 1, 1]], atol=1e-5)
        # mass is conserved up to the area change det F
        assert abs(w.sum() / (50.0 * 2 * math.pi * 1.8**2 * np.linalg.det(F)) - 1) < 1e-6
    # spots right of the centre move right, left of it move left (exx > 0)
    assert float(u[2]) > 0.5 and float(u[0]) < -0.5


def test_render_is_deterministic_and_seeded():
    a, b = make_speckle(SHAPE, seed=1), make_speckle(SHAPE, seed=1)
    c = make_speckle(SHAPE, seed=2)
    assert torch.equal(a.x, b.x) and torch.equal(a.amplitude, b.amplitude)
    assert not torch.equal(a.x[:10], c.x[:10])
    m = Sinusoidal(0.4, 0.2, wavelength=40.0)
    assert torch.equal(render(a, SHAPE, m), render(b, SHAPE, m))


def test_sinusoidal_renders_near_local_translation():
    # long wavelength: locally almost a translation by U(X) at the spot centres
    p = _spots([20.0, 50.0], [30.0, 30.0], r=1.8, a=50.0)
    m = Sinusoidal(amplitude_u=1.5, wavelength=200.0)
    img = render(p, SHAPE, m).numpy()
    u, _ = m.displacement(p.x, p.y, 0.0)
    Y, X = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    for k in range(2):
        px = float(p.x[k] + u[k])
        w = img * ((np.abs(X - px) < 11) & (np.abs(Y - 30) < 11))
        assert abs((w * X).sum() / w.sum() - px) < 1e-6


def test_folding_motion_raises(pattern):
    with pytest.raises(ValueError, match="det F"):
        render(pattern, SHAPE, HomogeneousStrain(exx=-1.5), check_coverage=False)


def test_coverage_warning(pattern):
    with pytest.warns(UserWarning, match="margin"):
        render(pattern, SHAPE, Translation(60.0, 0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render(pattern, SHAPE, Translation(3.0, -2.0))


# ------------------------------------------------------------------------------------------
# noise, quantisation, series
# ------------------------------------------------------------------------------------------


def test_add_noise_std_and_seed():
    z = torch.zeros(256, 256, dtype=torch.float64)
    n = add_noise(z, 3.0, seed=0)
    assert abs(float(n.std()) - 3.0) < 0.05 and abs(float(n.mean())) < 0.05
    assert torch.equal(n, add_noise(z, 3.0, seed=0))
    assert not torch.equal(n, add_noise(z, 3.0, seed=1))
    assert torch.equal(add_noise(z, 0.0), z) and float(z.abs().max()) == 0.0  # input intact


def test_quantize_ranges():
    x = torch.tensor([-5.0, 0.2, 0.6, 1.0, 127.5, 254.6, 255.0, 300.0], dtype=torch.float64)
    q8 = quantize(x, 8)
    assert q8.tolist() == [0, 0, 1, 1, 128, 255, 255, 255]
    q16 = quantize(x, 16)
    assert float(q16.min()) == 0 and float(q16.max()) == 65535
    assert float(q16[3]) == 257 and torch.equal(q16, torch.round(q16))
    assert quantize(x, 16, dtype=torch.int32).dtype == torch.int32
    assert float(quantize(x, 12).max()) == 4095


def test_render_series_noise_on_all_images(pattern):
    times = torch.tensor([1.0, 2.0, 3.0])
    still = Translation()
    ref, frames = render_series(pattern, SHAPE, still, times, noise_sigma=2.0, seed=5)
    clean = render(pattern, SHAPE)
    assert ref.shape == SHAPE and frames.shape == (3, *SHAPE)
    diffs = [ref - clean] + [f - clean for f in frames]
    for d in diffs:
        assert abs(float(d.std()) - 2.0) < 0.15
    for i in range(4):  # independent draws
        for j in range(i):
            c = float((diffs[i] * diffs[j]).mean()) / 4.0
            assert abs(c) < 0.1
    ref2, frames2 = render_series(pattern, SHAPE, still, times, noise_sigma=2.0, seed=5)
    assert torch.equal(ref, ref2) and torch.equal(frames, frames2)
    _, frames3 = render_series(pattern, SHAPE, still, times, noise_sigma=2.0, seed=6)
    assert not torch.equal(frames, frames3)
    # quantised 16-bit series
    ref16, fr16 = render_series(pattern, SHAPE, Translation(ut=0.1), times, bits=16)
    assert torch.equal(ref16, torch.round(ref16)) and float(fr16.max()) <= 65535
    assert abs(float(ref16.mean()) / 257 - float(clean.mean())) < 0.01


def test_render_series_reference_time(pattern):
    m = Translation(ut=0.25)
    with pytest.warns(UserWarning, match="reference_time=1.0"):
        ref, frames = render_series(pattern, SHAPE, m, [2.0], reference_time=1.0)
    assert float((ref - render(pattern, SHAPE, m, 1.0)).abs().max()) == 0.0
    ref0, _ = render_series(pattern, SHAPE, HomogeneousStrain(exx=0.01), [1.0],
                            reference_time=None)
    assert torch.equal(ref0, render(pattern, SHAPE))
    with pytest.warns(UserWarning, match="reference image is itself deformed"):
        render_series(pattern, SHAPE, HomogeneousStrain(exx=0.01), [1.0])


def test_synthetic_movie_defaults():
    mv = synthetic_movie()
    assert isinstance(mv, Movie)
    ref, frames, times, motion = mv
    assert ref.shape == (301, 301) and frames.shape == (9, 301, 301)
    assert times.tolist() == [float(i) for i in range(1, 10)]
    gt = ground_truth(motion, torch.tensor([[150.0, 150.0]]), times)
    np.testing.assert_allclose(gt["u"][:, 0].numpy(), times.numpy() / 20, atol=1e-15)
    assert float(gt["v"].abs().max()) == 0.0


# ------------------------------------------------------------------------------------------
# motions and ground truth
# ------------------------------------------------------------------------------------------


MOTIONS = [
    Translation(0.3, -0.2, 0.05, 0.01),
    HomogeneousStrain(0.01, -0.005, 0.002, center=(30.0, 20.0)),
    HomogeneousStrain(0.01, -0.005, 0.002, center=(30.0, 20.0), rate=0.5, omega=0.003),
    QuadraticInTime(0.05, 0.01, -0.02, 0.003),
    Sinusoidal(0.5, 0.2, 32.0, axis="x", phase=0.3, rate=0.2),
    Sinusoidal(0.5, -0.3, 20.0, axis="y"),
    Translation(ut=0.1) + HomogeneousStrain(0.01, rate=1.0) + Sinusoidal(0.2, rate=0.5),
]


@pytest.mark.parametrize("m", MOTIONS, ids=lambda m: type(m).__name__)
def test_motion_derivatives_consistent(m):
    g = torch.Generator().manual_seed(0)
    x, y, t = torch.rand(3, 50, generator=g, dtype=torch.float64) * torch.tensor(
        [[60.0], [60.0], [5.0]], dtype=torch.float64)
    h = 1e-5
    num = Custom(m.displacement, h=h, ht=h)
    for a, b in zip(m.gradient(x, y, t), num.gradient(x, y, t)):
        assert torch.allclose(a, b, atol=1e-8)
    for a, b in zip(m.velocity(x, y, t), num.velocity(x, y, t)):
        assert torch.allclose(a, b, atol=1e-8)
    u, v = m.displacement(1.0, torch.zeros(3, 1), torch.zeros(4))  # broadcasting
    assert u.shape == v.shape == (3, 4)


def test_ground_truth_formulas():
    pts = torch.tensor([[10.0, 20.0], [35.5, 7.25], [50.0, 50.0]], dtype=torch.float64)
    times = torch.tensor([0.0, 1.0, 2.5], dtype=torch.float64)
    m = (Translation(0.3, -0.2, 0.05, 0.01) + HomogeneousStrain(0.01, -0.004, 0.002,
                                                                  center=(30.0, 20.0), rate=0.5)
         + QuadraticInTime(0.0, 0.02, 0.1, 0.0) + Sinusoidal(0.4, 0.0, 40.0, rate=1.0))
    gt = ground_truth(m, pts, times)
    assert set(gt) >= {"u", "v", "ut", "vt"}
    X, Y = pts[:, 0].numpy()[None], pts[:, 1].numpy()[None]
    T = times.numpy()[:, None]
    sn = np.sin(2 * np.pi * X / 40.0)
    u = (0.3 + 0.05 * T + 0.5 * T * (0.01 * (X - 30) + 0.002 * (Y - 20)) + 0.02 * T**2
         + 0.4 * T * sn)
    v = -0.2 + 0.01 * T + 0.5 * T * (0.002 * (X - 30) - 0.004 * (Y - 20)) + 0.1 * T
    ut = 0.05 + 0.5 * (0.01 * (X - 30) + 0.002 * (Y - 20)) + 0.04 * T + 0.4 * sn
    vt = 0.01 + 0.5 * (0.002 * (X - 30) - 0.004 * (Y - 20)) + 0.1 + 0 * T
    for k, ref in dict(u=u, v=v, ut=ut, vt=vt).items():
        assert gt[k].shape == (3, 3)
        np.testing.assert_allclose(gt[k].numpy(), ref, atol=1e-13, err_msg=k)
    np.testing.assert_allclose(gt["dudx"].numpy(),
                               0.5 * T * 0.01 + 0.4 * T * np.cos(2 * np.pi * X / 40) * 2 * np.pi
                               / 40, atol=1e-13)


def test_ground_truth_relative_to_reference_time():
    pts = torch.tensor([[10.0, 20.0], [40.0, 5.0]], dtype=torch.float64)
    gt = ground_truth(Translation(0.3, 0.0, 0.1, 0.0), pts, [1.0, 4.0], reference_time=2.0)
    np.testing.assert_allclose(gt["u"].numpy(), [[-0.1, -0.1], [0.2, 0.2]], atol=1e-14)
    m = HomogeneousStrain(exx=0.02, center=(0.0, 0.0), rate=1.0)
    gt = ground_truth(m, pts, [1.0, 3.0], reference_time=1.0)
    # material point C = X / 1.02; u_rel = 0.02 * C * (t - 1)
    np.testing.assert_allclose(gt["u"][1].numpy(), 0.04 * pts[:, 0].numpy() / 1.02, atol=1e-12)
    np.testing.assert_allclose(gt["dudx"][1].numpy(), 0.04 / 1.02, atol=1e-12)
    static = ground_truth(HomogeneousStrain(exx=0.01), pts, [1.0], reference_time=0.0)
    assert float(static["u"].abs().max()) < 1e-14


def test_jump_is_discontinuous(pattern):
    j = Jump(x0=40.0, du=2.0, dv=-1.0, t_jump=3.0)
    u, v = j.displacement(torch.tensor([39.999, 40.001, 40.001]), 0.0,
                          torch.tensor([3.0, 2.999, 3.0]))
    assert u.tolist() == [0.0, 0.0, 2.0] and v.tolist() == [0.0, 0.0, -1.0]
    gt = ground_truth(j, torch.tensor([[39.9, 1.0], [40.1, 1.0]]), [2.99, 3.0])
    assert gt["u"].tolist() == [[0.0, 0.0], [0.0, 2.0]]
    ref = render(pattern, SHAPE)
    before = render(pattern, SHAPE, j, 2.99)
    after = render(pattern, SHAPE, j, 3.0).numpy()
    assert torch.equal(before, ref)
    # far from the crack: left unchanged, right shifted by exactly (2, -1) px
    np.testing.assert_allclose(after[:, :25], ref.numpy()[:, :25], atol=1e-9)
    rolled = np.roll(np.roll(ref.numpy(), 2, axis=1), -1, axis=0)
    np.testing.assert_allclose(after[:-1, 57:], rolled[:-1, 57:], atol=1e-9)
    assert np.abs(after[:, 30:50] - ref.numpy()[:, 30:50]).max() > 1.0


def test_sum_and_custom():
    m = Translation(0.5) + Translation(0.0, 0.25) + QuadraticInTime(bu=1.0)
    assert isinstance(m, Sum) and len(m.motions) == 3
    u, v = m.displacement(0.0, 0.0, 2.0)
    assert float(u) == 4.5 and float(v) == 0.25
    c = Custom(lambda x, y, t: (0.01 * x * t, 0.0 * y))
    dudx, dudy, dvdx, dvdy = c.gradient(torch.tensor([5.0]), 1.0, 2.0)
    assert abs(float(dudx) - 0.02) < 1e-9 and float(dudy) == 0.0
    assert abs(float(c.velocity(5.0, 1.0, 2.0)[0]) - 0.05) < 1e-9
