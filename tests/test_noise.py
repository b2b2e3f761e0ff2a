"""Tests of the noise-floor prediction and the noise estimators (torch_stsdic.core.noise)."""

from __future__ import annotations

import math

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic.core.noise import (
    estimate_noise_sigma,
    gradient_noise_factor,
    interpolated_noise_autocorrelation,
    interpolation_variance_factor,
    predicted_std,
    residual_noise_sigma,
)
from torch_stsdic.synth import Translation, add_noise, make_speckle, render, render_series

SHAPE = (130, 130)


@pytest.fixture(scope="module")
def clean_series():
    """A clean reference and 3 frames moving by u = 0.05 t (t = 1, 2, 3), and 25 POIs
    spaced by a subset width (independent subsets)."""
    pattern = make_speckle(SHAPE, seed=11)
    times = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    ref, frames = render_series(pattern, SHAPE, Translation(ut=0.05), times)
    g = torch.arange(23.0, 108.0, 21.0)
    ys, xs = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
    return ref, frames, times, pts


def _monte_carlo(ref, frames, times, pts, cfg, sigma_ref, sigma_def, reps):
    clean = sts.solve_window(ref, frames, pts, config=cfg, times=times)
    du, dut = [], []
    gen = torch.Generator().manual_seed(1234)
    for _ in range(reps):
        r = ref + sigma_ref * torch.randn(ref.shape, generator=gen, dtype=torch.float64)
        f = frames + sigma_def * torch.randn(frames.shape, generator=gen, dtype=torch.float64)
        sol = sts.solve_window(r, f, pts, config=cfg, times=times, init=clean.params)
        assert bool(sol.ok.all())
        du.append(sol.u - clean.u)
        dut.append(sol.ut - clean.ut)
    rms = lambda x: float(torch.cat(x).pow(2).mean().sqrt())  # noqa: E731
    return rms(du), rms(dut)


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt())


def test_prediction_matches_monte_carlo_classical(clean_series):
    ref, frames, times, pts = clean_series
    cfg = sts.DICConfig(subset_size=21, m=0, tol=1e-6)
    mu, _ = _monte_carlo(ref, frames[1:2], times[1:2], pts, cfg, 0.0, 4.0, reps=6)
    pred = predicted_std(ref, pts, cfg, sigma_ref=0.0, sigma_def=4.0, displacement=0.1)
    assert math.isnan(float(pred["ut"][0]))
    ratio = mu / _rms(pred["u"])
    assert 0.85 < ratio < 1.2, ratio


def test_prediction_matches_monte_carlo_sts_noisy_reference(clean_series):
    ref, frames, times, pts = clean_series
    cfg = sts.DICConfig(subset_size=21, m=1, tol=1e-6)
    mu, mut = _monte_carlo(ref, frames, times, pts, cfg, 4.0, 4.0, reps=4)
    disp = torch.tensor([0.1, 0.0, 0.05, 0.0]).expand(pts.shape[0], 4)
    pred = predicted_std(ref, pts, cfg, sigma_ref=4.0, sigma_def=4.0, displacement=disp)
    assert 0.85 < mu / _rms(pred["u"]) < 1.2, mu / _rms(pred["u"])
    assert 0.8 < mut / _rms(pred["ut"]) < 1.25, mut / _rms(pred["ut"])
    # the reference noise is not averaged away: the floor with a noisy reference is well
    # above the one with a clean reference
    clean_ref = predicted_std(ref, pts, cfg, sigma_ref=0.0, sigma_def=4.0, displacement=disp)
    assert _rms(pred["u"]) > 1.6 * _rms(clean_ref["u"])


