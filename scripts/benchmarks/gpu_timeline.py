"""Where a long movie's time goes on a GPU: one warm run of the benchmark's TIFF movie
(``benchmark.py --movie``'s, STS(5), 10,000 POIs) under torch.profiler and cProfile.

    python scripts/benchmarks/gpu_timeline.py --frames 120 --out timeline.txt

Prints the wall time and frames/s of a first (cold) and a second (warm) run, then for the warm
run: the device's busy time (the sum of its kernels) against the wall (what the GPU waits for),
the host-device synchronisations (``aten::item`` / ``_local_scalar_dense``,
``cudaStreamSynchronize``,
device-to-host copies) per block, the top operators by host time, and the top Python functions
by cumulative time."""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import benchmark as bm  # noqa: E402
import torch  # noqa: E402


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def one_run(tiff: Path, n_points: int, device: str, batch_frames: int | None, out_h5: Path,
            single_reference: bool = False):
    import torch_stsdic as sts
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan
    from torch_stsdic.movie.sinks import open_sink

    size, subset = 1024, 21
    side = max(2, round(n_points ** 0.5))
    step = min(10, (size - 1 - 2 * (subset // 2 + 8)) // (side - 1))
    pts = bm.poi_grid(size, side, subset, step=step)
    cfg = sts.DICConfig(subset_size=subset, m=2, dtype="float32",
                        memory_mb=bm._cuda_budget_mb() if device.startswith("cuda") else 512.0)
    _sync(device)
    t0 = time.perf_counter()
    plan = plan_run(str(tiff), 0, None, pts, None, None, 10, cfg, device, None, batch_frames)
    if single_reference:  # the blocks' own work, without the template made from the series
        plan.options["single_reference"] = "asked for (--single-reference)"
    sink = open_sink(plan, out_h5, overwrite=True)
    res = run_plan(plan, sink, progress=False)
    _sync(device)
    wall = time.perf_counter() - t0
    return res, wall, len(plan.blocks)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--batch-frames", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("timeline.txt"))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--single-reference", action="store_true",
                    help="measure against frame 0 alone (the blocks' work without the template)")
    args = ap.parse_args()
    dev = args.device
    tiff = bm.movie_tiff_path(args.frames, 1024)
    if not tiff.exists():
        bm.write_tiff_movie(tiff, args.frames, 1024)
    h5 = Path("/tmp/timeline.h5")
    args.out.write_text("")

    def say(s=""):  # printed and written as it comes: a run stopped at its limit keeps it
        print(s, flush=True)
        with args.out.open("a") as fh:
            fh.write(s + "\n")

    case = (tiff, args.points, dev, args.batch_frames, h5, args.single_reference)
    res, wall, nb = one_run(*case)
    say(f"cold: {wall:.2f} s, {args.frames / wall:.1f} frames/s, {nb} blocks")
    res, wall, nb = one_run(*case)
    say(f"warm: {wall:.2f} s, {args.frames / wall:.1f} frames/s, {nb} blocks, "
        f"usable {float(res.ok.float().mean()):.4f}")
    from torch.profiler import ProfilerActivity, profile
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.startswith("cuda") else [])
    with profile(activities=acts) as prof:
        res, wall_p, nb = one_run(*case)
    ka = prof.key_averages()
    dev_us = sum(e.self_device_time_total for e in ka if e.device_type.name == "CUDA")
    say(f"profiled: {wall_p:.2f} s wall, device kernels {dev_us / 1e6:.2f} s "
        f"({dev_us / 1e6 / wall_p:.0%} of the wall)")
    for name in ("aten::item", "aten::_local_scalar_dense", "cudaStreamSynchronize",
                 "cudaDeviceSynchronize", "cudaMemcpyAsync", "aten::nonzero",
                 "cudaLaunchKernel", "aten::copy_", "aten::to"):
        ev = [e for e in ka if e.key == name]
        if ev:
            e = ev[0]
            say(f"  {name}: {e.count} calls ({e.count / nb:.0f} a block), host "
                f"{e.cpu_time_total / 1e6:.2f} s")
    say("\nby host time (self):")
    say(ka.table(sort_by="self_cpu_time_total", row_limit=30, max_name_column_width=60))
    say("\nby device time:")
    if dev.startswith("cuda"):
        say(ka.table(sort_by="self_cuda_time_total", row_limit=15, max_name_column_width=60))
    pr = cProfile.Profile()
    pr.enable()
    _, wall_c, _ = one_run(*case)
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(45)
    say(f"\ncProfile: {wall_c:.2f} s wall")
    say(s.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
