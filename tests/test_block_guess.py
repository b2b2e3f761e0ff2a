"""A block's guessed reads (``torch_stsdic.movie.block_guess``, a GPU's choice): the answer
"nothing to do" of the last block taken unread, checked with the block's next read, a wrong
guess solving the block again the reading way; the result file is that of the reading way to
the bit."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torch_stsdic.kernels import native
from torch_stsdic.movie import block_guess
from torch_stsdic.movie.block_guess import BlockGuesses, GuessWrong, ReadGuesses


def _guesses(guessing: bool = True) -> BlockGuesses:
    g = BlockGuesses()
    g.run = SimpleNamespace(guesses=ReadGuesses(), device=torch.device("cpu"), stats={},
                            pending={})
    g.guessing, g.deferred, g.heard_sites = guessing, [], set()
    return g


def _strain_movie(tmp_path, seed: int, patch: tuple[int, int, int] | None = None):
    """A 23-frame strained speckle (``stsdic synth``, 160 px, noise 2) whose frame
    ``patch[0]`` shows another speckle over the square ``patch[1]:patch[2]`` (None: none)."""
    import tifffile

    from torch_stsdic import synth
    from torch_stsdic.cli import main

    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames", "23",
                 "--motion", "strain", "--exx", "0.002", "--noise", "2", "--seed", str(seed),
                 "--threads", "1"]) == 0
    movie = tmp_path / "m" / "movie.tif"
    if patch is not None:
        k, lo, hi = patch
        pages = tifffile.imread(movie)
        other = synth.render(synth.make_speckle((160, 160), seed=11), (160, 160)).numpy()
        pages[k, lo:hi, lo:hi] = np.clip(other[lo:hi, lo:hi], 0, 255).astype(pages.dtype)
        tifffile.imwrite(movie, pages)
    return movie


def test_a_guess_is_taken_only_after_a_quiet_answer_and_checked_with_the_next_read():
    g = _guesses()
    assert not g.may_guess("rescue")  # never heard: read
    g.heard("rescue", True)
    assert g.may_guess("rescue")
    assert not _guesses(guessing=False).may_guess("rescue")
    g.run.guesses.quiet["rescue"] = True
    # a guess that holds: the caller's numbers come back, the answer stays quiet
    g.defer("rescue", torch.tensor([0, 0, 0]))
    assert g.read(torch.tensor([4, 5])) == [4, 5]
    assert g.deferred == [] and g.run.guesses.quiet["rescue"]
    # one that does not: every answer heard, then GuessWrong names it
    g.defer("placement", torch.tensor(0))
    g.defer("rescue", torch.tensor([0, 2, 0]))
    with pytest.raises(GuessWrong, match="rescue"):
        g.read(torch.tensor([1]))
    assert g.deferred == []
    assert g.run.guesses.quiet == {"rescue": False, "placement": True}
    # settled at the block's end where no read came after it
    g.defer("placement", torch.tensor(3))
    with pytest.raises(GuessWrong, match="placement"):
        g.settle_guesses()
    g.settle_guesses()  # nothing deferred: nothing read, nothing raised


def test_a_masked_solves_rows_are_taken_to_a_size_learned_from_the_blocks_before(
        monkeypatch):
    """``compact``: no size known, every row masked (the count read with the next read, for
    the next block; in a block that reads its answers too, dropped where no read follows);
    known, the first C true rows (C a power of two at or above twice the
    count and R / 32), padded with -1; more rows than C is a wrong guess; a guess taken
    before the rescue (``from_here``) solves the whole block again. A block's most is held,
    half of it passed on where the next block asks for fewer."""
    from torch_stsdic.core import choices

    monkeypatch.setattr(choices, "COMPACT_ROWS", True)
    monkeypatch.setattr(choices, "GUESS_READS", True)
    assert block_guess.row_capacity(0, 100_000) == 4096  # R / 32 -> 3125 -> 4096
    assert block_guess.row_capacity(10, 1000) == 64
    assert block_guess.row_capacity(100, 1000) == 256
    assert block_guess.row_capacity(300, 1000) is None  # over half the rows: all masked
    g = _guesses()
    active = torch.zeros(1000, dtype=torch.bool)
    active[[3, 50, 700]] = True
    assert g.compact("check", active) is None  # nothing known: masked, counted
    assert g.read(torch.tensor([9])) == [9]
    assert g.run.guesses.sizes == {"check": 3}
    assert g.compact("check", active) == 64  # (the solver takes the first 64 active rows)
    g.settle_guesses()  # 3 <= 64: holds
    reading = _guesses(guessing=False)  # a block that reads: never taken, but learnt
    assert reading.compact("check", active) is None
    assert reading.read(torch.tensor([2])) == [2]
    assert reading.run.guesses.sizes == {"check": 3}
    reading.compact("classical", active)
    reading.settle_guesses()  # dropped: no read of its own
    assert not reading.deferred and "classical" not in reading.run.guesses.sizes
    monkeypatch.setattr(choices, "COMPACT_ROWS", False)
    assert g.compact("check", active) is None and not g.deferred  # the choice off
    monkeypatch.setattr(choices, "COMPACT_ROWS", True)
    many = torch.zeros(1000, dtype=torch.bool)
    many[:80] = True
    assert g.compact("check", many) == 64  # 80 rows asked for, 64 taken: wrong
    with pytest.raises(GuessWrong, match="rows at check") as wrong:
        g.settle_guesses()
    assert not wrong.value.whole
    g2 = _guesses()
    g2.run.guesses = g.run.guesses  # the next block: it holds the 80 it read
    assert g2.run.guesses.sizes["check"] == 80
    g2.compact("check", many)  # 160 -> 256 rows: holds
    g2.compact("check", many)
    g2.run.guesses.sizes["check"] = 80
    assert g2.compact("classical", active) is None  # another site: its own size
    calls = []

    def rest():
        calls.append(g2.guessing)
        g2.settle_guesses()
    g2.run.guesses.sizes["check"] = 10  # a guess before here that does not hold
    g2.deferred = []
    g2.compact("check", many)
    with pytest.raises(GuessWrong) as wrong:
        g2.from_here({}, rest)
    assert wrong.value.whole and calls == [True]  # raised for the whole block
    g3 = _guesses()
    g3.run.guesses.sizes["check"] = 40
    g3.compact("check", active)
    g3.settle_guesses()
    assert g3.run.guesses.sizes["check"] == 20  # 3 asked: half of the 40 held before


def test_a_reading_block_takes_its_masked_solves_rows_at_their_count_read_on_the_spot(
        monkeypatch):
    """``COMPACT_READING``: a block that reads its answers reads a compacted site's count at
    once (no deferred guess: nothing to be wrong about), takes the power of two at or above
    it (at least 64; none over half the rows) and learns it for the next block, as a count
    read later would be learnt; without the choice it solves every row masked."""
    from torch_stsdic.core import choices

    monkeypatch.setattr(choices, "COMPACT_ROWS", True)
    monkeypatch.setattr(choices, "GUESS_READS", True)
    assert block_guess.counted_capacity(0, 1000) == 64
    assert block_guess.counted_capacity(65, 1000) == 128
    assert block_guess.counted_capacity(300, 1000) is None  # 512: over half the rows
    active = torch.zeros(10_000, dtype=torch.bool)
    active[::50] = True  # 200 rows
    reading = _guesses(guessing=False)
    reading.run.guesses.sizes["check"] = 900  # held before: half of it passed on
    assert reading.compact("check", active) is None and reading.deferred  # the choice off
    reading.deferred = []
    monkeypatch.setattr(choices, "COMPACT_READING", True)
    assert reading.compact("check", active) == 256
    assert not reading.deferred and reading.run.guesses.sizes["check"] == 450
    few = torch.zeros(10_000, dtype=torch.bool)
    few[:500] = True
    assert reading.compact("check", few) == 512  # this block's most: 500
    assert reading.run.guesses.sizes["check"] == 500
    guessing = _guesses()  # a guessing block is not read: its guess as before
    guessing.run.guesses = reading.run.guesses
    assert guessing.compact("check", active) == 1024 and guessing.deferred


def test_a_wrong_guess_solves_the_block_again_with_the_counters_as_before(monkeypatch):
    from torch_stsdic.core import choices

    run = SimpleNamespace(device=torch.device("cpu"), guesses=ReadGuesses(),
                          stats={"fft_rows": torch.tensor(3), "rescued_rows": 2},
                          pending={"classical_rows": torch.tensor(1)})
    calls = []

    def solve(guessing: bool) -> str:
        calls.append(guessing)
        run.stats["fft_rows"] += 5  # in place, as a block adds its 0-d counts
        run.stats["rescued_rows"] += 1
        run.pending["classical_rows"] = run.pending["classical_rows"] + 4
        if guessing:
            raise GuessWrong(["placement"])
        return "solved"

    monkeypatch.setattr(choices, "GUESS_READS", True)
    assert block_guess.solve_guessing(run, solve) == "solved"
    assert calls == [True, False]
    # the wrong attempt's counts gone, the reading one's kept, the block counted
    assert int(run.stats["fft_rows"]) == 8 and run.stats["rescued_rows"] == 3
    assert int(run.pending["classical_rows"]) == 5
    assert run.stats["blocks_guessed_wrong"] == 1
    calls.clear()
    monkeypatch.setattr(choices, "GUESS_READS", None)  # the CPU's choice: read
    assert block_guess.solve_guessing(run, solve) == "solved" and calls == [False]


def _run_file(movie, path, *args) -> dict:
    """``stsdic run`` of ``movie`` (21 px subsets every 10 px, one thread) into ``path``: its
    datasets by name."""
    import h5py

    from torch_stsdic.cli import main

    assert main(["run", str(movie), "--subset", "21", "--step", "10", "--threads", "1",
                 "--no-progress", "--out", str(path), *args]) == 0
    with h5py.File(path) as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


@pytest.mark.parametrize("movie_kind,args,compact", [
    ("patch", (), False), ("patch", (), True), ("drift", (), True),
    ("drift", ("--m", "0", "--single-reference"), True)],
    ids=["patch", "patch-compact", "drift", "drift-classical"])
def test_guessed_reads_give_the_reading_runs_file_and_a_wrong_guess_is_caught(
        tmp_path, monkeypatch, movie_kind, args, compact):
    """``patch``: a strained speckle whose frame 15 is another speckle over a patch: the
    blocks before it find nothing to rescue, so the block holding frame 15 guesses "no row
    lost", wrongly, and rescues and checks its rows again. ``drift``: a speckle drifting
    right by 0.6 px a frame: the first carried blocks move no subset, so a later one guesses
    that its points stay clear of the border, wrongly, and is solved again from its start;
    so too a classical run's (``--m 0 --single-reference``: the placement read apart). With
    a GPU's choices, guessed and read give the same file to the bit; other blocks guess
    rightly. ``compact`` False: the masked solves not taken to a size (``COMPACT_ROWS``), so
    the patch's block guesses only its rescue wrong and is solved again from its rescue
    (with them, its classical group's size is wrong too: the whole block again)."""

    from torch_stsdic.cli import main
    from torch_stsdic.movie import block, choices

    if not native.available():
        pytest.skip("no native kernels (the paths agree to the bit on the C++ kernels)")
    if movie_kind == "patch":
        movie = _strain_movie(tmp_path, 3, patch=(15, 50, 110))
    else:
        assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames", "23",
                     "--motion", "translation", "--ut", "0.6", "--vt", "0.1", "--noise", "2",
                     "--seed", "4", "--threads", "1"]) == 0
        movie = tmp_path / "m" / "movie.tif"
    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value)
    monkeypatch.setattr(choices, "COMPACT_ROWS", compact)
    attempts: list[bool] = []  # each attempt at a block: guessing or not
    wrong: list[list[str]] = []  # the questions of each wrong guess
    wholes: list[bool] = []  # each wrong guess: the whole block solved again
    solve_block, init = block._solve_block, GuessWrong.__init__

    def spy(run, ks, ref, carry, guessing):
        attempts.append(guessing)
        return solve_block(run, ks, ref, carry, guessing)

    def heard_wrong(self, questions, whole=False):
        wrong.append(list(questions))
        wholes.append(whole or "placement" in questions)
        init(self, questions, whole)

    compact_rows = BlockGuesses.compact
    taken: list[int] = []  # the rows of each compacted solve

    def compacted(self, site, active):
        cap = compact_rows(self, site, active)
        if cap is not None:
            taken.append(cap)
        return cap

    monkeypatch.setattr(block, "_solve_block", spy)
    monkeypatch.setattr(GuessWrong, "__init__", heard_wrong)
    monkeypatch.setattr(BlockGuesses, "compact", compacted)
    out = {}
    for guess in (False, True):
        monkeypatch.setattr(choices, "GUESS_READS", guess)
        attempts.clear()
        wrong.clear()
        wholes.clear()
        taken.clear()
        out[guess] = _run_file(movie, tmp_path / f"g{int(guess)}.h5", *args)
        if not guess:
            assert not any(attempts) and not wrong and not taken
            continue
        if not args and compact:  # the checks' masked solves taken to a size
            assert len(taken) >= 3, taken
        if movie_kind == "patch":  # a rescue's wrong guess (solved from there again)
            assert any("rescue" in q for q in wrong), wrong
            if not compact:  # one that solves the block again from its rescue only
                assert any("rescue" in q and not w for q, w in zip(wrong, wholes)), wrong
        else:  # the placement's
            assert ["placement"] in wrong, wrong
        # a wrong placement (or a wrong size of a compacted solve before the rescue)
        # solves the whole block again, reading; a wrong rescue does not
        assert attempts.count(False) == sum(wholes), (attempts, wrong)
        assert attempts.count(True) > len(wrong)  # right guesses too
    if movie_kind == "patch":
        assert (out[True]["status"][15] != 0).sum() > 5  # the patch's rows: not converged
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k


