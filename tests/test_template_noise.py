"""The noise a template made from the series shares with the windows' frames
(:mod:`torch_stsdic.movie.template_noise`): on a render with known noise, the predicted u_std,
v_std, ut_std and vt_std of windows as long as the movie match the random error, where the
prediction without the shared noise is far too high."""

from __future__ import annotations

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie.template_noise import TemplateShares

N, UT, VT = 11, 0.1, 0.05


def _run() -> tuple[torch.Tensor, float]:
    """random / predicted error of (u, v) in each of frames 1.. and of (ut, vt) over them,
    every frame's mean error taken out, on an 11-frame render (noise sigma 2 on every image)
    solved with m = 5 windows against the template of all 11 frames."""
    mv = synth.synthetic_movie((201, 201), N - 1, synth.Translation(ut=UT, vt=VT),
                               noise_sigma=2.0, seed=1)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=5, subset_size=21), step=10,
                    progress=False)
    assert res.info["series_reference"]["frames"] == list(range(N))
    t = torch.arange(N, dtype=torch.float64)[:, None]
    e = torch.stack([res.u.double() - UT * t, res.v.double() - VT * t])[:, 1:]
    e = e - e.nanmean(-1, keepdim=True)
    p = torch.stack([res.std["u"].double(), res.std["v"].double()])[:, 1:]
    per_frame = (e.pow(2).nanmean((0, 2)) / p.pow(2).nanmean((0, 2))).sqrt()
    ev = torch.stack([res.ut.double() - UT, res.vt.double() - VT])[:, 1:]
    ev = ev - ev.nanmean(-1, keepdim=True)
    pv = torch.stack([res.std["ut"].double(), res.std["vt"].double()])[:, 1:]
    return per_frame, float(ev.pow(2).nanmean().sqrt() / pv.pow(2).nanmean().sqrt())


def test_predicted_error_with_the_shared_noise_matches_the_random_error(monkeypatch):
    """Measured (this render): random / predicted 0.93-1.10 in every frame, 1.0 for the
    velocity; without the shared noise 0.76-1.09 (the centre frames over-predicted: their
    windows' frames make the template, whose noise cancels there)."""
    per_frame, vel = _run()
    assert bool(((per_frame >= 0.85) & (per_frame <= 1.2)).all()), per_frame
    assert 0.85 <= vel <= 1.2, vel
    # the prediction that takes the template's noise for independent of the frames'
    monkeypatch.setattr(TemplateShares, "variance_factors",
                        lambda self, ks, m_used, *a, **k: torch.ones(*m_used.shape, 2,
                                                                     dtype=torch.float64))
    per_frame0, _ = _run()
    assert float(per_frame0.min()) < 0.8, per_frame0


def test_shares_sum_to_one_and_look_up_by_series_frame():
    share = torch.tensor([[0.5, 1.0], [0.25, 0.0], [0.25, 0.0]], dtype=torch.float64)
    ts = TemplateShares.make([0, 2, 4], share, 6, reference_frame=0)
    torch.testing.assert_close(ts.share_sq, torch.tensor([0.375, 1.0], dtype=torch.float64))
    got = ts.of(torch.tensor([[1, 2, 3], [2, 3, 4]]))  # (B, N, T)
    want = torch.tensor([[[0.0, 0.25, 0.0], [0.0, 0.0, 0.0]],
                         [[0.25, 0.0, 0.25], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    torch.testing.assert_close(got, want)


@pytest.mark.parametrize("m", [0, 1])
def test_a_frame_outside_the_template_keeps_its_prediction(m):
    """A window of frames no template frame shares: no covariance; the template's noise
    (share_sq = rho) as the solver took it: factors 1."""
    ts = TemplateShares.make([10], torch.ones(1, 3, dtype=torch.float64), 20)
    fac = ts.variance_factors(torch.tensor([3]), torch.full((1, 3), m, dtype=torch.int8),
                              torch.arange(20, dtype=torch.float64), rho=1.0)
    torch.testing.assert_close(fac, torch.ones(1, 3, 2, dtype=torch.float64))


def test_a_blocks_template_factors_copy_nothing_to_its_device():
    """The shares made on a run's device (``device=``: "meta" stands in for a GPU here):
    a block's factors move no tensor there (on a GPU each copy from the host waits for the
    device; made on the host, every block copied them there, once per half-width)."""
    share = torch.rand(3, 5, dtype=torch.float64)
    reg = torch.rand(5, dtype=torch.float64)
    ks = torch.tensor([1, 3], device="meta")
    m_used = torch.zeros(2, 5, dtype=torch.int8, device="meta")
    times = torch.arange(8, dtype=torch.float64, device="meta")
    moves: list[tuple[torch.device, torch.device]] = []
    to = torch.Tensor.to

    def moved(self, *a, **k):
        out = to(self, *a, **k)
        if out.device != self.device:
            moves.append((self.device, out.device))
        return out

    for device, want in (("meta", 0), (None, 1)):
        ts = TemplateShares.make([0, 2, 4], share, 8, 0, reg, device=device)
        moves.clear()
        torch.Tensor.to = moved
        try:
            fac = ts.variance_factors(ks, m_used, times, rho=0.5, m_max=1)
        finally:
            torch.Tensor.to = to
        assert tuple(fac.shape) == (2, 5, 2) and fac.device.type == "meta"
        assert (len(moves) > 0) == bool(want), moves
