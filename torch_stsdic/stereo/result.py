"""The result of a stereo run: per point and frame X, Y, Z, U, V, W (mm), velocity, status."""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torch_stsdic.io.results import STEREO_FORMAT

__all__ = ["StereoResult", "StereoFile", "best_fit_plane", "FIELDS", "STEREO_FORMAT",
           "is_stereo_file", "open_stereo", "CAMERA_FRAME", "PLANE_FRAME"]

#: the version of the stereo file format (its ``format`` attribute, STEREO_FORMAT, is named
#: in :mod:`torch_stsdic.io.results`; files written before it existed are recognised by
#: their ``kind`` attribute or their datasets W and X0: :func:`is_stereo_file`)
STEREO_FORMAT_VERSION = 1
_KIND = "torch_stsdic stereo result"

#: the coordinate frames of a result: the left camera's, or the best-fit plane of the
#: reference shape's (:meth:`StereoResult.in_plane_frame`)
CAMERA_FRAME = "left camera: X right, Y down, Z along the optical axis"
PLANE_FRAME = ("best-fit plane of the reference shape: X, Y in the plane (X along the left "
               "camera's x as far as the plane allows), Z its normal towards the camera; "
               "origin the usable reference points' centroid")

#: the entries of a covariance stored in a file: UU, VV, WW, UV, UW, VW
_COV_PAIRS = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])

#: the (F, N) fields of a result and their units
FIELDS = {"X": "mm", "Y": "mm", "Z": "mm", "U": "mm", "V": "mm", "W": "mm",
          "Ut": "mm per time unit", "Vt": "mm per time unit", "Wt": "mm per time unit",
          "reprojection_error": "px"}


