"""Exports in physical units: ``stsdic run --scale --unit`` then ``stsdic export --format
csv|vtk|mat`` read back with numpy, meshio and scipy.io; the units of every field."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from torch_stsdic.analysis.export import export_results
from torch_stsdic.cli import main
from torch_stsdic.io import ResultWriter, Units, read_results, units_of
from torch_stsdic.io.units import check_calibration

FAST = ["--threads", "1", "--no-progress"]
SCALE = 0.02


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> Path:
    """``stsdic run <frames> --scale 0.02 --unit mm --out r.h5`` on a small synthetic movie."""
    d = tmp_path_factory.mktemp("cal")
    assert main(["synth", "--out", str(d / "movie"), "--size", "81", "--frames", "5",
                 "--noise", "1", "--seed", "4", "--threads", "1"]) == 0  # fmt: skip
    out = d / "r.h5"
    code = main(["run", str(d / "movie" / "movie.tif"), "--subset", "17", "--step", "15",
                 "--scale", str(SCALE), "--unit", "mm", "--out", str(out), *FAST])  # fmt: skip
    assert code == 0
    return out


def _export(path: Path, fmt: str, out: Path, capsys) -> str:
    code = main(["export", str(path), "--format", fmt, "--out", str(out)])
    text, err = capsys.readouterr()
    assert code == 0, err
    return text


def test_file_keeps_pixels_and_records_the_scale(calibrated):
    with h5py.File(calibrated, "r") as f:
        assert float(f.attrs["scale"]) == SCALE and f.attrs["unit"] == "mm"
        assert f.attrs["time_unit"] == "frame"
        u = f["u"][()]
    # the synthetic motion is a few tenths of a px: stored in px, not in mm
    assert np.nanmax(np.abs(u)) > 0.1
    assert read_results(calibrated).units == Units(SCALE, "mm", "frame")


def test_vtk_read_back_with_meshio_is_u_times_scale(calibrated, tmp_path, capsys):
    meshio = pytest.importorskip("meshio")
    said = _export(calibrated, "vtk", tmp_path, capsys)
    assert "r.pvd" in said
    res = read_results(calibrated)
    pvd = (tmp_path / "r.pvd").read_text()
    assert pvd.count("<DataSet") == res.n_frames
    for row in (0, res.n_frames - 1):
        mesh = meshio.read(tmp_path / f"r_frame{int(res.frames[row]):05d}.vtu")
        np.testing.assert_array_equal(mesh.point_data["u"], res.u[row] * SCALE)
        np.testing.assert_array_equal(mesh.point_data["v"], res.v[row] * SCALE)
        np.testing.assert_array_equal(mesh.point_data["ut"], res.ut[row] * SCALE)
        np.testing.assert_array_equal(mesh.point_data["exx"], res.exx[row])  # dimensionless
        np.testing.assert_array_equal(mesh.point_data["status"], res.status[row])
        np.testing.assert_array_equal(mesh.point_data["zncc"], res.zncc[row])
        np.testing.assert_allclose(mesh.points[:, :2], res.points * SCALE)
        np.testing.assert_array_equal(mesh.point_data["displacement"][:, 0], res.u[row] * SCALE)
        # the nx x ny grid is a surface of (nx - 1) x (ny - 1) quads
        nx, ny = (len(np.unique(np.asarray(res.points)[:, i])) for i in (0, 1))
        assert nx >= 3 and ny >= 3
        assert [(c.type, len(c.data)) for c in mesh.cells] == [("quad", (nx - 1) * (ny - 1))]


def test_mat_read_with_scipy_has_frames_by_points_in_mm(calibrated, tmp_path, capsys):
    sio = pytest.importorskip("scipy.io")
    _export(calibrated, "mat", tmp_path, capsys)
    res = read_results(calibrated)
    d = sio.loadmat(tmp_path / "r.mat")
    assert d["u"].shape == (res.n_frames, res.n_points)
    np.testing.assert_allclose(d["u"], res.u * SCALE, rtol=1e-6)
    np.testing.assert_allclose(d["vt"], res.vt * SCALE, rtol=1e-6)
    np.testing.assert_array_equal(d["status"], res.status)
    np.testing.assert_allclose(d["x"].ravel(), res.x * SCALE)
    np.testing.assert_array_equal(d["frames"].ravel(), res.frames)
    np.testing.assert_array_equal(d["times"].ravel(), res.times)
    assert d["unit"][0] == "mm" and d["scale"].item() == SCALE and d["time_unit"][0] == "frame"
    assert d["units"]["ut"][0, 0][0] == "mm/frame"


def test_csv_first_line_is_the_header(calibrated, tmp_path, capsys):
    _export(calibrated, "csv", tmp_path, capsys)
    res = read_results(calibrated)
    first = tmp_path / "r_frame00000.csv"
    header = first.read_text().splitlines()[0]
    assert header.split(",")[:11] == ["x", "y", "u", "v", "ut", "vt", "exx", "eyy", "exy",
                                      "zncc", "status"]  # fmt: skip
    data = np.genfromtxt(first, delimiter=",", names=True)
    np.testing.assert_allclose(data["u"], res.u[0] * SCALE, rtol=1e-6)
    np.testing.assert_allclose(data["x"], res.x * SCALE)
    meta = json.loads((tmp_path / "r_csv.json").read_text())
    assert meta["unit"] == "mm" and meta["scale"] == SCALE
    assert meta["units"]["u"] == "mm" and meta["units"]["exx"] == "-"
    assert meta["units"]["ut"] == "mm/frame" and meta["units"]["status"] == ""
    assert [m["frame"] for m in meta["files"]] == res.frames.tolist()


def _writer_file(path: Path, attrs: dict | None = None) -> Path:
    """3 frames x 4 points with u, v, ut, vt, zncc, status and predicted-std / int fields."""
    pts = np.array([[10.0, 20.0], [30.0, 20.0], [10.0, 40.0], [30.0, 40.0]])
    names = ("u", "v", "ut", "vt", "zncc", "status", "u_std", "v_std", "m")
    with ResultWriter(path, points=pts, frames=[0, 1, 2], times=[0.0, 0.5, 1.0], config={},
                      inputs=[], fields=names, attrs=attrs) as w:  # fmt: skip
        for r in range(3):
            vals = {nm: np.arange(4.0) + 10 * r for nm in names}
            vals["status"] = np.array([0, 1, 2, 0])
            vals["m"] = np.full(4, 2.0)
            w.write_rows([r], vals)
    return path


def test_new_fields_come_through_with_units(tmp_path):
    """Fields the exporters do not know by name (predicted std, m) are exported generically:
    a std of a length is a length; an unknown name keeps its values."""
    meshio = pytest.importorskip("meshio")
    sio = pytest.importorskip("scipy.io")
    p = _writer_file(tmp_path / "s.h5", {"scale": 0.5, "unit": "um", "time_unit": "s"})
    export_results(p, tmp_path / "vtk", "vtk")
    mesh = meshio.read(tmp_path / "vtk" / "s_frame00001.vtu")
    np.testing.assert_array_equal(mesh.point_data["u_std"], (np.arange(4.0) + 10) * 0.5)
    np.testing.assert_array_equal(mesh.point_data["m"], 2.0)
    assert "displacement" in mesh.point_data and "velocity" in mesh.point_data
    # scattered-looking 2 x 2 grid: one quad
    assert [(c.type, len(c.data)) for c in mesh.cells] == [("quad", 1)]
    export_results(p, tmp_path / "mat", "mat", frames=[2])
    d = sio.loadmat(tmp_path / "mat" / "s.mat")
    assert d["v_std"].shape == (1, 4)
    np.testing.assert_array_equal(d["v_std"][0], (np.arange(4.0) + 20) * 0.5)
    assert d["units"]["vt"][0, 0][0] == "um/s" and d["units"]["v_std"][0, 0][0] == "um"
    files = export_results(p, tmp_path / "csv", "csv", comment=True)
    lines = files[0].read_text().splitlines()
    assert lines[0].startswith("# torch_stsdic") and "unit=um" in lines[0]
    assert lines[1].split(",")[-3:] == ["u_std", "v_std", "m"]


def test_no_calibration_is_pixels(tmp_path):
    sio = pytest.importorskip("scipy.io")
    p = _writer_file(tmp_path / "px.h5")
    assert units_of({}) == Units(None, "px", "frame")
    export_results(p, tmp_path, "mat")
    d = sio.loadmat(tmp_path / "px.mat")
    np.testing.assert_array_equal(d["u"][1], np.arange(4.0) + 10)
    assert d["unit"][0] == "px" and d["scale"].item() == 1.0
    with pytest.raises(ValueError, match="format"):
        export_results(p, tmp_path, "xls")


@pytest.mark.parametrize(
    ("name", "dims", "unit"),
    [("u", (1, 0), "mm"), ("vt", (1, -1), "mm/s"), ("ux", (0, 0), "-"), ("uxy", (-1, 0), "1/mm"),
     ("exy", (0, 0), "-"), ("exx_rate", (0, -1), "1/s"), ("u_std", (1, 0), "mm"),
     ("ut_std", (1, -1), "mm/s"), ("u_smooth", (1, 0), "mm"), ("zncc", (0, 0), "-"),
     ("status", None, ""), ("iterations", None, ""), ("sigma_noise", None, "")],
)  # fmt: skip
def test_field_units(name, dims, unit):
    units = Units(0.02, "mm", "s")
    assert units.dims(name) == dims
    assert units.unit_of(name) == unit
    factor = {None: 1.0}.get(dims, 0.02 ** dims[0] if dims else 1.0)
    assert units.factor(name) == pytest.approx(factor)
    assert units.label(name) == (f"{name} ({unit})" if unit else name)


def test_calibration_checks(capsys, calibrated, tmp_path):
    assert check_calibration(None, None) == {"unit": "px"}
    assert check_calibration(0.5, "um", "ms") == {"scale": 0.5, "unit": "um", "time_unit": "ms"}
    for bad, match in (((0.0, "mm"), "scale"), ((0.1, None), "unit"), ((None, "mm"), "unit"),
                       ((float("nan"), "mm"), "scale")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            check_calibration(*bad)
    movie = calibrated.parent / "movie" / "movie.tif"
    code = main(["run", str(movie), "--unit", "mm", "--out", str(tmp_path / "x.h5"), *FAST])
    err = capsys.readouterr().err
    assert code == 2 and "--unit" in err and "needs a scale" in err
    assert not (tmp_path / "x.h5").exists()


def test_track_records_the_calibration(tmp_path):
    """``track(..., scale=, unit=, time_unit=)``: attributes of ``out``, ``info["units"]``;
    the values stay in px; timestamps without a time unit say 'time unit'."""
    import torch

    from torch_stsdic import DICConfig, synth, track

    movie = synth.synthetic_movie((61, 61), 4, synth.Translation(ut=0.1), seed=1)
    frames = torch.cat([movie.ref[None], movie.frames]).float()
    pts = [[30.0, 30.0], [40.0, 30.0]]
    cfg = DICConfig(subset_size=15, m=1, search_radius=2)
    res = track(frames, points=pts, config=cfg, progress=False, out=tmp_path / "a.h5",
                scale=0.5, unit="um", time_unit="ms")  # fmt: skip
    assert res.info["units"] == {"scale": 0.5, "unit": "um", "time_unit": "ms"}
    assert read_results(tmp_path / "a.h5").units == Units(0.5, "um", "ms")
    np.testing.assert_allclose(res.u[-1].numpy(), 0.4, atol=0.02)  # px, not um
    plain = track(frames, points=pts, config=cfg, progress=False,
                  times=[0.0, 0.5, 1.0, 1.5, 2.0])  # fmt: skip
    assert plain.info["units"] == {"unit": "px", "time_unit": "time unit"}
    with pytest.raises(ValueError, match="unit"):
        track(frames, points=pts, config=cfg, progress=False, scale=0.5)
