"""A run's solved blocks written into its sink on a thread of their own (:class:`RowWriter`):
the block loop hands a block's rows over where they were solved and goes on with the next
block while the writer copies them to the host (from a GPU: into pinned memory, queued on
the device's stream, no wait in the block loop), subtracts the refined reference's offsets,
rounds them as a result file stores them, writes them and their strains. What the next
block needs of them (its carry) is made on the device from the same rows
(:func:`carried_rows`), so the loop never waits for the host copy."""

from __future__ import annotations

import _thread
import queue
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from torch_stsdic.io.stored import as_stored_tensors
from torch_stsdic.movie.carry import rows_numpy
from torch_stsdic.movie.refine import ReferenceOffsets, apply_offsets, restore_offsets

__all__ = ["RowWriter", "carried_rows", "replayed_rows", "WRITER_DEPTH"]

#: blocks waiting for the writer at most, besides the one it writes (the loop waits beyond:
#: bounded memory)
WRITER_DEPTH = 1


def _carried(rows: Mapping[str, Any], names: Sequence[str]) -> dict[str, Any]:
    """The fields of ``rows`` a carry is made from: the parameters ``names``, status, ZNCC
    and window half-width (:func:`~torch_stsdic.movie.carry.make_carry`)."""
    return {nm: rows[nm] for nm in (*names, "status", "zncc", "m") if nm in rows}


def carried_rows(block: dict[str, torch.Tensor], names: Sequence[str],
                 offsets: ReferenceOffsets | None, frames: Sequence[int]
                 ) -> dict[str, torch.Tensor]:
    """name -> (B, N) what the next block's carry is made from (parameters ``names``,
    status, ZNCC, window half-width), on the device of the solved rows ``block``: exactly the
    numbers the result file stores (``offsets`` subtracted, rounded as stored: a resumed run
    reads the same back) with the offsets added back (the solves' own terms)."""
    rows = _carried(block, names)
    if offsets is not None:
        rows = apply_offsets(rows, offsets, frames)
    stored = as_stored_tensors(rows)
    return stored if offsets is None else restore_offsets(stored, offsets)


def replayed_rows(stored: Mapping[str, np.ndarray], names: Sequence[str],
                  offsets: ReferenceOffsets | None, device: torch.device | str
                  ) -> dict[str, torch.Tensor]:
    """:func:`carried_rows` of a block replayed from the file (``stored``: its rows as read
    back): those fields alone copied to ``device``, the offsets added back."""
    rows = {nm: torch.from_numpy(np.asarray(a)).to(device)
            for nm, a in _carried(stored, names).items()}
    return rows if offsets is None else restore_offsets(rows, offsets)


#: the writer's answers besides one per block: every block before a mark is written (a
#: mark), the thread has ended (the end)
_MARK, _END = "mark", "end"


