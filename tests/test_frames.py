"""FrameCache: window frames, read-ahead in a background thread (same frames, each read once,
errors raised in the caller, the thread stopped), and track() equal with and without it."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.io import load_series
from torch_stsdic.movie.frames import FrameCache, default_ahead, frames_in_order, window_frames


def test_window_frames_shift_at_the_ends():
    w = window_frames(torch.tensor([0, 1, 5, 9]), 2, 10)
    assert w.tolist() == [[0, 1, 2, 3, 4], [0, 1, 2, 3, 4], [3, 4, 5, 6, 7], [5, 6, 7, 8, 9]]
    assert frames_in_order([[0], [1, 2], [7, 8, 9]], 1, 10) == [0, 1, 2, 3, 6, 7, 8, 9]
    assert frames_in_order([], 2, 10) == []


def test_default_ahead(monkeypatch):
    monkeypatch.delenv("TORCH_STSDIC_READ_AHEAD", raising=False)
    assert default_ahead(8, 2) == 12 and default_ahead(1, 0) == 4
    monkeypatch.setenv("TORCH_STSDIC_READ_AHEAD", "0")
    assert default_ahead(8, 2) == 0


class _Counting:
    """An ImageSeries that counts reads per frame (and can fail on one frame)."""

    def __init__(self, frames: np.ndarray, fail_at: int | None = None) -> None:
        self.inner = load_series(frames)
        self.count: dict[int, int] = {}
        self.threads: set[str] = set()
        self.fail_at = fail_at

    def __len__(self) -> int:
        return len(self.inner)

    def get(self, i, dtype=torch.float32, device=None):
        if i == self.fail_at:
            raise OSError(f"cannot decode frame {i}")
        self.count[i] = self.count.get(i, 0) + 1
        self.threads.add(threading.current_thread().name)
        return self.inner.get(i, dtype=dtype, device=device)


def _frames(n=9, size=40):
    g = torch.Generator().manual_seed(0)
    return (torch.rand(n, size, size, generator=g) * 255).numpy()


def _blocks(cache, blocks, m, n):
    out = []
    for b in blocks:
        idx = torch.unique(window_frames(torch.tensor(b), m, n)).tolist()
        view = cache.in_ring(idx)
        planes = torch.tensor(view.planes)
        out.append((idx, view.raw[planes].clone(), view.img.coeffs[planes].clone()))
    return out


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device (pinned memory, side stream)"))])
def test_read_ahead_gives_the_same_frames_each_read_once(device):
    frames = _frames()
    solver = SubsetSolver(sts.DICConfig(m=1))
    blocks, m, n = [[0], [1, 2, 3], [4, 5, 6], [7, 8]], 1, len(frames)
    plain = FrameCache(_Counting(frames), solver, torch.float32, "cpu")
    want = _blocks(plain, blocks, m, n)
    series = _Counting(frames)
    cache = FrameCache(series, solver, torch.float32, device, ahead=2)
    cache.schedule(frames_in_order(blocks, m, n))
    got = _blocks(cache, blocks, m, n)
    cache.close()
    tol = 0 if device == "cpu" else 1e-3  # the FFT prefilter on CUDA, the C++ one on CPU
    for (i1, r1, c1), (i2, r2, c2) in zip(want, got):
        assert i1 == i2 and torch.equal(r1, r2.cpu())
        torch.testing.assert_close(c2.cpu(), c1, rtol=0, atol=tol)
    assert series.count == {i: 1 for i in range(n)}  # every frame read once
    assert series.threads == {"stsdic-frames"}  # and in the background
    t = cache.times()
    assert t["ahead_read_s"] > 0 and t["ahead_prefilter_s"] > 0 and t["read_s"] == 0
    assert cache.reads == n and cache.prefiltered == n
    assert not any(th.name == "stsdic-frames" for th in threading.enumerate())


def test_out_of_order_frames_are_read_on_the_spot():
    frames = _frames()
    solver = SubsetSolver(sts.DICConfig(m=1))
    series = _Counting(frames)
    cache = FrameCache(series, solver, torch.float32, "cpu", ahead=3)
    cache.schedule([0, 1, 2, 3, 4])
    raw = cache.in_ring([3, 4]).frames_raw()  # 0..2 skipped (e.g. blocks replayed from a file)
    assert torch.equal(raw[0], torch.from_numpy(frames[3]))
    raw = cache.in_ring([1, 7]).frames_raw()  # behind the reader / not scheduled: read directly
    assert torch.equal(raw[1], torch.from_numpy(frames[7]))
    assert torch.equal(cache.read(8), torch.from_numpy(frames[8]))
    cache.close()
    cache.close()  # idempotent


def test_frames_the_store_drops_after_the_schedule_are_still_read_ahead():
    """A frame the store holds when the read-ahead is scheduled (an earlier pass's) but drops
    before a block needs it (a bounded store) is read by the reader, not on the spot by the
    blocks; one the store still holds when the reader reaches it is handed over as it is."""
    from torch_stsdic.movie.frames import FrameStore

    frames = _frames(n=12)
    solver = SubsetSolver(sts.DICConfig(m=1))
    blocks, m, n = [[0, 1], [2, 3, 4], [5, 6, 7], [8, 9], [10, 11]], 1, len(frames)
    store = FrameStore(1e3, max_frames=10)
    first = FrameCache(_Counting(frames), solver, torch.float32, "cpu", store=store)
    want = _blocks(first, blocks, m, n)  # the earlier pass: the store holds the last ten
    series = _Counting(frames)
    cache = FrameCache(series, solver, torch.float32, "cpu", ahead=3, store=store)
    cache.schedule(frames_in_order(blocks, m, n))
    got = _blocks(cache, blocks, m, n)
    cache.close()
    for (i1, r1, c1), (i2, r2, c2) in zip(want, got):
        assert i1 == i2 and torch.equal(r1, r2) and torch.equal(c1, c2)
    assert series.threads == {"stsdic-frames"}  # none read by the blocks themselves
    assert cache.times()["read_s"] == 0 and cache.times()["prefilter_s"] == 0
    # a frame the store held when the reader reached it: handed over, not read again, though
    # the store dropped it before the block asked for it
    store = FrameStore(1e3)
    _blocks(FrameCache(_Counting(frames), solver, torch.float32, "cpu", store=store),
            [[0, 1]], 1, n)  # frames 0..2 in the store
    series = _Counting(frames)
    cache = FrameCache(series, solver, torch.float32, "cpu", ahead=4, store=store)
    cache.schedule([0, 1, 2, 3])
    deadline = time.monotonic() + 20.0
    while cache._reader.queued < 4 and time.monotonic() < deadline:
        time.sleep(0.005)
    store._frames.clear()  # dropped (other frames put there)
    view = cache.in_ring([0, 1, 2, 3])
    cache.close()
    assert series.count == {3: 1}  # only the frame the store did not hold was read
    for j in range(4):
        assert torch.equal(view.raw[view.planes[j]], torch.from_numpy(frames[j]))


def test_reader_errors_reach_the_caller():
    solver = SubsetSolver(sts.DICConfig(m=1))
    cache = FrameCache(_Counting(_frames(), fail_at=2), solver, torch.float32, "cpu", ahead=2)
    cache.schedule([0, 1, 2, 3])
    cache.in_ring([0, 1])
    with pytest.raises(OSError, match="cannot decode frame 2"):
        cache.in_ring([1, 2])
    cache.close()


def test_close_waits_for_the_frame_under_way(monkeypatch):
    """A frame that takes longer than one of close's waits (a large frame on a busy CPU) is
    finished before close returns: a daemon thread still inside a torch op at the
    interpreter's shutdown aborts the process after its results are written."""
    import time

    from torch_stsdic.movie import frames as frames_mod

    class _Slow(_Counting):
        def get(self, i, dtype=torch.float32, device=None):
            if i == 2:
                self.started = time.monotonic()
                time.sleep(0.6)  # (the GIL released, as in a torch op)
            return super().get(i, dtype=dtype, device=device)

    monkeypatch.setattr(frames_mod._Reader, "JOIN_SLICE_S", 0.05)
    series = _Slow(_frames())
    cache = FrameCache(series, SubsetSolver(sts.DICConfig(m=1)), torch.float32, "cpu", ahead=1)
    cache.schedule(list(range(9)))
    reader = cache._reader
    cache.in_ring([0])
    deadline = time.monotonic() + 20.0
    while not hasattr(series, "started") and time.monotonic() < deadline:
        time.sleep(0.005)
    assert hasattr(series, "started"), "the reader never reached the slow frame"
    cache.close()
    assert not reader.is_alive()
    assert time.monotonic() - series.started >= 0.55  # it waited for the frame
    assert 3 not in series.count  # and read no further


def test_track_equal_with_and_without_read_ahead(monkeypatch):
    mv = synth.synthetic_movie((64, 64), 8, synth.Translation(ut=0.1, vt=-0.05), seed=1,
                               noise_sigma=1.0)
    kw = dict(reference=mv.ref, step=16, config=sts.DICConfig(subset_size=15, m=1),
              progress=False, batch_frames=3)
    monkeypatch.setenv("TORCH_STSDIC_READ_AHEAD", "0")
    want = sts.track(mv.frames, **kw)
    monkeypatch.setenv("TORCH_STSDIC_READ_AHEAD", "3")
    got = sts.track(mv.frames, **kw)
    torch.testing.assert_close(got.u, want.u, rtol=0, atol=0, equal_nan=True)
    assert torch.equal(got.status, want.status)
    assert got.info["frames_read"] == want.info["frames_read"] == 8
    assert got.info["frame_times_s"]["ahead_read_s"] > 0
    assert want.info["frame_times_s"]["ahead_read_s"] == 0
    err = (want.u - 0.1 * mv.times.view(-1, 1))[want.ok]
    assert want.ok.float().mean() > 0.5 and float(err.abs().max()) < 0.05


def test_read_ahead_is_bounded():
    """The reader stays at most ``ahead`` frames (+ the one it holds) ahead of the caller."""
    import time

    series = _Counting(_frames(n=12))
    cache = FrameCache(series, SubsetSolver(sts.DICConfig(m=1)), torch.float32, "cpu", ahead=2)
    cache.schedule(list(range(12)))
    cache.in_ring([0, 1, 2])
    deadline = time.monotonic() + 20.0
    while len(series.count) < 3 + 2 and time.monotonic() < deadline:  # the queue fills up
        time.sleep(0.01)
    time.sleep(0.2)  # and the reader would go on if it were not bounded
    assert 3 + 2 <= len(series.count) <= 3 + 2 + 1
    cache.close()


def test_coarse_to_fine_with_kept_pyramids_equals_fresh_ones_and_builds_once():
    from torch_stsdic.core.initial import coarse_to_fine
    from torch_stsdic.core.pyramid import PyramidStack

    mv = synth.synthetic_movie((96, 96), 4, synth.Translation(ut=3.0, vt=-2.0), seed=3,
                               noise_sigma=1.0)
    frames = mv.frames.float()
    ref = frames[:1]
    pts = torch.tensor([[40.0, 48.0], [56.0, 40.0], [48.0, 56.0]])
    fidx = torch.tensor([[1, 2], [2, 3], [3, 1]])
    want = coarse_to_fine(ref, frames, pts, 11, 3, 2, frame_index=fidx)
    pyr = (PyramidStack.of(ref), PyramidStack.of(frames))
    for _ in range(3):  # the same images searched again: their levels are not built again
        got = coarse_to_fine(ref, frames, pts, 11, 3, 2, frame_index=fidx, pyramids=pyr)
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    assert [p.builds for p in pyr[0].pyramids] == [2]
    assert [p.builds for p in pyr[1].pyramids] == [0, 2, 2, 2]  # frame 0 is never read
    err = want[0] - torch.tensor([[3.0, -2.0]]) * fidx.unsqueeze(-1).float()
    assert float(err.abs().max()) < 0.5


def test_a_run_prepares_each_frame_once_across_its_passes():
    """The shared-motion pass, the time-model pass and the blocks read the same frames:
    each is read, prefiltered and its pyramid levels built once in the run (the store), and
    once per pass without it."""
    from torch_stsdic.movie.frames import FrameStore
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan

    n = 9
    # the first target (frame 4) is 8 px from the reference frame, beyond the search
    # radius: the first block of every pass searches its weak peaks on the pyramids
    mv = synth.synthetic_movie((112, 112), n, synth.Translation(ut=2.0, vt=-1.0), seed=2,
                               noise_sigma=1.0, margin=24)
    cfg = sts.DICConfig(subset_size=15, m=1, search_radius=4)

    def run(store):
        plan = plan_run(mv.frames, 0, list(range(4, n)), None, None, None, 12, cfg, "cpu",
                        None, 3)
        return run_plan(plan, progress=False, frames=store)

    made, res = _prefilters(mv.frames, lambda: run(None))
    assert res.info["shared_motion"] and res.info["series_reference"]
    read = len(range(3, n)) + 1  # the windows of 4..8 (m = 1) and the reference frame 0
    assert sorted(made) == sorted(set(made)) and len(made) == read  # each frame once
    assert res.info["frames_read"] == res.info["prefiltered"] == read
    assert 0 < res.info["pyramid_levels"] <= 3 * read  # at most 3 levels a frame
    err = (res.u - 2.0 * (mv.times[4:] - mv.times[0]).view(-1, 1))[res.ok]
    # (the points of the last column leave the image)
    assert res.ok.float().mean() > 0.85 and float(err.abs().max()) < 0.05
    again = run(FrameStore(0))  # no store across passes: every pass prepares its frames
    assert again.info["prefiltered"] > 2 * read
    # (only the first pass's first block searches on the pyramids: the later passes start
    # from its solutions, and the rescue no longer searches the points leaving the image)
    assert again.info["pyramid_levels"] >= res.info["pyramid_levels"]
    torch.testing.assert_close(again.u, res.u, rtol=0, atol=0, equal_nan=True)


def _prefilters(frames: torch.Tensor, fn):
    """The movie frames (indices into ``frames`` (F, H, W)) B-spline prefiltered while
    ``fn()`` runs (the template's splats included), one entry per prefilter, and its
    result."""
    from torch_stsdic.core import interpolation

    frames = frames.float()
    made: list[int] = []
    init = interpolation.BSplineImage.__init__

    def counted(self, images, *a, **k):
        if tuple(images.shape[-2:]) == tuple(frames.shape[-2:]):  # whole frames
            for img in images.reshape(-1, *images.shape[-2:]):
                same = (frames == img.float().cpu()).flatten(1).all(1)
                made.extend(torch.nonzero(same).flatten().tolist())
        init(self, images, *a, **k)

    interpolation.BSplineImage.__init__ = counted
    try:
        return made, fn()
    finally:
        interpolation.BSplineImage.__init__ = init


def test_a_store_keeps_the_frames_it_is_told_to_within_its_budget():
    """``FrameStore.keeping``: the named frames kept beyond the store's budget (none here),
    the first put first up to ``keep_mb``; an inner block's frames let go at its end, not
    the outer block's; all let go after the outer one."""
    from collections import namedtuple

    from torch_stsdic.movie.frames import FrameStore

    frame = namedtuple("frame", "nbytes")
    store = FrameStore(0, max_frames=4, keep_mb=3 * 2**-20)  # three 1-byte frames
    with store.keeping([1, 2, 3, 4]):
        for i in range(6):
            store.put((i,), frame(1))
        assert [(i,) in store for i in range(6)] == [False, True, True, True, False, False]
        with store.keeping([5]):  # (the keep budget is full: 5 is not kept)
            store.put((5,), frame(1))
            assert (5,) not in store and store.get((2,)) is not None
        with store.keeping([2]):
            pass
        assert [(i,) in store for i in range(6)] == [False, True, True, True, False, False]
    assert not any((i,) in store for i in range(6))  # a store that keeps none: dropped
    store = FrameStore(1e3, keep_mb=1.0)  # one that keeps frames: they stay, least recent
    with store.keeping([0]):              # first out as ever
        store.put((0,), frame(10))
    assert (0,) in store


def test_a_long_movie_prepares_the_template_frames_once_in_its_passes(monkeypatch):
    """A movie longer than the store keeps frames for (none beyond a block: the store's
    budget is 0): the frames that the template's rounds and its shared classical pass read
    are prepared once by the passes (kept while they run), every frame at most twice in the
    run (the shared-motion pass's sweep and the blocks'), the same results to the bit as
    without (every round prepared them again)."""
    import contextlib

    from torch_stsdic.movie import series as series_mod
    from torch_stsdic.movie.frames import FrameStore
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan
    from torch_stsdic.movie.series_reference import set_series_reference

    monkeypatch.setattr(series_mod, "STORE_FRAMES", 0)  # 14 frames > 2 (3 + 2): a long movie
    n = 14
    mv = synth.synthetic_movie((96, 96), n, synth.Translation(ut=0.4, vt=-0.3), seed=5,
                               noise_sigma=1.0, margin=16)
    cfg = sts.DICConfig(subset_size=15, m=1)

    def run():
        plan = plan_run(mv.frames, 0, None, None, None, None, 12, cfg, "cpu", None, 3)
        set_series_reference(plan, True, max_frames=6)  # (a sample of the frames)
        return run_plan(plan, progress=False)

    made, res = _prefilters(mv.frames, run)
    assert res.info["shared_motion"] and res.info["series_reference"]
    sampled = res.info["series_reference"]["frames"]
    assert 3 <= len(sampled) < n
    count = np.bincount(made, minlength=n)
    assert count.max() <= 2 and all(count[k] <= 2 for k in sampled)
    monkeypatch.setattr(FrameStore, "keeping", lambda self, frames: contextlib.nullcontext())
    again, res2 = _prefilters(mv.frames, run)
    assert len(again) > len(made) + len(sampled)  # the template's rounds prepared them again
    for name in ("u", "v", "ut", "vt", "status"):
        torch.testing.assert_close(res2.field(name), res.field(name), rtol=0, atol=0,
                                   equal_nan=True)


def test_a_dropped_frame_with_its_pyramid_is_freed_at_once():
    """A prepared frame whose pyramid was built (its levels counted in the store) is freed
    when dropped, not left in a reference cycle for Python's cyclic collector (a long run's
    peak memory grew with its length while such frames waited for a full collection)."""
    import gc
    import weakref
    from collections import Counter

    from torch_stsdic.movie.frames import PreparedFrame

    raw = torch.rand(64, 64)
    builds: Counter[int] = Counter()
    frame = PreparedFrame(7, raw, SubsetSolver(sts.DICConfig()).prepare(raw), builds=builds)
    frame.pyramid().level(1)  # builds a level: counted for frame 7
    assert builds == Counter({7: 1})
    gone = weakref.ref(frame)
    enabled = gc.isenabled()
    gc.disable()
    try:
        del frame
        assert gone() is None  # freed by its reference count alone
    finally:
        if enabled:
            gc.enable()


def test_a_block_holds_the_frames_of_every_shorter_window_inside_a_load_segment():
    """Load steps at frames 10 and 22 leave a 12-frame segment: the longest window (m = 6)
    does not fit it and is not shifted, a shorter one (m = 4) is, and reaches frames 13, 14
    outside the longest's 15 .. 27. A block must hold them (it held the longest window's
    frames only: its rows solved with m = 4 read the wrong frames, or crashed the native
    kernel with a frame index past its frames, as a 10,000-frame run did)."""
    from torch_stsdic.movie.frames import block_frames, segment_bounds, window_frames

    seg = segment_bounds([10, 22], 40)
    ks = torch.tensor([21])
    longest = set(window_frames(ks, 6, 40, seg).flatten().tolist())
    assert {13, 14} <= set(window_frames(ks, 4, 40, seg).flatten().tolist()) - longest
    held = block_frames(ks, 6, 40, seg)
    assert held == sorted(set(held))  # sorted, once each
    for m in range(7):
        assert set(window_frames(ks, m, 40, seg).flatten().tolist()) <= set(held)
    # a target at the segment's start: m = 4 reaches past the longest window's last frame
    # (the frame index one past the block's frames that crashed the native kernel)
    first = torch.tensor([10])
    past = set(window_frames(first, 4, 40, seg).flatten().tolist()) - set(
        window_frames(first, 6, 40, seg).flatten().tolist())
    assert past == {17, 18} and past <= set(block_frames(first, 6, 40, seg))
    # without load steps the longest window holds every shorter one: nothing more is read
    for k in (0, 3, 20, 36, 39):
        kk = torch.tensor([k])
        assert block_frames(kk, 6, 40) == torch.unique(window_frames(kk, 6, 40)).tolist()


def test_the_ring_copies_each_frame_once_and_its_planes_hold_the_frames_asked_for():
    """Sliding blocks through FrameCache.in_ring: every frame copied into the shared stack
    once while it stays in use (not 2m+1 times), each plane the frame asked for (pixels and
    coefficients equal to a fresh stack's), planes freed and reused, the stack grown when a
    block needs more frames than it has planes."""
    frames = _frames(n=12)
    series = load_series(frames)
    solver = SubsetSolver(sts.DICConfig(m=1))
    cache = FrameCache(series, solver, torch.float32, "cpu")
    plain = FrameCache(series, solver, torch.float32, "cpu")
    blocks = [[0], [1], [2], [3, 4], [5], [6, 7, 8], [9], [10], [11]]
    for b in blocks:
        idx = torch.unique(window_frames(torch.tensor(b), 1, 12)).tolist()
        view = cache.in_ring(idx)
        raw = torch.stack([plain.frame(i).raw for i in idx])  # each frame prepared alone
        coeffs = torch.cat([plain.frame(i).prep.coeffs for i in idx])
        planes = torch.tensor(view.planes)
        assert torch.equal(view.raw[planes], raw)
        assert torch.equal(view.img.coeffs[planes], coeffs)
        assert torch.equal(view.frames_raw(), raw)
        assert len(set(view.planes)) == len(idx) and max(view.planes) < view.img.n_frames
        assert view.img.n_frames == view.raw.shape[0] == len(view.pyramids)
        # the pyramid of each plane is its frame's
        lev = view.pyramids.levels(1, planes)
        ref = sts.core.pyramid.PyramidStack.of(raw).levels(1)
        assert all(torch.equal(a, b) for a, b in zip(lev, ref))
    assert cache._ring.capacity == 5  # grew to the longest block (frames 5..9)
    assert cache._ring.copies == 12  # each frame once (the planes kept when it grew)
    assert cache._ring.pixel_copies == 12  # and its pixels once, where asked for


def test_the_ring_copies_a_frames_pixels_only_where_a_block_asks_for_them():
    """The coefficients of a block's frames go into the ring at once (every solve reads
    them); their pixels (the FFT guess's) only when a block asks for them, once while the
    frame holds its plane, kept when the stack grows."""
    frames = _frames(n=8)
    series = load_series(frames)
    solver = SubsetSolver(sts.DICConfig(m=1))
    cache = FrameCache(series, solver, torch.float32, "cpu")
    ring = cache._ring
    view = cache.in_ring([0, 1, 2])
    assert (ring.copies, ring.pixel_copies) == (3, 0)
    view = cache.in_ring([1, 2, 3])  # one frame new: its coefficients only
    assert (ring.copies, ring.pixel_copies) == (4, 0)
    raw = view.raw
    assert ring.pixel_copies == 3
    planes = torch.tensor(view.planes)
    assert torch.equal(raw[planes], torch.stack([cache.frame(i).raw for i in (1, 2, 3)]))
    view.raw  # noqa: B018  (asked again: no copy)
    assert ring.pixel_copies == 3
    view = cache.in_ring([1, 2, 3, 4, 5])  # the stack grows: the pixels held are kept
    assert ring.pixel_copies == 3
    raw = view.raw
    assert ring.pixel_copies == 5  # frames 4 and 5 only
    planes = torch.tensor(view.planes)
    assert torch.equal(raw[planes], torch.stack([cache.frame(i).raw for i in range(1, 6)]))


def test_upload_puts_a_host_tensor_on_the_device_with_its_values():
    """``frames.upload``: the values on the device asked for (on a GPU from pinned memory, a
    copy that does not wait for the device's queue); a tensor already there is itself."""
    from torch_stsdic.movie.frames import upload

    t = torch.arange(7, dtype=torch.long)
    assert upload(t, "cpu") is t
    if torch.cuda.is_available():
        g = upload(t, "cuda")
        assert g.device.type == "cuda" and torch.equal(g.cpu(), t)
        assert upload(g, "cuda") is g
