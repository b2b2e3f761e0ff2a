#!/usr/bin/env python3
"""A run's device choices (``torch_stsdic.core.choices``) against each other: the same
``stsdic run`` in fresh processes with the choices as the device makes them and as named
(``TORCH_STSDIC_CHOICES``), in interleaved rounds; each variant's wall time, the run's own
time (its summary line) and whether its result file equals the default's to the bit.

    python scripts/benchmarks/device_choices.py --rounds 3 -- \\
        ../shared/data/mudic-hourglass --roi 150 20 1120 734 --subset 31 --step 20 --device cuda
    python scripts/benchmarks/device_choices.py --variants MASKED_GROUPS=1 \\
        "MASKED_GROUPS=1,EVERY_CANDIDATE=1,UNTIL_DONE=0" -- movie.tif   # a GPU's on the CPU

Default variants: the other device's choices, one at a time, then all of them (on a GPU the
CPU's, which read the host where a GPU run masks; on the CPU the GPU's). A GPU decides
what its choices cost in launches against what they save in reads (``count_syncs.py``
counts both on any device); this times it. Prints per round and the medians; ``--out``
writes a JSON record."""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts" / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts" / "tools"))
from compare_results import compare  # noqa: E402  (bit for bit, volatile attributes left out)
from cpu_criteria import timed_run  # noqa: E402  (one fresh stsdic run process, timed)

_TIME = re.compile(r"^time: ([0-9.]+) s", re.M)


def _run(args: list[str], out: Path, choices: str) -> tuple[float, float | None]:
    """Wall seconds of one ``stsdic run`` process with ``choices`` in the environment, and
    the run's own seconds from its summary line (None: not found)."""
    wall, stdout = timed_run(args, out, {"TORCH_STSDIC_CHOICES": choices},
                             label=f"{choices or 'default'}: ")
    m = _TIME.search(stdout)
    return wall, (float(m.group(1)) if m else None)


def default_variants(device: str) -> list[str]:
    """The other device's choices, one at a time, then all of them: on a GPU the CPU's
    (``gpu_choices`` flipped), on the CPU the GPU's."""
    sys.path.insert(0, str(ROOT))
    from torch_stsdic.core.choices import gpu_choices

    gpu = gpu_choices()
    other = [f"{k}={int(v if device == 'cpu' else not v)}" for k, v in gpu.items()]
    return [*other, ",".join(other)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=None, metavar="NAME=0|1,...",
                    help="TORCH_STSDIC_CHOICES of each variant (default: the other "
                         "device's choices, one at a time, then all)")
    ap.add_argument("--out", type=Path, default=None, help="JSON record")
    ap.add_argument("run_args", nargs="+", help="stsdic run's arguments (after --)")
    a = ap.parse_args(argv)
    run_args = [str(Path(x).resolve()) if not x.startswith("-") and Path(x).exists() else x
                for x in a.run_args]
    device = run_args[run_args.index("--device") + 1] if "--device" in run_args else "cpu"
    variants = ["", *(a.variants or default_variants(device))]
    rows: list[dict] = []
    identical: dict[str, bool] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(max(1, a.rounds)):
            row: dict = {"round": i + 1}
            for j, v in enumerate(variants):
                out = Path(tmp) / f"v{j}.h5"
                wall, own = _run(run_args, out, v)
                row[v or "default"] = {"wall_s": round(wall, 2), "run_s": own}
                if i == 0 and j:
                    identical[v] = not compare(Path(tmp) / "v0.h5", out)
            rows.append(row)
            print(f"round {i + 1}: " + "; ".join(
                f"{k} {r['wall_s']} s (run {r['run_s']} s)" for k, r in row.items()
                if k != "round"), flush=True)
    summary = {}
    for v in variants:
        k = v or "default"
        walls = [r[k]["wall_s"] for r in rows]
        runs = [r[k]["run_s"] for r in rows if r[k]["run_s"] is not None]
        summary[k] = {"wall_s": round(statistics.median(walls), 2),
                      "run_s": round(statistics.median(runs), 2) if runs else None,
                      "identical_to_default": identical.get(v, True)}
    print("\nmedians over the rounds (the run's own seconds; same file as the default's):")
    for k, s in summary.items():
        print(f"  {k:<60} {s['wall_s']:7.2f} s ({s['run_s']} s)  "
              f"{'same' if s['identical_to_default'] else 'DIFFERENT'}")
    if a.out:
        rec = {"command": "stsdic run " + " ".join(run_args), "device": device,
               "rounds": rows, "summary": summary,
               "commit": subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short",
                                         "HEAD"], capture_output=True, text=True).stdout.strip(),
               "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        a.out.write_text(json.dumps(rec, indent=1) + "\n")
        print(f"-> {a.out}")
    return 0 if all(s["identical_to_default"] for s in summary.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
