"""The window's length chosen from the data (:mod:`torch_stsdic.movie.window_length`): the
decision from classical displacements with known motion, and the run that uses it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie.window_length import auto_max_m, measured_frames, window_lengths

SIGMA = 0.01  # px, one classical displacement's noise (both images)


def _grid(n_side: int = 12) -> torch.Tensor:
    g = torch.arange(n_side, dtype=torch.float64) * 10.0
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)


def _decide(disp: torch.Tensor, max_m: int = 6, seed: int = 0) -> torch.Tensor:
    """window_lengths of classical displacements ``disp`` (T, N, 2) plus noise (one
    reference image's error common to all frames, each frame's own), all frames measured."""
    gen = torch.Generator().manual_seed(seed)
    t_n, n = disp.shape[:2]
    ref_err = torch.randn(1, n, 2, generator=gen, dtype=torch.float64) * SIGMA / 2 ** 0.5
    own = torch.randn(t_n, n, 2, generator=gen, dtype=torch.float64) * SIGMA / 2 ** 0.5
    d = disp + ref_err + own
    std = torch.full((t_n, n), SIGMA, dtype=torch.float64)
    res = SimpleNamespace(u=d[..., 0], v=d[..., 1], std={"u": std, "v": std},
                          status=torch.zeros(t_n, n, dtype=torch.int8), info={})
    plan = SimpleNamespace(config=SimpleNamespace(m=max_m), series=range(t_n),
                           points=_grid(int(round(n ** 0.5))),
                           times=np.arange(t_n, dtype=np.float64))
    return window_lengths(plan, res, list(range(t_n)), None)


def test_linear_motion_gets_the_longest_window_everywhere():
    t = torch.arange(31, dtype=torch.float64)[:, None, None]
    disp = (0.3 * t).expand(31, 144, 2).clone()
    m = _decide(disp)
    assert m.shape == (31, 144)
    assert float((m == 6).double().mean()) > 0.97


def test_noise_shared_by_neighbouring_subsets_does_not_pass_for_a_bias():
    """Overlapping subsets share pixels, so neighbouring POIs' classical errors are
    correlated and the pooled bias estimate's terms are not independent: its standard error
    from their scatter alone is too small (on the renders of window_length.md 1.7-2x), and
    linear motion lost its windows at random (5-13 % of the rows shorter, 3-8 % classical,
    with this noise). With the pool's design effect the longest window holds nearly
    everywhere."""
    gen = torch.Generator().manual_seed(1)
    kernel = torch.tensor([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]],
                          dtype=torch.float64)[None, None]

    def field(frames: int) -> torch.Tensor:  # (F, 144, 2): a neighbour shares most of it
        z = torch.randn(frames * 2, 1, 14, 14, generator=gen, dtype=torch.float64)
        s = torch.nn.functional.conv2d(z, kernel)
        return (s / s.std()).view(frames, 2, 144).permute(0, 2, 1) * SIGMA / 2 ** 0.5

    t = torch.arange(31, dtype=torch.float64)[:, None, None]
    d = 0.3 * t + field(1) + field(31)  # the reference image's error, each frame's own
    std = torch.full((31, 144), SIGMA, dtype=torch.float64)
    res = SimpleNamespace(u=d[..., 0], v=d[..., 1], std={"u": std, "v": std},
                          status=torch.zeros(31, 144, dtype=torch.int8), info={})
    plan = SimpleNamespace(config=SimpleNamespace(m=6), series=range(31), points=_grid(),
                           times=np.arange(31, dtype=np.float64))
    m = window_lengths(plan, res, list(range(31)), None)
    assert float((m == 6).double().mean()) > 0.99, [int((m == k).sum()) for k in range(7)]


def test_acceleration_shortens_the_windows_where_it_is():
    """u = a t^2 / 2 on the right half: a window's line misses the target by a m (m+1) / 6;
    with a = 4e-3 px/frame^2 that is 0.6 sigma at m = 2 and 4.7 sigma at m = 6 (far more than
    the window saves), so the right half's windows are short and the left half's long."""
    t = torch.arange(31, dtype=torch.float64)[:, None]
    pts = _grid()
    right = (pts[:, 0] > 55).double()[None, :]
    disp = torch.stack([0.5 * 4e-3 * t ** 2 * right + 0.1 * t,
                        0.05 * t.expand(31, 144)], -1)
    m = _decide(disp)
    inner = (pts[:, 0] > 75) | (pts[:, 0] < 35)  # away from the border between the halves
    left_m = m[:, (pts[:, 0] < 35)].double().mean()
    right_m = m[:, (pts[:, 0] > 75)].double().mean()
    assert left_m > 5.8
    assert 1.0 <= right_m <= 3.5
    assert bool(inner.any())


def test_a_jump_shortens_the_windows_around_it():
    """A jump of 0.2 px (20 sigma) at frame 15: windows that span it are rejected, those of
    targets far from it keep their full length."""
    t = torch.arange(31, dtype=torch.float64)[:, None, None]
    disp = (0.05 * t + 0.2 * (t >= 15)).expand(31, 144, 2).clone()
    m = _decide(disp)
    med = m.double().median(1).values  # (T,) per target frame
    assert med[0] == 6 and med[30] == 6  # shifted windows at the ends stay clear of it
    assert med[14] == 0 and med[15] == 0  # no window around the jump is affine in time
    assert all(med[k] <= abs(k - 14.5) for k in range(8, 22))


def test_auto_max_m_and_test_frames():
    assert auto_max_m(11) == 5 and auto_max_m(100) == 6 and auto_max_m(3) == 1
    plan = SimpleNamespace(config=SimpleNamespace(m=2), series=range(200),
                           targets=list(range(0, 200)))
    frames = measured_frames(plan, None, max_frames=64)
    assert len(frames) <= 64 and frames[0] == 0 and frames[-1] == 199
    assert measured_frames(plan, None, max_frames=1000) == list(range(200))


def test_track_rejects_a_bad_window_length():
    mv = np.zeros((5, 40, 40))
    with pytest.raises(ValueError, match="window_length"):
        sts.track(mv, window_length="long", progress=False)
    movie = synth.synthetic_movie((61, 61), 6, synth.Translation(ut=0.1), noise_sigma=1.0,
                                  seed=1)
    series = torch.cat([movie.ref[None], movie.frames]).double()
    with pytest.raises(ValueError, match="reference_update"):
        sts.track(series, config=sts.DICConfig(m=3, subset_size=15), step=10,
                  reference_update=0.9, window_length="auto", progress=False)


@pytest.mark.slow
def test_auto_windows_on_a_render_beat_the_fixed_window():
    """A uniform drift of 0.1 px a frame, 21 noisy images: the chosen windows are the longest
    (m = 6 at nearly every row) and their error is below the fixed m = 2 run's."""
    mot = synth.Translation(ut=0.1, vt=-0.07)
    mv = synth.synthetic_movie((121, 121), 20, mot, noise_sigma=2.0, seed=4)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    rms = {}
    for wl, m in (("fixed", 2), ("auto", 6)):
        res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21), step=10,
                        progress=False, window_length=wl)
        gt = synth.ground_truth(mot, res.points.double(), times)
        e = torch.stack([res.u.double()[1:] - gt["u"][1:], res.v.double()[1:] - gt["v"][1:]])
        rms[wl] = float(e.pow(2).mean().sqrt())
        if wl == "auto":
            ok = res.status[1:] <= 1
            assert float((res.m[1:][ok] == 6).double().mean()) > 0.9
            assert res.info["window_length"]["max_m"] == 6
    assert rms["auto"] < 0.85 * rms["fixed"]


