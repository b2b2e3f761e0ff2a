"""Tests for torch_stsdic.movie.series: tracking a movie with sliding STS-DIC windows."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.analysis.points import grid_points
from torch_stsdic.analysis.smoothing import smooth_in_time, temporal_smoothing
from torch_stsdic.core.status import Status
from torch_stsdic.io import load_series, read_results
from torch_stsdic.movie.frames import default_ahead
from torch_stsdic.movie.plan import resolve_reference
from torch_stsdic.movie.series import track
from torch_stsdic.synth import (
    HomogeneousStrain,
    Jump,
    Translation,
    ground_truth,
    make_speckle,
    render_series,
    synthetic_movie,
)

REPO = Path(__file__).resolve().parents[1]
UT, VT = 0.3, -0.2
ROI = (22, 22, 58, 58)  # 3 x 3 points with step 18 on an 81 x 81 image
CFG = DICConfig(subset_size=21, m=2, tol=1e-6)
BATCH = 3


class Crash(RuntimeError):
    pass


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small tensors: intra-op threads only add spin-waiting on a shared machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def movie():
    """9 noise-free frames at t = 0..8 (frame 0 = the undeformed reference), u = 0.3 t,
    v = -0.2 t."""
    mv = synthetic_movie((81, 81), 8, Translation(ut=UT, vt=VT))
    return torch.cat([mv.ref[None], mv.frames]), mv.motion


def _counted(frames):
    """The series of ``frames`` and the list its reads (frame indices) are appended to."""
    ser = load_series(frames)
    reads: list[int] = []
    get = ser.get

    def counting_get(i, *args, **kwargs):
        reads.append(int(i))
        return get(i, *args, **kwargs)

    ser.get = counting_get  # type: ignore[method-assign]
    return ser, reads


@pytest.fixture(scope="module")
def sts_run(movie, tmp_path_factory):
    """STS-DIC (m = 2) in blocks of 3 target frames, written to a file, reads counted."""
    frames, _ = movie
    ser, reads = _counted(frames)
    reads_at_callback: list[int] = []
    out = tmp_path_factory.mktemp("sts") / "full.h5"
    # shared motion off: its measuring pass reads every frame once more (test_shared_motion)
    res = track(ser, config=CFG, roi=ROI, step=18, progress=False, batch_frames=BATCH, out=out,
                callback=lambda done, total: reads_at_callback.append(len(reads)),
                shared_motion=None)
    return res, out, reads, reads_at_callback


def test_linear_motion_all_frames_including_shifted_ends(movie, sts_run):
    res, _, _, _ = sts_run
    _, motion = movie
    assert res.n_points == 9 and res.frames.tolist() == list(range(9))
    assert bool((res.status == int(Status.CONVERGED)).all())
    truth = ground_truth(motion, res.points, res.times)
    # every row, the shifted windows of frames 0, 1, 7, 8 included (frame 0 = the reference)
    assert float((res.u - truth["u"]).abs().max()) < 0.01
    assert float((res.v - truth["v"]).abs().max()) < 0.01
    assert float((res.ut - UT).abs().max()) < 1e-3
    assert float((res.vt - VT).abs().max()) < 1e-3
    assert float(res.u[0].abs().max()) < 0.01  # the reference frame itself: ~0
    assert float((res.gradients["ux"]).abs().max()) < 1e-3
    s = res.strain(window=3)
    assert float(np.nanmax(np.abs(s["exx"].numpy()))) < 1e-3
    assert "exx_rate" in s


def test_batched_centres_equal_one_at_a_time(movie, sts_run):
    res, _, _, _ = sts_run
    seq = track(movie[0], config=CFG, roi=ROI, step=18, progress=False, batch_frames=1)
    assert res.info["blocks"] == 4 and seq.info["blocks"] == 9
    for name in ("u", "v", "ut", "vt"):
        diff = (getattr(res, name) - getattr(seq, name)).abs().max()
        assert float(diff) < 1e-6, name
    assert torch.equal(res.status, seq.status)


def test_template_reads_are_bounded(movie):
    """The reference made from the series reads its frames a fixed number of times: their
    noise, each round's classical measurement and mapping, the reference's measurement
    against the template, then the movie's blocks."""
    frames, _ = movie
    ser, reads = _counted(frames)
    res = track(ser, config=CFG, roi=ROI, step=18, progress=False, batch_frames=BATCH,
                shared_motion=None, series_reference=True)
    assert res.info["series_reference"]["iterations"] == 2
    counts = np.bincount(reads)
    assert counts.min() >= 1 and counts.max() <= 7, counts


