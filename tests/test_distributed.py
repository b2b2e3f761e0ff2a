"""Tests for torch_stsdic.movie.distributed: frame chunks tracked on Dask workers, merged into one
HDF5 file that matches a single-process ``track`` run."""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.core.status import Status
from torch_stsdic.io import read_results
from torch_stsdic.movie.distributed import (
    WARM_UP,
    chunk_plan,
    track_distributed,
    track_distributed_many,
)
from torch_stsdic.movie.estimates import measure_run
from torch_stsdic.movie.plan import plan_run
from torch_stsdic.movie.series import run_plan, track
from torch_stsdic.synth import (
    Custom,
    RigidJitter,
    Translation,
    make_speckle,
    render_series,
    synthetic_movie,
)

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
    """Two thread workers, chunks of 4 targets rounded up to whole blocks (blocks of 8
    targets after the first alone: 2 chunks, [0 .. 8] and [9 .. 12])."""
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
    # with a warm-up: the targets before each chunk but the first, and their reads
    warm = chunk_plan(range(13), 4, 13, 2, warm=2)
    assert [c["warm"] for c in warm] == [[], [2, 3], [6, 7], [10, 11]]
    assert [c["reads"] for c in warm] == [(0, 5), (0, 9), (4, 12), (8, 12)]
    # with the run's blocks: whole blocks, as few as make chunk_frames targets
    blocks = [[0], [1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]]
    whole = chunk_plan(range(13), 4, 13, 2, warm=2, blocks=blocks)
    assert [c["targets"] for c in whole] == [[0, 1, 2, 3], [4, 5, 6, 7, 8, 9], [10, 11, 12]]
    assert [c["warm"] for c in whole] == [[], [2, 3], [8, 9]]
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
    assert res.info["chunks"] == 2 and res.info["chunks_run"] == 2
    assert res.frames.tolist() == ref.frames.tolist() == list(range(13))
    assert torch.equal(res.points, ref.points)
    assert torch.equal(res.status, ref.status)
    assert bool((res.status == int(Status.CONVERGED)).all())
    # chunks restart from FFT-CC; converged points land on the same minimum (tol = 1e-8 px)
    assert _max_diff(res, ref) < 1e-6
    for g in ("ux", "uy", "vx", "vy"):
        assert float((res.gradients[g] - ref.gradients[g]).abs().max()) < 1e-6
    # the first block, and every other chunk's warm-up block (the WARM_UP targets before it),
    # start from the whole run's measuring pass (else FFT-CC): 9 points each
    assert res.info["fft_rows"] + res.info.get("first_guess_rows", 0) == 9 + WARM_UP * 9
    assert calls[-1] == (13, 13) and len(calls) == 2


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
    with h5py.File(part, "r+") as f:  # as if killed during chunk 2 (rows 9..12)
        f["completed"][10] = False
        f["u"][10] = np.nan
    again = track_distributed(movie, config=CFG, roi=ROI, step=18, chunk_frames=CHUNK,
                              n_workers=2, processes=False, out=part, resume=True,
                              progress=False)
    assert again.info["chunks_run"] == 1 and again.info["chunks_resumed"] == 1
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
        assert res.info["chunks"] == 2
        assert _max_diff(res, ref) < 1e-5
        assert read_results(o).completed.all()


@pytest.mark.slow
def test_worker_processes(dask_distributed, movie, single):
    """Real worker processes (each imports torch: ~10 s on a loaded 2-core machine)."""
    res = track_distributed(movie, config=CFG, roi=ROI, step=18, chunk_frames=CHUNK,
                            n_workers=2, processes=True, progress=False)
    assert res.info["worker_processes"] == 2
    assert _max_diff(res, single[0]) < 1e-6


# ---------------------------------------------------------------------------------------
# the run-level estimates measured once (issue 37)
# ---------------------------------------------------------------------------------------
SAMPLE12 = Path(__file__).resolve().parents[2] / "shared" / "data" / "dic-challenge-sample12"
#: the equality of a distributed run with the one-process run (usable in both): the
#: stopping rule's scale (config.tol 1e-4), and the statuses
MAX_DIFF_PX = 2e-3
MIN_EQUAL = 0.999


@pytest.fixture(scope="module")
def stepped_movie():
    """25 frames, 111 x 111 px, noise 3 grey levels: a field that grows in load steps (holds
    of 8 images: steps before frames 8, 16, 24) and a rigid shake of 0.15 px per frame."""
    size, times = 111, torch.arange(0.0, 25)

    def fn(x, y, t):
        a = 0.3 * torch.floor((t + 0.5) / 8.0)
        return a * torch.sin(2 * np.pi * x / 120.0), -0.5 * a * torch.cos(2 * np.pi * y / 150.0)

    c = ((size - 1) / 2, (size - 1) / 2)
    motion = Custom(fn) + RigidJitter.random(times, 0.15, 0.0, center=c, seed=2)
    ref, fr = render_series(make_speckle((size, size), seed=4), (size, size), motion, times[1:],
                            noise_sigma=3.0, seed=5)
    return torch.cat([ref[None], fr]).numpy()


