"""Frames of a movie held while they are in use: raw pixels and B-spline coefficients.

A sliding window reads every frame 2m+1 times; :class:`FrameCache` reads and prefilters each
frame once while consecutive blocks of windows overlap, and drops it after, so memory is
bounded by the block, not by the movie length. The passes of one run (the shared-motion pass,
the template's rounds, the time-model pass, the blocks) read the same frames again: a
:class:`FrameStore` shared by their caches keeps each prepared frame (pixels, B-spline
coefficients, Gaussian pyramid) within a memory budget, so that a frame is prepared once per
run while it stays in the budget.

Read-ahead: given the frames a run will need in order (:meth:`FrameCache.schedule`, from
:func:`frames_in_order`), a background thread (:class:`_Reader`) decodes the next frames,
moves them to the device and prefilters them there while the current block is solved, at
most ``ahead`` frames in advance (a bounded queue). On CUDA the decoded frame goes through
pinned memory with a non-blocking copy on a side stream, the prefilter runs on that stream,
and the consumer's stream waits on an event (no host synchronisation). A frame the store
holds when the reader reaches it is queued as it is (not read again; held by the queue). A
frame asked for out of order (a reference frame, a resumed run) is read on the spot, as
without read-ahead.
"""

from __future__ import annotations

import contextlib
import functools
import os
import queue
import threading
import time
import warnings
from collections import Counter, OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import torch

from torch_stsdic.core.choices import masked_groups
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.pyramid import ImagePyramid
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.io import ImageSeries
from torch_stsdic.movie.frame_ring import FrameRing, RingView

__all__ = ["FrameCache", "FrameStore", "PreparedFrame", "window_frames", "block_frames", "upload",
           "segment_bounds", "frames_in_order", "default_ahead", "half_widths",
           "window_half_widths", "rows_by_half_width", "grouped_rows", "true_rows"]


