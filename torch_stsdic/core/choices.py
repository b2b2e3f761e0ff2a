"""The choices a run makes by its device, where a GPU and a CPU pay for different things: a
GPU waits for every value the host reads (a synchronisation: the device's queue drained),
while its extra rows cost next to nothing; a CPU reads for free and pays for every row it
computes. Each choice is None by default (decided by the run's device); set it to True or
False to take one device's choice on the other (the tests, ``scripts/benchmarks/
count_syncs.py --gpu-choices``), or name them in the environment before the package is
imported: ``TORCH_STSDIC_CHOICES="MASKED_GROUPS=0,EVERY_CANDIDATE=1"`` (a fresh ``stsdic
run`` process: ``scripts/benchmarks/device_choices.py`` times them). Either way the results
are the same to the bit.
"""

from __future__ import annotations

import os
import warnings

import torch

__all__ = ["EVERY_CANDIDATE", "UNTIL_DONE", "MASKED_GROUPS", "MASKED_CHECK", "GUESS_READS",
           "COMPACT_ROWS", "COMPACT_READING", "SEARCH_READS", "GUESS_WAVES", "ENV",
           "every_candidate", "until_done", "masked_groups", "masked_check", "guess_reads",
           "compact_rows", "compact_reading", "search_reads", "guess_waves", "gpu_choices",
           "from_environment"]

#: The model check's shorter windows (where the solver mixes window lengths): every candidate
#: window of every failing row in one solve, each row's first that passes kept (True), or in
#: rounds, each failing row's next candidate a round (False); None: at once on a GPU (one
#: host read and one solve a block instead of one each a round: 5 rounds a block on the
#: muDIC hourglass), in rounds on the CPU (a row stops at the window that passes: the kernel
#: work is that of the windows tried, not of every candidate). A row's solution does not
#: depend on the rows solved with it.
EVERY_CANDIDATE: bool | None = None

#: Loops of rounds where a round that finds nothing changes nothing, so neither does any
#: after it: a carry's lost points filled from their neighbours ring by ring
#: (:meth:`~torch_stsdic.movie.carry.Carry.from_neighbours`) and the neighbour test's rounds
#: (:func:`~torch_stsdic.analysis.quality.median_test`, ``MEDIAN_ROUNDS``): stopped at the
#: first round that finds nothing, one host read a round (True), or every round run, no
#: read (False); None: until done on the CPU (the hourglass's carries: 2-3 rings of 8 fill
#: points; the neighbour test: 1-2 rounds of 4), every round on a GPU.
UNTIL_DONE: bool | None = None

#: A block's rows of mixed half-widths (its carried rows, a rescue's, those solved again
#: shorter; :meth:`~torch_stsdic.movie.block_windows.BlockWindows.solve_windows`): the
#: classical rows and the window rows each in one solve of all the rows asked about, the
#: others masked (``SubsetSolver.solve(active=)``: no read, a GPU's per-point kernels skip
#: them; True), or each group's rows alone, their counts read first (one host read; False);
#: None: masked on a GPU, alone on the CPU (which would prepare every masked row: the
#: Hessians, the uncertainty). So too the carried window velocity's shake
#: (:func:`~torch_stsdic.movie.block_start.window_shake`) and the reported velocity's
#: (:func:`~torch_stsdic.movie.shared_velocity.report_velocity`): every half-width's,
#: masked, or those the rows take, read first.
MASKED_GROUPS: bool | None = None


#: The model check's steps (:meth:`~torch_stsdic.movie.checks.BlockChecks.check_model`: its
#: classical solves, those solved in full, the rows that keep the classical solution and
#: those converged to the run's tol) over all the block's rows, the rows a step drops masked
#: (:class:`~torch_stsdic.movie.row_set.RowSet`: no read; True), or each step's rows taken
#: from the last's (one host read a step, four a block; False); None: masked on a GPU, taken
#: on the CPU. Masked, every solve of the check covers every row of the block (on the
#: hourglass about 7x the rows its classical solve needs, in more batches): launches a GPU
#: pays for instead of the reads.
MASKED_CHECK: bool | None = None


#: A block's questions whose answer was "nothing to do" in the last block that asked them
#: (its carried rows' placement moved no subset, no row was lost after its solve;
#: :mod:`~torch_stsdic.movie.block_guess`): answered so unread, the numbers that tell read
#: with the block's next read (the classical rescue's, after the model check) or at its end,
#: a wrong guess solving the block again reading every answer (True), or each read where it
#: is asked (False); None: guessed on a GPU (a clean movie's block then reads once, not
#: three times), read on the CPU (which reads for free and would pay for a block solved
#: again).
GUESS_READS: bool | None = None


#: A masked solve's rows (the groups of :data:`MASKED_GROUPS`, the model check's steps of
#: :data:`MASKED_CHECK`, the classical rescue) taken to a fixed number of rows, sized from the
#: most the last block asked for there (:meth:`~torch_stsdic.movie.block_guess.BlockGuesses.
#: compact`: ``torch.nonzero_static``, no read), their count read with the block's next read
#: like a guessed answer (more than that size: a wrong guess, the block solved again reading)
#: (True); or every row asked about solved masked (False); None: taken where the block
#: guesses (:data:`GUESS_READS`) on a GPU. A masked row costs a solve's preparation and its
#: first evaluation (the benchmark movie's 32-target blocks of 10,000 POIs: 320,000 rows a
#: solve of the model check where a few hundred are asked for); a row not taken costs
#: nothing. Needs the block's guesses (:data:`GUESS_READS`).
COMPACT_ROWS: bool | None = None


