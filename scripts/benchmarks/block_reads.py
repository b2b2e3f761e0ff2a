#!/usr/bin/env python
"""Each block's host reads and the numbers read, in a ``stsdic run`` with a GPU's choices
(``torch_stsdic.core.choices.gpu_choices``; those named in ``TORCH_STSDIC_CHOICES`` as
named): what a block asks the device and why it cannot guess it (the placement's moved
subsets and reference-cache misses, the rescue's waves and their rows).

    python scripts/benchmarks/block_reads.py                    # the hourglass, defaults
    python scripts/benchmarks/block_reads.py -- ../shared/data/dic-challenge-sample12 --m 2

Prints a line a block with its count of reads (every ``Block`` made, in order: the
passes' blocks included, the template's rounds, the classical pass; a block solved again
after a wrong guess twice) and one line a read (the line that reads and its two callers,
the numbers); the reads of :class:`~torch_stsdic.movie.block_guess.BlockGuesses` only (the
block loop's own). Counts, not times: any device."""

from __future__ import annotations

import sys
import tempfile
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_parts import HOURGLASS  # noqa: E402  (the documented region, one definition)


def main() -> int:
    args = sys.argv[1:]
    if args and args[0] == "--":
        args = args[1:]
    from torch_stsdic.cli.app import main as cli_main
    from torch_stsdic.movie import block_guess, choices

    named = choices.from_environment()  # (those named in the environment kept as named)
    for name, value in choices.gpu_choices().items():
        if name not in named:
            setattr(choices, name, value)

    from torch_stsdic.movie.block import Block

    blocks: list[tuple[int, list[str]]] = []  # each Block made: its targets, its reads
    made, read = Block.__init__, block_guess.BlockGuesses.read

    def numbered(self, *a, **k):
        made(self, *a, **k)
        self.reads_no = len(blocks)  # (an attribute: a restored block keeps it)
        blocks.append((self.b, []))

    def spy(self, numbers):
        out = read(self, numbers)
        st = traceback.extract_stack()[:-1][-3:][::-1]
        where = " < ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in st)
        blocks[self.reads_no][1].append(f"{where}: {out}")
        return out

    Block.__init__, block_guess.BlockGuesses.read = numbered, spy
    with tempfile.TemporaryDirectory() as tmp:
        code = cli_main(["run", *(args or HOURGLASS), "--out", str(Path(tmp) / "r.h5"),
                         "--no-progress"])
    for i, (b, lines) in enumerate(blocks):
        print(f"block {i} ({b} target{'s' if b != 1 else ''}): {len(lines)} read(s)")
        for line in lines:
            print("   ", line)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
