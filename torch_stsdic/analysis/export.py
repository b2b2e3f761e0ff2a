"""Exports of result files for other tools: CSV (one file per frame), VTK for ParaView (one
``.vtu`` per frame and a ``.pvd`` time series), MATLAB ``.mat``.

Every export converts the stored pixel values into the calibration the file records
(:mod:`torch_stsdic.io.units`: lengths times ``scale``, velocities in unit per time unit,
strains unchanged) and carries every (F, N) field of the file, whatever its name (new fields,
such as predicted uncertainties ``u_std``, come through with their unit).

Every file is written whole or not at all (``io.run_record.written_atomically``: a
temporary file beside it, renamed when complete): a full disk leaves no truncated file and
raises a ``WriteError`` naming the file, whose ``written`` lists the files that this export
finished before it.
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import h5py
import numpy as np

from torch_stsdic.core.status import Status
from torch_stsdic.io.results import CSV_COLUMNS, field_names, open_results
from torch_stsdic.io.run_record import WriteError, written_atomically
from torch_stsdic.io.units import Units, units_of

__all__ = ["FORMATS", "export_csv", "export_mat", "export_results", "export_vtk"]

#: the export formats of :func:`export_results` (and ``stsdic export --format``)
FORMATS = ("csv", "vtk", "mat")

Frames = int | Sequence[int] | None


# ----------------------------------------------------------------------------------------
# shared: rows, columns, values in physical units
# ----------------------------------------------------------------------------------------


def frame_rows(f: h5py.File, frames: Frames, path: Path) -> list[int]:
    """Result rows of image frames ``frames`` (default: every completed row)."""
    all_frames = f["frames"][()]
    if frames is None:
        return np.flatnonzero(f["completed"][()]).tolist()
    wanted = [frames] if isinstance(frames, (int, np.integer)) else list(frames)
    rows = []
    for fr in wanted:
        hit = np.flatnonzero(all_frames == int(fr))
        if not hit.size:
            raise KeyError(f"frame {fr} is not in {path} (frames {all_frames.tolist()})")
        rows.append(int(hit[0]))
    return rows


def _columns(f: h5py.File, *, fixed: bool = False) -> list[str]:
    """Field names in export order: x, y, u, v, ut, vt, strains, zncc, status (``fixed``:
    always, else those stored), then every other stored field (x and y are the point
    coordinates, not fields)."""
    names = field_names(f)
    head = [c for c in CSV_COLUMNS if fixed or c in ("x", "y") or c in names]
    return head + [n for n in names if n not in CSV_COLUMNS]


def _row_values(f: h5py.File, r: int, names: Sequence[str], units: Units,
                points: np.ndarray) -> dict[str, np.ndarray]:
    """(N,) values of row ``r`` of every field in ``names`` (``points`` (N, 2) give x, y), in
    physical units; a field the file lacks is all NaN."""
    out = {}
    for nm in names:
        if nm in ("x", "y"):
            out[nm] = units.convert(nm, points[:, 0 if nm == "x" else 1])
        elif nm in f:
            out[nm] = units.convert(nm, f[nm][r])
        else:
            out[nm] = np.full(len(points), np.nan)
    return out


def _describe(f: h5py.File, src: Path, units: Units, columns: Sequence[str]) -> dict[str, Any]:
    """The metadata of an export: source, calibration, columns with units, status codes."""
    return {
        "source": str(src),
        "software_version": str(f.attrs.get("software_version", "unknown")),
        "unit": units.unit,
        "scale": units.scale,
        "scale_note": "length units per px; null: values in px",
        "time_unit": units.time_unit,
        "columns": list(columns),
        "units": {c: units.unit_of(c) for c in columns},
        "status_codes": {s.name.lower(): int(s) for s in Status},
        "usable_status": [int(Status.CONVERGED), int(Status.MAX_ITER)],
    }


# ----------------------------------------------------------------------------------------
# CSV
# ----------------------------------------------------------------------------------------


def format_column(a: np.ndarray, spec: str | None = None) -> np.ndarray:
    """(N,) values as CSV cells: integers (and booleans) with ``%d``, the rest with ``%.9g``
    (or ``spec``); NaN and infinities as empty cells."""
    if spec is None:
        spec = "%d" if a.dtype.kind in "iub" else "%.9g"
    s = np.char.mod(spec, a)
    if a.dtype.kind == "f":
        s[~np.isfinite(a)] = ""
    return s


def export_csv(
    path_h5: str | os.PathLike[str],
    out_dir_or_pattern: str | os.PathLike[str],
    frames: Frames = None,
    *,
    comment: bool = False,
    sidecar: bool = True,
) -> list[Path]:
    """Write one CSV per frame, in the file's physical units; return the paths written.

    ``out_dir_or_pattern``: a directory (files ``<h5 stem>_frame<frame:05d>.csv``) or a pattern
    with ``{frame}`` (also ``{row}``, ``{time}``), e.g. ``"csv/f{frame:04d}.csv"``.
    ``frames``: image frame indices to export (default: all completed rows).
    The first line is the header: ``x, y, u, v, ut, vt, exx, eyy, exy, zncc, status`` (those
    the file has) then every other stored field, so ``np.genfromtxt(f, delimiter=",",
    names=True)`` and spreadsheets read it; NaN are empty cells. The units, calibration and
    the frame/time of every file go to a sidecar ``<h5 stem>_csv.json`` next to the files
    (``sidecar``); ``comment`` (opt-in) puts a ``# torch_stsdic ... frame=<f> time=<t>
    unit=...`` line before the header.
    """
    p = Path(path_h5)
    out = os.fspath(out_dir_or_pattern)
    written: list[Path] = []
    with open_results(p) as f:
        all_frames, times = f["frames"][()], f["times"][()]
        completed = f["completed"][()]
        rows = frame_rows(f, frames, p)
        units = units_of(f.attrs)
        columns = _columns(f, fixed=True)
        pts = f["points"][()]
        is_pattern = "{" in out
        if not is_pattern:
            Path(out).mkdir(parents=True, exist_ok=True)
        listing = []
        seen: set[Path] = set()
        for r in rows:
            fr, t = int(all_frames[r]), float(times[r])
            target = csv_target(out, is_pattern, p.stem, fr, r, t, seen)
            head = (f"# torch_stsdic results {p.name}: frame={fr} time={t!r} row={r} "
                    f"completed={bool(completed[r])} unit={units.unit} "
                    f"time_unit={units.time_unit}\n") if comment else ""
            write_csv(target, head, _row_values(f, r, columns, units, pts), written)
            listing.append({"file": target.name, "frame": fr, "time": t, "row": r,
                            "completed": bool(completed[r])})  # fmt: skip
        if sidecar and written:
            write_sidecar({**_describe(f, p, units, columns), "files": listing}, p.stem,
                          written)
    return written


def csv_target(out: str, is_pattern: bool, stem: str, frame: int, row: int, time: float,
               seen: set[Path]) -> Path:
    """The CSV file of one frame: ``out`` formatted with ``frame``, ``row``, ``time`` (a
    pattern) or ``<out>/<stem>_frame<NNNNN>.csv``; its folder made. ``seen``: the files so far
    (a pattern that gives one file twice is refused)."""
    target = (Path(out.format(frame=frame, row=row, time=time)) if is_pattern
              else Path(out) / f"{stem}_frame{frame:05d}.csv")
    if target in seen:
        raise ValueError(f"output pattern {out!r} gives the same file {target} twice")
    seen.add(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    return target


def write_csv(target: Path, head: str, values: dict[str, np.ndarray], written: list[Path]
              ) -> None:
    """One frame's CSV (written atomically): ``head`` (a comment line or ""), the header of
    ``values``' names, then one line per point (:func:`format_column`); ``target`` is added
    to ``written``."""
    cols = [format_column(a) for a in values.values()]
    with keeping_written(written), written_atomically(target) as tmp, \
            open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(head + ",".join(values) + "\n")
        for line in zip(*cols):
            fh.write(",".join(line) + "\n")
    written.append(target)


def write_sidecar(meta: dict[str, Any], stem: str, written: list[Path]) -> Path:
    """The CSV export's JSON sidecar ``<stem>_csv.json`` beside the first file written,
    atomically; the files written so far are removed if it fails (:func:`keeping_written`)."""
    side = written[0].parent / f"{stem}_csv.json"
    with keeping_written(written), written_atomically(side) as tmp:
        tmp.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return side


def write_pvd(pvd: Path, steps: list[tuple[float, str]], written: list[Path]) -> Path:
    """ParaView's time series ``pvd`` of the (time, .vtu file name) ``steps``; returns it."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "<Collection>"]  # fmt: skip
    lines += [f'<DataSet timestep="{t!r}" group="" part="0" file={quoteattr(n)}/>'
              for t, n in steps]  # fmt: skip
    lines += ["</Collection>", "</VTKFile>", ""]
    with keeping_written(written), written_atomically(pvd) as tmp:
        tmp.write_text("\n".join(lines), encoding="utf-8")
    return pvd