def upload(t: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """``t`` (on the host) on ``device`` without waiting for it: to a GPU from pinned memory,
    not blocking (a copy from pageable memory waits for the device's queue first); as it is
    elsewhere."""
    device = torch.device(device)
    if device.type == "cuda" and t.device.type == "cpu":
        return t.pin_memory().to(device, non_blocking=True)
    return t.to(device)


def window_frames(ks: torch.Tensor, m: int, n_series: int,
                  segments: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 2m+1) series frames of the windows of target frames ``ks`` (B,): ``k-m .. k+m``,
    shifted (not shrunk) at the ends of the series. With ``segments`` (T_series, 2), the first
    and last frame of each frame's load segment (:func:`segment_bounds`), a window is shifted
    to stay inside its target's segment where the segment holds 2m+1 frames (a window never
    spans a load step it can avoid)."""
    n_win = 2 * m + 1
    start = (ks - m).clamp(0, n_series - n_win)
    if segments is not None and m > 0:
        lo, hi = segments[ks, 0].to(ks), segments[ks, 1].to(ks)
        fits = hi - lo + 1 >= n_win
        inside = torch.minimum(torch.maximum(ks - m, lo), hi - 2 * m)
        start = torch.where(fits, inside, start)
    return start.unsqueeze(1) + torch.arange(n_win, device=ks.device)


def block_frames(ks: torch.Tensor, m: int, n_series: int,
                 segments: torch.Tensor | None = None) -> list[int]:
    """Sorted series frames (host numbers: ``ks`` and ``segments`` on the host) of the
    windows of targets ``ks`` for every half-width 0 .. ``m``
    (:func:`window_frames`): what a block whose rows may be solved with shorter windows
    needs. Inside a load segment too short for the longest window, a shorter one is shifted
    to stay in the segment and can reach frames the longest does not (a segment of 12
    frames, a target at its end: m = 4 starts 8 frames before it, m = 6 6 before)."""
    return torch.unique(torch.cat([window_frames(ks, h, n_series, segments).reshape(-1)
                                   for h in range(int(m) + 1)])).tolist()


def segment_bounds(steps: Sequence[int], n_series: int) -> torch.Tensor:
    """(T_series, 2) long: the first and last series frame of every frame's segment, the
    segments starting at frame 0 and at every frame of ``steps`` (frames that begin a new
    load state)."""
    starts = sorted({0, *(int(s) for s in steps if 0 < int(s) < n_series)})
    ends = [s - 1 for s in starts[1:]] + [n_series - 1]
    out = torch.empty(n_series, 2, dtype=torch.long)
    for a, b in zip(starts, ends):
        out[a : b + 1, 0], out[a : b + 1, 1] = a, b
    return out


def frames_in_order(blocks: Iterable[Sequence[int]], m: int, n_series: int,
                    segments: torch.Tensor | None = None) -> list[int]:
    """Every frame the windows of ``blocks`` (lists of target frames) use, once, in the order
    of first use."""
    seen: dict[int, None] = {}
    for block in blocks:
        win = window_frames(torch.tensor(list(block)), m, n_series, segments)
        for i in torch.unique(win).tolist():
            seen.setdefault(i, None)
    return list(seen)


def default_ahead(batch_frames: int, m: int) -> int:
    """Frames read ahead by default: one block's new frames plus a window (``batch_frames +
    2m``), at least 4. The environment variable ``TORCH_STSDIC_READ_AHEAD`` sets another
    count (``0``: no read-ahead, every frame is read when a block needs it)."""
    env = os.environ.get("TORCH_STSDIC_READ_AHEAD", "").strip()
    if env:
        return max(0, int(env))
    return max(4, int(batch_frames) + 2 * int(m))


@dataclass
class PreparedFrame:
    """Frame ``index`` as the solver reads it: pixels (H, W), B-spline coefficients, and its
    Gaussian pyramid (built on first use, :meth:`pyramid`; each ``pyrdown`` counted in
    ``builds``, per frame index, where given)."""

    index: int
    raw: torch.Tensor
    prep: BSplineImage
    builds: Counter[int] | None = field(default=None, repr=False)
    _pyramid: ImagePyramid | None = field(default=None, repr=False)

    def pyramid(self) -> ImagePyramid:
        if self._pyramid is None:
            # the counter's update bound to the index, not a closure over ``self``: a
            # frame -> pyramid -> closure -> frame cycle would outlive the frame until
            # Python's cyclic collector ran (~3.6 MB a block of 256 x 256 frames, freed
            # at a full collection: ever rarer in a long run, so its peak grew with it)
            count = self.builds
            self._pyramid = ImagePyramid(self.raw, on_build=None if count is None else
                                         functools.partial(count.update, (self.index,)))
        return self._pyramid

    @property
    def nbytes(self) -> int:
        """Bytes held: pixels, coefficients and (counted in advance) a pyramid's levels."""
        px = self.raw.numel() * self.raw.element_size()
        return px + self.prep.coeffs.numel() * self.prep.coeffs.element_size() + px // 3


