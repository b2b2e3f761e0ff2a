"""A run that writes a file keeps nothing of size frames x points (issue 50): strains
written block by block equal those of the whole result, resume included; the returned
result reads its fields from the file when asked."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.analysis.stored_result import StoredTrackResult
from torch_stsdic.io import read_results
from torch_stsdic.movie import estimates
from torch_stsdic.movie.series import track
from torch_stsdic.synth import HomogeneousStrain, synthetic_movie

CFG = DICConfig(subset_size=17, m=2, tol=1e-6)
KW = dict(config=CFG, roi=(16, 16, 84, 84), step=11, progress=False, batch_frames=3,
          shared_motion=None, series_reference=False)
STRAINS = ("exx", "eyy", "exy", "exx_rate", "eyy_rate", "exy_rate")


class Crash(RuntimeError):
    pass


@pytest.fixture(scope="module")
def frames():
    """11 frames of a homogeneous strain growing in time (non-zero strains and rates)."""
    mv = synthetic_movie((101, 101), 10, HomogeneousStrain(exx=0.002, eyy=-0.001, exy=0.0005),
                         noise_sigma=1.0, seed=4)
    return torch.cat([mv.ref[None], mv.frames])


@pytest.fixture(scope="module")
def in_memory(frames):
    """The run without a file: every field held, strains from the whole result."""
    res = track(frames, **KW)
    return res, res.strain(window=5, kind="green")


def _whole_result_strains(res) -> dict[str, np.ndarray]:
    """The strains of a run's result computed over the whole (F, N) result at once, as the
    run computed them before it wrote them block by block (``TrackResult.strain``)."""
    return {k: np.asarray(v) for k, v in res.strain(window=5, kind="green").items()}


def test_block_strains_equal_the_whole_result_computation(frames, in_memory, tmp_path):
    res = track(frames, out=tmp_path / "r.h5", **KW)
    assert isinstance(res, StoredTrackResult)
    assert not res._fields._held  # nothing read from the file yet
    stored = read_results(tmp_path / "r.h5")
    for name in ("u", "v", "ut", "vt", "zncc", "status", "m"):
        want = torch.from_numpy(stored.fields[name]).to(getattr(res, name).dtype)
        assert torch.equal(getattr(res, name), want), name
    assert res.iterations.dtype == torch.int32 and res.status.dtype == torch.int8
    mem, mem_strain = in_memory  # the run held in memory: full precision, the same rows
    assert torch.equal(res.status, mem.status) and torch.equal(res.m, mem.m)
    torch.testing.assert_close(res.u, mem.u, rtol=0, atol=1e-5)
    assert set(res.gradients) == set(mem.gradients) and set(res.std) == set(mem.std)
    whole = _whole_result_strains(res)
    assert np.nanmax(np.abs(stored.exx)) > 5e-4  # strains, not zeros
    for name in STRAINS:
        assert np.array_equal(np.isnan(stored.fields[name]), np.isnan(whole[name])), name
        np.testing.assert_allclose(stored.fields[name], whole[name], rtol=0, atol=1e-7,
                                   equal_nan=True, err_msg=name)
    counts = res.info["row_counts"]["status"]
    st = mem.status.numpy()
    assert counts == {str(c): int((st == c).sum()) for c in np.unique(st)}


def test_resumed_run_writes_the_same_strains(frames, tmp_path):
    full = track(frames, out=tmp_path / "full.h5", **KW)

    def crash(done, total):
        if done >= 4:  # after the blocks [0] and [1, 2, 3]
            raise Crash

    with pytest.raises(Crash):
        track(frames, out=tmp_path / "cut.h5", callback=crash, **KW)
    part = read_results(tmp_path / "cut.h5")
    assert part.completed.tolist() == [True] * 4 + [False] * 7
    assert np.isfinite(part.exx[:4]).any() and np.isnan(part.exx[4:]).all()  # per block
    res = track(frames, out=tmp_path / "cut.h5", resume=True, **KW)
    a, b = read_results(tmp_path / "full.h5"), read_results(tmp_path / "cut.h5")
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), name
    whole = _whole_result_strains(res)
    for name in STRAINS:
        np.testing.assert_allclose(b.fields[name], whole[name], rtol=0, atol=1e-7,
                                   equal_nan=True, err_msg=name)
    assert torch.equal(res.u, full.u) and torch.equal(res.status, full.status)
    assert res.info["row_counts"] == full.info["row_counts"]


def test_smoothed_run_strains_from_the_smoothed_fields(frames, tmp_path):
    kw = {**KW, "config": CFG.replace(m=0)}
    res = track(frames, out=tmp_path / "s.h5", smoothing=5, **kw)
    mem = track(frames, smoothing=5, **kw)  # held in memory: full precision
    torch.testing.assert_close(res.u, mem.u, rtol=0, atol=1e-5)
    torch.testing.assert_close(res.info["raw"]["u"], mem.info["raw"]["u"], rtol=0, atol=1e-5)
    stored = read_results(tmp_path / "s.h5")
    assert torch.equal(res.u, torch.from_numpy(stored.u_smooth).to(res.u.dtype))
    assert torch.equal(res.info["raw"]["u"], torch.from_numpy(stored.u).to(res.u.dtype))
    whole = _whole_result_strains(res)
    for name in STRAINS:
        np.testing.assert_allclose(stored.fields[name], whole[name], rtol=0, atol=1e-7,
                                   equal_nan=True, err_msg=name)


def test_file_run_holds_no_rows_and_the_pass_keeps_few(frames, tmp_path, monkeypatch):
    """The file's sink holds no (F, N) array; the shared motion's measuring pass keeps the
    first guess only at the frames the first block's windows can use."""
    from torch_stsdic.movie import sinks

    made: list = []
    real_init = sinks.MemorySink.__init__

    def spy(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(sinks.MemorySink, "__init__", spy)
    # a long movie's shared-motion pass measures on its own (a short one's rows come from
    # the pre-passes' shared classical pass, held whole within memory_mb / 4)
    monkeypatch.setattr(estimates, "_classical_pass", lambda plan, run: None)
    kw = {**KW, "shared_motion": "affine"}
    res = track(frames, out=tmp_path / "r.h5", **kw)
    file_sink = [s for s in made if isinstance(s, sinks.HDF5Sink)]
    assert len(file_sink) == 1 and file_sink[0].values == {}  # nothing of size F x N
    assert res.info.get("shared_motion")  # the run measured a shared motion
    passes = [s for s in made if not isinstance(s, sinks.HDF5Sink) and s.sparse]
    assert passes, "the measuring pass keeps its gradients at a few rows"
    m = CFG.m
    first = res.frames[0].item()
    kept = np.asarray(passes[0].plan.targets)[passes[0].sparse_rows]
    assert kept.max() <= first + 2 * m and len(kept) < len(passes[0].plan.targets)
    assert set(passes[0].values) == {"u", "v", "zncc", "status", "u_std"}
    # u and v side by side in one (F, n, 2) array: the fit reads it without a copy
    pair = passes[0].paired
    assert pair is not None and pair.shape[-1] == 2 and np.isfinite(pair).any()
    assert np.shares_memory(pair, passes[0].values["u"]) and np.array_equal(
        pair[..., 1], passes[0].values["v"], equal_nan=True)


@pytest.mark.parametrize("kind", ["translation", "affine", "quadratic"])
def test_fit_in_chunks_equals_the_whole_series(kind, monkeypatch):
    """The shared motion's fit of a long series, taken in chunks of frames and points
    (bounded memory), gives the very numbers of the fit over the whole series at once."""
    from torch_stsdic.core import shared_fit as sm

    g = torch.Generator().manual_seed(3)
    f, n = 600, 120
    pts = torch.rand(n, 2, generator=g, dtype=torch.float64) * 300
    t = torch.arange(f, dtype=torch.float64)[:, None, None]
    disp = 0.05 * t + 1e-4 * pts[None] * t + 0.01 * torch.randn(f, n, 2, generator=g,
                                                                 dtype=torch.float64)
    disp[torch.rand(f, n, generator=g) < 0.01] += 3.0  # wrong peaks
    disp[torch.rand(f, n, generator=g) < 0.005] = float("nan")
    valid = torch.rand(f, n, generator=g) > 0.05
    noise = 0.02 * torch.rand(f, n, generator=g, dtype=torch.float64)
    chunked = sm.fit_frame_motion(pts, disp, valid, kind, noise=noise)
    assert len(sm._wls_chunks(f)) > 1
    monkeypatch.setattr(sm, "FIT_CHUNK", 1 << 40)
    monkeypatch.setattr(sm, "WLS_FRAMES", 1 << 40)
    whole = sm.fit_frame_motion(pts, disp, valid, kind, noise=noise)
    for a, b in zip(chunked, whole):
        assert torch.equal(a.nan_to_num(-9.0), b.nan_to_num(-9.0))


def _whole_series_fit(x, d, ok, eye):
    """The series fit of ``fit_frame_motion`` over whole (F, N) arrays, as it was written
    before it went frame chunk by frame chunk (issue 50): the oracle of the chunked one."""
    from torch_stsdic.core import shared_fit as sm

    def fill(r, m):
        f = r.shape[0]
        t = torch.arange(f).unsqueeze(1).expand_as(m)
        prev = torch.where(m, t, torch.full_like(t, -1)).cummax(0).values
        nxt = torch.where(m, t, torch.full_like(t, f)).flip(0).cummin(0).values.flip(0)
        a = torch.where(prev >= 0, prev, nxt).clamp(0, f - 1)
        b = torch.where(nxt < f, nxt, prev).clamp(0, f - 1)
        ra = torch.gather(r, 0, a.unsqueeze(-1).expand(-1, -1, 2))
        rb = torch.gather(r, 0, b.unsqueeze(-1).expand(-1, -1, 2))
        frac = ((t - a).double() / (b - a).clamp(min=1).double()).clamp(0, 1).unsqueeze(-1)
        out = ra + (rb - ra) * frac
        return torch.where(m.any(0, keepdim=True).unsqueeze(-1), out, torch.zeros_like(out))

    def line(r):
        out = torch.empty_like(r)
        out[1:-1] = 0.5 * (r[:-2] + r[2:])
        out[0], out[-1] = 2 * r[1] - r[2], 2 * r[-2] - r[-3]
        return out

    d = d.double()
    keep = ok.all(0)
    if int(keep.sum()) < max(3 * x.shape[1], int(0.5 * int(ok.any(0).sum()))):
        keep = ok.double().mean(0) >= sm._VALID_SHARE
    use = ok & keep
    coef, _ = sm._frame_fit(x, d, use, eye)
    for _ in range(3):
        r = torch.where(use.unsqueeze(-1), d - x @ coef, torch.zeros_like(d))
        rf = fill(r, use)
        rough = (rf[2:] - 2 * rf[1:-1] + rf[:-2]).norm(dim=-1).median(0).values
        jump = rf - line(rf)
        s_r = torch.nanmedian(torch.where(keep, rough, torch.nan)).clamp(min=1e-9)
        w_pt = torch.where(keep & (rough <= 10.0 * s_r),
                           torch.clamp(3.0 * s_r / rough.clamp(min=1e-12), max=1.0),
                           torch.zeros_like(rough))
        shared = torch.nanmedian(torch.where(use.unsqueeze(-1), jump, torch.nan), 1).values
        dev = (jump - torch.nan_to_num(shared).unsqueeze(1)).norm(dim=-1)
        scale = torch.nanmedian(torch.where(use, dev, torch.nan)).clamp(min=1e-9)
        good = use & (dev <= torch.clamp(10.0 * scale, min=sm._GROSS_PX))
        w = w_pt.expand(d.shape[0], -1)
        full = torch.nan_to_num(torch.where(good.unsqueeze(-1), d, x @ coef + fill(r, good)))
        coef = sm._wls(x, full, w, eye)
    return coef, w, use


@pytest.mark.parametrize("f, n, chunk", [(700, 60, 7), (41, 30, 1), (3, 25, 1), (300, 90, 300)])
def test_series_fit_frame_chunk_by_frame_chunk_equals_the_whole_arrays(f, n, chunk,
                                                                       monkeypatch):
    """The series fit of a long movie's shared-motion pass, taken frame chunk by frame chunk
    from float32 measurements (the pass's precision; one (F, N) float64 array at a time),
    gives the very numbers of the fit over whole float64 arrays: long gaps, a point never
    valid, wrong peaks and points valid in only part of the frames included."""
    from torch_stsdic.core import shared_fit as sm

    g = torch.Generator().manual_seed(f + n)
    pts = torch.rand(n, 2, generator=g, dtype=torch.float64) * 300
    t = torch.arange(f, dtype=torch.float64)[:, None, None]
    disp = (0.05 * t + 1e-4 * pts[None] * t + 0.01 * torch.randn(
        f, n, 2, generator=g, dtype=torch.float64)).float()
    disp[torch.rand(f, n, generator=g) < 0.01] += 3.0  # wrong peaks
    disp[torch.rand(f, n, generator=g) < 0.005] = float("nan")
    ok = (torch.rand(f, n, generator=g) > 0.01) & torch.isfinite(disp).all(-1)
    ok[f // 3:2 * f // 3, :n // 6] = False  # long gaps: the fill reaches across chunks
    ok[:, -1] = False  # never valid
    ok[: f // 2, 1] = False  # valid in half of the frames only
    x = torch.stack([torch.ones(n, dtype=torch.float64), pts[:, 0] / 300, pts[:, 1] / 300], 1)
    eye = 1e-12 * torch.eye(3, dtype=torch.float64)
    monkeypatch.setattr(sm, "FIT_CHUNK", chunk * n)  # chunks of ``chunk`` frames
    got = sm._consistent_fit(x, disp, ok, eye)
    want = _whole_series_fit(x, disp, ok, eye)
    assert len(sm.frame_chunks(f, n)) == -(-f // chunk)
    for a, b in zip(got, want):
        assert torch.equal(a, b)
    ok[:, : n // 2] &= torch.rand(f, n // 2, generator=g) > 0.2  # few points valid throughout
    got = sm._consistent_fit(x, disp, ok, eye)
    want = _whole_series_fit(x, disp, ok, eye)
    for a, b in zip(got, want):
        assert torch.equal(a, b)


def test_lower_median_is_torch_nanmedian():
    """The median of all entries taken without a copy is ``torch.nanmedian``'s."""
    from torch_stsdic.core import shared_fit as sm

    g = torch.Generator().manual_seed(2)
    for n in (1, 2, 5, 1000, 1001):
        v = torch.rand(n, 3, generator=g, dtype=torch.float64) ** 3
        v[torch.rand(n, 3, generator=g) < 0.3] = torch.nan
        v[0, 0] = 0.0
        want = torch.nanmedian(v)
        assert torch.equal(sm._lower_median(v), want) or (want.isnan() and
                                                          sm._lower_median(v).isnan())
    assert sm._lower_median(torch.full((4, 2), torch.nan, dtype=torch.float64)).isnan()


def test_step_detection_in_chunks_equals_the_whole_series(monkeypatch):
    """The load steps of a long series found frame chunk by frame chunk (bounded memory)
    are those of the whole series at once, the increments' medians the very numbers."""
    from torch_stsdic.core import shared_fit as sm
    from torch_stsdic.core.shared_motion import detect_steps

    g = torch.Generator().manual_seed(5)
    f, n = 400, 90
    resid = 0.01 * torch.randn(f, n, 2, generator=g, dtype=torch.float64)
    resid[150:] += 0.3  # a load step into frame 150 (and 320 of the series below)
    resid[260:] -= 0.4
    resid[torch.rand(f, n, generator=g) < 0.005] = float("nan")
    valid = torch.rand(f, n, generator=g) > 0.05
    sigma = torch.full((f,), 0.01, dtype=torch.float64)
    frames = list(range(f))
    frames[200:] = [k + 60 for k in frames[200:]]  # a gap: frames 200.. are not adjacent
    monkeypatch.setattr(sm, "FIT_CHUNK", 7 * n)  # chunks of 7 frames
    chunked = detect_steps(resid, valid, sigma, frames)
    monkeypatch.setattr(sm, "FIT_CHUNK", 1 << 40)
    whole = detect_steps(resid, valid, sigma, frames)
    assert chunked == whole == [150, 320]


def test_shared_pass_in_chunks_equals_the_whole_series(frames, monkeypatch):
    """The shared-motion pass's fitted motion, load steps, scatter and standard errors are
    the same taken frame chunk by frame chunk (its fit, the fitted motion at the sample,
    the noise per frame, the steps) as over the whole series at once."""
    from torch_stsdic.core import shared_fit as sm
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan
    from torch_stsdic.movie.shared_pass import estimate_shared_motion

    plan = plan_run(frames, 0, None, None, (16, 16, 84, 84), None, 11, CFG, "cpu", None, 3)
    monkeypatch.setattr(sm, "FIT_CHUNK", 2 * plan.n_points)  # chunks of 2 frames
    chunked = estimate_shared_motion(plan, "affine", run=run_plan)
    monkeypatch.setattr(sm, "FIT_CHUNK", 1 << 40)
    whole = estimate_shared_motion(plan, "affine", run=run_plan)
    for name in ("params", "scatter", "se", "points", "measured"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name),
                                      err_msg=name)
    assert chunked.steps == whole.steps
    assert np.isfinite(chunked.se[1:]).all() and (chunked.se[1:] > 0).all()


def test_shared_pass_with_shake_and_load_steps_in_chunks_equals_the_whole_series(
        monkeypatch):
    """A render with a shared shake and load steps: the pass's fitted motion, standard
    errors and load steps taken two frames at a time (its fit from float32 measurements,
    its increments a chunk at a time) are those of the whole series at once."""
    from test_shared_motion import load_step_movie  # tests/ on the path

    from torch_stsdic.core import shared_fit as sm
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan
    from torch_stsdic.movie.shared_pass import estimate_shared_motion

    movie = load_step_movie()[0]
    plan = plan_run(movie, 0, None, None, None, None, 10, DICConfig(m=2), "cpu", None, 3)
    monkeypatch.setattr(sm, "FIT_CHUNK", 2 * plan.n_points)  # chunks of 2 frames
    chunked = estimate_shared_motion(plan, "affine", run=run_plan)
    monkeypatch.setattr(sm, "FIT_CHUNK", 1 << 40)
    whole = estimate_shared_motion(plan, "affine", run=run_plan)
    assert chunked.steps == whole.steps == [6, 12, 18]
    for name in ("params", "scatter", "se", "points", "measured"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name),
                                      err_msg=name)
    assert float(np.abs(chunked.params[1:, :2]).max()) > 0.1  # the shake was measured


def test_stored_result_rows_read_alone_equal_the_whole_results(frames, tmp_path):
    """A file-backed result's rows (any order, a subset of points) read from the file alone
    are those of the whole result's ``select``, and no whole field is read."""
    from torch_stsdic.analysis.result import TrackResult

    res = track(frames, out=tmp_path / "r.h5", **KW)
    ks = [int(res.frames[i]) for i in (5, 2, 3)]
    pts = torch.tensor([0, 3, 4])
    for fields in (res._fields, res.std, res.gradients):  # as a result opened afresh
        fields._held.clear()
    part = res.select(ks, pts)
    assert not (res._fields._held or res.std._held or res.gradients._held)  # none read whole
    want = TrackResult.select(res, ks, pts)  # through the whole fields
    assert part.frames.tolist() == ks and part.u.shape == (3, 3)
    for name in ("u", "v", "ut", "vt", "zncc", "status", "iterations", "m", "ux", "u_std"):
        a, b = part.field(name), want.field(name)
        assert a.dtype == b.dtype and torch.equal(a.nan_to_num(-9), b.nan_to_num(-9)), name


def test_window_share_counted_in_rows_equals_the_whole_array():
    """The run's summary of its windows' half-widths, counted a few rows at a time (a long
    movie's (T, N) array not copied whole), is that of the whole array."""
    from torch_stsdic.movie.estimates import _window_share

    g = torch.Generator().manual_seed(1)
    for shape in [(2000, 211), (7, 3), (1, 1)]:
        wm = torch.randint(0, 7, shape, generator=g).to(torch.int8)
        wm[wm == 3] = 5
        whole = wm.long()
        want = {"max_m": int(whole.max()),
                "chosen_m": {int(m): round(float((whole == m).double().mean()), 4)
                             for m in torch.unique(whole).tolist()}}
        assert _window_share(wm) == want
