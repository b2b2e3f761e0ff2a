"""Regenerate the command outputs pasted into the docs, so that docs and program agree.

The blocks between ``<!-- generated: NAME -->`` and ``<!-- end generated: NAME -->`` in
docs/cli.md are program output:

- ``help``: ``stsdic --help``;
- ``run-options``: the option table of ``stsdic run``, made from its argparse parser
  (option, default, meaning: the help text every option has);
- ``run-summary``: what ``stsdic run`` prints, for the small synthetic movie of
  :data:`SUMMARY_COMMANDS` (run in-process in a temporary folder; its time line is not
  compared by ``--check``);
- ``demo``: ``stsdic demo`` (run in a temporary folder), with the wall-clock and CPU time the
  run took and the machine's load; the demo's figures are copied, scaled down, to
  ``docs/demo/``;

and in README.md the block ``demo-table``: the same run's error table and ratios.

Usage::

    python scripts/tools/regenerate_docs.py            # rewrite the blocks and docs/demo/*.png
    python scripts/tools/regenerate_docs.py --check    # exit 1 if the blocks are stale (help text,
                                                 # run options and summary, demo errors);
                                                 # times are not compared
    python scripts/tools/regenerate_docs.py --check --cli   # the CLI blocks only (no demo: seconds)

The demo time quoted in the README, in docs/cli.md and in ``stsdic --help`` is one constant,
:data:`torch_stsdic.cli.demo.DEMO_TIME`; ``--check`` also verifies that every one quotes it.
"""

from __future__ import annotations

import argparse
import functools
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

ROOT = Path(__file__).resolve().parents[2]
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


@functools.lru_cache(maxsize=1)
def help_text() -> str:
    """``stsdic --help`` as a docs block."""
    return "```\n$ stsdic --help\n" + _stsdic(["--help"], ROOT).rstrip() + "\n```\n"


#: the commands whose output is the ``run-summary`` block
SUMMARY_COMMANDS = (["synth", "--out", "mv", "--size", "121", "--frames", "8"],
                    ["run", "mv/movie.tif", "--step", "10", "--out", "r.h5", "--no-progress"])


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _option_row(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    """One table row: the option with its value, the default, the meaning."""
    first, *aliases = action.option_strings
    if action.nargs != 0:
        meta = action.metavar
        if meta is None:
            meta = "{" + ",".join(map(str, action.choices)) + "}" if action.choices else \
                action.dest.upper()
        first += " " + (" ".join(meta) if isinstance(meta, tuple) else str(meta))
    flags = f"`{first}`" + "".join(f" (`{a}`)" for a in aliases)
    text = formatter._expand_help(action) if action.help else ""
    default = "-"
    found = re.search(r"\s*\(default: (.*)\)\s*$", text, flags=re.S)
    inner = re.search(r";\s*default: ([^)]*)\)\s*$", text)  # '(..., 0-based; default: 0)'
    if found and "(" not in found.group(1):
        default, text = found.group(1), text[: found.start()]
    elif inner:
        default, text = inner.group(1), text[: inner.start()] + ")"
    return f"| {flags} | {_cell(default)} | {_cell(text)} |"


def options_table(command: str = "run") -> str:
    """The option table of ``stsdic COMMAND``, one row per option, grouped as ``--help``
    groups them (-h and --debug left out)."""
    from torch_stsdic.cli.app import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    cmd = sub.choices[command]
    formatter = cmd._get_formatter()
    lines = ["| option | default | meaning |", "|--------|---------|---------|"]
    for group in cmd._action_groups:
        rows = [_option_row(a, formatter) for a in group._group_actions
                if a.option_strings and a.help != argparse.SUPPRESS
                and a.dest not in ("help", "debug")]
        if rows:
            lines.append(f"| **{group.title}** | | |")
            lines += rows
    return "\n".join(lines) + "\n"


@functools.lru_cache(maxsize=1)
def run_summary() -> str:
    """The ``run-summary`` block: :data:`SUMMARY_COMMANDS` run now, their commands and what
    ``stsdic run`` prints."""
    import contextlib
    import io

    from torch_stsdic.cli import main

    cwd = Path.cwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                code = main(SUMMARY_COMMANDS[0])
            buf = io.StringIO()
            with contextlib.redirect_stdout(buf):
                code = code or main(SUMMARY_COMMANDS[1])
        finally:
            os.chdir(cwd)
    if code:
        raise SystemExit(f"run-summary: the commands failed (exit code {code})")
    shown = [" ".join(["$ stsdic", *c]) for c in SUMMARY_COMMANDS]
    body = [ln.rstrip() for ln in buf.getvalue().splitlines()]
    return "```\n" + "\n".join(shown[1:] + body) + "\n```\n"


def _summary_stable(block: str) -> list[str]:
    """The lines of a pasted run summary that do not depend on the machine (not 'time:',
    and the template's build time taken out of the 'reference:' line)."""
    return [re.sub(r"round\(s\) \([\d.]+ s\)", "round(s)", ln)
            for ln in block.strip().splitlines() if not ln.startswith("time:")]


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
            "running; `python scripts/tools/regenerate_docs.py` reran it and pasted this block).\n")
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
    series = [r for k, r in res.items() if k.startswith("STS-DIC, series ref")]
    if series:
        t = series[0]
        text += (f"; with the reference made from the series (the default of `stsdic run`, no "
                 f"still frames needed) it has {t['rms_u'] / c['rms_u']:.2f}x")
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


def stale_cli(text: str) -> list[str]:
    """What is out of date in docs/cli.md's CLI reference: the 'stsdic --help' block, the
    option table of 'stsdic run' and its summary example (time line excepted)."""
    problems = []
    i, j = _block(text, "help")
    if text[i:j] != help_text():
        problems.append("the 'stsdic --help' block differs from the program's output")
    i, j = _block(text, "run-options")
    if text[i:j] != options_table("run"):
        problems.append("the option table of 'stsdic run' differs from its parser")
    i, j = _block(text, "run-summary")
    if _summary_stable(text[i:j]) != _summary_stable(run_summary()):
        problems.append("the summary example of 'stsdic run' differs from a run now")
    return problems


def stale(text: str, demo: bool = True) -> list[str]:
    """What is out of date in docs/cli.md and the README: the CLI reference
    (:func:`stale_cli`), demo time and (with ``demo``, which runs it) the demo's output."""
    from torch_stsdic.cli.demo import DEMO_TIME

    problems = stale_cli(text)
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
    ap.add_argument("--cli", action="store_true", help="only the CLI reference blocks of "
                    "docs/cli.md (help, run options, run summary): no demo run")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    text = CLI_DOC.read_text(encoding="utf-8")
    if args.check:
        problems = stale_cli(text) if args.cli else stale(text)
        for p in problems:
            print(f"stale: {p}")
        return 1 if problems else 0
    text = replace_block(text, "help", help_text())
    text = replace_block(text, "run-options", options_table("run"))
    text = replace_block(text, "run-summary", run_summary())
    if args.cli:
        CLI_DOC.write_text(text, encoding="utf-8")
        print(f"rewrote the CLI reference blocks of {CLI_DOC}")
        return 0
    run = demo_run(ROOT / "docs" / "demo")
    text = replace_block(text, "demo", demo_text(run))
    CLI_DOC.write_text(text, encoding="utf-8")
    readme = README.read_text(encoding="utf-8")
    README.write_text(replace_block(readme, "demo-table", readme_text(run), README),
                      encoding="utf-8")
    print(f"rewrote the generated blocks of {CLI_DOC}, {README} and docs/demo/*.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
