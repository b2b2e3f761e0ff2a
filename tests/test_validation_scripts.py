"""Smoke tests of the validation scripts (scripts/validation/*.py --quick), run from the
repository root."""

from __future__ import annotations

import ast
import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def _run(script: str, *args: str, timeout: float = 300.0) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "validation" / script), *args],
        cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env,
    )
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_reproduce_table1_quick(tmp_path):
    out = _run("reproduce_table1.py", "--quick", "--out", str(tmp_path))
    assert "frames=3" in out
    rows = _rows(tmp_path / "table1_quick.csv")
    assert {r["protocol"] for r in rows} == {"noisy", "clean", "mean8"}
    assert {r["formulation"] for r in rows} == {"auto (joint)", "joint+average"}
    for r in rows:
        assert math.isfinite(float(r["rms_u"])) and float(r["rms_u"]) < 0.1
        assert float(r["pred_u"]) > 0
    assert (tmp_path / "table1_quick.md").read_text().startswith("Table 1 reproduction")


def test_reproduce_fig6_quick(tmp_path):
    _run("reproduce_fig6.py", "--quick", "--out", str(tmp_path))
    rows = _rows(tmp_path / "fig6_quick.csv")
    assert {r["method"] for r in rows} == {"classical", "STS m=2", "smoothed classical"}
    assert {float(r["sigma"]) for r in rows} == {0.0, 5.0}
    assert (tmp_path / "fig6_quick.png").stat().st_size > 1000
    assert "STS/smoothed" in (tmp_path / "fig6_quick.md").read_text()


def test_time_model_limits_quick(tmp_path):
    _run("time_model_limits.py", "--quick", "--out", str(tmp_path))
    rows = _rows(tmp_path / "time_model_limits_quick.csv")
    clean = [r for r in rows if r["reference_noise"] == "none"]
    for r in clean:
        # noise-free: the displacement bias follows a m(m+1)/3
        assert float(r["bias_u"]) == pytest.approx(float(r["theory_bias_u"]), abs=1.5e-3)
    jump = _rows(tmp_path / "time_model_limits_jump_quick.csv")
    worst = max(abs(float(r["error_u_moving"])) for r in jump if r["m"] == "2")
    assert worst == pytest.approx(0.5 * 2 / 5, abs=0.03)
    assert (tmp_path / "time_model_limits_quick.png").stat().st_size > 1000


def test_dic_challenge_skips_without_data(tmp_path):
    out = _run("dic_challenge.py", "--quick", "--data", str(tmp_path / "absent"),
               "--out", str(tmp_path))
    assert "SKIPPED" in out
    assert not list(tmp_path.glob("*.csv"))


@pytest.mark.skipif(not (DATA / "dic-challenge-sample5").is_dir()
                    or not (DATA / "dic-challenge-sample14").is_dir(),
                    reason="DIC Challenge images not found in ../shared/data (not part of the "
                           "repository)")
def test_dic_challenge_quick(tmp_path):
    _run("dic_challenge.py", "--quick", "--out", str(tmp_path))
    rows = _rows(tmp_path / "dic_challenge_quick.csv")
    s5 = [r for r in rows if r["sample"] == "5"]
    assert len(s5) == 2
    for r in s5:
        assert float(r["u_rms"]) < 0.05 and float(r["v_rms"]) < 0.05
    s14 = [r for r in rows if r["sample"] == "14"]
    assert {r["image"] for r in s14} == {"L1", "L3", "L5"}
    assert all(float(r["u_rms"]) < 0.05 for r in s14)
    assert (tmp_path / "dic_challenge_sample14_quick.png").stat().st_size > 1000


def test_real_time_model_skips_without_data(tmp_path):
    out = _run("real_time_model.py", "--quick", "--data", str(tmp_path / "absent"),
               "--out", str(tmp_path))
    assert "SKIPPED" in out
    assert not list(tmp_path.glob("*.csv"))


@pytest.mark.skipif(not (DATA / "dic-challenge-sample12").is_dir(),
                    reason="DIC Challenge sample 12 not found in ../shared/data (not part of the "
                           "repository)")
@pytest.mark.slow  # 17 s; a research script, not a product path
def test_real_time_model_quick(tmp_path):
    _run("real_time_model.py", "--quick", "--series", "sample12", "--out", str(tmp_path))
    rows = _rows(tmp_path / "real_time_model_quick.csv")
    real = [r for r in rows if r["kind"] == "real"]
    synth = [r for r in rows if r["kind"] == "synthetic"]
    assert len(real) == 1 and len(synth) == 3
    # the real series: most windows rejected, and the STS - classical difference is the
    # straight line through the classical trajectory (motion, not noise)
    assert float(real[0]["m0"]) > 0.5
    # the check judged windows there (no pre-pass decided the points classical first)
    assert float(real[0]["m2"]) + float(real[0]["m1"]) > 0.05
    assert float(real[0]["z_median"]) > 3.0
    assert float(real[0]["u_corr_d_dtraj"]) > 0.95 and float(real[0]["v_corr_d_dtraj"]) > 0.95
    # the same texture moving affinely in time: (almost) no false alarms, and the predicted
    # std of a static texture within 25 % of the measured one
    for r in synth:
        assert float(r["m2"]) > 0.97 and float(r["fail_z"]) < 0.03
    static = [r for r in synth if r["series"].endswith("static")][0]
    assert float(static["cls_std_measured"]) == pytest.approx(
        float(static["cls_std_predicted"]), rel=0.25)
    assert (tmp_path / "real_time_model_quick.png").stat().st_size > 1000


def test_shared_motion_quick():
    """The render study on a small shaking movie: the shared motion brings the full windows
    back and beats classical; without it the windows fail."""
    out = _run("shared_motion.py", "--quick")
    rows = [ast.literal_eval(line) for line in out.splitlines() if line.startswith("{")]
    by = {r["case"]: r for r in rows}
    assert by["STS m=2"]["full_window_converged"] < 0.5
    assert by["STS m=2, shared motion"]["full_window_converged"] > 0.9
    assert by["STS m=2, shared motion"]["vs_classical"] < 0.95
