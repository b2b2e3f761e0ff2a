#!/usr/bin/env python
"""Where a ``stsdic run`` spends its time: every pass of the run (the shared-motion pass, the
template's rounds, the time-model pass, the blocks, the strains, writing) split into kinds of
work (preparing images, initial guesses, Gauss-Newton, checks, the rest of the pass).

    python scripts/benchmarks/run_parts.py                        # the hourglass, defaults
    python scripts/benchmarks/run_parts.py --baseline             # and --m 0 --single-reference
    python scripts/benchmarks/run_parts.py --out docs/bench/parts-hourglass-cpu.json -- \\
        ../shared/data/mudic-hourglass --roi 150 20 1120 734 --subset 31 --step 20

Arguments after ``--`` are ``stsdic run``'s (default: the muDIC hourglass with its documented
region, windows chosen per point: ``--m M`` for a fixed one). Each case runs in a fresh
process (``--repeats`` times, interleaved with the baseline; medians reported): the whole
process's wall time (imports included), and inside it the
seconds of each (pass, kind), every second counted once, in the innermost kind it was spent
in (a Gauss-Newton solve inside an initial guess counts as Gauss-Newton). On CUDA the device
is synchronised at every boundary, which slows the run down: use it for shares, not speed.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
HOURGLASS = [str(REPO.parent / "shared/data/mudic-hourglass"), "--roi", "150", "20", "1120",
             "734", "--subset", "31", "--step", "20"]


def split_run_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """A counting script's own arguments and ``stsdic run``'s (after ``--``; default the
    hourglass with its documented region, :data:`HOURGLASS`)."""
    if "--" in argv:
        return argv[:argv.index("--")], argv[argv.index("--") + 1:]
    return list(argv), list(HOURGLASS)


TAG = "RUN_PARTS "

#: (module, function, role): a role "pass:NAME" opens a pass, a role "kind:NAME" a kind
PROBES = [
    ("torch_stsdic.movie.shared_pass", "estimate_shared_motion", "pass:shared motion"),
    ("torch_stsdic.movie.series_reference", "build_series_reference", "pass:template"),
    ("torch_stsdic.movie.series_reference", "measure_time_model", "pass:time model"),
    ("torch_stsdic.movie.window_length", "measure_window_lengths", "pass:window lengths"),
    ("torch_stsdic.movie.refine", "measure_trajectory_gauge", "pass:trajectory gauge"),
    ("torch_stsdic.movie.sinks", "HDF5Sink.finish", "pass:strains + writing"),
    ("torch_stsdic.io.images", "ImageSeries.get", "kind:preparing images"),
    ("torch_stsdic.core.solver", "SubsetSolver.prepare", "kind:preparing images"),
    ("torch_stsdic.core.pyramid", "ImagePyramid.level", "kind:preparing images"),
    ("torch_stsdic.core.noise", "estimate_noise_sigma", "kind:preparing images"),
    ("torch_stsdic.core.solver", "SubsetSolver.initial_guess", "kind:initial guesses"),
    ("torch_stsdic.core.gauss_newton", "solve_batch", "kind:Gauss-Newton"),
    ("torch_stsdic.movie.checks", "BlockChecks.check_model", "kind:checks"),
    ("torch_stsdic.movie.checks", "BlockChecks.check_neighbours", "kind:checks"),
    ("torch_stsdic.movie.checks", "BlockChecks.rescue_classical", "kind:checks"),
    ("torch_stsdic.analysis.strain", "compute_strain", "kind:strains"),
]


def _probe() -> None:
    """In the child: wrap the probes, run the command, print the table as JSON."""
    import importlib

    import torch

    cuda = "--device" in sys.argv and "cuda" in " ".join(sys.argv)
    spent: dict[str, float] = {}
    state = {"pass": "blocks", "kind": "other"}

    def now() -> float:
        if cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def add(t: float) -> None:
        key = f"{state['pass']} | {state['kind']}"
        spent[key] = spent.get(key, 0.0) + t

    clock = [now()]

    def wrap(fn, role: str):
        what, name = role.split(":", 1)

        @functools.wraps(fn)
        def run(*a, **kw):
            if threading.current_thread() is not threading.main_thread():
                return fn(*a, **kw)  # read-ahead: overlapped, not on the run's path
            t = now()
            add(t - clock[0])
            clock[0] = t
            saved = dict(state)
            state[what] = name
            try:
                return fn(*a, **kw)
            finally:
                t = now()
                add(t - clock[0])
                clock[0] = t
                state.update(saved)
        return run

    import threading

    for mod, qual, role in PROBES:
        try:
            m = importlib.import_module(mod)
        except ImportError:
            continue
        owner, attr = m, qual
        if "." in qual:
            cls, attr = qual.split(".")
            owner = getattr(m, cls, None)
        if owner is None or not hasattr(owner, attr):
            continue
        setattr(owner, attr, wrap(getattr(owner, attr), role))
        # modules that imported the function by name get the wrapped one too
        for other in list(sys.modules.values()):
            if (other is not None and getattr(other, "__name__", "").startswith("torch_stsdic")
                    and "." not in qual and getattr(other, attr, None) is not None
                    and getattr(getattr(other, attr), "__wrapped__", None) is None
                    and getattr(other, attr) is getattr(m, attr).__wrapped__):
                setattr(other, attr, getattr(m, attr))

    from torch_stsdic.cli.app import main as cli_main

    t0 = time.perf_counter()
    rc = cli_main(["run", *sys.argv[2:]])
    t = now()
    add(t - clock[0])
    print(TAG + json.dumps({"rc": rc, "command_s": time.perf_counter() - t0,
                            "parts_s": spent}), flush=True)


def _case(args: list[str], out_dir: Path) -> dict:
    out = out_dir / "r.h5"
    cmd = [sys.executable, __file__, "--child", *args, "--out", str(out), "--overwrite"]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    line = [ln for ln in p.stdout.splitlines() if ln.startswith(TAG)]
    if p.returncode != 0 or not line:
        raise SystemExit(f"run failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
    rec = json.loads(line[-1][len(TAG):])
    if rec.get("rc"):  # the command failed (its error caught): no time to record
        raise SystemExit(f"stsdic run failed (rc {rec['rc']}):\n{p.stdout[-2000:]}\n"
                         f"{p.stderr[-3000:]}")
    rec["process_s"] = wall
    return rec


def _median_parts(recs: list[dict]) -> dict[str, float]:
    keys = sorted({k for r in recs for k in r["parts_s"]})
    return {k: round(statistics.median(r["parts_s"].get(k, 0.0) for r in recs), 3)
            for k in keys}


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _probe()
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--baseline", action="store_true",
                    help="also run the same with --m 0 --single-reference (interleaved)")
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("run_args", nargs="*", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    run_args = a.run_args or HOURGLASS
    cases = {"defaults": run_args}
    if a.baseline:
        cases["--m 0 --single-reference"] = [*run_args, "--m", "0", "--single-reference"]
    recs: dict[str, list[dict]] = {k: [] for k in cases}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(max(1, a.repeats)):
            for name, args in cases.items():
                recs[name].append(_case(args, Path(tmp)))
    import torch

    load = os.getloadavg()
    report = {"command": "stsdic run " + " ".join(run_args), "threads": torch.get_num_threads(),
              "load_average_after": [round(x, 2) for x in load], "repeats": a.repeats,
              "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                                       capture_output=True, text=True).stdout.strip(),
              "cases": {}}
    for name, rs in recs.items():
        parts = _median_parts(rs)
        report["cases"][name] = {
            "process_s": round(statistics.median(r["process_s"] for r in rs), 2),
            "process_s_all": [round(r["process_s"], 2) for r in rs],
            "command_s": round(statistics.median(r["command_s"] for r in rs), 2),
            "parts_s": parts}
        print(f"\n{name}: process {report['cases'][name]['process_s']:.1f} s "
              f"(all: {report['cases'][name]['process_s_all']}), command "
              f"{report['cases'][name]['command_s']:.1f} s")
        by_pass: dict[str, float] = {}
        for k, v in parts.items():
            by_pass[k.split(" | ")[0]] = by_pass.get(k.split(" | ")[0], 0.0) + v
        total = sum(parts.values()) or 1.0
        for k, v in sorted(parts.items(), key=lambda kv: -kv[1]):
            if v >= 0.005 * total:
                print(f"  {k:<45} {v:7.2f} s  {100 * v / total:5.1f} %")
        print("  by pass: " + ", ".join(f"{k} {v:.1f} s ({100 * v / total:.0f} %)"
                                        for k, v in sorted(by_pass.items(), key=lambda kv: -kv[1])))
    if a.baseline:
        r = (report["cases"]["defaults"]["process_s"]
             / report["cases"]["--m 0 --single-reference"]["process_s"])
        report["defaults_over_baseline"] = round(r, 2)
        print(f"\ndefaults / (--m 0 --single-reference): {r:.2f}x (whole processes)")
    if a.out:
        a.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
