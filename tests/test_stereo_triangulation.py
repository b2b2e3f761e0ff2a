"""Triangulation (distortion removed, reprojection error, sensitivity) and the synthetic
stereo renderer's exact truth."""

import numpy as np
import torch

from torch_stsdic import DICConfig, grid_points
from torch_stsdic.stereo.matching import epipolar_candidates, match_stereo
from torch_stsdic.stereo.render import SurfaceMotion, make_rig, make_scene, render_stereo
from torch_stsdic.stereo.triangulation import (
    distort,
    project,
    propagate_std,
    triangulate,
    undistort,
)


def _points(n=200, seed=0):
    g = np.random.default_rng(seed)
    return torch.as_tensor(np.stack([g.uniform(-20, 20, n), g.uniform(-15, 15, n),
                                     g.uniform(250, 330, n)], 1))


def test_triangulation_is_exact_with_distortion():
    rig = make_rig((200, 240), distortion=(-0.4, 0.3, 2e-3, -1e-3, 0.1), skew=0.5)
    X = _points()
    pl, pr = project(X, rig.left), project(X, rig.right, rig.R, rig.T)
    tri = triangulate(rig, pl, pr)
    assert float((tri.X - X).abs().max()) < 1e-9
    assert float(tri.reprojection_error.max()) < 1e-9
    assert bool(tri.in_front.all())
    # (F, N, 2) batches and NaN pixels
    pl2 = torch.stack([pl, pl]).clone()
    pl2[1, 0] = float("nan")
    tri2 = triangulate(rig, pl2, torch.stack([pr, pr]))
    assert bool(torch.isnan(tri2.X[1, 0]).all()) and float((tri2.X[0] - X).abs().max()) < 1e-9


def test_undistort_inverts_distort():
    rig = make_rig(distortion=(-0.4, 0.3, 2e-3, -1e-3, 0.1))
    g = torch.Generator().manual_seed(0)
    q = (torch.rand(500, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2
    xd, yd = distort(q[:, 0], q[:, 1], torch.as_tensor(rig.left.dist))
    K = torch.as_tensor(rig.left.K)
    px = torch.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], 1)
    assert float((undistort(px, rig.left) - q).abs().max()) < 1e-13


def test_sensitivity_and_propagated_std():
    rig = make_rig(distortion=(-0.2, 0.1, 1e-3, 0, 0))
    X = _points(20)
    pl, pr = project(X, rig.left), project(X, rig.right, rig.R, rig.T)
    tri = triangulate(rig, pl, pr)
    h = 1e-4
    for j in range(4):
        d = torch.zeros(20, 4, dtype=torch.float64)
        d[:, j] = h
        xp = triangulate(rig, pl + d[:, :2], pr + d[:, 2:]).X
        xm = triangulate(rig, pl - d[:, :2], pr - d[:, 2:]).X
        fd = (xp - xm) / (2 * h)
        assert float((fd - tri.sensitivity[:, :, j]).abs().max()) < 1e-6
    # Monte Carlo of the propagated std
    g = torch.Generator().manual_seed(1)
    s = torch.tensor([0.02, 0.03, 0.02, 0.01], dtype=torch.float64)
    k = 4000
    noise = torch.randn(k, 4, generator=g, dtype=torch.float64) * s
    xs = triangulate(rig, pl[0] + noise[:, :2], pr[0] + noise[:, 2:]).X
    mc = xs.std(0)
    pred = propagate_std(tri.sensitivity[0], s)
    assert torch.allclose(mc, pred, rtol=0.08)


def test_renderer_truth_and_cross_match():
    """Noise-free render: the matched right points agree with the exact truth."""
    rig = make_rig((120, 150))
    scene = make_scene(rig, SurfaceMotion(translation=(0.01, 0.0, 0.02)))
    left, right = render_stereo(scene, [0.0], noise_sigma=0.0, quadrature=2, cutoff=5)
    pts = grid_points((120, 150), step=12, subset_size=21)
    truth = scene.truth(pts, [0.0, 3.0])
    assert float((truth["left"][0] - pts).abs().max()) < 1e-9  # texture_of_pixel inverts
    u = truth["U"][1]
    assert torch.allclose(u, torch.tensor([0.03, 0.0, 0.06], dtype=torch.float64)
                          .expand_as(u), atol=1e-12)
    cand, valid = epipolar_candidates(rig, pts, (120, 150), 11.0)
    assert float(valid.any(1).float().mean()) > 0.8  # the bottom row leaves the right image
    cm = match_stereo(rig, left[0], right[0], pts, DICConfig(subset_size=21, m=0))
    ok = cm.status <= 1
    assert int(ok.sum()) >= 0.5 * len(pts)
    err = (cm.right - truth["right"][0])[ok].norm(dim=1)
    assert float(err.max()) < 0.02, float(err.max())
    # points whose right subset is cut by the border are reported, not guessed
    inside = ((truth["right"][0] >= 9) & (truth["right"][0] <= torch.tensor([140, 110]))
              ).all(1)
    assert bool((~inside <= ~ok).all())
