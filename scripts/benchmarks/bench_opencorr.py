#!/usr/bin/env python
"""OpenCorr (C++) next to ``stsdic run`` and the bare solver, on the same 1024x1024 pair.

    python scripts/benchmarks/bench_opencorr.py  # -> docs/bench/opencorr-cpu.json, prints a table
    python scripts/benchmarks/bench_opencorr.py --repeats 5 --threads 1 --out /tmp/oc.json

The data are ``scripts/benchmarks/bench_cli.py``'s (``ensure_data(0)``): the solver benchmark's
reference and its frame at t = 5 (u = 2.05, v = -0.20 px), 38,809 POIs (197 x 197, 5 px
apart), subset 21 (OpenCorr: subset radius 10), classical DIC. OpenCorr reads the same images as
8-bit PGM files.

Cases, each one fresh process per repetition (peak RSS from ``wait4``), interleaved round by
round so that the machine's load hits every case alike:

- ``opencorr``: the harness ``scripts/opencorr/bench_fftcc_icgn1.cpp`` built against OpenCorr
  (``scripts/opencorr/build.sh``): FFT-CC at every POI, then ``ICGN2D1::prepare`` (gradients
  and the bicubic B-spline table), then first-order IC-GN at every POI (max 10 iterations,
  0.001 criterion), timed inside the process by stage; one repetition per process.
  Its POI/s is given two ways: N / (fftcc + icgn) and N / (fftcc + prep + icgn);
- ``bare``: ``bench_cli.py``'s bare solver (prefilter + ``SubsetSolver.solve``), ``time_s``;
- ``cli``: ``stsdic run DIR --points poi.csv --subset 21 --m 0`` with the checks, its
  ``command_s`` (the command's own time, after Python's imports);
- ``cli --no-checks``: the same without the trust checks.

Correctness is checked too: the median u, v of OpenCorr's valid POIs (its result CSV), of the
bare solver and of the ``stsdic run`` result file, against the movie's u = 2.05, v = -0.20 px.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts" / "benchmarks"))

import bench_cli as bc  # noqa: E402  (the pair, the children, run_child)

bench = bc.bench
OC_DIR = REPO / "scripts" / "opencorr"
DEFAULT_BIN = "/tmp/opencorr/build/bench_native"
N_POINTS = 38_809
TRUTH = {"u": round(bench.MOTION["u0"] + bench.MOTION["ut"] * bench.CENTRE_T, 6),
         "v": round(bench.MOTION["v0"] + bench.MOTION["vt"] * bench.CENTRE_T, 6)}
TOL_PX = 0.02  # |median - truth| allowed for the correctness check
RE_MEDIAN = re.compile(r"MEDIAN threads=(\d+) fftcc=([\d.]+) prep=([\d.]+) icgn=([\d.]+) "
                       r"total=([\d.]+)")
RE_FLAGGED = re.compile(r"flagged \(zncc<0\): (\d+), of which not converged \(-4\): (\d+), "
                        r"mean iterations: ([\d.]+)")
RE_OMP = re.compile(r"omp_get_max_threads=(\d+)")


def _sha1(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


def ensure_pgm(folder: Path) -> tuple[Path, Path]:
    """img000.pgm, img001.pgm (8-bit binary PGM) of bench_cli's TIFF pair, written once."""
    import numpy as np
    from PIL import Image

    out = bench.cache_dir() / f"opencorr_pgm_m0_v{bench.MOVIE_VERSION}"
    out.mkdir(exist_ok=True)
    paths = []
    for name in ("img000", "img001"):
        pgm = out / f"{name}.pgm"
        if not pgm.exists():
            a = np.asarray(Image.open(folder / f"{name}.tif"))
            assert a.dtype == np.uint8 and a.ndim == 2, (a.dtype, a.shape)
            tmp = pgm.with_suffix(f".tmp{os.getpid()}")
            tmp.write_bytes(b"P5\n%d %d\n255\n" % (a.shape[1], a.shape[0]) + a.tobytes())
            os.replace(tmp, pgm)
        paths.append(pgm)
    return paths[0], paths[1]


def build_flags() -> dict[str, str]:
    """The compiler flags of each variant, as scripts/opencorr/build.sh builds them."""
    text = (OC_DIR / "build.sh").read_text()
    return {m.group(1): m.group(2).strip()
            for m in re.finditer(r"^build\s+(\S+)\s+(.+)$", text, re.MULTILINE)}