def test_lazy_reading_bounded_cache(movie):
    frames, _ = movie
    ser, reads = _counted(frames)
    reads_at_callback: list[int] = []
    res = track(ser, config=CFG, roi=ROI, step=18, progress=False, batch_frames=BATCH,
                callback=lambda done, total: reads_at_callback.append(len(reads)),
                shared_motion=None, series_reference=False)
    n = 9
    # every frame read and prefiltered once: the reference frame is held from the start
    assert sorted(reads) == list(range(n))
    assert res.info["prefiltered"] == n
    assert res.info["max_cached_frames"] <= BATCH + 2 * CFG.m
    # the first block (frame 0: window 0..4) reads its own frames (the reference among them),
    # and the read-ahead thread at most `ahead` (+ 1 in hand) more (tests/test_frames.py)
    assert 2 * CFG.m + 1 <= reads_at_callback[0] <= 2 * CFG.m + 2 + default_ahead(BATCH, CFG.m)
    assert reads_at_callback == sorted(reads_at_callback)


def test_sparse_targets_read_only_their_windows(movie):
    frames, motion = movie
    res = track(frames, frames=[8, 0], config=CFG.replace(m=1), roi=ROI, step=18,
                progress=False)
    assert res.frames.tolist() == [0, 8]
    # windows 0..2 and 6..8 (shifted at both ends): 6 frames, each read and prefiltered once
    # (the reference frame 0 among them)
    assert res.info["prefiltered"] == 6 and res.info["frames_read"] == 6
    truth = ground_truth(motion, res.points, res.times)
    assert float((res.u - truth["u"]).abs().max()) < 0.01


def test_killed_run_resumes_to_identical_result(movie, sts_run, tmp_path):
    full, full_path, _, _ = sts_run
    out = tmp_path / "killed.h5"

    def crash(done, total):
        if done >= 4:  # after the blocks [0] and [1, 2, 3]
            raise Crash

    with pytest.raises(Crash):
        track(movie[0], config=CFG, roi=ROI, step=18, progress=False, batch_frames=BATCH,
              out=out, callback=crash, shared_motion=None)  # as sts_run
    part = read_results(out)
    assert part.completed.tolist() == [True] * 4 + [False] * 5
    assert np.isnan(part.u[5:]).all()
    res = track(movie[0], config=CFG, roi=ROI, step=18, progress=False, batch_frames=BATCH,
                out=out, resume=True, shared_motion=None)
    assert res.info["frames_read"] < 9  # the finished blocks were not recomputed
    for name in ("u", "v", "ut", "vt", "zncc", "status", "iterations"):
        assert torch.equal(getattr(res, name), getattr(full, name)), name
    a, b = read_results(full_path), read_results(out)
    assert b.completed.all()
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), name


