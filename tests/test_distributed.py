"""Tests for torch_stsdic.movie.distributed: frame chunks tracked on Dask workers, merged into one
HDF5 file that matches a single-process ``track`` run."""

from __future__ import annotations

import sys

import h5py
import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.core.status import Status
from torch_stsdic.io import read_results
from torch_stsdic.movie.distributed import chunk_plan, track_distributed, track_distributed_many
from torch_stsdic.movie.series import track
from torch_stsdic.synth import Translation, synthetic_movie

ROI = (22, 22, 58, 58)  # 3 x 3 points with step 18 on an 81 x 81 image
CFG = DICConfig(subset_size=21, m=2, tol=1e-8)
CHUNK = 4


@pytest.fixture(scope="module")
def dask_distributed():
    return pytest.importorskip("dask.distributed")


@pytest.fixture(scope="module")
def movie():
    """13 noise-free frames (frame 0 = the undeformed reference), u = 0.3 t, v = -0.2 t."""
    mv = synthetic_movie((81, 81), 12, Translation(ut=0.3, vt=-0.2))
    return torch.cat([mv.ref[None], mv.frames]).numpy()


@pytest.fixture(scope="module")
def noisy_movie():
    mv = synthetic_movie((81, 81), 12, Translation(ut=0.3, vt=-0.2), noise_sigma=2.0, bits=8,
                         seed=5)
    return torch.cat([mv.ref[None], mv.frames]).numpy().astype(np.uint8)


@pytest.fixture(scope="module")
def single(movie, tmp_path_factory):
    out = tmp_path_factory.mktemp("single") / "single.h5"
    return track(movie, config=CFG, roi=ROI, step=18, progress=False, out=out), out


@pytest.fixture(scope="module")
def threaded(dask_distributed, movie, tmp_path_factory):
    """Two thread workers, chunks of 4 targets (13 targets: 4 chunks)."""
    out = tmp_path_factory.mktemp("dist") / "dist.h5"
    calls: list[tuple[int, int]] = []
    res = track_distributed(movie, config=CFG, roi=ROI, step=18, chunk_frames=CHUNK,
                            n_workers=2, processes=False, out=out, progress=False,
                            callback=lambda d, t: calls.append((d, t)))
    return res, out, calls


def _max_diff(a, b, names=("u", "v", "ut", "vt")) -> float:
    return max(float((getattr(a, n) - getattr(b, n)).abs().max()) for n in names)


def test_chunk_plan_targets_disjoint_reads_overlap():
    plan = chunk_plan(range(13), 4, 13, 2)
    assert [c["targets"] for c in plan] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11], [12]]
    # each chunk reads m = 2 frames beyond its edges; shifted (not shrunk) at the movie ends
    assert [c["reads"] for c in plan] == [(0, 5), (2, 9), (6, 12), (8, 12)]
    assert chunk_plan([3, 9], 1, 10, 1)[1]["reads"] == (7, 9)
    with pytest.raises(ValueError, match="chunk_frames"):
        chunk_plan(range(5), 0, 5, 0)


def test_missing_dask_says_how_to_install(movie, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(ImportError, match=r"pip install torch_stsdic\[dist\]"):
        track_distributed(movie, config=CFG, roi=ROI, step=18, progress=False)


@pytest.mark.parametrize("kwargs", [{"reference_update": 0.9}, {"smoothing": 5}])
def test_unsupported_options_rejected(movie, kwargs):
    with pytest.raises(ValueError, match="not supported"):
        track_distributed(movie, config=CFG, roi=ROI, step=18, progress=False, **kwargs)


def test_equals_single_process_run(threaded, single):
    res, _, calls = threaded
    ref, _ = single
    assert res.info["chunks"] == 4 and res.info["chunks_run"] == 4
    assert res.frames.tolist() == ref.frames.tolist() == list(range(13))
    assert torch.equal(res.points, ref.points)
    assert torch.equal(res.status, ref.status)
    assert bool((res.status == int(Status.CONVERGED)).all())
    # chunks restart from FFT-CC; converged points land on the same minimum (tol = 1e-8 px)
    assert _max_diff(res, ref) < 1e-6
    for g in ("ux", "uy", "vx", "vy"):
        assert float((res.gradients[g] - ref.gradients[g]).abs().max()) < 1e-6
    # every chunk re-initialised (its measuring pass's solutions as the first guess, else
    # FFT-CC): one row block per chunk (9 points each)
    assert res.info["fft_rows"] + res.info.get("first_guess_rows", 0) == 4 * 9
    assert calls[-1] == (13, 13) and len(calls) == 4


def test_file_has_the_track_layout(threaded, single):
    res, out, _ = threaded
    _, out_single = single
    a, b = read_results(out), read_results(out_single)
    assert sorted(a.fields) == sorted(b.fields)
    assert a.completed.all()
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.times, b.times)
    assert a.config == b.config  # same settings recorded: the file is resumable by track too
    for name in ("u", "v", "ut", "vt", "zncc"):
        np.testing.assert_array_equal(a.fields[name], getattr(res, name).numpy()
                                      .astype(np.float32))
        np.testing.assert_allclose(a.fields[name], b.fields[name], atol=1e-6, rtol=0)
    np.testing.assert_array_equal(a.status, b.status)
    with h5py.File(out, "r") as f:
        assert '"chunk_frames": 4' in f.attrs["distributed"]


