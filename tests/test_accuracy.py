"""Accuracy beyond the single-reference floor: the template's gauge from the trajectories
(``refine_reference``), off-grid points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic.core.offgrid import carry_params
from torch_stsdic.movie.refine import fit_intercepts
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
    """The template's gauge from the trajectories (``refine_reference=True``) on a 41-frame
    movie linear in time, STS m = 2: measured 0.37x classical DIC against the single
    reference, the template alone 0.49x (its registration, common to every frame, is what
    the trajectories' fits take out); without the fits' gauge the test fails (> 0.42x)."""
    motion = Translation(ut=0.05)
    movie = _movie(41, motion)
    pts = _grid()
    cfg0, cfg2 = sts.DICConfig(m=0, dtype="float32"), sts.DICConfig(m=2, dtype="float32")
    classical = sts.track(movie, points=pts, config=cfg0, progress=False,
                          series_reference=False)
    plain = sts.track(movie, points=pts, config=cfg2, progress=False)  # the template
    refined = sts.track(movie, points=pts, config=cfg2, progress=False, refine_reference=True)
    e0, e_plain, e_ref = (_rms(r, motion, pts) for r in (classical, plain, refined))
    assert e_plain > 0.45 * e0  # the template's registration floor (0.49x measured)
    assert e_ref < 0.42 * e0, (e_ref / e0, e_plain / e0)
    assert e_ref < 0.85 * e_plain
    truth = ground_truth(motion, pts, refined.times.numpy())["u"].numpy()
    # mean error over the 81 points (of one movie): -4.1e-3 px measured (the template alone
    # -7.4e-3: its registration is smooth in space, so the mean over a 121 px image keeps it)
    assert abs(float(np.mean(refined.u.numpy() - truth))) < 6e-3
    info = refined.info["refine_reference"]
    assert info["refined"] == len(pts) and info["frames_median"] == 40  # all but the reference
    assert 0.3 < info["shrink"] < 0.7 and 0.1 < info["rho"] < 0.5, info  # 0.48, 0.25
    # velocities have no offset: as the template measured them
    same = np.isfinite(plain.ut.numpy()) & np.isfinite(refined.ut.numpy())
    assert same[1:].mean() > 0.95
    np.testing.assert_allclose(refined.ut.numpy()[same], plain.ut.numpy()[same], atol=5e-5)
    # the reference's own row is the truth (zero displacement, gradients, std)
    assert refined.ok[0].all()
    for name in ("u", "v", "ux", "uy", "vx", "vy", "u_std", "v_std"):
        assert np.all(refined.field(name).numpy()[0] == 0.0), name
    # the predicted std is the template's (it counts the registration in full): measured
    # error / predicted 0.91 (the template alone 1.21)
    std = np.stack([refined.field("u_std").numpy(), refined.field("v_std").numpy()])[:, 3:-3]
    assert 0.75 < e_ref / np.sqrt(np.mean(std**2)) < 1.1


def test_refined_reference_with_a_noisier_reference():
    """Noise std 5 on the reference, 1 on the frames: the template's registration to the
    reference frame carries that frame's noise (0.42x the single reference's error, measured),
    and the trajectories' fits remove it (0.15x: rho 1.9 per-frame variances, below the 3.0
    the reference's noise allows, shrink 0.9). The reference's own zero kept in the fit
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
    template = sts.track(movie, points=pts, config=cfg, progress=False)
    refined = sts.track(movie, points=pts, config=cfg, progress=False, refine_reference=True)
    e_plain, e_ref = _rms(plain, motion, pts), _rms(refined, motion, pts)
    assert e_ref < 0.3 * e_plain, (e_ref, e_plain)
    assert e_ref < 0.5 * _rms(template, motion, pts)
    info = refined.info["refine_reference"]
    assert info["rho"] > 1.0 and info["shrink"] > 0.8, info


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
