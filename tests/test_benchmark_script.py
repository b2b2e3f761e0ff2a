"""scripts/benchmarks/benchmark.py: the --quick preset runs and records; the doc tables
regenerate."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from repo_scripts import load_script  # tests/ on the path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "benchmarks" / "benchmark.py"


def _load():
    return load_script(SCRIPT, "stsdic_benchmark")


def test_quick_preset_runs_and_records(tmp_path):
    out = tmp_path / "quick.json"
    env_cache = {"STSDIC_BENCH_CACHE": str(tmp_path / "cache")}
    p = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(out)],
                       capture_output=True, text=True, timeout=300,
                       env={**os.environ, **env_cache})
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads(out.read_text())
    assert rec["preset"] == "quick"
    for key in ("cpu_model", "cores", "torch", "torch_threads", "date", "command",
                "load_average"):
        assert key in rec["machine"], key
    kinds = [r["spec"]["kind"] for r in rec["results"]]
    assert kinds.count("solve") == 2 and "track" in kinds
    for r in rec["results"]:
        assert r["ok"], r
        assert r["poi_per_s"] > 0 and r["converged_frac"] > 0.9
        if r["spec"]["kind"] == "solve":
            md = r["median_s"]
            assert set(md) >= {"prefilter", "initial_guess", "iterations", "total"}
            parts = md["prefilter"] + md["initial_guess"] + md["iterations"]
            assert abs(parts - md["total"]) < 1e-6 + 1e-3 * md["total"]
            assert r["median_err_px"] < 0.05
    assert "| case |" in p.stdout and "POI/s" in p.stdout


def test_doc_tables_regenerate_between_markers(tmp_path):
    bench = _load()
    rec = {
        "preset": "targets", "_file": "targets-cpu.json",
        "machine": {"cpu_model": "X", "cores": 2, "torch": "2", "torch_threads": [2],
                    "date": "2026-01-01T00:00:00", "command": "benchmark.py --targets",
                    "load_average": [1.0, 1.0, 1.0], "git_commit": "abc", "device": "cpu"},
        "results": [
            {"name": "t0", "ok": True, "spec": {"kind": "track", "label": "table1", "m": 0,
                                               "dtype": "float32", "threads": 2},
             "median_s": {"total": 0.2}, "times_s": {"total": {"median": 0.2, "min": 0.2}},
             "n_points": 361, "n_frames": 9, "poi_per_s": 16245.0, "mean_iterations": 3.0,
             "converged_frac": 1.0, "u_rmse_px": 0.01, "peak_mem_mb": 10.0,
             "cpu_over_wall": 1.0, "load_after": 1.0},
            {"name": "t2", "ok": True, "spec": {"kind": "track", "label": "table1", "m": 2,
                                               "dtype": "float32", "threads": 2},
             "median_s": {"total": 0.5}, "times_s": {"total": {"median": 0.5, "min": 0.5}},
             "n_points": 361, "n_frames": 9, "poi_per_s": 6498.0, "mean_iterations": 3.0,
             "converged_frac": 1.0, "u_rmse_px": 0.01, "peak_mem_mb": 10.0,
             "cpu_over_wall": 1.0, "load_after": 1.0},
        ],
    }
    rows = bench.target_rows([rec])
    assert rows[0][3] == "PASS" and "0.50 s" in rows[0][2]
    assert rows[1][3] == "PASS" and "2.50x" in rows[1][2]
    doc = tmp_path / "b.md"
    doc.write_text("head\n<!-- BEGIN AUTOGEN targets -->\nold\n<!-- END AUTOGEN targets -->\n"
                   "tail\n")
    assert bench.update_doc([rec], doc)
    text = doc.read_text()
    assert "old" not in text and "Table 1 via sts.track" in text and text.endswith("tail\n")


def test_movie_preset_runs_and_splits_time(tmp_path):
    """--movie at a toy size (6 frames, 16 POIs): a TIFF from disk, the time split adds up."""
    out = tmp_path / "movie.json"
    env_cache = {"STSDIC_BENCH_CACHE": str(tmp_path / "cache")}
    p = subprocess.run([sys.executable, str(SCRIPT), "--movie", "--movie-frames", "6",
                        "--movie-points", "16", "--threads", "1", "--no-isolate", "--out",
                        str(out), "--no-update-doc"], capture_output=True, text=True,
                       timeout=300, env={**os.environ, **env_cache})
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (r,) = json.loads(out.read_text())["results"]
    assert r["ok"] and r["n_frames"] == 6 and r["n_points"] == 16
    assert r["converged_frac"] > 0.9 and r["u_rmse_px"] < 0.05
    sp = r["split_s"]
    wall = r["median_s"]["total"]
    assert abs(sp["solve_s"] + sp["wait_frames_s"] + sp["write_s"] + sp["other_s"] - wall) \
        < 1e-6 + 1e-3 * wall
    assert sp["ahead_read_s"] > 0 and sp["ahead_prefilter_s"] > 0  # read ahead in the thread
    assert 0 < r["overhead_share"] < 1 and r["frames_per_s"] > 0
    assert "| movie 6x1024 16 POIs STS(5) cpu" in p.stdout


def test_opencorr_bench_says_how_to_build_when_the_harness_is_missing(tmp_path):
    """scripts/benchmarks/bench_opencorr.py without a built OpenCorr harness: one line saying how to
    build it, no record written, exit status 1 (nothing else runs)."""
    out = tmp_path / "oc.json"
    proc = subprocess.run([sys.executable, str(SCRIPT.parent / "bench_opencorr.py"),
                           "--opencorr-bin", str(tmp_path / "missing"), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    msg = (proc.stdout + proc.stderr).strip().splitlines()
    assert proc.returncode == 1 and len(msg) == 1, proc.stdout + proc.stderr
    assert "scripts/opencorr/build.sh" in msg[0] and not out.exists()


def test_cuda_targets_compare_the_triton_solver_with_the_batched_loop():
    """On CUDA the targets preset also times the batched Gauss-Newton loop (per_point=0, the
    path before the whole-stage Triton solver) at 38,809 and 250,000 POIs, classical and
    STS(5), as comparison cases (left out of the targets' verdicts); the child sets the
    switch."""
    bench = _load()
    args = bench.parse_args(["--targets", "--device", "cuda", "--threads", "1"])
    cases = bench.preset_cases(args, "cuda")
    loop = [c for c in cases if c.get("per_point") == "0"]
    got = {(c["m"], c["n"] ** 2 if c.get("step") else c["n"]) for c in loop}
    assert got == {(0, 38_809), (2, 38_809), (0, 250_000), (2, 250_000)}
    assert all(c["compare"] and "per_point=0" in bench.case_name(c) for c in loop)
    same = {(c["m"], c["n"], c.get("step")) for c in cases
            if c["kind"] == "solve" and not c.get("compare")}
    assert {(c["m"], c["n"], c.get("step")) for c in loop} <= same  # the solver's own rows
    assert not any(c.get("per_point") for c in bench.preset_cases(args, "cpu"))


def test_cpu_criteria_reads_the_template_from_the_runs_and_records(tmp_path):
    """scripts/benchmarks/cpu_criteria.py on a small synthetic movie, one round: the
    defaults, the classical run, the template's seconds read from the run's summary line
    (a changed summary would leave the share out), the ratio per round and the record."""
    script = SCRIPT.parent / "cpu_criteria.py"
    movie = tmp_path / "movie"
    p = subprocess.run([sys.executable, "-m", "torch_stsdic", "synth", "--out", str(movie),
                        "--size", "120", "120", "--frames", "8"], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    out = tmp_path / "criteria.json"
    p = subprocess.run([sys.executable, str(script), "--rounds", "1", "--out", str(out), "--",
                        str(movie / "movie.tif")], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rec = json.loads(out.read_text())
    row = rec["rounds"][0]
    assert row["defaults_s"] > 0 and row["classical_s"] > 0
    assert abs(row["defaults_ratio"] - row["defaults_s"] / row["classical_s"]) < 0.01
    assert 0 < row["defaults_template_share"] < 1  # the summary line was read
    assert rec["summary"]["defaults_ratio"]["median"] == row["defaults_ratio"]
    assert "limits: ratio <= 3.0x" in p.stdout