def _timeless(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k != "seconds"}


def equality(a, b) -> dict[str, float]:
    """Every field of two results compared, among the point-frames usable in both: the
    largest difference of each float field where both used the same window (``max_<name>``;
    a classical row has no ut, vt), of u and v everywhere (``all_u``, ``all_v``), the share
    within MAX_DIFF_PX (``within``), and the shares of equal statuses and windows (``m``)."""
    ok = (a.status <= 1) & (b.status <= 1)
    same = ok & (a.m == b.m)
    out = {"statuses": float((a.status == b.status).float().mean()),
           "windows": float((a.m == b.m).float().mean()), "usable": int(ok.sum())}
    fields = {"u": (a.u, b.u), "v": (a.v, b.v), "ut": (a.ut, b.ut), "vt": (a.vt, b.vt),
              "zncc": (a.zncc, b.zncc)}
    fields.update({g: (a.gradients[g], b.gradients[g]) for g in a.gradients})
    fields.update({f"{k}_std": (a.std[k], b.std[k]) for k in a.std})
    for nm, (x, y) in fields.items():
        d = (x.double() - y.double()).abs()[same]
        both_nan = torch.isnan(x)[same] & torch.isnan(y)[same]
        assert bool((torch.isfinite(d) | both_nan).all()), f"{nm}: NaN in one run only"
        fin = d[torch.isfinite(d)]  # none: ut, vt of runs whose rows are all classical
        out[f"max_{nm}"] = float(fin.max()) if fin.numel() else 0.0
    du, dv = (a.u - b.u).abs()[ok], (a.v - b.v).abs()[ok]
    out["all_u"], out["all_v"] = float(du.max()), float(dv.max())
    out["within"] = float(((du <= MAX_DIFF_PX) & (dv <= MAX_DIFF_PX)).float().mean())
    return out


def test_given_estimates_change_nothing(stepped_movie):
    """run_plan with the estimates measured beforehand (measure_run) gives the numbers of a
    run that measures them itself, bit for bit."""
    kw = dict(config=DICConfig(m=2), step=20)
    plan = plan_run(stepped_movie, **kw)
    est = measure_run(plan, run=run_plan)
    assert est.shared is not None and est.shared.steps
    a = run_plan(plan, progress=False)
    b = track(stepped_movie, **kw, progress=False, run_estimates=est)
    for nm in ("u", "v", "ut", "vt", "zncc", "status", "m"):
        torch.testing.assert_close(getattr(a, nm), getattr(b, nm), rtol=0, atol=0,
                                   equal_nan=True, msg=nm)
    assert _timeless(a.info["shared_motion"]) == _timeless(b.info["shared_motion"])
    assert a.shared_motion.steps == est.shared.steps


def test_shake_and_load_steps_equal_the_one_process_run(dask_distributed, stepped_movie,
                                                        tmp_path):
    """A render with a shake and load steps, 2 workers, chunks of 6 targets: the shared motion
    and load steps are the whole movie's in every chunk, so every field equals the
    one-process run's at the stopping rule's scale (each chunk measuring its own moved the
    chunks near a step by ~0.03 px)."""
    kw = dict(config=DICConfig(m=2), step=10, progress=False)
    one = track(stepped_movie, out=tmp_path / "one.h5", **kw)
    dist = track_distributed(stepped_movie, out=tmp_path / "dist.h5", chunk_frames=6,
                             n_workers=2, processes=False, **kw)
    assert dist.info["chunks"] == 3 and dist.shared_motion.steps == [8, 16, 24]
    assert _timeless(dist.info["shared_motion"]) == _timeless(one.info["shared_motion"])
    eq = equality(one, dist)
    assert eq["statuses"] >= MIN_EQUAL and eq["windows"] >= MIN_EQUAL, eq
    assert eq["all_u"] <= MAX_DIFF_PX and eq["all_v"] <= MAX_DIFF_PX, eq
    assert eq["max_ut"] <= 10 * MAX_DIFF_PX and eq["max_vt"] <= 10 * MAX_DIFF_PX, eq
    # the file records the whole run's shared motion, as the one-process run's does
    a, b = read_results(tmp_path / "one.h5"), read_results(tmp_path / "dist.h5")
    np.testing.assert_array_equal(a.arrays["shared_motion"][0], b.arrays["shared_motion"][0])