class FrameStore:
    """The prepared frames of one run, shared by the frame caches of all its passes (see the
    module docstring), least recently used dropped first beyond ``budget_mb`` MiB or beyond
    ``max_frames`` frames (0: none kept beyond a cache's own block; a count, not only bytes,
    so that a long movie of small frames holds no more than a short one). Thread-safe.

    While :meth:`keeping` is open, the frames it names are kept besides, up to ``keep_mb``
    MiB of them (counted in the budget where that is larger): the few frames that several of
    a run's passes read (the template's sample) are prepared once even where the store keeps
    nothing else (a long movie).

    ``reads``, ``prefiltered`` and ``pyramid_builds`` count per frame index how often it was
    read from the series and prepared in the run (B-spline prefilters, ``pyrdown`` calls: one
    per pyramid level), ``times`` the
    seconds of the caches that finished (:meth:`FrameCache.times`, added up)."""

    def __init__(self, budget_mb: float, max_frames: int | None = None,
                 keep_mb: float = 0.0) -> None:
        self.budget = int(max(0.0, float(budget_mb)) * 2**20)
        self.max_frames = max_frames
        self.keep_budget = int(max(0.0, float(keep_mb)) * 2**20)
        self._frames: OrderedDict[tuple, PreparedFrame] = OrderedDict()
        #: the frames each open :meth:`keeping` keeps (frame indices) and those kept
        self._keep: list[frozenset[int]] = []
        self._kept: dict[tuple, PreparedFrame] = {}
        self._lock = threading.Lock()
        self.reads: Counter[int] = Counter()
        self.prefiltered: Counter[int] = Counter()
        self.pyramid_builds: Counter[int] = Counter()
        self.times: Counter[str] = Counter()

    def get(self, key: tuple) -> PreparedFrame | None:
        with self._lock:
            got = self._kept.get(key)
            if got is not None:
                return got
            got = self._frames.get(key)
            if got is not None:
                self._frames.move_to_end(key)
            return got

    def put(self, key: tuple, frame: PreparedFrame) -> None:
        with self._lock:
            kept = sum(f.nbytes for f in self._kept.values())
            if (any(key[0] in k for k in self._keep) and key not in self._kept
                    and kept + frame.nbytes <= self.keep_budget):
                self._frames.pop(key, None)
                self._kept[key] = frame
                kept += frame.nbytes
            else:
                self._frames[key] = frame
                self._frames.move_to_end(key)
            held = kept + sum(f.nbytes for f in self._frames.values())
            most = len(self._frames) if self.max_frames is None else self.max_frames
            while (held > max(self.budget, kept) or len(self._frames) > most) and self._frames:
                _, old = self._frames.popitem(last=False)
                held -= old.nbytes

    @contextlib.contextmanager
    def keeping(self, frames: Iterable[int]) -> Iterator[None]:
        """Within the block, the prepared frames of the indices ``frames`` put here are kept
        (the first put first, up to ``keep_mb`` MiB of them; the least recently used of the
        others dropped first, as ever); after it they are the others' like (a store that keeps
        none drops them at once), but where an enclosing block keeps them too."""
        mine = frozenset(int(i) for i in frames)
        with self._lock:
            self._keep.append(mine)
        try:
            yield
        finally:
            with self._lock:
                self._keep.remove(mine)
                still = frozenset().union(*self._keep)
                left = {k: f for k, f in self._kept.items() if k[0] not in still}
                for key in left:
                    del self._kept[key]
            for key, frame in left.items():
                self.put(key, frame)

    def __contains__(self, key: tuple) -> bool:
        with self._lock:
            return key in self._kept or key in self._frames


