#!/usr/bin/env python
"""Where a fresh process's first CUDA run spends its time (``stsdic run --device cuda`` on the
benchmark pair took 4.9 s the first time in a process, 0.16-0.18 s the next times).

    python scripts/benchmarks/gpu_first_use.py     # on a GPU machine; prints one line per phase

Phases, each timed once in this order: importing torch_stsdic; the CUDA context; cuFFT's
first transform; the fused Triton step's first launch (the op registered with
``torch.library``), then its second; then the whole command twice. The first launch is
also profiled (the 15 largest cumulative entries from torch and Triton).
"""

from __future__ import annotations

import contextlib
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))


def main() -> None:
    t = time.perf_counter()

    def lap(what: str) -> None:
        nonlocal t
        now = time.perf_counter()
        print(f"{what:<44}{now - t:8.3f} s", flush=True)
        t = now

    import torch

    import torch_stsdic  # noqa: F401
    lap("import torch + torch_stsdic")
    torch.zeros(1, device="cuda")
    torch.cuda.synchronize()
    lap("CUDA context")
    torch.fft.rfft2(torch.rand(64, 64, device="cuda"))
    torch.cuda.synchronize()
    lap("cuFFT, first transform")
    from test_triton import _case, _rhs  # a small step problem (tests/test_triton.py)

    img, k, c = _case(True, torch.float32, device="cuda")
    lap("a small step problem on the GPU")
    prof = cProfile.Profile()
    prof.enable()
    _rhs(img, k, c, True, True)
    torch.cuda.synchronize()
    prof.disable()
    lap("fused Triton step, first launch")
    _rhs(img, k, c, True, True)
    torch.cuda.synchronize()
    lap("fused Triton step, second launch")
    import bench_cli

    from torch_stsdic.cli import main as cli

    d, pts, _ = bench_cli.ensure_data(0)
    for i in (1, 2):
        with contextlib.redirect_stdout(io.StringIO()):
            cli(["run", str(d), "--points", str(pts), "--subset", "21", "--m", "0", "--out",
                 "/tmp/first_use.h5", "--overwrite", "--no-progress", "--device", "cuda"])
        lap(f"stsdic run --device cuda, time {i}")
    out = io.StringIO()
    pstats.Stats(prof, stream=out).sort_stats("cumtime").print_stats(r"torch|triton", 15)
    print("\n".join(line[:150] for line in out.getvalue().splitlines() if line.strip()))


if __name__ == "__main__":
    main()
