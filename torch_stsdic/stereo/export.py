"""Exports of stereo result files (``stsdic stereo``): CSV (one file per frame), VTK for
ParaView (one ``.vtu`` per frame and a ``.pvd`` time series), MATLAB ``.mat``.

The stereo counterpart of :mod:`torch_stsdic.analysis.export` (same file names, sidecar,
``{frame}`` patterns, atomic writes and VTK writer), for the fields of
:meth:`~torch_stsdic.stereo.result.StereoResult.to_hdf5`: X, Y, Z, U, V, W (mm), Ut, Vt, Wt
(mm per time unit), their ``*_std``, ``reprojection_error`` (px) and ``status``, each in the
unit its dataset's ``units`` attribute names (no conversion: a stereo file is in mm).

VTK: every frame's points sit at their measured 3D position (X, Y, Z of that frame); a
point not usable at that frame (status other than converged / max-iter, or no finite
position) sits at its reference position X0 with NaN fields (its status kept); a point
never triangulated (no finite X0: outside the right image, no cross match) is left out of
every frame, so all frames hold the same points and cells.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.analysis.export import (
    MatField,
    csv_target,
    export_as,
    frame_rows,
    grid_cells,
    keeping_written,
    stored_columns,
    write_csv,
    write_mat,
    write_pvd,
    write_sidecar,
    write_vtu,
)
from torch_stsdic.core.status import Status, usable
from torch_stsdic.stereo.result import FIELDS, open_stereo

__all__ = ["FORMATS", "COLUMNS", "export_stereo", "export_stereo_csv", "export_stereo_mat",
           "export_stereo_vtk", "stereo_units", "time_unit"]

#: the export formats of :func:`export_stereo` (as ``stsdic export --format``)
FORMATS = ("csv", "vtk", "mat")

_VALUES = ("X", "Y", "Z", "U", "V", "W", "Ut", "Vt", "Wt")
#: the CSV columns, in order: x, y (left reference px), then the (F, N) fields
COLUMNS: tuple[str, ...] = ("x", "y", *_VALUES, *(f"{k}_std" for k in _VALUES),
                            "exx", "eyy", "exy", "exx_std", "eyy_std", "exy_std",
                            "reprojection_error", "status")

Frames = int | Sequence[int] | None


def time_unit(f: Any) -> str:
    """The time unit of an open stereo file: "frame" where its times are its frame numbers
    (``stsdic stereo``), else "time unit" (times given to ``track_stereo``)."""
    fr, t = f["frames"][()], f["times"][()]
    return "frame" if np.array_equal(np.asarray(fr, dtype=np.float64), t) else "time unit"


def stereo_units(f: Any, names: Sequence[str]) -> dict[str, str]:
    """The unit of every column of ``names``: the ``units`` attribute of its dataset (x, y:
    px; status: ""), "mm per time unit" read as "mm/frame" where the times are frames."""
    tu = time_unit(f)
    out = {}
    for nm in names:
        if nm in ("x", "y"):
            out[nm] = "px"
            continue
        unit = str(f[nm].attrs.get("units", "")) if nm in f else \
            FIELDS.get(nm.removesuffix("_std"), "")
        out[nm] = unit.replace("mm per time unit", "mm/frame") if tu == "frame" else unit
    return out


def _all_rows(f: Any, frames: Frames, path: Path) -> list[int]:
    """Rows of image frames ``frames`` (default: every row; a stereo file holds no
    unfinished row)."""
    return list(range(len(f["frames"]))) if frames is None else frame_rows(f, frames, path)


def _row_values(f: Any, r: int, names: Sequence[str], points: np.ndarray
                ) -> dict[str, np.ndarray]:
    """(N,) values of row ``r`` of every column in ``names`` (x, y from ``points`` (N, 2));
    a field the file lacks is all NaN."""
    out = {}
    for nm in names:
        if nm in ("x", "y"):
            out[nm] = points[:, 0 if nm == "x" else 1]
        elif nm in f:
            out[nm] = f[nm][r]
        else:
            out[nm] = np.full(len(points), np.nan)
    return out


def _describe(f: Any, src: Path, columns: Sequence[str]) -> dict[str, Any]:
    """The metadata of a stereo export: source, frame convention, units, status codes,
    calibration summary."""
    return {
        "source": str(src),
        "kind": "stereo",
        "software_version": str(f.attrs.get("software_version", "unknown")),
        "coordinate_frame": str(f.attrs.get("frame", "left camera")),
        "unit": "mm",
        "time_unit": time_unit(f),
        "columns": list(columns),
        "units": stereo_units(f, columns),
        "status_codes": {s.name.lower(): int(s) for s in Status},
        "usable_status": [int(Status.CONVERGED), int(Status.MAX_ITER)],
        "calibration": json.loads(f.attrs.get("calibration", "{}")),
    }


# ----------------------------------------------------------------------------------------
# CSV
# ----------------------------------------------------------------------------------------


def export_stereo_csv(path_h5: str | os.PathLike[str],
                      out_dir_or_pattern: str | os.PathLike[str], frames: Frames = None, *,
                      comment: bool = False, sidecar: bool = True) -> list[Path]:
    """Write one CSV per frame of a stereo result file; return the paths written.

    File names as :func:`torch_stsdic.analysis.export.export_csv`: ``<stem>_frame<NNNNN>.csv``
    in a directory, or a pattern with ``{frame}`` (also ``{row}``, ``{time}``). Header
    :data:`COLUMNS` (x, y left reference px; X, Y, Z, U, V, W mm; Ut, Vt, Wt mm per time
    unit; their ``_std``; reprojection_error px; status); values as stored, NaN as empty
    cells. Units, calibration, frame and time of every file: ``<stem>_csv.json``
    (``sidecar``); ``comment`` puts a ``# torch_stsdic stereo results ...`` line first."""
    p = Path(path_h5)
    out = os.fspath(out_dir_or_pattern)
    written: list[Path] = []
    with open_stereo(p) as f:
        all_frames, times = f["frames"][()], f["times"][()]
        rows = _all_rows(f, frames, p)
        pts = f["points"][()]
        tu = time_unit(f)
        is_pattern = "{" in out
        if not is_pattern:
            Path(out).mkdir(parents=True, exist_ok=True)
        listing, seen = [], set()
        for r in rows:
            fr, t = int(all_frames[r]), float(times[r])
            target = csv_target(out, is_pattern, p.stem, fr, r, t, seen)
            head = (f"# torch_stsdic stereo results {p.name}: frame={fr} time={t!r} row={r} "
                    f"unit=mm time_unit={tu.replace(' ', '_')}\n") if comment else ""
            write_csv(target, head, _row_values(f, r, COLUMNS, pts), written)
            listing.append({"file": target.name, "frame": fr, "time": t, "row": r})
        if sidecar and written:
            write_sidecar({**_describe(f, p, COLUMNS), "files": listing}, p.stem, written)
    return written


