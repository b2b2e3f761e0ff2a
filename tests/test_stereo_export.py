"""Stereo result files out of the file: ``stsdic export --format csv|vtk|mat`` and ``stsdic
plot`` on a file written by ``stsdic stereo`` (a tiny rendered movie: 6 frames, step 20),
read back and compared number by number with the HDF5 datasets; the one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
import torch

import torch_stsdic.plot as plot_module
from torch_stsdic.cli import main
from torch_stsdic.core.status import Status
from torch_stsdic.io.results import ResultWriter
from torch_stsdic.stereo.export import COLUMNS, export_stereo
from torch_stsdic.stereo.render import SurfaceMotion, make_rig, make_scene, render_stereo
from torch_stsdic.stereo.result import STEREO_FORMAT, StereoResult, is_stereo_file

MOTION = SurfaceMotion(translation=(0.004, -0.003, 0.01), exx=2e-4, eyy=-1e-4, bulge=0.004,
                       bulge_radius=6.0)
#: points made unusable (POOR_FIT) at frame BAD_FRAME in the "holes" copy
BAD_FRAME = 3


def write_stereo_movies(d: Path, motion: SurfaceMotion = MOTION) -> None:
    """A 6-frame stereo render of ``motion`` in folder ``d``: ``left.tif``, ``right.tif`` (8
    bits) and the rig's calibration ``cal.yml``."""
    rig = make_rig((140, 180))
    scene = make_scene(rig, motion, seed=0, max_time=6)
    left, right = render_stereo(scene, np.arange(6.0), noise_sigma=2.0, seed=1, quadrature=2,
                                cutoff=5)
    for name, movie in (("left", left), ("right", right)):
        tifffile.imwrite(d / f"{name}.tif", movie.clamp(0, 255).round().to(torch.uint8).numpy())
    rig.save_opencv(d / "cal.yml")