class _Reader(threading.Thread):
    """Decodes, uploads and prefilters the frames ``order`` in turn into a bounded queue.

    The consumer's side (:meth:`take`, :meth:`close`, on the calling thread) uses only a
    ``queue.SimpleQueue`` (C) and plain attributes: a Ctrl-C there cannot leave a lock taken
    for good (``queue.Queue`` and ``threading.Event`` take theirs in Python code)."""

    _DONE = object()
    #: s a :meth:`close` waits at a time for the frame under way (then again, until it ends)
    JOIN_SLICE_S = 0.5
    #: s after which :meth:`close` warns that it still waits
    CLOSE_WARN_S = 60.0

    def __init__(self, cache: FrameCache, order: list[int], ahead: int) -> None:
        super().__init__(name="stsdic-frames", daemon=True)
        self.cache, self.order = cache, order
        self.pos = {i: p for p, i in enumerate(order)}
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.ahead = max(1, ahead)
        self.queued = 0  # producer: items put
        self.taken = 0  # consumer: items taken
        self.stopped = False
        self.next_pos = 0  # consumer: position in ``order`` of the next item in the queue
        self.read_s = self.prefilter_s = 0.0  # this thread's own time
        dev = torch.device(cache.device)
        self.stream = torch.cuda.Stream(device=dev) if dev.type == "cuda" else None

    def run(self) -> None:
        c = self.cache
        try:
            for p, i in enumerate(self.order):
                if self.stopped:
                    return
                held = c.store.get(c._key(i))
                if held is not None:  # prepared by a pass before: handed over as it is
                    # (held from here on: the store may drop it before the block needs it)
                    self._put((p, i, held, None, None))
                    continue
                t0 = time.perf_counter()
                cpu = c.series.get(i, dtype=c.dtype)
                t1 = time.perf_counter()
                ev = None
                if self.stream is not None:
                    with torch.cuda.device(self.stream.device), torch.cuda.stream(self.stream):
                        raw = upload(cpu, c.device)
                        prep = c.solver.prepare(raw)
                        ev = torch.cuda.Event()
                        ev.record(self.stream)
                else:
                    raw = cpu.to(c.device)
                    prep = c.solver.prepare(raw)
                t2 = time.perf_counter()
                self.read_s += t1 - t0
                self.prefilter_s += t2 - t1
                self._put((p, i, raw, prep, ev))
        except BaseException as exc:  # handed to the consumer, raised there
            self._put(exc)
        finally:
            self._put(self._DONE)

    def _put(self, item) -> None:
        """Into the queue once it holds fewer than ``ahead`` items (or never, once stopped)."""
        while not self.stopped:
            if self.queued - self.taken < self.ahead:
                self.q.put(item)
                self.queued += 1
                return
            time.sleep(0.002)

    def take(self, i: int):
        """(raw, prepared) of frame ``i`` read here, or the :class:`PreparedFrame` the store
        held when the reader reached it; None if it is not (any more) ahead in the queue."""
        p = self.pos.get(i)
        if p is None or p < self.next_pos:
            return None
        while True:
            item = self.q.get()
            if item is self._DONE:
                self.next_pos = len(self.order)
                self.q.put(item)  # stays done
                return None
            self.taken += 1
            if isinstance(item, BaseException):
                raise item
            pos, _, raw, prep, ev = item
            self.next_pos = pos + 1
            if pos == p:
                if isinstance(raw, PreparedFrame):  # (the store's)
                    return raw
                if ev is not None:  # the consumer's stream waits for the upload/prefilter
                    cur = torch.cuda.current_stream(raw.device)
                    cur.wait_event(ev)
                    raw.record_stream(cur)
                    prep.coeffs.record_stream(cur)
                return raw, prep

    def close(self) -> None:
        """Stop: the queue emptied and the frame under way finished (its decoding and
        prefilter, seconds at most on a loaded CPU; waited for in slices of
        :attr:`JOIN_SLICE_S`, a Ctrl-C still heard, warned about after :attr:`CLOSE_WARN_S`).
        A daemon thread still inside a torch op at the interpreter's shutdown aborts the
        process after the run's results are written ("terminate called without an active
        exception", exit 134)."""
        self.stopped = True  # a put in progress gives up within 2 ms
        while True:
            try:
                self.q.get_nowait()
            except queue.Empty:
                break
        t0 = time.perf_counter()
        warned = False
        while self.is_alive():
            self.join(timeout=self.JOIN_SLICE_S)
            if not warned and time.perf_counter() - t0 > self.CLOSE_WARN_S:
                warned = True
                warnings.warn(f"the frame reader is still reading frame(s) of "
                              f"{self.cache.series!r} after {self.CLOSE_WARN_S:.0f} s; "
                              "waiting for it", RuntimeWarning, stacklevel=2)