@pytest.mark.parametrize("args", [(), ("--single-reference",)], ids=["template", "frame-0"])
def test_a_clean_movies_blocks_guess_rightly_the_first_after_the_reference_frame_too(
        tmp_path, monkeypatch, args):
    """A clean strained speckle with a GPU's choices: no block guesses wrong. The block
    after the reference frame's own row (the identity: nothing lost, nothing to rescue)
    starts from rest or a first guess, not from a carry, and so reads its answers instead
    of taking the identity's "nothing" (which its rows, lost where the motion has no
    velocity yet, proved wrong); its masked solves' sizes read too."""
    from torch_stsdic.cli import main
    from torch_stsdic.core import choices

    if not native.available():
        pytest.skip("no native kernels")
    movie = _strain_movie(tmp_path, 4)
    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value)
    wrong: list[list[str]] = []
    init = GuessWrong.__init__

    def heard_wrong(self, questions, whole=False):
        wrong.append(list(questions))
        init(self, questions, whole)

    monkeypatch.setattr(GuessWrong, "__init__", heard_wrong)
    assert main(["run", str(movie), "--subset", "21", "--step", "10",
                 "--threads", "1", "--no-progress", "--out", str(tmp_path / "r.h5"),
                 *args]) == 0
    assert wrong == []


