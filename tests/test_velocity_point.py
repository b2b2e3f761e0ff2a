"""Where a window's velocity refers to (movie/velocity_point.py): the subset's gradient-
weighted centroid, by the known answer of a one-sided texture, and the velocities of a
strain growing in time referred back to the POIs."""

import math

import numpy as np
import pytest
import torch
from renders import speckle_movie  # tests/ on the path

import torch_stsdic as sts
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.movie import velocity_point
from torch_stsdic.movie.velocity_point import refer_to_points, velocity_maps
from torch_stsdic.synth import Custom, ground_truth


def test_maps_are_the_gradient_weighted_centroid():
    """A texture varying in x alone, over the right half of the subset only: ut refers to
    the x-centroid of gx^2 (a known average over the textured columns), vt has no texture
    (no map), and a subset with no texture at all gets no map."""
    solver = SubsetSolver(sts.DICConfig(subset_size=21))
    x = torch.arange(80, dtype=torch.float64)
    cols = torch.where(x >= 40, torch.sin(2 * math.pi * x / 7.0), torch.zeros_like(x)) * 50
    img = solver.prepare((100 + cols).expand(80, 80).clone())
    offsets, weights = solver.window.offsets_and_weights()
    pts = torch.tensor([[40.0, 40.0]], dtype=torch.float64)
    maps = velocity_maps(img, pts, offsets, weights)
    _, gx, _ = img.sample_subsets(pts[:1, 0], pts[:1, 1], offsets[:, 0].to(img.dtype),
                                  offsets[:, 1].to(img.dtype))
    g2 = gx[0].double() ** 2
    want = float((g2 * offsets[:, 0]).sum() / g2.sum())
    assert want > 3.0  # the texture's side
    assert float(maps[0, 0, 0]) == pytest.approx(want, rel=1e-6)
    assert abs(float(maps[0, 0, 1])) < 1e-6  # symmetric in y
    assert torch.all(maps[0, 1] == 0)
    flat = solver.prepare(torch.full((80, 80), 100.0, dtype=torch.float64))
    assert torch.all(velocity_maps(flat, pts, offsets, weights) == 0)


def test_maps_wait_for_no_device():
    """The maps' 2 x 2 systems solved element-wise (``kernels.linalg.sym2_pinv``): no
    decomposition whose error check waits for a GPU (torch's ``pinv``), as
    ``scripts/benchmarks/count_syncs.py`` counts them; a block maps the subsets it moved."""
    from pathlib import Path

    from repo_scripts import load_script

    cs = load_script(Path("scripts/benchmarks/count_syncs.py"), "count_syncs")
    solver = SubsetSolver(sts.DICConfig(subset_size=21))
    g = torch.Generator().manual_seed(1)
    img = solver.prepare(torch.rand(80, 80, generator=g, dtype=torch.float64) * 200)
    offsets, weights = solver.window.offsets_and_weights()
    pts = torch.tensor([[30.0, 30.0], [45.0, 41.0], [50.0, 35.0]], dtype=torch.float64)
    with cs.SyncCounter() as c:
        maps = velocity_maps(img, pts, offsets, weights)
    assert torch.isfinite(maps).all()
    linalg = {k for k, v in cs.SYNCING.items() if v == "linalg error check"}
    assert linalg and not any(c.counts[k] for k in linalg), dict(c.counts)


def test_refer_to_points_takes_the_gradient_times_the_map_off():
    """A velocity field linear in space with a map: each point's bias is the map times the
    field's gradient, taken off (the gradient from plane fits of the biased field itself:
    the bias's own scatter leaves a few per cent); a shift adds the gradient times the
    shift; rows without a velocity stay NaN."""
    g = torch.stack(torch.meshgrid(torch.arange(0.0, 100, 10), torch.arange(0.0, 100, 10),
                                   indexing="xy"), -1).reshape(-1, 2).double()
    n = g.shape[0]
    a, b, c, d = 4e-4, -1e-4, 2e-4, 3e-4
    ut = (0.05 + a * g[:, 0] + b * g[:, 1]).expand(2, n).clone()
    vt = (-0.03 + c * g[:, 0] + d * g[:, 1]).expand(2, n).clone()
    rng = torch.Generator().manual_seed(0)
    maps = torch.randn(n, 2, 4, generator=rng, dtype=torch.float64)
    bias = maps @ torch.tensor([a, b, c, d], dtype=torch.float64)
    ut[1, 7] = float("nan")
    u2, v2 = refer_to_points(g, maps, ut + bias[:, 0], vt + bias[:, 1],
                             torch.ones(2, n, dtype=torch.bool))
    ok = torch.isfinite(u2)
    assert not bool(ok[1, 7]) and int((~ok).sum()) == 1
    big = float(bias.abs().max())  # 1.6e-3 px/frame
    assert float((u2[ok] - ut[ok]).abs().max()) < 0.1 * big
    assert float((v2[0] - vt[0]).abs().max()) < 0.1 * big
    shift = torch.zeros(2, n, 2, dtype=torch.float64)
    shift[0, 3] = torch.tensor([2.0, -1.0])
    u3, _ = refer_to_points(g, maps, ut + bias[:, 0], vt + bias[:, 1],
                            torch.ones(2, n, dtype=torch.bool), shift)
    assert float(u3[0, 3] - u2[0, 3]) == pytest.approx(-(2 * a - b), rel=0.05)


def test_velocities_of_a_growing_strain_refer_to_the_points(monkeypatch):
    """A strain growing linearly in time (the velocity varies in space): each point's
    velocity error, constant in time, follows its subset's centroid; referred to the
    points, the error falls and its random part meets the predicted std."""
    c = 60.0

    def fn(x, y, t):
        return 0.05 * t + 6e-4 * t * (x - c), -0.03 * t + 4e-4 * t * (y - c)

    times = torch.arange(0.0, 21)
    movie = speckle_movie(Custom(fn), times)

    def per_point_error(r):
        gt = ground_truth(Custom(fn), r.points.double(), times)
        e = torch.stack([r.ut.double()[1:] - gt["ut"][1:], r.vt.double()[1:] - gt["vt"][1:]])
        ok = torch.isfinite(e) & (r.status[1:] <= 1)
        e = torch.where(ok, e, torch.nan)
        e = e - torch.nanmean(e, -1, keepdim=True)  # each frame's mean taken out
        p = torch.stack([r.std["ut"].double()[1:], r.std["vt"].double()[1:]])[ok]
        return (float(torch.nanmean(e, 1).pow(2).nanmean().sqrt()),  # constant in time
                float(torch.nanmean(e ** 2).sqrt() / p.pow(2).mean().sqrt()))

    res = sts.track(movie, config=sts.DICConfig(m=4), step=10, progress=False)
    const, honesty = per_point_error(res)
    monkeypatch.setattr(velocity_point, "refer_to_points", lambda pts, maps, ut, vt, *a, **k:
                        (ut, vt))
    raw = sts.track(movie, config=sts.DICConfig(m=4), step=10, progress=False)
    const_raw, honesty_raw = per_point_error(raw)
    assert np.isfinite(const) and const < 0.7 * const_raw, (const, const_raw)
    assert honesty < honesty_raw and 0.8 < honesty < 1.25, (honesty, honesty_raw)
