"""Regenerate the command outputs pasted into the docs, so that docs and program agree.

The blocks between ``<!-- generated: NAME -->`` and ``<!-- end generated: NAME -->`` in
docs/cli.md are program output:

- ``help``: ``stsdic --help``;
- ``demo``: ``stsdic demo`` (run in a temporary folder), with the wall-clock and CPU time the
  run took and the machine's load; the demo's figures are copied, scaled down, to
  ``docs/demo/``.

Usage::

    python scripts/regenerate_docs.py            # rewrite the blocks and docs/demo/*.png
    python scripts/regenerate_docs.py --check    # exit 1 if the blocks are stale (help text,
                                                 # demo errors); times are not compared

The demo time quoted in the README, in docs/cli.md and in ``stsdic --help`` is one constant,
:data:`torch_stsdic.cli.demo.DEMO_TIME`; ``--check`` also verifies that every one quotes it.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CLI_DOC = ROOT / "docs" / "cli.md"
README = ROOT / "README.md"
FIGURES = ("fields.png", "history.png", "error_per_frame.png")
#: table columns that do not depend on the machine (method .. valid); time and POI/s do
_DETERMINISTIC = re.compile(r"^(.*?\d+\.\d{4}\*?\s+\d+\.\d{4}\*?\s+\d+\.\d{4}\*?\s+\d+\.\d)")


def _stsdic(args: list[str], cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run([sys.executable, "-m", "torch_stsdic", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, check=True)  # fmt: skip
    return done.stdout


def help_text() -> str:
    """``stsdic --help`` as a docs block."""
    return "```\n$ stsdic --help\n" + _stsdic(["--help"], ROOT).rstrip() + "\n```\n"


def demo_text(figures_to: Path | None = None) -> str:
    """``stsdic demo`` run now, as a docs block with its measured time; its figures scaled to
    900 px wide into ``figures_to``."""
    with tempfile.TemporaryDirectory() as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = _stsdic(["demo", "--no-progress"], Path(tmp))
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        if figures_to is not None:
            _copy_figures(Path(tmp) / "stsdic-demo", figures_to)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cores = os.cpu_count() or 0
    block = "```\n$ stsdic demo\n" + "\n".join(ln.rstrip() for ln in out.splitlines()) + "\n```\n"
    note = (f"\nThis run took {wall:.1f} s of wall-clock time and {cpu:.1f} s of CPU time "
            f"(Python start-up, plots and files included) on a {cores}-core machine with a "
            f"load average of {load:.1f} when it ended (other jobs running; "
            f"`python scripts/regenerate_docs.py` reran it and pasted this block).\n")  # fmt: skip
    return block + note


def _copy_figures(src: Path, dst: Path) -> None:
    from PIL import Image

    dst.mkdir(parents=True, exist_ok=True)
    for name in FIGURES:
        with Image.open(src / name) as im:
            w, h = im.size
            if w > 900:
                im = im.resize((900, round(h * 900 / w)), Image.LANCZOS)
            im.convert("RGB").quantize(colors=255).save(dst / name, optimize=True)
        shutil.copystat(src / name, dst / name)


def _block(text: str, name: str) -> tuple[int, int]:
    """(start, end) offsets of the generated block ``name`` (its contents only)."""
    begin, end = f"<!-- generated: {name} -->\n", f"<!-- end generated: {name} -->"
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        raise SystemExit(f"{CLI_DOC}: no block {begin.strip()} .. {end}")
    return i + len(begin), j


def _stable(block: str) -> list[str]:
    """The lines of a pasted demo run that do not depend on the machine: everything inside
    the code fence except times and throughputs."""
    inside = block.split("```")[1] if block.count("```") >= 2 else block
    out = []
    for ln in inside.strip().splitlines():
        ln = re.sub(r" \(synthesised in [\d.]+ s\)", "", ln.rstrip())
        m = _DETERMINISTIC.match(ln)
        out.append(m.group(1) if m else ln)
    return out


def replace_block(text: str, name: str, new: str) -> str:
    i, j = _block(text, name)
    return text[:i] + new + text[j:]


def stale(text: str, demo: bool = True) -> list[str]:
    """What is out of date in docs/cli.md and the README: help text, demo time and (with
    ``demo``, which runs it) the demo's output."""
    from torch_stsdic.cli.demo import DEMO_TIME

    problems = []
    i, j = _block(text, "help")
    if text[i:j] != help_text():
        problems.append("the 'stsdic --help' block differs from the program's output")
    i, j = _block(text, "demo")
    pasted, fresh = _stable(text[i:j]), (_stable(demo_text()) if demo else None)
    if demo and pasted != fresh:
        diff = [f"{a!r} -> {b!r}" for a, b in zip(pasted, fresh) if a != b]
        problems.append(f"the demo's output differs ({len(pasted)} vs {len(fresh)} lines): "
                        + "; ".join(diff[:3]))
    for doc in (CLI_DOC, README):
        if DEMO_TIME not in doc.read_text(encoding="utf-8"):
            problems.append(f"{doc.name} does not quote the demo time {DEMO_TIME!r}")
    if DEMO_TIME not in help_text():
        problems.append(f"'stsdic --help' does not quote the demo time {DEMO_TIME!r}")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only report stale blocks (exit 1)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    text = CLI_DOC.read_text(encoding="utf-8")
    if args.check:
        problems = stale(text)
        for p in problems:
            print(f"stale: {p}")
        return 1 if problems else 0
    text = replace_block(text, "help", help_text())
    text = replace_block(text, "demo", demo_text(ROOT / "docs" / "demo"))
    CLI_DOC.write_text(text, encoding="utf-8")
    print(f"rewrote the generated blocks of {CLI_DOC} and docs/demo/*.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
