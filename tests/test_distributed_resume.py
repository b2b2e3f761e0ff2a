"""The distributed runner and the run-level estimates in the result file: it records them
as a one-process run does (the group ``run_estimates`` included), so a one-process resume of
its file reads them instead of measuring them again; a distributed resume reads them too,
but where chunks are left to run with a shared motion (each starts from its first guess,
which the file does not hold)."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
import torch
from test_resume_estimates import _no_measuring  # every measurement raises (tests/ on the path)

import torch_stsdic.movie.estimates as estimates
from torch_stsdic import DICConfig, synth
from torch_stsdic.io import read_results
from torch_stsdic.movie.distributed import track_distributed
from torch_stsdic.movie.series import track

#: 49 points (the template applies), blocks [0], [1..3], [4..6], ...; chunks of 4 targets
#: rounded up to whole blocks: [0..3], [4..9], [10..12]
KW = dict(config=DICConfig(subset_size=21, m=2), step=8, batch_frames=3, progress=False)
DIST = dict(chunk_frames=4, n_workers=2, processes=False)


@pytest.fixture(scope="module")
def dask_distributed():
    return pytest.importorskip("dask.distributed")


@pytest.fixture(scope="module")
def movie():
    mv = synth.synthetic_movie((81, 81), 12, synth.QuadraticInTime(au=0.11, bu=-0.003,
                               av=-0.06, bv=0.002), noise_sigma=2.0, seed=5)
    return torch.cat([mv.ref[None], mv.frames]).numpy()


@pytest.fixture(scope="module")
def dist(dask_distributed, movie, tmp_path_factory):
    """The distributed run with the template and the shared motion, and its file."""
    out = tmp_path_factory.mktemp("dist") / "dist.h5"
    res = track_distributed(movie, out=out, shared_motion="affine", **KW, **DIST)
    assert res.info["chunks"] == 3 and "series_reference" in res.info
    return res, out


def _unfinish(path, row):
    with h5py.File(path, "r+") as f:
        f["completed"][row] = False
        f["u"][row] = np.nan


def _same_files(a_path, b_path):
    a, b = read_results(a_path), read_results(b_path)
    assert b.completed.all() and sorted(a.fields) == sorted(b.fields)
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), name


def _timeless(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k != "seconds"}


def test_file_holds_the_estimates_a_one_process_resume_reads(dist, movie, tmp_path,
                                                             monkeypatch):
    """The distributed file holds the group; a one-process resume of it (a row of the last
    chunk unfinished) reads it, and ends bit for bit where the same resume measuring them
    again ends (a copy without the group)."""
    res, out = dist
    with h5py.File(out, "r") as f:
        g = f["run_estimates"]
        assert "series_reference/added_var" in g and "shared/origin" in g
    for name in ("read.h5", "old.h5"):
        shutil.copy(out, tmp_path / name)
        _unfinish(tmp_path / name, 11)
    with h5py.File(tmp_path / "old.h5", "r+") as f:
        del f["run_estimates"]
    old = track(movie, out=tmp_path / "old.h5", resume=True, shared_motion="affine", **KW)
    assert old.info["run_estimates"].startswith("measured again: the result file holds none")
    _no_measuring(monkeypatch)
    new = track(movie, out=tmp_path / "read.h5", resume=True, shared_motion="affine", **KW)
    assert new.info["run_estimates"] == estimates.FROM_FILE
    for key in ("series_reference", "shared_motion"):
        assert _timeless(new.info[key]) == _timeless(res.info[key]), key
    assert new.info["reference_noise_ratio"] == res.info["reference_noise_ratio"]
    _same_files(tmp_path / "old.h5", tmp_path / "read.h5")
    np.testing.assert_allclose(read_results(tmp_path / "read.h5").fields["u"],
                               read_results(out).fields["u"], atol=2e-3, rtol=0)


def test_distributed_resume_of_a_finished_file_reads_them(dist, movie, tmp_path, monkeypatch):
    """Nothing left to run: the estimates come from the file, nothing is measured."""
    res, out = dist
    shutil.copy(out, tmp_path / "done.h5")
    _no_measuring(monkeypatch)
    again = track_distributed(movie, out=tmp_path / "done.h5", resume=True,
                              shared_motion="affine", **KW, **DIST)
    assert again.info["run_estimates"] == estimates.FROM_FILE
    assert again.info["chunks_run"] == 0
    for name in ("u", "v", "ut", "vt", "zncc", "status"):
        assert torch.equal(getattr(again, name).nan_to_num(-1),
                           getattr(res, name).nan_to_num(-1)), name
    _same_files(out, tmp_path / "done.h5")


def test_pending_chunk_with_a_shared_motion_measures_again(dist, movie, tmp_path):
    """A chunk left to run starts from the shared motion's first guess (not stored): the
    estimates are measured again (the info says why), the file ends as the uninterrupted
    run's."""
    res, out = dist
    shutil.copy(out, tmp_path / "part.h5")
    _unfinish(tmp_path / "part.h5", 11)
    again = track_distributed(movie, out=tmp_path / "part.h5", resume=True,
                              shared_motion="affine", **KW, **DIST)
    assert again.info["chunks_run"] == 1
    assert "chunks still to run start from the shared motion" in again.info["run_estimates"]
    _same_files(out, tmp_path / "part.h5")


def test_pending_chunk_without_a_shared_motion_reads_them(dask_distributed, movie, tmp_path,
                                                          monkeypatch):
    """Without a shared motion a pending chunk needs nothing the file lacks: the template
    and its gauge are read back, and the file ends bit for bit as the uninterrupted run's."""
    out = tmp_path / "full.h5"
    res = track_distributed(movie, out=out, shared_motion=None, **KW, **DIST)
    shutil.copy(out, tmp_path / "part.h5")
    _unfinish(tmp_path / "part.h5", 11)
    _no_measuring(monkeypatch)
    again = track_distributed(movie, out=tmp_path / "part.h5", resume=True,
                              shared_motion=None, **KW, **DIST)
    assert again.info["run_estimates"] == estimates.FROM_FILE
    assert again.info["chunks_run"] == 1
    assert _timeless(again.info["series_reference"]) == _timeless(res.info["series_reference"])
    _same_files(out, tmp_path / "part.h5")
