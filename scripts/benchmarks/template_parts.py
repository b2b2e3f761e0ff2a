"""Where the reference made from the series spends its time: one build of the template
(``movie/series_reference.py``) on the benchmark's TIFF movie, every stage timed.

    python scripts/benchmarks/template_parts.py --frames 60 --points 2500 [--device cuda]

Prints the total and the seconds of each stage (the classical rounds, the frames' noise, the
local fits and their tests, the splats into the template, the gauge). The GPU runs only the
classical rounds and the gauge on the device; the rest is host work."""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import benchmark as bm  # noqa: E402
import torch  # noqa: E402

STAGES = ("_measure", "_frame_noise", "local_fit_weights", "time_model_holds", "_fit_choice",
          "_smooth", "template_image", "_gauge")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--points", type=int, default=2500)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=2, help="builds; the last one is reported")
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    args = ap.parse_args()
    import torch_stsdic as sts
    from torch_stsdic.movie import series_reference as sr
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series import run_plan

    tiff = bm.movie_tiff_path(args.frames, 1024)
    if not tiff.exists():
        bm.write_tiff_movie(tiff, args.frames, 1024)
    pts = bm.poi_grid(1024, round(args.points ** 0.5), 21, step=10)
    cfg = sts.DICConfig(subset_size=21, m=2, dtype="float32")
    spent: dict[str, float] = {}

    def timed(name):
        fn = getattr(sr, name)

        @functools.wraps(fn)
        def run(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                spent[name] = spent.get(name, 0.0) + time.perf_counter() - t0
        setattr(sr, name, run)

    for name in STAGES:
        timed(name)
    for _ in range(max(1, args.repeats)):
        spent.clear()
        plan = plan_run(str(tiff), 0, None, pts, None, None, 10, cfg, args.device, None, None)
        sr.set_series_reference(plan, "auto")
        ref = plan.series.get(0, dtype=torch.float64)
        t0 = time.perf_counter()
        tpl = sr.build_series_reference(plan, ref, run=run_plan)
        total = time.perf_counter() - t0
    rec = {"frames": args.frames, "points": int(pts.shape[0]), "device": args.device,
           "threads": torch.get_num_threads(), "total_s": round(total, 3),
           "stages_s": {k: round(v, 3) for k, v in spent.items()},
           "template_frames": len(tpl.frames), "noise_ratio": tpl.noise_ratio}
    print(json.dumps(rec))
    if args.out:
        args.out.write_text(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