@dataclass
class StereoResult:
    """3D shape, displacement and velocity of points over time, in the left-camera frame.

    Attributes:
        points: (N, 2) left reference points px. right_points: (N, 2) their matches in the
            right reference px (NaN where the cross-camera match failed).
        frames: (F,) series indices; times: (F,) their times.
        X, Y, Z: (F, N) position at each frame, mm (world = left camera frame: X right,
            Y down, Z along the optical axis). U, V, W: (F, N) displacement from the reference
            position, mm. Ut, Vt, Wt: (F, N) velocity from the STS time terms, mm per time unit
            (NaN for classical DIC, m = 0).
        X0: (N, 3) the reference shape, mm; X0_std: (N, 3) its predicted std (cross-match
            noise carried through the triangulation).
        std: name -> (F, N) predicted standard deviation of "X", "Y", "Z", "U", "V", "W",
            "Ut", "Vt", "Wt" (pixel stds of both cameras carried through the triangulation).
        U_cov: (F, N, 3, 3) mm^2 the displacement's predicted covariance in this result's
            frame (its diagonal: the squares of std "U", "V", "W"; the off-diagonal terms:
            the correlation of a point's errors along the lines of sight); None where the
            stds are not known (files written before it).
        reprojection_error: (F, N) px, RMS over the two cameras.
        status: (F, N) int8 :class:`torch_stsdic.Status` (the worst of the left track, the
            right track and the cross-camera match; INCONSISTENT where the reprojection error
            exceeds the run's limit).
        left, right: the two :class:`torch_stsdic.TrackResult` (px). cross: the
            :class:`~torch_stsdic.stereo.matching.CrossMatch`.
        calibration: the rig's summary (baseline, stereo angle, focal lengths, source).
    """

    points: Tensor
    right_points: Tensor
    frames: Tensor
    times: Tensor
    X: Tensor
    Y: Tensor
    Z: Tensor
    U: Tensor
    V: Tensor
    W: Tensor
    Ut: Tensor
    Vt: Tensor
    Wt: Tensor
    X0: Tensor
    X0_std: Tensor
    std: dict[str, Tensor]
    reprojection_error: Tensor
    status: Tensor
    left: Any = None
    right: Any = None
    cross: Any = None
    calibration: dict[str, Any] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    #: the coordinate frame of X..Wt and X0 (:data:`CAMERA_FRAME` or :data:`PLANE_FRAME`)
    frame: str = field(default="")
    #: surface strain "exx", "eyy", "exy" (F, N), dimensionless: Green-Lagrange in the
    #: reference tangent plane, b1 along the frame's X axis projected onto it; with their
    #: predicted std "exx_std", ... where the displacement's std is known
    #: (:func:`~torch_stsdic.stereo.strain.surface_strain`); empty where not computed
    strain: dict[str, Tensor] = field(default_factory=dict)
    U_cov: Tensor | None = None

    def __post_init__(self) -> None:
        self.frame = self.frame or CAMERA_FRAME

    @property
    def ok(self) -> Tensor:
        """(F, N) bool: usable (CONVERGED or MAX_ITER)."""
        return self.status <= 1

    @property
    def displacement(self) -> Tensor:
        """(F, N, 3) U, V, W mm."""
        return torch.stack([self.U, self.V, self.W], -1)

    def plane(self) -> tuple[Tensor, Tensor]:
        """The best-fit plane of the reference shape (the usable points of X0), in the left
        camera frame: origin (3,) mm and rotation (3, 3) (:func:`best_fit_plane`). Computed
        from this result's X0: call it on a camera-frame result."""
        ok0 = torch.isfinite(self.X0).all(1) & self.ok.any(0)
        if int(ok0.sum()) < 3:
            raise ValueError(f"best-fit plane: {int(ok0.sum())} usable reference points, 3 "
                             "or more needed")
        return best_fit_plane(self.X0.double(), ok0)

    def surface_strain(self, subset_size: float | None = None, k: int = 9
                       ) -> dict[str, Tensor]:
        """Green-Lagrange surface strain (F, N) of the usable points
        (:func:`~torch_stsdic.stereo.strain.surface_strain`): b1 along this result's X axis
        (the camera's x, or the plane frame's X) projected onto each tangent plane."""
        from torch_stsdic.stereo.strain import surface_strain

        size = subset_size if subset_size is not None else self.info.get("subset_size", 21)
        u = torch.where(self.ok[..., None], self.displacement.double(), torch.nan)
        sd = (torch.stack([self.std[c] for c in "UVW"], -1)
              if all(c in self.std for c in "UVW") else None)
        return surface_strain(self.points, self.X0, u, float(size), k=k, U_std=sd,
                              U_cov=self.U_cov)

    def in_plane_frame(self, plane: tuple[Tensor, Tensor] | None = None) -> StereoResult:
        """The same result with X, Y, Z, U, V, W, their velocities, X0 and the stds in the
        best-fit plane's frame (:meth:`plane`; ``plane``: its (origin, rotation) given, e.g.
        the whole result's for a part of its frames): positions ``(p - origin) @ R.T``,
        vectors ``d @ R.T``. The displacement's covariance turns exactly (``R C R^T``), and the stds
        of X, Y, Z, U, V, W are its diagonal's square roots; the other stds (velocity, X0,
        and all of them where no covariance is known) are rotated as independent components
        (each axis's variance ``R**2 @ var``), which leaves out their correlation."""
        if self.frame != CAMERA_FRAME:
            raise ValueError(f"in_plane_frame: the result is already in the {self.frame!r} "
                             "frame")
        origin, rot = self.plane() if plane is None else plane
        rot_t = rot.T.to(self.X.dtype)

        def vec(a: Tensor, b: Tensor, c: Tensor, shift: bool = False) -> tuple[Tensor, ...]:
            v = torch.stack([a, b, c], -1)
            out = (v - origin.to(v.dtype)) @ rot_t if shift else v @ rot_t
            return out.unbind(-1)

        def var_rot(names: tuple[str, str, str]) -> dict[str, Tensor]:
            if not all(k in self.std for k in names):
                return {}
            var = torch.stack([self.std[k] ** 2 for k in names], -1)
            return dict(zip(names, (var @ (rot_t ** 2)).clamp(min=0).sqrt().unbind(-1)))

        X, Y, Z = vec(self.X, self.Y, self.Z, shift=True)
        U, V, W = vec(self.U, self.V, self.W)
        Ut, Vt, Wt = vec(self.Ut, self.Vt, self.Wt)
        x0 = (self.X0 - origin.to(self.X0.dtype)) @ rot.T.to(self.X0.dtype)
        x0_std = ((self.X0_std ** 2) @ (rot.T.to(self.X0.dtype) ** 2)).sqrt()
        std = {**self.std, **var_rot(("Ut", "Vt", "Wt"))}
        u_cov = None
        if self.U_cov is None:
            std.update(**var_rot(("X", "Y", "Z")), **var_rot(("U", "V", "W")))
        else:
            r = rot.to(self.U_cov.dtype)
            u_cov = r @ self.U_cov @ r.T
            sd = torch.diagonal(u_cov, dim1=-2, dim2=-1).clamp(min=0).sqrt()
            for i, (a, b) in enumerate(zip("XYZ", "UVW")):
                if b in std:  # the reference's error cancels: X's std is U's
                    std[a] = std[b] = sd[..., i]
        info = {**self.info, "plane_origin_mm": origin.tolist(),
                "plane_rotation": rot.tolist()}
        out = dataclasses.replace(self, X=X, Y=Y, Z=Z, U=U, V=V, W=W, Ut=Ut, Vt=Vt, Wt=Wt,
                                  X0=x0, X0_std=x0_std, std=std, info=info,
                                  frame=PLANE_FRAME, strain={}, U_cov=u_cov)
        if self.strain:  # b1 now follows the plane's X
            out.strain = out.surface_strain()
        return out

    def __repr__(self) -> str:
        return (f"<StereoResult {self.frames.numel()} frames x {self.points.shape[0]} points, "
                f"ok={float(self.ok.float().mean()):.1%}>")

    def to_hdf5(self, path, overwrite: bool = False) -> None:
        """Write ``points`` (N, 2), ``right_points``, ``frames``, ``times``, X, Y, Z, U, V, W,
        Ut, Vt, Wt, their ``*_std``, ``reprojection_error``, ``status`` (F, N), ``X0``
        (N, 3) with ``units`` attributes, and the calibration summary (JSON attribute); root
        attributes ``format`` (:data:`STEREO_FORMAT`), ``version``, ``software_version``
        (:class:`StereoFile`, which also writes a long run a few frames at a time)."""
        out = StereoFile(path, self, overwrite=overwrite)
        try:
            out.write_rows(self, 0)
        finally:
            out.close()

    @classmethod
    def from_hdf5(cls, path: str | os.PathLike[str]) -> StereoResult:
        """Read a file written by :meth:`to_hdf5` (tensors float64 on the CPU, status int8;
        ``left``, ``right``, ``cross`` are not stored: None). ValueError (one line) for a
        file that is no stereo result, FileNotFoundError for a missing one."""
        with open_stereo(path) as f:
            t = {k: torch.as_tensor(f[k][()]) for k in
                 ("points", "right_points", "frames", "times", "X0", "X0_std", *FIELDS)}
            std = {k: torch.as_tensor(f[f"{k}_std"][()]) for k in FIELDS if f"{k}_std" in f}
            status = torch.as_tensor(f["status"][()].astype(np.int8))
            strain = {k: torch.as_tensor(f[k][()]) for k in
                      ("exx", "eyy", "exy", "exx_std", "eyy_std", "exy_std") if k in f}
            cal = json.loads(f.attrs.get("calibration", "{}"))
            info = json.loads(f.attrs.get("info", "{}"))
            frame = str(f.attrs.get("frame", CAMERA_FRAME))
            u_cov = None
            if "U_cov" in f:
                packed = torch.as_tensor(f["U_cov"][()])
                i, j = _COV_PAIRS
                u_cov = packed.new_zeros(*packed.shape[:-1], 3, 3)
                u_cov[..., i, j] = packed
                u_cov[..., j, i] = packed
        return cls(**t, std=std, status=status, calibration=cal, info=info, frame=frame,
                   strain=strain, U_cov=u_cov)


