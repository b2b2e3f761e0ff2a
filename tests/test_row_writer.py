"""The block loop's writer thread (:mod:`torch_stsdic.movie.row_writer`): the carry made on
the device from the solved rows is the one made from the rows as stored; the writer's errors
reach the run; it holds a bounded number of blocks; every block handed over is written."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from torch_stsdic.core.status import Status
from torch_stsdic.io.results import as_stored
from torch_stsdic.movie.carry import make_carry, rows_numpy
from torch_stsdic.movie.refine import ReferenceOffsets, apply_offsets, restore_offsets
from torch_stsdic.movie.row_writer import RowWriter, carried_rows

NAMES = ("u", "ux", "uy", "ut", "v", "vx", "vy", "vt")
FIELDS = (*NAMES, "zncc", "status", "iterations", "m", "u_std", "v_std")


def _block(b: int = 3, n: int = 50, seed: int = 0, dtype=torch.float64) -> dict[str, torch.Tensor]:
    """A solved block's rows as :func:`~torch_stsdic.movie.block.solve_block` returns them:
    values with many significant digits (float32 rounding matters), NaN rows, every status."""
    g = torch.Generator().manual_seed(seed)
    out = {nm: (torch.randn(b, n, generator=g, dtype=torch.float64) * 3.7).to(dtype)
           for nm in NAMES}
    out["zncc"] = (0.6 + 0.4 * torch.rand(b, n, generator=g, dtype=torch.float64)).to(dtype)
    out["u_std"] = out["v_std"] = torch.rand(b, n, generator=g, dtype=torch.float64).to(dtype)
    out["status"] = torch.randint(-3, 6, (b, n), generator=g).to(torch.int8)
    out["iterations"] = torch.randint(0, 40000, (b, n), generator=g).to(torch.int32)
    out["m"] = torch.randint(-1, 4, (b, n), generator=g).to(torch.int8)
    out["u"][-1, :5] = float("nan")
    out["ut"][:, 0] = float("nan")
    return out


def _offsets(n: int, reference_frame: int) -> ReferenceOffsets:
    g = np.random.default_rng(3)
    return ReferenceOffsets(
        values={nm: g.normal(0, 0.013, n) for nm in ("u", "v", "ux", "vy")},
        frames=np.ones(n, dtype=np.int64), degree=np.ones(n, dtype=np.int64),
        sigma=np.zeros(n), seconds=0.0, reference_frame=reference_frame)


def _host_seed(block, offsets, frames):
    """What the block loop carried from before the writer: the rows copied to the host, the
    offsets subtracted, rounded as stored, the offsets added back."""
    full = rows_numpy(block, FIELDS)
    if offsets is not None:
        full = apply_offsets(full, offsets, frames)
    stored = as_stored(full)
    return stored if offsets is None else restore_offsets(stored, offsets)


@pytest.mark.parametrize("with_offsets", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_carry_made_on_the_device_is_the_one_of_the_stored_rows(with_offsets, dtype):
    frames = [4, 5, 6]
    block = _block(dtype=dtype)
    offsets = _offsets(50, reference_frame=5) if with_offsets else None
    dev = carried_rows(block, NAMES, offsets, frames)
    host = _host_seed(block, offsets, frames)
    for nm, a in dev.items():  # the same numbers, field by field
        assert np.array_equal(a.cpu().numpy(), host[nm], equal_nan=True), nm
    times = np.array([4.0, 5.0, 6.0])
    prev = make_carry(_host_seed(_block(seed=1, dtype=dtype), None, [1, 2, 3]),
                      np.array([1.0, 2.0, 3.0]), NAMES, None, dtype, "cpu", frames=[1, 2, 3])
    a = make_carry(dev, times, NAMES, prev, dtype, "cpu", frames=frames)
    b = make_carry(host, times, NAMES, prev, dtype, "cpu", frames=frames)
    for field in ("vel_u", "vel_v", "valid", "vel_known", "fit_zncc", "window_m", "left"):
        x, y = getattr(a, field), getattr(b, field)
        if x is None or y is None:  # (vel_known: None, known everywhere)
            assert x is None and y is None, field
            continue
        assert torch.equal(x.nan_to_num(-9.0) if x.is_floating_point() else x,
                           y.nan_to_num(-9.0) if y.is_floating_point() else y), field
    for nm in NAMES:
        assert torch.equal(a.vals[nm].nan_to_num(-9.0), b.vals[nm].nan_to_num(-9.0)), nm
    for nm in a.rates:
        assert torch.equal(a.rates[nm], b.rates[nm]), nm
    if with_offsets:  # the reference frame's row: the truth where usable, as stored
        ok = dev["status"][1] <= int(Status.MAX_ITER)
        assert bool((dev["u"][1][ok] == torch.from_numpy(offsets.values["u"])[ok]).all())


class _ListSink:
    """A sink that records what it is given (slowly, where asked) and may fail."""

    def __init__(self, delay: float = 0.0, fail_at: int | None = None) -> None:
        self.rows, self.delay, self.fail_at = [], delay, fail_at
        self.reference_frames = {}

    def write_rows(self, rows, values, reference_frame=None):
        time.sleep(self.delay)
        if self.fail_at is not None and rows[0] == self.fail_at:
            raise OSError(28, "No space left on device")
        self.rows.append((list(rows), {k: np.array(v) for k, v in values.items()}))


def test_every_block_handed_over_is_written_in_order_with_the_values_as_solved():
    sink = _ListSink(delay=0.02)
    writer = RowWriter(sink, FIELDS, None)
    blocks = [_block(seed=s) for s in range(4)]
    for i, blk in enumerate(blocks):
        writer.put([3 * i, 3 * i + 1, 3 * i + 2], blk, [3 * i, 3 * i + 1, 3 * i + 2], 0)
    writer.close()  # (as after an interruption: what was handed over is written)
    assert [r for r, _ in sink.rows] == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]]
    assert writer.rows_written == 12
    for (_, got), blk in zip(sink.rows, blocks):
        want = rows_numpy(blk, FIELDS)
        for nm in FIELDS:
            assert np.array_equal(got[nm], want[nm], equal_nan=True), nm


def test_the_writer_holds_a_bounded_number_of_blocks():
    """A slow output holds the block loop back: at most one block waits besides the one
    being written (the loop's memory does not grow with the movie)."""
    sink = _ListSink(delay=0.05)
    writer = RowWriter(sink, FIELDS, None, depth=1)
    most = 0
    for i in range(6):
        writer.put([i], _block(b=1, seed=i), [i], 0)
        most = max(most, i + 1 - len(sink.rows))
    writer.close()
    assert len(sink.rows) == 6
    assert most <= 2


def test_the_writer_tells_its_own_seconds_apart_from_the_callers_wait():
    """``times()``: the writer thread's seconds (every write's) and the caller's wait for
    it. A caller that hands blocks over faster than they are written waits for them; one
    slower than the writer waits for none but the last."""
    sink = _ListSink(delay=0.05)
    writer = RowWriter(sink, FIELDS, None, depth=1)
    for i in range(6):
        writer.put([i], _block(b=1, seed=i), [i], 0)
    writer.close()
    t = writer.times()
    assert t["busy_s"] >= 6 * 0.05  # (sleeps: lower bounds whatever the machine's load)
    assert t["waited_s"] >= 3 * 0.05  # at most two blocks ahead: it waited for the rest

    slow_caller = RowWriter(_ListSink(delay=0.0), FIELDS, None, depth=1)
    for i in range(4):
        slow_caller.put([i], _block(b=1, seed=i), [i], 0)
        time.sleep(0.1)
    slow_caller.close()
    t = slow_caller.times()
    assert t["waited_s"] < 0.1 < 4 * 0.1  # its sleeps are not the writer's


def test_a_run_reports_the_writers_seconds():
    import torch_stsdic as sts
    from torch_stsdic import synth

    mv = synth.synthetic_movie((64, 64), 6, synth.Translation(ut=0.1), seed=2, noise_sigma=1.0)
    res = sts.track(mv.frames, reference=mv.ref, step=16, progress=False, batch_frames=2,
                    config=sts.DICConfig(subset_size=15, m=1))
    t = res.info["writer_times_s"]
    assert set(t) == {"busy_s", "waited_s"} and t["busy_s"] > 0 and t["waited_s"] >= 0


def test_an_error_of_the_writer_reaches_the_run_and_stops_the_writes():
    sink = _ListSink(fail_at=1)
    writer = RowWriter(sink, FIELDS, None)
    writer.put([0], _block(b=1), [0], 0)
    writer.put([1], _block(b=1, seed=1), [1], 0)
    with pytest.raises(OSError, match="No space left"):
        writer.wait()  # (or the next hand-over, or the close)
    for i in range(2, 5):  # handed over after the failure: not written
        writer.put([i], _block(b=1, seed=i), [i], 0)
    writer.close()  # the error was raised once
    assert [r for r, _ in sink.rows] == [[0]]
    assert writer._ended  # the thread has ended


def test_a_run_raises_its_output_error_with_the_blocks_before_it_written(tmp_path, monkeypatch):
    """Through ``track``: a write that fails (disk full) stops the run with that error, not
    a hang or a lost traceback; the blocks before it are in the file, resumable."""
    from torch_stsdic import DICConfig
    from torch_stsdic.io import read_results
    from torch_stsdic.io.results import ResultWriter
    from torch_stsdic.movie.series import track
    from torch_stsdic.synth import Translation, synthetic_movie

    mv = synthetic_movie((81, 81), 8, Translation(ut=0.3, vt=-0.2))
    frames = torch.cat([mv.ref[None], mv.frames])
    calls = {"n": 0}
    orig = ResultWriter.write_rows

    def full_disk(self, rows, values, mark_completed=True):
        if mark_completed:
            calls["n"] += 1
            if calls["n"] == 3:
                raise OSError(28, "No space left on device")
        return orig(self, rows, values, mark_completed=mark_completed)

    monkeypatch.setattr(ResultWriter, "write_rows", full_disk)
    out = tmp_path / "r.h5"
    with pytest.raises(OSError, match="No space left"):
        track(frames, config=DICConfig(subset_size=21, m=1), roi=(22, 22, 58, 58), step=18,
              progress=False, batch_frames=3, out=out, shared_motion=None)
    done = read_results(out).completed
    assert done.sum() >= 1 and done.tolist() == sorted(done.tolist(), reverse=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (pinned memory)")
def test_a_gpu_block_is_copied_to_pinned_memory_and_written_as_solved():
    """From a GPU the hand-over queues the copy into pinned host memory (no wait in the
    loop); the writer waits for it: the rows written are those solved, and the carry made
    on the device is the one of the stored rows."""
    sink = _ListSink()
    writer = RowWriter(sink, FIELDS, None)
    blocks = [_block(seed=s) for s in range(3)]
    for i, blk in enumerate(blocks):
        writer.put([i], {k: v.cuda() for k, v in blk.items()}, [i], 0)
    writer.close()
    for (_, got), blk in zip(sink.rows, blocks):
        want = rows_numpy(blk, FIELDS)
        for nm in FIELDS:
            assert np.array_equal(got[nm], want[nm], equal_nan=True), nm
    offsets = _offsets(50, reference_frame=1)
    dev = carried_rows({k: v.cuda() for k, v in blocks[0].items()}, NAMES, offsets, [0, 1, 2])
    host = _host_seed(blocks[0], offsets, [0, 1, 2])
    for nm, a in dev.items():
        assert a.is_cuda and np.array_equal(a.cpu().numpy(), host[nm], equal_nan=True), nm
