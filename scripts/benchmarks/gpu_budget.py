#!/usr/bin/env python
"""Whether a run keeps to the memory budget it is given on a GPU: the same ``stsdic run``
without ``--memory-mb`` (a GPU's own budget: at least 2 GiB within a tenth of its memory)
and with each budget of ``--budgets``, in one process, the device's peak allocation and the
wall time of each, and whether their result files are the default's to the bit (u, v,
status; a smaller budget also makes shorter blocks, whose carried starts differ: not
expected the same).

    python scripts/benchmarks/gpu_budget.py --device cuda --out budget.json -- \\
        ../shared/data/mudic-hourglass --roi 150 20 1120 734 --subset 31 --step 20

On the CPU (``--device cpu``) the peaks are not measured (the script runs through, a dry run
of its steps); a run's first use (the CUDA context, the kernels' builds) is taken by a
warm-up run first."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_parts import HOURGLASS  # noqa: E402  (the documented region, one definition)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--budgets", type=float, nargs="+", default=[256.0, 1024.0],
                    help="MiB given with --memory-mb (besides the run without it)")
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("run_args", nargs="*", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    from torch_stsdic.cli.app import main as cli_main

    cuda = a.device.startswith("cuda")
    args = [*(a.run_args or HOURGLASS), "--device", a.device, "--no-progress", "--overwrite"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        def run(extra: list[str], name: str) -> dict:
            out = Path(tmp) / f"{name}.h5"
            if cuda:
                torch.cuda.synchronize()
                torch.cuda.reset_peak_memory_stats()
                base = torch.cuda.memory_allocated()
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                code = cli_main(["run", *args, *extra, "--out", str(out)])
            if cuda:
                torch.cuda.synchronize()
            rec = {"case": name, "exit": int(code or 0), "wall_s": time.perf_counter() - t0,
                   "peak_mb": ((torch.cuda.max_memory_allocated() - base) / 2**20 if cuda
                               else None), "file": str(out)}
            print(f"{name:>14}: exit {rec['exit']}, {rec['wall_s']:.2f} s, peak "
                  + (f"{rec['peak_mb']:.0f} MiB" if cuda else "n/a (cpu)"), flush=True)
            return rec

        run([], "warm-up")
        rows.append(run([], "default"))
        for mb in a.budgets:
            rows.append(run(["--memory-mb", f"{mb:g}"], f"{mb:g} MiB"))
        with h5py.File(rows[0]["file"], "r") as f:
            ref = {k: f[k][()] for k in ("u", "v", "status")}
        for r in rows[1:]:
            with h5py.File(r["file"], "r") as f:
                r["same_as_default"] = all(np.array_equal(f[k][()], v, equal_nan=True)
                                           for k, v in ref.items())
            same = "the same" if r["same_as_default"] else "differ"
            print(f"{r['case']:>14}: u, v, status {same} to the bit as the default's")
    for r in rows:
        r.pop("file")
    if a.out:
        a.out.write_text(json.dumps({"device": a.device, "args": args, "rows": rows}, indent=1))
        print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