def test_textbook_formula_symmetric_window(clean_series):
    ref, _, _, pts = clean_series
    cfg = sts.DICConfig(subset_size=21, m=2)
    kw = dict(interp=1.0, second_order=False)
    sts5 = predicted_std(ref, pts, cfg, sigma_ref=3.0, sigma_def=5.0, **kw)
    # var(u) = (sigma_ref^2 + sigma_def^2 / T) [H_s^-1]_uu: the classical floor with
    # the same total variance
    equiv = math.sqrt(3.0**2 + 5.0**2 / 5)
    cl = predicted_std(ref, pts, cfg, sigma_ref=equiv, sigma_def=0.0, n_frames=1, **kw)
    assert torch.allclose(sts5["u"], cl["u"], rtol=1e-9)
    assert torch.allclose(sts5["v"], cl["v"], rtol=1e-9)
    # the velocity: sigma_def^2 / sum(dt^2), independent of the reference noise
    sts3 = predicted_std(ref, pts, cfg, sigma_ref=0.0, sigma_def=5.0, n_frames=3, **kw)
    assert torch.allclose(sts5["ut"] / sts3["ut"], torch.tensor(math.sqrt(2.0 / 10.0),
                                                                dtype=torch.float64))
    # a shifted window (dt = 0..4) couples u and ut: larger error of u
    shifted = predicted_std(ref, pts, cfg, sigma_ref=3.0, sigma_def=5.0,
                            dt=[0.0, 1.0, 2.0, 3.0, 4.0], **kw)
    assert bool((shifted["u"] > sts5["u"]).all())


def test_interpolated_noise_factors():
    assert float(interpolation_variance_factor(0.0)) == pytest.approx(1.0, abs=1e-9)
    assert float(interpolation_variance_factor(0.5)) == pytest.approx(0.7561, abs=1e-3)
    assert float(interpolation_variance_factor(0.5, 0.5)) == pytest.approx(0.7561**2, abs=1e-3)
    r = interpolated_noise_autocorrelation(torch.tensor([0.0, 0.3]), order=5, max_lag=3)
    assert r.shape == (2, 7)
    assert torch.allclose(r[0], torch.tensor([0, 0, 0, 1.0, 0, 0, 0], dtype=torch.float64),
                          atol=1e-9)
    assert torch.allclose(r[1], r[1].flip(-1), atol=1e-12)  # symmetric in the lag
    # Monte Carlo: interpolated white noise at a half-pixel shift
    from torch_stsdic.core.interpolation import BSplineImage

    gen = torch.Generator().manual_seed(0)
    n = torch.randn(1, 120, 120, generator=gen, dtype=torch.float64)
    y, x = torch.meshgrid(torch.arange(10.0, 110.0), torch.arange(10.0, 110.0), indexing="ij")
    vals = BSplineImage(n, 3).sample(x + 0.5, y)
    assert float(vals.var()) == pytest.approx(0.7561, rel=0.05)
    _, gx, _ = BSplineImage(n, 3).sample(x, y, grad=True)
    assert float(gx.var()) == pytest.approx(gradient_noise_factor(3), rel=0.05)


def test_predicted_std_errors(clean_series):
    ref, _, _, pts = clean_series
    with pytest.raises(ValueError, match="displacement"):
        predicted_std(ref, pts, sts.DICConfig(m=1), displacement=torch.zeros(3, 3))
    with pytest.raises(ValueError, match="interp"):
        predicted_std(ref, pts, sts.DICConfig(m=1), interp="bogus")
    with pytest.raises(ValueError, match="ref"):
        predicted_std(torch.zeros(3, 4, 5), pts, sts.DICConfig(m=1))


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0])
def test_estimate_noise_sigma(sigma):
    img = render(make_speckle((160, 160), seed=2), (160, 160))
    a = add_noise(img, sigma, seed=1)
    b = add_noise(img, sigma, seed=2)
    c = add_noise(img, sigma, seed=3)
    assert estimate_noise_sigma(a, b) == pytest.approx(sigma, rel=0.03)
    assert estimate_noise_sigma(a, b, robust=True) == pytest.approx(sigma, rel=0.05)
    assert estimate_noise_sigma(torch.stack([a, b, c])) == pytest.approx(sigma, rel=0.03)
    assert estimate_noise_sigma(a) == pytest.approx(sigma, rel=0.05)  # Immerkaer
    assert estimate_noise_sigma(a.numpy(), flat_fraction=None) == pytest.approx(sigma, rel=0.05)


