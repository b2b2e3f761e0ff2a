"""Tests for torch_stsdic.io: lazy image-series input and HDF5 result files."""

from __future__ import annotations

import csv
import pickle
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
import torch
from PIL import Image

from torch_stsdic.analysis.export import export_csv
from torch_stsdic.core.status import Status
from torch_stsdic.io import (
    CSV_COLUMNS,
    RESULTS_FORMAT,
    ImageSeries,
    InputError,
    ResultFileError,
    ResultWriter,
    load_series,
    natural_sort_key,
    parse_frame_spec,
    read_results,
)

REPO = Path(__file__).resolve().parents[1]


def _stack(t: int = 6, h: int = 12, w: int = 16, dtype: type = np.uint8) -> np.ndarray:
    rng = np.random.default_rng(0)
    hi = np.iinfo(dtype).max if np.dtype(dtype).kind in "iu" else 1.0
    return (rng.random((t, h, w)) * hi).astype(dtype)


# ------------------------------------------------------------------------------------------
# image series
# ------------------------------------------------------------------------------------------


def test_tiff_stack_and_file_lists_give_same_frames(tmp_path: Path) -> None:
    a = _stack()
    tifffile.imwrite(tmp_path / "stack.tif", a)
    pngs, tifs = [], []
    for i, fr in enumerate(a):
        Image.fromarray(fr).save(tmp_path / f"f{i}.png")
        tifffile.imwrite(tmp_path / f"g{i}.tif", fr)
        pngs.append(tmp_path / f"f{i}.png")
        tifs.append(str(tmp_path / f"g{i}.tif"))
    s_stack = load_series(tmp_path / "stack.tif")
    s_png = load_series(pngs)
    s_tif = load_series(tifs)
    for s in (s_stack, s_png, s_tif):
        assert len(s) == 6 and s.shape == (12, 16)
        assert s.dtype_name == "uint8" and s.bit_depth == 8 and s.max_value == 255
        x = s.read(range(6))
        assert x.shape == (6, 12, 16) and x.dtype == torch.float32
        np.testing.assert_array_equal(x.numpy(), a.astype(np.float32))
        assert s[2].shape == (12, 16)
        np.testing.assert_array_equal(s[-1].numpy(), a[-1])
        np.testing.assert_array_equal(s.times, np.arange(6.0))
        assert "6 frames of 12x16" in s.describe()
    assert s_stack.sources == [str(tmp_path / "stack.tif")]
    assert s_png.sources == [str(p) for p in pngs]
    assert s_stack.frame_name(3).endswith("stack.tif (page 3)")
    g = s_stack.get(1, dtype=torch.float64)
    assert g.dtype == torch.float64
    np.testing.assert_array_equal(g.numpy(), a[1])
    # a list mixing a multi-page TIFF and single files concatenates frames
    s_mix = load_series([tmp_path / "stack.tif", tmp_path / "f0.png"])
    assert len(s_mix) == 7
    np.testing.assert_array_equal(s_mix[6].numpy(), a[0])


def test_mean_and_read_specs(tmp_path: Path) -> None:
    a = _stack(t=8)
    tifffile.imwrite(tmp_path / "s.tif", a)
    s = load_series(tmp_path / "s.tif")
    m = s.mean_of("0:5")
    assert m.shape == (12, 16) and m.dtype == torch.float32
    np.testing.assert_allclose(m.numpy(), a[:5].astype(np.float64).mean(0), rtol=1e-6)
    np.testing.assert_allclose(s.mean_of([0, 1], dtype=torch.float64).numpy(), a[:2].mean(0))
    assert s.read("3,1").shape == (2, 12, 16)
    np.testing.assert_array_equal(s[1:3].numpy(), a[1:3])
    with pytest.raises(IndexError):
        s[8]
    # picklable (e.g. for multiprocessing / dask); reopened handles read the same data
    s[0]
    s2 = pickle.loads(pickle.dumps(s))
    np.testing.assert_array_equal(s2[4].numpy(), a[4])
    s.close()


