"""Camera movies as image series (torch_stsdic.io.photron / phantom / video): the shared real
samples against their headers and the reference readers (pyMRAW, pycine), movies written as
MRAW and lossless AVI against the same frames as TIFF, and the errors of broken files."""

from __future__ import annotations

import builtins
import ctypes
import pickle
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

from torch_stsdic.cli import main
from torch_stsdic.io import InputError, load_series, read_results
from torch_stsdic.io.photron import write_mraw

CAMERAS = Path(__file__).resolve().parents[2] / "shared" / "data" / "highspeed-camera"
needs_samples = pytest.mark.skipif(
    not (CAMERAS / "ball_12bit.cihx").exists(),
    reason=f"high-speed camera samples not found at {CAMERAS} (../shared/data)")

FAST = ["--threads", "1", "--no-progress"]
RUN = ["--subset", "17", "--step", "9", "--m", "1", "--search-radius", "3",
       "--shared-motion", "none"]


def _quiet_load(source, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_series(source, **kw)


# ---------------------------------------------------------------------------------------
# the shared real samples: their README's truth and the reference readers' grey values
# ---------------------------------------------------------------------------------------


@needs_samples
@pytest.mark.parametrize("name, frames, hw, bits, fps", [
    ("ball_12bit.cihx", 15, (384, 384), 12, 30000.0),
    ("ball_12bit.mraw", 15, (384, 384), 12, 30000.0),
    ("beam.cihx", 4, (80, 1024), 12, 50000.0),
    ("chart1.cine", 1, (1080, 2048), 12, 25.0),
])
def test_samples_read_as_their_headers_say(name, frames, hw, bits, fps):
    s = _quiet_load(CAMERAS / name)
    assert (len(s), s.shape, s.bit_depth, s.frame_rate) == (frames, hw, bits, fps)
    assert s.dtype_name == "uint16"
    np.testing.assert_array_equal(s.times, np.arange(frames) / fps)
    assert s.time_unit == "s" and f"{fps:g} /s" in s.describe()


@needs_samples
@pytest.mark.parametrize("name", ["ball_12bit.cihx", "beam.cihx"])
def test_photron_grey_values_equal_pymraw(name):
    pymraw = pytest.importorskip("pyMRAW")
    ref, cih = pymraw.load_video(str(CAMERAS / name))
    s = load_series(CAMERAS / name)
    got = np.stack([s._raw(i) for i in range(len(s))])
    assert got.dtype == np.uint16 and got.shape == ref.shape
    np.testing.assert_array_equal(got, ref)
    if name == "ball_12bit.cihx":  # the README's grey range
        assert (int(got.min()), int(got.max())) == (84, 4095)
    np.testing.assert_array_equal(s.read(":").numpy(), ref.astype(np.float32))
    assert s.frame_rate == cih["Record Rate(fps)"]


@needs_samples
def test_cine_grey_values_equal_pycine():
    raw = pytest.importorskip("pycine.raw")
    frames, _, bpp = raw.read_frames(str(CAMERAS / "chart1.cine"))
    ref = next(frames)
    with pytest.warns(UserWarning, match="colour filter array"):
        s = load_series(CAMERAS / "chart1.cine")
    assert s.bit_depth == bpp == 12
    np.testing.assert_array_equal(s._raw(0), ref)


@needs_samples
def test_stsdic_run_on_the_12bit_photron_sample_runs_to_the_end(tmp_path, capsys):
    out = tmp_path / "ball.h5"
    code = main(["run", str(CAMERAS / "ball_12bit.cihx"), "--out", str(out), *FAST])
    text = capsys.readouterr().out
    assert code == 0
    assert "t=0..0.000466667 s (frame rate 30000 /s of ball_12bit.cihx)" in text
    res = read_results(out)
    assert res.u.shape[0] == 15 and (res.status <= 1).mean() > 0.9
    np.testing.assert_allclose(res.times, np.arange(15) / 30000.0)
    assert res.attrs["time_unit"] == "s"
    assert res.attrs["time_source"] == "frame rate 30000 /s of ball_12bit.cihx"


# ---------------------------------------------------------------------------------------
# a speckle movie as MRAW (pyMRAW's writer, ours) and as lossless AVI = the same as TIFF
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def speckle(tmp_path_factory):
    """14 frames of 64 x 72 px, 12-bit in uint16, as TIFF, and where the frames are."""
    d = tmp_path_factory.mktemp("speckle")
    assert main(["synth", "--out", str(d), "--size", "72", "64", "--frames", "13", "--noise",
                 "1", "--bits", "12", "--seed", "4", "--threads", "1"]) == 0
    return d, tifffile.imread(d / "movie.tif")


def test_our_mraw_writer_reads_back_with_pymraw(speckle, tmp_path):
    pymraw = pytest.importorskip("pyMRAW")
    _, frames = speckle
    mraw, cih = write_mraw(tmp_path / "m.mraw", frames, 2000.0)
    ref, info = pymraw.load_video(str(cih))
    np.testing.assert_array_equal(ref, frames)
    assert info["Record Rate(fps)"] == 2000 and info["EffectiveBit Depth"] == 12


def _movies(speckle, tmp_path, fps):
    """The speckle frames as pyMRAW's MRAW and as a lossless AVI (FFV1)."""
    pymraw = pytest.importorskip("pyMRAW")
    pytest.importorskip("av")
    from torch_stsdic.io.video import write_video

    _, frames = speckle
    _, cih = pymraw.save_mraw(frames, str(tmp_path / "py" / "movie.cih"), bit_depth=16,
                              info_dict={"Record Rate(fps)": f"{fps:g}"})
    avi = write_video(tmp_path / "movie.avi", frames, fps)
    return {"mraw": Path(cih), "avi": avi}


def test_mraw_and_avi_give_the_tiff_frames_and_times_k_over_fps(speckle, tmp_path):
    fps = 250.0
    d, frames = speckle
    for kind, path in _movies(speckle, tmp_path, fps).items():
        s = load_series(path)
        assert (len(s), s.shape, s.frame_rate) == (14, (64, 72), fps), kind
        np.testing.assert_array_equal(s.times, np.arange(14) / fps)
        order = [0, 13, 5, 6, 7, 1, 12, 2, 2, 9]  # jumps back and forth
        for i in order:
            np.testing.assert_array_equal(s.numpy(i), frames[i].astype(np.float32))
        again = pickle.loads(pickle.dumps(s))  # no open file travels; it reopens
        np.testing.assert_array_equal(again.numpy(3), frames[3].astype(np.float32))


def test_runs_on_mraw_and_avi_equal_the_run_on_tiff(speckle, tmp_path, capsys):
    fps = 250.0
    d, _ = speckle
    movies = _movies(speckle, tmp_path, fps)
    times = tmp_path / "times.csv"
    times.write_text("".join(f"{k / fps!r}\n" for k in range(14)))
    runs = {"tiff": [d / "movie.tif", "--timestamps", times], "frames": [d / "movie.tif"],
            **{kind: [path] for kind, path in movies.items()}}
    results = {}
    for kind, inputs in runs.items():
        out = tmp_path / f"{kind}.h5"
        assert main(["run", *map(str, inputs), *RUN, "--out", str(out), *FAST]) == 0, kind
        results[kind] = read_results(out)
    capsys.readouterr()
    tiff, frames = results["tiff"], results["frames"]
    ok = tiff.status <= 1
    assert ok.mean() > 0.9
    for kind in movies:
        res = results[kind]
        np.testing.assert_array_equal(res.status, tiff.status)
        assert np.nanmax(np.abs(res.u - tiff.u)) <= 1e-6
        assert np.nanmax(np.abs(res.v - tiff.v)) <= 1e-6
        np.testing.assert_allclose(res.times, np.arange(14) / fps)
        assert res.attrs["time_unit"] == "s" and "250 /s" in res.attrs["time_source"]
        # against the frames' own times (0, 1, 2 ...): the same statuses, u and v within
        # float32 round-off of the time scale, velocities per second = per frame * fps
        np.testing.assert_array_equal(res.status, frames.status)
        assert np.nanmax(np.abs(res.u - frames.u)) <= 1e-5
        assert frames.attrs["time_unit"] == "frame"
        np.testing.assert_allclose(res.ut[ok], frames.ut[ok] * fps, rtol=1e-4, atol=1e-3)


def test_timestamps_given_replace_the_frame_rate(speckle, tmp_path):
    d, frames = speckle
    _, cih = write_mraw(tmp_path / "m.mraw", frames, 2000.0)
    s = load_series(cih, timestamps=np.arange(14) * 0.5)
    np.testing.assert_array_equal(s.times, np.arange(14) * 0.5)
    assert s.time_unit is None and s.time_source is None and " s (" not in s.describe()
    again = load_series(load_series(cih), timestamps=np.arange(14) * 2.0)
    assert again.time_unit is None


def test_synth_writes_mraw_and_avi(tmp_path, capsys):
    for fmt in ("mraw", "avi"):
        if fmt == "avi":
            pytest.importorskip("av")
        out = tmp_path / fmt
        assert main(["synth", "--out", str(out), "--format", fmt, "--size", "40", "--frames",
                     "3", "--bits", "16", "--fps", "500", "--threads", "1"]) == 0
        s = load_series(out / ("movie.cih" if fmt == "mraw" else "movie.avi"))
        assert (len(s), s.shape, s.frame_rate) == (4, (40, 40), 500.0)
    code = main(["synth", "--out", str(tmp_path / "f"), "--format", "mraw", "--bits", "0"])
    assert code != 0 and "--bits 8 to 16" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------
# other layouts and broken files
# ---------------------------------------------------------------------------------------


def _pack12(a: np.ndarray) -> bytes:
    v = a.astype(np.uint16).reshape(-1, 2)
    b = np.empty((v.shape[0], 3), np.uint8)
    b[:, 0] = v[:, 0] >> 4
    b[:, 1] = ((v[:, 0] & 15) << 4) | (v[:, 1] >> 8)
    b[:, 2] = v[:, 1] & 255
    return b.tobytes()


def test_photron_8_and_12_bit_and_a_cihx_header(tmp_path):
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 4096, (5, 6, 10)).astype(np.uint16)
    (tmp_path / "p12.mraw").write_bytes(b"".join(_pack12(f) for f in frames))
    xml = ("<cih><imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo><imageDataInfo>"
           "<resolution><width>10</width><height>6</height></resolution><colorInfo><type>Raw"
           "</type><bit>12</bit></colorInfo><effectiveBit><depth>12</depth><side>Lower</side>"
           "</effectiveBit></imageDataInfo><frameInfo><totalFrame>5</totalFrame><startFrame>"
           "7</startFrame></frameInfo><recordInfo><recordRate>125</recordRate></recordInfo>"
           "</cih>")
    (tmp_path / "p12.cihx").write_bytes(b"!!! binary preamble\x00\x00" + xml.encode())
    s = load_series(tmp_path / "p12.cihx")
    assert (len(s), s.shape, s.bit_depth, s.frame_rate) == (5, (6, 10), 12, 125.0)
    np.testing.assert_array_equal(np.stack([s._raw(i) for i in range(5)]), frames)
    eight = (frames >> 4).astype(np.uint8)
    _, cih = write_mraw(tmp_path / "p8.mraw", eight, 60.0)
    s8 = load_series(cih)
    assert (s8.dtype_name, s8.bit_depth) == ("uint8", 8)
    np.testing.assert_array_equal(s8.read(":").numpy(), eight.astype(np.float32))