def write_stereo_run(d: Path) -> Path:
    """``stsdic stereo --m 1 --step 20`` on a 6-frame render (48 points, 12 never matched),
    its movies ``left.tif``, ``right.tif`` and calibration in folder ``d``: the result file."""
    write_stereo_movies(d)
    out = d / "r.h5"
    assert main(["stereo", "--left", str(d / "left.tif"), "--right", str(d / "right.tif"),
                 "--calibration", str(d / "cal.yml"), "--m", "1", "--step", "20", "--roi",
                 "20", "20", "160", "120", "--out", str(out), "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def stereo_h5(tmp_path_factory) -> Path:
    """:func:`write_stereo_run` in a folder of its own."""
    return write_stereo_run(tmp_path_factory.mktemp("stereo"))


@pytest.fixture(scope="module")
def holes_h5(stereo_h5, tmp_path_factory) -> Path:
    """A copy whose frame BAD_FRAME has 2/3 of its triangulated points POOR_FIT (their
    values kept, as a run keeps them)."""
    p = tmp_path_factory.mktemp("holes") / "h.h5"
    shutil.copy(stereo_h5, p)
    with h5py.File(p, "r+") as f:
        ok = np.flatnonzero(np.isfinite(f["X0"][()]).all(1))
        st = f["status"][()]
        st[BAD_FRAME, ok[: 2 * len(ok) // 3]] = int(Status.POOR_FIT)
        f["status"][...] = st
    return p


def _data(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f}


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_file_is_recognised_and_reads_back(stereo_h5, tmp_path):
    with h5py.File(stereo_h5, "r") as f:
        assert f.attrs["format"] == STEREO_FORMAT and is_stereo_file(f)
        n = f["points"].shape[0]
        assert n == 48 and int(np.isnan(f["X0"][()]).any(1).sum()) == 12
    res = StereoResult.from_hdf5(stereo_h5)
    d = _data(stereo_h5)
    for k in ("W", "Ut", "X0", "points", "status", "reprojection_error"):
        np.testing.assert_array_equal(getattr(res, k).numpy(), d[k])
    np.testing.assert_array_equal(res.std["W"].numpy(), d["W_std"])
    assert res.calibration["baseline_mm"] > 100
    # a file written before the format attribute: recognised by its kind, then its datasets
    old = tmp_path / "old.h5"
    shutil.copy(stereo_h5, old)
    with h5py.File(old, "r+") as f:
        del f.attrs["format"], f.attrs["version"], f.attrs["kind"]
    written = export_stereo(old, tmp_path / "csv", "csv", frames=[2])
    assert [w.name for w in written] == ["old_frame00002.csv"]
    # ... and one written before U_cov: read without it, its strain std from the stds alone
    # (the components taken independent), finite where the strain is
    with h5py.File(old, "r+") as f:
        del f["U_cov"]
    no_cov = StereoResult.from_hdf5(old)
    assert no_cov.U_cov is None and res.U_cov is not None
    st, st_cov = no_cov.surface_strain(), res.surface_strain()
    for k in ("exx", "eyy", "exy"):
        torch.testing.assert_close(st[k], st_cov[k], equal_nan=True)
        assert torch.equal(torch.isfinite(st[k + "_std"]), torch.isfinite(st[k]))
    assert not torch.allclose(st["exx_std"].nan_to_num(), st_cov["exx_std"].nan_to_num())


def test_csv_columns_are_the_file_values(stereo_h5, tmp_path, capsys):
    code, said, err = _run(capsys, "export", str(stereo_h5), "--out", str(tmp_path))
    assert code == 0, err
    assert "wrote 6 CSV file(s)" in said and "mm" in said
    d = _data(stereo_h5)
    for k in range(6):
        path = tmp_path / f"r_frame{k:05d}.csv"
        lines = path.read_text().splitlines()
        assert lines[0] == ",".join(COLUMNS)
        a = np.genfromtxt(path, delimiter=",", names=True)
        np.testing.assert_array_equal(a["x"], d["points"][:, 0])
        for name in ("W", "U", "Z", "Wt", "W_std", "reprojection_error"):
            np.testing.assert_allclose(a[name], d[name][k], rtol=1e-8, equal_nan=True)
        np.testing.assert_array_equal(a["status"], d["status"][k])
        # NaN <-> an empty cell, exactly where the file holds NaN
        w_cells = np.array([ln.split(",")[COLUMNS.index("W")] for ln in lines[1:]])
        np.testing.assert_array_equal(w_cells == "", np.isnan(d["W"][k]))
        assert (w_cells == "").sum() == 12
    meta = json.loads((tmp_path / "r_csv.json").read_text())
    assert meta["kind"] == "stereo" and meta["columns"] == list(COLUMNS)
    u = meta["units"]
    assert (u["x"], u["X"], u["W"], u["W_std"], u["reprojection_error"], u["status"]) == \
        ("px", "mm", "mm", "mm", "px", "")
    assert u["Ut"] == u["Wt_std"] == "mm/frame" and meta["time_unit"] == "frame"
    assert [e["frame"] for e in meta["files"]] == list(range(6))
    assert meta["status_codes"]["inconsistent"] == 7 and meta["usable_status"] == [0, 1]
    assert meta["calibration"]["source"].startswith("OpenCV")


def test_frames_and_pattern_and_comment(stereo_h5, tmp_path, capsys):
    d = _data(stereo_h5)
    pattern = str(tmp_path / "p" / "f{frame:02d}.csv")
    code, _, err = _run(capsys, "export", str(stereo_h5), "--out", pattern, "--frames", "1,4",
                        "--comment")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "p").glob("*.csv")) == ["f01.csv", "f04.csv"]
    for k in (1, 4):
        text = (tmp_path / "p" / f"f{k:02d}.csv").read_text()
        assert text.startswith(f"# torch_stsdic stereo results r.h5: frame={k} ")
        a = np.genfromtxt(tmp_path / "p" / f"f{k:02d}.csv", delimiter=",", names=True,
                          skip_header=1)  # the comment line
        np.testing.assert_allclose(a["V"], d["V"][k], rtol=1e-8, equal_nan=True)
    code, _, err = _run(capsys, "export", str(stereo_h5), "--out", str(tmp_path / "last"),
                        "--frames", "-1")
    assert code == 0, err
    assert [p.name for p in (tmp_path / "last").glob("*.csv")] == ["r_frame00005.csv"]


def test_vtk_points_at_their_3d_position_and_x0_where_unusable(holes_h5, tmp_path, capsys):
    meshio = pytest.importorskip("meshio")
    code, said, err = _run(capsys, "export", str(holes_h5), "--format", "vtk", "--out",
                           str(tmp_path), "--frames", f"0,{BAD_FRAME},5")
    assert code == 0, err
    assert "open h.pvd" in said
    d = _data(holes_h5)
    keep = np.isfinite(d["X0"]).all(1)
    pvd = (tmp_path / "h.pvd").read_text()
    assert pvd.count("<DataSet") == 3 and f'timestep="{float(BAD_FRAME)!r}"' in pvd
    for k in (0, BAD_FRAME, 5):
        mesh = meshio.read(tmp_path / f"h_frame{k:05d}.vtu")
        ok = (d["status"][k] <= 1)[keep]
        xyz = np.stack([d[c][k] for c in "XYZ"], -1)[keep]
        assert len(mesh.points) == int(keep.sum()) == 36
        np.testing.assert_allclose(mesh.points[ok], xyz[ok], rtol=1e-12)
        np.testing.assert_allclose(mesh.points[~ok], d["X0"][keep][~ok], rtol=1e-12)
        pd = mesh.point_data
        np.testing.assert_array_equal(pd["status"], d["status"][k][keep])
        np.testing.assert_allclose(pd["W"][ok], d["W"][k][keep][ok], rtol=1e-12)
        assert np.isnan(pd["W"][~ok]).all() and np.isnan(pd["displacement"][~ok]).all()
        np.testing.assert_allclose(pd["displacement"][ok],
                                   np.stack([d[c][k] for c in "UVW"], -1)[keep][ok])
        np.testing.assert_allclose(pd["reference_position"], d["X0"][keep])
        np.testing.assert_array_equal(pd["x"], d["points"][keep, 0])
        assert pd["velocity"].shape == (36, 3)
        # the left grid's quads: 6 x 6 triangulated points -> 25 quads
        assert [c.type for c in mesh.cells] == ["quad"] and len(mesh.cells[0].data) == 25
    assert (~((d["status"][BAD_FRAME] <= 1)[keep])).sum() == 24


def test_mat_arrays_are_the_file_arrays(stereo_h5, tmp_path, capsys):
    sio = pytest.importorskip("scipy.io")
    code, said, err = _run(capsys, "export", str(stereo_h5), "--format", "mat", "--out",
                           str(tmp_path), "--frames", "2:4")
    assert code == 0, err
    m = sio.loadmat(tmp_path / "r.mat", squeeze_me=True)
    d = _data(stereo_h5)
    np.testing.assert_array_equal(m["frames"], [2, 3])
    for name in ("X", "W", "Ut", "W_std", "reprojection_error", "status"):
        np.testing.assert_array_equal(m[name], d[name][2:4])
    np.testing.assert_array_equal(m["x"], d["points"][:, 0])
    np.testing.assert_array_equal(m["X0"], d["X0"])
    np.testing.assert_array_equal(m["times"], d["times"][2:4])
    assert m["units"]["W"] == "mm" and m["units"]["Wt"] == "mm/frame"
    assert int(m["status_codes"]["outside"]) == int(Status.OUTSIDE)
    assert json.loads(str(m["calibration"]))["baseline_mm"] > 100


def test_plot_maps_shape_and_histories(holes_h5, tmp_path, capsys, monkeypatch):
    seen = {}
    real = plot_module.plot_history

    def keep(times, series, **kw):
        seen[Path(kw["path"]).name] = (dict(series), kw)
        return real(times, series, **kw)

    monkeypatch.setattr(plot_module, "plot_history", keep)
    code, said, err = _run(capsys, "plot", str(holes_h5), "--out", str(tmp_path), "--dpi",
                           "50")
    assert code == 0, err
    names = {"fields_frame00005.png", "quality_frame00005.png", "shape_frame00005.png",
             "history_mean.png", "velocity_history_mean.png"}
    assert {p.name for p in tmp_path.glob("*.png")} == names
    assert all((tmp_path / n).stat().st_size > 8000 for n in names)
    # the mean W rests on the usable points; frame BAD_FRAME (12 of 48) is left out
    d = _data(holes_h5)
    ok = d["status"] <= 1
    curves, kw = seen["history_mean.png"]
    np.testing.assert_array_equal(kw["counts"], ok.sum(1))
    assert kw["min_count"] == 20 and kw["ylabel"] == "displacement (mm)"
    mean_w = np.nanmean(np.where(ok, d["W"], np.nan), axis=1)
    np.testing.assert_allclose(curves["W"], mean_w)
    assert f"frame(s) {BAD_FRAME} left out" in said
    assert seen["velocity_history_mean.png"][1]["ylabel"] == "velocity (mm/frame)"
    # --frame, --fields, --point
    code, said, err = _run(capsys, "plot", str(holes_h5), "--out", str(tmp_path / "b"),
                           "--frame", "2", "--fields", "Z,reprojection_error", "--point",
                           "100", "60", "--dpi", "40")
    assert code == 0, err
    assert (tmp_path / "b" / "fields_frame00002.png").stat().st_size > 5000
    assert "history_x100_y60.png" in said


def test_one_line_errors(stereo_h5, tmp_path, capsys):
    missing = str(tmp_path / "nope.h5")
    for cmd in (["export", missing, "--out", str(tmp_path)], ["plot", missing, "--out",
                                                               str(tmp_path)]):
        code, _, err = _run(capsys, *cmd)
        assert code == 1 and err.strip() == f"stsdic: error: result file not found: {missing}"
    # a stereo file on a 2-D-only path
    code, _, err = _run(capsys, "plot", str(stereo_h5), "--out", str(tmp_path), "--animate",
                        "W")
    assert code == 2 and "--animate W: for 2-D result files" in err
    assert err.count("\n") == 1
    code, _, err = _run(capsys, "plot", str(stereo_h5), "--out", str(tmp_path), "--min-zncc",
                        "0.5")
    assert code == 2 and "no ZNCC" in err
    # a 2-D file where a stereo one is needed
    two_d = tmp_path / "2d.h5"
    ResultWriter(two_d, points=np.array([[10.0, 10.0], [20.0, 10.0]]), frames=np.arange(2),
                 times=np.arange(2.0), config={}, inputs=[]).close()
    for call in (lambda: export_stereo(two_d, tmp_path / "x"),
                 lambda: StereoResult.from_hdf5(two_d)):
        with pytest.raises(ValueError, match="is a 2-D result file") as e:
            call()
        assert "\n" not in str(e.value)
    with pytest.raises(FileNotFoundError, match="result file not found"):
        export_stereo(missing, tmp_path / "x", "vtk")
    not_h5 = tmp_path / "a.h5"
    not_h5.write_text("no")
    with pytest.raises(ValueError, match="not a readable HDF5"):
        StereoResult.from_hdf5(not_h5)
    # ... and a stereo file given to the 2-D reader names the stereo one
    from torch_stsdic.io import read_results
    from torch_stsdic.io.results import ResultFileError

    with pytest.raises(ResultFileError, match="is a stereo result") as e:
        read_results(stereo_h5)
    assert "StereoResult.from_hdf5" in str(e.value) and "\n" not in str(e.value)


def test_plane_frame_is_a_rigid_change_of_frame(stereo_h5, tmp_path):
    """``in_plane_frame`` (``stsdic stereo --coordinates plane``): the reference shape's
    best-fit plane becomes Z = 0 (the usable X0's centroid at the origin, their Z the plane
    residuals), lengths and the displacement's norm are kept, and mapping back with the
    stored origin and rotation gives the camera frame's X, Y, Z; the file says which frame."""
    cam = StereoResult.from_hdf5(stereo_h5)
    pl = cam.in_plane_frame()
    origin, rot = cam.plane()
    assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=rot.dtype), atol=1e-12)
    ok0 = torch.isfinite(cam.X0).all(1) & cam.ok.any(0)
    x0 = pl.X0[ok0]
    assert float(x0.mean(0).abs().max()) < 1e-9
    # Z is the normal: its spread is the shape's departure from a plane, far below X, Y's
    assert float(x0[:, 2].std()) < 0.05 * float(x0[:, :2].std(0).min())
    # X is the camera's x projected onto the plane (as docs/stereo.md says)
    ex = torch.tensor([1.0, 0.0, 0.0], dtype=rot.dtype)
    want = ex - (ex @ rot[2]) * rot[2]
    assert torch.allclose(rot[0], want / want.norm(), atol=1e-12)
    both = cam.ok & torch.isfinite(cam.U)
    n_cam = cam.displacement.norm(dim=-1)[both]
    n_pl = pl.displacement.norm(dim=-1)[both]
    assert torch.allclose(n_cam, n_pl, atol=1e-12)
    # the displacement's covariance (read back from the file) turns as R C R^T, and the
    # plane frame's stds of U, V, W (and X, Y, Z) are its diagonal
    assert cam.U_cov is not None and cam.U_cov.shape == (*cam.U.shape, 3, 3)
    torch.testing.assert_close(torch.diagonal(cam.U_cov, dim1=-2, dim2=-1).sqrt(),
                               torch.stack([cam.std[c] for c in "UVW"], -1), equal_nan=True)
    torch.testing.assert_close(pl.U_cov, rot @ cam.U_cov @ rot.T, equal_nan=True)
    for a, b, i in (("U", "X", 0), ("V", "Y", 1), ("W", "Z", 2)):
        want = pl.U_cov[..., i, i].sqrt()
        torch.testing.assert_close(pl.std[a], want, equal_nan=True)
        torch.testing.assert_close(pl.std[b], want, equal_nan=True)
    assert not torch.allclose(pl.std["W"][both], cam.std["W"][both])  # W: the plane normal
    # a strain has its predicted std wherever it has a value (the never-matched points, whose
    # X0 is NaN, next to matched ones are left out of the neighbourhood's variance)
    for r in (cam, pl):
        st = r.surface_strain()
        for k in ("exx", "eyy", "exy"):
            assert torch.equal(torch.isfinite(st[k]), torch.isfinite(st[k + "_std"])), k
            assert int(torch.isfinite(st[k]).sum()) > 0
    back = torch.stack([pl.X, pl.Y, pl.Z], -1) @ rot.to(pl.X.dtype) + origin.to(pl.X.dtype)
    assert torch.allclose(back[both], torch.stack([cam.X, cam.Y, cam.Z], -1)[both], atol=1e-9)
    with pytest.raises(ValueError, match="already"):
        pl.in_plane_frame()
    out = tmp_path / "plane.h5"
    pl.to_hdf5(out)
    with h5py.File(out, "r") as f:
        assert f.attrs["frame"].startswith("best-fit plane")
        np.testing.assert_allclose(f["plane_rotation"][()], rot.numpy(), atol=1e-12)
        np.testing.assert_allclose(f["plane_origin"][()], origin.numpy(), atol=1e-12)
        np.testing.assert_allclose(f["W"][()], pl.W.numpy())
        assert f["U_cov"].shape == (*pl.U.shape, 6) and f["U_cov"].attrs["units"] == "mm^2"
    back_pl = StereoResult.from_hdf5(out)
    assert back_pl.frame == pl.frame
    torch.testing.assert_close(back_pl.U_cov, pl.U_cov, equal_nan=True)


