"""Interrupt ``stsdic run`` on a real image folder at random moments, resume, compare.

Campaign of issue 13: an uninterrupted reference run, then ``--sigint`` runs stopped by
SIGINT and ``--sigkill`` runs killed by SIGKILL, each at a moment drawn uniformly over the
reference run's duration (start-up included), while another process keeps a CPU busy (a run
that finishes before its moment is recorded apart and the moment drawn again). Each
stopped run is continued with ``--resume`` and its u, v and status are compared with the
reference (bit for bit). Recorded per try: the signal, the moment, the exit code, whether
stderr held a traceback, the message line, the resume's exit code, identical or not.

    python scripts/tools/interrupt_resume.py ../shared/data/dic-challenge-sample12 \\
        --sigint 12 --sigkill 2 --work /tmp/ir --record docs/faults/interrupt_resume.json \
        [-- more 'stsdic run' options]

Exit code 0 when every try passed (never 134/139, never a traceback, resume identical).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _cmd(folder: Path, out: Path, extra: list[str]) -> list[str]:
    return [sys.executable, "-m", "stsdic_launcher", "run", str(folder), "--out", str(out),
            "--no-progress", *extra]


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _fields(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in ("u", "v", "status", "completed")}


def _same(a: Path, b: Path) -> bool:
    fa, fb = _fields(a), _fields(b)
    return bool(fa["completed"].all() and fb["completed"].all() and all(
        np.array_equal(fa[k], fb[k], equal_nan=True) for k in ("u", "v", "status")))


def _run(cmd: list[str], sig: int | None = None, at: float = 0.0) -> dict:
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    if sig is not None:
        try:
            p.wait(timeout=at)
        except subprocess.TimeoutExpired:
            p.send_signal(sig)
    out, err = p.communicate()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    return {"exit": p.returncode, "seconds": round(time.monotonic() - t0, 2),
            "traceback": "Traceback" in err, "stderr_lines": len(lines),
            "message": lines[-1] if lines else "", "stdout_tail": out.splitlines()[-4:]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--sigint", type=int, default=12)
    ap.add_argument("--sigkill", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=Path("interrupt_resume_work"))
    ap.add_argument("--record", type=Path, default=None, help="write the results (JSON)")
    ap.add_argument("--no-load", action="store_true", help="no CPU-loading process")
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:cut])
    extra = argv[cut + 1:]  # options for 'stsdic run', after '--'
    if not args.folder.is_dir():
        print(f"no folder {args.folder}", file=sys.stderr)
        return 2
    args.work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    load = None if args.no_load else subprocess.Popen(
        [sys.executable, "-c", "while True: pass"])
    try:
        ref = args.work / "reference.h5"
        ref.unlink(missing_ok=True)
        base = _run(_cmd(args.folder, ref, extra))
        if base["exit"] != 0:
            print(f"reference run failed: {base}", file=sys.stderr)
            return 1
        duration = base["seconds"]
        print(f"reference run: {duration:.1f} s; {base['stdout_tail']}", flush=True)
        sigs = [signal.SIGINT] * args.sigint + [signal.SIGKILL] * args.sigkill
        rng.shuffle(sigs)
        tries = []
        late = []  # runs that finished before their signal: drawn again, listed apart
        for k, sig in enumerate(sigs):
            out = args.work / f"try{k:02d}.h5"
            while True:
                for p in (out, out.with_name(out.name + ".partial")):
                    p.unlink(missing_ok=True)
                at = rng.uniform(0.0, duration)
                stop = _run(_cmd(args.folder, out, extra), sig, at)
                if stop["exit"] != 0:
                    break
                late.append({"signal": signal.Signals(sig).name, "at_s": round(at, 2),
                             "seconds": stop["seconds"],
                             "identical": _same(out, ref) if out.exists() else False})
                print(f"finished before the signal at {at:.1f} s: drawn again", flush=True)
            done = int(_fields(out)["completed"].sum()) if out.exists() else 0
            resume = _run(_cmd(args.folder, out, [*extra, "--resume"]))
            same = resume["exit"] == 0 and _same(out, ref)
            row = {"try": k, "signal": signal.Signals(sig).name, "at_s": round(at, 2),
                   "exit": stop["exit"], "traceback": stop["traceback"],
                   "stderr_lines": stop["stderr_lines"], "message": stop["message"],
                   "frames_kept": done, "resume_exit": resume["exit"],
                   "resume_traceback": resume["traceback"], "identical": same}
            row["ok"] = (same and not stop["traceback"] and not resume["traceback"]
                         and stop["exit"] not in (134, 139, -6, -11))
            tries.append(row)
            print(json.dumps(row), flush=True)
    finally:
        if load is not None:
            load.kill()
            load.wait()
    ok = all(t["ok"] for t in tries)
    summary = {"folder": str(args.folder), "run_args": extra, "reference_seconds": duration,
               "cpu_load": not args.no_load, "seed": args.seed, "tries": tries,
               "finished_before_signal": late,
               "all_ok": ok,
               "exit_codes": sorted({t["exit"] for t in tries}),
               "identical": sum(t["identical"] for t in tries)}
    print(f"{len(tries)} tries, exit codes {summary['exit_codes']}, identical after resume: "
          f"{summary['identical']}/{len(tries)}, all ok: {ok}")
    if args.record:
        args.record.parent.mkdir(parents=True, exist_ok=True)
        args.record.write_text(json.dumps(summary, indent=1) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
