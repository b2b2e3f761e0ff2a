"""Frames of a movie held while they are in use: raw pixels and B-spline coefficients.

A sliding window reads every frame 2m+1 times; :class:`FrameCache` reads and prefilters each
frame once while consecutive blocks of windows overlap, and drops it after, so memory is
bounded by the block, not by the movie length.

Read-ahead: given the frames a run will need in order (:meth:`FrameCache.schedule`, from
:func:`frames_in_order`), a background thread (:class:`_Reader`) decodes the next frames,
moves them to the device and prefilters them there while the current block is solved, at
most ``ahead`` frames in advance (a bounded queue). On CUDA the decoded frame goes through
pinned memory with a non-blocking copy on a side stream, the prefilter runs on that stream,
and the consumer's stream waits on an event (no host synchronisation). A frame asked for
out of order (a reference frame, a resumed run) is read on the spot, as without read-ahead.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable, Sequence

import torch

from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.io import ImageSeries

__all__ = ["FrameCache", "window_frames", "segment_bounds", "frames_in_order",
           "default_ahead"]


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


class _Reader(threading.Thread):
    """Decodes, uploads and prefilters the frames ``order`` in turn into a bounded queue.

    The consumer's side (:meth:`take`, :meth:`close`, on the calling thread) uses only a
    ``queue.SimpleQueue`` (C) and plain attributes: a Ctrl-C there cannot leave a lock taken
    for good (``queue.Queue`` and ``threading.Event`` take theirs in Python code)."""

    _DONE = object()

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
                t0 = time.perf_counter()
                cpu = c.series.get(i, dtype=c.dtype)
                t1 = time.perf_counter()
                ev = None
                if self.stream is not None:
                    with torch.cuda.device(self.stream.device), torch.cuda.stream(self.stream):
                        raw = cpu.pin_memory().to(c.device, non_blocking=True)
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
        """(raw, prepared) of frame ``i``, or None if it is not (any more) ahead in the queue."""
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
                if ev is not None:  # the consumer's stream waits for the upload/prefilter
                    cur = torch.cuda.current_stream(raw.device)
                    cur.wait_event(ev)
                    raw.record_stream(cur)
                    prep.coeffs.record_stream(cur)
                return raw, prep

    def close(self) -> None:
        self.stopped = True  # a put in progress gives up within 2 ms
        while True:
            try:
                self.q.get_nowait()
            except queue.Empty:
                break
        self.join(timeout=5.0)


class FrameCache:
    """Frames of the current block: raw pixels and prefiltered coefficients, by index.

    ``load`` keeps exactly the frames asked for (older ones are dropped), so a frame is read
    and prefiltered once while consecutive blocks overlap. After :meth:`schedule` a background
    thread reads ahead (see the module docstring); :meth:`close` stops it.

    :meth:`times` reports seconds spent on frames (see there)."""

    def __init__(self, series: ImageSeries, solver: SubsetSolver, dtype, device,
                 ahead: int = 0) -> None:
        self.series, self.solver = series, solver
        self.dtype, self.device = dtype, device
        self.ahead = int(ahead)
        self.raw: OrderedDict[int, torch.Tensor] = OrderedDict()
        self.prep: dict[int, BSplineImage] = {}
        self.reads = 0
        self.prefiltered = 0
        self.max_cached = 0
        self._t = {"read_s": 0.0, "prefilter_s": 0.0, "wait_s": 0.0}
        self._reader: _Reader | None = None
        self._ahead_s = [0.0, 0.0]  # read, prefilter time of finished readers

    def times(self) -> dict[str, float]:
        """Seconds spent on frames: ``read_s`` / ``prefilter_s`` in the calling thread
        (decoding + copy to the device / B-spline prefilter; on CUDA the kernel launches),
        ``ahead_read_s`` / ``ahead_prefilter_s`` the same in the read-ahead thread (overlapped
        with the solve), and ``wait_s``: the time :meth:`load` spent getting frames (reading
        them itself or waiting for the reader), i.e. what frames cost the calling thread."""
        r = self._reader
        ahead = [self._ahead_s[0] + (r.read_s if r else 0.0),
                 self._ahead_s[1] + (r.prefilter_s if r else 0.0)]
        return {**self._t, "ahead_read_s": ahead[0], "ahead_prefilter_s": ahead[1]}

    def schedule(self, order: list[int]) -> None:
        """Read the frames ``order`` ahead in the background, in this order (no-op when
        ``ahead`` is 0 or nothing is to be read)."""
        self.close()
        order = [i for i in order if i not in self.raw]  # held already (the reference)
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

    def put(self, i: int, raw: torch.Tensor, prep: BSplineImage) -> None:
        """Hold frame ``i`` already read and prepared (the reference frame): a block that
        needs it takes it from here, and :meth:`schedule` does not read it again."""
        self.raw[i], self.prep[i] = raw, prep
        self.prefiltered += 1

    def read(self, i: int) -> torch.Tensor:
        """(H, W) frame ``i`` from the cache or the series (counted)."""
        if i in self.raw:
            return self.raw[i]
        self.reads += 1
        t0 = time.perf_counter()
        out = self.series.get(i, dtype=self.dtype).to(self.device)
        self._t["read_s"] += time.perf_counter() - t0
        return out

    def _fetch(self, i: int) -> tuple[torch.Tensor, BSplineImage]:
        got = self._reader.take(i) if self._reader is not None else None
        if got is not None:
            self.reads += 1
            return got
        raw = self.read(i)
        t0 = time.perf_counter()
        prep = self.solver.prepare(raw)
        self._t["prefilter_s"] += time.perf_counter() - t0
        return raw, prep

    def load(self, idx: list[int]) -> tuple[torch.Tensor, BSplineImage]:
        """Frames ``idx``: raw (L, H, W) and a prepared L-frame stack."""
        keep = set(idx)
        for k in [k for k in self.raw if k not in keep]:
            del self.raw[k]
            del self.prep[k]
        t0 = time.perf_counter()
        for i in idx:
            if i not in self.raw:
                self.raw[i], self.prep[i] = self._fetch(i)
                self.prefiltered += 1
        self._t["wait_s"] += time.perf_counter() - t0
        self.max_cached = max(self.max_cached, len(self.raw))
        raw = torch.stack([self.raw[i] for i in idx])
        return raw, BSplineImage.stack([self.prep[i] for i in idx])