class FrameCache:
    """Frames of the current block: raw pixels, prefiltered coefficients and pyramids, by
    index.

    ``in_ring`` keeps exactly the frames asked for (older ones are dropped), so a frame is read
    and prefiltered once while consecutive blocks overlap. After :meth:`schedule` a background
    thread reads ahead (see the module docstring); :meth:`close` stops it. With a ``store``
    (:class:`FrameStore`, shared by the caches of one run's passes) a frame another pass
    prepared is taken from there, and every frame prepared here is put there.

    :meth:`times` reports seconds spent on frames (see there)."""

    def __init__(self, series: ImageSeries, solver: SubsetSolver, dtype, device,
                 ahead: int = 0, store: FrameStore | None = None) -> None:
        self.series, self.solver = series, solver
        self.dtype, self.device = dtype, device
        self.ahead = int(ahead)
        self.store = store if store is not None else FrameStore(0)
        self.entries: OrderedDict[int, PreparedFrame] = OrderedDict()
        self.reads = 0
        self.prefiltered = 0
        self.max_cached = 0
        self._t = {"read_s": 0.0, "prefilter_s": 0.0, "wait_s": 0.0}
        self._reader: _Reader | None = None
        self._ahead_s = [0.0, 0.0]  # read, prefilter time of finished readers
        self._order = int(solver.config.interpolation_order)
        self._ring = FrameRing()

    def _key(self, i: int) -> tuple:
        return (int(i), str(self.dtype), str(torch.device(self.device)), self._order)

    def times(self) -> dict[str, float]:
        """Seconds spent on frames: ``read_s`` / ``prefilter_s`` in the calling thread
        (decoding + copy to the device / B-spline prefilter; on CUDA the kernel launches),
        ``ahead_read_s`` / ``ahead_prefilter_s`` the same in the read-ahead thread (overlapped
        with the solve), and ``wait_s``: the time :meth:`in_ring` spent getting frames (reading
        them itself or waiting for the reader), i.e. what frames cost the calling thread."""
        r = self._reader
        ahead = [self._ahead_s[0] + (r.read_s if r else 0.0),
                 self._ahead_s[1] + (r.prefilter_s if r else 0.0)]
        return {**self._t, "ahead_read_s": ahead[0], "ahead_prefilter_s": ahead[1]}

    def schedule(self, order: list[int]) -> None:
        """Read the frames ``order`` ahead in the background, in this order (no-op when
        ``ahead`` is 0 or nothing is to be read; frames held here are not read, and a frame
        the store holds when the reader reaches it is handed over as it is: a frame in the
        store now may be dropped from it before a block needs it)."""
        self.close()
        order = [i for i in order if i not in self.entries]
        if self.ahead > 0 and order:
            self._reader = _Reader(self, list(order), self.ahead)
            self._reader.start()

    def close(self) -> None:
        """Stop the read-ahead thread (idempotent)."""
        if self._reader is not None:
            self._reader.close()
            self._ahead_s[0] += self._reader.read_s
            self._ahead_s[1] += self._reader.prefilter_s
            self._reader = None

    def finish(self) -> dict[str, float]:
        """:meth:`close`, and add this cache's :meth:`times` to the store's: returns the
        store's (the run's, over the passes finished so far)."""
        self.close()
        self.store.times.update(self.times())
        return dict(self.store.times)

    def hold(self, i: int) -> PreparedFrame:
        """Frame ``i`` prepared (:meth:`frame`) and held (the reference frame): a block that
        needs it takes it from here, and :meth:`schedule` does not read it again."""
        entry = self.frame(i)
        self.entries[i] = entry
        return entry

    def read(self, i: int) -> torch.Tensor:
        """(H, W) frame ``i`` from the cache, the store or the series (counted)."""
        if i in self.entries:
            return self.entries[i].raw
        got = self.store.get(self._key(i))
        if got is not None:
            return got.raw
        self._count_read(i)
        t0 = time.perf_counter()
        out = self.series.get(i, dtype=self.dtype).to(self.device)
        self._t["read_s"] += time.perf_counter() - t0
        return out

    def frame(self, i: int) -> PreparedFrame:
        """Frame ``i`` prepared (held here, from the store, or read and prepared now), without
        holding it in the block's frames (the reference: :meth:`put`)."""
        return self.entries.get(i) or self._fetch(i)

    def _count_read(self, i: int) -> None:
        self.reads += 1
        self.store.reads.update((int(i),))

    def _prepared(self, i: int, raw: torch.Tensor, prep: BSplineImage) -> PreparedFrame:
        """A frame prepared by this cache: counted, and put in the store."""
        entry = PreparedFrame(int(i), raw, prep, builds=self.store.pyramid_builds)
        self.prefiltered += 1
        self.store.prefiltered.update((int(i),))
        self.store.put(self._key(i), entry)
        return entry

    def _fetch(self, i: int) -> PreparedFrame:
        got = self.store.get(self._key(i))
        if got is not None:
            return got
        ahead = self._reader.take(i) if self._reader is not None else None
        if isinstance(ahead, PreparedFrame):  # the store held it when the reader passed
            return ahead
        if ahead is not None:
            self._count_read(i)
            return self._prepared(i, *ahead)
        raw = self.read(i)
        t0 = time.perf_counter()
        prep = self.solver.prepare(raw)
        self._t["prefilter_s"] += time.perf_counter() - t0
        return self._prepared(i, raw, prep)

    def _hold_only(self, idx: list[int]) -> None:
        """Hold exactly the frames ``idx`` (older ones dropped, new ones fetched)."""
        keep = set(idx)
        for k in [k for k in self.entries if k not in keep]:
            del self.entries[k]
        t0 = time.perf_counter()
        for i in idx:
            if i not in self.entries:
                self.entries[i] = self._fetch(i)
        self._t["wait_s"] += time.perf_counter() - t0
        self.max_cached = max(self.max_cached, len(self.entries))

    def in_ring(self, idx: list[int]) -> RingView:
        """Frames ``idx`` held, in the stack that consecutive blocks share
        (:class:`~torch_stsdic.movie.frame_ring.FrameRing`: only frames new since the last
        call are copied; address them by :attr:`RingView.planes`)."""
        self._hold_only(idx)
        return self._ring.fill(self.entries, idx)