class StereoFile:
    """A stereo result file (the layout of :meth:`StereoResult.to_hdf5`) written a few frames
    at a time: made from ``first`` (a result of some of the run's frames, or all of them:
    its per-point arrays, calibration, frame and fields), for ``frames`` and ``times`` (the
    run's, default ``first``'s); :meth:`write_rows` writes a part's (F, N) rows from row
    ``row0``, :meth:`close` the run's ``info`` (default ``first``'s)."""

    def __init__(self, path: str | os.PathLike[str], first: StereoResult, *,
                 frames: Tensor | None = None, times: Tensor | None = None,
                 overwrite: bool = False) -> None:
        import h5py

        from torch_stsdic.io.run_record import software_version

        frames = first.frames if frames is None else frames
        times = first.times if times is None else times
        n_f = int(frames.numel())
        self.info = first.info
        self.f = f = h5py.File(path, "w" if overwrite else "w-")
        try:
            f.attrs["format"] = STEREO_FORMAT
            f.attrs["version"] = STEREO_FORMAT_VERSION
            f.attrs["software_version"] = software_version()
            f.attrs["kind"] = _KIND
            f.attrs["frame"] = first.frame
            f.attrs["calibration"] = json.dumps(first.calibration, default=str)
            d = f.create_dataset("points", data=first.points.cpu().numpy())
            d.attrs["units"] = "px"
            d = f.create_dataset("right_points", data=first.right_points.cpu().numpy())
            d.attrs["units"] = "px"
            f.create_dataset("frames", data=frames.cpu().numpy())
            f.create_dataset("times", data=times.cpu().numpy())

            def rows(name: str, a: Tensor, unit: str, **attrs: str) -> None:
                d = f.create_dataset(name, shape=(n_f, *a.shape[1:]), dtype=np.dtype(
                    a.cpu().numpy().dtype))
                d.attrs["units"] = unit
                for k, v in attrs.items():
                    d.attrs[k] = v

            for name, (a, unit, attrs) in self._fields(first).items():
                rows(name, a, unit, **attrs)
            d = f.create_dataset("X0", data=first.X0.cpu().numpy())
            d.attrs["units"] = "mm"
            d = f.create_dataset("X0_std", data=first.X0_std.cpu().numpy())
            d.attrs["units"] = "mm"
            if "plane_origin_mm" in first.info:
                d = f.create_dataset("plane_origin", data=np.asarray(
                    first.info["plane_origin_mm"], dtype=np.float64))
                d.attrs["units"] = "mm"
                d.attrs["what"] = "the best-fit plane's origin in the left camera frame"
                d = f.create_dataset("plane_rotation", data=np.asarray(
                    first.info["plane_rotation"], dtype=np.float64))
                d.attrs["what"] = ("rows: the plane frame's axes in the left camera frame; "
                                   "camera -> plane: (p - plane_origin) @ plane_rotation.T")
        except BaseException:
            f.close()
            raise

    @staticmethod
    def _fields(res: StereoResult) -> dict[str, tuple[Tensor, str, dict[str, str]]]:
        """The (F, ...) datasets of ``res``: name -> (values, unit, other attributes)."""
        out: dict[str, tuple[Tensor, str, dict[str, str]]] = {}
        for name, unit in FIELDS.items():
            out[name] = (getattr(res, name), unit, {})
            if name in res.std:
                out[f"{name}_std"] = (res.std[name], unit, {})
        for name, a in res.strain.items():
            out[name] = (a, "1", {"what": ("predicted std (first order) of " if
                                           name.endswith("_std") else "")
                                  + ("Green-Lagrange surface strain in the reference tangent "
                                     "plane (b1: the frame's X axis projected onto it); exy: "
                                     "tensor shear")})
        if res.U_cov is not None:
            i, j = _COV_PAIRS
            out["U_cov"] = (res.U_cov[..., i, j], "mm^2", {
                "what": "the displacement's predicted covariance, (F, N, 6): UU, VV, WW, UV, "
                        "UW, VW"})
        out["status"] = (res.status.to(torch.int8), "", {
            "codes": "0 converged, 1 max_iter, 2 diverged, 3 outside, 4 low texture, "
                     "5 not computed, 6 poor fit, 7 inconsistent"})
        return out

    def write_rows(self, part: StereoResult, row0: int) -> None:
        """The (F, N) rows of ``part`` (a result of frames ``row0 ..`` of the run)."""
        fields = self._fields(part)
        for name in self.f:
            if name in fields:
                a = fields[name][0].cpu().numpy()
                self.f[name][row0:row0 + a.shape[0]] = a

    def close(self, info: dict[str, Any] | None = None) -> None:
        """Write the run's ``info`` (default the first part's) and close the file."""
        if self.f.id.valid:
            self.f.attrs["info"] = json.dumps(self.info if info is None else info, default=str)
            self.f.close()


