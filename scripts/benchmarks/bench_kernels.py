"""Per-sample cost of the solver's inner kernels: fused C++ (torch_stsdic.kernels.native) vs torch
on a CPU; fused Triton (torch_stsdic.kernels, ``--device cuda``) vs torch on a GPU.

Times, in ns per sample and per thread count, on a 1024x1024 float32 image with POIs on a
grid (the solver's access pattern): B-spline value sampling, value + gradient, and one joint
IC-GN right-hand side (warp + sample + ZNSSD + J^T e) for 1 and 5 frames. The torch rows run
the same functions the solver falls back to (eager; torch.compile is left out: minutes of
compile time). Writes docs/bench/kernels-cpu.json and prints a markdown table.

    python scripts/benchmarks/bench_kernels.py [--threads 1,2] [--out PATH]
    python scripts/benchmarks/bench_kernels.py --device cuda    # IC-GN step: Triton vs torch, ->
                                                     # docs/bench/kernels-cuda.json
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as torch_stsdic does, before torch loads
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # the checkout this script is in, not an installed torch_stsdic

import torch  # noqa: E402
from benchmark import _cpu_model  # noqa: E402  (scripts/benchmarks/benchmark.py, beside this file)

import torch_stsdic  # noqa: E402
from torch_stsdic import kernels  # noqa: E402
from torch_stsdic.core.formulations import ic_rhs_kernel  # noqa: E402
from torch_stsdic.core.interpolation import BSplineImage, sample_kernel  # noqa: E402
from torch_stsdic.core.shape import AffineShape  # noqa: E402
from torch_stsdic.kernels import native  # noqa: E402


def _median_time(fn, repeats: int, device: str = "cpu") -> float:
    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    fn()  # warm-up (and the Triton compile)
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _gpu_cases(n: int, device: str):
    """IC-GN step right-hand side on the GPU: the Triton op and the torch code."""
    out = []
    for t in (1, 5):
        c = {k: (v.to(device) if isinstance(v, torch.Tensor) else v)
             for k, v in _problem(n, t).items() if k != "img"}
        img = _problem(1, t)["img"].to(device=device)
        a = img.kernel_args()
        name = f"IC-GN step right-hand side, {t} frame{'s' if t > 1 else ''}"

        def fused(c=c, a=a, t=t):
            return kernels.ic_rhs(a, 3, c["p"], c["px"], c["py"], c["dx"], c["dy"], c["basis"],
                                  c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"],
                                  c["w"], 1024, 1024, c["k"], t > 1, True)

        def plain(c=c, a=a, t=t):
            return ic_rhs_kernel(a[0], c["p"], c["px"], c["py"], c["dx"], c["dy"],
                                 c["basis"].T.contiguous(), c["dt"], c["fidx"], c["ft"],
                                 c["fnorm"], c["gx"], c["gy"], c["w"], *a[1:7], 1024, 1024,
                                 c["basis"].shape[1], c["k"], t > 1, True, 3)

        if kernels.usable(a[0], 3, c["dx"].numel(), c["p"]):
            out.append((name, "triton", n * t * c["dx"].numel(), fused))
        out.append((name, "torch", n * t * c["dx"].numel(), plain))
    return out


def _problem(n: int, t: int, subset: int = 21):
    g = torch.Generator().manual_seed(0)
    img = BSplineImage(torch.rand(t, 1024, 1024, generator=g) * 255, 3)
    half = subset // 2
    d = torch.arange(-half, half + 1.0)
    dx, dy = d.repeat(subset), d.repeat_interleave(subset)
    side = int(n**0.5) + 1
    grid = torch.arange(side) * (900 // side) + 50.0
    yy, xx = torch.meshgrid(grid, grid, indexing="ij")
    px = xx.reshape(-1, 1)[:n] + 0.3
    py = yy.reshape(-1, 1)[:n] + 0.6
    shape = AffineShape(temporal=t > 1)
    k = shape.n_basis
    p = torch.randn(n, 2 * k, generator=g) * 0.01
    p[:, 0] += 1.3
    dtt = (torch.arange(t) - t // 2).float().expand(n, t).contiguous()
    fidx = (torch.arange(t) * img.kernel_args()[-1]).expand(n, t).contiguous()
    ft = torch.randn(n, dx.numel(), generator=g)
    ft = ft - ft.mean(1, keepdim=True)
    return dict(img=img, dx=dx, dy=dy, px=px, py=py, p=p, k=k, dt=dtt, fidx=fidx, ft=ft,
                fnorm=ft.norm(dim=1), gx=torch.randn_like(ft), gy=torch.randn_like(ft),
                w=torch.ones(dx.numel()), basis=shape.spatial_basis(dx, dy), t=t)


def _cases(n_native: int, n_torch: int):
    """(name, implementation, samples, callable) for every measured kernel."""
    out = []
    for impl, n in (("native", n_native), ("torch", n_torch)):
        if impl == "native" and not native.available():
            continue
        c = _problem(n, 1)
        a = c["img"].kernel_args()
        x = (c["px"] + c["dx"]).contiguous()
        y = (c["py"] + c["dy"]).contiguous()
        off = torch.zeros(n, 1, dtype=torch.long)
        for grad in (False, True):
            name = "B-spline value" + (" + gradient" if grad else "")
            if impl == "native":
                def fn(x=x, y=y, g=grad, a=a, off=off):
                    return native.sample(a, 3, x, y, off, g)
            else:
                def fn(x=x, y=y, g=grad, a=a, off=off):
                    return sample_kernel(a[0], x, y, off, *a[1:7], 3, g)
            out.append((name, impl, x.numel(), fn))
        for t in (1, 5):
            c = _problem(n, t)
            a = c["img"].kernel_args()
            name = f"IC-GN step right-hand side, {t} frame{'s' if t > 1 else ''}"
            if impl == "native":
                def fn(c=c, a=a, t=t):
                    return native.ic_rhs(a, 3, c["p"], c["px"], c["py"], c["dx"], c["dy"],
                                         c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"],
                                         c["gx"], c["gy"], c["w"], 1024, 1024, c["k"], t > 1,
                                         True)
            else:
                def fn(c=c, a=a, t=t):
                    return ic_rhs_kernel(a[0], c["p"], c["px"], c["py"], c["dx"], c["dy"],
                                          c["basis"].T.contiguous(), c["dt"], c["fidx"],
                                          c["ft"], c["fnorm"], c["gx"], c["gy"], c["w"],
                                          *a[1:7], 1024, 1024, c["basis"].shape[1], c["k"],
                                          t > 1, True, 3)
            out.append((name, impl, n * t * c["dx"].numel(), fn))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", default="1,2", help="comma list of torch thread counts")
    ap.add_argument("--points", type=int, default=10_000, help="POIs for the native kernels")
    ap.add_argument("--torch-points", type=int, default=1_000, help="POIs for the torch code")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (Triton vs torch)")
    ap.add_argument("--out", default=None,
                    help="JSON record (default docs/bench/kernels-<device>.json)")
    args = ap.parse_args(argv)
    dev = args.device
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available")
    args.out = args.out or str(REPO / "docs" / "bench" / f"kernels-{dev.split(':')[0]}.json")
    threads = [int(x) for x in args.threads.split(",")] if dev == "cpu" else [1]
    rows = []
    for th in threads:
        torch.set_num_threads(th)
        cases = (_cases(args.points, args.torch_points) if dev == "cpu"
                 else _gpu_cases(args.points * 10, dev))
        for name, impl, samples, fn in cases:
            sec = _median_time(fn, args.repeats, dev)
            rows.append({"kernel": name, "impl": impl, "threads": th, "samples": samples,
                         "median_s": sec, "ns_per_sample": sec / samples * 1e9})
            print(f"{th}t {impl:6s} {name}: {sec / samples * 1e9:.3g} ns/sample", flush=True)
    rec = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "arch": platform.machine(),
        "cpu": _cpu_model(),
        "torch": torch.__version__,
        "device": dev if dev == "cpu" else torch.cuda.get_device_name(),
        "command": " ".join(["python scripts/benchmarks/bench_kernels.py",
                             *(sys.argv[1:] if argv is None else argv)]),
        "package": str(Path(torch_stsdic.__file__).parent),
        "native_library": str(native.build()) if native.available() else None,
        "results": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rec, indent=1))
    print()
    print(table(rows))


def table(rows) -> str:
    """Markdown: kernel x (impl, threads) in ns per sample."""
    cols = sorted({(r["impl"], r["threads"]) for r in rows},
                  key=lambda c: (c[0] == "torch", c[1]))
    kernels = list(dict.fromkeys(r["kernel"] for r in rows))
    head = "| kernel | " + " | ".join(f"{i}, {t} thread{'s' if t > 1 else ''}" for i, t in cols)
    lines = [head + " |", "|---|" + "---:|" * len(cols)]
    for k in kernels:
        vals = []
        for i, t in cols:
            r = [x for x in rows if x["kernel"] == k and x["impl"] == i and x["threads"] == t]
            vals.append(f"{r[0]['ns_per_sample']:.3g}" if r else "-")
        lines.append(f"| {k} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