def test_16bit_and_12bit(tmp_path: Path) -> None:
    a = _stack(t=3, dtype=np.uint16)
    assert a.max() > 255
    tifffile.imwrite(tmp_path / "s16.tif", a, photometric="minisblack")
    s = load_series(tmp_path / "s16.tif")
    assert s.dtype_name == "uint16" and s.bit_depth == 16 and s.max_value == 65535
    np.testing.assert_array_equal(s[2].numpy(), a[2].astype(np.float32))
    # 16-bit PNG keeps the native scale too
    Image.fromarray(a[0]).save(tmp_path / "p16.png")
    p = load_series(tmp_path / "p16.png")
    assert len(p) == 1 and p.dtype_name == "uint16"
    np.testing.assert_array_equal(p[0].numpy(), a[0])
    # 8-bit PNG: single 2-D image file is a 1-frame series
    Image.fromarray((a[0] >> 8).astype(np.uint8)).save(tmp_path / "p8.png")
    assert len(load_series(tmp_path / "p8.png")) == 1
    # BMP and JPEG through PIL
    g8 = (a[0] >> 8).astype(np.uint8)
    Image.fromarray(g8).save(tmp_path / "b.bmp")
    Image.fromarray(g8).save(tmp_path / "j.jpg", quality=100)
    bj = load_series([tmp_path / "b.bmp", tmp_path / "j.jpg"])
    assert len(bj) == 2 and bj.dtype_name == "uint8"
    np.testing.assert_array_equal(bj[0].numpy(), g8)
    assert np.abs(bj[1].numpy() - g8).max() <= 8
    # 12-bit data in 16-bit TIFF: bit depth from header (tifffile packs 12-bit samples
    # only with imagecodecs, a dependency; without it the rest above has still run)
    pytest.importorskip("imagecodecs", reason="writing packed 12-bit TIFF needs imagecodecs")
    tifffile.imwrite(tmp_path / "s12.tif", a >> 4, photometric="minisblack", bitspersample=12)
    s12 = load_series(tmp_path / "s12.tif")
    assert s12.bit_depth == 12
    np.testing.assert_array_equal(s12[1].numpy(), a[1] >> 4)


def test_natural_sort_directory_and_glob(tmp_path: Path) -> None:
    d = tmp_path / "frames"
    d.mkdir()
    for i in (10, 2, 1, 33, 3):
        Image.fromarray(np.full((4, 5), i, np.uint8)).save(d / f"frame_{i}.png")
    (d / "notes.txt").write_text("not an image")
    s = load_series(d)
    assert [s[i][0, 0].item() for i in range(len(s))] == [1, 2, 3, 10, 33]
    assert [Path(p).name for p in s.sources][:4] == [
        "frame_1.png",
        "frame_2.png",
        "frame_3.png",
        "frame_10.png",
    ]
    g = load_series(str(d / "frame_*.png"))
    assert [g[i][0, 0].item() for i in range(len(g))] == [1, 2, 3, 10, 33]
    assert sorted(["a10", "a2", "A1"], key=natural_sort_key) == ["A1", "a2", "a10"]


def test_timestamps(tmp_path: Path) -> None:
    a = _stack(t=4)
    s = load_series(a, timestamps=[0.0, 0.5, 1.5, 2.0])
    np.testing.assert_array_equal(s.times, [0.0, 0.5, 1.5, 2.0])
    assert s.times.dtype == np.float64
    with pytest.raises(InputError, match="timestamps"):
        load_series(a, timestamps=[0.0, 1.0, 2.0])
    with pytest.raises(InputError, match="strictly increasing"):
        load_series(a, timestamps=[0.0, 1.0, 1.0, 2.0])
    with pytest.raises(InputError, match="non-finite"):
        load_series(a, timestamps=[0.0, 1.0, np.nan, 2.0])


