"""End-to-end tests of the ``stsdic`` command line (in-process ``main([...])``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from torch_stsdic.cli import main

# one torch thread: the tests run on small, busy machines where competing threads are slow
FAST = ["--threads", "1"]
SUBCOMMANDS = ["run", "export", "plot", "view", "synth", "demo"]


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _assert_one_line_error(code: int, err: str, *names: str) -> str:
    assert code != 0
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith("stsdic: error: "), line
    for name in names:
        assert name in line, (name, line)
    return line


# ----------------------------------------------------------------------------------------
# fixtures: one small synthetic movie and one result file for the module
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def movie(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("movie")
    code = main(
        ["synth", "--out", str(d), "--size", "81", "--frames", "7", "--noise", "1", "--seed", "3"]
        + FAST
    )
    assert code == 0
    return d


@pytest.fixture(scope="module")
def result(movie, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "r.h5"
    code = main(
        ["run", str(movie / "movie.tif"), "--subset", "17", "--step", "15", "--m", "2"]
        + ["--search-radius", "3", "--out", str(out), "--no-progress"]
        + FAST
    )
    assert code == 0
    return out


# ----------------------------------------------------------------------------------------
# help
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("cmd", [None, *SUBCOMMANDS])
def test_help(capsys, cmd):
    argv = ["--help"] if cmd is None else [cmd, "--help"]
    code, out, err = _run(capsys, *argv)
    assert code == 0
    assert out.startswith("usage: stsdic")
    assert "examples:" in out
    if cmd == "run":
        for opt in (
            "--reference",
            "--frames",
            "--subset",
            "--step",
            "--m",
            "--roi",
            "--mask",
            "--points",
            "--formulation",
            "--criterion",
            "--shape",
            "--window",
            "--interpolation",
            "--search-radius",
            "--tol",
            "--max-iter",
            "--strain-window",
            "--strain-kind",
            "--timestamps",
            "--reference-update",
            "--device",
            "--dtype",
            "--resume",
            "--overwrite",
            "--no-progress",
            "--no-checks",
            "--out",
        ):
            assert opt in out, opt
        assert "(default: 21)" in out  # subset
    if cmd == "synth":
        for motion in ("translation", "strain", "sinusoidal", "quadratic", "jump"):
            assert motion in out


@pytest.mark.parametrize("module", ["torch_stsdic", "torch_stsdic.cli"])
def test_python_m_help(module):
    proc = subprocess.run(
        [sys.executable, "-m", module, "--help"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    for cmd in SUBCOMMANDS:
        assert cmd in proc.stdout


def test_help_lists_each_command_once(capsys):
    code, out, _ = _run(capsys, "--help")
    assert code == 0
    listed = [ln.split()[0] for ln in out.splitlines() if ln.startswith("  ") and ln.split()]
    for cmd in SUBCOMMANDS:
        assert listed.count(cmd) == 1, (cmd, out)
    assert "COMMAND\n" not in out  # no bare metavar line above the list


def test_help_states_every_default_once():
    """Every option with a default names it once in its help ('(default: ...)' as
    options.add_option writes it, or 'default: ...' inside a parenthesis)."""
    import argparse

    from torch_stsdic.cli.app import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    checked = 0
    for name, p in sub.choices.items():
        for a in p._actions:
            if not a.option_strings or a.help == argparse.SUPPRESS:
                continue
            if a.default in (None, False, argparse.SUPPRESS):
                continue
            text = a.help.replace("%(default)s", str(a.default))
            assert text.count("default: ") == 1, (name, a.option_strings, text)
            checked += 1
    assert checked > 40


def test_no_command(capsys):
    code, out, err = _run(capsys)
    assert code == 2
    _assert_one_line_error(code, err, "command")


# ----------------------------------------------------------------------------------------
# synth
# ----------------------------------------------------------------------------------------


def test_synth_writes_movie_and_truth(movie):
    stack = tifffile.imread(movie / "movie.tif")
    assert stack.shape == (8, 81, 81) and stack.dtype == np.uint8  # reference + 7 frames
    meta = json.loads((movie / "motion.json").read_text())
    assert meta["motion"]["type"] == "translation"
    assert meta["motion"]["params"]["ut"] == pytest.approx(0.05)
    assert meta["times"] == list(range(8))
    truth = np.genfromtxt(movie / "truth.csv", delimiter=",", names=True)
    assert {"frame", "time", "x", "y", "u", "v", "ut", "vt"} <= set(truth.dtype.names)
    np.testing.assert_allclose(truth["u"], 0.05 * truth["time"], atol=1e-12)
    np.testing.assert_allclose(truth["ut"], 0.05)
    assert (movie / "times.csv").exists()


def test_synth_files_layout_strain_16bit(capsys, tmp_path):
    code, out, err = _run(
        capsys, "synth", "--out", tmp_path, "--size", "48", "40", "--frames", "3",
        "--motion", "strain", "--exx", "0.01", "--bits", "16", "--noise", "0",
        "--layout", "files", "--truth-step", "8", *FAST,
    )  # fmt: skip
    assert code == 0, err
    files = sorted(tmp_path.glob("frame_*.tif"))
    assert [f.name for f in files] == [f"frame_{k:05d}.tif" for k in range(4)]
    img = tifffile.imread(files[0])
    assert img.shape == (40, 48) and img.dtype == np.uint16 and img.max() > 255
    truth = np.genfromtxt(tmp_path / "truth.csv", delimiter=",", names=True)
    np.testing.assert_allclose(truth["dudx"], 0.01 * truth["time"], atol=1e-12)
    cx = (48 - 1) / 2
    np.testing.assert_allclose(truth["u"], 0.01 * truth["time"] * (truth["x"] - cx), atol=1e-9)
    # existing files are not replaced without --overwrite
    before = files[0].read_bytes()
    code, out, err = _run(capsys, "synth", "--out", tmp_path, "--layout", "files", *FAST)
    _assert_one_line_error(code, err, "exists", "--overwrite")
    assert files[0].read_bytes() == before


# ----------------------------------------------------------------------------------------
# run, export, plot
# ----------------------------------------------------------------------------------------


def test_run_result_file(result):
    with h5py.File(result, "r") as f:
        for name in (
            "points",
            "frames",
            "times",
            "completed",
            "u",
            "v",
            "ut",
            "vt",
            "zncc",
            "status",
            "exx",
            "eyy",
            "exy",
        ):
            assert name in f, name
        assert f["completed"][()].all()
        fields = json.loads(f.attrs["fields"])
        assert {"exx", "eyy", "exy"} <= set(fields)
        times = f["times"][()]
        u, v, ut = f["u"][()], f["v"][()], f["ut"][()]
        status = f["status"][()]
        exx = f["exx"][()]
    assert u.shape == (8, 16)  # grid 13..67 px: subset/2 + 2 (cubic) + 3 (search radius)
    assert (status <= 1).mean() > 0.95
    ok = status <= 1
    err = (u - 0.05 * times[:, None])[ok]
    # measured: RMS u error 0.0051 px, |v| 0.011 px, |ut - 0.05| 0.0048 px/frame, |exx|
    # 2.7e-4 at most (noise 1, 8-bit); bands about 3x
    assert np.sqrt(np.mean(err**2)) < 0.015
    assert np.abs(v[ok]).max() < 0.035
    assert np.abs(ut[ok] - 0.05).max() < 0.015
    assert np.nanmax(np.abs(exx)) < 1e-3


def test_run_summary_and_resume_overwrite(capsys, movie, tmp_path):
    out = tmp_path / "r.h5"
    base = ["run", movie / "movie.tif", "--subset", "17", "--step", "25", "--m", "1",
            "--search-radius", "3",
            "--frames", "0:4", "--out", out, "--no-progress", *FAST]  # fmt: skip
    code, stdout, err = _run(capsys, *base)
    assert code == 0, err
    assert "points: 9" in stdout and "frames: 4" in stdout
    assert "converged:" in stdout and "POI/s" in stdout
    # existing output: refused without --overwrite / --resume, and left untouched
    before = out.read_bytes()
    code, _, err = _run(capsys, *base)
    _assert_one_line_error(code, err, str(out), "--overwrite")
    assert out.read_bytes() == before
    code, stdout, err = _run(capsys, *base, "--resume")
    assert code == 0, err
    code, stdout, err = _run(capsys, *base, "--overwrite")
    assert code == 0, err
    assert not out.with_name(out.name + ".partial").exists()


def test_run_no_checks_is_recorded_and_resumed_alike(capsys, movie, tmp_path):
    out = tmp_path / "r.h5"
    base = ["run", movie / "movie.tif", "--subset", "17", "--step", "25", "--m", "1",
            "--search-radius", "3", "--frames", "0:4", "--out", out, "--no-progress",
            *FAST]  # fmt: skip
    code, stdout, err = _run(capsys, *base, "--no-checks")
    assert code == 0, err
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["config"])["track"]["checks"] is False
    code, _, err = _run(capsys, *base, "--resume")  # checks on: not the same run
    _assert_one_line_error(code, err, "--no-checks")
    code, _, err = _run(capsys, *base, "--no-checks", "--resume")
    assert code == 0, err


def test_a_file_recorded_with_the_old_default_memory_budget_resumes(capsys, movie, tmp_path):
    """``--memory-mb`` not given is recorded as null (a GPU then takes its own budget); a file
    that recorded the default as 256.0 (before null) resumes alike, another budget does not."""
    out = tmp_path / "r.h5"
    base = ["run", movie / "movie.tif", "--subset", "17", "--step", "25", "--m", "1",
            "--search-radius", "3", "--frames", "0:4", "--out", out, "--no-progress",
            *FAST]  # fmt: skip
    code, _, err = _run(capsys, *base)
    assert code == 0, err

    def recorded(memory_mb):
        with h5py.File(out, "r+") as f:
            cfg = json.loads(f.attrs["config"])
            old, cfg["memory_mb"] = cfg["memory_mb"], memory_mb
            f.attrs["config"] = json.dumps(cfg)
        return old

    assert recorded(256.0) is None  # written as not given
    code, _, err = _run(capsys, *base, "--resume")
    assert code == 0, err
    recorded(512.0)
    code, _, err = _run(capsys, *base, "--resume")
    _assert_one_line_error(code, err, "--memory-mb")
    code, _, err = _run(capsys, *base, "--memory-mb", "512", "--resume")
    assert code == 0, err


def test_run_points_and_timestamps(capsys, movie, tmp_path):
    pts = tmp_path / "poi.csv"
    pts.write_text("x,y\n30,30\n40,40\n50,35\n")
    ts = tmp_path / "t.csv"
    ts.write_text("frame,time\n" + "".join(f"{k},{0.5 * k}\n" for k in range(8)))
    out = tmp_path / "p.h5"
    code, stdout, err = _run(
        capsys, "run", movie / "movie.tif", "--subset", "17", "--m", "1", "--points", pts,
        "--timestamps", ts, "--frames", "2:5", "--out", out, "--no-progress", *FAST,
    )  # fmt: skip
    assert code == 0, err
    with h5py.File(out, "r") as f:
        np.testing.assert_allclose(f["points"][()], [[30, 30], [40, 40], [50, 35]])
        np.testing.assert_allclose(f["times"][()], [1.0, 1.5, 2.0])
        ut = f["ut"][()]
    # 0.05 px/frame = 0.1 px per time unit (measured |ut - 0.1| 0.0078 at most; a velocity
    # per frame instead would be off by 0.05)
    assert np.abs(ut - 0.1).max() < 0.025


def test_export_csv(capsys, result, tmp_path):
    code, out, err = _run(capsys, "export", result, "--out", tmp_path, "--frames", "1:3")
    assert code == 0, err
    files = sorted(tmp_path.glob("*.csv"))
    assert [f.name for f in files] == ["r_frame00001.csv", "r_frame00002.csv"]
    lines = files[0].read_text().splitlines()
    cols = lines[0].split(",")  # the header first; units in the sidecar r_csv.json
    assert cols[:11] == ["x", "y", "u", "v", "ut", "vt", "exx", "eyy", "exy", "zncc", "status"]
    assert len(lines) == 1 + 16 and (tmp_path / "r_csv.json").exists()  # header + 4x4 points
    code, out, err = _run(capsys, "export", result, "--out", tmp_path / "all")
    assert code == 0 and len(list((tmp_path / "all").glob("*.csv"))) == 8


def test_plot_pngs(capsys, result, movie, tmp_path):
    code, out, err = _run(capsys, "plot", result, "--out", tmp_path, "--image", movie / "movie.tif")
    assert code == 0, err
    names = {p.name for p in tmp_path.glob("*.png")}
    assert {"fields_frame00007.png", "history_mean.png", "strain_history_mean.png"} <= names
    code, out, err = _run(
        capsys, "plot", result, "--out", tmp_path, "--frame", "3", "--fields", "u,exx",
        "--point", "40", "40", "--no-image",
    )  # fmt: skip
    assert code == 0, err
    assert (tmp_path / "fields_frame00003.png").stat().st_size > 1000
    assert any(p.name.startswith("history_x") for p in tmp_path.glob("*.png"))


def test_demo_quick(capsys, tmp_path):
    code, out, err = _run(capsys, "demo", "--quick", "--out", tmp_path, "--no-progress", *FAST)
    assert code == 0, err
    assert "classical DIC" in out and "STS-DIC" in out and "ratio" in out
    assert "RMS u err" in out and "POI/s" in out
    for name in ("error_per_frame.png", "fields.png", "history.png", "demo.json"):
        assert (tmp_path / name).exists(), name
    summary = json.loads((tmp_path / "demo.json").read_text())
    for row in summary["results"]:
        assert row["rms_u"] < 0.1
    # the printed table holds the file's numbers
    for row in summary["results"]:
        assert f"{row['rms_u']:.4f}" in out and f"{row['rms_ut']:.4f}" in out
    assert f"plots and numbers in {tmp_path}/: error_per_frame.png" in out


def test_demo_no_plots_and_bad_settings(capsys, tmp_path):
    out_dir = tmp_path / "d"
    code, out, err = _run(
        capsys, "demo", "--quick", "--no-plots", "--noise", "0", "--out", out_dir,
        "--no-progress", *FAST,
    )  # fmt: skip
    assert code == 0, err
    assert "noise sigma 0 grey levels," in out and "plots and numbers" not in out
    assert not out_dir.exists()
    code, _, err = _run(capsys, "demo", "--quick", "--frames", "3", "--out", out_dir)
    assert code == 2
    _assert_one_line_error(code, err, "--frames 3", "--m 2", "at least 5 frames")
    code, _, err = _run(capsys, "demo", "--quick", "--subset", "121", "--out", out_dir)
    _assert_one_line_error(code, err, "--subset 121")
    assert code == 2 and not out_dir.exists()


# ----------------------------------------------------------------------------------------
# bad input: one line, named culprit, no traceback, outputs untouched
# ----------------------------------------------------------------------------------------


@pytest.fixture()
def existing_out(tmp_path) -> Path:
    p = tmp_path / "keep.h5"
    p.write_bytes(b"precious old result")
    return p


def _run_args(movie: Path, out: Path, *extra) -> list:
    return ["run", movie / "movie.tif", "--subset", "17", "--step", "15", "--out", out,
            "--overwrite", "--no-progress", *extra, *FAST]  # fmt: skip


def _check_untouched(p: Path) -> None:
    assert p.read_bytes() == b"precious old result"
    assert not p.with_name(p.name + ".partial").exists()


def test_missing_input(capsys, tmp_path, existing_out):
    missing = tmp_path / "nope.tif"
    code, _, err = _run(capsys, "run", missing, "--out", existing_out, "--overwrite")
    _assert_one_line_error(code, err, "nope.tif")
    _check_untouched(existing_out)


def test_unreadable_input(capsys, tmp_path, existing_out):
    bad = tmp_path / "bad.tif"
    bad.write_text("this is not an image")
    code, _, err = _run(capsys, "run", bad, "--out", existing_out, "--overwrite")
    _assert_one_line_error(code, err, "bad.tif")
    _check_untouched(existing_out)


def test_mixed_sizes(capsys, tmp_path, existing_out):
    a, b = tmp_path / "a.tif", tmp_path / "b.tif"
    tifffile.imwrite(a, np.zeros((40, 40), np.uint8))
    tifffile.imwrite(b, np.zeros((30, 40), np.uint8))
    code, _, err = _run(capsys, "run", a, b, a, "--m", "1", "--out", existing_out, "--overwrite")
    line = _assert_one_line_error(code, err, "b.tif")
    assert "size" in line
    _check_untouched(existing_out)


def test_non_finite_pixels(capsys, tmp_path, existing_out):
    rng = np.random.default_rng(0)
    stack = rng.uniform(0, 255, (5, 40, 40)).astype(np.float32)
    stack[3, 10, 10] = np.nan
    f = tmp_path / "nan.tif"
    tifffile.imwrite(f, stack, photometric="minisblack")
    code, _, err = _run(capsys, "run", f, "--subset", "11", "--out", existing_out, "--overwrite")
    line = _assert_one_line_error(code, err, "nan.tif")
    assert "non-finite" in line
    _check_untouched(existing_out)


@pytest.mark.parametrize(
    ("extra", "names"),
    [
        (["--roi", "0", "0", "500", "500"], ["--roi"]),
        (["--subset", "101"], ["--subset", "101"]),
        (["--m", "5"], ["--m", "11"]),
        (["--subset", "20"], ["--subset"]),
        (["--frames", "20"], ["--frames"]),
        (["--reference", "x"], ["--reference"]),
        (["--formulation", "best"], ["--formulation"]),
        (["--reference-update", "2"], ["--reference-update"]),
    ],
)
def test_bad_arguments_exit_2(capsys, movie, existing_out, extra, names):
    argv = _run_args(movie, existing_out)
    argv[2:4] = []  # drop "--subset 17": the extra options are the ones tested
    code, _, err = _run(capsys, *argv, *extra)
    assert code == 2
    _assert_one_line_error(code, err, *names)
    _check_untouched(existing_out)


def test_bad_side_files(capsys, movie, tmp_path, existing_out):
    mask = tmp_path / "mask.npy"
    np.save(mask, np.ones((10, 10), bool))
    code, _, err = _run(capsys, *_run_args(movie, existing_out, "--mask", mask))
    _assert_one_line_error(code, err, "--mask", "mask.npy")
    pts = tmp_path / "pts.csv"
    pts.write_text("x,y\n10,10\n900,10\n")
    code, _, err = _run(capsys, *_run_args(movie, existing_out, "--points", pts))
    _assert_one_line_error(code, err, "--points", "pts.csv")
    ts = tmp_path / "ts.txt"
    ts.write_text("0\n1\n2\n")
    code, _, err = _run(capsys, *_run_args(movie, existing_out, "--timestamps", ts))
    _assert_one_line_error(code, err, "--timestamps")
    code, _, err = _run(capsys, *_run_args(movie, existing_out, "--timestamps", tmp_path / "n"))
    _assert_one_line_error(code, err, "--timestamps")
    _check_untouched(existing_out)


def test_export_and_plot_errors(capsys, result, tmp_path):
    code, _, err = _run(capsys, "export", tmp_path / "missing.h5", "--out", tmp_path)
    _assert_one_line_error(code, err, "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    code, _, err = _run(capsys, "plot", junk, "--out", tmp_path)
    _assert_one_line_error(code, err, "junk.h5")
    code, _, err = _run(capsys, "export", result, "--out", tmp_path, "--frames", "50")
    _assert_one_line_error(code, err, "--frames")
    code, _, err = _run(capsys, "plot", result, "--out", tmp_path, "--fields", "u,bogus")
    _assert_one_line_error(code, err, "--fields", "bogus")
    code, _, err = _run(capsys, "plot", result, "--out", tmp_path, "--frame", "99")
    _assert_one_line_error(code, err, "--frame")
    assert not list(tmp_path.glob("*.png"))


def test_debug_shows_traceback(capsys, tmp_path):
    code, _, err = _run(capsys, "run", tmp_path / "nope.tif", "--out", tmp_path / "o.h5",
                        "--debug")  # fmt: skip
    assert code == 1
    assert "Traceback" in err and "stsdic: error:" in err


def test_run_refine_reference(capsys, movie, tmp_path):
    out = tmp_path / "rr.h5"  # step 8: 36 points (the template's local fits need 25)
    base = ["run", movie / "movie.tif", "--subset", "17", "--step", "8", "--m", "1",
            "--out", out, "--no-progress", *FAST]  # fmt: skip
    code, out_text, err = _run(capsys, *base, "--refine-reference", "--refine-frames", "6")
    assert code == 0, err
    # the summary says what the refinement did (the file records it in its info)
    line = [ln for ln in out_text.splitlines() if ln.startswith("refined reference:")]
    assert len(line) == 1 and " of 36 points (fits over " in line[0], out_text
    with h5py.File(out, "r") as f:
        assert np.isfinite(f["u"][()]).all()
    code, _, err = _run(capsys, *base, "--overwrite", "--refine-reference", "--reference", "0:2")
    _assert_one_line_error(code, err, "refine_reference")
    # a setting of the template: not without it
    code, _, err = _run(capsys, *base, "--overwrite", "--refine-reference", "--single-reference")
    _assert_one_line_error(code, err, "refine_reference: sets the gauge of the template")


def test_run_formulation_average_is_deprecated(capsys, movie, tmp_path):
    code, _, err = _run(capsys, "run", movie / "movie.tif", "--subset", "17", "--step", "25",
                        "--m", "1", "--frames", "0:3", "--formulation", "average",
                        "--out", tmp_path / "a.h5", "--no-progress", *FAST)  # fmt: skip
    assert code == 0, err
    assert "stsdic: warning:" in err and "deprecated" in err and "joint+average" in err
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert np.isfinite(f["ut"][()]).all()  # the velocity converges (joint first)
