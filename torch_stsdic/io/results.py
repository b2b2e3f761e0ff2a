"""HDF5 result files: written row by row as a run goes, read back, and extended (strains).

:class:`ResultWriter` writes an HDF5 file row by row (one row = one output frame) and flushes
after every :meth:`ResultWriter.write_rows`, so a killed run leaves a readable file holding
every finished row (``completed`` flags). ``resume=True`` continues such a file.
:func:`read_results` loads one; :func:`add_fields` adds (F, N) fields (e.g. strains) to a
finished one. This module is the only one that knows the file layout.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import shutil
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from torch_stsdic.core.status import Status
from torch_stsdic.io.file_fields import FileFields
from torch_stsdic.io.run_record import (
    OS_REASONS,
    WriteError,
    as_numpy,
    chunks,
    config_json,
    creation_properties,
    diff_config,
    is_io_error,
    now_stamp,
    software_version,
    write_error,
)
from torch_stsdic.io.stored import as_stored, as_stored_tensors, field_dtype
from torch_stsdic.io.units import Units, units_of

__all__ = ["CSV_COLUMNS", "DEFAULT_FIELDS", "RESULTS_FORMAT", "RESULTS_FORMAT_VERSION",
           "STRAIN_FIELDS", "ResultFileError", "ResultWriter", "Results", "add_fields",
           "as_stored", "as_stored_tensors", "field_names", "open_results", "read_results"]


class ResultFileError(ValueError):
    """A result file is not a torch_stsdic file, or does not match the run that resumes it.

    ``path``: the file; ``problems``: ``(what, text)`` pairs, ``what`` being "open" (not
    readable as HDF5), "format" (not a result file), "missing" (a dataset), "points",
    "frames", "times" or ``"config:<key>"`` (a setting, nested keys dotted:
    ``config:track.step``), so that a command line can name its own options."""

    def __init__(self, message: str, path: Any = None,
                 problems: Sequence[tuple[str, str]] = ()) -> None:
        super().__init__(message)
        self.path = path
        self.problems = list(problems)


# ----------------------------------------------------------------------------------------
# HDF5 results
# ----------------------------------------------------------------------------------------

RESULTS_FORMAT = "torch_stsdic-results"
#: the ``format`` attribute of a stereo result file (``stsdic stereo``,
#: :mod:`torch_stsdic.stereo.result`): named here so that the 2-D reader can point to it
STEREO_FORMAT = "torch_stsdic-stereo-results"
RESULTS_FORMAT_VERSION = 1
DEFAULT_FIELDS: tuple[str, ...] = ("u", "v", "ut", "vt", "zncc", "status")
STRAIN_FIELDS: tuple[str, ...] = ("exx", "eyy", "exy")
CSV_COLUMNS: tuple[str, ...] = ("x", "y", "u", "v", "ut", "vt", "exx", "eyy", "exy", "zncc",
                                 "status")
#: run-level arrays (not (F, N) fields) and groups (of arrays by path) a result file may hold
RUN_ARRAYS = ("shared_motion", "series_reference")
RUN_GROUPS = ("run_estimates",)
_RESERVED = {"points", "frames", "times", "completed", *RUN_ARRAYS, *RUN_GROUPS}
#: result files up to this size (bytes) are made in memory and written in one piece (larger
#: ones on disk: a long movie's file image would add its size to the run's peak memory)
SKELETON_IN_MEMORY = 32 << 20
class _FieldShape:
    """The (F, N) shape of a result file's fields: F rows (output frames) of N points."""

    frames: np.ndarray  # (F,) image frame numbers of the rows
    points: np.ndarray  # (N, 2) x, y in px

    @property
    def n_rows(self) -> int:
        """F, the number of output frames (rows of every field)."""
        return len(self.frames)

    n_frames = n_rows

    @property
    def n_points(self) -> int:
        """N, the number of points."""
        return len(self.points)