def test_residual_noise_sigma():
    shape = (120, 120)
    pattern = make_speckle(shape, seed=4)
    ref, frames = render_series(pattern, shape, Translation(ut=1.0), [1.0])  # integer shift
    g = torch.arange(20.0, 101.0, 20.0)
    ys, xs = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
    cfg = sts.DICConfig(m=0)
    for s_ref, s_def in ((3.0, 0.0), (0.0, 4.0), (3.0, 4.0)):
        r = add_noise(ref, s_ref, seed=1) if s_ref else ref
        f = add_noise(frames[0], s_def, seed=2) if s_def else frames[0]
        sol = sts.solve_window(r, f, pts, config=cfg)
        est = residual_noise_sigma(r, f, pts, sol.params, cfg)
        assert est == pytest.approx(math.hypot(s_ref, s_def), rel=0.06)
    with pytest.raises(ValueError, match="params"):
        residual_noise_sigma(ref, frames[0], pts, torch.zeros(len(pts), 3), cfg)


def test_estimate_noise_sigma_errors():
    img = torch.zeros(20, 20)
    with pytest.raises(ValueError, match="other"):
        estimate_noise_sigma(img, torch.zeros(10, 10))
    with pytest.raises(ValueError, match="method"):
        estimate_noise_sigma(img, method="nope")
    with pytest.raises(ValueError, match="stack"):
        estimate_noise_sigma(img, method="stack")


def test_noise_estimate_of_a_float32_image_equals_the_float64_one():
    """Immerkaer's estimate works on a float32 image as it is (no float64 copy; the mean in
    float64): on integer grey levels (a camera's, up to 16 bits) its kernels are exact, the
    estimate equals the float64 one; on a render with float noise it agrees to 1e-6."""
    img = add_noise(render(make_speckle((160, 160), seed=3), (160, 160)), 4.0, seed=5)
    grey = img.round().double()  # integer levels
    for x in (grey, grey * 300.0, img.double()):
        a = estimate_noise_sigma(x)
        b = estimate_noise_sigma(x.float())
        assert b == pytest.approx(a, rel=0 if x is not img else 1e-6, abs=1e-9)
    assert estimate_noise_sigma(grey.float(), flat_fraction=None) == pytest.approx(
        estimate_noise_sigma(grey, flat_fraction=None), rel=1e-12)


def test_quantiles_from_histograms_equal_the_sorted_rows():
    """:func:`_quantiles`' two order statistics, from the rows' histograms (whole numbers on
    the CPU: the Sobel magnitudes of integer grey levels) or by selection (any other
    values), are the sorted rows' to the bit: ties, both ends, 16-bit ranges."""
    import math

    from torch_stsdic.core import noise

    def by_sorting(x, q):
        n = x.shape[1]
        pos = q * (n - 1)
        lo = int(math.floor(pos))
        s = x.sort(1).values
        if lo + 1 >= n:
            return s[:, lo]
        v_lo, v_hi = s[:, lo], s[:, lo + 1]
        return v_lo + (v_hi - v_lo) * (pos - lo)

    gen = torch.Generator().manual_seed(5)
    cases = [torch.randint(0, top, (f, n), generator=gen).float()
             for top, f, n in ((4, 5, 13), (3000, 3, 401), (70_000, 2, 999), (1, 2, 7))]
    cases += [torch.randint(0, 300, (2, 64), generator=gen).double(),  # float64 rows
              torch.randint(0, 300, (2, 64), generator=gen),  # integer rows
              torch.randn(3, 77, generator=gen),  # negative: by selection
              torch.rand(2, 50, generator=gen) * 9]  # fractions: by selection
    for x in cases:
        for q in (0.0, 0.1, 0.25, 0.5, 0.77, 1.0):
            want = by_sorting(x, q)
            got = noise._quantiles(x, q)
            assert got.dtype == want.dtype and torch.equal(got, want), (x.dtype, q)
    assert noise._histograms(cases[1]) is not None  # the histograms' path
    assert noise._histograms(cases[-1]) is None
    big = torch.tensor([[0.0, float(noise._HISTOGRAM_BINS)]])
    assert noise._histograms(big) is None