def test_arrays_and_tensors() -> None:
    a = _stack(t=3, dtype=np.uint16)
    s = load_series(a)
    assert len(s) == 3 and s.shape == (12, 16) and s.dtype_name == "uint16"
    np.testing.assert_array_equal(s[1].numpy(), a[1])
    t = load_series(torch.from_numpy(a.astype(np.float32)))
    assert t.dtype_name == "float32"
    np.testing.assert_array_equal(t.read([0, 2]).numpy(), a[[0, 2]])
    assert len(load_series(a[0])) == 1
    for bad in (np.zeros(5), np.zeros((2, 3, 4, 5, 6)), np.zeros((2, 3, 4, 5))):
        with pytest.raises(InputError, match="shape"):
            load_series(bad)
    f = a.astype(np.float64)
    f[2, 3, 4] = np.inf
    sf = load_series(f)
    sf[1]
    with pytest.raises(InputError, match=r"\[2\].*non-finite"):
        sf[2]


def test_colour_to_grey_warns_once(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rgb = (rng.random((3, 6, 7, 3)) * 255).astype(np.uint8)
    paths = []
    for i, im in enumerate(rgb):
        paths.append(tmp_path / f"c{i}.png")
        Image.fromarray(im).save(paths[-1])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        s = load_series(paths)
        frames = [s[i] for i in range(3)] + [s[0], s.mean_of("0:3")]
    colour_warnings = [w for w in rec if "grey" in str(w.message)]
    assert len(colour_warnings) == 1
    assert s.is_colour
    lum = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    np.testing.assert_allclose(frames[1].numpy(), lum[1], rtol=1e-6)
    # RGBA in a TIFF: alpha dropped
    rgba = np.concatenate([rgb, np.full((3, 6, 7, 1), 7, np.uint8)], axis=-1)
    tifffile.imwrite(tmp_path / "rgba.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    with pytest.warns(UserWarning, match="grey"):
        s2 = load_series(tmp_path / "rgba.tif")
    assert len(s2) == 3
    np.testing.assert_allclose(s2[2].numpy(), lum[2], rtol=1e-6)


def test_mixed_sizes_error_names_file(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((8, 10), np.uint8)).save(tmp_path / "a1.png")
    Image.fromarray(np.zeros((8, 10), np.uint8)).save(tmp_path / "a2.png")
    Image.fromarray(np.zeros((9, 10), np.uint8)).save(tmp_path / "a3.png")
    with pytest.raises(InputError, match=r"a3\.png is 9x10.*a1\.png is 8x10"):
        load_series(tmp_path)
    # lazily on read too: a file changed after the header scan
    s = load_series([tmp_path / "a1.png", tmp_path / "a2.png"])
    Image.fromarray(np.zeros((5, 5), np.uint8)).save(tmp_path / "a2.png")
    s[0]
    with pytest.raises(InputError, match=r"a2\.png is 5x5"):
        s[1]
    # pages of different sizes within one TIFF
    tifffile.imwrite(tmp_path / "m.tif", np.zeros((8, 10), np.uint8))
    tifffile.imwrite(tmp_path / "m.tif", np.zeros((9, 10), np.uint8), append=True)
    with pytest.raises(InputError, match=r"m\.tif.*9x10"):
        load_series(tmp_path / "m.tif")


def test_missing_empty_corrupt(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="nope.tif"):
        load_series(tmp_path / "nope.tif")
    with pytest.raises(InputError, match="missing.png"):
        Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "ok.png")
        load_series([tmp_path / "ok.png", tmp_path / "missing.png"])
    with pytest.raises(InputError, match="matches no file"):
        load_series(str(tmp_path / "*.jpg"))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no image file"):
        load_series(empty)
    with pytest.raises(InputError, match="empty list"):
        load_series([])
    (tmp_path / "junk.tif").write_bytes(b"this is not an image at all")
    with pytest.raises(InputError, match="junk.tif"):
        load_series(tmp_path / "junk.tif")
    good = tmp_path / "good.tif"
    tifffile.imwrite(good, _stack(t=1)[0])
    (tmp_path / "bad.tif").write_bytes(good.read_bytes()[:12])  # truncated TIFF
    with pytest.raises(InputError, match="bad.tif"):
        load_series([good, tmp_path / "bad.tif"])
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 20)
    with pytest.raises(InputError, match="bad.png"):
        load_series([tmp_path / "bad.png"])
    with pytest.raises(InputError):
        load_series(42)