def test_sigkilled_process_resumes_to_identical_result(movie, sts_run, tmp_path):
    """A real hard kill (SIGKILL, no cleanup) in the middle of a run, then resume."""
    full, _, _, _ = sts_run
    np.save(tmp_path / "movie.npy", movie[0].numpy())
    out = tmp_path / "killed.h5"
    script = textwrap.dedent(f"""
        import os, signal
        import numpy as np, torch
        from torch_stsdic import DICConfig
        from torch_stsdic.movie.series import track
        torch.set_num_threads(1)

        def kill(done, total):
            if done >= 4:
                os.kill(os.getpid(), signal.SIGKILL)

        track(np.load({str(tmp_path / "movie.npy")!r}), config=DICConfig(**{CFG.to_dict()!r}),
              roi={ROI!r}, step=18, progress=False, batch_frames={BATCH}, out={str(out)!r},
              callback=kill, shared_motion=None)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    # the callback counts the rows handed to the writer thread: killed at once, the file
    # holds the blocks it wrote by then, whole ([0], [1, 2, 3]), none after them
    part = read_results(out).completed
    kept = int(part.sum())
    assert kept in (0, 1, 4) and part.tolist() == [True] * kept + [False] * (9 - kept)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the recorded input name differs (array vs tensor)
        res = track(movie[0], config=CFG, roi=ROI, step=18, progress=False,
                    batch_frames=BATCH, out=out, resume=True, shared_motion=None)
    for name in ("u", "v", "ut", "vt", "zncc", "status", "iterations"):
        assert torch.equal(getattr(res, name), getattr(full, name)), name


def test_classical_m0_and_progress_bar(movie, capsys):
    frames, motion = movie
    res = track(frames, config=CFG.replace(m=0), roi=ROI, step=18, batch_frames=4,
                progress=True)
    assert "frame" in capsys.readouterr().err  # tqdm on stderr
    truth = ground_truth(motion, res.points, res.times)
    assert bool(torch.isnan(res.ut).all()) and bool(torch.isnan(res.vt).all())
    assert bool((res.status == int(Status.CONVERGED)).all())
    assert float((res.u - truth["u"]).abs().max()) < 0.01
    assert float((res.v - truth["v"]).abs().max()) < 0.01


def test_classical_reference_row_is_the_identity_without_a_solve(movie):
    """Classical DIC of the reference frame against itself has nothing to find: its row is
    stored as the identity (a pair through ``stsdic run`` did twice the solver's work), a
    subset leaving the image is OUTSIDE as the solver says, and the next frame starts like
    the first block (FFT cross-correlation), with the same results."""
    frames, motion = movie
    pts = torch.tensor([[40.0, 40.0], [22.0, 30.0], [5.0, 40.0]])  # the last: subset outside
    res = track(frames[:3], config=CFG.replace(m=0), points=pts, progress=False,
                series_reference=False)
    assert res.status[0].tolist() == [int(Status.CONVERGED)] * 2 + [int(Status.OUTSIDE)]
    assert res.iterations[0].tolist() == [0, 0, 0]
    assert res.u[0, :2].tolist() == [0.0, 0.0] and res.v[0, :2].tolist() == [0.0, 0.0]
    assert float(res.zncc[0, 0]) == 1.0
    truth = ground_truth(motion, res.points, res.times)
    ok = res.status[1:, :2] == int(Status.CONVERGED)
    assert bool(ok.all())
    assert float((res.u[1:, :2] - truth["u"][1:, :2]).abs().max()) < 0.01


@pytest.mark.parametrize("m", [0, 2])
def test_points_that_leave_the_view_stay_outside_without_fft(m, monkeypatch):
    """A specimen that moves out of the view (3 px a frame: 90 px gone by the end, more than
    the neighbour fill's 8 rings of 4 px): a point whose rows left the view and that has
    no neighbour in view to carry it stays OUTSIDE in later blocks; it is not searched by
    FFT cross-correlation again in every block (where it found wrong peaks inside the
    image: POOR_FIT rows and most of the run's time; in this movie of 150 POIs the FFT
    searched 300 / 740 rows at m = 0 / 2 before, 150 / 300 now). Counted with the FFT
    rescue's rows."""
    import torch_stsdic.movie.rescue as rescue

    motion = Translation(ut=3.0)
    mv = synthetic_movie((61, 161), 30, motion, noise_sigma=2.0, margin=100.0)
    frames = torch.cat([mv.ref[None], mv.frames])
    fft_rows = []
    solve_own = rescue.BlockRescue._solve_own

    def spy(self, rows, init, mm, near=None, **kw):
        if init is None:
            fft_rows.append(int(rows.numel()))
        return solve_own(self, rows, init, mm, near, **kw)

    monkeypatch.setattr(rescue.BlockRescue, "_solve_own", spy)
    res = track(frames, config=CFG.replace(m=m), step=4, progress=False,
                series_reference=False, shared_motion=None, window_length="fixed")
    truth = ground_truth(motion, res.points, res.times)
    x_now = res.points[:, 0].double() + truth["u"]  # (F, N) where each point is
    gone = x_now > 161  # the point itself beyond the image (its subset off-centre before)
    assert bool(gone[-1].sum() > 0.3 * gone.shape[1])
    st = res.status
    assert not bool((st == int(Status.POOR_FIT)).any())
    assert bool((st[gone] == int(Status.OUTSIDE)).all())
    trusted = st <= 1
    assert float((res.u - truth["u"])[trusted].abs().max()) < 0.1  # no wrong peak trusted
    # the first block's searches only (every point at most twice), not one a block
    assert sum(fft_rows) <= 2 * st.shape[1], fft_rows


def test_lost_points_after_a_jump_are_recovered_by_fft():
    # at t = 4 everything jumps by (6, -5) px: the carried guess is far off; the points that
    # do not converge from it start again from their neighbours that did, or from the FFT
    # redo (search radius 10 px), and are found again
    motion = Translation(ut=UT) + Jump(-1e9, du=6.0, dv=-5.0, t_jump=4.0)
    mv = synthetic_movie((81, 81), 7, motion)
    frames = torch.cat([mv.ref[None], mv.frames])
    res = track(frames, config=CFG.replace(m=0), roi=ROI, step=18, progress=False,
                batch_frames=1)
    assert res.info["redone_rows"] + res.info["neighbour_rescued_rows"] >= 9
    truth = ground_truth(motion, res.points, res.times)
    assert bool((res.status == int(Status.CONVERGED)).all())
    assert float((res.u - truth["u"]).abs().max()) < 0.01
    assert float((res.v - truth["v"]).abs().max()) < 0.01


def test_smoothing_baseline_unbiased_on_linear_motion(movie):
    frames, motion = movie
    res = track(frames, config=CFG, roi=ROI, step=18, progress=False, batch_frames=4,
                smoothing=5)
    assert res.config.m == 0 and res.info["smoothing"] == 5
    truth = ground_truth(motion, res.points, res.times)
    assert float((res.u - truth["u"]).abs().max()) < 0.01
    assert float((res.v - truth["v"]).abs().max()) < 0.01
    assert float((res.ut - UT).abs().max()) < 2e-3  # the slope of the local line fit
    nan = torch.full_like(res.u, float("nan"))
    raw = replace(res, u=res.info["raw"]["u"], v=res.info["raw"]["v"], ut=nan, vt=nan)
    again = temporal_smoothing(raw, 5)
    assert torch.allclose(again.u, res.u, atol=1e-12)
    assert torch.allclose(again.ut, res.ut, atol=1e-12)


def test_smooth_in_time_linear_exact_and_ends_shifted():
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.5, 6.0, 7.0])  # uneven frame times
    vals = np.stack([1.5 + 0.7 * t, -2.0 * t], 1)  # (F, 2) linear in time
    sm, rate = smooth_in_time(vals, 5, t, return_rate=True)
    assert np.allclose(sm, vals, atol=1e-12) and np.allclose(rate, [0.7, -2.0], atol=1e-12)
    mean = smooth_in_time(vals, 5, t, fit="mean")
    assert abs(mean[0, 0] - vals[:5, 0].mean()) < 1e-12  # shifted window: rows 0..4
    assert abs(mean[0, 0] - vals[0, 0]) > 0.5  # a moving mean is biased at the ends
    noisy = torch.tensor(vals) + torch.tensor([[0.0, 0.0], [np.nan, 0.0]] + [[0.0, 0.0]] * 5)
    out = smooth_in_time(noisy, 3, torch.tensor(t))
    assert isinstance(out, torch.Tensor) and bool(torch.isfinite(out).all())
    assert torch.allclose(out, torch.tensor(vals), atol=1e-12)  # NaN left out of the fit
    with pytest.raises(ValueError, match="span"):
        smooth_in_time(vals, 4)


def test_reference_is_mean_of_still_frames():
    pattern = make_speckle((81, 81), seed=3)
    # 3 still frames (own noise each), then motion: u = 0.3 per frame
    times = torch.tensor([0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    _, frames = render_series(pattern, (81, 81), Translation(ut=UT), times, noise_sigma=2.0,
                              seed=5)
    ser = load_series(frames)
    raw, frame, desc = resolve_reference("0:3", ser, torch.float64, torch.device("cpu"))
    assert frame == -1 and desc == "mean:0,1,2"
    assert torch.allclose(raw, frames[:3].mean(0))
    res = track(ser, reference="0:3", frames="4:", config=CFG.replace(m=1), roi=ROI, step=18,
                progress=False)
    assert res.info["reference"] == "mean:0,1,2"
    assert bool((res.reference_frames == -1).all())
    expected = UT * (res.frames.double() - 2.0)
    assert float((res.u - expected[:, None]).abs().max()) < 0.05
    assert float(res.v.abs().max()) < 0.05


def test_reference_update_accumulates_and_resumes(tmp_path):
    motion = Translation(ut=1.2, vt=0.4) + HomogeneousStrain(exx=0.004, center=(50, 50),
                                                              rate=1.0)
    mv = synthetic_movie((101, 101), 9, motion, noise_sigma=1.0, seed=2)
    frames = torch.cat([mv.ref[None], mv.frames])  # t = 0..9, 10.8 px of motion at the end
    kw = dict(config=DICConfig(subset_size=21, m=1), roi=(16, 30, 40, 70), step=12,
              progress=False, batch_frames=3, reference_update=0.99999)
    full = track(frames, out=tmp_path / "a.h5", **kw)
    assert [u["frame"] for u in full.info["reference_updates"]] == [3, 6, 9]
    assert full.reference_frames.tolist() == [0, 0, 0, 0, 3, 3, 3, 6, 6, 6]
    truth = ground_truth(motion, full.points, full.times)  # to the FIRST reference
    assert bool((full.status == int(Status.CONVERGED)).all())
    assert float((full.u - truth["u"]).abs().max()) < 0.03
    assert float((full.v - truth["v"]).abs().max()) < 0.03
    assert float((full.ut - truth["ut"]).abs().max()) < 0.02
    assert float((full.gradients["ux"] - truth["dudx"]).abs().max()) < 0.01

    def crash(done, total):
        if done >= 7:  # after the update at frame 6
            raise Crash

    with pytest.raises(Crash):
        track(frames, out=tmp_path / "b.h5", callback=crash, **kw)
    res = track(frames, out=tmp_path / "b.h5", resume=True, **kw)
    assert res.reference_frames.tolist() == full.reference_frames.tolist()
    for name in ("u", "v", "ut", "vt", "zncc", "status"):
        assert torch.equal(getattr(res, name), getattr(full, name)), name


def test_grid_points_roi_mask():
    pts = grid_points((81, 81), 10, subset_size=21)
    assert float(pts.min()) >= 10 and float(pts.max()) <= 70
    mask = np.zeros((81, 81), bool)
    mask[:, :40] = True
    masked = grid_points((81, 81), 10, mask=mask, subset_size=21)
    assert 0 < len(masked) < len(pts) and float(masked[:, 0].max()) < 40
    roi = grid_points((81, 81), 5, roi=(30, 30, 50, 40), subset_size=21)
    assert float(roi[:, 0].min()) >= 30 and float(roi[:, 1].max()) <= 40


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(roi=(200, 200, 300, 300)), "roi"),
        (dict(config=DICConfig(subset_size=51)), "subset_size"),
        (dict(config=DICConfig(m=3)), r"2m\+1"),
        (dict(mask=np.ones((10, 10), bool)), "mask"),
        (dict(mask=np.zeros((40, 40), bool)), "no points"),
        (dict(roi=(0, 0, 5, 5)), "no points"),
        (dict(reference=7), "reference"),
        (dict(reference="0:2,9"), "reference"),
        (dict(frames=[0, 9]), "frames"),
        (dict(times=[0.0, 1.0]), "times"),
        (dict(points=[[np.nan, 3.0]]), "points"),
        (dict(batch_frames=0), "batch_frames"),
        (dict(reference_update=1.5), "reference_update"),
        (dict(smoothing=4), "smoothing"),
    ],
)
def test_bad_inputs_name_the_argument(kwargs, match):
    frames = torch.rand(6, 40, 40, dtype=torch.float64)
    with pytest.raises(ValueError, match=match):
        track(frames, progress=False, **kwargs)