@contextlib.contextmanager
def keeping_written(written: list[Path]) -> Iterator[None]:
    """A :class:`WriteError` inside the block lists the files finished before it."""
    try:
        yield
    except WriteError as exc:
        exc.written = list(written)  # type: ignore[attr-defined]
        raise


# ----------------------------------------------------------------------------------------
# VTK (XML UnstructuredGrid + ParaView collection)
# ----------------------------------------------------------------------------------------

_VTK_TYPES = {
    "f4": "Float32", "f8": "Float64", "i1": "Int8", "i2": "Int16", "i4": "Int32",
    "i8": "Int64", "u1": "UInt8", "b1": "UInt8",
}  # fmt: skip
_VTK_VERTEX, _VTK_QUAD = 1, 9


def grid_cells(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(connectivity, offsets, types) of the cells over ``points`` (N, 2): on a regular grid
    one quad per grid cell whose four corners are points (a surface in ParaView), and a
    vertex for every point in no quad; scattered points are vertices."""
    from torch_stsdic.analysis.strain import detect_grid

    n = len(points)
    grid = detect_grid(points) if n else None
    quads = np.zeros((0, 4), dtype=np.int64)
    if grid is not None and grid.nx > 1 and grid.ny > 1:
        index = np.full((grid.ny, grid.nx), -1, dtype=np.int64)
        index[grid.iy, grid.ix] = np.arange(n)
        corners = np.stack([index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]], -1)
        corners = corners.reshape(-1, 4)
        quads = corners[(corners >= 0).all(axis=1)]
    lone = np.setdiff1d(np.arange(n), quads.ravel())
    conn = np.concatenate([quads.ravel(), lone]).astype(np.int64)
    sizes = np.concatenate([np.full(len(quads), 4), np.ones(len(lone), dtype=np.int64)])
    types = np.concatenate([np.full(len(quads), _VTK_QUAD), np.full(len(lone), _VTK_VERTEX)])
    return conn, np.cumsum(sizes).astype(np.int64), types.astype(np.uint8)


def _data_array(name: str, a: np.ndarray, components: int = 1) -> str:
    """One inline base64 ``DataArray`` (UInt64 byte-count header, little endian)."""
    a = np.ascontiguousarray(a)
    if a.dtype.kind == "b":
        a = a.astype(np.uint8)
    a = a.astype(a.dtype.newbyteorder("<"), copy=False)
    vtk_type = _VTK_TYPES[f"{a.dtype.kind}{a.dtype.itemsize}"]
    raw = a.tobytes()
    blob = base64.b64encode(np.uint64(len(raw)).tobytes() + raw).decode("ascii")
    comp = f' NumberOfComponents="{components}"' if components > 1 else ""
    return (f'<DataArray type="{vtk_type}" Name={quoteattr(name)}{comp} format="binary">'
            f"{blob}</DataArray>")


def write_vtu(path: Path, points: np.ndarray, point_data: dict[str, np.ndarray],
              cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
    """A VTK XML UnstructuredGrid: ``points`` (N, 2) or (N, 3), point data name -> (N,) or
    (N, 3) arrays, ``cells`` from :func:`grid_cells` (default: computed)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    conn, offsets, types = cells if cells is not None else grid_cells(pts[:, :2])
    arrays = [_data_array(nm, a, 1 if a.ndim == 1 else a.shape[1])
              for nm, a in point_data.items()]  # fmt: skip
    text = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
        'header_type="UInt64">',
        "<UnstructuredGrid>",
        f'<Piece NumberOfPoints="{len(pts)}" NumberOfCells="{len(types)}">',
        "<Points>", _data_array("Points", pts, 3), "</Points>",
        "<Cells>", _data_array("connectivity", conn), _data_array("offsets", offsets),
        _data_array("types", types), "</Cells>",
        "<PointData>", *arrays, "</PointData>",
        "</Piece>", "</UnstructuredGrid>", "</VTKFile>", "",
    ])  # fmt: skip
    with written_atomically(path) as tmp:
        tmp.write_text(text, encoding="ascii")


