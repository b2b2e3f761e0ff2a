#!/usr/bin/env python3
"""Issue 45's CPU limits as a user meets them: a default ``stsdic run`` against the same
run with ``--m 0 --single-reference``, whole processes (imports and exit included), in
interleaved rounds, and the template's share of the default run.

    python scripts/benchmarks/cpu_criteria.py --rounds 7 --out docs/bench/cpu-criteria.json
    python scripts/benchmarks/cpu_criteria.py --rounds 5 --before c3aa9f9   # and that version
    python scripts/benchmarks/cpu_criteria.py -- ../shared/data/dic-challenge-sample12

Default case: the muDIC hourglass with its documented region. Each round runs (the
``--before`` revision's defaults, from a temporary worktree on ``PYTHONPATH``,) the defaults
and the classical run, each a fresh ``python -m torch_stsdic run`` process timed by the
wall clock; the template's seconds are read from the result file (its
``series_reference`` record, in ms; the summary line's "(X s)" where the file has none).
Prints per round and the medians: the ratio defaults / classical (per round, so a load
change hits both alike) and the template's share of the defaults' process; the limits are
3.0x and 15 %. On a shared VM the speed swings by 25 % between rounds minutes apart: read
the medians of several rounds."""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_parts import HOURGLASS  # noqa: E402  (the documented region, one definition)

ROOT = Path(__file__).resolve().parents[2]
LIMITS = {"ratio": 3.0, "template_share": 0.15}
_TEMPLATE = re.compile(r"round\(s\) \(([0-9.]+) s\)")


def timed_run(args: list[str], out: Path, env: dict[str, str] | None = None,
              label: str = "") -> tuple[float, str]:
    """Wall seconds and stdout of one fresh ``stsdic run`` process writing ``out`` (started
    in its folder), ``env`` added to the environment; a failed run stops the benchmark with
    its stderr (``label`` in front of the message)."""
    cmd = [sys.executable, "-m", "torch_stsdic", "run", *args, "--out", str(out),
           "--overwrite", "--no-progress"]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **(env or {})},
                       cwd=out.parent)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise SystemExit(f"{label}{' '.join(cmd)} failed ({p.returncode}):\n"
                         f"{p.stderr[-2000:]}")
    return wall, p.stdout


def _run(args: list[str], out: Path, tree: Path | None) -> tuple[float, float | None]:
    """Wall seconds of one ``stsdic run`` process and its template's seconds (None: none)."""
    wall, stdout = timed_run(args, out, None if tree is None else {"PYTHONPATH": str(tree)})
    m = _TEMPLATE.search(stdout)
    if m is None:
        return wall, None
    from torch_stsdic.io.results import read_results

    record = read_results(out, fields=[]).arrays.get("series_reference")
    seconds = None if record is None else record[1].get("seconds")
    return wall, float(m.group(1) if seconds is None else seconds)


def _short(rev: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev],
                          capture_output=True, text=True, check=True).stdout.strip()


def _summary(rows: list[dict], key: str) -> dict:
    vals = [r[key] for r in rows if r.get(key) is not None]
    if not vals:
        return {}
    # (4 decimals: a share's median is judged against its limit unrounded, 0.1503 > 0.15)
    return {"median": round(statistics.median(vals), 4), "min": round(min(vals), 4),
            "max": round(max(vals), 4)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--before", default=None, help="a git revision whose defaults run too")
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("run_args", nargs="*", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    # paths absolute: the runs start in a temporary folder (in the repository's, python -m
    # would import the working tree's package instead of the --before version's)
    run_args = [str(Path(x).resolve()) if not x.startswith("-") and Path(x).exists() else x
                for x in (a.run_args or HOURGLASS)]
    versions = {"defaults": (run_args, None), "classical": (
        [*run_args, "--m", "0", "--single-reference"], None)}
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        tree = None
        if a.before:
            tree = Path(tmp) / "before"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach",
                            str(tree), a.before], check=True)
            versions = {"before": (run_args, tree), **versions}
        try:
            for i in range(max(1, a.rounds)):
                row: dict = {"round": i + 1}
                for name, (args, where) in versions.items():
                    wall, tmpl = _run(args, Path(tmp) / f"{name}.h5", where)
                    row[f"{name}_s"] = round(wall, 2)
                    if name != "classical" and tmpl is not None:
                        row[f"{name}_template_s"] = tmpl
                        row[f"{name}_template_share"] = round(tmpl / wall, 4)
                for name in ("defaults", "before"):
                    if f"{name}_s" in row:
                        row[f"{name}_ratio"] = round(row[f"{name}_s"] / row["classical_s"], 3)
                rows.append(row)
                print(" ".join(f"{k} {v}" for k, v in row.items()), flush=True)
        finally:
            if tree is not None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                                str(tree)], check=False)
    keys = [k for k in rows[0] if k != "round"]
    summary = {k: _summary(rows, k) for k in keys}
    print("\nmedian (min-max) over the rounds:")
    for k, s in summary.items():
        if s:
            print(f"  {k:<28} {s['median']:8.3f} ({s['min']:.3f}-{s['max']:.3f})")
    ratio = summary.get("defaults_ratio", {}).get("median")
    share = summary.get("defaults_template_share", {}).get("median")
    print(f"limits: ratio <= {LIMITS['ratio']}x: {ratio}x "
          f"({'met' if ratio is not None and ratio <= LIMITS['ratio'] else 'not met'}); "
          f"template <= {LIMITS['template_share']:.0%}: "
          f"{'-' if share is None else f'{share:.2%}'} "
          f"({'met' if share is not None and share <= LIMITS['template_share'] else 'not met'})")
    if a.out:
        cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text(
        ).splitlines() if ln.startswith("model name")), platform.processor()) \
            if Path("/proc/cpuinfo").exists() else platform.processor()
        rec = {"command": "stsdic run " + " ".join(run_args), "rounds": rows,
               "summary": summary, "limits": LIMITS, "commit": _short("HEAD"),
               "before": _short(a.before) if a.before else None, "cpu": cpu,
               "cores": os.cpu_count(), "load_average_after": [round(x, 2)
                                                               for x in os.getloadavg()],
               "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        a.out.write_text(json.dumps(rec, indent=1) + "\n")
        print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