def test_plan_then_run_equals_track_and_file_has_strains(movie, tmp_path):
    """A plan can be made and inspected first, then run into a sink; track(out=...) writes
    the same file as the CLI, strains included."""
    from torch_stsdic import HDF5Sink, plan_run, run_plan

    frames, _ = movie
    plan = plan_run(frames, config=CFG, roi=ROI, step=18, batch_frames=BATCH)
    assert plan.n_rows == 9 and plan.n_points == 9
    assert plan.blocks == [[0], [1, 2, 3], [4, 5, 6], [7, 8]]
    assert plan.fields[:6] == ("u", "v", "ut", "vt", "zncc", "status")
    direct = track(frames, config=CFG, roi=ROI, step=18, batch_frames=BATCH, progress=False,
                   out=tmp_path / "a.h5")
    planned = run_plan(plan, HDF5Sink(plan, tmp_path / "b.h5"), progress=False)
    assert torch.equal(direct.u, planned.u) and torch.equal(direct.vt, planned.vt)
    stored = read_results(tmp_path / "a.h5")
    strain = direct.strain(window=5, kind="green")
    for name in ("exx", "eyy", "exy", "exx_rate"):
        assert name in stored.fields
        np.testing.assert_allclose(stored.fields[name], np.asarray(strain[name]), atol=1e-6,
                                   equal_nan=True)
    # uniform translation: zero strain where measured
    assert np.nanmax(np.abs(stored.exx)) < 1e-4
    nostrain = track(frames, config=CFG, roi=ROI, step=18, progress=False,
                     out=tmp_path / "c.h5", strain_window=None)
    assert "exx" not in read_results(tmp_path / "c.h5").fields and nostrain.n_frames == 9