def test_chosen_windows_are_recorded_and_a_resumed_run_reads_them(tmp_path):
    """A run with chosen windows stopped after its first blocks and resumed ends with the
    numbers of an uninterrupted run: the decision is read back from the file, not made
    again; the result's m never exceeds the decision."""
    mot = synth.Translation(ut=0.1, vt=0.05)
    mv = synth.synthetic_movie((81, 81), 11, mot, noise_sigma=2.0, seed=2)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    kw = {"config": sts.DICConfig(m=3, subset_size=15), "step": 8, "progress": False,
          "window_length": "auto", "batch_frames": 2}
    whole = sts.track(series, out=tmp_path / "a.h5", **kw)

    class Stop(Exception):
        pass

    def stop(done, total):
        if done >= 3:
            raise Stop

    with pytest.raises(Stop):
        sts.track(series, out=tmp_path / "b.h5", callback=stop, **kw)
    again = sts.track(series, out=tmp_path / "b.h5", resume=True, **kw)
    assert again.info["run_estimates"] == "read from the result file"
    assert torch.equal(again.u, whole.u) and torch.equal(again.m, whole.m)
    assert int(whole.m.max()) <= 3 and float((whole.m[1:] == 3).double().mean()) > 0.5
    assert whole.info["window_length"]["max_m"] <= 3


def test_a_rescued_row_near_the_border_keeps_within_its_points_window(tmp_path, monkeypatch):
    """The hourglass (16 frames): rows rescued from an earlier target near the image border
    are placed as carried rows are, a shorter window where the point leaves the view within
    the run's; that window stays within the one the point's measured motion supports (the
    block's ``window_cap``), and so does every row the block solved before its model check.
    It once took the longest that stays in view (162 rows here beyond their cap, each solved
    again shorter afterwards)."""
    from pathlib import Path

    from torch_stsdic.cli import main
    from torch_stsdic.movie import block, rescue

    data = Path(__file__).resolve().parents[2] / "shared" / "data" / "mudic-hourglass"
    if not data.is_dir():
        pytest.skip(f"{data} is absent (../shared/data: real image sets)")
    solve_own, check_model = rescue.BlockRescue._solve_own, block.Block.check_model
    seen = {"placed": 0, "capped": 0, "over": 0, "blocks": 0, "block_over": 0}

    def spy(self, rows, init, m, near=None, **kw):
        out = solve_own(self, rows, init, m, near, **kw)
        if init is not None and self.window_cap is not None:
            solved = self.status[rows] <= 1
            seen["placed"] += int(solved.sum())
            seen["capped"] += int((solved & (self.window_cap[rows] < self.run.m)).sum())
            seen["over"] += int((solved & (self.m_used[rows] > self.window_cap[rows])).sum())
        return out

    def spy_check(blk):
        if blk.window_cap is not None:
            seen["blocks"] += 1
            seen["block_over"] += int(((blk.m_used > blk.window_cap)
                                       & (blk.status <= 1)).sum())
        return check_model(blk)

    monkeypatch.setattr(rescue.BlockRescue, "_solve_own", spy)
    monkeypatch.setattr(block.Block, "check_model", spy_check)
    assert main(["run", str(data), "--roi", "150", "20", "1120", "734", "--subset", "31",
                 "--step", "40", "--frames", "0:16", "--no-progress",
                 "--out", str(tmp_path / "r.h5")]) == 0
    assert seen["placed"] > 100 and seen["capped"] > 50, seen  # the case arose
    assert seen["blocks"] >= 2 and seen["over"] == 0 and seen["block_over"] == 0, seen