def test_nan_in_float_tiff(tmp_path: Path) -> None:
    a = _stack(t=4, dtype=np.float32)
    a[2, 1, 1] = np.nan
    tifffile.imwrite(tmp_path / "f.tif", a, photometric="minisblack")
    s = load_series(tmp_path / "f.tif")
    np.testing.assert_array_equal(s[1].numpy(), a[1])
    with pytest.raises(InputError, match=r"f\.tif \(page 2\).*non-finite"):
        s[2]
    with pytest.raises(InputError, match="non-finite"):
        s.mean_of("0:4")


def test_lazy_reading_decodes_only_requested_pages(tmp_path: Path, monkeypatch) -> None:
    a = _stack(t=50, h=32, w=32)
    tifffile.imwrite(tmp_path / "big.tif", a)
    calls: list[int] = []
    orig = tifffile.TiffPage.asarray

    def counting(self, *args, **kwargs):
        calls.append(self.index)
        return orig(self, *args, **kwargs)

    def forbidden(*args, **kwargs):
        raise AssertionError("whole-file read")

    monkeypatch.setattr(tifffile.TiffPage, "asarray", counting)
    monkeypatch.setattr(tifffile.TiffFile, "asarray", forbidden)
    monkeypatch.setattr(tifffile.TiffPageSeries, "asarray", forbidden)
    monkeypatch.setattr(tifffile, "imread", forbidden)
    s = load_series(tmp_path / "big.tif")
    assert calls == [] and len(s) == 50
    np.testing.assert_array_equal(s[5].numpy(), a[5])
    assert calls == [5]
    s.read([7, 40])
    assert calls == [5, 7, 40]
    s.mean_of("10:13")
    assert calls == [5, 7, 40, 10, 11, 12]


def test_parse_frame_spec() -> None:
    assert parse_frame_spec("0", 10) == [0]
    assert parse_frame_spec("0:5", 10) == [0, 1, 2, 3, 4]
    assert parse_frame_spec("10:100:2", 20) == [10, 12, 14, 16, 18]
    assert parse_frame_spec("3,7,9", 10) == [3, 7, 9]
    assert parse_frame_spec(" 3 , 7 ", 10) == [3, 7]
    assert parse_frame_spec("-1", 10) == [9]
    assert parse_frame_spec("-3:", 10) == [7, 8, 9]
    assert parse_frame_spec(":", 3) == [0, 1, 2]
    assert parse_frame_spec("all", 3) == [0, 1, 2]
    assert parse_frame_spec("::-1", 3) == [2, 1, 0]
    assert parse_frame_spec("0:3,2,5", 10) == [0, 1, 2, 5]
    assert parse_frame_spec(4, 10) == [4]
    for bad in ("", "a", "10", "-11", "1:2:0", "5:2", "1,,2", "1:2:3:4", "1.5"):
        with pytest.raises(InputError):
            parse_frame_spec(bad, 10)
    assert issubclass(InputError, ValueError)


# ------------------------------------------------------------------------------------------
# result files
# ------------------------------------------------------------------------------------------

FIELDS = ("u", "v", "ut", "vt", "zncc", "status")


def _writer_args(n: int = 5, f: int = 4, **config) -> dict:
    xs, ys = np.meshgrid(np.arange(n) * 10.0 + 3, [7.5])
    return dict(
        points=np.stack([xs.ravel(), ys.ravel()], 1),
        frames=np.arange(1, f + 1) * 2,
        times=np.arange(1, f + 1) * 0.5,
        config={"subset": 21, "step": 10, "ref": [0, 1], **config},
        inputs=["a.tif", "b.tif"],
    )


