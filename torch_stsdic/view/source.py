"""What ``stsdic view`` shows of a result file, read lazily: one row or one point at a time.

:class:`ResultSource` (a 2-D file, ``stsdic run``) and :class:`StereoSource` (``stsdic
stereo``) answer the page's questions: the file's description (:meth:`meta`), one field at
one row in its physical unit (:meth:`row_values`), every field at one point and row
(:meth:`point_values`), one point's history with its predicted std (:meth:`history`), colour
limits and the summary. The file is opened for every question (``locking=False``), so a
file still being written shows each row as soon as the run has flushed it; nothing reads a
whole (F, N) field, so a 10,000-frame file opens at once. Units, colour maps and validity
follow ``stsdic plot`` (:mod:`torch_stsdic.plot`, :mod:`torch_stsdic.io.units`).
"""

from __future__ import annotations

import contextlib
import io
import json
import threading
import warnings
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from torch_stsdic.core.status import Status, usable
from torch_stsdic.io.results import RUN_ARRAYS, field_names, open_results
from torch_stsdic.io.stored import INT_FIELDS
from torch_stsdic.io.units import Units, units_of
from torch_stsdic.plot import STATUS_COLOURS, colour_norm, is_diverging, straddles_zero

__all__ = ["ImageSource", "ResultSource", "StereoSource", "colour_maps", "open_source"]

#: colour limits over the movie come from at most this many finished rows, evenly spread
LIMIT_ROWS = 24
#: default of the page's minimum ZNCC (as ``stsdic plot --min-zncc``)
MIN_ZNCC = 0.8
#: fields never hidden where a point is unusable (they say why it is)
QUALITY_FIELDS = ("status", "zncc", "iterations", "m", "reprojection_error")


def colour_maps(n: int = 256) -> dict[str, Any]:
    """The page's colour tables: ``viridis`` and ``RdBu_r`` as ``n`` RGB triples (the maps of
    ``stsdic plot``), and the status colours and names by code."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    out: dict[str, Any] = {}
    for name in ("viridis", "RdBu_r"):
        rgb = colormaps[name](np.linspace(0.0, 1.0, n))[:, :3]
        out[name] = np.round(rgb * 255).astype(int).tolist()
    out["status"] = [{"code": int(c), "name": c.name.lower(), "colour": to_hex(STATUS_COLOURS[c])}
                     for c in Status]
    return out


class ImageSource:
    """Frames of an image series as 8-bit PNG, grey levels scaled once for all frames (the
    0.5 .. 99.5 percentiles of the first frame shown), the last few kept."""

    def __init__(self, series: Any, keep: int = 16) -> None:
        self.series = series
        self._cache: OrderedDict[int, bytes] = OrderedDict()
        self._keep = keep
        self._range: tuple[float, float] | None = None
        self._lock = threading.Lock()
        self._read = threading.Lock()

    def __len__(self) -> int:
        return len(self.series)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) px."""
        h, w = self.series.shape[-2:]
        return int(h), int(w)

    def grey(self, k: int) -> np.ndarray:
        """Frame ``k`` (H, W) as float32 grey levels."""
        with self._read, warnings.catch_warnings():  # one reader of the files at a time
            warnings.simplefilter("ignore")
            return self.series.numpy(int(k))

    def png(self, k: int) -> bytes:
        """Frame ``k`` as an 8-bit grey PNG."""
        from PIL import Image

        with self._lock:
            if k in self._cache:
                self._cache.move_to_end(k)
                return self._cache[k]
        img = self.grey(k)
        if self._range is None:
            fin = img[np.isfinite(img)]
            lo, hi = (float(v) for v in np.percentile(fin, [0.5, 99.5])) if fin.size else (0, 1)
            self._range = (lo, hi if hi > lo else lo + 1.0)
        lo, hi = self._range
        g = np.clip((np.nan_to_num(img, nan=lo) - lo) * (255.0 / (hi - lo)), 0, 255)
        buf = io.BytesIO()
        Image.fromarray(g.astype(np.uint8)).save(buf, format="PNG", compress_level=1)
        data = buf.getvalue()
        with self._lock:
            self._cache[k] = data
            while len(self._cache) > self._keep:
                self._cache.popitem(last=False)
        return data


