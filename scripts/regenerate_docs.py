"""Regenerate the command outputs pasted into the docs, so that docs and program agree.

The blocks between ``<!-- generated: NAME -->`` and ``<!-- end generated: NAME -->`` in
docs/cli.md are program output:

- ``help``: ``stsdic --help``;
- ``demo``: ``stsdic demo`` (run in a temporary folder), with the wall-clock and CPU time the
  run took and the machine's load; the demo's figures are copied, scaled down, to
  ``docs/demo/``;

and in README.md the block ``demo-table``: the same run's error table and ratios.

Usage::

    python scripts/regenerate_docs.py            # rewrite the blocks and docs/demo/*.png
    python scripts/regenerate_docs.py --check    # exit 1 if the blocks are stale (help text,
                                                 # demo errors); times are not compared

The demo time quoted in the README, in docs/cli.md and in ``stsdic --help`` is one constant,
:data:`torch_stsdic.cli.demo.DEMO_TIME`; ``--check`` also verifies that every one quotes it.
"""

from __future__ import annotations

import argparse
import json
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


def demo_run(figures_to: Path | None = None) -> dict:
    """Run ``stsdic demo`` now (in a temporary folder): its output, wall-clock and CPU time,
    the load average, and demo.json; its figures scaled to 900 px wide into ``figures_to``."""
    with tempfile.TemporaryDirectory() as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = _stsdic(["demo", "--no-progress"], Path(tmp))
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        summary = json.loads((Path(tmp) / "stsdic-demo" / "demo.json").read_text())
        if figures_to is not None:
            _copy_figures(Path(tmp) / "stsdic-demo", figures_to)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return {"out": out, "wall": wall, "cpu": cpu, "load": load, "summary": summary}


def demo_text(run: dict) -> str:
    """The docs/cli.md block of a demo run: its output and its measured time."""
    lines = [ln.rstrip() for ln in run["out"].splitlines()]
    block = "```\n$ stsdic demo\n" + "\n".join(lines) + "\n```\n"
    note = (f"\nThis run took {run['wall']:.1f} s of wall-clock time and {run['cpu']:.1f} s of "
            f"CPU time (Python start-up, plots and files included) on a {os.cpu_count()}-core "
            f"machine with a load average of {run['load']:.1f} when it ended (other jobs "
            "running; `python scripts/regenerate_docs.py` reran it and pasted this block).\n")
    return block + note


def readme_text(run: dict) -> str:
    """The README block of a demo run: its error table up to the 'valid' column, and the
    ratios the README's text discusses (no times: the block is the same on every machine)."""
    lines = [ln.rstrip() for ln in run["out"].splitlines()]
    head = next(i for i, ln in enumerate(lines) if ln.startswith("method"))
    cut = lines[head].index("valid") + len("valid")
    table = []
    for ln in lines[head:]:
        if not ln.strip() or ln.startswith("ratio"):
            break
        table.append(ln[:cut].rstrip())
    res = {r["method"]: r for r in run["summary"]["results"]}
    c, s = res["classical DIC"], res["STS-DIC"]
    m = run["summary"]["settings"]["m"]
    bound = ((1 + 1 / (2 * m + 1)) / 2) ** 0.5
    text = ("```\n" + "\n".join(table) + "\n```\n\n"
            f"Measured here: STS-DIC's u error is {s['rms_u'] / c['rms_u']:.2f} of classical "
            f"DIC's (the single-reference bound is sqrt((1 + 1/{2 * m + 1}) / 2) = {bound:.2f})")
    averaged = [r for k, r in res.items() if k.startswith("STS-DIC, ref=mean")]
    if averaged:
        a = averaged[0]
        text += (f"; with an averaged reference STS-DIC has {a['rms_u'] / c['rms_u']:.2f}x the "
                 f"error of classical DIC with a single reference "
                 f"({c['rms_u'] / a['rms_u']:.1f}x better)")
    text += (f"; its velocity error is {c['rms_ut'] / s['rms_ut']:.1f}x smaller than that of "
             "finite differences of classical results.\n")
    return text


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


def _block(text: str, name: str, doc: Path = CLI_DOC) -> tuple[int, int]:
    """(start, end) offsets of the generated block ``name`` (its contents only)."""
    begin, end = f"<!-- generated: {name} -->\n", f"<!-- end generated: {name} -->"
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        raise SystemExit(f"{doc}: no block {begin.strip()} .. {end}")
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


def replace_block(text: str, name: str, new: str, doc: Path = CLI_DOC) -> str:
    i, j = _block(text, name, doc)
    return text[:i] + new + text[j:]


def stale(text: str, demo: bool = True) -> list[str]:
    """What is out of date in docs/cli.md and the README: help text, demo time and (with
    ``demo``, which runs it) the demo's output."""
    from torch_stsdic.cli.demo import DEMO_TIME

    problems = []
    i, j = _block(text, "help")
    if text[i:j] != help_text():
        problems.append("the 'stsdic --help' block differs from the program's output")
    if demo:
        run = demo_run()
        i, j = _block(text, "demo")
        pasted, fresh = _stable(text[i:j]), _stable(demo_text(run))
        if pasted != fresh:
            diff = [f"{a!r} -> {b!r}" for a, b in zip(pasted, fresh) if a != b]
            problems.append(f"the demo's output differs ({len(pasted)} vs {len(fresh)} "
                            "lines): " + "; ".join(diff[:3]))
        readme = README.read_text(encoding="utf-8")
        i, j = _block(readme, "demo-table", README)
        if readme[i:j] != readme_text(run):
            problems.append("the README's demo table differs from a run now")
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
    run = demo_run(ROOT / "docs" / "demo")
    text = replace_block(text, "help", help_text())
    text = replace_block(text, "demo", demo_text(run))
    CLI_DOC.write_text(text, encoding="utf-8")
    readme = README.read_text(encoding="utf-8")
    README.write_text(replace_block(readme, "demo-table", readme_text(run), README),
                      encoding="utf-8")
    print(f"rewrote the generated blocks of {CLI_DOC}, {README} and docs/demo/*.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
