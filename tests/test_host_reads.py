"""A solve without host reads of its own (issue 45, item 3): the per-point kernel iterates every
row of a stage (rows not to iterate masked, not chosen by an index), and a block's reference
subsets are kept once for all its solves (the cache's misses not counted per solve). Both
give what the solves gave before, bit for bit."""

import os

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core import gauss_newton, point_solve
from torch_stsdic.core.gauss_newton import ReferenceCache
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.kernels import native

pytestmark = pytest.mark.skipif(not native.available(), reason="no native kernels")

N = 96


@pytest.fixture
def per_point():
    old = os.environ.get("TORCH_STSDIC_PER_POINT")
    os.environ["TORCH_STSDIC_PER_POINT"] = "1"
    yield
    if old is None:
        os.environ.pop("TORCH_STSDIC_PER_POINT", None)
    else:
        os.environ["TORCH_STSDIC_PER_POINT"] = old


def _window(flat_left: bool = False):
    """A 5-frame window of a speckle render (a strain and a drift), its left quarter flat in
    every image where ``flat_left`` (those points have no texture), and a grid of points."""
    pattern = synth.make_speckle((N, N), seed=5)
    motion = synth.HomogeneousStrain(exx=0.01, eyy=-0.004, exy=0.003, center=(N / 2, N / 2)) \
        + synth.Translation(0.4, -0.3, ut=0.05, vt=0.02)
    times = torch.arange(0.0, 5.0, dtype=torch.float64)
    ref, frames = synth.render_series(pattern, (N, N), motion, times, noise_sigma=1.0, seed=3,
                                      reference_time=None)
    if flat_left:
        ref = ref.clone()
        frames = frames.clone()
        ref[:, : N // 4] = 100.0
        frames[:, :, : N // 4] = 100.0
    c = torch.arange(14.0, N - 14.0, 4.0, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    return ref, frames, torch.stack([xx.reshape(-1), yy.reshape(-1)], 1), times


def test_a_stage_iterates_every_row_without_an_index_of_them(per_point, monkeypatch):
    """Points without texture (LOW_TEXTURE, not iterated) in the same stage as textured ones:
    the kernel runs every row, no index of the rows to iterate is made (``start_stage`` is
    not called), the untextured rows end as before (LOW_TEXTURE, 0 iterations, no result)
    and every other row equals its solve without them, bit for bit."""
    ref, frames, pts, times = _window(flat_left=True)
    cfg = sts.DICConfig(m=2, subset_size=15)
    init = torch.zeros(pts.shape[0], 2, dtype=torch.float64)
    init[:, 0], init[:, 1] = 0.4, -0.3
    full = sts.solve_window(ref, frames, pts, config=cfg, times=times, init=init)
    flat = full.status == int(sts.Status.LOW_TEXTURE)
    assert 0 < int(flat.sum()) < pts.shape[0] // 2
    assert bool((full.iterations[flat] == 0).all())
    assert bool(torch.isnan(full.params[flat]).all())
    textured = ~flat
    assert bool((full.status[textured] == int(sts.Status.CONVERGED)).all())

    def no_index(*a, **k):
        raise AssertionError("the rows to iterate were chosen by an index")
    monkeypatch.setattr(point_solve, "start_stage", no_index)
    again = sts.solve_window(ref, frames, pts, config=cfg, times=times, init=init)
    alone = sts.solve_window(ref, frames, pts[textured], config=cfg, times=times,
                             init=init[textured])
    assert torch.equal(again.status, full.status)
    assert torch.equal(again.params[textured], alone.params)
    assert torch.equal(again.zncc[textured], alone.zncc)
    assert torch.equal(again.iterations[textured], alone.iterations)


def _solver_and_images(cfg):
    ref, frames, pts, times = _window()
    solver = SubsetSolver(cfg)
    solver.reference_cache = ReferenceCache(256.0)
    ref_img = solver.prepare(ref.to(torch.float32))
    frames_img = solver.prepare(frames.to(torch.float32))
    return solver, ref, ref_img, frames_img, pts.to(torch.float32), times


#: the operations that make a host wait for a GPU, as the dispatcher names them
READS = ("_local_scalar_dense", "is_nonzero", "nonzero", "_unique2", "unique_dim",
         "unique_consecutive")


class _Dispatched(TorchDispatchMode):
    """Records the names of the torch operations dispatched inside it (only ``names`` where
    given) in :attr:`seen`."""

    def __init__(self, names: tuple[str, ...] | None = None) -> None:
        super().__init__()
        self.names, self.seen = names, []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if self.names is None or name in self.names:
            self.seen.append(name)
        return func(*args, **(kwargs or {}))


def test_kept_subsets_are_read_without_counting_the_misses(per_point, monkeypatch):
    """``keep_reference_subsets`` samples the points' reference subsets once; a solve given its
    token reads them with no count of the misses (``_keep_missing`` not called) and equals a
    solve that samples its own; once the cache has dropped them (another reference) the
    token is stale and the solve samples them again."""
    cfg = sts.DICConfig(m=2, subset_size=15)
    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(cfg)
    dt = (times - 2.0).to(torch.float32)
    init = torch.tensor([0.4, 0.0, 0.0, 0.05, -0.3, 0.0, 0.0, 0.02]).expand(pts.shape[0], -1)
    token = solver.keep_reference_subsets(ref_img, pts)
    assert token is not None and solver.reference_cache.count == pts.shape[0]

    calls = []
    real = gauss_newton._keep_missing

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)
    monkeypatch.setattr(gauss_newton, "_keep_missing", counted)
    kept = solver.solve(ref_img, frames_img, pts[::2], dt, init=init[::2], on_grid=True,
                        kept=token)
    assert calls == []
    own, _, own_ref, own_frames, _, _ = _solver_and_images(cfg)
    plain = own.solve(own_ref, own_frames, pts[::2], dt, init=init[::2], on_grid=True)
    assert torch.equal(kept.params, plain.params) and torch.equal(kept.status, plain.status)
    assert torch.equal(kept.std, plain.std)

    # another reference: the cache drops what it kept, the old token no longer holds
    other = solver.prepare((ref.flip(1)).to(torch.float32))
    solver.keep_reference_subsets(other, pts[:3])
    assert solver.reference_cache.token() != token
    calls.clear()
    again = solver.solve(ref_img, frames_img, pts[::2], dt, init=init[::2], on_grid=True,
                         kept=token)
    assert calls  # sampled again
    assert torch.equal(again.params, plain.params)


def test_a_block_keeps_its_subsets_once(monkeypatch):
    """In a movie run the blocks' solves read their reference subsets through the block's
    token: ``_keep_missing`` runs where a block keeps them (its POIs, its moved subsets), not
    in every solve."""
    pattern = synth.make_speckle((N, N), seed=2)
    motion = synth.Translation(0.2, -0.1, ut=0.1, vt=0.05)
    times = torch.arange(0.0, 12.0, dtype=torch.float64)
    _, movie = synth.render_series(pattern, (N, N), motion, times, noise_sigma=1.0, seed=4,
                                   reference_time=None)
    callers = []
    real = gauss_newton._keep_missing

    def counted(ctx, *a, **k):
        import inspect
        callers.append(inspect.stack()[1].function)
        return real(ctx, *a, **k)
    monkeypatch.setattr(gauss_newton, "_keep_missing", counted)
    res = sts.track(movie.to(torch.float32), config=sts.DICConfig(m=2, subset_size=15), step=8,
                    progress=False, series_reference=False)
    assert float((res.status <= int(sts.Status.MAX_ITER)).double().mean()) > 0.9
    per_solve = callers.count("_cached_reference_data")
    assert callers.count("keep_subsets") >= 2  # the blocks kept them
    # the first block's FFT start solves through another path; every later solve is served
    assert per_solve <= 2, callers


def test_rows_grouped_by_half_width_in_one_read():
    """``rows_by_half_width``: each half-width the chosen rows take, with their indices in
    ascending order (as an index per half-width gave them); half-widths clamped to
    0 .. m_max; rows not chosen left out."""
    from torch_stsdic.movie.frames import rows_by_half_width

    m_of = torch.tensor([3, 1, 3, 0, 2, 1, 9, 3, -1], dtype=torch.int8)
    rows = torch.tensor([1, 1, 1, 1, 0, 1, 1, 0, 1], dtype=torch.bool)
    got = [(m, r.tolist()) for m, r in rows_by_half_width(m_of, rows, 4)]
    assert got == [(0, [3, 8]), (1, [1, 5]), (3, [0, 2]), (4, [6])]
    assert rows_by_half_width(m_of, torch.zeros_like(rows), 4) == []


def test_the_reference_cache_tells_its_geometry_by_a_host_key(monkeypatch):
    """A solve's geometry is told from the cache's by a key of host facts (window kind and
    settings, the spatial shape, dtype, device), not by comparing tensors (``torch.equal``:
    a read of the device): equal settings, equal keys, the cache applies; another sigma or
    window size is another key; a window of the user's own has none (its tensors compared)."""
    from torch_stsdic.core import window as window_mod
    from torch_stsdic.core.formulations import Geometry

    cfg = sts.DICConfig(m=2, subset_size=15)
    solver, _, ref_img, _, pts, _ = _solver_and_images(cfg)
    shape = solver.shape

    def geo(win):
        return Geometry.make(shape, win, "znssd", torch.float32, "cpu")
    g1, g2 = geo(window_mod.GaussianWindow(15)), geo(window_mod.GaussianWindow(15))
    assert g1.key is not None and g1.key == g2.key and g1 is not g2
    other = geo(window_mod.GaussianWindow(15, sigma=2.0))
    assert other.key != g1.key
    assert geo(window_mod.SquareWindow(17)).key != geo(window_mod.SquareWindow(15)).key
    assert geo(window_mod.make_window("square", 15)).key == geo(window_mod.SquareWindow(15)).key
    assert Geometry.make(shape.spatial(), window_mod.SquareWindow(15), "znssd", torch.float32,
                         "cpu").key == geo(window_mod.SquareWindow(15)).key  # same subsets

    class Mine(window_mod.SquareWindow):
        pass
    assert geo(Mine(15)).key is None

    cache = ReferenceCache(64.0)
    assert cache.applies(ref_img, g1)
    with monkeypatch.context() as mp:
        mp.setattr(torch, "equal", lambda *a: (_ for _ in ()).throw(
            AssertionError("compared on the device")))
        assert cache.applies(ref_img, g2)  # by the key: no torch.equal
    assert not cache.applies(ref_img, other)  # another key: the tensors differ
    assert cache.applies(ref_img, geo(Mine(15))) is False  # a square's, not the Gaussian's


def test_the_shared_velocity_at_the_target_reads_nothing_and_is_the_line_where_centred():
    """``shared_velocity.target_slope`` takes the quadratic's derivative at the target where
    a window is shifted and the motion bends, the line's slope elsewhere, without a host
    read of whether any window is shifted; a shifted window of two distinct times (no
    quadratic) gives the line, not an error."""
    from torch_stsdic.core.shared_motion import window_slope
    from torch_stsdic.movie.shared_velocity import target_slope

    reads = _Dispatched(("_local_scalar_dense", "is_nonzero", "nonzero"))

    centred = torch.arange(-3.0, 4.0, dtype=torch.float64)
    shifted = torch.arange(0.0, 7.0, dtype=torch.float64)  # the movie's first frame
    repeated = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    dt = torch.stack([centred, shifted, repeated])[:, None, :].expand(3, 4, 7)  # (B, N, T)
    b1, c2 = torch.tensor([0.3, -0.1]), torch.tensor([0.02, 0.05])  # px/frame, px/frame^2
    g = 1.5 + b1 * dt.unsqueeze(-1) + c2 * dt.unsqueeze(-1) ** 2  # (B, N, T, 2)
    frame_var = torch.full((3, 4), 1e-6, dtype=torch.float64)
    with reads:
        slope, used, var = target_slope(g, dt, frame_var)
    assert not reads.seen
    line = window_slope(g.double(), dt)
    assert not used[0].any() and torch.equal(slope[0], line[0]) and not var[0].any()
    assert used[1].all() and torch.allclose(slope[1], b1.double().expand(4, 2), atol=1e-9)
    assert not used[2].any() and torch.equal(slope[2], line[2])


def test_the_cache_keeps_new_subsets_with_one_read_of_the_misses(monkeypatch):
    """``keep_reference_subsets`` of points of which some are kept already and some repeat
    (a block's moved subsets: the same pixel in several targets) reads the device once for
    its misses (how many distinct pixels: not a count, an index and a unique) and keeps
    each new pixel's subset once, the same numbers as sampling it alone."""
    from torch_stsdic.core import gauss_newton as gn

    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(sts.DICConfig(m=0,
                                                                                    subset_size=15))
    assert solver.keep_reference_subsets(ref_img, pts[:10]) is not None
    count = solver.reference_cache.count
    moved = torch.cat([pts[5:20], pts[12:20], pts[:3]])  # kept, new, repeated
    reads = _Dispatched(READS)
    sampled_rows, in_sampling = [], _Dispatched(READS)  # the sampling's own reads apart
    real = gn._sampled

    def sampled(ctx, p, dt, fidx, ridx, rows, *rest):
        sampled_rows.append(rows.clone())
        with in_sampling:
            return real(ctx, p, dt, fidx, ridx, rows, *rest)
    monkeypatch.setattr(gn, "_sampled", sampled)
    with reads:
        assert solver.keep_reference_subsets(ref_img, moved) is not None
    monkeypatch.setattr(gn, "_sampled", real)
    # one read of the misses (how many distinct pixels), besides the sampling's own (the C++
    # sampler's argument checks on the CPU); no unique, no index
    assert not {"_unique2", "nonzero"} & set(reads.seen), reads.seen
    assert len(reads.seen) == len(in_sampling.seen) + 1, (reads.seen, in_sampling.seen)
    cache = solver.reference_cache
    assert cache.count == count + 10  # pts[10:20] new, each once
    # the first row of each new pixel, in the keys' order (rows 5..14 of `moved`)
    assert sampled_rows[0].tolist() == list(range(5, 15))
    fresh = SubsetSolver(solver.config)
    fresh.reference_cache = ReferenceCache(256.0)
    fresh.keep_reference_subsets(ref_img, pts[10:20])
    for k in ("ft", "gx", "gy", "gram"):
        assert torch.equal(cache.rows[k][count:], fresh.reference_cache.rows[k])


def test_the_cache_keeps_new_subsets_without_a_read_given_their_count(monkeypatch):
    """With the count of its misses read by the caller (``missing_reference_subsets``, a
    0-d tensor a block reads with its other facts), ``keep_reference_subsets`` reads nothing
    of its own (the missing pixels from their marks, ascending) and keeps what the counting
    path keeps, the same rows in the same order."""
    cfg = sts.DICConfig(m=0, subset_size=15)
    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(cfg)
    other = SubsetSolver(cfg)
    other.reference_cache = ReferenceCache(256.0)
    moved = torch.cat([pts[5:20], pts[12:20], pts[:3]])  # kept, new, repeated
    for s in (solver, other):
        assert s.keep_reference_subsets(ref_img, pts[:10]) is not None
    count = solver.reference_cache.count
    n_miss = solver.missing_reference_subsets(ref_img, moved)
    assert n_miss.dim() == 0 and int(n_miss) == 10  # pts[10:20]
    reads = _Dispatched(READS)
    with reads:
        assert solver.keep_reference_subsets(ref_img, moved, missing=int(n_miss)) is not None
    # no unique, no index (the C++ sampler's argument checks read scalars on the CPU only)
    assert not [r for r in reads.seen if r != "_local_scalar_dense"], reads.seen
    assert other.keep_reference_subsets(ref_img, moved) is not None  # the counting path
    a, b = solver.reference_cache, other.reference_cache
    assert a.count == b.count == count + 10
    assert torch.equal(a.slot, b.slot)
    for k in ("ft", "gx", "gy", "gram", "fnorm", "texture"):
        assert torch.equal(a.rows[k], b.rows[k]), k
    assert int(solver.missing_reference_subsets(ref_img, moved)) == 0  # all kept now
    assert solver.keep_reference_subsets(ref_img, moved, missing=0) is not None
    assert a.count == count + 10


def test_the_cache_keeps_up_to_a_capacity_of_new_subsets_unread_and_drops_the_padding():
    """With a ``capacity`` instead of the count (a block that places its subsets unread),
    ``keep_reference_subsets`` reads nothing of its own, keeps the first misses as the
    counting path does (the same rows, slots and numbers) and pads to the capacity under
    the spare key (no pixel's); ``drop_padding`` with the count read later takes the
    padding back. Too small a capacity keeps the first misses only (the rest not kept:
    the caller's count tells)."""
    cfg = sts.DICConfig(m=0, subset_size=15)
    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(cfg)
    other = SubsetSolver(cfg)
    other.reference_cache = ReferenceCache(256.0)
    moved = torch.cat([pts[5:20], pts[12:20], pts[:3]])  # kept, new (10), repeated
    for s in (solver, other):
        assert s.keep_reference_subsets(ref_img, pts[:10]) is not None
    count = solver.reference_cache.count
    reads = _Dispatched(READS)
    with reads:
        assert solver.keep_reference_subsets(ref_img, moved, capacity=16) is not None
    assert not [r for r in reads.seen if r != "_local_scalar_dense"], reads.seen
    assert other.keep_reference_subsets(ref_img, moved) is not None  # the counting path
    a, b = solver.reference_cache, other.reference_cache
    assert a.count == count + 16 and b.count == count + 10  # padded, then dropped
    a.drop_padding(10)
    assert a.count == count + 10
    spare = a.pixels
    assert a.slot.numel() == spare + 1 and int(a.slot[spare]) >= count + 10  # the padding's
    assert torch.equal(a.slot[:spare], b.slot[:spare])
    for k in ("ft", "gx", "gy", "gram", "fnorm", "texture"):
        assert torch.equal(a.rows[k], b.rows[k]), k
    a.drop_padding(3)  # (once only: nothing padded since)
    assert a.count == count + 10
    # too small: the first misses (ascending pixels) kept, the others still missing
    small = SubsetSolver(cfg)
    small.reference_cache = ReferenceCache(256.0)
    small.keep_reference_subsets(ref_img, pts[:10])
    small.keep_reference_subsets(ref_img, moved, capacity=4)
    assert int(small.missing_reference_subsets(ref_img, moved)) == 6
    small.reference_cache.drop_padding(10)  # (a count over the capacity: all 4 kept)
    assert small.reference_cache.count == count + 4


@pytest.mark.parametrize("window", ["square", "circular"])
def test_subsets_known_inside_are_gathered_without_reading_the_points(window):
    """``sample_subsets(inside=True)`` (whole pixels inside the image, known to the caller)
    gives the same subsets as the tested path, and once the image has seen the offsets it
    reads nothing of the points or offsets (the offsets' facts kept with them)."""
    from torch_stsdic.core.formulations import Geometry

    cfg = sts.DICConfig(m=0, subset_size=15, window=window)
    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(cfg)
    geo = Geometry.make(solver.shape, solver.window, "znssd", torch.float32, "cpu")
    ref_img._pixel_grid()  # the per-pixel images (a run's POIs made them)
    px, py = pts[:, :1], pts[:, 1:]
    want = ref_img.sample_subsets(px, py, geo.dx, geo.dy)
    first = ref_img.sample_subsets(px, py, geo.dx, geo.dy, inside=True)
    for a, b in zip(want, first):
        assert torch.equal(a, b)
    ops = _Dispatched()
    with ops:
        again = ref_img.sample_subsets(px[:7], py[:7], geo.dx, geo.dy, inside=True)
    # no facts of the points or offsets (their max and min); the C++ gather's own argument
    # check reads a flag on the CPU only
    assert not {"max", "min", "abs"} & set(ops.seen), sorted(set(ops.seen))
    for a, b in zip(want, again):
        assert torch.equal(a[:7], b)


def test_points_off_the_reference_image_are_kept_without_an_error():
    """A reference update moves the POIs with the specimen (``pts0 + u``): points that left
    the image are off the new reference. Keeping their subsets indexed the cache with a
    negative pixel key (an IndexError that stopped ``--reference-update`` runs on the
    hourglass); they now take their border pixel's key, and the points inside solve as they
    do without the others."""
    cfg = sts.DICConfig(m=0, subset_size=15)
    solver, ref, ref_img, frames_img, pts, times = _solver_and_images(cfg)
    h, w = ref_img.height, ref_img.width
    off = torch.tensor([[-40.0, 10.0], [w + 30.0, 20.0], [15.0, -25.0], [20.0, h + 9.0],
                        [-3.0, -3.0]], dtype=pts.dtype)
    token = solver.keep_reference_subsets(ref_img, torch.cat([off, pts]))
    assert token is not None
    init = torch.tensor([0.4, 0.0, 0.0, -0.3, 0.0, 0.0]).expand(pts.shape[0], -1)
    kept = solver.solve(ref_img, frames_img, pts, torch.zeros(1), frame_index=torch.tensor([2]),
                        init=init, on_grid=True, kept=token)
    own, _, own_ref, own_frames, _, _ = _solver_and_images(cfg)
    plain = own.solve(own_ref, own_frames, pts, torch.zeros(1), frame_index=torch.tensor([2]),
                      init=init, on_grid=True)
    assert torch.equal(kept.params, plain.params) and torch.equal(kept.status, plain.status)


def _above_neighbours_by_frame(s, noise, frames, z, ratio, reach):
    """The frame-by-frame form the shared motion's jump test had: the reference answer."""
    adjacent = (frames[1:] - frames[:-1]) == 1
    out = []
    for j in range(s.shape[0]):
        if not bool(adjacent[j]) or not bool(torch.isfinite(s[j])):
            continue
        near = [i for i in range(max(0, j - reach), min(s.shape[0], j + reach + 1)) if i != j]
        base = torch.nanmedian(s[near]) if near else torch.tensor(float("nan"))
        if not bool(torch.isfinite(base)):
            continue
        if float(s[j]) > z * float(noise[j]) and float(s[j]) > ratio * float(base):
            out.append(int(frames[j + 1]))
    return out


def test_the_jump_tests_take_every_frame_at_once_with_one_read():
    """The shared-motion pass's jump tests (``_above_neighbours``: a step's increment against
    the median of those within reach; ``_predicted_increments``: each increment as the ones
    about it predict it) give the frame-by-frame answers (random increments with NaN,
    gaps in the frames, float32 and float64, reach 0 to 6) with one host read, and the
    shared fit's median with none."""
    from torch_stsdic.core import shared_fit
    from torch_stsdic.core.shared_motion import _above_neighbours, _predicted_increments

    g = torch.Generator().manual_seed(7)
    found = 0
    for trial in range(60):
        n = int(torch.randint(1, 40, (1,), generator=g))
        dtype = torch.float32 if trial % 2 else torch.float64
        s = torch.rand(n, generator=g, dtype=torch.float64).to(dtype)
        s[torch.rand(n, generator=g) < 0.15] = torch.nan
        s[torch.rand(n, generator=g) < 0.1] *= 40.0  # jumps
        noise = torch.rand(n, generator=g, dtype=torch.float64) * 0.5
        frames = torch.cumsum(1 + (torch.rand(n + 1, generator=g) < 0.1).long(), 0) + 3
        reach, z, ratio = trial % 7, 2.0 + trial % 3, 3.0
        reads = _Dispatched(("_local_scalar_dense", "is_nonzero", "nonzero", "equal"))
        with reads:
            got = _above_neighbours(s, noise, frames, z, ratio, reach)
        want = _above_neighbours_by_frame(s, noise, frames, z, ratio, reach)
        assert got == want, (trial, got, want)
        assert len(reads.seen) <= 1, reads.seen
        found += len(want)
    assert found > 10  # the cases found jumps, not only none
    for f1 in (5, 6, 9, 30):
        inc = torch.randn(f1, 4, 2, generator=g, dtype=torch.float64)
        line = torch.tensor([4.0, 1.0, -2.0], dtype=torch.float64)[:, None, None] / 3.0
        want = torch.empty_like(inc)
        for j in range(f1):
            if 2 <= j <= f1 - 3:
                want[j] = inc[[j - 2, j - 1, j + 1, j + 2]].median(0).values
            elif j < 2:
                want[j] = (line * inc[j + 1:j + 4]).sum(0)
            else:
                want[j] = (line * inc[[j - 1, j - 2, j - 3]]).sum(0)
        assert torch.equal(_predicted_increments(inc), want)
    v = torch.rand(300, 7, generator=g, dtype=torch.float64)
    v[v < 0.2] = torch.nan
    reads = _Dispatched(("_local_scalar_dense", "is_nonzero", "nonzero", "equal"))
    with reads:
        med = shared_fit._lower_median(v)
    assert not reads.seen
    assert torch.equal(med, torch.nanmedian(v))


def test_moved_subsets_keep_the_points_dtype_and_the_kept_subsets():
    """A placement's moved centres are whole pixels in the points' dtype whatever the
    guess's (a neighbour rescue's guesses are float64): float64 centres made the block's
    later solves run in float64 without the reference cache's subsets (a read a batch)."""
    from types import SimpleNamespace

    from torch_stsdic.movie.block_placement import BlockPlacement

    pts = torch.tensor([[20.0, 30.0], [40.0, 50.0], [60.0, 10.0]])  # float32, a run's
    fake = SimpleNamespace(
        pts=pts, centres=None, kept=None,
        run=SimpleNamespace(solver=SimpleNamespace(window=SimpleNamespace(half=5))),
        ref=SimpleNamespace(img=SimpleNamespace(height=80, width=80)))
    shift = torch.tensor([[2.3, 0.0], [0.0, 0.0], [0.0, -1.2]], dtype=torch.float64)
    facts, (moved, centres, off) = BlockPlacement._centre_facts(
        fake, shift, torch.zeros(3, dtype=torch.bool))
    assert centres.dtype == pts.dtype
    assert torch.equal(centres, torch.tensor([[23.0, 30.0], [40.0, 50.0], [60.0, 8.0]]))
    assert moved.tolist() == [True, False, True] and off.tolist() == [True, False, True]
    assert [int(f) for f in facts] == [2, 1, 2]


def test_a_gpus_fft_search_gathers_its_regions_without_a_read(monkeypatch):
    """FFT cross-correlation's search regions, some over the image's border: gathered as a
    GPU gathers them (``choices.SEARCH_READS`` False: index arithmetic, no host read of
    whether every region lies inside) they give the CPU's displacements and ZNCC to the bit,
    and the search reads nothing where the CPU's way reads twice a batch."""
    from torch_stsdic.core import choices, initial

    ref, frames, pts, _ = _window()
    pts = torch.cat([pts, torch.tensor([[3.0, 40.0], [N - 4.0, 50.0]], dtype=torch.float64)])
    runs = {}
    for by_view in (True, False):
        monkeypatch.setattr(choices, "SEARCH_READS", by_view)
        reads = _Dispatched(("_local_scalar_dense", "is_nonzero"))
        with reads:
            runs[by_view] = initial.fft_cross_correlation(ref, frames, pts, 15, 6)
        runs[by_view] += (len(reads.seen),)
    assert runs[True][2] >= 2 and runs[False][2] == 0
    assert torch.equal(runs[True][0], runs[False][0])
    assert torch.equal(runs[True][1], runs[False][1])


def test_a_gpus_walk_over_weak_frames_searches_every_row_with_the_same_answers(monkeypatch):
    """A window whose motion outruns the search radius: its later frames' first peaks are
    weak, and the walk searches them again around the motion carried along the window. As
    a GPU walks (``choices.SEARCH_READS`` False: every row searched at every frame, the
    answers of the rows not weak dropped) it gives the CPU's displacements and ZNCC to the
    bit, with no host read; and the walk does find the motion there."""
    from torch_stsdic.core import choices, initial

    pattern = synth.make_speckle((N, N), seed=8)
    times = torch.arange(0.0, 5.0, dtype=torch.float64)
    ref, frames = synth.render_series(pattern, (N, N), synth.Translation(0.0, 0.0, ut=2.6,
                                                                        vt=-1.1),
                                      times, noise_sigma=1.0, seed=4, reference_time=None)
    c = torch.arange(26.0, N - 26.0, 6.0, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    pts = torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)
    n, t = pts.shape[0], frames.shape[0]
    fidx = torch.arange(t).expand(n, t)
    ridx = torch.zeros(n, dtype=torch.long)
    dt = times.expand(n, t)
    d0, s0 = initial.fft_cross_correlation(ref, frames, pts, 15, 4)
    assert (s0[:, -1] < 0.8).float().mean() > 0.5  # 10.4 px out of a 4 px search
    runs = {}
    for reads in (True, False):
        monkeypatch.setattr(choices, "SEARCH_READS", reads)
        seen = _Dispatched(("_local_scalar_dense", "is_nonzero", "nonzero"))
        with seen:
            d, s = initial.walk_weak_frames(d0, s0, dt, ref[None], frames, pts, fidx, ridx,
                                            15, 4)
        runs[reads] = (d, s, len(seen.seen))
    assert runs[True][2] > 0 and runs[False][2] == 0
    assert torch.equal(runs[True][0], runs[False][0])
    assert torch.equal(runs[True][1], runs[False][1])
    d = runs[False][0]
    assert (runs[False][1][:, -1] >= 0.8).float().mean() > 0.9
    # (FFT peaks refined by a parabola: within half a pixel of the motion, not a wrong peak,
    # at nearly every point)
    err = (d[:, -1] - torch.tensor([10.4, -4.4], dtype=d.dtype)).abs().amax(1)
    assert (err < 0.5).float().mean() > 0.9


def test_a_gpus_first_guesses_search_every_row_with_the_same_answers(monkeypatch):
    """A solve without starting parameters takes its first guesses by FFT search at the rows
    whose subsets are inside the image (the CPU reads which, and takes them by index); as a
    GPU does it (``choices.SEARCH_READS`` False) every row is searched and the others'
    answers dropped: the same solutions to the bit, points over the border included."""
    from torch_stsdic.core import choices
    from torch_stsdic.core import solver as solver_mod

    ref, frames, pts, times = _window()
    pts = torch.cat([pts, torch.tensor([[2.0, 40.0], [N - 3.0, 50.0], [40.0, 1.0]],
                                       dtype=torch.float64)])
    cfg = sts.DICConfig(m=2, subset_size=15, initial_guess="fft")  # (not from seeds)
    searched, runs = [], {}
    guess = solver_mod.SubsetSolver.initial_guess

    def counted(self, shape, ref_pixels, frame_pixels, points, *a, **kw):
        searched.append(points.shape[0])
        return guess(self, shape, ref_pixels, frame_pixels, points, *a, **kw)

    monkeypatch.setattr(solver_mod.SubsetSolver, "initial_guess", counted)
    for reads in (True, False):
        monkeypatch.setattr(choices, "SEARCH_READS", reads)
        runs[reads] = sts.solve_window(ref, frames, pts, config=cfg, times=times)
    assert searched[0] == pts.shape[0] - 3 and searched[-1] == pts.shape[0]
    for name in ("params", "status", "zncc"):
        a, b = getattr(runs[True], name), getattr(runs[False], name)
        assert torch.equal(torch.nan_to_num(a), torch.nan_to_num(b)), name