def _finite_list(a: np.ndarray) -> list[float | None]:
    """A float array as a JSON list, NaN and inf as null."""
    a = np.asarray(a, dtype=np.float64)
    return [float(v) if np.isfinite(v) else None for v in a.ravel()]


class _Source:
    """What both kinds of result file share: lazy reads by row and point, limits, meta."""

    kind = "2d"
    path: Path
    points: np.ndarray  # (N, 2) reference x, y px
    frames: np.ndarray  # (F,) image frame numbers
    times: np.ndarray  # (F,)
    fields: list[str]
    images: ImageSource | None = None

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._limits: dict[tuple[str, float], tuple[float, float, bool, int]] = {}

    # -- the file -----------------------------------------------------------------------
    @contextlib.contextmanager
    def _file(self) -> Iterator[h5py.File]:
        """The file, opened for one question (sees every row flushed so far)."""
        with self._lock, h5py.File(self.path, "r", locking=False) as f:
            yield f

    def completed(self) -> np.ndarray:
        """(F,) bool: rows finished so far."""
        with self._file() as f:
            return f["completed"][()].astype(bool) if "completed" in f else \
                np.ones(len(self.frames), dtype=bool)

    @property
    def n_rows(self) -> int:
        return len(self.frames)

    @property
    def n_points(self) -> int:
        return len(self.points)

    # -- units and validity (by kind) ------------------------------------------------------
    def unit_of(self, name: str) -> str:
        raise NotImplementedError

    def convert(self, name: str, values: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def label(self, name: str) -> str:
        u = self.unit_of(name)
        return f"{name} ({u})" if u else name

    def _valid(self, f: h5py.File, rows: Any, cols: Any, min_zncc: float) -> np.ndarray:
        """Usable (converged, max-iter) with ZNCC >= ``min_zncc`` at ``f[...][rows, cols]``."""
        st = f["status"][rows, cols] if "status" in f else None
        ok = usable(st) if st is not None else np.ones(np.shape(f[self.fields[0]][rows, cols]),
                                                       dtype=bool)
        if "zncc" in f and min_zncc > -1.0:
            ok = ok & (np.nan_to_num(f["zncc"][rows, cols], nan=-1.0) >= min_zncc)
        return ok

    def _check(self, name: str) -> None:
        if name not in self.fields:
            raise KeyError(f"no field {name!r} in {self.path.name}")

    def _check_row(self, row: int) -> int:
        if not 0 <= row < self.n_rows:
            raise IndexError(f"row {row} out of range (0..{self.n_rows - 1})")
        return int(row)

    def _check_point(self, k: int) -> int:
        if not 0 <= k < self.n_points:
            raise IndexError(f"point {k} out of range (0..{self.n_points - 1})")
        return int(k)

    # -- questions ------------------------------------------------------------------------
    def row_values(self, name: str, row: int, min_zncc: float = MIN_ZNCC) -> np.ndarray:
        """(N,) float32 field ``name`` at ``row`` in its unit; NaN where the point is not
        usable (except for the quality fields) or the row is not finished."""
        self._check(name)
        row = self._check_row(row)
        with self._file() as f:
            return self._values(f, name, np.array([row]), min_zncc)[0]

    def _values(self, f: h5py.File, name: str, rows: np.ndarray, min_zncc: float
                ) -> np.ndarray:
        """(len(rows), N) float32 of :meth:`row_values` for increasing ``rows``, read at once."""
        sel = rows.tolist()
        vals = self.convert(name, f[name][sel].astype(np.float64))
        if name not in QUALITY_FIELDS:
            vals = np.where(self._valid(f, sel, slice(None), min_zncc), vals, np.nan)
        if "completed" in f:  # an unfinished row holds the fill values: nothing to show
            vals = np.where(f["completed"][()][rows][:, None], vals, np.nan)
        return vals.astype(np.float32)

    def positions(self, row: int) -> np.ndarray:
        """(N, 2) float32 where the points are in the frame of ``row``, px (the reference
        positions where the motion is unknown)."""
        return self.points.astype(np.float32)

    def point_values(self, row: int, k: int) -> dict[str, Any]:
        """Every field of point ``k`` at ``row``, stored values in their units (usable or
        not: the status says)."""
        row, k = self._check_row(row), self._check_point(k)
        out: dict[str, Any] = {}
        with self._file() as f:
            for nm in self.fields:
                v = f[nm][row, k]
                if nm in INT_FIELDS:
                    out[nm] = int(v)
                else:
                    c = float(self.convert(nm, np.float64(v)))
                    out[nm] = c if np.isfinite(c) else None
        return {"point": k, "row": row, "x": float(self.points[k, 0]),
                "y": float(self.points[k, 1]), "values": out,
                "status_name": (Status(out["status"]).name.lower()
                                if "status" in out and out["status"] in set(Status) else None)}

    def history(self, k: int, name: str, min_zncc: float = MIN_ZNCC) -> dict[str, Any]:
        """Point ``k``'s ``name`` over the finished rows in its unit (null where not usable)
        and its predicted std ``name_std`` where the file has it."""
        self._check(name)
        k = self._check_point(k)
        std_name = f"{name}_std"
        with self._file() as f:
            done = f["completed"][()].astype(bool) if "completed" in f else \
                np.ones(self.n_rows, dtype=bool)
            vals = self.convert(name, f[name][:, k].astype(np.float64))
            ok = done & (True if name in QUALITY_FIELDS else
                         self._valid(f, slice(None), k, min_zncc))
            vals = np.where(ok, vals, np.nan)
            std = None
            if std_name in f:
                std = np.where(ok, self.convert(std_name, f[std_name][:, k].astype(np.float64)),
                               np.nan)
        return {"point": k, "name": name, "label": self.label(name),
                "x": float(self.points[k, 0]), "y": float(self.points[k, 1]),
                "times": _finite_list(self.times), "frames": self.frames.tolist(),
                "values": _finite_list(vals), "std": None if std is None else _finite_list(std),
                "std_name": std_name if std is not None else None}

    def limits(self, name: str, row: int | None = None, min_zncc: float = MIN_ZNCC
               ) -> dict[str, Any]:
        """Colour limits of ``name`` as ``stsdic plot`` takes them (robust percentiles; a
        diverging map centred on 0 for strains and the like where the values reach both
        signs): over up to :data:`LIMIT_ROWS` finished rows spread over the movie, or over
        ``row`` alone."""
        self._check(name)
        if name == "status":
            return {"name": name, "cmap": "status", "lo": 0, "hi": len(Status) - 1,
                    "label": "status", "rows": 0}
        key = (name, float(min_zncc))
        if row is None and key in self._limits:
            lo, hi, sym, rows_used = self._limits[key]
        else:
            if row is None:
                done = np.flatnonzero(self.completed())
                pick = done[np.unique(np.linspace(0, len(done) - 1, min(LIMIT_ROWS, len(done)))
                                      .round().astype(int))] if done.size else done
            else:
                pick = np.array([self._check_row(row)])
            if pick.size:
                with self._file() as f:
                    vals = self._values(f, name, pick, min_zncc)
            else:
                vals = np.zeros((0, self.n_points))
            sym = is_diverging(name) and straddles_zero(vals)
            norm = colour_norm(vals, None, 1.0 if name == "zncc" else None, sym)
            lo, hi = float(norm.vmin), float(norm.vmax)
            rows_used = int(pick.size)
            if row is None and len(pick) and self.completed().all():
                self._limits[key] = (lo, hi, sym, rows_used)
        return {"name": name, "cmap": "RdBu_r" if sym else "viridis", "lo": lo, "hi": hi,
                "label": self.label(name), "rows": rows_used}

    def row_stats(self, row: int, min_zncc: float = MIN_ZNCC) -> dict[str, Any]:
        """The status shares (percent, by name) at ``row`` and the share of usable points."""
        row = self._check_row(row)
        with self._file() as f:
            done = bool(f["completed"][row]) if "completed" in f else True
            st = f["status"][row].astype(np.int64) if "status" in f else None
            ok = self._valid(f, row, slice(None), min_zncc)
        shares = {} if st is None else {
            c.name.lower(): 100.0 * float((st == int(c)).sum()) / max(1, st.size) for c in Status}
        return {"row": row, "finished": done, "status": shares,
                "usable": 100.0 * float(ok.mean()) if done and ok.size else 0.0}

    def meta(self) -> dict[str, Any]:
        """The page's description of the file: kind, points, frames, fields and units."""
        from torch_stsdic.analysis.strain import detect_grid

        grid = detect_grid(self.points) if self.n_points > 1 else None
        cell = [float(grid.sx), float(grid.sy)] if grid is not None else [_spacing(self.points)] * 2
        fields = [{"name": nm, "label": self.label(nm), "unit": self.unit_of(nm),
                   "has_std": f"{nm}_std" in self.fields} for nm in self.fields
                  if not nm.endswith("_std")]
        fields += [{"name": nm, "label": self.label(nm), "unit": self.unit_of(nm),
                    "has_std": False} for nm in self.fields if nm.endswith("_std")]
        img = None if self.images is None else {"height": self.images.shape[0],
                                                "width": self.images.shape[1],
                                                "frames": len(self.images)}
        grid_info = None if grid is None else {"nx": int(grid.nx), "ny": int(grid.ny),
                                               "ix": grid.ix.tolist(), "iy": grid.iy.tolist()}
        return {"mode": "result", "kind": self.kind, "file": self.path.name,
                "grid": grid_info,
                "n_points": self.n_points, "n_rows": self.n_rows,
                "points": self.points.astype(np.float32).ravel().tolist(),
                "cell": cell, "frames": self.frames.tolist(), "times": _finite_list(self.times),
                "time_label": self.time_label, "fields": fields,
                "default_field": self.default_field, "image": img,
                "has_zncc": "zncc" in self.fields, "min_zncc": MIN_ZNCC,
                "length_unit": self.length_unit, "summary": self.summary()}

    def progress(self) -> dict[str, Any]:
        """Which rows are finished: '1'/'0' per row (a file still being written grows)."""
        done = self.completed()
        return {"completed": "".join("1" if d else "0" for d in done),
                "finished": int(done.sum()), "n_rows": len(done)}

    time_label = "time (frame)"
    length_unit = "px"
    default_field = "u"

    def summary(self) -> list[list[str]]:
        raise NotImplementedError


def _spacing(points: np.ndarray) -> float:
    """The median distance px from a scattered point to its nearest neighbour (10 for a
    single point): the size of the squares the page draws."""
    import torch

    from torch_stsdic.analysis.points import nearest_points

    if len(points) < 2:
        return 10.0
    dist, _ = nearest_points(torch.as_tensor(points, dtype=torch.float64), 2)
    return float(dist[:, 1].median())


class ResultSource(_Source):
    """A 2-D result file (``stsdic run``), in the units it records."""

    kind = "2d"

    def __init__(self, path: Path, images: ImageSource | None = None) -> None:
        super().__init__(path)
        with open_results(path) as f:
            self.fields = [n for n in field_names(f) if n in f]
            self.points = f["points"][()]
            self.frames = f["frames"][()]
            self.times = f["times"][()]
            self.attrs = {k: (v.item() if isinstance(v, np.generic) else v)
                          for k, v in f.attrs.items()}
            self.arrays = [nm for nm in RUN_ARRAYS if nm in f]
            self._shared = ({k: (v.item() if isinstance(v, np.generic) else v)
                             for k, v in f["shared_motion"].attrs.items()}
                            if "shared_motion" in f else None)
        self.units: Units = units_of(self.attrs)
        self.config = _json(self.attrs.get("config"), {})
        self.inputs = list(_json(self.attrs.get("inputs"), []))
        self.images = images
        self.time_label = self.units.time_label
        self.length_unit = self.units.unit
        self.default_field = "u" if "u" in self.fields else self.fields[0]

    def unit_of(self, name: str) -> str:
        return self.units.unit_of(name)

    def convert(self, name: str, values: np.ndarray) -> np.ndarray:
        return self.units.convert(name, values)

    def positions(self, row: int) -> np.ndarray:
        """(N, 2) reference positions + (u, v) at ``row`` px (the reference position where
        u or v is not known)."""
        row = self._check_row(row)
        if "u" not in self.fields or "v" not in self.fields:
            return super().positions(row)
        with self._file() as f:
            d = np.stack([f["u"][row], f["v"][row]], 1).astype(np.float64)
        d = np.where(np.isfinite(d).all(1, keepdims=True), d, 0.0)
        return (self.points + d).astype(np.float32)

    def summary(self) -> list[list[str]]:
        """(label, text) lines of the run: what it measured and how."""
        cfg, track = self.config, self.config.get("track") or {}
        done = self.completed()
        lines = [["file", str(self.path.name)],
                 ["points", f"{self.n_points}"],
                 ["frames", f"{int(done.sum())} of {self.n_rows} finished"
                  + ("" if done.all() else " (run not finished)")],
                 ["reference", str(track.get("reference", "?"))],
                 ["m", str(cfg.get("m", "?"))],
                 ["subset", f"{cfg.get('subset_size', '?')} px, {cfg.get('shape', '?')}, "
                  f"{cfg.get('criterion', '?')}"],
                 ["grid", f"step {track.get('step', '?')} px"
                  + (f", roi {track['roi']}" if track.get("roi") else "")],
                 ["calibration", "none (px)" if self.units.scale is None else
                  f"{self.units.scale:g} {self.units.unit}/px"],
                 ["time unit", self.units.time_unit]]
        if self._shared:
            lines.append(["shared motion", f"{self._shared.get('kind', '?')}, "
                          + ("carried" if self._shared.get("applied") else "not carried")])
        if self.attrs.get("strain"):
            st = _json(self.attrs.get("strain"), {})
            lines.append(["strain", f"{st.get('kind', '?')}, window {st.get('window', '?')}"])
        lines += [["inputs", ", ".join(self.inputs) or "?"],
                  ["written", f"{self.attrs.get('created', '?')}, torch_stsdic "
                   f"{self.attrs.get('software_version', '?')}"]]
        return lines


class StereoSource(_Source):
    """A stereo result file (``stsdic stereo``): U, V, W, velocities, the 3-D shape X, Y, Z
    (mm), the reprojection error (px) and status on the left reference points."""

    kind = "stereo"
    default_field = "W"
    length_unit = "mm"

    def __init__(self, path: Path, images: ImageSource | None = None) -> None:
        from torch_stsdic.stereo.export import COLUMNS, stereo_units, time_unit
        from torch_stsdic.stereo.result import open_stereo

        super().__init__(path)
        with open_stereo(path) as f:
            self.fields = [c for c in COLUMNS if c not in ("x", "y") and c in f]
            self.points = f["points"][()]
            self.frames = f["frames"][()]
            self.times = f["times"][()]
            self._units = stereo_units(f, self.fields)
            tu = time_unit(f)
            self.frame_name = str(f.attrs.get("frame", ""))
            self.info = _json(f.attrs.get("info"), {})
            self.calibration = _json(f.attrs.get("calibration"), {})
            self.software = str(f.attrs.get("software_version", "?"))
        self.time_label = f"time ({tu})"
        self.images = images

    def unit_of(self, name: str) -> str:
        u = self._units.get(name, "")
        return "-" if u == "1" else u

    def convert(self, name: str, values: np.ndarray) -> np.ndarray:
        return np.asarray(values)

    def _valid(self, f: h5py.File, rows: Any, cols: Any, min_zncc: float) -> np.ndarray:
        """Usable status and a finite position (as ``stsdic plot`` of a stereo file)."""
        ok = usable(f["status"][rows, cols])
        for c in ("X", "Y", "Z"):
            ok = ok & np.isfinite(f[c][rows, cols])
        return ok

    def shape3d(self, row: int) -> np.ndarray:
        """(N, 3) float32 X, Y, Z mm at ``row`` (NaN where not usable)."""
        row = self._check_row(row)
        with self._file() as f:
            xyz = np.stack([f[c][row] for c in ("X", "Y", "Z")], 1).astype(np.float64)
            ok = self._valid(f, row, slice(None), -1.0)
        return np.where(ok[:, None], xyz, np.nan).astype(np.float32)

    def summary(self) -> list[list[str]]:
        cal = self.calibration
        lines = [["file", self.path.name], ["points", str(self.n_points)],
                 ["frames", str(self.n_rows)],
                 ["coordinates", self.frame_name or "left camera"]]
        for key in ("baseline_mm", "stereo_angle_deg"):
            if key in cal:
                val = cal[key]
                lines.append([key.replace("_", " "),
                              f"{val:.4g}" if isinstance(val, (int, float)) else str(val)])
        for key in ("m", "subset_size", "step", "cross_ok", "reference_reprojection_px"):
            if key in self.info:
                val = self.info[key]
                lines.append([key.replace("_", " "),
                              f"{val:.4g}" if isinstance(val, float) else str(val)])
        lines.append(["written", f"torch_stsdic {self.software}"])
        return lines

    def meta(self) -> dict[str, Any]:
        out = super().meta()
        out["has_shape"] = True
        return out


def _json(text: Any, default: Any) -> Any:
    try:
        return json.loads(text) if isinstance(text, (str, bytes)) else default
    except (json.JSONDecodeError, TypeError):
        return default


def find_series(inputs: Sequence[str], near: Path) -> Any:
    """The image series of ``inputs`` (as recorded: relative to the folder the run was
    started in, tried there and beside ``near``), or None."""
    from torch_stsdic.io import load_series

    for base in (Path.cwd(), near.parent):
        paths = [p if Path(p).is_absolute() else str(base / p) for p in inputs]
        if paths and all(Path(p).exists() or any(c in p for c in "*?[") for p in paths):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    return load_series(paths[0] if len(paths) == 1 else paths)
            except Exception:  # noqa: BLE001 - no background then; the page says so
                continue
    return None


def open_source(path: Path, image: Sequence[str] | None = None,
                no_image: bool = False) -> _Source:
    """The source of a result file (2-D or stereo, by its content), with the image series
    ``image`` (default: the inputs the file records, where they still exist)."""
    from torch_stsdic.io import load_series
    from torch_stsdic.stereo.result import is_stereo_file

    series = None
    if image and not no_image:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            series = load_series(image[0] if len(image) == 1 else list(image))
    try:
        with h5py.File(path, "r", locking=False) as f:
            stereo = is_stereo_file(f)
    except OSError:  # not HDF5: the 2-D reader says what it is
        stereo = False
    if stereo:
        return StereoSource(path, ImageSource(series) if series is not None else None)
    src = ResultSource(path)
    if series is None and not no_image:
        series = find_series(src.inputs, path)
    src.images = ImageSource(series) if series is not None else None
    return src
