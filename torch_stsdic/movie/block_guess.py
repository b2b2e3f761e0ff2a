"""A block's guessed reads (:class:`BlockGuesses`, mixed into
:class:`torch_stsdic.movie.block.Block`): on a GPU each value the host reads waits for the
device, and a block of a clean movie asks two questions whose answer is nearly always the
last block's "nothing to do": did the carried rows' placement move a subset inside the image
(:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.keep_outside`), and is any row
lost after the solve (:meth:`~torch_stsdic.movie.rescue.BlockRescue.rescue`). Where the last
block answered "nothing", the block takes that answer unread and keeps the numbers that
tell, to read with its next read (the classical rescue's, after the model check, which is
then the block's one read:
:meth:`~torch_stsdic.movie.checks.BlockChecks.rescue_classical`) or once at its end
(:meth:`BlockGuesses.settle_guesses`); a wrong guess raises :class:`GuessWrong` and the block
is solved again reading every answer: from its rescue where that guess was wrong
(:meth:`BlockGuesses.from_here`), from its start where the placement's was
(:func:`solve_guessing`). The results
are those of the reading way to the bit: a guess only skips work that the answer "nothing"
skips. A GPU's choice (:data:`~torch_stsdic.core.choices.GUESS_READS`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from torch_stsdic.core.choices import compact_reading, compact_rows, guess_reads

__all__ = ["GuessWrong", "ReadGuesses", "BlockGuesses", "solve_guessing", "row_capacity",
           "counted_capacity", "PLACEMENT", "RESCUE", "SUBSETS_OFF", "MISSED"]

#: the questions a block may guess (the keys of :attr:`ReadGuesses.quiet`)
PLACEMENT, RESCUE = "placement", "rescue"
#: a placement's (:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.keep_outside`)
#: question "a subset lies off the reference image", guessed "no" where the last block's
#: placement read so, and its site of the reference subsets the solver's cache missed
SUBSETS_OFF, MISSED = "subsets off the image", "reference subsets missed"
#: a masked solve's rows at a site (:meth:`BlockGuesses.compact`): the question "at most
#: this many rows" is named ``SIZE + site``
SIZE = "rows at "
#: the fewest rows a compacted solve takes (a power of two: few shapes)
MIN_CAPACITY = 64
#: the fewest rows of a masked solve whose count a reading block reads to compact it
#: (:data:`~torch_stsdic.core.choices.COMPACT_READING`): below, a masked row's preparation
#: times the rows costs about a read. Estimated, not timed: on one H200 the masked choices
#: cost the 500-frame movie's blocks about 60 ms a solve of 320,000 rows (0.2 us a row;
#: the solve's seconds against frame 0, 7.4 -> 12.9 s, at b7f0068 -> 124f915), 4,096 rows
#: about 0.8 ms, several reads' worth
READ_ROWS = 4096


class GuessWrong(Exception):
    """A block's guessed answers were not "nothing to do" (:attr:`questions`); ``whole``:
    one of them was guessed before the block's rescue (the block is solved again from its
    start)."""

    def __init__(self, questions: list[str], whole: bool = False) -> None:
        super().__init__(", ".join(questions))
        self.questions = list(questions)
        self.whole = whole


@dataclass
class ReadGuesses:
    """A run's answers to its blocks' questions: whether the last block that asked each one
    found nothing to do (then the next block may guess so), and the rows a masked solve at
    each site asked for (:meth:`BlockGuesses.compact`): the most in the last block that read
    them, or half what was held before, whichever is more."""

    quiet: dict[str, bool] = field(default_factory=dict)
    sizes: dict[str, int] = field(default_factory=dict)


@dataclass
class _Deferred:
    """A guess taken and not checked yet: a question's where its ``numbers`` (K,) int64 are
    all 0, a size's (``SIZE + site``: ``numbers`` its count) where the count is at most
    ``limit`` (-1: any, a count only learnt); ``early``: taken before the block's rescue."""

    question: str
    numbers: torch.Tensor
    limit: int = 0
    early: bool = False
    #: called with the numbers read where the guess holds
    then: Callable[[list[int]], None] | None = None
    #: False: no guess, numbers only read with the block's next read (:meth:`BlockGuesses.
    #: read_later`)
    checked: bool = True


def row_capacity(asked: int, rows: int) -> int | None:
    """The rows a compacted solve takes where the blocks before asked for ``asked`` of a
    site's ``rows`` (R) (:attr:`ReadGuesses.sizes`): :func:`counted_capacity` of twice
    ``asked`` and R / 32, the larger (counts vary from block to block, a wrong guess costs
    the block's rescue and checks again)."""
    return counted_capacity(max(2 * asked, rows / 32), rows)


