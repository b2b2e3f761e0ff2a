"""Windows of different lengths in one solve (``SubsetSolver.solve(frame_count=)``): each row
iterated over its own first ``frame_count`` frames, the later columns padding. Checked against
solving each length on its own, on the C++ per-point kernel, the batched torch loop and the
Triton kernels (their interpreter on the CPU): the same statuses and iterations; parameters,
ZNCC, predicted std, noise and the classical step equal to rounding."""

from __future__ import annotations

import os

import pytest
import torch

if not torch.cuda.is_available():  # no GPU: Triton's interpreter, before Triton is imported
    os.environ.setdefault("TRITON_INTERPRET", "1")

from test_native_solve import _movie  # tests/ on the path

import torch_stsdic as sts
from torch_stsdic import kernels
from torch_stsdic.core.gauss_newton import classical_step_width
from torch_stsdic.core.solution import packed_classical_step
from torch_stsdic.kernels import native

M = 3  # the longest half-width; the rows take 1, 2 or 3


@pytest.fixture(autouse=True)
def _modes(monkeypatch):
    yield
    kernels.set_triton("auto")
    native.set_native("auto")


def _problem(n: int = 64, every: float = 6.0):
    """A 7-frame render, its points, and rows (point, half-width h) with h = 1, 2, 3 cycling
    over the points: each row's centred window of 2h + 1 frames, padded to 7 columns with
    nonsense (a far time, the last frame) that the solve must not read."""
    ref, frames, pts, times = _movie(M, n, 10.0, every, ((8.2, 30.0), (8.6, 36.0)))
    n_pts = pts.shape[0]
    half = torch.arange(n_pts) % M + 1
    t_all = 2 * M + 1
    dt = torch.full((n_pts, t_all), 99.0, dtype=torch.float64)
    fidx = torch.full((n_pts, t_all), t_all - 1, dtype=torch.long)
    for h in range(1, M + 1):
        at = half == h
        cols = torch.arange(M - h, M + h + 1)
        dt[at, : 2 * h + 1] = times[cols] - times[M]
        fidx[at, : 2 * h + 1] = cols
    return ref, frames, pts, half, dt, fidx


def _solve(mode: str, dtype: str, criterion: str = "znssd"):
    """(mixed solution, {h: (rows, solution of those rows alone)}) in ``mode``."""
    if mode == "triton":
        if not kernels.available():
            pytest.skip("triton is not importable")
        kernels.set_triton("1")
        native.set_native("0")
    elif mode == "torch":
        kernels.set_triton("0")
        native.set_native("0")
    elif not native.available():
        pytest.skip("no native kernels")
    ref, frames, pts, half, dt, fidx = _problem(48 if mode == "triton" else 64,
                                                 8.0 if mode == "triton" else 6.0)
    # the Triton kernels on a GPU where there is one, else through the interpreter
    dev = "cuda" if mode == "triton" and torch.cuda.is_available() else "cpu"
    ref, frames, pts, half, dt, fidx = (t.to(dev) for t in (ref, frames, pts, half, dt, fidx))
    cfg = sts.DICConfig(m=M, dtype=dtype, subset_size=11 if mode == "triton" else 15,
                        criterion=criterion)
    solver = sts.SubsetSolver(cfg)
    ref, frames = ref.to(getattr(torch, dtype)), frames.to(getattr(torch, dtype))
    ref_img, frames_img = solver.prepare(ref), solver.prepare(frames)
    p = pts.to(getattr(torch, dtype))
    init = torch.zeros(p.shape[0], 8, dtype=p.dtype, device=dev)
    init[:, 0], init[:, 4] = 0.4, -0.3  # near the render's translation
    kw = dict(ref_pixels=ref.unsqueeze(0).to(p.dtype), frame_pixels=frames.to(p.dtype),
              classical_step=True, has_time=True)
    mixed = solver.solve(ref_img, frames_img, p, dt, frame_index=fidx, init=init,
                         frame_count=2 * half + 1, **kw)
    alone = {}
    for h in range(1, M + 1):
        rows = torch.nonzero(half == h).flatten()
        alone[h] = rows, solver.solve(ref_img, frames_img, p[rows], dt[rows, : 2 * h + 1],
                                      frame_index=fidx[rows, : 2 * h + 1], init=init[rows],
                                      **kw)
    return mixed, alone


@pytest.mark.parametrize("mode,dtype,criterion", [
    ("native", "float32", "znssd"), ("native", "float64", "znssd"), ("native", "float64", "ssd"),
    ("torch", "float64", "znssd"), ("triton", "float32", "znssd")])