def test_immerkaer_of_a_stack_is_each_frames_own_and_its_quantile_torchs():
    """:func:`immerkaer_sigmas` of a stack gives every frame the single-image estimate bit for
    bit (frames of other noise levels beside it change nothing), each near the noise added
    to a smooth ramp; its flat-pixel cut is ``torch.quantile``'s, ties and ends included."""
    from torch_stsdic.core.noise import _quantiles, immerkaer_sigmas

    gen = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.arange(96.0), torch.arange(80.0), indexing="ij")
    ramp = 40 + 0.3 * xx + 0.2 * yy
    sig = torch.tensor([0.5, 2.0, 4.0])
    stack = (ramp + sig.view(-1, 1, 1) * torch.randn(3, 96, 80, generator=gen)).float()
    for flat in (0.5, None):
        got = immerkaer_sigmas(stack, flat)
        own = [sts.estimate_noise_sigma(f, flat_fraction=flat) for f in stack]
        assert got.tolist() == own
        assert torch.allclose(got, sig.double(), rtol=0.12)
        assert immerkaer_sigmas(stack[1:2], flat).tolist() == own[1:2]
    x = torch.randint(0, 4, (5, 13), generator=gen).float()
    for q in (0.0, 0.25, 0.5, 0.9, 1.0):
        assert torch.equal(_quantiles(x, q), torch.quantile(x, q, dim=1))


def test_the_native_noise_estimate_equals_the_torch_code_to_the_bit(monkeypatch):
    """Immerkaer's estimate by the C++ kernels (two passes a frame: Sobel's histogram, then
    the flat pixels' Laplacian sum, both exact on whole-number grey levels) gives the torch
    code's numbers to the bit: 8, 12 and 16-bit levels, float32 and float64, flat fractions,
    a frame large enough that the cut is taken over every second magnitude, the smallest
    frames; fractional, NaN or out-of-range levels take the torch code."""
    from torch_stsdic.core import noise
    from torch_stsdic.kernels import native

    if not native.available():
        pytest.skip("no C++ compiler: the native kernels are not built")
    gen = torch.Generator().manual_seed(11)
    cases = [(torch.rand(4, 96, 131, generator=gen) * 255).round(),
             (torch.rand(3, 60, 47, generator=gen) * 4095).round().double(),
             (torch.rand(2, 40, 40, generator=gen) * 65535).round(),
             (torch.rand(1, 3, 3, generator=gen) * 9).round(),
             (torch.rand(2, 5, 11, generator=gen) * 3).round().double() - 1.0,
             torch.full((2, 9, 9), 7.0)]  # flat: every magnitude 0
    big = (torch.rand(1, 2004, 2004, generator=gen) * 255).round()  # 4 M magnitudes: step 2
    assert noise._cut_step(2002 * 2002) == 2
    calls = []
    native_mean = noise._native_flat_mean

    def counted(frames, q):
        out = native_mean(frames, q)
        calls.append(out is not None)
        return out

    def torch_only(frames, q):
        return None

    for x in [*cases, big]:
        for q in (0.5, 0.1, 0.9, 1.0):
            monkeypatch.setattr(noise, "_native_flat_mean", counted)
            got = noise.immerkaer_sigmas(x, q)
            assert calls.pop() is True
            monkeypatch.setattr(noise, "_native_flat_mean", torch_only)
            want = noise.immerkaer_sigmas(x, q)
            assert got.dtype == want.dtype and torch.equal(got, want), (tuple(x.shape), q)
            if x is big:
                break
    monkeypatch.setattr(noise, "_native_flat_mean", native_mean)
    # not whole numbers, NaN, beyond 20 bits: the torch code
    for x in (cases[0] + 0.5, torch.where(cases[0] > 250, torch.nan, cases[0]),
              cases[0] * 2.0 ** 13):
        assert noise._native_flat_mean(x, 0.5) is None
    with torch.no_grad():
        assert noise._native_flat_mean(cases[0], 0.5) is not None
