"""Disk full and other I/O faults in ``run``, ``export`` and ``plot`` (issue 34, item 3): one
line that names the file, nothing half-written left behind (no 0-byte ``*.creating`` after a
failed start, no truncated CSV / VTU, no 0-byte MAT or PNG), finished frames kept and
``--resume`` working once there is space. Faults are injected by monkeypatching; where a
small tmpfs can be mounted (root on Linux), also on a real full file system."""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

import torch_stsdic.io.results as results_module
from torch_stsdic.cli import main
from torch_stsdic.io.results import ResultWriter

FAST = ["--threads", "1", "--no-progress"]
RUN = ["--subset", "17", "--step", "7", "--m", "1", "--search-radius", "3", "--memory-mb", "0.2",
       "--shared-motion", "none"]
FULL = "no space left on the device (the disk is full)"


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    d = tmp_path_factory.mktemp("movie")
    assert main(["synth", "--out", str(d), "--size", "81", "--frames", "11", "--noise", "1",
                 "--seed", "5", "--threads", "1"]) == 0
    return d / "movie.tif"


@pytest.fixture(scope="module")
def result(movie, tmp_path_factory):
    out = tmp_path_factory.mktemp("res") / "r.h5"
    assert main(["run", str(movie), *RUN, "--out", str(out), *FAST]) == 0
    return out


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _line(err: str) -> str:
    assert "Traceback" not in err and "0x" not in err, err  # no HDF5 paragraph, no pointer
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("stsdic: warning:")]
    assert len(lines) == 1 and lines[0].startswith("stsdic: error: "), err
    return lines[0]


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def _enospc(*_a, **_k):
    raise OSError(errno.ENOSPC, "No space left on device")


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def test_run_full_disk_at_start_leaves_no_creating_file(capsys, monkeypatch, movie, tmp_path):
    """HDF5 fails to make the file (as on a full disk: its own paragraph with errno and a C
    pointer): one line naming the file, no 0-byte ``*.creating`` left."""
    real = h5py.File

    def full(name, mode="r", *args, **kwargs):
        if mode == "w":
            if isinstance(name, (str, os.PathLike)):
                Path(name).touch()  # HDF5 has opened the file when the write fails
            raise ValueError("Unable to synchronously create file (file write failed: time = "
                             "Thu Nov 26 16:51:56 2026 , filename = 'r.h5.creating', file "
                             "descriptor = 3, errno = 28, error message = 'No space left on "
                             "device', buf = 0x558e95ce5068, total write size = 96)")
        return real(name, mode, *args, **kwargs)

    monkeypatch.setattr(results_module.h5py, "File", full)
    out = tmp_path / "r.h5"
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1
    line = _line(err)
    assert f"cannot create the result file {out}: {FULL}" in line, line
    assert _files(tmp_path) == []


def test_run_refuses_a_disk_without_room_before_hdf5_writes(capsys, monkeypatch, movie,
                                                           tmp_path):
    """Too little free space for the result file: refused before HDF5 writes a byte (HDF5
    meeting a full disk half-way can crash the interpreter when it exits)."""
    real = results_module.shutil.disk_usage

    def small(path):
        u = real(path)
        return type(u)(u.total, u.total - 4096, 4096)

    monkeypatch.setattr(results_module.shutil, "disk_usage", small)
    out = tmp_path / "r.h5"
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1
    line = _line(err)
    assert str(out) in line and FULL in line and "4.1 kB free" in line, line
    assert line.count(str(out)) == 1, line  # said once
    assert _files(tmp_path) == []


def test_run_full_disk_mid_run_keeps_frames_then_resumes(capsys, monkeypatch, movie, result,
                                                        tmp_path):
    """HDF5 fails writing a frame's data (its error text carries the errno): the finished
    frames stay, one line names the file, and --resume finishes identically."""
    out = tmp_path / "r.h5"
    real = h5py.Dataset.__setitem__
    state = {"n": 0, "armed": True}

    def failing(self, key, value):
        if state["armed"] and self.name == "/u":
            state["n"] += 1
            if state["n"] == 4:
                raise OSError("Can't write data (file write failed: time = ..., errno = 28, "
                              "error message = 'No space left on device', buf = 0x7f0c)")
        return real(self, key, value)

    monkeypatch.setattr(h5py.Dataset, "__setitem__", failing)
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1
    line = _line(err)
    assert f"cannot write the result file {out}: {FULL}" in line, line
    assert "3 of 12 frames finished" in line and "--resume" in line, line
    state["armed"] = False
    code, text, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    assert "resumed: 3 of 12" in text
    with h5py.File(out, "r") as a, h5py.File(result, "r") as b:
        assert a["completed"][()].all()
        for k in ("u", "v", "status"):
            np.testing.assert_array_equal(a[k][()], b[k][()], err_msg=k)


def test_writer_names_the_file_for_every_write(tmp_path, monkeypatch):
    """Strains and the shared motion (written after the frames) fail as one OSError naming
    the file, like the frames."""
    w = ResultWriter(tmp_path / "r.h5", points=np.zeros((2, 2)), frames=np.arange(3),
                     times=np.arange(3.0), config={}, inputs=[])
    monkeypatch.setattr(h5py.Group, "create_dataset", lambda *a, **k: _enospc())
    with pytest.raises(OSError, match=f"cannot write the result file .*r.h5: {re.escape(FULL)}"):
        w.write_array("shared_motion", np.zeros((3, 6)))
    with pytest.raises(OSError, match=f"cannot write the result file .*r.h5: {re.escape(FULL)}"):
        w.add_fields({"exx": np.zeros((3, 2))})
    w.close(commit=False)


