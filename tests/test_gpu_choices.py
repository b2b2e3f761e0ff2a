"""A run with a GPU's choices (``torch_stsdic.core.choices``: masked solves of a block's
groups of rows, every shorter window at once, every ring of the neighbour fill), taken on
the CPU: the same result file as with the CPU's choices, to the bit."""

from __future__ import annotations

import pytest
import torch

from torch_stsdic.kernels import native


def _run(tmp_path, name: str, movie, args=()) -> dict:
    import h5py

    from torch_stsdic.cli import main

    path = tmp_path / f"{name}.h5"
    assert main(["run", str(movie), "--subset", "21", "--step", "10", "--threads", "1",
                 "--no-progress", "--out", str(path), *args]) == 0
    with h5py.File(path) as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


def _take_choices(monkeypatch, gpu: bool) -> None:
    """Every choice of ``torch_stsdic.core.choices`` as a GPU run (``gpu``) or a CPU run
    makes it."""
    from torch_stsdic.core import choices

    for name, value in choices.gpu_choices().items():
        monkeypatch.setattr(choices, name, value if gpu else not value)


def _same_files(out: dict) -> None:
    """The two runs' files (``out[True]`` a GPU's choices, ``out[False]`` a CPU's) hold the
    same datasets, equal to the bit."""
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k


@pytest.mark.parametrize("args", [(), ("--m", "3")], ids=["chosen-windows", "m3"])
def test_a_gpu_runs_choices_give_the_cpu_runs_file(tmp_path, monkeypatch, args):
    """A speckle moving right by 1.5 px a frame out of a 160 px view: near the border the
    blocks move subsets inside, shorten windows and leave rows OUTSIDE (``keep_outside``),
    rescue rows, solve groups of half-widths. With a GPU's choices the groups are masked
    solves over all the rows (``SubsetSolver.solve(active=)``), with the CPU's each group
    alone; the files are the same to the bit."""
    from torch_stsdic.cli import main
    from torch_stsdic.core.solver import SubsetSolver

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames", "24",
                 "--motion", "translation", "--ut", "1.5", "--vt", "0.2", "--noise", "2",
                 "--seed", "4", "--threads", "1"]) == 0
    movie = tmp_path / "m" / "movie.tif"
    solve = SubsetSolver.solve
    masked = []

    def spy(self, *a, active=None, **k):
        if active is not None:
            masked.append(int(active.numel()))
        return solve(self, *a, active=active, **k)

    monkeypatch.setattr(SubsetSolver, "solve", spy)
    out = {}
    for gpu in (False, True):
        _take_choices(monkeypatch, gpu)
        masked.clear()
        out[gpu] = _run(tmp_path, f"g{int(gpu)}", movie, args)
        if gpu:
            assert len(masked) >= 2, masked  # the groups solved masked
        else:
            assert not masked
    st, m = out[True]["status"], out[True]["m"]
    assert (st == 3).sum() > 50  # OUTSIDE: the points that left the view
    assert ((m > 0) & (m < m.max())).sum() > 20  # windows shortened
    _same_files(out)


