#!/usr/bin/env python
"""Each block's host reads and the numbers read, in a ``stsdic run`` with a GPU's choices
(``torch_stsdic.movie.choices``, set through ``TORCH_STSDIC_CHOICES``): what a block asks
the device and why it cannot guess it (the placement's moved subsets and reference-cache
misses, the rescue's waves and their rows).

    python scripts/benchmarks/block_reads.py                    # the hourglass, defaults
    python scripts/benchmarks/block_reads.py -- ../shared/data/dic-challenge-sample12 --m 2

Prints one line a read (the block, its targets, the line that reads and its two callers,
the numbers) and a line a block with its count; the reads of :class:`~torch_stsdic.movie.
block_guess.BlockGuesses` only (the block loop's own; the passes' blocks included: the
template's rounds, the classical pass). Counts, not times: any device."""

from __future__ import annotations

import os
import sys
import tempfile
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
HOURGLASS = [str(REPO.parent / "shared/data/mudic-hourglass"), "--roi", "150", "20", "1120",
             "734", "--subset", "31", "--step", "20"]
GPU_CHOICES = "EVERY_CANDIDATE=1,UNTIL_DONE=0,MASKED_GROUPS=1,MASKED_CHECK=1,GUESS_READS=1"


def main() -> int:
    args = sys.argv[1:]
    if args and args[0] == "--":
        args = args[1:]
    os.environ.setdefault("TORCH_STSDIC_CHOICES", GPU_CHOICES)
    from torch_stsdic.cli.app import main as cli_main
    from torch_stsdic.movie import block_guess

    blocks: dict[int, list[str]] = {}
    targets: dict[int, int] = {}
    read = block_guess.BlockGuesses.read

    def spy(self, numbers):
        out = read(self, numbers)
        st = traceback.extract_stack()[:-1][-3:][::-1]
        where = " < ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in st)
        blocks.setdefault(id(self), []).append(f"{where}: {out}")
        targets[id(self)] = self.b
        return out

    block_guess.BlockGuesses.read = spy
    with tempfile.TemporaryDirectory() as tmp:
        code = cli_main(["run", *(args or HOURGLASS), "--out", str(Path(tmp) / "r.h5"),
                         "--no-progress"])
    for i, (key, lines) in enumerate(blocks.items()):
        b = targets[key]
        print(f"block {i} ({b} target{'s' if b != 1 else ''}): {len(lines)} read(s)")
        for line in lines:
            print("   ", line)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
