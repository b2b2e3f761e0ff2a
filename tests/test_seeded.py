"""Seeded initial guess: FFT at one POI per cell, neighbours start from their seed."""

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core.initial import carry_from_seed, seed_cells
from torch_stsdic.core.shape import AffineShape

SIZE = (121, 121)


@pytest.fixture(scope="module")
def pattern():
    return synth.make_speckle(SIZE, seed=11)


def _dense(lo=20, hi=101, step=4):
    c = torch.arange(lo, hi, step, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)


def test_seed_cells_pick_the_point_nearest_each_cell_centre():
    pts = torch.tensor([[1.0, 1.0], [5.0, 5.0], [9.0, 9.0], [12.0, 1.0], [5.0, 5.0]])
    group = torch.tensor([0, 0, 0, 0, 1])
    cell, seeds = seed_cells(pts, group, 10.0)
    assert seeds.numel() == 3  # (0,0) of group 0, (1,0) of group 0, (0,0) of group 1
    assert cell[0] == cell[1] == cell[2] and len({int(cell[3]), int(cell[0]), int(cell[4])}) == 3
    assert int(seeds[cell[0]]) == 1  # (5, 5) is nearest the centre of [0, 10)^2
    assert int(seeds[cell[3]]) == 3 and int(seeds[cell[4]]) == 4
    # every seed belongs to its own cell
    assert torch.equal(cell[seeds], torch.arange(seeds.numel()))


def test_carry_from_seed_is_exact_for_affine_fields():
    shape = AffineShape(temporal=True)
    # u = 0.3 + 0.01 dx - 0.02 dy + 0.05 dt ; v = -1 + 0.003 dx + 0.004 dy - 0.01 dt
    p = torch.tensor([[0.3, 0.01, -0.02, 0.05, -1.0, 0.003, 0.004, -0.01]], dtype=torch.float64)
    off = torch.tensor([[7.0, -3.0]], dtype=torch.float64)
    q = carry_from_seed(shape, p, off)
    assert q[0, 0] == pytest.approx(0.3 + 0.07 + 0.06)
    assert q[0, 4] == pytest.approx(-1.0 + 0.021 - 0.012)
    assert torch.equal(q[0, [1, 2, 3, 5, 6, 7]], p[0, [1, 2, 3, 5, 6, 7]])


@pytest.mark.parametrize("m", [0, 1])
def test_seeded_equals_fft_on_a_smooth_field(pattern, m):
    motion = synth.HomogeneousStrain(exx=0.02, eyy=-0.01, exy=0.005, omega=0.02,
                                     center=(60, 60)) + synth.Translation(2.6, -1.7, ut=0.2)
    times = torch.arange(0.0, 2 * m + 1, dtype=torch.float64)
    ref, frames = synth.render_series(pattern, SIZE, motion, times, noise_sigma=1.0, seed=1,
                                      reference_time=None)
    fr = frames if m else frames[0]
    pts = _dense()
    seeded = sts.solve_window(ref, fr, pts, config=sts.DICConfig(m=m, dtype="float64"))
    info = seeded.info["initial_guess"]
    assert info["method"] == "seeded"
    assert info["seeds"] * 4 <= pts.shape[0]
    fft = sts.solve_window(ref, fr, pts,
                           config=sts.DICConfig(m=m, dtype="float64", initial_guess="fft"))
    assert fft.info["initial_guess"]["method"] == "fft"
    assert bool(seeded.ok.all()) and bool(fft.ok.all())
    assert torch.allclose(seeded.params, fft.params, atol=1e-3)
    u_true, v_true = motion.displacement(pts[:, 0], pts[:, 1], float(times[m]))
    assert (seeded.u - u_true).abs().max() < 0.02
    assert (seeded.v - v_true).abs().max() < 0.02


