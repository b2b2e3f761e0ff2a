"""A stereo camera system in one convention, and readers for the formats users already have.

Convention (every reader converts to it, :class:`StereoCalibration` holds only it):

* The **left camera is the world frame**: a point X_L (mm) in front of the left camera has
  X_L[2] > 0; the right camera sees it at ``X_R = R @ X_L + T`` (R (3, 3), T (3,) mm).
* Pinhole with OpenCV's distortion model, coefficients in **OpenCV order k1, k2, p1, p2, k3**:
  normalised ``x = X/Z, y = Y/Z``, ``r2 = x^2 + y^2``,
  ``xd = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)``,
  ``yd = y (1 + ...) + p1 (r2 + 2 y^2) + 2 p2 x y``, pixel ``= K @ (xd, yd, 1)`` with
  ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
* Pixels as everywhere in torch_stsdic: x = column, y = row, pixel centres at integer
  coordinates, 0-based (OpenCV's convention; MATLAB's 1-based principal point is shifted by -1).
* ``image_size`` is (height, width) px.

Readers (:func:`load_calibration` picks one from the file's content):

* OpenCV FileStorage YAML or XML (``cameraMatrix1/2`` or ``M1/M2`` or ``K1/K2``,
  ``distCoeffs1/2`` or ``D1/D2``, ``R``, ``T``, image size from ``imageSize``, ``image_size``,
  ``image_width``/``image_height`` or ``width``/``height``).
* VIC-3D project XML (a ``<calibration>`` block: per camera ``cx cy fx fy skew kappa1 kappa2
  kappa3`` then ``<orientation>`` alpha beta gamma (deg) tx ty tz (mm), world -> camera,
  ``R = Rz(gamma) Ry(beta) Rx(alpha)``; image size from ``<polygonmask width= height=>`` or
  ``<image width= height=>``). The kappas are read as the radial terms of r^2, r^4, r^6 in
  normalised coordinates (the model of Sutton, Orteu & Schreier's book, which VIC-3D follows);
  ``vic_kappa="none"`` ignores them.
* DICe camera-system XML (``xml_file_format = DICe_xml_camera_system_file``; ``CAMERA 0/1``
  sublists with CX, CY, FX, FY, FS, K1, K2, K3, P1, P2, TX, TY, TZ and ``rotation_3x3_matrix``
  or ALPHA/BETA/GAMMA, ``IMAGE_HEIGHT_WIDTH``, optional
  ``extrinsics_relative_camera_to_camera``).
* JSON or NPZ with this module's own keys (``K_left, dist_left, K_right, dist_right, R, T,
  image_size_left, image_size_right``; written by :meth:`StereoCalibration.save_json` /
  :meth:`~StereoCalibration.save_npz`).
* MATLAB ``stereoParameters`` exported with ``toStruct`` to a .mat file (needs scipy) or to
  JSON: ``CameraParameters1/2`` (``IntrinsicMatrix`` = K transposed, or ``K``; 1-based
  principal point; ``RadialDistortion``, ``TangentialDistortion``, ``ImageSize`` [rows cols]),
  ``RotationOfCamera2`` (R transposed: MATLAB multiplies row vectors) and
  ``TranslationOfCamera2``.

Any missing field is a ``ValueError`` with a one-line message naming the field and the file.
"""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Camera", "StereoCalibration", "load_calibration", "rotation_from_euler",
           "euler_from_rotation"]


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