def test_a_gpu_runs_model_check_masks_its_rows_and_gives_the_cpu_runs_file(tmp_path,
                                                                             monkeypatch):
    """A movie whose motion oscillates in time, differently over the image: the model check
    solves rows classically, in full, shorter and classical to the run's tol. With a GPU's
    choices every step is a masked solve over all the block's rows (no host read of which
    rows), with the CPU's each step's rows are taken; the same file to the bit, and the
    check's steps did work (rows shortened and left classical)."""
    from test_mixed_windows import _oscillating_movie  # (tests/ on the path)

    from torch_stsdic.core.solver import SubsetSolver
    from torch_stsdic.movie import checks

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    _oscillating_movie(tmp_path / "osc.tif")
    solve, check_model = SubsetSolver.solve, checks.BlockChecks.check_model
    masked, counted = [], []
    in_check = [False]

    def spy(self, *a, active=None, **k):
        if in_check[0]:
            masked.append(active is not None)
        return solve(self, *a, active=active, **k)

    def spy_check(self):
        in_check[0] = True
        try:
            shortened, classical = check_model(self)
        finally:
            in_check[0] = False
        counted.append((int(shortened), int(classical)))
        return shortened, classical

    monkeypatch.setattr(SubsetSolver, "solve", spy)
    monkeypatch.setattr(checks.BlockChecks, "check_model", spy_check)
    out, solves = {}, {}
    for gpu in (False, True):
        _take_choices(monkeypatch, gpu)
        masked.clear()
        counted.clear()
        out[gpu] = _run(tmp_path, f"o{int(gpu)}", tmp_path / "osc.tif", ("--step", "8"))
        solves[gpu] = list(masked)
        shortened, classical = map(sum, zip(*counted))
        assert shortened >= 500 and classical >= 5, counted  # the check's steps worked
    assert solves[True] and all(solves[True])  # every solve of the check masked
    assert not any(solves[False])
    _same_files(out)


def test_a_gpu_runs_classical_rescue_of_lost_rows_gives_the_cpu_runs_file(tmp_path,
                                                                           monkeypatch):
    """A stretching speckle whose middle is covered by a noise flash for three frames: rows
    there stay lost after the rescue and the model check, and the classical rescue tries
    them from their carried guesses, on a GPU in one masked solve of every row of the block
    (no read of whether any is lost); the same file to the bit."""
    import numpy as np
    import tifffile

    from torch_stsdic.cli import main
    from torch_stsdic.movie import checks

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames", "24",
                 "--motion", "strain", "--exx", "0.004", "--noise", "2", "--seed", "7",
                 "--threads", "1"]) == 0
    frames = tifffile.imread(tmp_path / "m" / "movie.tif")
    frames[9:12, 50:90, 50:90] = np.random.default_rng(1).integers(0, 255, (3, 40, 40),
                                                                    dtype=np.uint8)
    tifffile.imwrite(tmp_path / "flash.tif", frames)
    rescue_classical = checks.BlockChecks.rescue_classical
    tried = []

    def spy(self, guess, carry):
        if guess is not None:
            tried.append(int((self.lost() & torch.isfinite(guess).all(1)).sum()))
        return rescue_classical(self, guess, carry)

    monkeypatch.setattr(checks.BlockChecks, "rescue_classical", spy)
    out = {}
    for gpu in (False, True):
        _take_choices(monkeypatch, gpu)
        tried.clear()
        out[gpu] = _run(tmp_path, f"f{int(gpu)}", tmp_path / "flash.tif")
        assert sum(tried) >= 50, tried  # lost rows with a carried guess, tried classically
    assert (out[True]["status"] == 6).sum() >= 50  # POOR_FIT under the flash
    _same_files(out)


def test_choices_are_named_in_the_environment_and_a_wrong_entry_is_told(monkeypatch):
    """``TORCH_STSDIC_CHOICES`` sets the named choices (a fresh process reads it at import:
    ``scripts/benchmarks/device_choices.py`` times them); a malformed entry or an unknown
    name is warned about and skipped, the others still set."""
    from torch_stsdic.core import choices

    for name in ("EVERY_CANDIDATE", "UNTIL_DONE", "MASKED_GROUPS", "MASKED_CHECK"):
        monkeypatch.setattr(choices, name, None)
    with pytest.warns(UserWarning, match="'BOGUS=1' skipped"):
        got = choices.from_environment("MASKED_GROUPS=1, until_done=0,BOGUS=1")
    assert got == {"MASKED_GROUPS": True, "UNTIL_DONE": False}
    assert choices.MASKED_GROUPS is True and choices.UNTIL_DONE is False
    assert choices.EVERY_CANDIDATE is None
    cpu = torch.device("cpu")
    assert choices.masked_groups(cpu) and not choices.until_done(cpu)
    assert not choices.every_candidate(cpu)  # None: the device's (the CPU's: rounds)
    with pytest.warns(UserWarning, match="'MASKED_GROUPS=yes' skipped"):
        choices.from_environment("MASKED_GROUPS=yes")
    assert choices.MASKED_GROUPS is True  # unchanged
    import os
    import subprocess
    import sys

    env = {**os.environ, choices.ENV: "MASKED_GROUPS=1,EVERY_CANDIDATE=0,SEARCH_READS=0"}
    out = subprocess.run([sys.executable, "-c", "from torch_stsdic.core import choices as c; "
                          "print(c.MASKED_GROUPS, c.EVERY_CANDIDATE, c.UNTIL_DONE, "
                          "c.search_reads(__import__('torch').device('cpu')))"],
                         capture_output=True, text=True, env=env, check=True).stdout
    assert out.split() == ["True", "False", "None", "False"]  # read at import
    # the old name is the very module: a choice set there is the one the package reads
    from torch_stsdic.movie import choices as old_name
    assert old_name is choices