class ResultWriter(_FieldShape):
    """Write DIC results to HDF5, one row (= one output frame) at a time.

    Layout: ``points`` (N, 2) float64 (x, y), ``frames`` (F,) int64 image indices,
    ``times`` (F,) float64, one (F, N) dataset per field (float32 filled with NaN;
    ``status`` int8 filled with ``Status.NOT_COMPUTED``; ``iterations`` int16 filled with -1),
    ``completed`` (F,) bool. Root attributes: ``format``, ``version``, ``software_version``,
    ``created``, ``config`` (JSON), ``inputs`` (JSON list), ``fields`` (JSON list).

    Every :meth:`write_rows` flushes the file, so a killed process leaves a readable file
    with all rows written so far flagged in ``completed``.

    Safety: a new ``path`` is written in place (a killed run keeps its rows). An existing
    ``path`` is an error unless ``overwrite=True`` - then the new results go to
    ``<path>.partial``, atomically renamed over ``path`` by :meth:`close` (the old file stays
    intact until then; after a kill or an exception inside ``with`` the ``.partial`` remains
    and can be resumed) - or ``resume=True``: the file (or its ``.partial``, preferred) is
    reopened after checking that points, frames, times, fields and config match
    (:class:`ResultFileError` otherwise; top-level config keys in ``resume_ignore`` are not
    compared); finished rows are kept, see :meth:`pending_rows`. ``resume=True`` on a
    missing file starts a new one.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        points: Any,
        frames: Any,
        times: Any,
        config: Mapping[str, Any],
        inputs: Sequence[str],
        fields: Sequence[str] = DEFAULT_FIELDS,
        extra_fields: Sequence[str] = (),
        resume: bool = False,
        overwrite: bool = False,
        resume_ignore: Sequence[str] = (),
        attrs: Mapping[str, Any] | None = None,
    ) -> None:
        if resume and overwrite:
            raise ValueError("ResultWriter: choose either resume=True or overwrite=True")
        self.path = Path(path)
        self._partial = self.path.with_name(self.path.name + ".partial")
        self._rename_on_close = False
        self._file: h5py.File | None = None

        pts = np.asarray(as_numpy(points), dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must have shape (N, 2), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("points must be finite")
        fr = np.asarray(as_numpy(frames))
        if fr.ndim != 1 or (fr.size and fr.dtype.kind not in "iu"):
            raise ValueError(f"frames must be a 1-D integer array, got {fr.dtype} {fr.shape}")
        fr = fr.astype(np.int64)
        if len(set(fr.tolist())) != len(fr):
            raise ValueError("frames must not contain duplicates")
        tm = np.asarray(as_numpy(times), dtype=np.float64)
        if tm.shape != fr.shape:
            raise ValueError(f"times must have shape {fr.shape} like frames, got {tm.shape}")
        names = list(fields) + list(extra_fields)
        for nme in names:
            if not isinstance(nme, str) or not nme.isidentifier() or nme in _RESERVED:
                raise ValueError(f"invalid field name {nme!r}")
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate field names in {names}")
        self.points, self.frames, self.times = pts, fr, tm
        self.fields: tuple[str, ...] = tuple(fields)
        self.extra_fields: tuple[str, ...] = tuple(extra_fields)
        self.config: dict[str, Any] = json.loads(config_json(config))
        self.inputs = [str(s) for s in inputs]
        self._resume_ignore = set(resume_ignore)
        self._attrs = dict(attrs or {})

        if self.path.is_dir():
            raise IsADirectoryError(f"result path is a directory: {self.path}")
        if resume:
            self._open_resume()
        elif self.path.exists():
            if not overwrite:
                raise FileExistsError(
                    f"result file {self.path} exists: pass overwrite=True to replace it "
                    "(atomically, at close) or resume=True to continue it"
                )
            self._create(self._partial, mode="w")
            self._rename_on_close = True
        else:
            if self._partial.exists():  # left by a killed overwrite of a since-deleted file
                warnings.warn(f"removing stale {self._partial}", stacklevel=2)
                self._partial.unlink()
            self._create(self.path, mode="x")

    # -- opening --------------------------------------------------------------------------
    def _create(self, target: Path, mode: str) -> None:
        """Write the file's skeleton (attributes, every dataset allocated and filled) under a
        temporary name, then rename it to ``target``: a process killed meanwhile leaves no
        half-made file. Writing rows later changes no HDF5 metadata (see
        :func:`creation_properties`), so a SIGKILL at any moment leaves a file that opens and
        resumes. The free space is checked first: HDF5 meeting a full disk half-way gives
        paragraphs of errors (and can crash the interpreter when it exits)."""
        if mode == "x" and target.exists():
            raise FileExistsError(f"result file {target} exists")
        target.parent.mkdir(parents=True, exist_ok=True)
        self._check_space(target)
        tmp = target.with_name(target.name + ".creating")
        f = None
        try:
            if self.file_size() <= SKELETON_IN_MEMORY:  # HDF5 never meets the disk here
                image = io.BytesIO()
                with h5py.File(image, "w") as mem:
                    self._write_skeleton(mem)
                with open(tmp, "wb") as fh:
                    fh.write(image.getbuffer())
            else:
                f = h5py.File(tmp, "w")
                self._write_skeleton(f)
                f.close()
            os.replace(tmp, target)
        except BaseException as exc:
            if f is not None:
                with contextlib.suppress(Exception):  # a full disk fails the close too
                    f.close()
                f = None  # not kept alive by the error's traceback
            tmp.unlink(missing_ok=True)
            if is_io_error(exc):
                raise write_error(target, exc, "create the result file") from None
            raise
        self._file = h5py.File(target, "r+")
        self._target = target

    def _write_skeleton(self, f: h5py.File) -> None:
        """The attributes and every dataset, allocated and filled (see :meth:`_create`)."""
        f.attrs["format"] = RESULTS_FORMAT
        f.attrs["version"] = RESULTS_FORMAT_VERSION
        f.attrs["software_version"] = software_version()
        f.attrs["created"] = now_stamp()
        f.attrs["config"] = config_json(self.config)
        f.attrs["inputs"] = json.dumps(self.inputs)
        f.attrs["fields"] = json.dumps(list(self.fields + self.extra_fields))
        f.attrs["status_codes"] = Status.describe()
        for k, v in self._attrs.items():
            f.attrs[k] = v
        n_f, n_p = self.n_rows, self.n_points
        f.create_dataset("points", data=self.points)
        f.create_dataset("frames", data=self.frames)
        f.create_dataset("times", data=self.times)
        for name in self.fields + self.extra_fields:
            dt, fill = field_dtype(name)
            f.create_dataset(name, shape=(n_f, n_p), dtype=dt, fillvalue=fill,
                             chunks=chunks(n_f, n_p, np.dtype(dt).itemsize),
                             dcpl=creation_properties())
        f.create_dataset("completed", data=np.zeros(n_f, dtype=bool))

    def file_size(self) -> int:
        """Bytes the result file takes on disk, estimated from above (every dataset is
        allocated when the file is made: whole chunks, plus HDF5's headers)."""
        n_f, n_p = self.n_rows, self.n_points
        size = (32 << 10) + len(config_json(self.config)) + 8 * n_f * 3 + 16 * n_p
        for name in self.fields + self.extra_fields:
            item = np.dtype(field_dtype(name)[0]).itemsize
            ch = chunks(n_f, n_p, item) or (1, 1)
            size += (4 << 10) + (-(-n_f // ch[0]) * ch[0]) * (-(-n_p // ch[1]) * ch[1]) * item
        return size

    def _check_space(self, target: Path) -> None:
        """OSError (ENOSPC) naming ``target`` when its folder has not room for the file."""
        try:
            free = shutil.disk_usage(target.parent).free
        except OSError:  # not measurable here: HDF5 will say
            return
        need = self.file_size()
        if free < need:
            raise WriteError(errno.ENOSPC, f"cannot create the result file {target}: "
                             f"{OS_REASONS[errno.ENOSPC]}: it needs {_size(need)}, "
                             f"{_size(free)} free")

    def _check_match(self, f: h5py.File, where: Path) -> list[tuple[str, str]]:
        """What keeps ``f`` from being continued by this writer: (what, text) pairs."""
        problems: list[tuple[str, str]] = []
        if f.attrs.get("format") != RESULTS_FORMAT:
            return [("format", f"{where} is not a {RESULTS_FORMAT} file")]
        for name in ("points", "frames", "times", "completed", *self.fields, *self.extra_fields):
            if name not in f:
                problems.append(("missing", f"dataset {name!r} missing"))
        if problems:
            return problems
        pts = f["points"][()]
        if pts.shape != self.points.shape:
            problems.append(("points", f"points: {pts.shape[0]} in file, {self.n_points} now"))
        elif not np.array_equal(pts, self.points):
            problems.append(("points", "points: same count but different coordinates"))
        fr = f["frames"][()]
        if not np.array_equal(fr, self.frames):
            problems.append(("frames", f"frames differ ({len(fr)} in file, {self.n_rows} now)"))
        elif not np.allclose(f["times"][()], self.times, rtol=1e-12, atol=0, equal_nan=True):
            problems.append(("times", "times differ"))
        try:
            old = json.loads(f.attrs.get("config", "{}"))
        except (json.JSONDecodeError, TypeError):
            old = {}
        new = self.config
        ign = self._resume_ignore
        diff = diff_config(
            {k: v for k, v in old.items() if k not in ign},
            {k: v for k, v in new.items() if k not in ign},
        )
        problems.extend((f"config:{key}", f"config differs: {text}") for key, text in diff)
        return problems

    def _open_resume(self) -> None:
        candidates = [p for p in (self._partial, self.path) if p.exists()]
        if not candidates:
            self._create(self.path, mode="x")
            return
        first: tuple[Path, list[tuple[str, str]]] | None = None
        for cand in candidates:
            try:  # look read-only first: a file that does not match is never modified
                with h5py.File(cand, "r") as f:
                    probs = self._check_match(f, cand)
            except (OSError, KeyError, ValueError, TypeError) as exc:
                probs = [("open", f"cannot read {cand} as HDF5 (corrupt, truncated or not "
                                  f"HDF5): {' '.join(str(exc).split())}")]
            if not probs:
                f = h5py.File(cand, "r+")
                self._file = f
                self._target = cand
                self._rename_on_close = cand == self._partial
                old_inputs = json.loads(f.attrs.get("inputs", "[]"))
                if old_inputs != self.inputs:
                    warnings.warn(
                        f"resuming {cand}: input files differ from the recorded ones",
                        stacklevel=3,
                    )
                return
            if first is None:
                first = (cand, probs)
        assert first is not None
        cand, probs = first
        raise ResultFileError(
            "cannot resume: " + " | ".join(f"{cand}: {t}" for _, t in probs)
            + " (use overwrite=True to start again)",
            path=cand, problems=probs,
        )

    # -- writing --------------------------------------------------------------------------
    @property
    def file_path(self) -> Path:
        """File being written now (``path`` or ``<path>.partial``)."""
        return self._target

    def _h5(self) -> h5py.File:
        if self._file is None:
            raise ValueError(f"ResultWriter for {self.path} is closed")
        return self._file

    def write_rows(
        self,
        row_indices: Any,
        values: Mapping[str, Any],
        *,
        mark_completed: bool = True,
    ) -> None:
        """Write rows ``row_indices`` (k,) (positions in ``frames``, not image indices).

        ``values`` maps field names to ``(k, N)`` arrays/tensors (``(N,)`` if k == 1). All
        of ``fields`` are required when ``mark_completed``; ``extra_fields`` are optional.
        The rows are then flagged completed and the file is flushed.
        """
        f = self._h5()
        rows = np.atleast_1d(np.asarray(as_numpy(row_indices)))
        if rows.ndim != 1 or (rows.size and rows.dtype.kind not in "iu"):
            raise ValueError(f"row_indices must be integers, got {row_indices!r}")
        rows = rows.astype(np.int64)
        nf, n_p = self.n_rows, self.n_points
        if rows.size and (rows.min() < -nf or rows.max() >= nf):
            raise IndexError(f"row index out of range for {nf} rows: {rows.tolist()}")
        rows = rows % max(nf, 1)
        if len(set(rows.tolist())) != len(rows):
            raise ValueError("row_indices contain duplicates")
        known = set(self.fields + self.extra_fields)
        unknown = set(values) - known
        if unknown:
            raise KeyError(f"unknown field(s) {sorted(unknown)}; file has {sorted(known)}")
        if mark_completed:
            missing = [n for n in self.fields if n not in values]
            if missing:
                raise ValueError(f"write_rows: missing field(s) {missing}")
        k = len(rows)
        data: dict[str, np.ndarray] = {}
        for name, val in values.items():
            a = as_numpy(val)
            if a.ndim == 1 and k == 1:
                a = a[None]
            if a.shape != (k, n_p):
                raise ValueError(f"field {name!r}: expected shape ({k}, {n_p}), got {a.shape}")
            data[name] = a.astype(field_dtype(name)[0], copy=False)
        if k == 0:
            return
        order = np.argsort(rows)
        srows = rows[order]
        contiguous = bool(np.all(np.diff(srows) == 1))
        try:
            for name, a in data.items():
                a = a[order]
                ds = f[name]
                if contiguous:
                    ds[int(srows[0]) : int(srows[-1]) + 1] = a
                else:
                    for j, r in enumerate(srows):
                        ds[int(r)] = a[j]
            f.flush()
            if mark_completed:  # only once the rows' data are in the file
                f["completed"][srows] = True
                f.flush()
        except (OSError, ValueError, RuntimeError) as exc:
            if is_io_error(exc):  # HDF5's I/O failures
                raise self._write_error(exc) from None
            raise

    def _write_error(self, exc: BaseException) -> OSError:
        """``exc`` (from HDF5: a full disk, a lost device ...) as an OSError naming the file."""
        return write_error(self._target, exc, "write the result file")

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        """HDF5's I/O failures inside the block as one OSError naming the file."""
        try:
            yield
        except (OSError, ValueError, RuntimeError) as exc:
            if is_io_error(exc):
                raise self._write_error(exc) from None
            raise

    def read_rows(self, first: int, last: int,
                  fields: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Rows ``first..last`` (inclusive) of ``fields`` (default the required fields) as
        stored, e.g. to replay finished rows when resuming."""
        f = self._h5()
        return {nm: f[nm][first : last + 1] for nm in (fields or self.fields)}

    def add_fields(self, values: Mapping[str, Any], attrs: Mapping[str, Any] | None = None
                   ) -> None:
        """Add or replace (F, N) float fields (e.g. strains) and root attributes."""
        with self._writing():
            _add_fields(self._h5(), values, attrs)
            self._h5().flush()

    def write_array(self, name: str, values: Any, attrs: Mapping[str, Any] | None = None
                    ) -> None:
        """Write (or replace) the run-level array ``name`` (``RUN_ARRAYS``, e.g. the shared
        motion, (T_series, 6), float64) or group (``RUN_GROUPS``: ``values`` maps paths in it,
        ``"a/b"``, to arrays kept in their dtypes) and then its attributes (JSON strings for
        nested values: a group that has them is whole), flushed."""
        if name not in RUN_ARRAYS + RUN_GROUPS:
            raise ValueError(f"{name!r} is not a run-level array or group")
        f = self._h5()
        with self._writing():
            f.pop(name, None)  # replaced
            if name in RUN_GROUPS:
                obj = f.create_group(name)
                for path, a in values.items():
                    obj.create_dataset(path, data=np.asarray(a))
            else:
                obj = f.create_dataset(name, data=np.asarray(values, dtype=np.float64),
                                       **({"compression": "gzip", "compression_opts": 1}
                                          if np.ndim(values) == 2 and np.size(values) > 4096
                                          else {}))
            f.flush()
            for k, v in (attrs or {}).items():
                obj.attrs[k] = v if isinstance(v, (str, int, float, bool)) else json.dumps(v)
            f.flush()

    def read_run(self, name: str) -> tuple[Any, dict[str, Any]] | None:
        """A run-level array or group and its attributes (None: not in the file)."""
        f = self._h5()
        return _run_item(f, name) if name in RUN_ARRAYS + RUN_GROUPS and name in f else None

    def attrs(self) -> dict[str, Any]:
        """The file's root attributes (a copy)."""
        return {k: _py(v) for k, v in self._h5().attrs.items()}

    def completed_rows(self) -> np.ndarray:
        """Row indices (sorted int64) already completed."""
        return np.flatnonzero(self._h5()["completed"][()]).astype(np.int64)

    def pending_rows(self) -> np.ndarray:
        """Row indices (sorted int64) still to compute."""
        return np.flatnonzero(~self._h5()["completed"][()]).astype(np.int64)

    @property
    def is_complete(self) -> bool:
        """True when every row is completed."""
        return bool(self._h5()["completed"][()].all())

    def close(self, commit: bool = True) -> None:
        """Close the file; for an overwrite, rename ``<path>.partial`` over ``path`` if
        ``commit`` (otherwise the ``.partial`` is left for ``resume``). Idempotent."""
        if self._file is None:
            return
        f, self._file = self._file, None
        try:
            try:
                f.flush()
            finally:
                f.close()
        except OSError as exc:
            if commit:
                raise self._write_error(exc) from exc
            # after an error: the rows flushed before it stay in the file; the first error
            # is the one to report, not a second one from the same full disk
        if self._rename_on_close and commit:
            os.replace(self._target, self.path)
            self._target = self.path
            self._rename_on_close = False

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close(commit=exc_type is None)

    def __repr__(self) -> str:
        state = "closed" if self._file is None else f"open on {self._target}"
        return f"<ResultWriter {self.path} ({self.n_rows} rows x {self.n_points} points, {state})>"


@dataclass
class Results(_FieldShape):
    """Contents of a result file. Fields are attributes: ``res.u`` is ``(F, N)``."""

    path: Path
    points: np.ndarray  # (N, 2) float64, columns x, y
    frames: np.ndarray  # (F,) int64 image indices
    times: np.ndarray  # (F,) float64
    completed: np.ndarray  # (F,) bool
    fields: Mapping[str, np.ndarray]  # name -> (F, N) (a dict, or FileFields: read lazily)
    config: dict[str, Any]
    inputs: list[str]
    attrs: dict[str, Any] = field(default_factory=dict)
    #: run-level arrays (``RUN_ARRAYS``) present in the file: name -> (values, attributes)
    arrays: dict[str, tuple[np.ndarray, dict[str, Any]]] = field(default_factory=dict)

    def __getattr__(self, name: str) -> np.ndarray:
        fields = self.__dict__.get("fields")
        if fields is not None and name in fields:
            return fields[name]
        raise AttributeError(
            f"{type(self).__name__} has no attribute or field {name!r}"
            + (f" (fields: {sorted(fields)})" if fields is not None else "")
        )

    @property
    def units(self) -> Units:
        """The calibration recorded in the file (pixels and frames when none)."""
        return units_of(self.attrs)

    @property
    def x(self) -> np.ndarray:
        """(N,) point x (column) coordinates."""
        return self.points[:, 0]

    @property
    def y(self) -> np.ndarray:
        """(N,) point y (row) coordinates."""
        return self.points[:, 1]

    def row_of(self, frame: int) -> int:
        """Row index holding image frame ``frame``."""
        hits = np.flatnonzero(self.frames == int(frame))
        if not hits.size:
            raise KeyError(f"frame {frame} is not in {self.path}")
        return int(hits[0])


def _size(n: int) -> str:
    """Bytes for people: '140 kB', '2.1 GB'."""
    for unit, k in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n} bytes"


def open_results(path: Path) -> h5py.File:
    """Open a result file read-only; clear errors for a missing, unreadable or foreign file."""
    if not path.exists():
        partial = path.with_name(path.name + ".partial")
        hint = f" ({partial} exists: an unfinished overwrite run)" if partial.exists() else ""
        raise FileNotFoundError(f"result file not found: {path}{hint}")
    try:
        f = h5py.File(path, "r", locking=False)
    except OSError as exc:
        raise ResultFileError(f"{path} is not a readable HDF5 result file: {exc}") from exc
    if f.attrs.get("format") != RESULTS_FORMAT:
        stereo = f.attrs.get("format") == STEREO_FORMAT or ("W" in f and "X0" in f)
        f.close()
        if stereo:
            raise ResultFileError(
                f"{path} is a stereo result ('stsdic stereo'), not a 2-D one: read it with "
                "torch_stsdic.stereo.StereoResult.from_hdf5, export it with "
                "torch_stsdic.stereo.export.export_stereo (or 'stsdic export')")
        raise ResultFileError(f"{path} is not a {RESULTS_FORMAT} file")
    return f


def _py(v: Any) -> Any:
    return v.item() if isinstance(v, np.generic) else v


def _run_item(f: h5py.File, name: str) -> tuple[Any, dict[str, Any]]:
    """A run-level array's values, or a run-level group's arrays by path, and attributes."""
    obj, arrays = f[name], {}
    if isinstance(obj, h5py.Dataset):
        return obj[()], {k: _py(v) for k, v in obj.attrs.items()}
    obj.visititems(lambda p, o: arrays.update({p: o[()]} if isinstance(o, h5py.Dataset) else {}))
    return arrays, {k: _py(v) for k, v in obj.attrs.items()}


def field_names(f: h5py.File) -> list[str]:
    """The (F, N) field names of an open result file, in their stored order."""
    try:
        return list(json.loads(f.attrs["fields"]))
    except (KeyError, json.JSONDecodeError):
        return [k for k in f if k not in _RESERVED and f[k].ndim == 2]


def read_results(path: str | os.PathLike[str], fields: Sequence[str] | None = None, *,
                 lazy: bool = False) -> Results:
    """Load a result file (all fields, or only ``fields``). Works on a file still being
    written or left by a killed run: rows with ``completed`` False hold NaN / NOT_COMPUTED.
    ``lazy``: each field is read when first used (:class:`FileFields`)."""
    p = Path(path)
    with open_results(p) as f:
        names = field_names(f)
        if fields is not None:
            bad = [n for n in fields if n not in names]
            if bad:
                raise KeyError(f"field(s) {bad} not in {p} (has {names})")
            names = list(fields)
        attrs = {k: _py(f.attrs[k]) for k in f.attrs}
        arrays = {nm: _run_item(f, nm) for nm in RUN_ARRAYS if nm in f}
        return Results(
            path=p, points=f["points"][()], frames=f["frames"][()], times=f["times"][()],
            completed=f["completed"][()].astype(bool),
            fields=FileFields(p, names) if lazy else {n: f[n][()] for n in names},
            config=json.loads(attrs.pop("config", "{}")),
            inputs=list(json.loads(attrs.pop("inputs", "[]"))),
            attrs=attrs, arrays=arrays,
        )


def add_fields(path: str | os.PathLike[str], values: Mapping[str, Any],
               attrs: Mapping[str, Any] | None = None) -> None:
    """Add or replace (F, N) float fields (e.g. strains) in a result file, and set root
    attributes ``attrs``. Raises ValueError naming a field of the wrong shape."""
    with h5py.File(path, "r+") as f:
        _add_fields(f, values, attrs)


def _add_fields(f: h5py.File, values: Mapping[str, Any],
                attrs: Mapping[str, Any] | None) -> None:
    names = json.loads(f.attrs.get("fields", "[]"))
    n_f, n_p = len(f["frames"]), len(f["points"])
    for name, val in values.items():
        a = np.asarray(as_numpy(val), dtype=np.float32)
        if a.shape != (n_f, n_p):
            raise ValueError(f"field {name}: shape {a.shape}, expected ({n_f}, {n_p})")
        if name in f:
            f[name][...] = a
        else:
            f.create_dataset(name, data=a, chunks=chunks(n_f, n_p, 4), fillvalue=np.nan)
        if name not in names:
            names.append(name)
    f.attrs["fields"] = json.dumps(names)
    for k, v in (attrs or {}).items():
        f.attrs[k] = v
