"""Status that tells the truth: the model, fit and neighbour checks, and windows that adapt
to motions the affine-in-time model cannot follow (rotation, acceleration, a crack).

The family tests render small movies with noise on every image and count, over point-frames
whose subset stays inside the image: the share trusted (usable status) and the share of
trusted results off by more than 0.1 px. Before the checks existed, STS (m = 2) reported
96 % of a 4 deg/frame rotation, 80 % of the accelerated motion and 24 % of the crack movie
wrong while marked CONVERGED.
"""

from __future__ import annotations

import pytest
import torch

from torch_stsdic import DICConfig, track
from torch_stsdic.quality import (
    median_test,
    model_mismatch,
    neighbours,
    poor_fit,
    residual_mismatch,
)
from torch_stsdic.status import Status, usable
from torch_stsdic.synth import (
    Translation,
    ground_truth,
    make_speckle,
    motion_family,
    render_series,
)

SIZE = 161


def test_model_mismatch_is_a_noise_scaled_test():
    std_c = torch.full((4, 2), 0.02)
    std_s = torch.full((4, 2), 0.012)  # var_c - var_s = 0.000256: sd 0.016 (+0.005 tol)
    d_c = torch.zeros(4, 2)
    d_s = torch.tensor([[0.03, 0.0], [0.0, -0.045], [0.06, 0.0], [float("nan"), 0.0]])
    # allowed: 3 * sqrt(0.016^2 + 0.005^2) = 0.050 px
    assert model_mismatch(d_s, d_c, std_s, std_c).tolist() == [False, False, True, True]


def test_residual_mismatch_scales_with_the_subset_and_skips_noise_free_matches():
    sig_c = torch.full((4,), 2.0)
    sig_w = torch.tensor([2.1, 2.5, 3.0, 3.0])
    zncc = torch.tensor([0.99, 0.99, 0.99, 0.99999])
    # 21 x 21: limit 1 + 6/21 = 1.29 (2.57 grey levels); the last is a noise-free match
    assert residual_mismatch(sig_w, sig_c, 441, zncc).tolist() == [False, False, True, False]
    # 11 x 11: limit 1 + 6/11 = 1.55 (3.09): nothing flagged
    assert not bool(residual_mismatch(sig_w, sig_c, 121, zncc).any())


def test_poor_fit_residual_and_zncc():
    sigma = torch.cat([torch.full((30,), 2.0), torch.tensor([4.5, 2.1])])
    zncc = torch.cat([torch.full((31,), 0.99), torch.tensor([0.5])])
    solved = torch.ones(32, dtype=torch.bool)
    bad = poor_fit(sigma, zncc, solved, zncc_floor=0.8)
    assert torch.nonzero(bad).flatten().tolist() == [30, 31]
    # a frame matched against itself: round-off residuals around a median of ~0 are no misfit
    tiny = torch.rand(40, generator=torch.Generator().manual_seed(0)) * 1e-3
    assert not bool(poor_fit(tiny, torch.full((40,), 0.999999), torch.ones(40, dtype=torch.bool),
                             zncc_floor=0.8).any())


def _grid(n=7, step=10.0):
    ys, xs = torch.meshgrid(torch.arange(n) * step, torch.arange(n) * step, indexing="ij")
    return torch.stack([xs.flatten(), ys.flatten()], 1).double()


def test_median_test_flags_outliers_not_linear_fields_or_noise():
    pts = _grid()
    gen = torch.Generator().manual_seed(0)
    # a rotation-like linear field with large gradients (3.5 px between neighbours)
    gu = torch.tensor([-0.05, -0.35], dtype=torch.float64)
    gv = torch.tensor([0.35, -0.05], dtype=torch.float64)
    u = pts @ gu + 0.01 * torch.randn(49, generator=gen, dtype=torch.float64)
    v = pts @ gv + 0.01 * torch.randn(49, generator=gen, dtype=torch.float64)
    vals = torch.stack([u, v], -1)[None]
    grads = torch.stack([gu, gv])[None, None].expand(1, 49, 2, 2)
    nb = neighbours(pts)
    ok = torch.ones(1, 49, dtype=torch.bool)
    clean = median_test(vals, ok, nb, 0.05, points=pts, gradients=grads)
    assert not bool(clean.any())  # corners and edges included
    bad = vals.clone()
    bad[0, 0, 0] += 0.5  # a corner point off by 0.5 px
    bad[0, 24, 1] -= 0.3  # the centre point
    out = median_test(bad, ok, nb, 0.05, points=pts, gradients=grads)
    assert torch.nonzero(out[0]).flatten().tolist() == [0, 24]


def _family(motion, n_frames=8, noise=2.0, seed=0):
    times = torch.arange(1.0, n_frames + 1.0)
    pattern = make_speckle((SIZE, SIZE), seed=seed, margin=SIZE)
    ref, frames = render_series(pattern, (SIZE, SIZE), motion, times, noise_sigma=noise,
                                seed=seed + 1)
    return torch.cat([ref[None], frames]).float(), times