def test_broken_photron_files_are_one_line_errors(tmp_path):
    frames = np.zeros((4, 8, 8), np.uint16)
    mraw, cih = write_mraw(tmp_path / "m.mraw", frames, 100.0)
    mraw.write_bytes(mraw.read_bytes()[:-10])
    with pytest.raises(InputError, match=r"m\.mraw is truncated: its 4 frames of 8x8 px"):
        load_series(cih)
    cih.unlink()
    with pytest.raises(InputError, match=r"its header m\.cihx or m\.cih is missing"):
        load_series(mraw)
    lone = tmp_path / "lone.cih"
    lone.write_text("Total Frame : 2\n")
    with pytest.raises(InputError, match=r"lone\.mraw are missing"):
        load_series(lone)


def _write_cine(path: Path, frames: np.ndarray, fps: int, black: int, white: int,
                real_bpp: int) -> None:
    """An uncompressed 16-bit grey cine (rows bottom-up), its headers made with pycine's
    own structures."""
    cine = pytest.importorskip("pycine.cine")
    n, h, w = frames.shape
    fh, bi, setup = cine.CINEFILEHEADER(), cine.BITMAPINFOHEADER(), cine.SETUP()
    off_bi = ctypes.sizeof(fh)
    off_setup = off_bi + ctypes.sizeof(bi)
    off_table = off_setup + ctypes.sizeof(setup)
    first = off_table + 8 * n
    fh.Type, fh.Headersize, fh.Version, fh.ImageCount = 18755, 44, 1, n
    fh.OffImageHeader, fh.OffSetup, fh.OffImageOffsets = off_bi, off_setup, off_table
    bi.biSize, bi.biWidth, bi.biHeight, bi.biBitCount = 40, w, h, 16
    bi.biSizeImage = w * h * 2
    setup.FrameRate16, setup.FrameRate, setup.RealBPP = fps, fps, real_bpp
    setup.BlackLevel, setup.WhiteLevel, setup.Length = black, white, ctypes.sizeof(setup)
    offsets = [first + k * (8 + w * h * 2) for k in range(n)]
    with open(path, "wb") as f:
        f.write(bytes(fh) + bytes(bi) + bytes(setup) + struct.pack(f"<{n}q", *offsets))
        for fr in frames:
            f.write(struct.pack("<II", 8, w * h * 2) + fr[::-1].astype("<u2").tobytes())


