"""Scaling of ``stsdic run --workers``: the hourglass with one process, then 1 and 2 Dask worker
processes at several chunk sizes, each run's wall time with the load average around it, and
the overhead per chunk (to size ``--chunk-frames``); each distributed file compared with the
one-process file (docs/bench/distributed-cpu.json, docs/benchmarks.md "Beyond one machine").

    python scripts/benchmarks/bench_distributed.py [--out docs/bench/distributed-cpu.json]

Needs ``../shared/data/mudic-hourglass`` and Dask distributed."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from torch_stsdic.movie.distributed import chunk_plan  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "mudic-hourglass"
CASE = ["--subset", "31", "--step", "20", "--roi", "150", "20", "1120", "734", "--m", "2"]
#: (workers, chunk frames); None: one process, no Dask
RUNS: list[tuple[int | None, int | None]] = [(None, None), (1, 40), (1, 10), (2, 20), (2, 10)]


def run(out: Path, workers: int | None, chunk: int | None) -> dict[str, Any]:
    extra = [] if workers is None else ["--workers", str(workers), "--chunk-frames", str(chunk)]
    load0 = os.getloadavg()
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "torch_stsdic", "run", str(DATA), *CASE,
                           *extra, "--out", str(out), "--overwrite", "--no-progress"],
                          capture_output=True, text=True, cwd=REPO, check=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - t
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("time:"))
    with h5py.File(out, "r") as f:
        frames = int(f["completed"].shape[0])
        batch = int(json.loads(f.attrs["config"])["track"]["batch_frames"])
        attrs = f["shared_motion"].attrs if "shared_motion" in f else {}
        pass_s = float(attrs["seconds"]) if "seconds" in attrs else None
    return {"workers": workers, "chunk_frames": chunk, "wall_s": round(wall, 2),
            "summary_time_line": line, "frames": frames,
            "shared_pass_s": None if pass_s is None else round(pass_s, 2),
            "batch_frames": batch, "chunks": None if chunk is None else len(chunk_plan(
                range(frames), chunk, frames, 2, blocks=_blocks(frames, batch))),
            "load_average_before": [round(x, 2) for x in load0],
            "load_average_after": [round(x, 2) for x in os.getloadavg()]}


def _blocks(frames: int, batch: int) -> list[list[int]]:
    """The run's blocks of targets: the first alone, then ``batch`` at a time."""
    return [[0]] + [list(range(i, min(i + batch, frames))) for i in range(1, frames, batch)]


def compare(one: Path, other: Path) -> dict[str, float]:
    with h5py.File(one, "r") as a, h5py.File(other, "r") as b:
        sa, sb = a["status"][()], b["status"][()]
        ok = (sa <= 1) & (sb <= 1)
        du = np.abs(a["u"][()] - b["u"][()])[ok]
        dv = np.abs(a["v"][()] - b["v"][()])[ok]
        return {"max_du_px": float(du.max()), "max_dv_px": float(dv.max()),
                "within_2e-3": float(((du <= 2e-3) & (dv <= 2e-3)).mean()),
                "statuses_equal": float((sa == sb).mean()),
                "windows_equal": float((a["m"][()] == b["m"][()]).mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "bench" / "distributed-cpu.json")
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"{DATA} not found")
    sys.path.insert(0, str(REPO / "scripts" / "benchmarks"))
    import benchmark as bench

    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for workers, chunk in RUNS:
            out = Path(tmp) / f"w{workers}-c{chunk}.h5"
            rec = run(out, workers, chunk)
            if files:
                rec["vs_one_process"] = compare(files[0], out)
            files.append(out)
            runs.append(rec)
            print(json.dumps(rec), flush=True)
    by = {(r["workers"], r["chunk_frames"]): r["wall_s"] for r in runs}
    chunks = {(r["workers"], r["chunk_frames"]): r["chunks"] for r in runs}
    derived = {
        "dask_start_and_one_chunk_s": round(by[(1, 40)] - by[(None, None)], 2),
        "overhead_per_chunk_s": round((by[(1, 10)] - by[(1, 40)]) / (chunks[(1, 10)] - 1), 2),
        "speedup_2_workers_chunks_20": round(by[(None, None)] / by[(2, 20)], 3),
        "speedup_2_workers_chunks_10": round(by[(None, None)] / by[(2, 10)], 3),
    }
    rec = {"what": "issue 37: stsdic run --workers on the hourglass (40 frames), wall time "
                   "per run (process start, Dask cluster, measuring pass, chunks, strains)",
           "command": "python3 scripts/benchmarks/bench_distributed.py",
           "case": ["mudic-hourglass", *CASE],
           "date": time.strftime("%Y-%m-%d %H:%M"),
           "machine": bench.machine_info([os.cpu_count() or 1], "cpu"),
           "derived": derived, "runs": runs}
    args.out.write_text(json.dumps(rec, indent=1) + "\n")
    print(json.dumps(derived))


if __name__ == "__main__":
    main()
