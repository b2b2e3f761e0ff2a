"""The reference's noise ratio on resume: against one reference image given as an array
(``series_reference=False``), the ratio (the reference's noise variance over a frame's,
which scales the predicted u_std, v_std, ut_std, vt_std) is measured on the frames of the
first block. A run with a result file measures it before its first block and records it
with the run-level estimates, so a resumed run reads it back instead of measuring it on its
first pending block (before, a run cut after its first block measured 3.115 instead of
3.141 here, one cut after two blocks 3.084, and every resumed row's u_std, v_std moved by up
to 3.1e-5 and 6.2e-5 px)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch
from test_resume_estimates import MOTION, N_FRAMES, Crash  # the same movie (tests/ on the path)

import torch_stsdic as sts
import torch_stsdic.movie.estimates as estimates
from torch_stsdic import synth
from torch_stsdic.io import read_results


@pytest.fixture(scope="module")
def movie():
    """The movie, and a reference image noisier than its frames (a ratio near 3)."""
    mv = synth.synthetic_movie((121, 121), N_FRAMES - 1, MOTION, noise_sigma=2.0, seed=5)
    series = torch.cat([mv.ref[None], mv.frames])
    g = torch.Generator().manual_seed(9)
    ref = mv.ref + 3.0 * torch.randn(mv.ref.shape, generator=g, dtype=mv.ref.dtype)
    return series, np.concatenate([[0.0], mv.times.numpy()]), ref.numpy()


def _run(movie, **kw):
    series, times, ref = movie
    return sts.track(series, reference=ref, config=sts.DICConfig(m=2, subset_size=21), step=8,
                     times=times, progress=False, batch_frames=3, series_reference=False, **kw)


def _cut(movie, path, rows, **kw):
    """A run into ``path`` stopped after its first ``rows`` rows (whole blocks)."""
    def crash(done, total):
        if done >= rows:
            raise Crash

    with pytest.raises(Crash):
        _run(movie, out=path, callback=crash, **kw)
    assert int(read_results(path).completed.sum()) == rows


def _same_files(a_path, b_path):
    """Every field of two result files bit for bit (NaN where NaN)."""
    a, b = read_results(a_path), read_results(b_path)
    assert b.completed.all() and sorted(a.fields) == sorted(b.fields)
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), (
            name, float(np.nanmax(np.abs(a.fields[name].astype(np.float64)
                                         - b.fields[name].astype(np.float64)))))


@pytest.mark.parametrize("shared_motion, rows", [(None, 1), ("affine", 4)])
def test_resumed_single_reference_keeps_the_noise_ratio(movie, tmp_path, shared_motion, rows):
    """Cut after the first block (1 row) or two (4 rows), resumed: every field of the file,
    u_std .. vt_std included, equals the uninterrupted run's bit for bit, and so does the
    ratio, which is the one a run without a file measures on its first block."""
    kw = {"shared_motion": shared_motion}
    full = _run(movie, out=tmp_path / "full.h5", **kw)
    ratio = full.info["reference_noise_ratio"]
    assert 2.0 < ratio < 4.0  # the reference is noisier than the frames
    assert _run(movie, **kw).info["reference_noise_ratio"] == ratio  # in memory: 1st block
    _cut(movie, tmp_path / "cut.h5", rows, **kw)
    with h5py.File(tmp_path / "cut.h5", "r") as f:
        meta = json.loads(f["run_estimates"].attrs["meta"])
    assert meta["estimates"]["fields"]["noise_ratio"] == ["value", ratio]
    res = _run(movie, out=tmp_path / "cut.h5", resume=True, **kw)
    assert res.info["run_estimates"] == estimates.FROM_FILE
    assert res.info["reference_noise_ratio"] == ratio
    for name in ("u", "v", "ut", "vt"):
        assert torch.equal(res.std[name].nan_to_num(-1), full.std[name].nan_to_num(-1)), name
    _same_files(tmp_path / "full.h5", tmp_path / "cut.h5")


def test_file_without_the_ratio_measures_it_on_the_first_block(movie, tmp_path):
    """A file whose estimates were recorded without the ratio (before it was recorded): the
    resumed run measures it on the first block's frames, not on its first pending block."""
    full = _run(movie, out=tmp_path / "full.h5", shared_motion=None)
    _cut(movie, tmp_path / "cut.h5", 1, shared_motion=None)
    with h5py.File(tmp_path / "cut.h5", "r+") as f:
        g = f["run_estimates"]
        meta = json.loads(g.attrs["meta"])
        meta["estimates"]["fields"]["noise_ratio"] = ["value", None]
        g.attrs["meta"] = json.dumps(meta)
    res = _run(movie, out=tmp_path / "cut.h5", resume=True, shared_motion=None)
    assert res.info["run_estimates"] == estimates.FROM_FILE
    assert res.info["reference_noise_ratio"] == full.info["reference_noise_ratio"]
    _same_files(tmp_path / "full.h5", tmp_path / "cut.h5")