def test_uncompressed_cine_against_pycine(tmp_path):
    raw = pytest.importorskip("pycine.raw")
    rng = np.random.default_rng(2)
    frames = rng.integers(64, 4000, (3, 6, 8)).astype(np.uint16)
    _write_cine(tmp_path / "g.cine", frames, 7000, 64, 4000, 12)
    s = load_series(tmp_path / "g.cine")
    assert (len(s), s.shape, s.bit_depth, s.frame_rate) == (3, (6, 8), 12, 7000.0)
    got = np.stack([s._raw(i) for i in range(3)])
    np.testing.assert_array_equal(got, frames)  # the stored samples, top row first
    ref = np.stack(list(raw.read_frames(str(tmp_path / "g.cine"))[0]))
    # pycine stretches black..white level to the full 12 bits
    np.testing.assert_array_equal(np.interp(got, [64, 4000], [0, 4095]).astype(np.uint16), ref)


def test_not_a_cine_and_a_missing_pyav_are_one_line_errors(tmp_path, monkeypatch):
    (tmp_path / "x.cine").write_bytes(b"XX" + bytes(100))
    with pytest.raises(InputError, match=r"x\.cine: not a Phantom cine file"):
        load_series(tmp_path / "x.cine")
    (tmp_path / "v.avi").write_bytes(bytes(100))
    real = builtins.__import__

    def no_av(name, *a, **k):
        if name == "av" or name.startswith("av."):
            raise ImportError("No module named 'av'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_av)
    with pytest.raises(InputError) as err:
        load_series(tmp_path / "v.avi")
    assert str(err.value) == ('reading video files needs PyAV: pip install '
                              '"torch_stsdic[cameras]" (or pip install av)')


def test_a_lossy_video_is_read_with_a_warning(tmp_path):
    av = pytest.importorskip("av")
    path = tmp_path / "lossy.avi"
    with av.open(str(path), "w") as c:
        st = c.add_stream("mpeg4", rate=25)
        st.width, st.height, st.pix_fmt = 32, 32, "yuv420p"
        for k in range(3):
            img = np.full((32, 32, 3), 40 * k, np.uint8)
            c.mux(st.encode(av.VideoFrame.from_ndarray(img, format="rgb24")))
        c.mux(st.encode(None))
    with pytest.warns(UserWarning, match="codec 'mpeg4' is lossy"):
        s = load_series(path)
    assert (len(s), s.shape, s.dtype_name, s.frame_rate) == (3, (32, 32), "uint8", 25.0)
    assert abs(float(s.numpy(2).mean()) - s.numpy(2)[0, 0]) < 1  # a flat luma plane


@pytest.mark.parametrize("rate, ext", [(30000.0, "mkv"), (24.0, "mkv"), (1000.0, "avi")])
def test_video_frames_in_any_order(tmp_path, rate, ext):
    """Matroska's 1 ms ticks do not tell 30,000 /s frames apart: no seeking by them there."""
    pytest.importorskip("av")
    from torch_stsdic.io.video import write_video

    rng = np.random.default_rng(5)
    frames = rng.integers(0, 256, (60, 12, 20)).astype(np.uint8)
    s = load_series(write_video(tmp_path / f"v.{ext}", frames, rate))
    assert (len(s), s.frame_rate) == (60, rate)
    order = [59, 0, 30, 31, 29, 5, 58, 2, 40, 41, 42, 10, *rng.integers(0, 60, 40).tolist()]
    for i in order:
        np.testing.assert_array_equal(s.numpy(i), frames[i].astype(np.float32))


def test_an_avi_rate_the_container_cannot_store_is_refused(tmp_path):
    pytest.importorskip("av")
    from torch_stsdic.io.video import write_video

    with pytest.raises(ValueError, match="does not store 2500 frames/s.*write a .mkv"):
        write_video(tmp_path / "v.avi", np.zeros((3, 8, 8), np.uint8), 2500.0)
    assert not (tmp_path / "v.avi").exists()


def test_a_time_unit_other_than_the_movies_is_refused(speckle, tmp_path, capsys):
    _, frames = speckle
    _, cih = write_mraw(tmp_path / "m.mraw", frames, 2000.0)
    code = main(["run", str(cih), *RUN, "--time-unit", "ms", "--out", str(tmp_path / "r.h5"),
                 *FAST])
    err = capsys.readouterr().err
    assert code != 0
    assert "time_unit: the times are in s, from the frame rate 2000 /s of m.cih; give " \
        "timestamps for another unit" in err
