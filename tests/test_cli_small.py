"""The small ones of issue 34 (item 4): a --reference range past the series is refused, a
mask of another size and a wrong count of --timestamps are usage errors (exit code 2, as
docs/cli.md says), no "-0.0 %" in the summary, and a resumed run says that it resumed, its
POI/s counting only the frames it solved."""

from __future__ import annotations

import argparse
import errno
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig, track
from torch_stsdic.cli import main, run_summary
from torch_stsdic.io.results import ResultWriter

FAST = ["--threads", "1", "--no-progress"]
RUN = ["--subset", "17", "--step", "7", "--m", "1", "--search-radius", "3", "--memory-mb", "0.2",
       "--shared-motion", "none"]


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """12 frames of 81 x 81 px."""
    d = tmp_path_factory.mktemp("movie")
    assert main(["synth", "--out", str(d), "--size", "81", "--frames", "11", "--noise", "1",
                 "--seed", "5", "--threads", "1"]) == 0
    return d / "movie.tif"


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("spec", ["10:20", "0:13", "-20:", "5:30:2"])
def test_reference_range_past_the_series_is_refused(capsys, movie, tmp_path, spec):
    code, _, err = _run(capsys, "run", movie, *RUN, f"--reference={spec}",
                        "--out", tmp_path / "r.h5", *FAST)
    assert code == 2, err
    assert f"--reference {spec}" in err and "0..11" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "r.h5").exists()


def test_reference_range_inside_the_series_is_taken(movie):
    from torch_stsdic.movie.plan import reference_frames

    assert reference_frames("10:12", 12) == [10, 11]
    assert reference_frames("-2:", 12) == [10, 11]
    assert reference_frames("0:5,7", 12) == [0, 1, 2, 3, 4, 7]
    with pytest.raises(ValueError, match="reaches past the series of 12 frames"):
        track(str(movie), reference="10:20", frames=[11], step=30,
              config=DICConfig(subset_size=17, m=0))


def test_mask_of_another_size_is_a_usage_error(capsys, movie, tmp_path):
    np.save(tmp_path / "mask.npy", np.ones((80, 81)))
    code, _, err = _run(capsys, "run", movie, *RUN, "--mask", tmp_path / "mask.npy",
                        "--out", tmp_path / "r.h5", *FAST)
    assert code == 2, err
    assert "--mask" in err and "80x81" in err and "81x81" in err, err


def test_points_outside_the_image_are_a_usage_error(capsys, movie, tmp_path):
    (tmp_path / "p.csv").write_text("x,y\n40,40\n200,40\n")
    code, _, err = _run(capsys, "run", movie, *RUN, "--points", tmp_path / "p.csv",
                        "--out", tmp_path / "r.h5", *FAST)
    assert code == 2, err
    assert "--points" in err and "outside" in err, err


def test_wrong_count_of_timestamps_is_a_usage_error(capsys, movie, tmp_path):
    (tmp_path / "t.csv").write_text("\n".join(str(0.5 * k) for k in range(11)) + "\n")
    code, _, err = _run(capsys, "run", movie, *RUN, "--timestamps", tmp_path / "t.csv",
                        "--out", tmp_path / "r.h5", *FAST)
    assert code == 2, err
    assert "--timestamps" in err and "11" in err and "12 frames" in err, err
    # times that do not increase are a fault of the file, not of the command line
    (tmp_path / "t.csv").write_text("\n".join(str(-k) for k in range(12)) + "\n")
    code, _, err = _run(capsys, "run", movie, *RUN, "--timestamps", tmp_path / "t.csv",
                        "--out", tmp_path / "r.h5", *FAST)
    assert code == 1 and "--timestamps" in err, err


def test_summary_never_says_minus_zero(capsys):
    """1 of 3 results converged, 2 at max-iter: 100 - 33.3.. - 66.6.. is -1.4e-14 in floats."""
    status = np.array([[0, 1, 1]], dtype=np.int8)
    res = SimpleNamespace(status=torch.as_tensor(status), m=None, info={})
    args = argparse.Namespace(reference="0", m=0, device="cpu", resume=False)
    run_summary.print_summary(res, args, 1.0, "movie.tif")
    out = capsys.readouterr().out
    assert "not trusted: 0.0 %" in out, out
    assert "-0.0" not in out, out


def test_resumed_run_says_so_and_counts_only_what_it_solved(capsys, monkeypatch, movie,
                                                           tmp_path):
    out = tmp_path / "r.h5"
    real = ResultWriter.write_rows
    calls = {"n": 0}

    def failing(self, rows, values, *, mark_completed=True):
        if mark_completed:
            calls["n"] += 1
            if calls["n"] == 4:  # blocks of one frame: 3 frames finished
                raise self._write_error(OSError(errno.ENOSPC, "No space left on device"))
        return real(self, rows, values, mark_completed=mark_completed)

    monkeypatch.setattr(ResultWriter, "write_rows", failing)
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1 and "3 of 12 frames finished" in err, err
    monkeypatch.setattr(ResultWriter, "write_rows", real)
    code, text, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    assert "resumed: 3 of 12 frames were finished in the file and kept, 9 solved now" in text
    # the run-level estimates came from the file, and the template's line says so
    assert "the run's estimates read from the result file" in text, text
    assert "(read from the result file, made in" in text, text
    m = re.search(r"time: .*? (\d+) POI/s \(frames solved now\)", text)
    assert m, text
    # a second --resume has nothing left to solve and says so
    code, text, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    assert "resumed: 12 of 12 frames" in text and "no frame left to solve" in text, text
    # a fresh run says nothing of resuming
    code, text, _ = _run(capsys, "run", movie, *RUN, "--out", tmp_path / "b.h5", *FAST)
    assert code == 0 and "resumed:" not in text and "POI/s   (" in text, text
    assert "read from the result file" not in text and "a template of" in text, text


def test_a_run_stopped_before_its_first_frame_keeps_its_estimates(capsys, monkeypatch, movie,
                                                                  tmp_path):
    """The run-level estimates (template, shared motion) are recorded before the first block:
    a run that fails there keeps its file for --resume, which reads them instead of
    measuring them again; with nothing recorded the file is removed as before."""
    out = tmp_path / "r.h5"
    real = ResultWriter.write_rows

    def failing(self, rows, values, *, mark_completed=True):
        if mark_completed:
            raise self._write_error(OSError(errno.ENOSPC, "No space left on device"))
        return real(self, rows, values, mark_completed=mark_completed)

    monkeypatch.setattr(ResultWriter, "write_rows", failing)
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1 and "no frame finished; the run's estimates" in err, err
    assert out.exists() and "--resume" in err
    monkeypatch.setattr(ResultWriter, "write_rows", real)
    code, text, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    assert "resumed: 0 of 12 frames" in text, text
    assert "the run's estimates read from the result file" in text, text
    # a single reference, classical: nothing run-level to keep, so no file is left behind
    out2 = tmp_path / "c.h5"
    monkeypatch.setattr(ResultWriter, "write_rows", failing)
    code, _, err = _run(capsys, "run", movie, *RUN, "--m", "0", "--single-reference",
                        "--shared-motion", "none", "--out", out2, *FAST)
    assert code == 1 and "nothing was written yet" in err and not out2.exists(), err
