"""A resumed run takes the run-level estimates (shared motion, the reference made from the
series with its gauge, added variance and time-model test, the refined reference's offsets)
from its result file instead of measuring them again, and still ends bit for bit where an
uninterrupted run ends; a file written before they were recorded is measured again."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

import torch_stsdic as sts
import torch_stsdic.movie.estimates as estimates
from torch_stsdic import synth
from torch_stsdic.io import read_results

N_FRAMES = 15
MOTION = synth.QuadraticInTime(au=0.11, bu=-0.003, av=-0.06, bv=0.002)
BATCH = 3


class Crash(Exception):
    pass


@pytest.fixture(scope="module")
def movie():
    mv = synth.synthetic_movie((121, 121), N_FRAMES - 1, MOTION, noise_sigma=2.0, seed=5)
    series = torch.cat([mv.ref[None], mv.frames])
    return series, np.concatenate([[0.0], mv.times.numpy()])


def _run(movie, dtype=torch.float64, **kw):
    series, times = movie
    kw = {"shared_motion": "affine", **kw}
    return sts.track(series.to(dtype), config=sts.DICConfig(m=2, subset_size=21), step=8,
                     times=times, progress=False, batch_frames=BATCH, **kw)


def _cut(movie, path, rows=6, **kw):
    """A run of ``movie`` into ``path`` stopped after its first ``rows`` rows or more."""
    def crash(done, total):
        if done >= rows:
            raise Crash

    with pytest.raises(Crash):
        _run(movie, out=path, callback=crash, **kw)
    done = int(read_results(path).completed.sum())
    assert 0 < done < N_FRAMES


def _no_measuring(monkeypatch):
    """Every estimate's measurement raises."""
    def refuse(*args, **kwargs):
        raise AssertionError("the run-level estimates were measured again")

    for name in ("measure_run", "build_series_reference", "estimate_shared_motion",
                 "measure_trajectory_gauge", "measure_time_model"):
        monkeypatch.setattr(estimates, name, refuse)


def _timeless(info):
    """``info`` without its wall times (the interrupted run measured the estimates itself)."""
    return {k: v for k, v in info.items() if k != "seconds"}


def _same(full, res, a_path, b_path):
    for name in ("u", "v", "ut", "vt", "zncc", "status", "iterations"):
        assert np.array_equal(getattr(res, name).numpy(), getattr(full, name).numpy(),
                              equal_nan=name not in ("status", "iterations")), name
    a, b = read_results(a_path), read_results(b_path)
    assert b.completed.all()
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_resume_reads_the_estimates_from_the_file(movie, tmp_path, monkeypatch, dtype):
    """A run against the template, with the shared motion, stopped after two blocks: resumed
    without measuring anything again (every estimator raises), it equals the uninterrupted
    run bit for bit (the template at the run's precision: float32 and float64); so does
    resuming the finished file."""
    full = _run(movie, dtype, out=tmp_path / "full.h5")
    assert full.info["series_reference"]["classical_points"] is not None
    assert "run_estimates" not in full.info  # a new run says nothing
    _cut(movie, tmp_path / "cut.h5", dtype=dtype)
    with h5py.File(tmp_path / "cut.h5", "r") as f:
        g = f["run_estimates"]
        assert g["series_reference/added_var"].dtype == np.float64
        assert g["series_reference/model_holds"].dtype == bool
        assert "series_reference/gauge/values/u" in g and "shared/origin" in g
    _no_measuring(monkeypatch)
    res = _run(movie, dtype, out=tmp_path / "cut.h5", resume=True)
    assert res.info["run_estimates"] == estimates.FROM_FILE
    for key in ("series_reference", "shared_motion"):
        assert _timeless(res.info[key]) == _timeless(full.info[key]), key
    _same(full, res, tmp_path / "full.h5", tmp_path / "cut.h5")
    again = _run(movie, dtype, out=tmp_path / "full.h5", resume=True)  # nothing left to do
    assert again.info["run_estimates"] == estimates.FROM_FILE
    _same(full, again, tmp_path / "full.h5", tmp_path / "full.h5")


@pytest.mark.filterwarnings("ignore:refine_reference")  # this motion decelerates
def test_refined_reference_offsets_are_read_too(movie, tmp_path, monkeypatch):
    """The template's gauge from the trajectories (``refine_reference``) comes back from the
    file as it was measured."""
    kw = {"refine_reference": True, "refine_frames": 9, "shared_motion": None}
    full = _run(movie, out=tmp_path / "full.h5", **kw)
    _cut(movie, tmp_path / "cut.h5", **kw)
    _no_measuring(monkeypatch)
    res = _run(movie, out=tmp_path / "cut.h5", resume=True, **kw)
    assert res.info["run_estimates"] == estimates.FROM_FILE
    assert _timeless(res.info["refine_reference"]) == _timeless(full.info["refine_reference"])
    _same(full, res, tmp_path / "full.h5", tmp_path / "cut.h5")


def test_file_without_the_estimates_is_measured_again(movie, tmp_path, monkeypatch):
    """A file written before the estimates were recorded (no group ``run_estimates``) still
    resumes: they are measured again (the run's info says so), the result is the
    uninterrupted run's, and the file then holds them."""
    full = _run(movie, out=tmp_path / "full.h5")
    _cut(movie, tmp_path / "old.h5")
    with h5py.File(tmp_path / "old.h5", "r+") as f:
        del f["run_estimates"]
    calls = []
    build = estimates.build_series_reference
    monkeypatch.setattr(estimates, "build_series_reference",
                        lambda *a, **k: calls.append(1) or build(*a, **k))
    res = _run(movie, out=tmp_path / "old.h5", resume=True)
    assert calls == [1]
    assert res.info["run_estimates"].startswith("measured again: the result file holds none")
    _same(full, res, tmp_path / "full.h5", tmp_path / "old.h5")
    with h5py.File(tmp_path / "old.h5", "r") as f:
        assert "run_estimates" in f


def test_unfinished_first_block_measures_the_shared_motion_again(movie, tmp_path):
    """The shared motion's first guess (the first block's) is not stored: a file whose first
    block is unfinished is measured again, and still ends where the uninterrupted run does."""
    full = _run(movie, out=tmp_path / "full.h5")
    _cut(movie, tmp_path / "cut.h5")
    with h5py.File(tmp_path / "cut.h5", "r+") as f:
        f["completed"][0] = False
    res = _run(movie, out=tmp_path / "cut.h5", resume=True)
    assert "first block is unfinished" in res.info["run_estimates"]
    _same(full, res, tmp_path / "full.h5", tmp_path / "cut.h5")