def counted_capacity(asked: float, rows: int) -> int | None:
    """The rows a compacted solve takes where ``asked`` of its ``rows`` (R) are asked for (a
    reading block's count, read; :func:`row_capacity`'s margin): the power of two at or
    above ``asked``, at least :data:`MIN_CAPACITY` (a few shapes over a run); None where
    that is over half of ``rows`` (every row solved masked: a taken half saves little)."""
    cap = MIN_CAPACITY
    while cap < asked:
        cap *= 2
    return None if 2 * cap > rows else cap


class BlockGuesses:
    """The guessed reads of a :class:`~torch_stsdic.movie.block.Block` (its ``run`` with a
    :class:`ReadGuesses` as ``run.guesses``; ``guessing`` set per attempt)."""

    run: Any
    #: whether this attempt may guess (False: the reading way, the attempt after a wrong guess)
    guessing: bool = False
    #: the guesses taken and not checked yet
    deferred: list[_Deferred]
    #: the sites whose counts this block has read (the run's sizes then hold its most)
    heard_sites: set[str]

    def may_guess(self, question: str) -> bool:
        """Whether ``question`` is answered "nothing to do" unread: this attempt guesses and
        the last block that asked it found nothing."""
        return self.guessing and self.run.guesses.quiet.get(question, False)

    def defer(self, question: str, zeros: torch.Tensor) -> None:
        """``question`` guessed "nothing to do": ``zeros`` (any shape, integers) are all 0
        where it holds; read with the block's next read (:meth:`read`) or at its end."""
        self.deferred.append(_Deferred(question, zeros.reshape(-1).to(torch.int64)))

    def compact(self, site: str, active: torch.Tensor) -> int | None:
        """The capacity of a masked solve's rows ``active`` (R,) bool at ``site``
        (:data:`~torch_stsdic.core.choices.COMPACT_ROWS`, where this attempt guesses): C, the
        most rows the solve takes (``SubsetSolver.solve(capacity=)``: the first C active
        ones, a fixed shape, no read), from the most rows the last block asked for there
        (:func:`row_capacity`); the guess "at most C" deferred (:meth:`read`: more is a wrong
        guess). A block that reads its answers reads the count here (one read,
        :data:`~torch_stsdic.core.choices.COMPACT_READING`, where the rows are at least
        :data:`READ_ROWS`) and takes that many
        (:func:`counted_capacity`). None: every row masked (no guess; the count read with
        the block's next read, for the next block: in a block that reads its answers, with
        the next answer it reads, if any)."""
        dev = self.run.device
        if not compact_rows(dev) or not guess_reads(dev):
            return None
        if not self.guessing and compact_reading(dev) and active.numel() >= READ_ROWS:
            asked = int(active.sum())  # (the reading way: one read, the exact count)
            self._learn(site, asked)
            return counted_capacity(asked, active.numel())
        known = self.run.guesses.sizes.get(site) if self.guessing else None
        cap = None if known is None else row_capacity(known, active.numel())
        # the count read with the next read: checked against ``cap``, or only learnt
        self.deferred.append(_Deferred(SIZE + site, active.sum().reshape(1),
                                       -1 if cap is None else cap))
        return cap

    def defer_count(self, site: str, count: torch.Tensor, limit: int,
                    then: Callable[[list[int]], None] | None = None) -> None:
        """The guess "at most ``limit``" of ``count`` (a 0-d integer tensor: the rows asked for
        at ``site``, learnt as :meth:`compact`'s), read with the next read (:meth:`read`; more
        is a wrong guess); ``then(values)`` where it holds."""
        self.deferred.append(_Deferred(SIZE + site, count.reshape(1).to(torch.int64), limit,
                                       then=then))

    def read_later(self, name: str, numbers: torch.Tensor,
                   then: Callable[[list[int]], None]) -> None:
        """``numbers`` (any shape, integers) read with the block's next read, no guess:
        ``then(values)`` is called with them (facts a block needs only once they are read)."""
        self.deferred.append(_Deferred(name, numbers.reshape(-1).to(torch.int64), then=then,
                                       checked=False))

    def learned_capacity(self, site: str, rows: int) -> int | None:
        """The rows a guessing block takes at ``site`` without reading their count:
        :func:`counted_capacity` of twice the most the blocks before asked for there
        (:attr:`ReadGuesses.sizes`), of ``rows`` (R) in all; None where that is unknown or
        over half of R (read instead)."""
        known = self.run.guesses.sizes.get(site)
        return None if known is None else counted_capacity(2 * known, rows)

    def heard(self, question: str, quiet: bool) -> None:
        """The answer to ``question`` as read (``quiet``: nothing to do), for the next block
        to guess from."""
        self.run.guesses.quiet[question] = bool(quiet)

    def ask(self, question: str, numbers: torch.Tensor, tell: int, asking: bool = True
            ) -> list[int] | None:
        """``numbers`` (K,) int64 read (:meth:`read`), their first ``tell`` all 0 where the
        answer to ``question`` is "nothing to do" (heard so for the next block where
        ``asking``); None where ``asking`` and that answer is guessed instead
        (:meth:`may_guess`: those ``tell`` numbers deferred, the caller goes on as if every
        number were 0)."""
        if asking and self.may_guess(question):
            self.defer(question, numbers[:tell])
            return None
        values = self.read(numbers)
        if asking:
            self.heard(question, not any(values[:tell]))
        return values

    def read(self, numbers: torch.Tensor) -> list[int]:
        """``numbers`` (K,) int64 read on the host, with the deferred guesses' numbers in the
        same read (one synchronisation); a guess that does not hold raises
        :class:`GuessWrong` (after every answer is heard)."""
        if not self.deferred:
            return numbers.tolist()
        k = numbers.numel()
        values = torch.cat([numbers.reshape(-1).to(torch.int64)]
                           + [d.numbers for d in self.deferred]).tolist()
        self._check(values[k:])
        return values[:k]

    def settle_guesses(self) -> None:
        """The deferred guesses read (one read; none where every guess was read already) and
        checked: :class:`GuessWrong` where one does not hold. A block that reads its answers
        drops the counts it would only learn from (no read of its own for them)."""
        if not self.guessing:
            self.deferred = [d for d in self.deferred if d.limit >= 0]
        if self.deferred:
            self._check(torch.cat([d.numbers for d in self.deferred]).tolist())

    def _check(self, values: list[int]) -> None:
        wrong, whole, at = [], False, 0
        for d in self.deferred:
            part = values[at:at + d.numbers.numel()]
            at += d.numbers.numel()
            if not d.checked:  # facts only read
                holds = True
            elif d.question.startswith(SIZE):  # a count, learnt
                self._learn(d.question[len(SIZE):], part[0])
                holds = d.limit < 0 or part[0] <= d.limit
            else:
                holds = not any(part)
                self.heard(d.question, holds)
            if holds and d.then is not None:
                d.then(part)
            if not holds:
                wrong.append(d.question)
                whole |= d.early
        self.deferred = []
        if wrong:
            raise GuessWrong(wrong, whole)

    def _learn(self, site: str, asked: int) -> None:
        """The rows ``asked`` for at ``site`` read: the site's size for the next block
        (:attr:`ReadGuesses.sizes`) the most this block asked for there, or half the most
        before it."""
        sizes = self.run.guesses.sizes
        before = sizes.get(site, 0) if site in self.heard_sites else sizes.get(site, 0) // 2
        sizes[site] = max(asked, before)
        self.heard_sites.add(site)

    def from_here(self, counts: dict[str, torch.Tensor], rest: Callable[[], None]) -> None:
        """``rest()``, the rest of the block (its rescues and checks), guessing; where a
        guess it checks was wrong, the block, the run's counters and the block's ``counts``
        as they were here, and ``rest()`` again, reading every answer (the block's solve
        is not done again). A wrong guess made before here (the placement's, a compacted
        solve's of the block's solve) is raised (:func:`solve_guessing` solves the whole
        block again)."""
        if not self.guessing:
            rest()
            return
        for d in self.deferred:  # guessed before here: wrong, the whole block again
            d.early = True
        # the block's tensors copied (solves change them in place), its containers anew
        state = {k: v.clone() if isinstance(v, torch.Tensor) else
                 (type(v)(v) if isinstance(v, (dict, list, set)) else v)
                 for k, v in vars(self).items() if k != "run"}
        stats, held = _counters(self.run.stats), dict(counts)
        try:
            rest()
        except GuessWrong as wrong:
            if PLACEMENT in wrong.questions or wrong.whole:
                raise
            for k in [k for k in vars(self) if k != "run" and k not in state]:
                delattr(self, k)
            vars(self).update(state)
            _guessed_wrong(self.run, stats)
            counts.clear()
            counts.update(held)
            self.guessing = False
            rest()


def _guessed_wrong(run: Any, stats: dict[str, Any]) -> None:
    """``run``'s counters back to ``stats`` (:func:`_counters`, taken before the guess), the
    wrong guess counted (``blocks_guessed_wrong``)."""
    run.stats.clear()
    run.stats.update(stats)
    run.stats["blocks_guessed_wrong"] = run.stats.get("blocks_guessed_wrong", 0) + 1


def _counters(stats: dict[str, Any]) -> dict[str, Any]:
    """A copy of a run's counters (0-d tensors among them copied: blocks add to them in
    place)."""
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in stats.items()}


def solve_guessing(run: Any, solve: Callable[[bool], Any]) -> Any:
    """``solve(guessing)`` (a block) with its reads guessed where ``run``'s device guesses
    (:func:`~torch_stsdic.core.choices.guess_reads`); after a wrong guess, the run's
    counters as they were before it and the block solved again reading every answer
    (counted in ``run.stats["blocks_guessed_wrong"]``)."""
    if not guess_reads(run.device):
        return solve(False)
    stats, pending = _counters(run.stats), dict(run.pending)
    try:
        return solve(True)
    except GuessWrong:
        _guessed_wrong(run, stats)
        run.pending = pending
        return solve(False)
