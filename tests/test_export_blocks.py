"""MATLAB exports written a block of points at a time (issue 50): what ``scipy.io.loadmat``
reads back is what ``savemat`` of the whole (frames, points) arrays gives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torch_stsdic.analysis import export as ex
from torch_stsdic.io import ResultWriter

sio = pytest.importorskip("scipy.io")


def _file(path: Path, f: int = 37, n: int = 23) -> Path:
    """``f`` frames x ``n`` points of float, int8 and int fields, NaNs among them."""
    rng = np.random.default_rng(3)
    pts = np.stack(np.meshgrid(np.arange(n) * 7.0, [5.0], indexing="ij"), -1).reshape(-1, 2)
    names = ("u", "v", "ut", "vt", "zncc", "status", "u_std", "m", "iterations")
    with ResultWriter(path, points=pts, frames=list(range(f)), times=np.arange(f) * 0.5,
                      config={}, inputs=[], fields=names,
                      attrs={"scale": 0.02, "unit": "mm", "time_unit": "s"}) as w:
        for r in range(f):
            vals = {nm: rng.normal(size=n) for nm in names}
            vals["u"][r % n] = np.nan
            vals["status"] = rng.integers(0, 8, n)
            vals["m"] = rng.integers(0, 3, n).astype(float)
            vals["iterations"] = rng.integers(0, 30, n)
            w.write_rows([r], vals)
    return path


def _whole_export(path: Path, out: Path, frames) -> dict:
    """The export as it was written before blocks: savemat of the whole arrays."""
    from torch_stsdic.io.results import open_results
    from torch_stsdic.io.units import units_of

    with open_results(path) as f:
        units = units_of(f.attrs)
        rows = sorted(set(ex.frame_rows(f, frames, path)))
        names = [c for c in ex._columns(f) if c not in ("x", "y")]
        data = {nm: units.convert(nm, f[nm][rows]) for nm in names}
    sio.savemat(out, data, do_compression=True, oned_as="row")
    return sio.loadmat(out)


@pytest.mark.parametrize("frames", [None, [3, 4, 9, 30]])
def test_mat_export_in_blocks_reads_back_as_the_whole_arrays(frames, tmp_path, monkeypatch):
    p = _file(tmp_path / "r.h5")
    want = _whole_export(p, tmp_path / "whole.mat", frames)
    monkeypatch.setattr(ex, "MAT_BLOCK_BYTES", 8 * 37 * 4)  # 4 points a block: 6 blocks
    ex.export_results(p, tmp_path / "mat", "mat", frames=frames)
    got = sio.loadmat(tmp_path / "mat" / "r.mat")
    fields = [k for k in want if not k.startswith("__")]
    assert len(fields) > 8
    for k in fields:
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, k
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert got["u"].shape == (37 if frames is None else 4, 23)
    assert np.isnan(got["u"]).any() and got["status"].dtype == np.int8
    assert got["unit"][0] == "mm" and got["x"].shape == (1, 23)  # the rest as before
    info = {name: (shape, cls) for name, shape, cls in sio.whosmat(tmp_path / "mat" / "r.mat")}
    whole = {name: (shape, cls) for name, shape, cls in sio.whosmat(tmp_path / "whole.mat")}
    assert all(info[k] == whole[k] for k in whole) and info["status"][1] == "int8"


def test_mat_array_written_in_blocks_equals_savemat(tmp_path):
    """Every numeric type, a name of 1 and of many characters, columns in blocks of 3."""
    for dtype in (np.float64, np.float32, np.int8, np.uint8, np.int16, np.uint16, np.int32,
                  np.uint32, np.int64, np.uint64):
        a = (np.arange(5 * 11).reshape(5, 11) % 100).astype(dtype)
        for name in ("a", "a_rather_long_name"):
            field = ex.MatField(a.shape, lambda cols, a=a: a[:, cols])
            target = tmp_path / f"{np.dtype(dtype).name}_{name}.mat"
            ex.MAT_BLOCK_BYTES, old = 8 * 5 * 3, ex.MAT_BLOCK_BYTES
            try:
                ex.write_mat(target, {"other": np.arange(3.0)}, {name: field})
            finally:
                ex.MAT_BLOCK_BYTES = old
            got = sio.loadmat(target)
            assert got[name].dtype == a.dtype and got[name].shape == a.shape
            np.testing.assert_array_equal(got[name], a)
            np.testing.assert_array_equal(got["other"], [[0.0, 1.0, 2.0]])


def test_stereo_mat_export_in_blocks_is_the_file(tmp_path, monkeypatch):
    """A stereo file's MATLAB export, 3 points a block: every (frames, points) field is the
    file's (NaN where the file has none), the rest as before."""
    import h5py
    from test_stereo_export import write_stereo_run  # tests/ on the path

    from torch_stsdic.stereo.export import COLUMNS, export_stereo

    (tmp_path / "run").mkdir()
    path = write_stereo_run(tmp_path / "run")
    monkeypatch.setattr(ex, "MAT_BLOCK_BYTES", 8 * 2 * 3)
    export_stereo(path, tmp_path / "mat", "mat", frames=[2, 3])
    got = sio.loadmat(tmp_path / "mat" / f"{path.stem}.mat")
    with h5py.File(path, "r") as f:
        n = f["points"].shape[0]
        for name in (c for c in COLUMNS if c not in ("x", "y")):
            want = f[name][2:4] if name in f else np.full((2, n), np.nan)
            assert got[name].dtype == want.dtype, name
            np.testing.assert_array_equal(got[name], want, err_msg=name)
        np.testing.assert_array_equal(got["X0"], f["X0"][()])
