"""``stsdic synth`` renders, writes and checks a movie one frame at a time (issue 50): the
files hold the very numbers of the whole-movie rendering (:func:`synthetic_movie`), and the
whole movie is never made."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import torch

from torch_stsdic import synth
from torch_stsdic.cli import main
from torch_stsdic.io import load_series


def test_iter_series_gives_the_images_of_render_series():
    pattern = synth.make_speckle((40, 48), radius=2.0, seed=5, margin=16.0)
    motion = synth.HomogeneousStrain(exx=0.01, exy=0.004, center=(23.5, 19.5), rate=1.0)
    times = torch.arange(1.0, 6.0)
    for kw in ({"noise_sigma": 3.0, "bits": 12, "seed": 9}, {"noise_sigma": 0.0},
               {"noise_sigma": 2.0, "reference_time": None}):
        ref, frames = synth.render_series(pattern, (40, 48), motion, times, **kw)
        images = list(synth.iter_series(pattern, (40, 48), motion, times, **kw))
        assert len(images) == 6
        assert torch.equal(images[0], ref) and torch.equal(torch.stack(images[1:]), frames)
    motion2, tt, it = synth.synthetic_images((33, 33), 4, noise_sigma=5.0, bits=8, seed=2)
    mv = synth.synthetic_movie((33, 33), 4, noise_sigma=5.0, bits=8, seed=2)
    got = list(it)
    assert torch.equal(tt, mv.times) and repr(motion2) == repr(mv.motion)
    assert torch.equal(got[0], mv.ref) and torch.equal(torch.stack(got[1:]), mv.frames)


def _whole_movie(size: int, frames: int, noise: float, seed: int) -> np.ndarray:
    """The movie as ``stsdic synth`` wrote it before it streamed: the whole stack rendered
    by :func:`synthetic_movie` (its margin for the default translation), then quantised."""
    import math

    from torch_stsdic.cli.synth import _max_border_motion

    motion = synth.Translation(ut=0.05)
    reach = _max_border_motion(motion, size, size, np.arange(frames + 1.0))
    margin = max(16.0, 8.0 * 2.0) + math.ceil(reach)
    mv = synth.synthetic_movie((size, size), frames, motion, noise_sigma=noise, seed=seed,
                               radius=2.0, margin=margin)
    return synth.quantize(torch.cat([mv.ref[None], mv.frames]), 8).numpy().astype(np.uint8)


@pytest.mark.parametrize("layout", ["multipage", "files"])
def test_synth_writes_the_whole_movies_numbers_frame_by_frame(layout, tmp_path, monkeypatch):
    import torch_stsdic.cli.synth as cli_synth

    def refuse(*args, **kwargs):
        raise AssertionError("synth made the whole movie at once")

    monkeypatch.setattr(synth, "synthetic_movie", refuse)
    monkeypatch.setattr(cli_synth, "TRUTH_CHUNK", 50)  # the truth a few frames at a time
    out = tmp_path / layout
    assert main(["synth", "--out", str(out), "--size", "41", "--frames", "6", "--noise", "2",
                 "--seed", "4", "--layout", layout, "--truth-step", "8",
                 "--threads", "1"]) == 0
    monkeypatch.undo()
    want = _whole_movie(41, 6, 2.0, 4)
    if layout == "multipage":
        got = tifffile.imread(out / "movie.tif")
        assert len(tifffile.TiffFile(out / "movie.tif").series) == 1
    else:
        got = np.stack([tifffile.imread(out / f"frame_{k:05d}.tif") for k in range(7)])
    assert got.shape == want.shape and got.dtype == np.uint8
    np.testing.assert_array_equal(got, want)
    s = load_series(out / "movie.tif" if layout == "multipage" else out)
    assert len(s) == 7 and s.shape == (41, 41)
    # the ground truth: every frame and point, as the whole truth formats it
    meta = json.loads((out / "motion.json").read_text())
    xs = np.arange(0, 41, 8, dtype=np.float64)
    gx, gy = np.meshgrid(xs, xs)
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    times = np.arange(7, dtype=np.float64)
    tr = synth.ground_truth(synth.Translation(ut=0.05), pts, times)
    keys = ("u", "v", "ut", "vt", "dudx", "dudy", "dvdx", "dvdy")
    lines = ["frame,time,x,y," + ",".join(keys)]
    for f in range(7):
        for j in range(len(pts)):
            vals = ",".join(f"{float(tr[k][f, j]):.10g}" for k in keys)
            lines.append(f"{f},{times[f]:g},{pts[j, 0]:g},{pts[j, 1]:g},{vals}")
    assert (out / "truth.csv").read_text() == "\n".join(lines) + "\n"
    assert meta["truth"]["points"] == len(pts) and meta["frames"] == 7


def test_camera_writers_take_frames_one_at_a_time(tmp_path):
    from torch_stsdic.io.photron import write_mraw

    frames = (np.arange(4 * 12 * 10, dtype=np.uint16).reshape(4, 12, 10) * 9)
    whole = write_mraw(tmp_path / "a.mraw", frames, 500.0)
    one_by_one = write_mraw(tmp_path / "b.mraw", (f for f in frames), 500.0)
    assert whole[0].read_bytes() == one_by_one[0].read_bytes()
    assert whole[1].read_text() == one_by_one[1].read_text()
    with pytest.raises(ValueError, match="frame 1"):
        write_mraw(tmp_path / "c.mraw", iter([frames[0], frames[1, :5]]), 500.0)
    pytest.importorskip("av")
    from torch_stsdic.io.video import write_video

    path = write_video(tmp_path / "m.avi", (f for f in frames), 500.0)
    s = load_series(path)
    np.testing.assert_array_equal(np.stack([s.get(k).numpy() for k in range(4)]), frames)
