"""The rescue of a block's lost rows (movie.block.Block.rescue): every target of a long block
at once in each step (a few solves, not up to three a target), with the results of blocks
solved one target after another."""

from __future__ import annotations

import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.core.status import Status
from torch_stsdic.movie import block as block_mod
from torch_stsdic.movie.series import track
from torch_stsdic.synth import Translation, synthetic_movie

UT, VT = 0.45, -0.3  # px per frame


@pytest.fixture(scope="module")
def movie():
    """21 noisy frames (t = 0..20; frame 0 the reference) of a translation at (UT, VT)."""
    mv = synthetic_movie((81, 81), 20, Translation(ut=UT, vt=VT), noise_sigma=1.0, seed=3)
    return torch.cat([mv.ref[None], mv.frames])


def _track(frames, batch: int, monkeypatch) -> tuple:
    """Classical DIC of the movie against frame 0 (no template, no shared motion: the
    first block starts without a guess), in blocks of ``batch`` targets; the number of
    solves its blocks made."""
    calls = []
    solve = block_mod.Block.solve

    def counting(self, rows, init, *a, **k):
        calls.append(int(rows.numel()))
        return solve(self, rows, init, *a, **k)

    monkeypatch.setattr(block_mod.Block, "solve", counting)
    res = track(frames, config=DICConfig(m=0, subset_size=21), roi=(22, 22, 58, 58), step=12,
                progress=False, batch_frames=batch, series_reference=False,
                shared_motion=None, find_specimen=False, strain_window=None)
    monkeypatch.undo()
    return res, calls


def test_a_long_block_is_rescued_in_a_few_solves_with_the_same_results(movie, monkeypatch):
    """A first block of 20 targets has no guess: every row is lost. Target by target that
    was an FFT solve and then a solve a target from the one before (20 and more); all at
    once it is the FFT of the first target and a wave a stretch of targets (the velocity
    unknown at the first target: one target; then up to 8 at a time). The answer is the
    one-target blocks' and the known motion."""
    long_, calls = _track(movie, 20, monkeypatch)
    short, calls_short = _track(movie, 1, monkeypatch)
    assert len(calls) <= 8, calls
    assert len(calls_short) >= 20  # one block a target (the comparison's premise)
    assert bool((long_.status <= int(Status.MAX_ITER)).all())
    assert torch.equal(long_.status, short.status)
    t = long_.times.double().view(-1, 1)
    for got, ref, rate in ((long_.u, short.u, UT), (long_.v, short.v, VT)):
        assert float((got.double() - ref.double()).abs().max()) < 2e-3
        assert float((got.double() - rate * t).abs().max()) < 0.05


@pytest.mark.parametrize("m", [0, 2])
def test_a_long_blocks_rescue_keeps_points_leaving_the_image_in_view(m, monkeypatch):
    """The specimen moves up and out of view. One-target blocks carry each point and move
    its subset inside the image while the point is in view (an off-centre subset; a
    shorter window where it leaves within the window's frames); a long block's rows start
    in the rescue and must be placed the same way: the same statuses as one-target blocks,
    points measured until they leave (a long block's rescue that solved centred subsets
    with the run's window there disagreed at 26 % (m = 0) and 10 % (m = 2) of the top
    points' rows)."""
    mv = synthetic_movie((97, 97), 20, Translation(ut=0.2, vt=-1.4), noise_sigma=1.0, seed=5,
                         margin=40.0)
    frames = torch.cat([mv.ref[None], mv.frames])
    runs = []
    for batch in (1, 20):
        res = track(frames, config=DICConfig(m=m, subset_size=21), roi=(20, 14, 76, 60),
                    step=10, progress=False, batch_frames=batch, series_reference=False,
                    shared_motion=None, find_specimen=False, strain_window=None,
                    window_length="fixed")
        runs.append(res)
    short, long_ = runs
    top = short.points[:, 1] < 30  # the rows of points that leave within the movie
    assert bool(top.any())
    ok_short = short.status <= int(Status.MAX_ITER)
    ok_long = long_.status <= int(Status.MAX_ITER)
    # the top points are measured off-centre for frames after their centred subset left
    y = short.points[:, 1].double() + short.v.double()
    assert bool((ok_short & (y < 10.5)).any())
    assert float((ok_long[:, top] == ok_short[:, top]).double().mean()) >= 0.98
    assert int(ok_long.sum()) >= int(ok_short.sum()) - 2
    both = ok_short & ok_long  # (a subset moved by other whole px: other pixels, other noise)
    d = (long_.v - short.v).double()[both]
    assert float(d.pow(2).mean().sqrt()) < 2e-3 and float(d.abs().max()) < 0.02


def test_a_point_predicted_out_of_view_from_further_back_is_outside_only_along_a_run():
    """The rescue gives up on a row predicted out of view (OUTSIDE) only where the guess comes
    from the target before (or the same one), or where the point's row at the target before
    is OUTSIDE: along each run of rows predicted out. Against the target-by-target rule on
    random cases, and a hand-made one."""
    from torch_stsdic.movie.rescue import _outside_runs

    def one_by_one(out, near, left):
        chain = out & near
        for j in range(1, out.shape[0]):
            chain[j] |= out[j] & (chain[j - 1] | left[j - 1])
        return chain

    gen = torch.Generator().manual_seed(0)
    for b in range(1, 10):
        for _ in range(50):
            out, near, left = (torch.rand(b, 4, generator=gen) < p for p in (0.6, 0.3, 0.2))
            assert torch.equal(_outside_runs(out, near, left), one_by_one(out, near, left))
    # one point, 6 targets: predicted out at 1..5, from the target before only at 2; the row
    # at 4 is in view: the run 2..3 is OUTSIDE, 1 and 5 wait for a nearer guess
    out = torch.tensor([[0], [1], [1], [1], [0], [1]], dtype=torch.bool)
    near = torch.tensor([[0], [0], [1], [0], [0], [0]], dtype=torch.bool)
    left = torch.zeros(6, 1, dtype=torch.bool)
    assert _outside_runs(out, near, left).flatten().tolist() == [0, 0, 1, 1, 0, 0]


def test_a_block_with_no_lost_row_reads_once_in_its_rescue(movie, monkeypatch):
    """The rescue's steps are told what to do by facts read with its waves' numbers
    (``BlockRescue._facts``): a block with no lost row reads the device once in its
    rescue (its first wave's read), not once a step (3-4 before: the neighbours', two FFT
    passes); a block with lost rows reads again after each step that changed its rows."""
    from pathlib import Path

    from repo_scripts import load_script  # tests/ on the path

    from torch_stsdic.movie import rescue as rescue_mod

    cs = load_script(Path(__file__).resolve().parents[1] / "scripts" / "benchmarks"
                     / "count_syncs.py", "count_syncs")
    reads: list[tuple[int, int]] = []  # per block: (rows lost at the rescue, reads in it)
    rescue = rescue_mod.BlockRescue.rescue

    def counted(self, *a, **k):
        lost = int(self.lost().sum())
        with cs.SyncCounter() as c:
            out = rescue(self, *a, **k)
        reads.append((lost, cs.block_total(dict(c.counts), cpu_kernels=False)))
        return out

    monkeypatch.setattr(rescue_mod.BlockRescue, "rescue", counted)
    _track(movie, 5, monkeypatch)
    clean = [r for lost, r in reads if lost == 0]
    assert len(clean) >= 3 and all(r == 1 for r in clean), reads
    assert any(lost and r > 1 for lost, r in reads), reads  # (the counter sees the reads)