def test_command_writes_the_plane_frame(stereo_h5, tmp_path, capsys):
    """``stsdic stereo --coordinates plane`` writes the plane frame's fields; the CSV sidecar
    and ``stsdic export``'s units line name that frame."""
    d = stereo_h5.parent
    out = tmp_path / "p.h5"
    assert main(["stereo", "--left", str(d / "left.tif"), "--right", str(d / "right.tif"),
                 "--calibration", str(d / "cal.yml"), "--m", "1", "--step", "20", "--roi",
                 "20", "20", "160", "120", "--coordinates", "plane", "--out", str(out),
                 "--no-progress"]) == 0
    want = StereoResult.from_hdf5(stereo_h5).in_plane_frame()
    got = StereoResult.from_hdf5(out)
    assert got.frame == want.frame
    assert torch.allclose(got.W, want.W, equal_nan=True, atol=1e-9)
    export_stereo(out, tmp_path / "csv", "csv")
    meta = json.loads(next((tmp_path / "csv").glob("*_csv.json")).read_text())
    assert "best-fit plane" in json.dumps(meta)
    capsys.readouterr()
    code, said, err = _run(capsys, "export", str(out), "--out", str(tmp_path / "csv2"))
    assert code == 0, err
    assert "(best-fit plane of the reference shape frame)" in said and "left camera" not in said
    code, said, err = _run(capsys, "export", str(stereo_h5), "--out", str(tmp_path / "csv3"))
    assert "(left camera frame)" in said