# ----------------------------------------------------------------------------------------
# export and plot
# ----------------------------------------------------------------------------------------


class _FillingFile:
    """A text file that takes ``room`` characters, then fails as a full disk does."""

    def __init__(self, fh, room):
        self.fh, self.room = fh, room

    def write(self, text):
        if len(text) > self.room:
            self.fh.write(text[: self.room])
            self.fh.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(text)
        return self.fh.write(text)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.fh.close()


def test_export_csv_full_disk_leaves_no_truncated_file(capsys, monkeypatch, result, tmp_path):
    import torch_stsdic.analysis.export as export_module

    opened = {"n": 0}

    def fake_open(path, mode="r", **kw):
        fh = open(path, mode, **kw)  # noqa: SIM115
        if "w" in mode and str(path).endswith(".csv"):
            opened["n"] += 1
            if opened["n"] == 3:  # the disk fills during the third frame's file
                return _FillingFile(fh, 500)
        return fh

    monkeypatch.setattr(export_module, "open", fake_open, raising=False)
    out = tmp_path / "csv"
    (out).mkdir()
    (out / "r_frame00002.csv").write_text("old export\n")  # an earlier export: kept as it was
    code, _, err = _run(capsys, "export", result, "--out", out)
    assert code == 1
    line = _line(err)
    assert f"cannot write {out / 'r_frame00002.csv'}: {FULL}" in line, line
    assert "2 file(s) finished before it are whole" in line, line
    assert _files(out) == ["r_frame00000.csv", "r_frame00001.csv", "r_frame00002.csv"]
    assert (out / "r_frame00002.csv").read_text() == "old export\n"
    for p in (out / "r_frame00000.csv", out / "r_frame00001.csv"):
        assert len(p.read_text().splitlines()) == 65  # header + 64 points: whole


def test_export_mat_full_disk_leaves_no_empty_file(capsys, monkeypatch, result, tmp_path):
    pytest.importorskip("scipy")
    import scipy.io

    def full(path, *a, **k):
        Path(path).write_bytes(b"")  # the file is made, then the disk is full
        _enospc()

    monkeypatch.setattr(scipy.io, "savemat", full)
    out = tmp_path / "mat"
    code, _, err = _run(capsys, "export", result, "--format", "mat", "--out", out)
    assert code == 1
    line = _line(err)
    assert f"cannot write {out / 'r.mat'}: {FULL}" in line, line
    assert _files(out) == []


def test_export_vtk_full_disk_leaves_no_truncated_file(capsys, monkeypatch, result, tmp_path):
    real = Path.write_text
    calls = {"n": 0}

    def filling(self, text, *a, **k):
        if self.suffix == ".vtu":
            calls["n"] += 1
            if calls["n"] == 2:
                real(self, text[:100], *a, **k)
                _enospc()
        return real(self, text, *a, **k)

    monkeypatch.setattr(Path, "write_text", filling)
    out = tmp_path / "vtk"
    code, _, err = _run(capsys, "export", result, "--format", "vtk", "--out", out)
    assert code == 1
    line = _line(err)
    assert f"cannot write {out / 'r_frame00001.vtu'}: {FULL}" in line, line
    assert _files(out) == ["r_frame00000.vtu"]


def test_plot_full_disk_leaves_no_truncated_png(capsys, monkeypatch, result, tmp_path):
    from matplotlib.figure import Figure

    def full(self, fname, *a, **k):
        Path(fname).write_bytes(b"\x89PNG\r\n\x1a\n")  # a few bytes, then the disk is full
        _enospc()

    monkeypatch.setattr(Figure, "savefig", full)
    out = tmp_path / "plots"
    code, _, err = _run(capsys, "plot", result, "--out", out, "--no-image")
    assert code == 1
    line = _line(err)
    assert f"cannot write {out / 'fields_frame00011.png'}: {FULL}" in line, line
    assert _files(out) == []


# ----------------------------------------------------------------------------------------
# a real full file system
# ----------------------------------------------------------------------------------------


def _fill(folder: Path, leave: int) -> None:
    """Fill ``folder``'s file system but ``leave`` bytes (within a page)."""
    free = os.statvfs(folder).f_bavail * os.statvfs(folder).f_frsize
    with open(folder / "filler", "wb") as fh:
        fh.write(b"\0" * max(0, free - leave))


@pytest.mark.parametrize("leave", [0, 4096, 40960], ids=["full", "4k", "40k"])
def test_real_full_disk(capsys, movie, result, tmp_path, leave, tmpfs):
    """On a real small file system filled up: run, export and plot each fail with one line
    naming the file and leave nothing half-written (the filler aside)."""
    with tmpfs(tmp_path / "small", "size=96k") as d:
        _fill(d, leave)
        code, _, err = _run(capsys, "run", movie, *RUN, "--out", d / "r.h5", *FAST)
        assert code == 1 and str(d / "r.h5") in _line(err) and FULL in err
        code, _, err = _run(capsys, "export", result, "--out", d / "csv")
        assert code == 1 and "cannot write" in _line(err) and FULL in err
        code, _, err = _run(capsys, "export", result, "--format", "mat", "--out", d / "mat")
        if code:  # a compressed .mat may fit in 40 kB
            assert "cannot write" in _line(err) and FULL in err
        code, _, err = _run(capsys, "plot", result, "--out", d / "p", "--no-image")
        assert code == 1 and "cannot write" in _line(err) and FULL in err
        for p in d.rglob("*"):
            if p.is_file() and p.name != "filler":
                assert p.stat().st_size > 0 and not p.name.startswith("."), p
                assert not p.name.endswith((".creating", ".partial")), p
                if p.suffix == ".csv":
                    assert len(p.read_text().splitlines()) == 65, p