def test_resume_recomputes_only_unfinished_chunks(dask_distributed, threaded, movie,
                                                  tmp_path):
    res, out, _ = threaded
    part = tmp_path / "part.h5"
    part.write_bytes(out.read_bytes())
    with h5py.File(part, "r+") as f:  # as if killed during chunk 2 (rows 4..7)
        f["completed"][5] = False
        f["u"][5] = np.nan
    again = track_distributed(movie, config=CFG, roi=ROI, step=18, chunk_frames=CHUNK,
                              n_workers=2, processes=False, out=part, resume=True,
                              progress=False)
    assert again.info["chunks_run"] == 1 and again.info["chunks_resumed"] == 3
    for name in ("u", "v", "ut", "vt"):
        assert torch.equal(getattr(again, name), getattr(res, name))
    assert read_results(part).completed.all()


@pytest.mark.parametrize("m, tol", [(1, 1e-4), (0, 1e-6)])
def test_noisy_movie_equals_single_process_within_tolerance(dask_distributed, noisy_movie, m,
                                                            tol):
    """The chunk restarts move converged points by at most a few x tol (the stopping
    threshold on the last increment), with or without noise (docs/benchmarks.md). With a
    tol near float32 round-off (1e-6 px here, uint8 input -> float32) a point may stop at
    MAX_ITER instead of CONVERGED in one of the runs: usable either way, same values."""
    cfg = DICConfig(subset_size=21, m=m, tol=tol)
    ref = track(noisy_movie, config=cfg, roi=ROI, step=18, progress=False)
    res = track_distributed(noisy_movie, config=cfg, roi=ROI, step=18, chunk_frames=3,
                            n_workers=2, processes=False, progress=False)
    assert bool(res.ok.all()) and bool(ref.ok.all())
    assert _max_diff(res, ref, ("u", "v")) < 5 * tol


def test_list_of_movies_shares_the_workers(dask_distributed, movie, noisy_movie, single,
                                           tmp_path):
    outs = [tmp_path / "a.h5", tmp_path / "b.h5"]
    cfg = CFG.replace(m=1)
    a, b = track_distributed_many([movie, noisy_movie.astype(np.float64)], outs, config=cfg,
                                  roi=ROI, step=18, chunk_frames=5, n_workers=2,
                                  processes=False, progress=False)
    for res, mv, o in ((a, movie, outs[0]), (b, noisy_movie.astype(np.float64), outs[1])):
        ref = track(mv, config=cfg, roi=ROI, step=18, progress=False)
        assert res.info["chunks"] == 3
        assert _max_diff(res, ref) < 1e-5
        assert read_results(o).completed.all()


@pytest.mark.slow
def test_worker_processes(dask_distributed, movie, single):
    """Real worker processes (each imports torch: ~10 s on a loaded 2-core machine)."""
    res = track_distributed(movie, config=CFG, roi=ROI, step=18, chunk_frames=CHUNK,
                            n_workers=2, processes=True, progress=False)
    assert res.info["worker_processes"] == 2
    assert _max_diff(res, single[0]) < 1e-6