# ----------------------------------------------------------------------------------------
# VTK
# ----------------------------------------------------------------------------------------


def export_stereo_vtk(path_h5: str | os.PathLike[str], out_dir: str | os.PathLike[str],
                      frames: Frames = None) -> list[Path]:
    """ParaView files: ``<stem>_frame<NNNNN>.vtu`` per frame and ``<stem>.pvd`` (last).

    Points: the triangulated points (finite X0), at (X, Y, Z) of the frame where usable,
    else at X0 with NaN fields; on the left grid joined into quads (the 2-D export's cells).
    Point data: every field (X ... Wt, their _std, reprojection_error, status), x, y (left
    reference px), and the vectors ``displacement`` (U, V, W), ``velocity`` (Ut, Vt, Wt)
    and ``reference_position`` (X0), mm."""
    p, out = Path(path_h5), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    steps = []
    names = [c for c in COLUMNS if c not in ("x", "y")]
    with open_stereo(p) as f:
        pts, x0 = f["points"][()], f["X0"][()]
        keep = np.isfinite(x0).all(axis=1)
        cells = grid_cells(pts[keep])
        for r in _all_rows(f, frames, p):
            vals = _row_values(f, r, names, pts)
            pos = np.column_stack([vals["X"], vals["Y"], vals["Z"]])
            ok = usable(np.asarray(vals["status"])) & np.isfinite(pos).all(axis=1)
            data = {nm: (v if v.dtype.kind in "iub" else np.where(ok, v, np.nan))[keep]
                    for nm, v in vals.items()}
            data["x"], data["y"] = pts[keep, 0], pts[keep, 1]
            data["displacement"] = np.column_stack([data["U"], data["V"], data["W"]])
            data["velocity"] = np.column_stack([data["Ut"], data["Vt"], data["Wt"]])
            data["reference_position"] = x0[keep]
            fr = int(f["frames"][r])
            target = out / f"{p.stem}_frame{fr:05d}.vtu"
            with keeping_written(written):
                write_vtu(target, np.where(ok[:, None], pos, x0)[keep], data, cells)
            written.append(target)
            steps.append((float(f["times"][r]), target.name))
    return [*written, write_pvd(out / f"{p.stem}.pvd", steps, written)]