def test_a_block_after_one_whose_rows_lack_a_velocity_reads_its_answers(tmp_path,
                                                                        monkeypatch):
    """Frame 1 of a strained speckle is another speckle over a patch: at the reference
    frame's block (frame 0 alone) the patch's points keep no velocity (their window's
    frames 0-2 hold the patch), so the next block starts their later targets in the
    rescue's waves where frame 0's block lost no row. That block's carry does not know the
    velocity everywhere (``Carry.vel_known``): it reads its answers, and guesses nothing
    wrong (the run's other blocks may, for the patch)."""

    from torch_stsdic.cli import main
    from torch_stsdic.movie import block, choices

    if not native.available():
        pytest.skip("no native kernels")
    movie = _strain_movie(tmp_path, 3, patch=(1, 60, 100))
    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value)
    now: dict = {}
    wrong: list[tuple] = []  # (the block's first target, its carry's known velocities)
    solve_block, init = block._solve_block, GuessWrong.__init__

    firsts: list[int] = []  # each block's first target

    def spy(run, ks, ref, carry, guessing):
        known = None if carry is None or carry.vel_known is None else carry.vel_known
        now["block"] = (ks[0], run.m, None if known is None else int(known.sum()),
                        None if known is None else known.numel())
        firsts.append(ks[0])
        return solve_block(run, ks, ref, carry, guessing)

    def heard_wrong(self, questions, whole=False):
        wrong.append(now["block"])
        init(self, questions, whole)

    monkeypatch.setattr(block, "_solve_block", spy)
    monkeypatch.setattr(GuessWrong, "__init__", heard_wrong)
    assert main(["run", str(movie), "--subset", "21", "--step", "10", "--threads", "1",
                 "--no-progress", "--out", str(tmp_path / "r.h5"), "--m", "2",
                 "--single-reference"]) == 0
    assert 1 in firsts  # the block after frame 0's was solved
    assert not [w for w in wrong if w[0] == 1], wrong