@dataclass(frozen=True, eq=False)
class Camera:
    """One camera: intrinsics ``K`` (3, 3), distortion (k1, k2, p1, p2, k3), image size (H, W)."""

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera matrix needs finite positive focal lengths, got "
                             f"fx={K[0, 0]}, fy={K[1, 1]}")
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        if d.size > 5:
            if np.any(d[5:] != 0):
                raise ValueError(f"distortion: only k1, k2, p1, p2, k3 are supported, got "
                                 f"{d.size} non-zero-padded coefficients")
            d = d[:5]
        d = np.concatenate([d, np.zeros(5 - d.size)])
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)
        if self.image_size is not None:
            h, w = (int(v) for v in self.image_size)
            if h <= 0 or w <= 0:
                raise ValueError(f"image size must be positive, got {self.image_size}")
            object.__setattr__(self, "image_size", (h, w))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Two cameras in the module's convention: world = left camera, ``X_R = R X_L + T`` (mm).

    Attributes:
        left, right: the :class:`Camera` s.
        R: (3, 3) rotation left -> right. T: (3,) translation, mm.
        source: where it was read from (format and path), for the run summary.
    """

    left: Camera
    right: Camera
    R: np.ndarray
    T: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        T = np.asarray(self.T, dtype=np.float64).ravel()
        if R.shape != (3, 3):
            raise ValueError(f"R must be 3x3, got shape {R.shape}")
        if T.shape != (3,):
            raise ValueError(f"T must have 3 values, got {T.size}")
        err = np.abs(R @ R.T - np.eye(3)).max()
        if not err < 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
            raise ValueError(f"R is not a rotation (|R R^T - I| = {err:.2g}, "
                             f"det = {np.linalg.det(R):.6g})")
        if not np.linalg.norm(T) > 0:
            raise ValueError("T is zero: the two cameras are at the same place")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "T", T)

    # ---- summary and checks ---------------------------------------------------------------
    @property
    def baseline(self) -> float:
        """Distance between the optical centres, mm (= |T|)."""
        return float(np.linalg.norm(self.T))

    @property
    def stereo_angle(self) -> float:
        """Angle between the two optical axes, degrees."""
        c = float(np.clip(self.R[2, 2], -1.0, 1.0))  # z_R . z_L, z_L in right coordinates
        return math.degrees(math.acos(c))

    @property
    def right_centre(self) -> np.ndarray:
        """The right camera's optical centre in the world (left) frame, mm: -R^T T."""
        return -self.R.T @ self.T

    def summary(self) -> dict[str, Any]:
        """Baseline (mm), stereo angle (deg), focal lengths (px), image sizes, source."""
        return {
            "baseline_mm": self.baseline, "stereo_angle_deg": self.stereo_angle,
            "fx_left": self.left.fx, "fy_left": self.left.fy,
            "fx_right": self.right.fx, "fy_right": self.right.fy,
            "image_size_left": self.left.image_size, "image_size_right": self.right.image_size,
            "source": self.source,
        }

    def describe(self) -> str:
        """One line for a run summary."""
        s = self.summary()
        return (f"stereo rig: baseline {s['baseline_mm']:.2f} mm, stereo angle "
                f"{s['stereo_angle_deg']:.2f} deg, f left {s['fx_left']:.1f}/{s['fy_left']:.1f}"
                f" px, f right {s['fx_right']:.1f}/{s['fy_right']:.1f} px ({self.source})")

    def check_images(self, left_shape, right_shape=None) -> None:
        """ValueError (one line) when an image's (H, W) differs from the calibration's."""
        right_shape = left_shape if right_shape is None else right_shape
        for name, cam, shp in (("left", self.left, left_shape), ("right", self.right,
                                                                   right_shape)):
            hw = tuple(int(v) for v in tuple(shp)[-2:])
            if cam.image_size is not None and hw != tuple(cam.image_size):
                raise ValueError(
                    f"calibration: {name} images are {hw[1]}x{hw[0]} (WxH) but the calibration "
                    f"({self.source or 'given'}) is for {cam.image_size[1]}x{cam.image_size[0]}")

    # ---- writers (for exchange and the format round-trip tests) --------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "convention": "left camera = world; X_R = R X_L + T (mm); dist = k1 k2 p1 p2 k3; "
                          "pixel centres at integers, 0-based; image_size = (height, width)",
            "K_left": self.left.K.tolist(), "dist_left": self.left.dist.tolist(),
            "K_right": self.right.K.tolist(), "dist_right": self.right.dist.tolist(),
            "R": self.R.tolist(), "T": self.T.tolist(),
            "image_size_left": None if self.left.image_size is None else
            list(self.left.image_size),
            "image_size_right": None if self.right.image_size is None else
            list(self.right.image_size),
        }

    def save_json(self, path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    def save_npz(self, path) -> None:
        d = {k: np.asarray(v, dtype=np.float64) for k, v in self.to_dict().items()
             if k != "convention" and v is not None}
        np.savez(path, **d)

    def save_opencv(self, path) -> None:
        """OpenCV FileStorage, YAML or XML by the suffix (.yml/.yaml or .xml)."""
        h, w = self.left.image_size or (0, 0)
        mats = {"cameraMatrix1": self.left.K, "distCoeffs1": self.left.dist[None, :],
                "cameraMatrix2": self.right.K, "distCoeffs2": self.right.dist[None, :],
                "R": self.R, "T": self.T[:, None]}
        if str(path).lower().endswith(".xml"):
            lines = ['<?xml version="1.0"?>', "<opencv_storage>"]
            if self.left.image_size:
                lines.append(f"<imageSize>{w} {h}</imageSize>")
            for k, m in mats.items():
                data = " ".join(repr(float(v)) for v in m.ravel())
                lines.append(f'<{k} type_id="opencv-matrix"><rows>{m.shape[0]}</rows>'
                             f"<cols>{m.shape[1]}</cols><dt>d</dt><data>{data}</data></{k}>")
            lines.append("</opencv_storage>")
        else:
            lines = ["%YAML:1.0", "---"]
            if self.left.image_size:
                lines.append(f"imageSize: [ {w}, {h} ]")
            for k, m in mats.items():
                data = ", ".join(repr(float(v)) for v in m.ravel())
                lines += [f"{k}: !!opencv-matrix", f"   rows: {m.shape[0]}",
                          f"   cols: {m.shape[1]}", "   dt: d", f"   data: [ {data} ]"]
        Path(path).write_text("\n".join(lines) + "\n")

    def save_dice(self, path) -> None:
        """DICe camera-system XML (Teuchos ParameterList), OPENCV lens model, world = left."""
        def cam(i, c: Camera, R, T):
            k1, k2, p1, p2, k3 = (repr(float(v)) for v in c.dist)
            h, w = c.image_size or (0, 0)
            rows = "\n".join(
                f'      <Parameter name="ROW {j}" type="string" value="{{ '
                f'{", ".join(repr(float(v)) for v in R[j])} }}" />' for j in range(3))
            return f"""  <ParameterList name="CAMERA {i}">
    <Parameter name="CX" type="double" value="{float(c.K[0, 2])!r}" />
    <Parameter name="CY" type="double" value="{float(c.K[1, 2])!r}" />
    <Parameter name="FX" type="double" value="{float(c.K[0, 0])!r}" />
    <Parameter name="FY" type="double" value="{float(c.K[1, 1])!r}" />
    <Parameter name="FS" type="double" value="{float(c.K[0, 1])!r}" />
    <Parameter name="K1" type="double" value="{k1}" />
    <Parameter name="K2" type="double" value="{k2}" />
    <Parameter name="K3" type="double" value="{k3}" />
    <Parameter name="P1" type="double" value="{p1}" />
    <Parameter name="P2" type="double" value="{p2}" />
    <Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
    <Parameter name="TX" type="double" value="{float(T[0])!r}" />
    <Parameter name="TY" type="double" value="{float(T[1])!r}" />
    <Parameter name="TZ" type="double" value="{float(T[2])!r}" />
    <ParameterList name="rotation_3x3_matrix">
{rows}
    </ParameterList>
    <Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{{ {h}, {w} }}" />
  </ParameterList>"""
        text = ("<ParameterList>\n"
                '  <Parameter name="xml_file_format" type="string" '
                'value="DICe_xml_camera_system_file" />\n'
                '  <Parameter name="system_type_3D" type="string" value="OPENCV" />\n'
                + cam(0, self.left, np.eye(3), np.zeros(3)) + "\n"
                + cam(1, self.right, self.R, self.T) + "\n</ParameterList>\n")
        Path(path).write_text(text)

    def save_vic(self, path) -> None:
        """VIC-3D project XML ``<calibration>`` (radial kappas only: p1 = p2 = 0 required)."""
        for c in (self.left, self.right):
            if c.dist[2] != 0 or c.dist[3] != 0:
                raise ValueError("VIC-3D calibrations have no tangential distortion (p1, p2)")
        h, w = self.left.image_size or (0, 0)

        def cam(i, c: Camera, R, T):
            vals = [c.K[0, 2], c.K[1, 2], c.K[0, 0], c.K[1, 1], c.K[0, 1], c.dist[0],
                    c.dist[1], c.dist[4]]
            ori = list(euler_from_rotation(R)) + [float(v) for v in T]
            return (f'  <camera id="{i}">{" ".join(repr(float(v)) for v in vals)}'
                    f'<orientation>{" ".join(repr(float(v)) for v in ori)}</orientation>\n'
                    "  </camera>")
        text = ('<?xml version="1.0" encoding="ISO-8859-1"?>\n<!DOCTYPE vpml>\n<project>\n'
                ' <calibration lri="calibration">\n'
                + cam(0, self.left, np.eye(3), np.zeros(3)) + "\n"
                + cam(1, self.right, self.R, self.T) + "\n </calibration>\n"
                f' <polygonmask width="{w}" height="{h}"/>\n</project>\n')
        Path(path).write_text(text)

    def save_matlab(self, path) -> None:
        """MATLAB ``toStruct(stereoParameters)`` layout, .mat (scipy) or .json."""
        def cam(c: Camera):
            K1 = c.K.copy()
            K1[0, 2] += 1.0
            K1[1, 2] += 1.0
            return {"IntrinsicMatrix": K1.T, "RadialDistortion": c.dist[[0, 1, 4]],
                    "TangentialDistortion": c.dist[[2, 3]],
                    "ImageSize": np.asarray(c.image_size or (0, 0), dtype=np.float64)}
        s = {"CameraParameters1": cam(self.left), "CameraParameters2": cam(self.right),
             "RotationOfCamera2": self.R.T, "TranslationOfCamera2": self.T[None, :]}
        if str(path).lower().endswith(".json"):
            def lists(v):
                return {k: lists(x) for k, x in v.items()} if isinstance(v, dict) else \
                    np.asarray(v).tolist()
            Path(path).write_text(json.dumps(lists(s)))
        else:
            from scipy.io import savemat
            savemat(path, {"stereoParams": s})


# ---- rotations -----------------------------------------------------------------------------
def rotation_from_euler(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """``Rz(gamma) @ Ry(beta) @ Rx(alpha)``, angles in degrees (VIC-3D's and DICe's order)."""
    a, b, g = (math.radians(v) for v in (alpha, beta, gamma))
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(g), -math.sin(g), 0], [math.sin(g), math.cos(g), 0], [0, 0, 1]])
    return rz @ ry @ rx