def export_vtk(path_h5: str | os.PathLike[str], out_dir: str | os.PathLike[str],
               frames: Frames = None) -> list[Path]:
    """ParaView files, in the file's physical units: ``<stem>_frame<NNNNN>.vtu`` per frame
    and the time series ``<stem>.pvd`` (last in the returned list).

    Points (x, y, 0) are the reference positions (y is the image row, pointing down); on a
    grid they are joined into quads. Point data: every field of the file (u, v, ut, vt,
    strains, zncc, status, predicted std ...), and the vectors ``displacement`` (u, v, 0)
    and ``velocity`` (ut, vt, 0) for ParaView's Warp By Vector and glyphs."""
    p, out = Path(path_h5), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    steps = []
    with open_results(p) as f:
        units = units_of(f.attrs)
        names = [c for c in _columns(f) if c not in ("x", "y")]
        xy = units.convert("x", f["points"][()])  # x and y are both lengths
        pts = f["points"][()]
        cells = grid_cells(pts)
        for r in frame_rows(f, frames, p):
            vals = _row_values(f, r, names, units, pts)
            for vec, (a, b) in (("displacement", ("u", "v")), ("velocity", ("ut", "vt"))):
                if a in vals and b in vals:
                    vals[vec] = np.column_stack([vals[a], vals[b], np.zeros_like(vals[a])])
            fr = int(f["frames"][r])
            target = out / f"{p.stem}_frame{fr:05d}.vtu"
            with keeping_written(written):
                write_vtu(target, xy, vals, cells)
            written.append(target)
            steps.append((float(f["times"][r]), target.name))
    return [*written, write_pvd(out / f"{p.stem}.pvd", steps, written)]