def _drift_movie(tmp_path, frames: int = 47):
    """A speckle drifting right ever faster (``stsdic synth``, 160 px, noise 2, u = 0.3 t +
    0.01 t^2, v = 0.1 t): from some block on, every block moves the subsets of the points at
    the right border, and the run carries its shared motion (not affine in time): the moved
    subsets' motion is taken at their centres."""
    from torch_stsdic.cli import main

    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames",
                 str(frames), "--motion", "quadratic", "--au", "0.3", "--bu", "0.01",
                 "--av", "0.1", "--noise", "2", "--seed", "4", "--threads", "1"]) == 0
    return tmp_path / "m" / "movie.tif"


@pytest.mark.parametrize("wrong_kind,args", [
    (None, ()), ("missed", ()), ("off", ()), (None, ("--m", "0", "--single-reference"))],
    ids=["right", "missed", "off", "classical"])
def test_a_placement_after_one_that_moved_subsets_reads_nothing_and_gives_the_same_file(
        tmp_path, monkeypatch, wrong_kind, args):
    """With a GPU's choices, a block whose last block's placement moved subsets near the
    border (all inside the image) places its own unread: its subsets' facts (the rows moved,
    off their POIs, whether every subset is inside, the reference subsets the cache misses)
    read with the block's one later read. The file is the reading run's to the bit.
    ``missed``: the solver's cache emptied before each unread placement and its capacity
    for missed subsets made 1, too few: that guess is wrong, the block solved again
    reading (the subsets sampled again: the same numbers). ``off``: the first unread
    placement's facts say a subset is off the image: the guess "inside" is wrong, that
    block solved again reading (its facts as they are), later ones unread again; the same
    file again. ``classical``: ``--m 0 --single-reference`` (no shorter windows: its
    placement made the reading way's and taken unread alike)."""

    from torch_stsdic.core import choices
    from torch_stsdic.movie import block_placement

    if not native.available():
        pytest.skip("no native kernels (the paths agree to the bit on the C++ kernels)")
    movie = _drift_movie(tmp_path)
    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value)
    unread: list[int] = []  # each unread placement's capacity of missed subsets (-1: a
    # wrong guess)
    wrong: list[list[str]] = []
    settle, init = block_placement.BlockPlacement.settle_unread, GuessWrong.__init__

    def spy(self, placed, capacity, mark):
        unread.append(capacity)
        if wrong_kind == "off" and sum(c >= 0 for c in unread) == 1:  # (facts: moved,
            # inside, off, missed)
            placed.facts[1] = 0
        if wrong_kind == "missed":  # the cache emptied: every subset of the block missed
            cache = self.run.solver.reference_cache
            cache._empty()
            cache.slot.fill_(-1)
        return settle(self, placed, capacity, mark)

    def heard_wrong(self, questions, whole=False):
        wrong.append(list(questions))
        unread.append(-1)  # (in order with the placements)
        init(self, questions, whole)

    monkeypatch.setattr(block_placement.BlockPlacement, "settle_unread", spy)
    monkeypatch.setattr(GuessWrong, "__init__", heard_wrong)
    if wrong_kind == "missed":
        learned = BlockGuesses.learned_capacity
        monkeypatch.setattr(BlockGuesses, "learned_capacity", lambda self, site, rows: (
            1 if site == "reference subsets missed" else learned(self, site, rows)))
    out = {}
    for guess in (False, True):
        monkeypatch.setattr(choices, "GUESS_READS", guess)
        unread.clear()
        wrong.clear()
        out[guess] = _run_file(movie, tmp_path / f"g{int(guess)}.h5", *args)
        if not guess:
            assert not unread
            continue
        assert any(c >= 0 for c in unread), "no block placed its subsets unread"
        if wrong_kind == "missed":
            assert any("rows at reference subsets missed" in q for q in wrong), (wrong, unread)
        elif wrong_kind == "off":
            assert ["subsets off the image"] in wrong, (wrong, unread)
            # and later blocks place unread again (the reading attempt heard "inside")
            assert sum(c >= 0 for c in unread) > 1, unread
        else:  # (the blocks before the first moves guess "none moved": wrong once)
            assert not any(set(q) & {"subsets off the image", "rows at reference subsets "
                                     "missed"} for q in wrong), wrong
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k