def test_stereo_input_guards_are_one_line(stereo_h5, tmp_path, capsys):
    """Bad input to ``stsdic stereo`` gives one line naming the problem, exit code 1, no
    file: series of other lengths, a non-finite pixel, too few frames for the window, a
    region off the image, a reference frame out of range, a missing file."""
    d = stereo_h5.parent
    right = tifffile.imread(d / "right.tif")
    tifffile.imwrite(tmp_path / "short.tif", right[:4], photometric="minisblack")
    nan = right.astype(np.float32)
    nan[2, 40, 40] = np.nan
    tifffile.imwrite(tmp_path / "nan.tif", nan, photometric="minisblack")
    base = ["stereo", "--left", str(d / "left.tif"), "--calibration", str(d / "cal.yml"),
            "--step", "20", "--no-progress"]
    cases = [
        (["--right", str(tmp_path / "short.tif")], "differ in length: 6 and 4"),
        (["--right", str(tmp_path / "nan.tif")], "non-finite pixel"),
        (["--right", str(d / "right.tif"), "--m", "4"], "fewer than the 2m+1 = 9"),
        (["--right", str(d / "right.tif"), "--roi", "500", "500", "600", "600"], "off the image"),
        (["--right", str(d / "right.tif"), "--reference", "9"], "out of range"),
        (["--right", str(tmp_path / "missing.tif")], "not found"),
    ]
    for extra, msg in cases:
        out = tmp_path / "o.h5"
        code = main([*base, *extra, "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and msg in err[-1] and err[-1].startswith("stsdic: error:"), (extra, err)
        assert not out.exists()


def test_interrupted_run_resumes_to_the_same_file(stereo_h5, tmp_path, capsys, monkeypatch):
    """``stsdic stereo`` writes each camera's track as it goes (``<out>.left.h5``,
    ``<out>.right.h5``); stopped during the right camera, it says what is kept (exit 130)
    and ``--resume`` keeps the left camera's frames and writes the file an uninterrupted run
    writes; the cameras' files are removed once the result is written."""
    import torch_stsdic.stereo.run as stereo_run

    d = stereo_h5.parent
    out = tmp_path / "r.h5"
    argv = ["stereo", "--left", str(d / "left.tif"), "--right", str(d / "right.tif"),
            "--calibration", str(d / "cal.yml"), "--m", "1", "--step", "20", "--roi", "20",
            "20", "160", "120", "--out", str(out), "--no-progress"]
    real, calls, stop = stereo_run.track, [], [True]

    def stop_on_right(*a, **k):
        calls.append(k.get("resume"))
        if stop[0] and len(calls) == 2:  # the right camera
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(stereo_run, "track", stop_on_right)
    assert main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "left camera 6 frame(s) in r.left.h5" in err and "--resume" in err, err
    assert not out.exists() and (tmp_path / "r.left.h5").exists()
    calls.clear()
    stop[0] = False
    assert main([*argv, "--resume"]) == 0
    assert calls == [True, False]  # the left camera's file continued, the right one new
    assert not (tmp_path / "r.left.h5").exists() and not (tmp_path / "r.right.h5").exists()
    with h5py.File(out, "r") as a, h5py.File(stereo_h5, "r") as b:
        for k in ("X", "Y", "Z", "U", "V", "W", "status", "exx"):
            np.testing.assert_array_equal(a[k][()], b[k][()], err_msg=k)