# ----------------------------------------------------------------------------------------
# MATLAB
# ----------------------------------------------------------------------------------------


def export_mat(path_h5: str | os.PathLike[str], out_dir: str | os.PathLike[str],
               frames: Frames = None) -> list[Path]:
    """One MATLAB file ``<stem>.mat`` (:func:`scipy.io.savemat`), in physical units: every
    field as a (frames, points) array (``u``, ``v``, ``ut``, ...; NaN for failed points),
    ``x``, ``y`` (1, N) reference coordinates, ``frames``, ``times``, ``completed`` (1, F),
    ``unit``, ``scale`` (1 with unit "px"), ``time_unit``, ``units`` (a struct: field ->
    unit) and ``status_codes`` (a struct). The fields are read and written a block of points
    at a time (:func:`write_mat`): a long file's export holds none of them whole."""
    p, out = Path(path_h5), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open_results(p) as f:
        units = units_of(f.attrs)
        rows = sorted(set(frame_rows(f, frames, p)))
        names = [c for c in _columns(f) if c not in ("x", "y")]
        pts = f["points"][()]
        fields = {nm: MatField((len(rows), len(pts)), stored_columns(
            f[nm], rows, lambda a, nm=nm: units.convert(nm, a))) for nm in names}
        data: dict[str, Any] = dict(
            x=units.convert("x", pts[:, 0]), y=units.convert("y", pts[:, 1]),
            frames=f["frames"][()][rows].astype(np.float64), times=f["times"][()][rows],
            completed=f["completed"][()][rows], unit=units.unit,
            scale=units.length_factor, time_unit=units.time_unit, source=str(p),
            units={nm: units.unit_of(nm) for nm in ["x", "y", *names]},
            status_codes={s.name.lower(): int(s) for s in Status},
        )  # fmt: skip
        return [write_mat(out / f"{p.stem}.mat", data, fields)]