@pytest.mark.parametrize("wrong_kind", [None, "capacity", "choice off"])
def test_a_rescue_after_one_that_found_rows_in_one_wave_reads_nothing_and_gives_the_same_file(
        tmp_path, monkeypatch, wrong_kind):
    """With a GPU's choices, every block's rows of every fifth point after its first target
    lost before its rescue (made so: marked DIVERGED), which one wave finds again from the
    first target: a block after one whose rescue took that one wave and left nothing to
    its neighbours or FFT takes its waves unread (each wave's rows masked over every row,
    at most a learned number; its rows' placement unread too), and the guesses (the
    wave's size, "the next wave finds nothing") read with the block's one read. The file is
    the reading run's to the bit. ``capacity``: each wave's capacity made 1, too few: the
    guess is wrong and the block's rescue done again reading; the same file. ``choice
    off``: ``GUESS_WAVES`` False, every wave read (the other guesses taken)."""

    from torch_stsdic.core import choices
    from torch_stsdic.core.status import Status
    from torch_stsdic.movie import rescue

    if not native.available():
        pytest.skip("no native kernels (the paths agree to the bit on the C++ kernels)")
    movie = _drift_movie(tmp_path)
    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value)
    real_rescue, real_unread = rescue.BlockRescue.rescue, rescue.BlockRescue._waves_unread
    unread: list[int] = []  # each unread rescue: its waves
    wrong: list[list[str]] = []
    init = GuessWrong.__init__

    def lose_then_rescue(self, carry, carried, m=None):
        if m is None and self.b > 1:  # the block's rescue: every fifth point's later rows
            point = torch.arange(self.b * self.n) % self.n
            later = torch.arange(self.b * self.n) >= self.n
            lose = (point % 5 == 0) & later & (self.status <= 1)
            self.status.masked_fill_(lose, int(Status.DIVERGED))
        return real_rescue(self, carry, carried, m)

    def spy(self, carry, tried, fft_tried, caps):
        unread.append(len(caps))
        return real_unread(self, carry, tried, fft_tried, caps)

    def heard_wrong(self, questions, whole=False):
        wrong.append(list(questions))
        init(self, questions, whole)

    monkeypatch.setattr(rescue.BlockRescue, "rescue", lose_then_rescue)
    monkeypatch.setattr(rescue.BlockRescue, "_waves_unread", spy)
    monkeypatch.setattr(GuessWrong, "__init__", heard_wrong)
    if wrong_kind == "capacity":
        learned = BlockGuesses.learned_capacity
        monkeypatch.setattr(BlockGuesses, "learned_capacity", lambda self, site, rows: (
            1 if site.startswith("rescue wave ") else learned(self, site, rows)))
    if wrong_kind == "choice off":
        monkeypatch.setattr(choices, "GUESS_WAVES", False)
    out = {}
    for guess in (False, True):
        monkeypatch.setattr(choices, "GUESS_READS", guess)
        unread.clear()
        wrong.clear()
        out[guess] = _run_file(movie, tmp_path / f"g{int(guess)}.h5")
        if not guess or wrong_kind == "choice off":
            assert not unread
            continue
        assert unread and set(unread) == {1}, unread
        if wrong_kind == "capacity":
            assert any("rows at rescue wave 0" in q for q in wrong), wrong
        else:  # right where nothing else was wrong: a wrong size of the cache's new
            # subsets solves a wave's rows from other subsets (its rows lost again), and a
            # block whose carried start moved subsets after one that moved none guessed
            # none for its waves' rows too
            waves_wrong = [q for q in wrong if any(x.startswith("rescue wave") for x in q)]
            assert all({"rows at reference subsets missed", "placement"} & set(q)
                       for q in waves_wrong), wrong
            assert len(waves_wrong) < len(unread), (wrong, unread)
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k