class RowWriter:
    """Writes solved blocks into ``sink`` (its ``write_rows``) on a thread of its own, in the
    order they are handed over (:meth:`put`), at most ``depth`` waiting besides the one
    being written. An error of the writer is raised in the caller at its next :meth:`put`,
    :meth:`wait` or :meth:`close`; :meth:`close` writes every block handed over first (an
    interrupted run keeps every block it finished).

    Made of the primitives a Ctrl-C cannot wedge (as the kernels' thread pool,
    :mod:`torch_stsdic.kernels.native.rows`): two ``queue.SimpleQueue`` (tasks to the
    thread, an answer back for each) and a thread started by ``_thread.start_new_thread``;
    a ``queue.Queue``'s lock, taken in Python code, stays taken if the interrupt lands just
    after it is acquired, and the next hand-over would wait forever."""

    def __init__(self, sink: Any, fields: Sequence[str], offsets: ReferenceOffsets | None,
                 depth: int = WRITER_DEPTH) -> None:
        self.sink, self.fields, self.offsets = sink, tuple(fields), offsets
        self.depth = max(1, int(depth))
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        self._answers: queue.SimpleQueue = queue.SimpleQueue()
        self._pending = 0  # blocks handed over and not answered yet (the caller's count)
        self._error: BaseException | None = None  # the first failed write's error
        self._raised = False  # (raised once in the caller)
        self._ended = False
        #: the rows written so far (their blocks' rows; read by the caller's thread)
        self.rows_written = 0
        #: seconds the writer's thread spent on blocks (host copy, offsets, write, strains:
        #: beside the caller's work) and seconds the caller waited for it (a full queue in
        #: :meth:`put`, :meth:`wait`, :meth:`close`): :meth:`times`
        self.busy_s = 0.0
        self.waited_s = 0.0
        _thread.start_new_thread(self._work, ())

    def put(self, rows: Sequence[int], block: dict[str, torch.Tensor], frames: Sequence[int],
            reference_frame: int) -> None:
        """Hand over the solved rows ``rows`` (output rows of series frames ``frames``): their
        fields ``block`` (name -> (B, N) tensors, not changed afterwards), measured against
        ``reference_frame``. From a GPU the copy to pinned host memory is queued here. Waits
        while ``depth`` blocks wait for the writer already."""
        self._raise()
        while self._pending > self.depth:
            self._answer()
        self._raise()
        fields = {nm: block[nm].detach() for nm in self.fields if nm in block}
        done = None
        dev = next(iter(fields.values())).device
        if dev.type == "cuda":
            fields = {nm: torch.empty(t.shape, dtype=t.dtype, pin_memory=True).copy_(
                t, non_blocking=True) for nm, t in fields.items()}
            done = torch.cuda.Event()
            done.record()
        self._tasks.put((list(rows), fields, done, list(frames), int(reference_frame)))
        self._pending += 1

    def wait(self) -> None:
        """Return once every block handed over is written (raises the writer's error)."""
        if not self._ended:
            self._tasks.put(_MARK)
            while self._answer() != _MARK:
                pass
        self._raise()

    def close(self) -> None:
        """Write what was handed over, end the thread (raises the writer's error). Another
        interruption meanwhile does not cut a block's write short: it is raised after."""
        interrupted: BaseException | None = None
        if not self._ended:
            self._tasks.put(None)
            while not self._ended:
                try:
                    self._answer()
                except KeyboardInterrupt as exc:  # a file closed mid-write would lose more
                    interrupted = exc
        if interrupted is not None:
            raise interrupted
        self._raise()

    def times(self) -> dict[str, float]:
        """``{"busy_s", "waited_s"}``: the writer's own seconds (on its thread, beside the
        caller's work) and the seconds the caller waited for it (what writing cost the
        caller's wall time)."""
        return {"busy_s": self.busy_s, "waited_s": self.waited_s}

    def _answer(self) -> Any:
        """The writer's next answer (waits for it): a block's, a mark or the end."""
        t0 = time.perf_counter()
        try:
            got = self._answers.get()
        finally:
            self.waited_s += time.perf_counter() - t0
        if got == _END:
            self._ended = True
        elif got != _MARK:
            self._pending -= 1
        return got

    def _raise(self) -> None:
        if self._error is not None and not self._raised:
            self._raised = True
            raise self._error

    def _work(self) -> None:
        while True:
            item = self._tasks.get()
            if item is None or item == _MARK:
                self._answers.put(_END if item is None else _MARK)
                if item is None:
                    return
                continue
            t0 = time.perf_counter()
            try:
                if self._error is None:  # after a failed write the rest are not written
                    rows, fields, done, frames, ref_frame = item
                    if done is not None:
                        done.synchronize()
                    full = rows_numpy(fields, self.fields)
                    if self.offsets is not None:
                        full = apply_offsets(full, self.offsets, frames)
                    self.sink.write_rows(rows, full, reference_frame=ref_frame)
                    self.rows_written += len(rows)
            except BaseException as exc:  # noqa: BLE001 (raised in the caller)
                self._error = exc
            finally:
                self.busy_s += time.perf_counter() - t0  # (before the answer: read after it)
                self._answers.put(len(item[0]))
