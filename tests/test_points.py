"""Nearest neighbours of POIs: the cell search equals the full search."""

from __future__ import annotations

import torch

from torch_stsdic.analysis.points import _nearest_brute, nearest_among, nearest_points
from torch_stsdic.analysis.quality import neighbours


def test_nearest_points_by_cells_equals_the_full_search():
    gen = torch.Generator().manual_seed(0)
    cloud = torch.rand(6000, 2, generator=gen, dtype=torch.float64) * 900.0
    dense = torch.rand(1500, 2, generator=gen, dtype=torch.float64) * 40.0  # a cluster
    xs = torch.arange(0.0, 600.0, 7.0, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    for pts in (cloud, torch.cat([cloud, dense]), grid):
        for k in (9, 25):
            d, i = nearest_points(pts, k)
            d0, _ = _nearest_brute(pts, pts, k, 2048, torch.float64)
            assert torch.allclose(d, d0, atol=1e-4)  # the same distances (ties in any order)
            assert bool((i[:, 0] == torch.arange(len(pts))).all())  # itself first
            dd = (pts[i] - pts.unsqueeze(1)).norm(dim=-1)
            assert torch.allclose(dd, d, atol=1e-4)


def test_nearest_among_a_sample_by_cells_equals_the_full_search():
    """Queries among another, sparser set (the measuring pass's sample): inside its extent,
    off its edges and far outside it, on a grid (ties) and scattered."""
    gen = torch.Generator().manual_seed(1)
    xs = torch.arange(0.0, 980.0, 5.0, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    sample = grid[torch.linspace(0, len(grid) - 1, 1000).round().long().unique()]
    scattered = torch.rand(700, 2, generator=gen, dtype=torch.float64) * 600.0 + 100.0
    far = torch.tensor([[-500.0, -500.0], [3000.0, 40.0], [490.0, 1e6]], dtype=torch.float64)
    for pts, query in ((sample, torch.cat([grid, far])), (scattered, torch.cat([grid, far]))):
        for k in (1, 4, 9):
            d, i = nearest_among(query, pts, k)
            d0, _ = _nearest_brute(query, pts, k, 2048, torch.float64)
            assert i.shape == (len(query), k) and bool((i >= 0).all())
            assert torch.allclose(d, d0, atol=1e-9)  # the same distances (ties in any order)
            dd = (pts[i] - query.unsqueeze(1)).norm(dim=-1)
            assert torch.allclose(dd, d, atol=1e-9)
            assert bool((d[:, 1:] >= d[:, :-1]).all())  # nearest first


def test_grid_neighbours_equal_the_searched_ones():
    xs = torch.arange(0.0, 300.0, 10.0, dtype=torch.float64)
    pts = torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    pts = pts[torch.rand(len(pts), generator=torch.Generator().manual_seed(2)) > 0.15]
    nb = neighbours(pts)
    d, i = _nearest_brute(pts, pts, 9, 2048, torch.float64)
    want = torch.where(d[:, 1:] <= 2.5 * d[:, 1].median(), d[:, 1:], 0.0)
    got = torch.where(nb >= 0, (pts[nb.clamp(min=0)] - pts.unsqueeze(1)).norm(dim=-1), 0.0)
    assert torch.allclose(got.sort(1).values, want.sort(1).values)