# ----------------------------------------------------------------------------------------
# MATLAB files, their (frames, points) fields a block of points at a time
# ----------------------------------------------------------------------------------------
#: bytes of a (frames, points) field read and written at a time into a MATLAB file (its
#: points' values over every frame: MATLAB stores an array column by column)
MAT_BLOCK_BYTES = 32 << 20


class MatField:
    """A (F, N) array of a MATLAB file read a block of columns at a time: ``read(cols)`` the
    (F, n) values of the columns ``cols`` (a slice)."""

    def __init__(self, shape: tuple[int, int], read: Any) -> None:
        self.shape, self.read = (int(shape[0]), int(shape[1])), read


def stored_columns(ds: h5py.Dataset, rows: list[int], convert: Any) -> Any:
    """The reader of a :class:`MatField`: the rows ``rows`` (sorted) of the (F, N) dataset
    ``ds``, a block of its columns at a time, through ``convert``."""
    def read(cols: slice) -> np.ndarray:
        if not rows:
            return convert(np.zeros((0, cols.stop - cols.start)))
        whole = len(rows) == ds.shape[0]
        return convert(ds[:, cols] if whole else ds[rows, cols])
    return read


#: MATLAB's class and element type codes of the arrays a field may hold (MAT-file format,
#: level 5): numpy dtype -> (mxCLASS, miTYPE)
_MAT_TYPES = {np.dtype(np.float64): (6, 9), np.dtype(np.float32): (7, 7),
              np.dtype(np.int8): (8, 1), np.dtype(np.uint8): (9, 2),
              np.dtype(np.int16): (10, 3), np.dtype(np.uint16): (11, 4),
              np.dtype(np.int32): (12, 5), np.dtype(np.uint32): (13, 6),
              np.dtype(np.int64): (14, 12), np.dtype(np.uint64): (15, 13)}


def _mat_element(kind: int, payload: bytes) -> bytes:
    """A level-5 data element: its tag and ``payload`` padded to 8 bytes (the small format,
    4 bytes in the tag, for 1 to 4 bytes, as MATLAB and scipy write a short name)."""
    if 0 < len(payload) <= 4:
        return np.array([len(payload) << 16 | kind], "<u4").tobytes() + payload.ljust(4, b"\0")
    pad = -len(payload) % 8
    return np.array([kind, len(payload)], "<u4").tobytes() + payload + b"\0" * pad


