"""Solves of data-chosen rows of a fixed set (``SubsetSolver.solve(active=)``): the rows to
solve given as a mask, not an index, so that a block keeps its shapes and reads nothing; the
active rows get what they get solved alone, the others nothing."""

from __future__ import annotations

import pytest
import torch
from test_mixed_windows import _modes, _problem  # noqa: F401  (tests/ on the path; a fixture)

import torch_stsdic as sts
from torch_stsdic import kernels
from torch_stsdic.kernels import native

M = 3


def _setup(mode: str):
    dtype = "float64"
    if mode == "torch":
        kernels.set_triton("0")
        native.set_native("0")
    elif mode == "triton":  # on a GPU where there is one, else through the interpreter
        if not kernels.available():
            pytest.skip("triton is not importable")
        kernels.set_triton("1")
        native.set_native("0")
        dtype = "float32"
    elif not native.available():
        pytest.skip("no native kernels")
    small = mode == "triton"
    ref, frames, pts, half, dt, fidx = _problem(48 if small else 64, 8.0 if small else 6.0)
    dev = "cuda" if small and torch.cuda.is_available() else "cpu"
    ref, frames, pts, half, dt, fidx = (t.to(dev) for t in (ref, frames, pts, half, dt, fidx))
    ref, frames = ref.to(getattr(torch, dtype)), frames.to(getattr(torch, dtype))
    pts = pts.to(getattr(torch, dtype))
    solver = sts.SubsetSolver(sts.DICConfig(m=M, subset_size=11 if small else 15,
                                            dtype=dtype))
    ref_img, frames_img = solver.prepare(ref), solver.prepare(frames)
    init = torch.zeros(pts.shape[0], 8, dtype=pts.dtype, device=pts.device)
    init[:, 0], init[:, 4] = 0.4, -0.3
    return solver, ref_img, frames_img, pts, half, dt, fidx, init


@pytest.mark.parametrize("mode,off_centre", [("native", False), ("torch", False),
                                             ("triton", False), ("native", True)])
def test_the_active_rows_are_solved_as_alone_and_the_others_not_at_all(mode, off_centre):
    """Every third row active, windows of mixed length, the others' guesses NaN (a masked row
    of a block may have none; ``off_centre``: some subsets moved off their POIs by whole
    pixels, as a block moves them near the border): the active rows' numbers equal those of
    the same rows solved alone to the bit; the others are NOT_COMPUTED with NaN numbers and
    no iteration."""
    solver, ref_img, frames_img, pts, half, dt, fidx, init = _setup(mode)
    n = pts.shape[0]
    active = (torch.arange(n) % 3 == 1).to(pts.device)
    init_nan = init.clone()
    init_nan[~active] = float("nan")
    kw = dict(has_time=True, classical_step=mode == "native")
    centres = None
    if off_centre:  # (the points are whole pixels: the block's facts)
        pts = pts.round()
        centres = pts + torch.where((torch.arange(n) % 4 == 1).unsqueeze(1),
                                    torch.tensor([2.0, -1.0], dtype=pts.dtype), 0.0)
        kw["on_grid"] = True
    masked = solver.solve(ref_img, frames_img, pts, dt, frame_index=fidx, init=init_nan,
                          frame_count=2 * half + 1, active=active, centres=centres, **kw)
    rows = torch.nonzero(active).flatten()
    alone = solver.solve(ref_img, frames_img, pts[rows], dt[rows], frame_index=fidx[rows],
                         init=init[rows], frame_count=2 * half[rows] + 1,
                         centres=None if centres is None else centres[rows], **kw)
    assert bool((alone.status <= int(sts.Status.MAX_ITER)).float().mean() > 0.8)
    for name in ("params", "zncc", "status", "iterations", "std", "sigma"):
        a, b = getattr(masked, name)[rows], getattr(alone, name)
        assert torch.equal(torch.isnan(a) if a.is_floating_point() else a == a,
                           torch.isnan(b) if b.is_floating_point() else b == b), name
        assert torch.equal(a.nan_to_num(0) if a.is_floating_point() else a,
                           b.nan_to_num(0) if b.is_floating_point() else b), name
    off = ~active
    assert bool((masked.status[off] == int(sts.Status.NOT_COMPUTED)).all())
    assert bool(torch.isnan(masked.params[off]).all()) and bool(torch.isnan(masked.zncc[off]).all())
    assert bool((masked.iterations[off] == 0).all())