def test_reference_subsets_kept_between_solves_change_nothing(monkeypatch):
    """The run keeps its points' reference subsets between solves (windows, the model check's
    classical solves, shorter windows, later blocks; emptied at a reference update): the
    results are those of sampling them in every solve."""
    import torch_stsdic.movie.series as series_mod
    from torch_stsdic.core.gauss_newton import ReferenceCache

    motion = Translation(ut=1.2, vt=0.4) + Jump(50.0, du=0.6, dv=-0.4, t_jump=4.5)
    mv = synthetic_movie((101, 101), 9, motion, noise_sigma=1.0, seed=2)
    frames = torch.cat([mv.ref[None], mv.frames])
    kw = dict(config=DICConfig(subset_size=21, m=2), roi=(16, 24, 84, 76), step=8,
              progress=False, batch_frames=3, reference_update=0.99999, shared_motion=None)
    caches: list[ReferenceCache] = []
    refs: list[int] = []

    class Counting(ReferenceCache):
        def __init__(self, budget_mb, expected=0):
            super().__init__(budget_mb, expected)
            caches.append(self)

        def applies(self, ref, geo):
            if self.coeffs is not ref.coeffs:
                refs.append(id(ref.coeffs))
            return super().applies(ref, geo)

    monkeypatch.setattr(series_mod, "ReferenceCache", Counting)
    kept = track(frames, **kw)
    # a subset per point of the last reference, and per subset a block moved inside the image
    assert len(caches) == 1 and 0 < caches[0].count <= 2 * kept.n_points and not caches[0].off
    assert len(kept.info["reference_updates"]) >= 2
    assert len(refs) >= 2  # emptied at an update, filled again from the new reference
    # the check solved rows classically, kept some of them and shortened others
    assert kept.info["shortened_rows"] > 0 and kept.info["classical_rows"] > 0
    monkeypatch.setattr(series_mod, "ReferenceCache",
                        lambda budget_mb, expected=0: ReferenceCache(0.0))
    fresh = track(frames, **kw)
    for name in ("status", "m"):
        assert torch.equal(kept.field(name), fresh.field(name)), name
    for name in ("u", "v", "ut", "vt", "zncc"):
        a, b = kept.field(name), fresh.field(name)
        assert torch.allclose(a, b, atol=1e-5, rtol=0, equal_nan=True), name