def _append_mat_array(fh: Any, name: str, field: MatField) -> None:
    """Append (F, N) ``field`` as the compressed MATLAB array ``name`` to the level-5 file
    ``fh`` (open for writing at its end): its columns read and compressed a block at a time,
    the element's compressed length written in its tag last."""
    import zlib

    f, n = field.shape
    step = max(1, MAT_BLOCK_BYTES // (8 * max(f, 1)))
    blocks = (field.read(slice(c, min(c + step, n))) for c in range(0, n, step))
    first = next(blocks)
    dtype = np.dtype(first.dtype).newbyteorder("=")
    if dtype not in _MAT_TYPES:
        raise TypeError(f"{name}: a {dtype} array is not written block by block")
    cls, mi = _MAT_TYPES[dtype]
    nbytes = f * n * dtype.itemsize
    head = (_mat_element(6, np.array([cls, 0], "<u4").tobytes())  # array flags
            + _mat_element(5, np.array([f, n], "<i4").tobytes())  # dimensions
            + _mat_element(1, name.encode("ascii")))  # array name
    body = np.array([mi, nbytes], "<u4").tobytes()  # the real part's tag; its data follows
    matrix = head + body
    size = len(matrix) + nbytes + (-nbytes % 8)
    z = zlib.compressobj()
    start = fh.tell()
    fh.write(np.array([15, 0], "<u4").tobytes())  # miCOMPRESSED, length written below
    out = z.compress(np.array([14, size], "<u4").tobytes() + matrix)  # miMATRIX
    written = 0
    for block in itertools.chain([first], blocks):  # column-major: each point's frames
        if np.dtype(block.dtype).newbyteorder("=") != dtype:
            raise TypeError(f"{name}: its blocks differ in type ({block.dtype}, {dtype})")
        raw = np.ascontiguousarray(block.T, dtype=dtype.newbyteorder("<")).tobytes()
        written += len(raw)
        out += z.compress(raw)
        fh.write(out)
        out = b""
    if written != nbytes:
        raise ValueError(f"{name}: {written} bytes read, {nbytes} expected")
    fh.write(out + z.compress(b"\0" * (-nbytes % 8)) + z.flush())
    end = fh.tell()
    fh.seek(start + 4)
    fh.write(np.array([end - start - 8], "<u4").tobytes())
    fh.seek(end)


def write_mat(target: Path, data: dict[str, Any], fields: dict[str, MatField] | None = None
              ) -> Path:
    """``data`` as one MATLAB file (:func:`scipy.io.savemat`, compressed, 1-D arrays as rows),
    written atomically; ``fields``: (F, N) arrays appended to it a block of columns at a
    time (:class:`MatField`; what ``scipy.io.loadmat`` reads back is what ``savemat`` of the
    whole arrays gives), so that a long result is never held whole."""
    try:
        from scipy.io import savemat
    except ImportError as exc:  # pragma: no cover - scipy comes with the test extra
        raise ImportError("MATLAB export needs scipy: pip install scipy") from exc
    data = dict(data)
    streamed = {}
    for name, fld in (fields or {}).items():
        if fld.shape[0] * fld.shape[1] == 0:  # nothing to stream: as savemat writes it
            data[name] = fld.read(slice(0, fld.shape[1]))
        else:
            streamed[name] = fld
    with written_atomically(target) as tmp:
        savemat(tmp, data, do_compression=True, oned_as="row")
        if streamed:
            with open(tmp, "r+b") as fh:
                fh.seek(0, os.SEEK_END)
                for name, fld in streamed.items():
                    _append_mat_array(fh, name, fld)
    return target


def export_as(fmt: str, writers: dict[str, Any], path_h5: str | os.PathLike[str],
              out: str | os.PathLike[str], frames: Frames, kwargs: dict[str, Any]
              ) -> list[Path]:
    """Call the writer of format ``fmt`` (``writers``: "csv", "vtk", "mat" -> a function of
    (path_h5, out, frames, **kwargs)); only CSV takes options."""
    if fmt not in writers:
        raise ValueError(f"format: {fmt!r} is not one of {', '.join(FORMATS)}")
    if fmt != "csv" and kwargs:
        raise TypeError(f"{fmt} export takes no options {sorted(kwargs)}")
    return writers[fmt](path_h5, out, frames, **kwargs)


def export_results(path_h5: str | os.PathLike[str], out: str | os.PathLike[str],
                   fmt: str = "csv", frames: Frames = None, **kwargs: Any) -> list[Path]:
    """Export a result file in format ``fmt`` (one of :data:`FORMATS`) into ``out``; the
    paths written. ``kwargs`` go to :func:`export_csv`."""
    return export_as(fmt, {"csv": export_csv, "vtk": export_vtk, "mat": export_mat},
                     path_h5, out, frames, kwargs)
