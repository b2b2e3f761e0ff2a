"""Accuracy beyond the single-reference floor: refined reference, off-grid points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic.core.offgrid import carry_params
from torch_stsdic.movie.refine import fit_intercepts, predicted_profile
from torch_stsdic.synth import (
    HomogeneousStrain,
    Translation,
    ground_truth,
    make_speckle,
    render_series,
)

SIZE = (121, 121)
SAMPLE12 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "dic-challenge-sample12"


def _movie(n_frames: int, motion, seed: int = 1, sigma: float = 5.0) -> torch.Tensor:
    """(n_frames, H, W) float32: frame 0 is the reference, noise on every image."""
    pat = make_speckle(SIZE, radius=2.0, seed=seed)
    ref, frames = render_series(pat, SIZE, motion, torch.arange(1, n_frames),
                                noise_sigma=sigma, seed=seed + 10)
    return torch.cat([ref[None], frames]).float()


def _grid(offset: float = 0.0) -> np.ndarray:
    g = np.arange(25.0, 97.0, 8.0) + offset
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel()], 1)


def _rms(res, motion, pts, rows=slice(3, -3)) -> float:
    truth = ground_truth(motion, pts, res.times.numpy())
    eu = (res.u.numpy() - truth["u"].numpy())[rows]
    ev = (res.v.numpy() - truth["v"].numpy())[rows]
    return float(np.sqrt(np.mean(eu**2 + ev**2) / 2))


# ---- refined reference ----------------------------------------------------------------
def test_fit_intercepts_linear_and_quadratic():
    rng = np.random.default_rng(0)
    t = np.arange(41.0)
    n, sig = 400, 0.02
    off = rng.normal(0, 0.02, n)
    lin = off + 0.05 * t[:, None] + rng.normal(0, sig, (41, n))
    quad = off + 0.003 * t[:, None] ** 2 + rng.normal(0, sig, (41, n))
    # + the odd, 1-px periodic interpolation bias of a sub-pixel shift (0.05 t px): absorbed
    biased = lin + 0.01 * np.sin(2 * np.pi * 0.05 * t[:, None])
    for y, deg in ((lin, 1), (quad, 2), (biased, 1)):
        y = y.copy()
        y[0] = 0.0  # the reference against itself: 0, whatever the offset (left out)
        res = fit_intercepts(t, {"u": y, "v": y.copy()})
        err = res.values["u"] - off
        # predicted intercept std of the chosen fit (frames 1..40): linear ~ sig * 0.32,
        # quadratic ~ sig * 0.48, times sqrt(rho / (rho + d)) ~ 0.95 after the shrink; a
        # 5-frame fit would give ~ sig * 0.9
        assert np.sqrt(np.mean(err**2)) < sig * (0.4 if deg == 1 else 0.6)
        assert abs(err.mean()) < 3 * sig / np.sqrt(n)
        assert np.mean(res.degree == deg) > 0.9
        assert np.median(res.frames) == 40
        assert 0.6 < res.rho < 1.6  # var(off) / sig^2 = 1
        np.testing.assert_allclose(np.median(res.sigma), sig, rtol=0.2)


def test_fit_intercepts_short_series_keeps_the_line():
    """Ten frames (the reference and 9): the trajectory's noise is known from 6 third
    differences only, so the curvature test uses Student's t at their degrees of freedom; with
    the normal's 3 it rejected 4 % (white noise) to 12 % (renders) of straight trajectories,
    whose short extrapolated fits then did worse than no refinement."""
    rng = np.random.default_rng(1)
    t = np.arange(10.0)
    n = 4000
    off = rng.normal(0, 1.0, n)
    y = off + 0.05 * t[:, None] + rng.normal(0, 1.0, (10, n))
    y[0] = 0.0
    res = fit_intercepts(t, {"u": y, "v": y.copy()})
    assert np.mean((res.frames == 9) & (res.degree == 1)) > 0.97
    # shrunk intercept of a 9-frame line: rho d / (rho + d) = 0.35 (d = 0.53, rho = 1)
    assert np.sqrt(np.mean((res.values["u"] - off) ** 2)) < 0.65
    assert 0.7 < res.rho < 1.4


def test_fit_intercepts_unusable_points_get_no_offset():
    t = np.arange(9.0)
    y = np.full((9, 2), np.nan)
    y[:, 0] = 0.1 * t + 0.01
    res = fit_intercepts(t, {"u": y, "v": y})
    assert res.frames[1] == 0 and res.values["u"][1] == 0.0


def test_refined_reference_lifts_the_floor():
    """STS m=2 with the refined reference below 0.6x classical (0.77x is the single-reference
    floor, ~0.35x predicted), no bias; without refinement the test fails (> 0.7x)."""
    motion = Translation(ut=0.05)
    movie = _movie(41, motion)
    pts = _grid()
    cfg0, cfg2 = sts.DICConfig(m=0, dtype="float32"), sts.DICConfig(m=2, dtype="float32")
    single = dict(series_reference=False)  # the refined reference against the single one
    classical = sts.track(movie, points=pts, config=cfg0, progress=False, **single)
    plain = sts.track(movie, points=pts, config=cfg2, progress=False, **single)
    refined = sts.track(movie, points=pts, config=cfg2, progress=False, refine_reference=True)
    e0, e_plain, e_ref = (_rms(r, motion, pts) for r in (classical, plain, refined))
    assert e_plain > 0.7 * e0  # the single-reference floor
    assert e_ref < 0.6 * e0
    truth = ground_truth(motion, pts, refined.times.numpy())["u"].numpy()
    # no bias: the mean over 81 points of per-point offsets of ~10e-3 px has a std of ~1.1e-3
    # px (one movie), so 4e-3 is a 3.5 sigma bound; the bias study over seeds and crops is
    # scripts/validation/refined_reference.py (docs/accuracy.md)
    assert abs(float(np.mean(refined.u.numpy() - truth))) < 4e-3
    info = refined.info["refine_reference"]
    assert info["refined"] == len(pts) and info["frames_median"] == 40  # all but the reference
    # velocities have no reference offset: unchanged
    np.testing.assert_allclose(refined.ut.numpy(), plain.ut.numpy(), atol=5e-5)  # solver tol
    # the reference's own row is the truth (zero displacement, gradients, std), not minus the
    # fitted offset (~15e-3 px RMS before)
    assert refined.ok[0].all()
    for name in ("u", "v", "ux", "uy", "vx", "vy", "u_std", "v_std"):
        assert np.all(refined.field(name).numpy()[0] == 0.0), name
    # the error grows away from the reference as the first-order theory says (the offset's
    # error shares the frames' noise: lower near the reference, higher at the far end of the
    # fitted line), and no more: a term in the displacement (e.g. a gain error from the noisy
    # reference gradient) would show here. Bands of 8 frames, ratio far / near.
    err = np.stack([refined.u.numpy() - truth, refined.v.numpy()])  # (2, T, N)
    near, far = slice(3, 11), slice(30, 38)
    e0 = np.stack([classical.u.numpy() - truth, classical.v.numpy()])[:, 1:]
    a_f2 = np.mean(np.var(e0, axis=1, ddof=1))
    rho = (np.mean(e0.mean(1) ** 2) - a_f2 / e0.shape[1]) / a_f2  # var(offset) / a_f^2
    var = predicted_profile(refined.times.numpy(), 0, range(1, 41), 2, rho, info["shrink"])
    ratio = np.sqrt(np.mean(err[:, far] ** 2) / np.mean(err[:, near] ** 2))
    pred = np.sqrt(var[far].mean() / var[near].mean())  # ~1.5
    assert 0.75 < ratio / pred < 1.33, (ratio, pred)
    # and the level: within 25 % of the prediction over frames 3..37
    level = np.sqrt(np.mean(err[:, 3:-3] ** 2) / (a_f2 * var[3:-3].mean()))
    assert 0.8 < level < 1.25, level
    # the stored predicted std follows: the refined error, not the unrefined one (2.4x
    # higher), in every band of frames, growing with them
    std = np.stack([refined.field("u_std").numpy(), refined.field("v_std").numpy()])
    for band in (slice(1, 3), near, slice(15, 25), far):
        r = np.sqrt(np.mean(err[:, band] ** 2) / np.mean(std[:, band] ** 2))
        assert 0.75 < r < 1.33, (band, r)
    assert np.sqrt(np.mean(std[:, far] ** 2) / np.mean(std[:, near] ** 2)) > 1.2


def test_refined_reference_with_a_noisier_reference():
    """Noise std 5 on the reference, 1 on the frames: the reference's offset is nearly all of
    the error, and the refinement removes it (the offset's variance over the points, rho ~ 25
    per-frame variances, is estimated: no shrink). The reference's own zero kept in the fit
    made a step no line passed (short quadratic fits: 0.53x the unrefined error here, 0.9x
    with clean frames)."""
    motion = Translation(ut=0.05)
    pat = make_speckle(SIZE, radius=2.0, seed=3)
    ref, frames = render_series(pat, SIZE, motion, torch.arange(1, 21))
    g = torch.Generator().manual_seed(5)
    ref = ref + 5.0 * torch.randn(ref.shape, generator=g, dtype=ref.dtype)
    frames = frames + 1.0 * torch.randn(frames.shape, generator=g, dtype=frames.dtype)
    movie = torch.cat([ref[None], frames]).float()
    pts = _grid()
    cfg = sts.DICConfig(m=2, dtype="float32")
    plain = sts.track(movie, points=pts, config=cfg, progress=False, series_reference=False)
    refined = sts.track(movie, points=pts, config=cfg, progress=False, refine_reference=True)
    e_plain, e_ref = _rms(plain, motion, pts), _rms(refined, motion, pts)
    assert e_ref < 0.3 * e_plain, (e_ref, e_plain)
    info = refined.info["refine_reference"]
    assert info["rho"] is None or info["rho"] > 5 and info["shrink"] > 0.95


def test_refine_reference_refuses_what_it_cannot_do():
    movie = _movie(6, Translation(ut=0.05))
    with pytest.raises(ValueError, match="refine_reference"):
        sts.track(movie, reference=movie[0].numpy(), progress=False, refine_reference=True)
    with pytest.raises(ValueError, match="refine_reference"):
        sts.track(movie, reference="0:3", progress=False, refine_reference=True)
    with pytest.raises(ValueError, match="refine_reference"):
        sts.track(movie, progress=False, refine_reference=True, reference_update=0.9)
    with pytest.raises(ValueError, match="refine_frames"):
        sts.track(movie, progress=False, refine_frames=9)


# ---- off-grid points ---------------------------------------------------------------------
def test_carry_params_is_exact_for_polynomials():
    names = ("u", "ux", "uy", "uxx", "uxy", "uyy", "ut", "v", "vx", "vy", "vxx", "vxy", "vyy",
             "vt")
    g = torch.Generator().manual_seed(0)
    p = torch.randn(5, len(names), dtype=torch.float64, generator=g) * 0.1
    d = torch.rand(5, 2, dtype=torch.float64, generator=g) - 0.5
    q = carry_params(p, names, d)
    i = {nm: k for k, nm in enumerate(names)}

    def field(par, c, x, y):
        return (par[:, i[c]] + par[:, i[c + "x"]] * x + par[:, i[c + "y"]] * y
                + 0.5 * par[:, i[c + "xx"]] * x * x + par[:, i[c + "xy"]] * x * y
                + 0.5 * par[:, i[c + "yy"]] * y * y)

    x, y = torch.tensor(0.3, dtype=torch.float64), torch.tensor(-0.2, dtype=torch.float64)
    for c in ("u", "v"):  # the same field, expanded about the old and the new centre
        torch.testing.assert_close(field(q, c, x, y), field(p, c, x + d[:, 0], y + d[:, 1]))
    torch.testing.assert_close(q[:, i["ut"]], p[:, i["ut"]])


def test_off_grid_points_at_the_grid_floor():
    """Classical DIC at points between pixels within 10 % of the same points on the grid
    (without the snap the reference noise's share grows by ~1/3)."""
    motion = Translation(ut=0.05) + HomogeneousStrain(exx=2e-3, eyy=-1e-3, exy=5e-4,
                                                         center=(60.0, 60.0), rate=1.0)
    movie = _movie(12, motion, seed=4)
    cfg = sts.DICConfig(m=0, dtype="float32")
    on, off = _grid(), _grid() + np.array([0.37, -0.41])
    r_on = sts.track(movie, points=on, config=cfg, progress=False)
    r_off = sts.track(movie, points=off, config=cfg, progress=False)
    e_on, e_off = _rms(r_on, motion, on, slice(1, None)), _rms(r_off, motion, off, slice(1, None))
    assert e_off < 1.1 * e_on
    assert e_off > 0.9 * e_on


def test_average_formulation_is_retired_into_joint_average():
    with pytest.warns(DeprecationWarning, match="joint\\+average"):
        cfg = sts.DICConfig(formulation="average")
    assert cfg.formulation == "joint+average"


@pytest.mark.skipif(not SAMPLE12.is_dir(), reason=f"real series not found at {SAMPLE12}")
def test_average_converges_on_a_real_series():
    """Frames 0..6 of a real loading series: the retired "average" (now joint+average)
    converges where joint does (the averaged image alone converged at 1.7 % on sample 3)."""
    files = sorted(SAMPLE12.glob("*.tif*"))[:7]
    with pytest.warns(DeprecationWarning):
        cfg = sts.DICConfig(m=2, formulation="average", dtype="float32")
    # checks=False: the solver's convergence itself (the checks mark the background and the
    # specimen's edges POOR_FIT whatever the formulation)
    res = sts.track([str(f) for f in files], step=60, config=cfg, progress=False, checks=False)
    assert float((res.status == 0).float().mean()) > 0.9


def test_nn_off_grid_points_are_carried_differentiably():
    from torch_stsdic.nn import STSDIC

    motion = Translation(ut=0.05) + HomogeneousStrain(exx=2e-3, center=(60.0, 60.0), rate=1.0)
    movie = _movie(5, motion, seed=5, sigma=2.0).double()
    cfg = sts.DICConfig(m=1, subset_size=17, tol=1e-8)
    on = torch.tensor(_grid()[:6])
    off = (on + torch.tensor([0.3, -0.2], dtype=torch.float64)).requires_grad_(True)
    mod = STSDIC(cfg)
    out_on = mod.forward_full(movie[:1], movie[1:4][None], on)
    out_off = mod.forward_full(movie[:1], movie[1:4][None], off)
    names = out_on.param_names
    expect = carry_params(out_on.params[0], names, (off - on).detach())
    torch.testing.assert_close(out_off.params[0], expect)
    truth = ground_truth(motion, off.detach().numpy(), [2.0])["u"][0]
    assert (out_off.disp[0, :, 0] - truth).abs().max() < 0.05
    out_off.disp[..., 0].sum().backward()  # d u / d x = the measured ux
    torch.testing.assert_close(off.grad[:, 0], out_off.params[0, :, names.index("ux")],
                               atol=1e-6, rtol=1e-4)


def test_off_centre_subsets_are_the_centred_solution_carried():
    """``centres=``: the subset centred elsewhere, its solution carried to the POI. Equal to
    solving at the centres and carrying the parameters (u += ux dx + uy dy) and the std
    (sqrt(sd_u^2 + (dy sd_uy)^2)) by hand; on a strain field, near the truth at the POI."""
    from torch_stsdic.core.offgrid import carry_std

    motion = Translation(ut=0.05) + HomogeneousStrain(exx=2e-3, eyy=-3e-3, exy=1e-3,
                                                         center=(60.0, 60.0), rate=1.0)
    movie = _movie(4, motion, seed=6, sigma=2.0).double()
    cfg = sts.DICConfig(m=1, subset_size=17)
    pts = torch.tensor(_grid()[:12])
    shift = torch.tensor([0.0, 7.0], dtype=torch.float64).expand(12, 2)
    off = sts.solve_window(movie[0], movie[1:4], pts, config=cfg, centres=pts + shift)
    at_c = sts.solve_window(movie[0], movie[1:4], pts + shift, config=cfg)
    names = at_c.param_names
    torch.testing.assert_close(off.params, carry_params(at_c.params, names, -shift),
                               atol=2e-6, rtol=0)
    torch.testing.assert_close(off.std, carry_std(at_c.std, names, -shift), atol=1e-7,
                               rtol=1e-5)
    i, iy = names.index("u"), names.index("uy")
    expect = torch.sqrt(at_c.std[:, i] ** 2 + (7.0 * at_c.std[:, iy]) ** 2)
    torch.testing.assert_close(off.std[:, i], expect)
    assert bool((off.std[:, i] > at_c.std[:, i]).all())
    truth = ground_truth(motion, pts.numpy(), [2.0])
    assert float((off.u - truth["u"][0]).abs().max()) < 0.05
    assert float((off.v - truth["v"][0]).abs().max()) < 0.05
    with pytest.raises(ValueError, match="centres"):
        sts.solve_window(movie[0], movie[1:4], pts, config=cfg, centres=pts[:3])