def test_default_block_length_on_the_cpu_and_on_a_gpu():
    """8 target frames at most on the CPU, their frames within half of memory_mb (the
    window's 2m frames on top); on a GPU 32 within a frames' budget of at least 2 GiB (a
    tenth of the device's memory at most) where no memory_mb is given, within half of the
    one given else."""
    from torch_stsdic.movie.plan import default_batch_frames

    cfg = DICConfig(m=2)  # 256 MiB: 128 for the frames, 12 MiB a 1024^2 float32 frame
    assert default_batch_frames(cfg, (1024, 1024), 4) == 8
    assert default_batch_frames(cfg, (2048, 2048), 4) == 2  # 48 MiB a frame
    assert default_batch_frames(DICConfig(m=6), (2048, 2048), 4) == 2  # whatever m
    assert default_batch_frames(cfg, (4096, 4096), 4) == 1  # 192 MiB: one at least
    assert default_batch_frames(DICConfig(m=2, memory_mb=8000), (1024, 1024), 4) == 8
    assert default_batch_frames(cfg, (1024, 1024), 4, "cuda", device_mb=80_000) == 32
    # a tenth of a 4 GiB card: 409 MiB, 34 frames' worth
    assert default_batch_frames(cfg, (1024, 1024), 4, "cuda", device_mb=4096) == 32
    assert default_batch_frames(cfg, (2048, 2048), 4, "cuda", device_mb=4096) == 8
    assert default_batch_frames(cfg, (4096, 4096), 4, "cuda", device_mb=80_000) == 10
    # a budget given is kept to on a GPU too: 256 MiB given, as on the CPU (but up to 32)
    given = DICConfig(m=2, memory_mb=256.0)
    assert default_batch_frames(given, (2048, 2048), 4, "cuda", device_mb=80_000) == 2
    assert default_batch_frames(DICConfig(m=2, memory_mb=8000), (1024, 1024), 4, "cuda",
                                device_mb=80_000) == 32
    # blocks that start from an earlier round's solutions (no carry extrapolated over
    # them): the budget alone on the CPU, a GPU's cap kept
    assert default_batch_frames(cfg, (1024, 1024), 4, carried=False) == 10
    assert default_batch_frames(cfg, (4096, 4096), 4, carried=False) == 1
    assert default_batch_frames(cfg, (1024, 1024), 4, "cuda", device_mb=80_000,
                                carried=False) == 32