def test_mixed_windows_equal_each_length_alone(mode, dtype, criterion):
    mixed, alone = _solve(mode, dtype, criterion)
    atol = 1e-6 if dtype == "float64" else 2e-4
    n_ok = 0
    for h, (rows, sol) in alone.items():
        assert torch.equal(mixed.status[rows], sol.status), h
        assert torch.equal(mixed.iterations[rows], sol.iterations), h
        ok = sol.status <= int(sts.Status.MAX_ITER)
        n_ok += int(ok.sum())
        for name in ("params", "std"):
            torch.testing.assert_close(getattr(mixed, name)[rows][ok], getattr(sol, name)[ok],
                                       rtol=1e-4, atol=atol)
        for name in ("zncc", "sigma"):
            torch.testing.assert_close(getattr(mixed, name)[rows][ok], getattr(sol, name)[ok],
                                       rtol=1e-4, atol=atol)
        if mode != "torch":  # the classical step comes from the fused kernels' frame rhs
            a = packed_classical_step(mixed.info)[rows]
            b = packed_classical_step(sol.info)
            assert a.shape[1] == classical_step_width(3)
            assert torch.equal(torch.isnan(a), torch.isnan(b))
            assert torch.isfinite(b).any()
            torch.testing.assert_close(a.nan_to_num(0), b.nan_to_num(0), rtol=1e-4,
                                       atol=atol)
    assert n_ok > 0.8 * mixed.status.numel()
    # the windows' velocity differs with their length: a solve that read the padding
    # would not give each row what its own window gives (checked above); and the lengths
    # are all there
    assert all(rows.numel() for rows, _ in alone.values())


def test_frame_count_is_checked():
    ref, frames, pts, half, dt, fidx = _problem()
    solver = sts.SubsetSolver(sts.DICConfig(m=M, subset_size=15))
    r, f = solver.prepare(ref), solver.prepare(frames)
    p = pts.float()
    init = torch.zeros(p.shape[0], 8)
    with pytest.raises(ValueError, match=r"frame_count must be \(N,\)"):
        solver.solve(r, f, p, dt, frame_index=fidx, init=init, frame_count=half[:3])
    with pytest.raises(ValueError, match="integers"):
        solver.solve(r, f, p, dt, frame_index=fidx, init=init, frame_count=half.float())
    with pytest.raises(ValueError, match="needs init"):
        solver.solve(r, f, p, dt, frame_index=fidx, frame_count=half)
    fa = sts.SubsetSolver(sts.DICConfig(m=M, subset_size=15, formulation="joint+average"))
    with pytest.raises(ValueError, match="one window length a call"):
        fa.solve(r, f, p, dt, frame_index=fidx, init=init, frame_count=half)


def test_a_movie_block_solves_every_window_length_in_one_call(tmp_path, monkeypatch):
    """A movie whose points leave the image (the blocks shorten their windows there) run with
    the blocks' one call for every window length, and with one call a half-width (the
    fallback of a formulation that takes one length a call): the same result file."""
    import h5py

    from torch_stsdic.cli import main
    from torch_stsdic.movie import block, block_windows

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    assert main(["synth", "--out", str(tmp_path / "mv"), "--size", "121", "--frames", "15",
                 "--motion", "translation", "--ut", "2.0", "--vt", "0.7", "--noise", "2",
                 "--seed", "4", "--threads", "1"]) == 0
    calls = {"mixed": 0}
    solve = block.Block.solve

    def spy(self, idx, init, m=None, *a, **k):
        calls["mixed"] += isinstance(m, torch.Tensor) and m.numel() > 0
        return solve(self, idx, init, m, *a, **k)

    monkeypatch.setattr(block.Block, "solve", spy)
    out = {}
    for mixes in (True, False):
        if not mixes:
            monkeypatch.setattr(block_windows.BlockWindows, "mixes_windows",
                                property(lambda self: False))
        path = tmp_path / f"r{int(mixes)}.h5"
        assert main(["run", str(tmp_path / "mv" / "movie.tif"), "--subset", "21", "--step",
                     "12", "--threads", "1", "--no-progress", "--out", str(path)]) == 0
        with h5py.File(path) as f:
            out[mixes] = {k: f[k][()] for k in ("u", "v", "ut", "vt", "status", "m", "u_std")}
        if mixes:
            assert calls["mixed"] > 0  # the blocks took the one call
            calls["mixed"] = 0
    assert calls["mixed"] == 0  # and the fallback one a half-width
    m = out[True]["m"]
    assert len(set(m[m > 0].tolist())) >= 3  # windows of several lengths in the blocks
    for k, v in out[True].items():
        assert (v.tobytes() == out[False][k].tobytes()), k


def _oscillating_movie(path) -> None:
    """A 121 x 121, 21-frame movie whose motion oscillates in time, differently over the
    image (u's amplitude grows with x, v's falls): the model check shortens windows in
    rounds of several depths."""
    import tifffile

    from torch_stsdic import synth
    n = 121

    def oscillating(x, y, t):  # px: u, v oscillate in time, their amplitudes vary with x
        s = x / n
        return 3.0 * s * torch.sin(0.5 * t), 1.5 * (1.0 - s) * torch.sin(0.35 * t)

    times = torch.arange(0.0, 21.0, dtype=torch.float64)
    _, frames = synth.render_series(synth.make_speckle((n, n), seed=5), (n, n),
                                    synth.Custom(oscillating), times, noise_sigma=2.0,
                                    seed=3, reference_time=None)
    tifffile.imwrite(path, frames.clamp(0, 255).round().to(torch.uint8).numpy())