def _row(r: int, n: int = 5, k: int = 1, strain: bool = False) -> dict:
    base = np.arange(n, dtype=np.float64)[None] + 100 * r + np.arange(k)[:, None] * 100
    vals = {name: base + i * 0.25 for i, name in enumerate(FIELDS[:5])}
    vals["status"] = np.full((k, n), int(Status.MAX_ITER), np.int8)
    if strain:
        vals.update({"exx": base * 1e-4, "eyy": -base * 1e-4, "exy": base * 0})
    return vals


def test_result_writer_roundtrip(tmp_path: Path) -> None:
    p = tmp_path / "out" / "res.h5"
    with ResultWriter(p, **_writer_args(), extra_fields=("exx", "eyy", "exy")) as w:
        assert w.completed_rows().tolist() == []
        w.write_rows([1], _row(1, strain=True))
        w.write_rows([3, 2], {k: torch.as_tensor(v[::-1].copy()) for k, v in _row(2, k=2).items()})
        assert w.completed_rows().tolist() == [1, 2, 3]
        assert w.pending_rows().tolist() == [0]
        with pytest.raises(ValueError, match="missing"):
            w.write_rows([0], {"u": np.zeros((1, 5))})
        with pytest.raises(ValueError, match="shape"):
            w.write_rows([0], {**_row(0), "u": np.zeros((1, 4))})
        with pytest.raises(KeyError):
            w.write_rows([0], {**_row(0), "bogus": np.zeros((1, 5))})
    res = read_results(p)
    assert res.points.shape == (5, 2) and res.points.dtype == np.float64
    np.testing.assert_array_equal(res.frames, [2, 4, 6, 8])
    np.testing.assert_array_equal(res.times, [0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(res.completed, [False, True, True, True])
    assert res.u.shape == (4, 5) and res.u.dtype == np.float32
    assert res.status.dtype == np.int8
    assert np.isnan(res.u[0]).all() and (res.status[0] == Status.NOT_COMPUTED).all()
    np.testing.assert_array_equal(res.u[1], np.arange(5) + 100)
    # rows [3, 2] got the reversed pair: row 2 <- base 200, row 3 <- base 300
    np.testing.assert_array_equal(res.v[2], np.arange(5) + 200.25)
    np.testing.assert_array_equal(res.u[3], np.arange(5) + 300)
    assert np.isnan(res.exx[2]).all() and res.exx[1, 1] == np.float32(101e-4)
    assert res.config == {"subset": 21, "step": 10, "ref": [0, 1]}
    assert res.inputs == ["a.tif", "b.tif"]
    assert res.attrs["format"] == RESULTS_FORMAT and "created" in res.attrs
    with pytest.raises(AttributeError):
        res.nothing  # noqa: B018
    with h5py.File(p, "r") as f:
        assert f["completed"].dtype == bool and f["frames"].shape == (4,)


def test_killed_writer_keeps_finished_rows(tmp_path: Path) -> None:
    # a real kill: SIGKILL in a child process after two rows
    p = tmp_path / "killed.h5"
    script = textwrap.dedent(
        f"""
        import os, signal, sys
        import numpy as np
        sys.path.insert(0, {str(REPO)!r})
        from torch_stsdic.io import ResultWriter
        w = ResultWriter({str(p)!r}, points=np.zeros((3, 2)), frames=np.arange(4),
                         times=np.arange(4.0), config={{"a": 1}}, inputs=["x.tif"])
        names = ("u", "v", "ut", "vt", "zncc", "status")
        for r in (0, 2):
            w.write_rows([r], {{k: np.full((1, 3), r + 1) for k in names}})
        os.kill(os.getpid(), {int(getattr(signal, "SIGKILL", 9))})
        """
    )
    if sys.platform == "win32":
        script = script.replace("os.kill(os.getpid(), 9)", "os._exit(3)")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode != 0, proc.stderr.decode()
    res = read_results(p)
    np.testing.assert_array_equal(res.completed, [True, False, True, False])
    np.testing.assert_array_equal(res.u[:, 0], [1, np.nan, 3, np.nan])
    np.testing.assert_array_equal(res.status[:, 0], [1, 5, 3, 5])
    # in-process: writer dropped without close(); file readable and resumable
    q = tmp_path / "dropped.h5"
    w = ResultWriter(q, **_writer_args())
    w.write_rows([0], _row(0))
    del w
    assert read_results(q).completed.tolist() == [True, False, False, False]
    with ResultWriter(q, **_writer_args(), resume=True) as w2:
        assert w2.pending_rows().tolist() == [1, 2, 3]


def test_resume(tmp_path: Path) -> None:
    p = tmp_path / "r.h5"
    with ResultWriter(p, **_writer_args()) as w:
        w.write_rows([0, 1], _row(0, k=2))
    with ResultWriter(p, **_writer_args(), resume=True) as w:
        assert w.completed_rows().tolist() == [0, 1]
        for r in w.pending_rows():
            w.write_rows([r], _row(int(r)))
        assert w.is_complete
    res = read_results(p)
    assert res.completed.all()
    np.testing.assert_array_equal(res.u[1], np.arange(5) + 100)  # kept from the first run
    np.testing.assert_array_equal(res.u[3], np.arange(5) + 300)
    before = p.read_bytes()
    with pytest.raises(ResultFileError, match="step: 10 -> 11"):
        ResultWriter(p, **_writer_args(step=11), resume=True)
    bad_pts = _writer_args()
    bad_pts["points"] = bad_pts["points"] + 1
    with pytest.raises(ResultFileError, match="points"):
        ResultWriter(p, **bad_pts, resume=True)
    bad_frames = _writer_args(f=3)
    with pytest.raises(ResultFileError, match="frames"):
        ResultWriter(p, **bad_frames, resume=True)
    with pytest.raises(ResultFileError, match="exx"):
        ResultWriter(p, **_writer_args(), extra_fields=("exx",), resume=True)
    assert p.read_bytes() == before
    # keys listed in resume_ignore (e.g. the device) are not compared
    ResultWriter(p, **_writer_args(device="cuda"), resume=True, resume_ignore=["device"]).close()
    # resume on a missing file starts a new one
    with ResultWriter(tmp_path / "new.h5", **_writer_args(), resume=True) as w:
        assert w.pending_rows().tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        ResultWriter(tmp_path / "x.h5", **_writer_args(), resume=True, overwrite=True)


def test_existing_file_is_protected(tmp_path: Path) -> None:
    p = tmp_path / "r.h5"
    p.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="overwrite"):
        ResultWriter(p, **_writer_args())
    assert p.read_bytes() == b"precious"
    with pytest.raises(ResultFileError):
        ResultWriter(p, **_writer_args(), resume=True)
    assert p.read_bytes() == b"precious"
    with pytest.raises(ResultFileError, match="not a"):
        read_results(p)


def test_overwrite_is_atomic(tmp_path: Path) -> None:
    p = tmp_path / "r.h5"
    partial = tmp_path / "r.h5.partial"
    with ResultWriter(p, **_writer_args()) as w:
        w.write_rows([0], _row(0))
    w = ResultWriter(p, **_writer_args(step=5), overwrite=True)
    assert w.file_path == partial and partial.exists()
    w.write_rows([3], _row(3))
    old = read_results(p)  # old file untouched while the new one is written
    assert old.config["step"] == 10 and old.completed.tolist() == [True, False, False, False]
    w.close()
    assert not partial.exists()
    new = read_results(p)
    assert new.config["step"] == 5 and new.completed.tolist() == [False, False, False, True]
    # an exception inside `with` keeps the old file and leaves the .partial for resume
    with pytest.raises(RuntimeError):
        with ResultWriter(p, **_writer_args(step=7), overwrite=True) as w:
            w.write_rows([1], _row(1))
            raise RuntimeError("boom")
    assert read_results(p).config["step"] == 5 and partial.exists()
    with ResultWriter(p, **_writer_args(step=7), resume=True) as w:
        assert w.file_path == partial and w.completed_rows().tolist() == [1]
    assert not partial.exists()
    assert read_results(p).config["step"] == 7 and read_results(p).completed[1]


def test_export_csv(tmp_path: Path) -> None:
    p = tmp_path / "res.h5"
    with ResultWriter(p, **_writer_args(), extra_fields=("exx", "eyy", "exy")) as w:
        w.write_rows([0], _row(0, strain=True))
        w.write_rows([2], {k: v for k, v in _row(2).items()})  # strain left NaN
    files = export_csv(p, tmp_path / "csv", comment=True)
    assert [f.name for f in files] == ["res_frame00002.csv", "res_frame00006.csv"]
    res = read_results(p)
    for f, row in zip(files, (0, 2)):
        lines = f.read_text().splitlines()
        assert lines[0].startswith("#") and f"frame={res.frames[row]}" in lines[0]
        assert f"time={float(res.times[row])!r}" in lines[0]
        rows = list(csv.DictReader(lines[1:]))
        assert tuple(rows[0].keys()) == CSV_COLUMNS and len(rows) == 5
        for j, r in enumerate(rows):
            assert float(r["x"]) == res.points[j, 0] and float(r["y"]) == res.points[j, 1]
            for name in ("u", "v", "ut", "vt", "zncc", "exx", "eyy", "exy"):
                val = res.fields[name][row, j]
                if np.isnan(val):
                    assert r[name] == ""
                else:
                    assert np.float32(r[name]) == val
            assert int(r["status"]) == res.status[row, j]
    # pattern, explicit frame list, no comment, file without strain datasets
    q = tmp_path / "plain.h5"
    with ResultWriter(q, **_writer_args()) as w:
        w.write_rows([1], _row(1))
    out = export_csv(
        q, str(tmp_path / "pat" / "f{frame:03d}_t{time:.1f}.csv"), [4, 8], comment=False
    )
    assert [f.name for f in out] == ["f004_t1.0.csv", "f008_t2.0.csv"]
    data = np.genfromtxt(out[0], delimiter=",", names=True)
    assert data.dtype.names == CSV_COLUMNS
    np.testing.assert_array_equal(data["u"], np.arange(5) + 100)
    assert np.isnan(data["exx"]).all()
    np.testing.assert_array_equal(np.genfromtxt(out[1], delimiter=",", names=True)["status"], 5)
    with pytest.raises(KeyError):
        export_csv(q, tmp_path / "x", [3])


def test_image_series_type() -> None:
    s = load_series(np.zeros((2, 3, 4), np.uint8))
    assert isinstance(s, ImageSeries) and load_series(s) is s
    s2 = load_series(s, timestamps=[1.0, 2.0])
    np.testing.assert_array_equal(s2.times, [1.0, 2.0])
    np.testing.assert_array_equal(s.times, [0.0, 1.0])


def test_tables_read_by_numpy_equal_the_line_parser(tmp_path):
    """read_table's fast path (numpy's parser, for regular tables) gives what the line by
    line parser gives; irregular tables fall back to it and its errors name the line."""
    from torch_stsdic.io import tables

    texts = ["x,y\n1.5,2\n3,4e1\n", "# c\n1 2\n\n3 4\n", '"X", "Y"\n1, 2\n 3 ,4\n',
             "t\n0\n0.5\n1\n"]
    for i, text in enumerate(texts):
        f = tmp_path / f"t{i}.csv"
        f.write_text(text)
        fast = tables._fast_table(text)
        assert fast is not None, text
        orig = tables._fast_table
        try:
            tables._fast_table = lambda _text: None  # the line-by-line parser alone
            slow = tables.read_table(str(f), "points")
        finally:
            tables._fast_table = orig
        assert fast[0] == slow[0] and np.array_equal(fast[1], slow[1]), text
        assert np.array_equal(tables.read_table(str(f), "points")[1], slow[1])
    for text, msg in (("1,2\n3\n", "line 2: 1 values"), ("x y\n1 2\n3 a\n", "line 3"),
                      ("1,2\n3,4 # note\n", "line 2: not numbers")):
        f = tmp_path / "bad.csv"
        f.write_text(text)
        assert tables._fast_table(text) is None
        with pytest.raises(InputError, match=msg):
            tables.read_table(str(f), "points")