@pytest.mark.parametrize("mode,off_centre", [("native", False), ("torch", False),
                                             ("triton", False), ("native", True)])
def test_a_solve_to_a_capacity_equals_the_masked_solve_of_every_row(mode, off_centre):
    """``capacity``: the first C active rows solved alone (``nonzero_static``, padding rows
    into a spare row), every other row as the masked solve leaves it: with C above the
    active rows' count every field equal to the masked solve's to the bit (the classical
    step's columns too; row 0 active: a padding row landing on a solved one fails); with C
    below it, the first C active rows so and the later ones NOT_COMPUTED."""
    solver, ref_img, frames_img, pts, half, dt, fidx, init = _setup(mode)
    n = pts.shape[0]
    active = (torch.rand(n, generator=torch.Generator().manual_seed(5)) < 0.3).to(pts.device)
    active[0] = True
    kw = dict(frame_index=fidx, init=torch.where(active.unsqueeze(1), init, 0.0),
              frame_count=2 * half + 1, has_time=True, classical_step=mode == "native")
    if off_centre:
        pts = pts.round()
        kw["centres"] = pts + torch.where((torch.arange(n) % 4 == 1).unsqueeze(1),
                                          torch.tensor([2.0, -1.0], dtype=pts.dtype), 0.0)
        kw["on_grid"] = True
    full = solver.solve(ref_img, frames_img, pts, dt, active=active, **kw)
    count = int(active.sum())
    cap = 1 << count.bit_length()  # (above the count: padding rows among them)
    got = solver.solve(ref_img, frames_img, pts, dt, active=active, capacity=cap, **kw)
    assert bool((full.status[active] <= int(sts.Status.MAX_ITER)).float().mean() > 0.8)
    for name in ("params", "zncc", "status", "iterations", "std", "sigma", "points"):
        a, b = getattr(full, name), getattr(got, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert torch.equal(a.nan_to_num(-7.0), b.nan_to_num(-7.0)), name
    for key, value in full.info.items():
        if key.startswith("classical_step"):
            assert torch.equal(value.nan_to_num(-7.0), got.info[key].nan_to_num(-7.0)), key
    short = solver.solve(ref_img, frames_img, pts, dt, active=active, capacity=count - 3, **kw)
    rows = torch.nonzero(active).flatten()
    first, later = rows[: count - 3], rows[count - 3:]
    assert torch.equal(short.params[first], full.params[first])
    assert bool((short.status[later] == int(sts.Status.NOT_COMPUTED)).all())
    assert bool(torch.isnan(short.params[later]).all())
    for wrong in (0, 2.0, True):
        with pytest.raises(ValueError, match="capacity must be a positive int"):
            solver.solve(ref_img, frames_img, pts, dt, active=active, capacity=wrong, **kw)
    with pytest.raises(ValueError, match="without active"):
        solver.solve(ref_img, frames_img, pts, dt, capacity=8, **kw)


def test_an_all_active_mask_is_no_mask_and_a_wrong_one_is_told():
    solver, ref_img, frames_img, pts, half, dt, fidx, init = _setup("native")
    kw = dict(frame_index=fidx, init=init, frame_count=2 * half + 1, has_time=True)
    every = solver.solve(ref_img, frames_img, pts, dt, **kw)
    same = solver.solve(ref_img, frames_img, pts, dt,
                        active=torch.ones(pts.shape[0], dtype=torch.bool), **kw)
    assert torch.equal(every.params.nan_to_num(0), same.params.nan_to_num(0))
    assert torch.equal(every.status, same.status)
    with pytest.raises(ValueError, match=r"active must be \(N,\)"):
        solver.solve(ref_img, frames_img, pts, dt, active=torch.ones(3, dtype=torch.bool), **kw)
    with pytest.raises(ValueError, match=r"active must be \(N,\) = .* bool"):
        solver.solve(ref_img, frames_img, pts, dt, active=torch.ones(pts.shape[0]), **kw)
    with pytest.raises(ValueError, match="active .* needs init"):
        solver.solve(ref_img, frames_img, pts, dt[:, :1], frame_index=fidx[:, :1],
                     active=torch.ones(pts.shape[0], dtype=torch.bool),
                     ref_pixels=ref_img.coeffs[:, 2:-2, 2:-2], frame_pixels=frames_img.coeffs)
