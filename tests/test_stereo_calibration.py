"""Stereo calibration import: one convention, every format gives the same triangulated points,
one-line errors for missing fields and wrong image sizes, the rig summary."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_stsdic.stereo.calibration import (
    Camera,
    StereoCalibration,
    euler_from_rotation,
    load_calibration,
    rotation_from_euler,
)
from torch_stsdic.stereo.render import make_rig
from torch_stsdic.stereo.triangulation import project, triangulate

GT4 = Path(__file__).resolve().parents[2] / "shared" / "data" / "stereo-gt4-dspecimen"


def _pairs(rig, n=50, seed=0):
    g = np.random.default_rng(seed)
    X = np.stack([g.uniform(-15, 15, n), g.uniform(-12, 12, n), g.uniform(260, 320, n)], 1)
    X = torch.as_tensor(X)
    return project(X, rig.left), project(X, rig.right, rig.R, rig.T)


def _write_all(rig, d: Path, vic: bool):
    paths = {"opencv_yaml": d / "cal.yml", "opencv_xml": d / "cal_cv.xml",
             "dice": d / "cal_dice.xml", "json": d / "cal.json", "npz": d / "cal.npz",
             "matlab_json": d / "stereoParams.json"}
    rig.save_opencv(paths["opencv_yaml"])
    rig.save_opencv(paths["opencv_xml"])
    rig.save_dice(paths["dice"])
    rig.save_json(paths["json"])
    rig.save_npz(paths["npz"])
    rig.save_matlab(paths["matlab_json"])
    try:
        import scipy.io  # noqa: F401
        paths["matlab_mat"] = d / "stereoParams.mat"
        rig.save_matlab(paths["matlab_mat"])
    except ImportError:
        pass
    if vic:
        paths["vic"] = d / "cal_vic.xml"
        rig.save_vic(paths["vic"])
    return paths


@pytest.mark.parametrize("tangential", [True, False])
def test_every_format_triangulates_the_same_points(tmp_path, tangential):
    dist = (-0.3, 0.2, 1e-3, -5e-4, 0.05) if tangential else (-0.3, 0.2, 0.0, 0.0, 0.05)
    rig = make_rig((200, 240), distortion=dist, skew=0.4)
    pl, pr = _pairs(rig)
    ref = triangulate(rig, pl, pr).X
    paths = _write_all(rig, tmp_path, vic=not tangential)
    assert len(paths) >= 6
    for name, p in paths.items():
        cal = load_calibration(p)
        assert cal.left.image_size == (200, 240), name
        X = triangulate(cal, pl, pr).X
        err = float((X - ref).abs().max())
        assert err <= 1e-6, f"{name}: {err:.3g} mm"
        assert cal.describe().startswith("stereo rig: baseline")


def test_vic_world_frame_is_converted_to_left_camera(tmp_path):
    # VIC-3D poses are world -> camera with a world that is not the left camera
    rig = make_rig((100, 120), distortion=(0.1, -0.05, 0, 0, 0.0))
    Rw = rotation_from_euler(170.0, 8.0, -3.0)
    Tw = np.array([-50.0, 3.0, 20.0])
    R1, T1 = rig.R @ Rw, rig.R @ Tw + rig.T  # world -> right = (left -> right) o (world -> left)

    def line(i, c, R, T):
        v = [c.K[0, 2], c.K[1, 2], c.K[0, 0], c.K[1, 1], c.K[0, 1], c.dist[0], c.dist[1],
             c.dist[4]]
        o = list(euler_from_rotation(R)) + list(T)
        return (f'<camera id="{i}">{" ".join(repr(float(x)) for x in v)}<orientation>'
                f'{" ".join(repr(float(x)) for x in o)}</orientation></camera>')
    p = tmp_path / "proj.xml"
    p.write_text('<?xml version="1.0"?>\n<!DOCTYPE vpml>\n<project><calibration>'
                 + line(0, rig.left, Rw, Tw) + line(1, rig.right, R1, T1)
                 + '</calibration><polygonmask width="120" height="100"/></project>')
    cal = load_calibration(p)
    assert np.abs(cal.R - rig.R).max() < 1e-12
    assert np.abs(cal.T - rig.T).max() < 1e-9


def test_euler_round_trip():
    for a, b, g in ((179.9, 9.4, -0.06), (-30, 20, 45), (0, 0, 0)):
        R = rotation_from_euler(a, b, g)
        assert np.abs(rotation_from_euler(*euler_from_rotation(R)) - R).max() < 1e-12


def test_summary():
    rig = make_rig(distance=300.0, angle=20.0)
    s = rig.summary()
    assert s["baseline_mm"] == pytest.approx(2 * 300 * math.sin(math.radians(10)), rel=1e-9)
    assert s["stereo_angle_deg"] == pytest.approx(20.0, abs=1e-9)
    assert s["fx_left"] == pytest.approx(2400.0)


def test_missing_field_is_one_line(tmp_path):
    rig = make_rig()
    p = tmp_path / "cal.yml"
    rig.save_opencv(p)
    text = p.read_text()
    cut = text[:text.index("T: !!opencv-matrix")]
    (tmp_path / "no_t.yml").write_text(cut)
    with pytest.raises(ValueError) as e:
        load_calibration(tmp_path / "no_t.yml")
    msg = str(e.value)
    assert "\n" not in msg and "translation" in msg and "no_t.yml" in msg
    rig.save_dice(tmp_path / "d.xml")
    t = (tmp_path / "d.xml").read_text().replace('<Parameter name="FY"', '<Parameter name="XX"')
    (tmp_path / "d2.xml").write_text(t)
    with pytest.raises(ValueError, match="missing field FY of CAMERA 0") as e:
        load_calibration(tmp_path / "d2.xml")
    assert "\n" not in str(e.value)
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(ValueError, match="format not recognised"):
        load_calibration(tmp_path / "x.txt")
    with pytest.raises(ValueError, match="no such file"):
        load_calibration(tmp_path / "absent.yml")


def test_wrong_image_size_is_one_line():
    rig = make_rig((200, 240))
    rig.check_images((5, 200, 240), (5, 200, 240))
    with pytest.raises(ValueError) as e:
        rig.check_images((200, 240), (240, 200))
    assert "\n" not in str(e.value) and "right images are 200x240" in str(e.value)


def test_invalid_rotation_and_camera():
    with pytest.raises(ValueError, match="not a rotation"):
        StereoCalibration(Camera(np.eye(3)), Camera(np.eye(3)), 2 * np.eye(3), [1, 0, 0])
    with pytest.raises(ValueError, match="focal"):
        Camera(np.diag([0.0, 1.0, 1.0]))


@pytest.mark.skipif(not (GT4 / "cal.xml").is_file(),
                    reason="GT4 stereo data (../shared/data/stereo-gt4-dspecimen) not present")
def test_gt4_vic_calibration():
    cal = load_calibration(GT4 / "cal.xml")
    s = cal.summary()
    assert s["baseline_mm"] == pytest.approx(123.2, abs=0.1)
    assert s["stereo_angle_deg"] == pytest.approx(18.8, abs=0.1)
    assert cal.left.image_size == (1200, 1920)
    assert s["fx_left"] == pytest.approx(6636.03, abs=0.01)