def test_sample12_equals_the_one_process_run(dask_distributed):
    """DIC Challenge sample 12 (a loading series with a step before frame 10; its uneven
    load steps put every point classical), defaults but step 20, 2 workers, chunks of 6
    (4 s on the 2-core machine). The few
    point-frames whose window length the model check decides at its margin may take
    another window (m): a different estimate, as between two one-process runs with other
    blocks (batch_frames 4 and 8: 0.023 % of them, up to 0.016 px); every other usable
    point-frame agrees at the stopping rule's scale."""
    if not SAMPLE12.is_dir():
        pytest.skip(f"DIC Challenge sample 12 not found at {SAMPLE12} (../shared/data)")
    one = track(str(SAMPLE12), step=20, progress=False)
    dist = track_distributed(str(SAMPLE12), step=20, chunk_frames=6, n_workers=2,
                             processes=False, progress=False)
    eq = equality(one, dist)
    assert eq["statuses"] >= MIN_EQUAL and eq["windows"] >= MIN_EQUAL, eq
    assert eq["within"] >= MIN_EQUAL, eq
    assert eq["max_u"] <= MAX_DIFF_PX and eq["max_v"] <= MAX_DIFF_PX, eq


def test_command_line_workers_give_the_one_process_file(dask_distributed, stepped_movie,
                                                        tmp_path, capsys):
    """``stsdic run --scheduler`` (a threads cluster here; --workers starts processes) writes
    the file ``stsdic run`` writes, says the same summary, and resumes an interrupted run."""
    import tifffile

    from torch_stsdic.cli import main

    tif = tmp_path / "movie.tif"
    tifffile.imwrite(tif, np.clip(np.round(stepped_movie), 0, 255).astype(np.uint8))
    base = ["run", str(tif), "--step", "20", "--threads", "1", "--no-progress"]
    assert main([*base, "--out", str(tmp_path / "one.h5")]) == 0
    one_out = capsys.readouterr().out
    cluster = dask_distributed.LocalCluster(n_workers=2, threads_per_worker=1,
                                            processes=False, dashboard_address=None)
    try:
        dist = [*base, "--scheduler", cluster.scheduler_address, "--chunk-frames", "6"]
        assert main([*dist, "--out", str(tmp_path / "two.h5")]) == 0
        two_out = capsys.readouterr().out
        a, b = read_results(tmp_path / "one.h5"), read_results(tmp_path / "two.h5")
        assert sorted(a.fields) == sorted(b.fields) and a.config == b.config
        np.testing.assert_array_equal(a.status, b.status)
        np.testing.assert_allclose(a.fields["u"], b.fields["u"], atol=MAX_DIFF_PX, rtol=0)
        np.testing.assert_array_equal(a.arrays["shared_motion"][0], b.arrays["shared_motion"][0])
        # the same summary but for the time line
        assert [ln for ln in one_out.splitlines() if not ln.startswith(("time:", "results:"))] \
            == [ln for ln in two_out.splitlines() if not ln.startswith(("time:", "results:"))]
        with h5py.File(tmp_path / "two.h5", "r+") as f:  # as if stopped during chunk 3
            f["completed"][13] = False
            f["u"][13] = np.nan
        assert main([*dist, "--out", str(tmp_path / "two.h5"), "--resume"]) == 0
        assert "resumed: 24 of 25 frames" in capsys.readouterr().out
        again = read_results(tmp_path / "two.h5")
        assert again.completed.all()
        np.testing.assert_array_equal(again.fields["u"], b.fields["u"])
    finally:
        cluster.close()
    assert main([*base, "--out", str(tmp_path / "x.h5"), "--chunk-frames", "6"]) == 2
    assert "--chunk-frames" in capsys.readouterr().err


def test_a_warm_up_block_seeds_its_poor_fit_rows_as_trusted(movie, monkeypatch):
    """With ``warm_up`` (a chunk's rows before its targets) the first block only seeds the
    carry: its rows the fit check made POOR_FIT without their point's history (ZNCC still
    above ``lost_zncc``) are carried on as trusted; without warm-up, and in later blocks,
    they are not. (The first block was once recognised by identity with ``plan.blocks``,
    a property made anew on every read: never.)"""
    import torch_stsdic.movie.series as series_mod

    seeds = []
    solve, carry = series_mod.solve_block, series_mod.make_carry

    def poor_first_point(run, ks, ref, c):
        out = solve(run, ks, ref, c)
        out["status"][:, 0] = int(Status.POOR_FIT)  # high ZNCC: poor for the residual alone
        return out

    def recording(rows, times, names, *args, **kwargs):
        if "ut" in names:  # the run's own blocks (m = 2), not a pre-pass's classical ones
            seeds.append(torch.as_tensor(rows["status"]).cpu().numpy().copy())
        return carry(rows, times, names, *args, **kwargs)

    monkeypatch.setattr(series_mod, "solve_block", poor_first_point)
    monkeypatch.setattr(series_mod, "make_carry", recording)
    plan = plan_run(movie, config=CFG, roi=ROI, step=18, batch_frames=4)
    assert len(plan.blocks) >= 3
    for warm in (True, False):
        seeds.clear()
        run_plan(plan, progress=False, warm_up=warm)
        first, later = seeds[0], seeds[1:]
        assert len(later) == len(plan.blocks) - 2  # the last block carries nothing on
        assert (first[:, 0] == (Status.CONVERGED if warm else Status.POOR_FIT)).all()
        assert all((s[:, 0] == Status.POOR_FIT).all() for s in later)