def linked_fftw(binary: Path) -> list[str]:
    try:
        out = subprocess.run(["ldd", str(binary)], capture_output=True, text=True).stdout
    except OSError:
        return []
    return [ln.strip() for ln in out.splitlines() if "fftw" in ln or "gomp" in ln]


def read_opencorr_csv(path: Path) -> dict[str, Any]:
    import numpy as np

    d = np.genfromtxt(path, delimiter=",", names=True)
    ok = d["zncc"] >= 0
    return {"n_points": int(len(d)), "n_valid": int(ok.sum()),
            "u": float(np.median(d["u"][ok])), "v": float(np.median(d["v"][ok])),
            "u_rms_from_median": float(np.sqrt(np.mean((d["u"][ok] - np.median(d["u"][ok]))
                                                       ** 2))),
            "v_rms_from_median": float(np.sqrt(np.mean((d["v"][ok] - np.median(d["v"][ok]))
                                                       ** 2))),
            "median_zncc": float(np.median(d["zncc"][ok]))}


def run_opencorr(binary: Path, ref: Path, tar: Path, pts_csv: Path, threads: int,
                 out_csv: Path) -> dict[str, Any]:
    """One fresh OpenCorr process, one repetition; its stage times, RSS and result."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    out_csv.unlink(missing_ok=True)
    cmd = [str(binary), str(ref), str(tar), str(pts_csv), str(threads), "1", str(out_csv), "10"]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    out, err = p.stdout.read(), p.stderr.read()
    code = os.waitstatus_to_exitcode(status)
    m = RE_MEDIAN.search(out)
    if code != 0 or m is None:
        raise RuntimeError(f"OpenCorr run failed ({code}): {' '.join(cmd)}\n{out[-2000:]}\n"
                           f"{err[-2000:]}")
    fftcc, prep, icgn, total = (float(g) for g in m.groups()[1:])
    rec: dict[str, Any] = {
        "threads": int(m.group(1)), "fftcc_s": fftcc, "prep_s": prep, "icgn_s": icgn,
        "total_s": total, "fftcc_icgn_s": fftcc + icgn,
        "poi_per_s_fftcc_icgn": N_POINTS / (fftcc + icgn), "poi_per_s_total": N_POINTS / total,
        "process_wall_s": wall, "max_rss_mb": usage.ru_maxrss / 1024.0,
    }
    if (mo := RE_OMP.search(out)) is not None:
        rec["omp_get_max_threads"] = int(mo.group(1))
    if (mf := RE_FLAGGED.search(out)) is not None:
        rec.update(flagged=int(mf.group(1)), not_converged=int(mf.group(2)),
                   mean_iterations=float(mf.group(3)))
    rec.update(read_opencorr_csv(out_csv))
    return rec


def cli_result_uv(path: Path) -> dict[str, Any]:
    """Median u, v of frame 1 in a ``stsdic run`` result file."""
    import numpy as np

    from torch_stsdic.io.results import read_results

    try:
        res = read_results(path, fields=["u", "v"])
        row = res.row_of(1)
        u, v = res.fields["u"][row], res.fields["v"][row]
        ok = np.isfinite(u) & np.isfinite(v)
        return {"u": float(np.median(u[ok])), "v": float(np.median(v[ok])),
                "n_valid": int(ok.sum())}
    except Exception as exc:  # recorded, not fatal: the timing still counts
        return {"result_error": f"{type(exc).__name__}: {exc}"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--opencorr-bin", default=DEFAULT_BIN,
                    help=f"the built harness (default {DEFAULT_BIN})")
    ap.add_argument("--out", default=None,
                    help="JSON record (default docs/bench/opencorr-cpu.json)")
    args = ap.parse_args()
    binary = Path(args.opencorr_bin).resolve()
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        sys.exit(f"OpenCorr harness not found at {binary}: build it with "
                 f"scripts/opencorr/build.sh (see scripts/opencorr/README.md) or pass "
                 f"--opencorr-bin")

    folder, pts_csv, _ = bc.ensure_data(0)
    ref_pgm, tar_pgm = ensure_pgm(folder)
    tag = f"{os.getpid()}"
    out_h5 = bench.cache_dir() / f"opencorr_cli_r{tag}.h5"
    oc_csv = bench.cache_dir() / f"opencorr_out_r{tag}.csv"
    cli = ["run", str(folder), "--points", str(pts_csv), "--subset", "21", "--m", "0",
           "--out", str(out_h5), "--overwrite", "--no-progress", "--threads", str(args.threads)]
    ours = {"bare": ["bare", str(folder), str(pts_csv), "0"],
            "cli": ["cli", *cli], "cli --no-checks": ["cli", *cli, "--no-checks"]}
    names = ["opencorr", *ours]
    machine = bench.machine_info([args.threads], "cpu")  # its load average: before the runs
    runs: dict[str, list[dict[str, Any]]] = {k: [] for k in names}
    try:
        for rnd in range(args.repeats):  # interleaved: one run of every case per round
            for name in names:
                load = os.getloadavg()[0]
                if name == "opencorr":
                    rec = run_opencorr(binary, ref_pgm, tar_pgm, pts_csv, args.threads, oc_csv)
                else:
                    res, wall, rss = bc.run_child(ours[name], args.threads)
                    rec = {**res, "process_wall_s": wall, "max_rss_mb": rss}
                    if name != "bare":
                        rec.update(cli_result_uv(out_h5))
                rec.update(round=rnd, load_avg_1m_before=load)
                runs[name].append(rec)
                t = rec.get("total_s", rec.get("time_s", rec.get("command_s")))
                print(f"round {rnd}: {name:<16} {t:.3f} s", flush=True)
    finally:
        out_h5.unlink(missing_ok=True)
        oc_csv.unlink(missing_ok=True)

    def med(name: str, key: str) -> float | None:
        vals = [r[key] for r in runs[name] if r.get(key) is not None]
        return statistics.median(vals) if vals else None

    oc = {k: med("opencorr", k) for k in (
        "fftcc_s", "prep_s", "icgn_s", "total_s", "fftcc_icgn_s", "process_wall_s",
        "max_rss_mb", "u", "v", "n_valid", "flagged", "not_converged", "mean_iterations",
        "median_zncc")}
    oc["poi_per_s_fftcc_icgn"] = N_POINTS / oc["fftcc_icgn_s"]
    oc["poi_per_s_total"] = N_POINTS / oc["total_s"]
    oc["process_poi_per_s"] = N_POINTS / oc["process_wall_s"]
    summary: dict[str, Any] = {"opencorr": oc}
    for name in ours:
        t = med(name, "time_s" if name == "bare" else "command_s")
        s = {"time_s": t, "poi_per_s": N_POINTS / t,
             "process_wall_s": med(name, "process_wall_s"),
             "process_poi_per_s": N_POINTS / med(name, "process_wall_s"),
             "max_rss_mb": med(name, "max_rss_mb"), "u": med(name, "u"), "v": med(name, "v")}
        s["vs_opencorr_fftcc_icgn"] = s["poi_per_s"] / oc["poi_per_s_fftcc_icgn"]
        s["vs_opencorr_total"] = s["poi_per_s"] / oc["poi_per_s_total"]
        s["process_vs_opencorr_process"] = s["process_poi_per_s"] / oc["process_poi_per_s"]
        if name != "bare":
            s["stages_s"] = {k: med(name, k) for k in (
                "inputs_s", "plan_s", "frames_read_s", "frames_prefilter_s", "solve_s",
                "checks_s", "write_s", "strain_s")}
        summary[name] = s

    checks = {}
    for name in names:
        u, v = summary[name]["u"], summary[name]["v"]
        checks[name] = {"u": u, "v": v,
                        "ok": u is not None and v is not None
                        and abs(u - TRUTH["u"]) < TOL_PX and abs(v - TRUTH["v"]) < TOL_PX}
    for name in ours:
        if summary[name]["u"] is not None:
            checks[name]["du_vs_opencorr"] = summary[name]["u"] - oc["u"]
            checks[name]["dv_vs_opencorr"] = summary[name]["v"] - oc["v"]
    accuracy = {"truth": TRUTH, "tolerance_px": TOL_PX, "cases": checks,
                "ok": all(c["ok"] for c in checks.values()),
                "note": "median over POIs; OpenCorr: POIs with zncc >= 0 (its -4 = not "
                        "converged in 10 iterations); stsdic run: finite u, v of frame 1"}

    flags = build_flags()
    opencorr_info = {
        "binary": str(binary), "binary_sha1": _sha1(binary),
        "binary_mtime": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(
            binary.stat().st_mtime)),
        "build_flags": flags.get(binary.name), "build_script": "scripts/opencorr/build.sh",
        "build_variants": flags, "linked": linked_fftw(binary),
        "harness": "scripts/opencorr/bench_fftcc_icgn1.cpp",
        "harness_sha1": _sha1(OC_DIR / "bench_fftcc_icgn1.cpp"),
        "source": "github.com/vincentjzy/OpenCorr src/, commits 5f84be6fe5520d92e9eb6a555fe3ca"
                  "f1d10e4a2a and 500f447d2350d894acf9f9030bb3fbffc5afb9dc (see "
                  "scripts/opencorr/README.md); Eigen 3.4.1 (cmeel-eigen wheel), FFTW 3.3.5 "
                  "(pyfftw 0.15.1 wheel)",
        "settings": "subset radius 10 (IC-GN 21x21, FFT-CC 20x20 window), max_iteration 10, "
                    "max_deformation_norm 0.001, one repetition per process",
        "inputs": {"ref": str(ref_pgm), "tar": str(tar_pgm), "ref_sha1": _sha1(ref_pgm),
                   "tar_sha1": _sha1(tar_pgm), "pois": str(pts_csv)},
        "timing": "fftcc = new FFTCC2D + setImages + compute; prep = new ICGN2D1 + setImages + "
                  "prepare (gradients + B-spline table); icgn = ICGN2D1::compute; total = "
                  "fftcc + prep + icgn; image loading not timed; process_wall_s also includes "
                  "process start, PGM loading and writing the result CSV",
    }
    record = {"kind": "opencorr", "date": time.strftime("%Y-%m-%d"), "m": 0,
              "n_points": N_POINTS, "threads": args.threads, "repeats": args.repeats,
              "machine": machine, "load_average_end": list(os.getloadavg()),
              "opencorr": opencorr_info,
              "summary": summary, "accuracy": accuracy, "runs": runs}
    path = Path(args.out) if args.out else bench.BENCH_DIR / "opencorr-cpu.json"
    path.write_text(json.dumps(record, indent=1) + "\n")

    print(f"\n{args.threads} threads, {args.repeats} repeat(s), medians; {binary}")
    print(f"{'case':<22}{'time s':>8}{'POI/s':>9}{'x OC(f+i)':>11}{'x OC(tot)':>11}"
          f"{'process s':>11}{'RSS MB':>8}{'med u':>9}{'med v':>9}")
    rows = [("opencorr fftcc+icgn", oc["fftcc_icgn_s"], oc["poi_per_s_fftcc_icgn"]),
            ("opencorr total", oc["total_s"], oc["poi_per_s_total"])]
    for label, t, rate in rows:
        print(f"{label:<22}{t:>8.3f}{rate:>9.0f}{rate / oc['poi_per_s_fftcc_icgn']:>11.2f}"
              f"{rate / oc['poi_per_s_total']:>11.2f}{oc['process_wall_s']:>11.2f}"
              f"{oc['max_rss_mb']:>8.0f}{oc['u']:>9.4f}{oc['v']:>9.4f}")
    for name in ours:
        s = summary[name]
        uv = (f"{s['u']:>9.4f}{s['v']:>9.4f}" if s["u"] is not None else f"{'-':>9}{'-':>9}")
        print(f"{name:<22}{s['time_s']:>8.3f}{s['poi_per_s']:>9.0f}"
              f"{s['vs_opencorr_fftcc_icgn']:>11.2f}{s['vs_opencorr_total']:>11.2f}"
              f"{s['process_wall_s']:>11.2f}{s['max_rss_mb']:>8.0f}{uv}")
    print(f"opencorr stages: fftcc {oc['fftcc_s']:.3f}, prep {oc['prep_s']:.3f}, "
          f"icgn {oc['icgn_s']:.3f} s; valid {oc['n_valid']:.0f}/{N_POINTS}, "
          f"not converged {oc['not_converged']}")
    bc.print_stages(summary)
    print(f"accuracy (truth u {TRUTH['u']:.2f}, v {TRUTH['v']:.2f}, tol {TOL_PX} px): "
          + ("ok" if accuracy["ok"] else "FAILED: " + ", ".join(
              n for n, c in checks.items() if not c["ok"])))
    print(f"-> {path}")


if __name__ == "__main__":
    main()