def test_the_model_checks_shorter_windows_take_every_rows_next_one_at_once(tmp_path,
                                                                           monkeypatch):
    """A movie whose motion oscillates in time, differently over the image (the model check
    shortens windows in rounds of several depths): the blocks' check with every failing row's
    next shorter window in one solve a round gives the same result file as one solve a
    half-width, in no more solves (a round as many as the deepest row's tries), some of them
    with rows of several half-widths."""
    import math

    import h5py

    from torch_stsdic.cli import main
    from torch_stsdic.movie import block_windows, checks, choices

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    _oscillating_movie(tmp_path / "osc.tif")
    tries = []  # per block: the number of rows of each solve of the shorter windows
    mixed_rounds = []  # the half-widths a solve of several took
    try_window = checks.BlockChecks._try_window
    check_model = checks.BlockChecks.check_model

    def spy_try(self, idx, sel, m, *a, **k):
        tries[-1].append(sel.numel())
        if isinstance(m, torch.Tensor) and m.unique().numel() > 1:
            mixed_rounds.append(sorted(m.unique().tolist()))
        return try_window(self, idx, sel, m, *a, **k)

    def spy_check(self):
        tries.append([])
        return check_model(self)

    monkeypatch.setattr(checks.BlockChecks, "_try_window", spy_try)
    monkeypatch.setattr(checks.BlockChecks, "check_model", spy_check)
    monkeypatch.setattr(choices, "EVERY_CANDIDATE", False)  # the rounds (the CPU's choice)
    out, calls = {}, {}
    for mixes in (True, False):
        if not mixes:
            monkeypatch.setattr(block_windows.BlockWindows, "mixes_windows",
                                property(lambda self: False))
        tries.clear()
        path = tmp_path / f"r{int(mixes)}.h5"
        assert main(["run", str(tmp_path / "osc.tif"), "--subset", "21", "--step", "8",
                     "--threads", "1", "--no-progress", "--out", str(path)]) == 0
        with h5py.File(path) as f:
            out[mixes] = {k: f[k][()] for k in ("u", "v", "ut", "vt", "status", "m", "u_std")}
        calls[mixes] = [len(t) for t in tries]
        rows = sum(map(sum, tries))
        assert rows >= 100, rows  # the check shortened many rows' windows
    assert sum(calls[True]) <= sum(calls[False]), calls
    assert max(calls[True]) >= 4  # rows that tried four windows or more
    assert mixed_rounds  # rows of several half-widths in one solve
    m = out[True]["m"]
    assert len(set(m[(m > 0) & (m < 6)].tolist())) >= 3  # shortened to several lengths
    for k, v in out[True].items():
        assert (v.tobytes() == out[False][k].tobytes()), k
    assert math.isfinite(float(abs(out[True]["u"][out[True]["status"] == 0]).max()))


def test_the_model_check_tries_every_shorter_window_at_once_as_a_gpu_run_does(tmp_path,
                                                                               monkeypatch):
    """The check's shorter windows all at once (``core.choices.EVERY_CANDIDATE``, a GPU run's
    choice: one read and one solve a block) keep, at every failing row, the window the rounds
    keep (the longest that passes): the same result file to the bit, in one solve of the
    shorter windows a block where the rounds take up to four or more."""
    import h5py

    from torch_stsdic.cli import main
    from torch_stsdic.movie import checks, choices

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    _oscillating_movie(tmp_path / "osc.tif")
    judge = checks.BlockChecks._judge_window
    check_model = checks.BlockChecks.check_model
    tries: list[list[int]] = []  # per block: the rows of each solve of shorter windows

    def spy_judge(self, idx, sel, *a, **k):
        tries[-1].append(sel.numel())
        return judge(self, idx, sel, *a, **k)

    def spy_check(self):
        tries.append([])
        return check_model(self)

    monkeypatch.setattr(checks.BlockChecks, "_judge_window", spy_judge)
    monkeypatch.setattr(checks.BlockChecks, "check_model", spy_check)
    out, solves, rows = {}, {}, {}
    for every in (False, True):
        monkeypatch.setattr(choices, "EVERY_CANDIDATE", every)
        tries.clear()
        path = tmp_path / f"e{int(every)}.h5"
        assert main(["run", str(tmp_path / "osc.tif"), "--subset", "21", "--step", "8",
                     "--threads", "1", "--no-progress", "--out", str(path)]) == 0
        with h5py.File(path) as f:
            out[every] = {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}
        solves[every] = [len(t) for t in tries]
        rows[every] = sum(map(sum, tries))
    assert max(solves[False]) >= 4 and max(solves[True]) == 1, solves
    assert rows[True] > rows[False] >= 100, rows  # every candidate tried, not the first passing
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k