def test_device_choices_script_times_the_variants_and_finds_the_same_file(tmp_path):
    """``scripts/benchmarks/device_choices.py`` on a small movie: the default and a GPU's
    choices in fresh processes (set through the environment), their times recorded and the
    files the same to the bit."""
    import json
    from pathlib import Path

    from repo_scripts import load_script  # tests/ on the path

    from torch_stsdic.cli import main

    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "128", "--frames", "8",
                 "--motion", "translation", "--ut", "0.5", "--noise", "2", "--seed", "2",
                 "--threads", "1"]) == 0
    script = load_script(Path(__file__).resolve().parents[1] / "scripts" / "benchmarks"
                         / "device_choices.py", "device_choices")
    rec = tmp_path / "rec.json"
    assert script.main(["--rounds", "1", "--variants", "MASKED_GROUPS=1,EVERY_CANDIDATE=1",
                        "--out", str(rec), "--", str(tmp_path / "m" / "movie.tif"),
                        "--subset", "21", "--step", "12", "--threads", "1"]) == 0
    got = json.loads(rec.read_text())
    assert set(got["summary"]) == {"default", "MASKED_GROUPS=1,EVERY_CANDIDATE=1"}
    assert all(s["identical_to_default"] and s["wall_s"] > 0 for s in got["summary"].values())


def test_a_gpu_runs_classical_blocks_give_the_cpu_runs_file(tmp_path, monkeypatch):
    """A classical run (m = 0, no shared motion) of enough POIs for the pilot points
    (``block_start.pilot_shift``: 48 a target, 384 POIs at least) on a shaking speckle: with
    a GPU's choices the pilots, the carried rows and a rescue's rows from their guesses are
    masked solves (no read of which), with the CPU's each taken by an index; the same file
    to the bit, and the pilots were solved."""
    from torch_stsdic.cli import main
    from torch_stsdic.movie import block_start

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "220", "--frames", "10",
                 "--motion", "translation", "--ut", "0.6", "--vt", "-0.4", "--noise", "2",
                 "--seed", "6", "--threads", "1"]) == 0
    movie = tmp_path / "m" / "movie.tif"
    pilot = block_start.pilot_shift
    pilots = []

    def spy(blk, init, rows):
        out = pilot(blk, init, rows)
        pilots.append(None if out is None else int(out.sum()))
        return out

    monkeypatch.setattr(block_start, "pilot_shift", spy)
    import torch_stsdic.movie.block as block
    monkeypatch.setattr(block, "pilot_shift", spy)
    out = {}
    for gpu in (False, True):
        _take_choices(monkeypatch, gpu)
        pilots.clear()
        out[gpu] = _run(tmp_path, f"c{int(gpu)}", movie, ("--step", "9", "--m", "0",
                                                          "--single-reference"))
        assert pilots and max(p or 0 for p in pilots) >= 48, pilots  # pilots solved
    _same_files(out)
