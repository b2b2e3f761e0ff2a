"""The classical pass that a run's pre-passes share (:mod:`torch_stsdic.movie.classical_pass`):
the shared-motion pass, the template's first round and the window-length pass measure
classical DIC against the reference image once, and the run's result is the one they give
measuring it each on their own, within the solver's tolerance."""

from __future__ import annotations

import numpy as np
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.movie import estimates, series


def _movie() -> torch.Tensor:
    mv = synth.synthetic_movie((101, 101), 13, synth.QuadraticInTime(au=0.15, bu=-0.004,
                                                                     av=-0.1, bv=0.002),
                               noise_sigma=2.0, bits=8, seed=5)
    return torch.cat([mv.ref[None], mv.frames])


def _track(monkeypatch, shared: bool) -> tuple[sts.TrackResult, list[tuple]]:
    """The default run (windows chosen up to m = 6, template, shared motion), and every
    classical sub-run it made against the reference image: (targets, points)."""
    subs: list[tuple] = []
    inner = series.run_plan

    def recording(plan, *args, **kwargs):
        classical = plan.config.m == 0 and not plan.options.get("checks", True)
        if classical and plan.reference_frame >= 0:
            subs.append((tuple(plan.targets), plan.n_points))
        return inner(plan, *args, **kwargs)

    monkeypatch.setattr(series, "run_plan", recording)
    if not shared:
        monkeypatch.setattr(estimates, "_classical_pass", lambda plan, run: None)
    res = sts.track(_movie(), step=10, config=sts.DICConfig(m=6), window_length="auto",
                    progress=False)
    monkeypatch.undo()
    return res, subs


def test_the_pre_passes_share_one_classical_measurement(monkeypatch):
    alone, subs_alone = _track(monkeypatch, shared=False)
    shared, subs_shared = _track(monkeypatch, shared=True)
    # each pass measured on its own: the shared-motion pass, the template's first round, the
    # window-length pass (and the template's gauge, against the template: not counted)
    assert len(subs_alone) == 3
    assert len(subs_shared) == 1
    frames = set(subs_shared[0][0])
    assert all(set(t) <= frames for t, _ in subs_alone)
    assert subs_shared[0][1] == max(n for _, n in subs_alone)  # at every POI
    # the same run within the solver's tolerance (a point's classical solution depends on
    # the other points and frames of its pass only through its initial guess)
    both = (alone.status <= 1) & (shared.status <= 1)
    assert float((alone.status == shared.status).double().mean()) >= 0.99
    for nm in ("u", "v"):
        d = (alone.field(nm) - shared.field(nm))[both]
        assert float(d.pow(2).mean().sqrt()) < 2e-3
    assert np.array_equal(alone.m.numpy() >= 0, shared.m.numpy() >= 0)


def test_a_single_reference_run_shares_it_with_the_time_model_pass(monkeypatch):
    """Without a template (``series_reference=False``) the time model is decided from a
    classical pass of its own: the shared-motion pass's serves it."""
    subs: list[tuple] = []
    inner = series.run_plan

    def recording(plan, *args, **kwargs):
        if plan.config.m == 0 and not plan.options.get("checks", True):
            subs.append(tuple(plan.targets))
        return inner(plan, *args, **kwargs)

    monkeypatch.setattr(series, "run_plan", recording)
    called = []
    orig = estimates.measure_time_model
    monkeypatch.setattr(estimates, "measure_time_model",
                        lambda *a, **k: called.append(k.get("measured")) or orig(*a, **k))
    sts.track(_movie(), step=6, config=sts.DICConfig(m=2), series_reference=False,
              progress=False)
    assert called and called[0] is not None and called[0].served >= 2
    assert len(subs) == 1