# ----------------------------------------------------------------------------------------
# MATLAB
# ----------------------------------------------------------------------------------------


def _nan_columns(n_rows: int):
    """The reader of a field the file does not hold: NaN, ``n_rows`` rows."""
    def read(cols: slice) -> np.ndarray:
        return np.full((n_rows, cols.stop - cols.start), np.nan)
    return read


def export_stereo_mat(path_h5: str | os.PathLike[str], out_dir: str | os.PathLike[str],
                      frames: Frames = None) -> list[Path]:
    """One MATLAB file ``<stem>.mat``: every field as a (frames, points) array as stored (X,
    ..., Wt, their _std, reprojection_error, status), ``x``, ``y`` (1, N) left reference px,
    ``X0``, ``X0_std`` (N, 3) mm, ``right_points`` (N, 2) px, ``frames``, ``times``,
    ``unit`` ("mm"), ``time_unit``, ``units`` and ``status_codes`` (structs),
    ``usable_status``, ``calibration`` (JSON text: ``jsondecode(calibration)``),
    ``coordinate_frame``, ``source``."""
    p, out = Path(path_h5), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = [c for c in COLUMNS if c not in ("x", "y")]
    with open_stereo(p) as f:
        rows = sorted(set(_all_rows(f, frames, p)))
        pts = f["points"][()]
        n = len(pts)
        # the (frames, points) fields a block of points at a time (NaN where not stored)
        fields = {nm: MatField((len(rows), n), stored_columns(f[nm], rows, np.asarray)
                               if nm in f else _nan_columns(len(rows))) for nm in names}
        data: dict[str, Any] = dict(
            x=pts[:, 0], y=pts[:, 1], X0=f["X0"][()], X0_std=f["X0_std"][()],
            right_points=f["right_points"][()],
            frames=f["frames"][()][rows].astype(np.float64), times=f["times"][()][rows],
            unit="mm", time_unit=time_unit(f),
            units=stereo_units(f, ["x", "y", *names]) | {"X0": "mm", "X0_std": "mm",
                                                          "right_points": "px"},
            status_codes={s.name.lower(): int(s) for s in Status},
            usable_status=np.array([int(Status.CONVERGED), int(Status.MAX_ITER)], np.float64),
            calibration=str(f.attrs.get("calibration", "{}")),
            coordinate_frame=str(f.attrs.get("frame", "left camera")), source=str(p),
        )  # fmt: skip
        return [write_mat(out / f"{p.stem}.mat", data, fields)]


def export_stereo(path_h5: str | os.PathLike[str], out: str | os.PathLike[str],
                  fmt: str = "csv", frames: Frames = None, **kwargs: Any) -> list[Path]:
    """Export a stereo result file in format ``fmt`` (one of :data:`FORMATS`) into ``out``;
    the paths written. ``kwargs`` go to :func:`export_stereo_csv`."""
    return export_as(fmt, {"csv": export_stereo_csv, "vtk": export_stereo_vtk,
                           "mat": export_stereo_mat}, path_h5, out, frames, kwargs)