#: A block that reads its answers (a run's first blocks, the reference frame's and the one
#: after it; a block solved again after a wrong guess) takes its masked solves' rows
#: (:data:`COMPACT_ROWS`'s call sites) to their count, read on the spot: one host read a
#: call site, the rows asked for solved alone (True); or every row solved masked, the count
#: learnt with the block's next read (False); None: read on a GPU (a read against the
#: preparation of every masked row: 320,000 a solve in the benchmark movie's 32-target
#: blocks). Needs :data:`COMPACT_ROWS`.
COMPACT_READING: bool | None = None


#: The FFT searches (:mod:`torch_stsdic.core.initial`: a run's first guesses, the rescue of
#: lost points) read on the host (True) or not (False); None: read on the CPU, not on a GPU.
#: Reading, a solve searches the rows whose subsets are inside the image, taken by index
#: after a read of whether there are any; not reading, every row, the others' answers
#: dropped.
#: Reading, the search regions are gathered from a strided view of the image where every
#: region of a batch lies inside it (a read of whether they do; else by index arithmetic on
#: clamped coordinates: two reads a batch), and the walk over a window's weak frames
#: searches again only the rows that are weak (a read of whether any is, and of which: five
#: reads a frame of the window); not reading, every region by index arithmetic and every
#: row searched at every frame of the walk, the answers of rows not weak dropped.
SEARCH_READS: bool | None = None


#: A block's rescue after one whose rescue found its rows in at most two waves and left
#: none to its neighbours or FFT: that many waves taken unread, each over every row masked
#: (at most a learned number of rows solved), the sizes and "the next wave finds nothing"
#: read with the block's next read (:meth:`~torch_stsdic.movie.rescue.BlockRescue.
#: _waves_unread`; True), or each wave read (False); None: unread on a GPU. A wave taken
#: unread computes its guesses, placement and masked solves over every row of the block
#: where a read one takes its rows alone: one read fewer a wave against more launches (the
#: 120-frame benchmark movie's block after one that lost 31 rows: 1 read and 8,161
#: launch-like operations against 2 and 7,310). Needs :data:`GUESS_READS` and
#: :data:`MASKED_GROUPS`.
GUESS_WAVES: bool | None = None


#: the environment variable that sets choices at import (``NAME=0|1`` by commas)
ENV = "TORCH_STSDIC_CHOICES"


def from_environment(text: str | None = None) -> dict[str, bool]:
    """The choices named in ``text`` (default: the environment's :data:`ENV`), set on this
    module; a malformed entry or an unknown name is warned about and skipped."""
    text = os.environ.get(ENV, "") if text is None else text
    names = set(gpu_choices())  # every choice
    out: dict[str, bool] = {}
    for entry in filter(None, (e.strip() for e in text.split(","))):
        name, _, value = entry.partition("=")
        name, value = name.strip().upper(), value.strip()
        if name not in names or value not in ("0", "1"):
            warnings.warn(f"{ENV}: {entry!r} skipped (NAME=0 or NAME=1, NAME one of "
                          f"{', '.join(sorted(names))})", stacklevel=2)
            continue
        out[name] = value == "1"
        globals()[name] = out[name]
    return out


def _choose(value: bool | None, device: torch.device, on_gpu: bool) -> bool:
    return (on_gpu if device.type != "cpu" else not on_gpu) if value is None else bool(value)


def every_candidate(device: torch.device) -> bool:
    """Whether the model check tries every shorter window at once on ``device``
    (:data:`EVERY_CANDIDATE`)."""
    return _choose(EVERY_CANDIDATE, device, on_gpu=True)


def until_done(device: torch.device) -> bool:
    """Whether a loop of rounds stops at the first round that finds nothing on ``device``
    (:data:`UNTIL_DONE`)."""
    return _choose(UNTIL_DONE, device, on_gpu=False)


def masked_groups(device: torch.device) -> bool:
    """Whether a block solves its groups of rows masked over all the rows asked about on
    ``device`` (:data:`MASKED_GROUPS`)."""
    return _choose(MASKED_GROUPS, device, on_gpu=True)


def masked_check(device: torch.device) -> bool:
    """Whether the model check masks the rows its steps drop on ``device``
    (:data:`MASKED_CHECK`)."""
    return _choose(MASKED_CHECK, device, on_gpu=True)


def guess_reads(device: torch.device) -> bool:
    """Whether a block guesses the answers "nothing to do" of the last block on ``device``
    (:data:`GUESS_READS`)."""
    return _choose(GUESS_READS, device, on_gpu=True)


def compact_rows(device: torch.device) -> bool:
    """Whether a guessing block takes its masked solves' rows to a size learned from the last
    block on ``device`` (:data:`COMPACT_ROWS`)."""
    return _choose(COMPACT_ROWS, device, on_gpu=True)


def compact_reading(device: torch.device) -> bool:
    """Whether a block that reads its answers takes its masked solves' rows to their count,
    read on the spot, on ``device`` (:data:`COMPACT_READING`)."""
    return _choose(COMPACT_READING, device, on_gpu=True)


def search_reads(device: torch.device) -> bool:
    """Whether the FFT searches read on the host on ``device`` (:data:`SEARCH_READS`)."""
    return _choose(SEARCH_READS, device, on_gpu=False)


def guess_waves(device: torch.device) -> bool:
    """Whether a block's rescue takes the last block's waves unread on ``device``
    (:data:`GUESS_WAVES`)."""
    return _choose(GUESS_WAVES, device, on_gpu=True)


def gpu_choices() -> dict[str, bool]:
    """Every choice as a GPU run makes it (by name), for a caller to set on the CPU."""
    return {"EVERY_CANDIDATE": True, "UNTIL_DONE": False, "MASKED_GROUPS": True,
            "MASKED_CHECK": True, "GUESS_READS": True, "COMPACT_ROWS": True,
            "COMPACT_READING": True, "SEARCH_READS": False, "GUESS_WAVES": True}


from_environment()