def is_stereo_file(f: Any) -> bool:
    """Whether the open HDF5 file ``f`` is a stereo result: its ``format`` attribute, else
    (files written before it) its ``kind`` attribute or the datasets W and X0."""
    return (f.attrs.get("format") == STEREO_FORMAT or f.attrs.get("kind") == _KIND
            or ("W" in f and "X0" in f))


def open_stereo(path: str | os.PathLike[str]) -> Any:
    """Open a stereo result file read-only (an ``h5py.File``). One-line errors:
    FileNotFoundError for a missing file, ValueError for one that is not HDF5, a 2-D result
    ('stsdic run') or another file."""
    import h5py

    from torch_stsdic.io.results import RESULTS_FORMAT

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"result file not found: {p}")
    try:
        f = h5py.File(p, "r", locking=False)
    except OSError as exc:
        raise ValueError(f"{p} is not a readable HDF5 result file: {exc}") from None
    if is_stereo_file(f):
        return f
    two_d = f.attrs.get("format") == RESULTS_FORMAT
    f.close()
    if two_d:
        raise ValueError(f"{p} is a 2-D result file ('stsdic run'), not a stereo result "
                         "('stsdic stereo'): it has no X, Y, Z, U, V, W")
    raise ValueError(f"{p} is not a torch_stsdic stereo result file (written by 'stsdic "
                     "stereo')")


def best_fit_plane(points: Tensor, valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Least-squares plane through (N, 3) points: (origin (3,), rotation (3, 3)) whose rows
    are the plane's axes (x: the camera's x projected onto the plane, y in the plane, z its
    normal, towards the left camera); a point's plane coordinates are
    ``(p - origin) @ rotation.T``."""
    p = points if valid is None else points[valid]
    p = p[torch.isfinite(p).all(1)]
    c = p.mean(0)
    _, _, vh = torch.linalg.svd(p - c, full_matrices=False)
    n = vh[2]
    if float(n @ (-c)) < 0:  # normal towards the camera (at the origin)
        n = -n
    ex = torch.zeros_like(n)
    ex[0] = 1.0
    x = ex - (ex @ n) * n
    if float(torch.linalg.norm(x)) < 1e-6:  # the plane seen edge-on along x: its long axis
        x = vh[0] - (vh[0] @ n) * n
    x = x / torch.linalg.norm(x)
    if float(x[0]) < 0:
        x = -x
    y = torch.linalg.cross(n, x)
    return c, torch.stack([x, y, n])
