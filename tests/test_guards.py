"""Input guards of issue 24: nothing the user gave is lost, no empty file is left behind, and
every entry point refuses the same bad images."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import tifffile

from torch_stsdic.cli import main

FAST = ["--threads", "1", "--no-progress"]


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(code: int, err: str, *names: str) -> str:
    assert code != 0
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("stsdic: error: "), lines[0]
    assert "Traceback" not in err and "Errno" not in err, err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def movie(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("movie")
    assert main(["synth", "--out", str(d), "--size", "61", "--frames", "6", "--noise", "1",
                 "--threads", "1"]) == 0  # fmt: skip
    return d / "movie.tif"


# ----------------------------------------------------------------------------------------
# 1. an output that is one of the inputs is refused, whatever the flags
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("flag", [[], ["--overwrite"], ["--resume"]])
def test_out_is_the_input_movie(capsys, movie, tmp_path, flag):
    mv = tmp_path / "movie.tif"
    shutil.copy(movie, mv)
    before = mv.read_bytes()
    code, _, err = _run(capsys, "run", mv, "--out", mv, *flag, *FAST)
    _one_line(code, err, "--out", "input")
    assert mv.read_bytes() == before
    assert not list(tmp_path.glob("*.partial"))


def test_out_is_a_frame_of_a_folder_or_a_side_file(capsys, movie, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    stack = tifffile.imread(movie)
    for i, im in enumerate(stack):
        tifffile.imwrite(frames / f"f{i}.tif", im)
    target = frames / "f3.tif"
    before = target.read_bytes()
    for src in (frames, str(frames / "f*.tif")):
        code, _, err = _run(capsys, "run", src, "--out", target, "--overwrite", *FAST)
        _one_line(code, err, "f3.tif", "input")
        assert target.read_bytes() == before
    pts = tmp_path / "pts.csv"
    pts.write_text("x,y\n30,30\n")
    link = tmp_path / "link.csv"
    link.symlink_to(pts)  # another name of the same file
    code, _, err = _run(capsys, "run", movie, "--points", pts, "--out", link, "--overwrite", *FAST)
    _one_line(code, err, "--points")
    assert pts.read_text() == "x,y\n30,30\n"