def test_a_gpu_solves_in_batches_of_its_own_budget_with_the_same_answers(monkeypatch):
    """On a GPU a solve's batches take at least 2 GiB within a tenth of the device's memory
    (``gpu_budget_mb``; None on the CPU, which keeps ``memory_mb``) where no ``memory_mb`` is
    given: fewer batches, fewer launches; a ``memory_mb`` given is kept to. A row's answer
    does not depend on its batch: a movie run in batches of 16 rows (a tiny ``memory_mb``,
    the same blocks) and in one batch a solve gives the same numbers to the bit."""
    from torch_stsdic.core import gauss_newton
    from torch_stsdic.core.config import gpu_budget_mb

    assert gpu_budget_mb("cpu") is None
    assert gpu_budget_mb("cuda", device_mb=141_000) == 2048.0
    assert gpu_budget_mb("cuda:1", device_mb=8192) == pytest.approx(819.2)
    frames = synthetic_movie((81, 81), 6, Translation(ut=UT, vt=VT))
    frames = torch.cat([frames.ref[None], frames.frames])

    def run(memory_mb):
        cfg = DICConfig(subset_size=CFG.subset_size, m=2, memory_mb=memory_mb)
        return track(frames, config=cfg, roi=ROI, step=9, progress=False, batch_frames=3,
                     shared_motion=None)

    sizes = []
    size_of = gauss_newton.BatchContext.batch_size
    monkeypatch.setattr(gauss_newton.BatchContext, "batch_size",
                        lambda self, t: sizes.append(size_of(self, t)) or sizes[-1])
    small = run(1e-3)
    assert max(sizes) == 16  # the floor: many batches a solve
    sizes.clear()
    # the same budget as a GPU's (the CPU's batch size made as on a 20 GiB card)
    monkeypatch.setattr(gauss_newton, "gpu_budget_mb", lambda device: 2048.0)
    one = run(None)  # (no budget given: the GPU's own)
    assert min(sizes) > 10_000  # every solve in one batch
    sizes.clear()
    given = run(1e-3)  # a budget given is kept to on a GPU too (a GPU shared with others)
    assert max(sizes) == 16
    assert torch.equal(given.u.nan_to_num(-7), small.u.nan_to_num(-7))
    for name in ("u", "v", "ut", "vt", "zncc", "status", "iterations", "u_std"):
        assert torch.equal(small.field(name).nan_to_num(-7), one.field(name).nan_to_num(-7)), \
            name
    assert (small.status == 0).float().mean() > 0.9