def euler_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_euler` (degrees)."""
    R = np.asarray(R, dtype=np.float64)
    sy = math.hypot(R[0, 0], R[1, 0])
    if sy > 1e-9:
        a, b, g = math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], sy), \
            math.atan2(R[1, 0], R[0, 0])
    else:
        a, b, g = math.atan2(-R[1, 2], R[1, 1]), math.atan2(-R[2, 0], sy), 0.0
    return math.degrees(a), math.degrees(b), math.degrees(g)


def _relative(R0, T0, R1, T1):
    """World->camera poses of both cameras -> (R, T) left -> right."""
    R = R1 @ R0.T
    return R, T1 - R @ T0


# ---- readers -------------------------------------------------------------------------------
def load_calibration(path: str | os.PathLike, *, vic_kappa: str = "opencv",
                     format: str | None = None) -> StereoCalibration:
    """Read a stereo calibration file in any supported format (see the module docstring).

    Args:
        path: the file. The format is found from its content (``format`` forces one of
            "opencv", "vic", "dice", "json", "npz", "matlab").
        vic_kappa: VIC-3D radial terms: "opencv" (kappa1..3 on r^2, r^4, r^6) or "none".

    Raises:
        ValueError: one line naming the missing or invalid field and the file.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"calibration: no such file {p}")
    try:
        fmt = format or _sniff(p)
        reader = {"opencv": _read_opencv, "vic": lambda q: _read_vic(q, vic_kappa),
                  "dice": _read_dice, "json": _read_json, "npz": _read_npz,
                  "matlab": _read_matlab}.get(fmt)
        if reader is None:
            raise ValueError(f"unknown calibration format {fmt!r}")
        return reader(p)
    except ValueError as e:
        msg = _one_line(e)
        raise ValueError(msg if msg.startswith("calibration") else
                         f"calibration {p.name}: {msg}") from None


def _sniff(p: Path) -> str:
    suf = p.suffix.lower()
    if suf == ".npz":
        return "npz"
    if suf == ".mat":
        return "matlab"
    head = p.read_bytes()[:200000].decode("latin-1")
    if suf == ".json" or head.lstrip().startswith("{"):
        return "matlab" if "CameraParameters1" in head else "json"
    if "%YAML" in head[:50] or "opencv_storage" in head or "opencv-matrix" in head:
        return "opencv"
    if "DICe_xml_camera_system_file" in head:
        return "dice"
    if "<calibration" in head or "vpml" in head[:300]:
        return "vic"
    raise ValueError("format not recognised (OpenCV YAML/XML, VIC-3D XML, DICe XML, JSON, "
                     "NPZ or MATLAB .mat expected)")


def _need(d: dict, names: tuple[str, ...], what: str):
    for n in names:
        if n in d and d[n] is not None:
            return d[n]
    raise ValueError(f"missing field {what} ({' or '.join(names)})")


def _size_hw(w, h) -> tuple[int, int] | None:
    if w is None or h is None:
        return None
    return int(round(float(h))), int(round(float(w)))


def _read_opencv(p: Path) -> StereoCalibration:
    text = p.read_text(encoding="latin-1")
    vals: dict[str, Any] = {}
    if "<opencv_storage" in text:
        root = ET.fromstring(text[text.index("<opencv_storage"):])
        for el in root:
            if el.get("type_id") == "opencv-matrix":
                rows, cols = int(el.findtext("rows")), int(el.findtext("cols"))
                data = np.array((el.findtext("data") or "").split(), dtype=np.float64)
                if data.size != rows * cols:
                    raise ValueError(f"{el.tag}: {data.size} values for {rows}x{cols}")
                vals[el.tag] = data.reshape(rows, cols)
            elif el.text and el.text.strip():
                vals[el.tag] = np.array(el.text.split(), dtype=np.float64)
    else:
        mat = re.compile(r"^(\w+)\s*:\s*!!opencv-matrix\s*rows\s*:\s*(\d+)\s*cols\s*:\s*(\d+)"
                         r"\s*dt\s*:\s*\w+\s*data\s*:\s*\[([^\]]*)\]", re.M | re.S)
        for m in mat.finditer(text):
            data = np.array([float(v) for v in m.group(4).replace(",", " ").split()])
            rows, cols = int(m.group(2)), int(m.group(3))
            if data.size != rows * cols:
                raise ValueError(f"{m.group(1)}: {data.size} values for {rows}x{cols}")
            vals[m.group(1)] = data.reshape(rows, cols)
        for m in re.finditer(r"^(\w+)\s*:\s*\[([^\]]*)\]", text, re.M):
            vals.setdefault(m.group(1), np.array(m.group(2).replace(",", " ").split(),
                                                 dtype=np.float64))
        for m in re.finditer(r"^(\w+)\s*:\s*([-+0-9.eE]+)\s*$", text, re.M):
            vals.setdefault(m.group(1), np.array([float(m.group(2))]))
    K1 = _need(vals, ("cameraMatrix1", "camera_matrix1", "M1", "K1"), "left camera matrix")
    K2 = _need(vals, ("cameraMatrix2", "camera_matrix2", "M2", "K2"), "right camera matrix")
    D1 = _need(vals, ("distCoeffs1", "dist_coeffs1", "D1"), "left distortion")
    D2 = _need(vals, ("distCoeffs2", "dist_coeffs2", "D2"), "right distortion")
    R = _need(vals, ("R",), "rotation")
    T = _need(vals, ("T",), "translation")
    size = None
    for key in ("imageSize", "image_size", "ImageSize"):
        if key in vals and np.asarray(vals[key]).size == 2:
            w, h = np.asarray(vals[key]).ravel()
            size = _size_hw(w, h)
    if size is None:
        w = vals.get("image_width", vals.get("width"))
        h = vals.get("image_height", vals.get("height"))
        size = None if w is None or h is None else _size_hw(np.ravel(w)[0], np.ravel(h)[0])
    if np.asarray(R).size == 3:  # a Rodrigues vector
        R = _rodrigues(np.asarray(R, dtype=np.float64).ravel())
    return StereoCalibration(Camera(K1, D1, size), Camera(K2, D2, size), np.reshape(R, (3, 3)),
                             np.ravel(T), source=f"OpenCV {p.name}")


def _rodrigues(r: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(r))
    if th < 1e-15:
        return np.eye(3)
    k = r / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


def _read_vic(p: Path, kappa: str) -> StereoCalibration:
    if kappa not in ("opencv", "none"):
        raise ValueError(f"vic_kappa must be 'opencv' or 'none', got {kappa!r}")
    text = p.read_text(encoding="latin-1")
    cal = re.search(r"<calibration[^>]*>(.*?)</calibration>", text, re.S)
    if cal is None:
        raise ValueError("missing field <calibration> (VIC-3D project XML)")
    cams = re.findall(r'<camera\s+id="(\d+)"\s*>([^<]*)<orientation>([^<]*)</orientation>',
                      cal.group(1))
    if len(cams) < 2:
        raise ValueError(f"<calibration> holds {len(cams)} complete <camera> entries "
                         "(with <orientation>), 2 needed")
    size = None
    m = re.search(r'<(?:polygonmask|image)\b[^>]*\bwidth="(\d+)"[^>]*\bheight="(\d+)"', text)
    if m:
        size = _size_hw(m.group(1), m.group(2))
    poses, cameras = [], []
    for cid, intr, ori in sorted(cams, key=lambda c: int(c[0]))[:2]:
        iv = np.array(intr.split(), dtype=np.float64)
        ov = np.array(ori.split(), dtype=np.float64)
        if iv.size < 5:
            raise ValueError(f"camera {cid}: {iv.size} intrinsic values, needs cx cy fx fy skew "
                             "[kappa1 kappa2 kappa3]")
        if ov.size != 6:
            raise ValueError(f"camera {cid}: <orientation> has {ov.size} values, needs "
                             "alpha beta gamma tx ty tz")
        cx, cy, fx, fy, s = iv[:5]
        kap = np.concatenate([iv[5:8], np.zeros(3 - iv[5:8].size)])
        if kappa == "none":
            kap[:] = 0
        K = np.array([[fx, s, cx], [0, fy, cy], [0, 0, 1]])
        cameras.append(Camera(K, np.array([kap[0], kap[1], 0.0, 0.0, kap[2]]), size))
        poses.append((rotation_from_euler(*ov[:3]), ov[3:]))
    R, T = _relative(*poses[0], *poses[1])
    return StereoCalibration(cameras[0], cameras[1], R, T, source=f"VIC-3D {p.name}")


def _read_dice(p: Path) -> StereoCalibration:
    root = ET.parse(p).getroot()

    def params(el) -> dict[str, str]:
        return {c.get("name"): c.get("value") for c in el if c.tag == "Parameter"}

    def sub(el, name):
        for c in el:
            if c.tag == "ParameterList" and c.get("name") == name:
                return c
        return None

    top = params(root)
    cams = []
    for i in (0, 1):
        el = sub(root, f"CAMERA {i}")
        if el is None:
            raise ValueError(f"missing field CAMERA {i}")
        q = params(el)

        def f(name, default=None, q=q, i=i):
            if name in q:
                return float(q[name])
            if default is None:
                raise ValueError(f"missing field {name} of CAMERA {i}")
            return default
        model = q.get("LENS_DISTORTION_MODEL", "NO_LENS_DISTORTION")
        k1, k2, k3 = f("K1", 0.0), f("K2", 0.0), f("K3", 0.0)
        p1, p2 = f("P1", 0.0), f("P2", 0.0)
        if model in ("NO_LENS_DISTORTION", "NONE"):
            dist = np.zeros(5)
        elif model in ("OPENCV_LENS_DISTORTION", "OPENCV_DIS", "K1R2_K2R4_K3R6"):
            dist = np.array([k1, k2, p1, p2, k3])
        else:
            raise ValueError(f"CAMERA {i}: lens model {model} is not the OpenCV model "
                             "(k1 r^2 + k2 r^4 + k3 r^6 + tangential)")
        if any(f(n, 0.0) != 0 for n in ("K4", "K5", "K6", "S1", "S2", "S3", "S4", "T1", "T2")):
            raise ValueError(f"CAMERA {i}: K4-K6, S1-S4, T1-T2 are not supported")
        hw = q.get("IMAGE_HEIGHT_WIDTH")
        if hw is None:
            raise ValueError(f"missing field IMAGE_HEIGHT_WIDTH of CAMERA {i}")
        h, w = (float(v) for v in hw.strip("{} ").split(","))
        K = np.array([[f("FX"), f("FS", 0.0), f("CX")], [0, f("FY"), f("CY")], [0, 0, 1]])
        rot = sub(el, "rotation_3x3_matrix")
        if rot is not None:
            rp = params(rot)
            R = np.array([[float(v) for v in _need(rp, (f"ROW {j}",), f"ROW {j} of CAMERA {i} "
                                                   "rotation").strip("{} ").split(",")]
                          for j in range(3)])
        else:
            R = rotation_from_euler(f("ALPHA", 0.0), f("BETA", 0.0), f("GAMMA", 0.0))
        cams.append((Camera(K, dist, _size_hw(w, h)), R,
                     np.array([f("TX", 0.0), f("TY", 0.0), f("TZ", 0.0)])))
    rel = str(top.get("extrinsics_relative_camera_to_camera", "false")).lower() == "true"
    if rel:  # camera 1's pose is already camera 0 -> camera 1
        R, T = cams[1][1], cams[1][2]
    else:
        R, T = _relative(cams[0][1], cams[0][2], cams[1][1], cams[1][2])
    return StereoCalibration(cams[0][0], cams[1][0], R, T, source=f"DICe {p.name}")


def _from_own(d: dict, src: str) -> StereoCalibration:
    def size(key):
        v = d.get(key)
        if v is None:
            return None
        v = np.asarray(v).ravel()
        return (int(v[0]), int(v[1])) if v.size == 2 else None
    left = Camera(_need(d, ("K_left",), "K_left"), _need(d, ("dist_left",), "dist_left"),
                  size("image_size_left"))
    right = Camera(_need(d, ("K_right",), "K_right"), _need(d, ("dist_right",), "dist_right"),
                   size("image_size_right"))
    return StereoCalibration(left, right, _need(d, ("R",), "R"), _need(d, ("T",), "T"),
                             source=src)


def _read_json(p: Path) -> StereoCalibration:
    d = json.loads(p.read_text())
    if "CameraParameters1" in d:
        return _from_matlab(d, f"MATLAB {p.name}")
    return _from_own({k: (None if v is None else np.asarray(v, dtype=np.float64))
                      for k, v in d.items() if k != "convention"}, f"JSON {p.name}")


def _read_npz(p: Path) -> StereoCalibration:
    with np.load(p) as z:
        return _from_own({k: z[k] for k in z.files}, f"NPZ {p.name}")


def _read_matlab(p: Path) -> StereoCalibration:
    if p.suffix.lower() == ".json":
        return _read_json(p)
    try:
        from scipy.io import loadmat
    except ImportError as e:  # pragma: no cover
        raise ValueError("reading a MATLAB .mat file needs scipy (pip install scipy)") from e
    m = loadmat(p, squeeze_me=True, struct_as_record=False)
    keys = [k for k in m if not k.startswith("__")]
    if not keys:
        raise ValueError("the .mat file holds no variable")
    top = m[keys[0]] if len(keys) == 1 else {k: m[k] for k in keys}
    return _from_matlab(_struct_dict(top), f"MATLAB {p.name}")


def _struct_dict(s) -> Any:
    if isinstance(s, dict):
        return {k: _struct_dict(v) for k, v in s.items()}
    if hasattr(s, "_fieldnames"):
        return {k: _struct_dict(getattr(s, k)) for k in s._fieldnames}
    return s


def _from_matlab(d: dict, src: str) -> StereoCalibration:
    def cam(c: dict, which: str) -> Camera:
        if not isinstance(c, dict):
            raise ValueError(f"{which} is not a struct")
        if "IntrinsicMatrix" in c:
            K = np.asarray(c["IntrinsicMatrix"], dtype=np.float64).reshape(3, 3).T
        else:
            K = np.asarray(_need(c, ("K",), f"{which}.IntrinsicMatrix or K"),
                           dtype=np.float64).reshape(3, 3)
        K = K.copy()
        K[0, 2] -= 1.0  # MATLAB: centre of the first pixel is (1, 1)
        K[1, 2] -= 1.0
        rad = np.atleast_1d(np.asarray(c.get("RadialDistortion", np.zeros(2)), np.float64))
        tan = np.atleast_1d(np.asarray(c.get("TangentialDistortion", np.zeros(2)), np.float64))
        rad = np.concatenate([rad, np.zeros(3 - rad.size)])
        tan = np.concatenate([tan, np.zeros(2 - tan.size)])
        size = c.get("ImageSize")
        hw = None
        if size is not None and np.asarray(size).size == 2 and np.all(np.asarray(size) > 0):
            r, cc = np.asarray(size, dtype=np.float64).ravel()
            hw = _size_hw(cc, r)
        return Camera(K, np.array([rad[0], rad[1], tan[0], tan[1], rad[2]]), hw)
    c1 = cam(_need(d, ("CameraParameters1",), "CameraParameters1"), "CameraParameters1")
    c2 = cam(_need(d, ("CameraParameters2",), "CameraParameters2"), "CameraParameters2")
    Rm = np.asarray(_need(d, ("RotationOfCamera2",), "RotationOfCamera2"), np.float64)
    Tm = np.asarray(_need(d, ("TranslationOfCamera2",), "TranslationOfCamera2"), np.float64)
    return StereoCalibration(c1, c2, Rm.reshape(3, 3).T, Tm.ravel(), source=src)