def test_seeded_recovers_across_a_displacement_jump(pattern):
    """A crack at x = 60: the right part slides 7 px down. Cells that straddle the crack
    start some POIs from a seed on the other side; those must be redone from FFT."""

    def fn(x, y, t):
        right = (x >= 60).double()
        return torch.zeros_like(x) + 0.2, 7.0 * right

    motion = synth.Custom(fn, gradient_fn=lambda x, y, t: (torch.zeros_like(x),) * 4)
    ref, frames = synth.render_series(pattern, SIZE, motion, torch.tensor([1.0]),
                                      noise_sigma=0.5, seed=2, reference_time=None)
    pts = _dense(22, 99, 3)
    cfg = sts.DICConfig(m=0, dtype="float64", search_radius=9)
    sol = sts.solve_window(ref, frames[0], pts, config=cfg)
    info = sol.info["initial_guess"]
    assert info["method"] == "seeded"
    fft = sts.solve_window(ref, frames[0], pts, config=cfg.replace(initial_guess="fft"))
    away = (pts[:, 0] - 59.5).abs() > 12  # subsets that do not cross the crack
    v_true = torch.where(pts[:, 0] >= 60, 7.0, 0.0).double()
    assert bool(sol.ok[away].all())
    # the same minimum as FFT at every POI (the renderer's spots near the crack overlap, so
    # the truth itself is only met to ~0.05 px next to it)
    assert (sol.params[away] - fft.params[away]).abs().max() < 1e-3
    assert (sol.v[away] - v_true[away]).abs().max() < 0.1
    assert (sol.u[away] - 0.2).abs().max() < 0.1
    assert info["fft_points"] > info["seeds"]  # some POIs needed the FFT fallback


def test_seeds_are_not_shared_between_windows(pattern):
    """Two windows (different frames) of the same POIs in one call: each POI must start from
    a seed of its own window."""
    motion = synth.Translation(0.0, 0.0, ut=1.5, vt=-1.0)
    ref, frames = synth.render_series(pattern, SIZE, motion, torch.tensor([1.0, 6.0]),
                                      noise_sigma=0.5, seed=3, reference_time=None)
    cfg = sts.DICConfig(m=0, dtype="float64")
    solver = sts.SubsetSolver(cfg)
    pts = _dense(25, 96, 4)
    n = pts.shape[0]
    both = torch.cat([pts, pts])
    fidx = torch.cat([torch.zeros(n, 1), torch.ones(n, 1)]).long()
    sol = solver.solve(solver.prepare(ref), solver.prepare(frames), both,
                       torch.zeros(2 * n, 1, dtype=torch.float64), frame_index=fidx,
                       ref_pixels=ref.unsqueeze(0), frame_pixels=frames)
    assert sol.info["initial_guess"]["method"] == "seeded"
    assert bool(sol.ok.all())
    assert (sol.u[:n] - 1.5).abs().max() < 0.02 and (sol.u[n:] - 9.0).abs().max() < 0.02
    assert (sol.v[:n] + 1.0).abs().max() < 0.02 and (sol.v[n:] + 6.0).abs().max() < 0.02


def test_initial_guess_config_is_validated():
    with pytest.raises(ValueError, match="initial_guess"):
        sts.DICConfig(initial_guess="magic")
    with pytest.raises(ValueError, match="seed_spacing"):
        sts.DICConfig(seed_spacing=0.0)


@pytest.mark.parametrize("per_frame", [False, True])
def test_fft_regions_gathered_from_windows_equal_the_clamped_ones(per_frame):
    """FFT-CC's search regions: gathered from a strided view where inside the image, by
    clamped index arithmetic (zero outside) elsewhere; the same numbers either way."""
    from torch_stsdic.core.initial import _regions, _regions_clamped

    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 60, 90, generator=g)
    n, t = 200, 4
    index = torch.randint(0, 3, (n, t), generator=g)
    shape = (n, t) if per_frame else (n,)
    cx = torch.randint(-25, 95, shape, generator=g)
    cy = torch.randint(-25, 65, shape, generator=g)
    got = _regions(img, index, cx, cy, 21)
    assert got.shape == (n, t, 21, 21)
    assert torch.equal(got, _regions_clamped(img, index, cx, cy, 21))
    inside = (cx >= 0) & (cy >= 0) & (cx + 21 <= 90) & (cy + 21 <= 60)
    assert inside.any() and (~inside).any()  # both paths ran
    assert torch.equal(_regions(img[:, :10], index, cx, cy, 21),  # smaller than a region
                       _regions_clamped(img[:, :10], index, cx, cy, 21))