def rows_by_half_width(m_of: torch.Tensor, rows: torch.Tensor, m_max: int
                       ) -> list[tuple[int, torch.Tensor]]:
    """The ``rows`` (R,) bool grouped by their half-width ``m_of`` (R,) (clamped to 0 ..
    ``m_max``): ``(m, (R_m,) long row indices ascending)`` for each half-width they take, in
    increasing order. One host read (a count of each), not an index per half-width: the
    rows sorted by half-width (a stable sort keeps their order), split by the counts."""
    key, counts = _half_width_counts(m_of, rows, m_max)
    return [(m, part) for m, part in enumerate(grouped_rows(key, counts)) if counts[m]]


def grouped_rows(key: torch.Tensor, counts: Sequence[int]) -> list[torch.Tensor]:
    """The rows of each group g = 0 .. G-1 of ``key`` (R,) integer (G or more: in no group),
    as (R_g,) long indices ascending, given every group's size ``counts`` (G,) (read by the
    caller, with whatever else it reads at once): the rows sorted by group (a stable sort
    keeps their order), split by the counts; no host read here."""
    counts = [int(c) for c in counts]
    return list(torch.argsort(key, stable=True)[:sum(counts)].split(counts))


def true_rows(mask: torch.Tensor, count: int) -> torch.Tensor:
    """(count,) long: the rows where ``mask`` (R,) bool is True, ascending, given how many
    there are (read by the caller, with whatever else it reads at once): ``nonzero`` of a
    known size, no host read."""
    return torch.nonzero_static(mask, size=int(count)).flatten()


def _half_width_counts(m_of: torch.Tensor, rows: torch.Tensor, m_max: int
                       ) -> tuple[torch.Tensor, list[int]]:
    """(R,) each row's half-width (``m_max + 1`` where not in ``rows``) and the count of
    each half-width 0 .. ``m_max`` (one host read)."""
    key = torch.where(rows, m_of.long().clamp(0, m_max), m_max + 1)
    return key, torch.bincount(key, minlength=m_max + 2)[:m_max + 1].tolist()


def half_widths(m_of: torch.Tensor, rows: torch.Tensor, m_max: int) -> list[int]:
    """The half-widths 0 .. ``m_max`` that ``m_of`` (R,) takes at the ``rows`` (R,) bool, in
    increasing order: one host read (a count of each), not a ``unique`` and a copy."""
    return [m for m, c in enumerate(_half_width_counts(m_of, rows, m_max)[1]) if c]


def window_half_widths(m_of: torch.Tensor, rows: torch.Tensor, m_max: int) -> Sequence[int]:
    """The half-widths of windows (1 .. ``m_max``) a caller goes through, masking each by
    its rows: those ``m_of`` takes at the ``rows`` (:func:`half_widths`, one host read; 0
    among them where a row is classical), or on a GPU every one, no read
    (:data:`~torch_stsdic.core.choices.MASKED_GROUPS`)."""
    if masked_groups(m_of.device):
        return range(1, m_max + 1)
    return half_widths(m_of, rows, m_max)