def _scores(res, motion, times, subset):
    pts = res.points.double()
    truth = ground_truth(motion, pts, times)
    r = (subset // 2 + 2) * 1.5
    xd, yd = pts[:, 0] + truth["u"], pts[:, 1] + truth["v"]
    inside = (xd >= r) & (xd <= SIZE - 1 - r) & (yd >= r) & (yd <= SIZE - 1 - r)
    ok = torch.as_tensor(usable(res.status[1:])) & inside
    err = torch.hypot(res.u[1:].double() - truth["u"], res.v[1:].double() - truth["v"])
    trusted = float(ok.sum()) / float(inside.sum())
    wrong = float((ok & (err > 0.1)).sum()) / max(float(ok.sum()), 1.0)
    return trusted, wrong, res.m[1:][ok]


@pytest.mark.parametrize("family", ["rotation4", "acceleration", "crack"])
def test_sts_is_trusted_only_where_right(family):
    motion = motion_family(family, SIZE, t_jump=4.0)
    series, times = _family(motion)
    subset = 25
    # the model check alone (a uniform acceleration is also a shared motion: see below)
    res = track(series, config=DICConfig(m=2, subset_size=subset), step=16, progress=False,
                shared_motion=None)
    trusted, wrong, m_used = _scores(res, motion, times, subset)
    assert wrong <= 0.01, f"{wrong:.1%} of trusted results off by > 0.1 px"
    assert trusted >= 0.8, f"only {trusted:.1%} trusted"
    assert int(m_used.min()) >= 0 and int(m_used.max()) <= 2
    assert float((m_used < 2).float().mean()) > 0.05  # the windows did adapt
    # where the window was shortened to classical, no velocity is claimed
    classical = (res.m == 0) & torch.as_tensor(usable(res.status))
    assert bool(torch.isnan(res.ut[classical]).all())
    # with the shared motion (the default) every family stays right, and a uniform
    # acceleration -- the same curve at every point -- keeps its full windows
    res = track(series, config=DICConfig(m=2, subset_size=subset), step=16, progress=False)
    trusted, wrong, m_used = _scores(res, motion, times, subset)
    assert wrong <= 0.01 and trusted >= 0.8, (wrong, trusted)
    if family == "acceleration":
        assert res.shared_motion.applied and float((m_used == 2).float().mean()) > 0.95


def test_linear_motion_keeps_full_windows_and_std_matches_scatter():
    motion = Translation(ut=0.05, vt=-0.03)
    series, times = _family(motion, n_frames=10, noise=3.0, seed=4)
    res = track(series, config=DICConfig(m=2, subset_size=21), step=12, progress=False)
    ok = torch.as_tensor(usable(res.status[1:]))
    assert float(ok.float().mean()) > 0.97
    assert float((res.m[1:][ok] == 2).float().mean()) > 0.97  # few false alarms (3 sigma)
    truth = ground_truth(motion, res.points.double(), times)
    err = (res.u[1:].double() - truth["u"])[ok]
    # the predicted std of u is the measured scatter (within 25 %)
    ratio = float(err.std() / res.std["u"][1:][ok].double().mean())
    assert 0.75 < ratio < 1.33, ratio


def test_status_codes_documented():
    assert Status.POOR_FIT == 6 and Status.INCONSISTENT == 7
    assert "poor_fit" in Status.describe()


def test_median_test_flags_a_patch_of_wild_values_not_a_jump():
    """Subsets across a specimen's edge find peaks px apart: a patch of wild values, each as
    far from its neighbours as they are from each other, which the normalised residual alone
    cannot judge. The patch is flagged; a 0.5 px jump (a crack) beside a smooth field is not
    wild, only its outliers would be."""
    n = 9
    pts = _grid(n)
    gen = torch.Generator().manual_seed(1)
    u = 0.01 * torch.randn(n * n, generator=gen, dtype=torch.float64)
    v = 0.01 * torch.randn(n * n, generator=gen, dtype=torch.float64)
    x = pts[:, 0]
    vals = torch.stack([u + 0.5 * (x >= 45), v], -1)[None]  # a crack at x = 45
    nb = neighbours(pts)
    ok = torch.ones(1, n * n, dtype=torch.bool)
    assert not bool(median_test(vals, ok, nb, 0.05).any())
    wild = vals.clone()
    patch = (x <= 20) & (pts[:, 1] <= 30)  # 3 x 4 points in a corner
    wild[0, patch] += 20.0 * torch.randn(int(patch.sum()), 2, generator=gen,
                                          dtype=torch.float64)
    out = median_test(wild, ok, nb, 0.05)[0]
    assert bool(out[patch].all())
    far = (x >= 40)  # beyond the patch's neighbourhood: untouched
    assert not bool(out[far].any())
