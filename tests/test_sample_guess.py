"""The first block's initial guess from the measuring pass's sample (sample_guess.py)."""

from __future__ import annotations

import torch
from renders import speckle_movie  # tests/ on the path

import torch_stsdic as sts
from torch_stsdic.movie.sample_guess import GUESS_TOL, MeasuredSample
from torch_stsdic.synth import Translation


def _field(p: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth known motion: displacement (M, 2) and gradients (M, 2, 2) at time t."""
    x, y = p[:, 0] - 100.0, p[:, 1] - 80.0
    u = 0.4 * t + 2e-3 * t * x + 1e-3 * y + 2e-6 * x * x
    v = -0.3 * t + 1e-3 * t * y + 5e-4 * x
    g = torch.stack([torch.stack([2e-3 * t + 4e-6 * x, torch.full_like(x, 1e-3)], -1),
                     torch.stack([torch.full_like(x, 5e-4), torch.full_like(x, 1e-3 * t)],
                                 -1)], -2)
    return torch.stack([u, v], -1), g


def _sample(frames: list[int], pts: torch.Tensor) -> MeasuredSample:
    d, g = zip(*(_field(pts, float(t)) for t in frames))
    return MeasuredSample(points=pts, frames=torch.tensor(frames), disp=torch.stack(d),
                          grad=torch.stack(g))


def _grid(step: float, lo: float = 10.0, hi: float = 200.0) -> torch.Tensor:
    a = torch.arange(lo, hi, step, dtype=torch.float64)
    yy, xx = torch.meshgrid(a, a, indexing="ij")
    return torch.stack([xx.flatten(), yy.flatten()], 1)


def test_a_smooth_field_is_guessed_at_every_point_with_its_velocity():
    frames = [3, 4, 5, 6, 7]
    sample = _sample(frames, _grid(30.0, 15.0))
    pts = _grid(7.0)
    win = torch.tensor([frames])
    dt = (win - 5).double()
    g = sample.guess(pts, win, dt)
    assert bool(torch.isfinite(g["u"]).all())
    truth, grad = _field(pts, 5.0)
    # carried by the gradients: the error is the quadratic term over < 30 px, < 0.01 px
    assert float((g["u"] - truth[:, 0]).abs().max()) < 0.01
    assert float((g["v"] - truth[:, 1]).abs().max()) < 1e-9
    ut = 0.4 + 2e-3 * (pts[:, 0] - 100.0)  # d u / dt
    assert float((g["ut"] - ut).abs().max()) < 1e-6
    assert float((g["ux"] - grad[:, 0, 0]).abs().max()) < 2e-4
    assert float((g["vy"] - grad[:, 1, 1]).abs().max()) < 1e-12


def test_the_guess_averages_the_sample_points_noise():
    """Noisy sample solutions (0.02 px displacement, 2e-3 px/px gradient noise, as a classical
    pass gives): the mean of the nearest points' carried guesses is nearer the truth than the
    nearest point's alone."""
    frames = [2]
    spts = _grid(30.0, 15.0)
    gen = torch.Generator().manual_seed(4)
    d, g = _field(spts, 2.0)
    d = d + 0.02 * torch.randn(d.shape, generator=gen, dtype=torch.float64)
    g = g + 2e-3 * torch.randn(g.shape, generator=gen, dtype=torch.float64)
    sample = MeasuredSample(points=spts, frames=torch.tensor(frames), disp=d[None],
                            grad=g[None])
    pts = _grid(7.0, 20.0, 190.0)
    guess = sample.guess(pts, torch.tensor([frames]), torch.zeros(1, 1))
    truth, _ = _field(pts, 2.0)
    near = (pts.unsqueeze(1) - spts.unsqueeze(0)).norm(dim=-1).argmin(1)
    alone = d[near] + (g[near] @ (pts - spts[near]).unsqueeze(-1)).squeeze(-1)
    err = (torch.stack([guess["u"], guess["v"]], 1) - truth).square().mean().sqrt()
    err_alone = (alone - truth).square().mean().sqrt()
    assert bool(torch.isfinite(guess["u"]).all())
    assert float(err) < 0.8 * float(err_alone)  # 0.73 measured; the nearest alone: 1


def test_no_guess_where_a_sample_point_disagrees_with_its_neighbours():
    """A wrong sample point (a false peak 5 px off) guides nobody: its leave-one-out test
    fails, and the points around it take the next sample point or no guess."""
    frames = [1, 2, 3]
    spts = _grid(30.0, 15.0)
    sample = _sample(frames, spts)
    bad = int(((spts - torch.tensor([105.0, 105.0])).norm(dim=1)).argmin())
    sample = MeasuredSample(points=spts, frames=sample.frames,
                            disp=sample.disp.clone().index_put_(
                                (torch.tensor([1]), torch.tensor([bad])),
                                torch.tensor([[5.0, 0.0]], dtype=torch.float64)),
                            grad=sample.grad)
    pts = _grid(5.0)
    g = sample.guess(pts, torch.tensor([frames]), torch.tensor([[-1.0, 0.0, 1.0]]))
    truth, _ = _field(pts, 2.0)
    ok = torch.isfinite(g["u"])
    assert bool(ok.float().mean() > 0.5)  # the rest of the field is guessed
    # no point is guessed from the wrong one: every guess is near the truth
    assert float((g["u"][ok] - truth[ok, 0]).abs().max()) < GUESS_TOL


def test_no_guess_across_a_discontinuity():
    """A crack (the right half moves 3 px more): sample points whose neighbour across the
    crack disagrees guide no one; no guess is more than GUESS_TOL off."""
    frames = [1]
    spts = _grid(20.0, 10.0)
    pts = _grid(4.0)

    def crack(p):
        d, g = _field(p, 1.0)
        d[:, 0] += 3.0 * (p[:, 0] > 103.0)
        return d, g

    d, g = crack(spts)
    sample = MeasuredSample(points=spts, frames=torch.tensor(frames), disp=d[None],
                            grad=g[None])
    guess = sample.guess(pts, torch.tensor([frames]), torch.zeros(1, 1))
    truth, _ = crack(pts)
    ok = torch.isfinite(guess["u"])
    assert bool(ok.any()) and not bool(ok.all())
    assert float((guess["u"][ok] - truth[ok, 0]).abs().max()) < GUESS_TOL
    assert "ut" not in guess  # one frame: no velocity


def test_frames_the_pass_did_not_measure_get_no_guess():
    sample = _sample([1, 2, 3], _grid(30.0, 15.0))
    g = sample.guess(_grid(9.0), torch.tensor([[2, 3, 4]]), torch.tensor([[-1.0, 0.0, 1.0]]))
    assert bool(torch.isnan(g["u"]).all())


def test_a_run_starts_its_first_block_from_the_pass_and_lands_on_the_same_minimum():
    """STS(5) with the shared motion measured: the first block starts from the pass's
    solutions (no FFT cross-correlation there) and gives what FFT starts give."""
    times = torch.arange(0.0, 9)
    movie = speckle_movie(Translation(ut=0.37, vt=-0.21), times)
    kw = dict(config=sts.DICConfig(m=2), step=10, progress=False, frames=[4])
    guessed = sts.track(movie, **kw)
    plain = sts.track(movie, shared_motion=None, **kw)
    n = guessed.n_points
    assert guessed.info["first_guess_rows"] == n and guessed.info["fft_rows"] == 0
    assert plain.info.get("first_guess_rows", 0) == 0 and plain.info["fft_rows"] > 0
    assert torch.equal(guessed.status, plain.status)
    assert float((guessed.u - plain.u).abs().max()) < 1e-4
    assert float((guessed.u - 0.37 * 4).abs().max()) < 0.05
    assert float((guessed.ut - 0.37).abs().max()) < 0.02


def test_a_poi_that_is_a_sample_point_starts_from_its_own_solution():
    """The template's rounds guess every POI from the round before, measured at all POIs:
    each POI is a sample point itself, and its own solution is its best guess (the mean
    with its neighbours carried to it adds the field's curvature: here ~0.03 px at 40 px
    spacing); where its own disagrees with the others (a false peak) there is no guess."""
    frames = [2]
    pts = _grid(40.0, 15.0)

    def bent(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d, g = _field(p, 2.0)
        x = p[:, 0] - 100.0
        d[:, 0] += 2e-5 * x * x
        g[:, 0, 0] += 4e-5 * x
        return d, g

    d, g = bent(pts)
    sample = MeasuredSample(points=pts, frames=torch.tensor(frames), disp=d[None], grad=g[None])
    guess = sample.guess(pts, torch.tensor([frames]), torch.zeros(1, 1))
    assert bool(torch.isfinite(guess["u"]).all())
    assert float((guess["u"] - d[:, 0]).abs().max()) < 1e-12
    assert float((guess["ux"] - g[:, 0, 0]).abs().max()) < 1e-12
    # the neighbours' mean alone (the POIs moved off the sample points by 1e-3 px) is off
    off = sample.guess(pts + 1e-3, torch.tensor([frames]), torch.zeros(1, 1))
    assert float((off["u"] - d[:, 0]).abs().max()) > 0.01
    wrong = d.clone()
    wrong[10, 0] += 5.0  # a false peak: no guess there
    sample = MeasuredSample(points=pts, frames=torch.tensor(frames), disp=wrong[None],
                            grad=g[None])
    guess = sample.guess(pts, torch.tensor([frames]), torch.zeros(1, 1))
    assert not bool(torch.isfinite(guess["u"][10]))
