"""Small numeric text tables given by users: timestamps, points of interest, masks.

Readers for the files that accompany an image series (CSV or whitespace-separated text with
optional header and ``#`` comments; masks as images or ``.npy``). Every error is an
:class:`~torch_stsdic.io.images.InputError` whose message starts with ``what`` (the option or
argument name the user gave, e.g. ``--points``) and the path.
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np

from torch_stsdic.io.images import InputError, load_series

__all__ = ["MismatchError", "read_table", "read_timestamps", "read_points", "read_mask"]


class MismatchError(InputError):
    """A side file that is readable but does not fit the images: a mask of another size,
    points outside the image (a command line reports it as a usage error)."""


def read_table(path: str, what: str) -> tuple[list[str] | None, np.ndarray]:
    """A small numeric text table (CSV, or whitespace separated; '#' comments; optional
    header line). Returns (header or None, (rows, cols) float array)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} {path}: file not found")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{what} {path}: cannot read: {exc}") from exc
    fast = _fast_table(text)
    if fast is not None:
        header, arr = fast
        if not np.isfinite(arr).all():
            raise InputError(f"{what} {path}: contains non-finite values")
        return header, arr
    header: list[str] | None = None  # line by line: the error names the line
    rows: list[list[float]] = []
    ncol = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in (line.split(",") if "," in line else line.split())]
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            if header is None and not rows:
                header = [c.strip().strip('"').lower() for c in cells]
                continue
            raise InputError(f"{what} {path}, line {lineno}: not numbers: {line!r}") from None
        if ncol is None:
            ncol = len(vals)
        elif len(vals) != ncol:
            raise InputError(f"{what} {path}, line {lineno}: {len(vals)} values, expected {ncol}")
        rows.append(vals)
    if not rows:
        raise InputError(f"{what} {path}: no numbers in the file")
    arr = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{what} {path}: contains non-finite values")
    return header, arr


#: a '#' after something else on its line (only whole-line comments are comments)
_INLINE_COMMENT = re.compile(r"^[ \t]*[^#\s][^\n]*#", re.MULTILINE)


def _fast_table(text: str) -> tuple[list[str] | None, np.ndarray] | None:
    """:func:`read_table`'s result by numpy's C parser (a 38,809-row point list: 2 ms, 0.1 s
    in Python), or None where the table is not regular (then the line-by-line parser says
    where)."""
    first, skip = None, 0
    for ln in io.StringIO(text):  # the first line that is neither blank nor a comment
        skip += 1
        if ln.strip() and not ln.lstrip().startswith("#"):
            first = ln.strip()
            break
    if first is None or ("#" in text and _INLINE_COMMENT.search(text)):  # the line parser
        return None
    comma = "," in first
    cells = first.split(",") if comma else first.split()
    header = None
    try:
        [float(c) for c in cells]
        skip -= 1  # a data line: read it
    except ValueError:
        header = [c.strip().strip('"').lower() for c in cells]
    try:
        arr = np.loadtxt(io.StringIO(text), delimiter="," if comma else None, skiprows=skip,
                         ndmin=2, dtype=np.float64, comments="#")
    except ValueError:
        return None
    if arr.shape[0] == 0:
        return None
    return header, arr


def read_timestamps(path: str, what: str = "timestamps") -> np.ndarray:
    """(T,) frame times from a table: the column named time/t/times/timestamp(s), else the
    last column."""
    header, arr = read_table(path, what)
    col = arr.shape[1] - 1
    if header is not None:
        for name in ("time", "t", "times", "timestamp", "timestamps"):
            if name in header:
                col = header.index(name)
                break
        if col >= arr.shape[1]:
            raise InputError(f"{what} {path}: header and data columns do not match")
    return arr[:, col]


def read_points(path: str, shape: tuple[int, int], what: str = "points") -> np.ndarray:
    """(N, 2) POIs (x, y) px from a table (columns named x and y, else the first two), all
    inside an image of ``shape`` (H, W)."""
    header, arr = read_table(path, what)
    cx, cy = 0, 1
    if header is not None and "x" in header and "y" in header:
        cx, cy = header.index("x"), header.index("y")
    if arr.shape[1] <= max(cx, cy):
        raise InputError(f"{what} {path}: needs two columns x, y (px)")
    pts = arr[:, [cx, cy]]
    h, w = shape
    bad = (pts[:, 0] < 0) | (pts[:, 0] > w - 1) | (pts[:, 1] < 0) | (pts[:, 1] > h - 1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise MismatchError(
            f"{what} {path}: point {k} ({pts[k, 0]:g}, {pts[k, 1]:g}) is outside the "
            f"{w}x{h} (WxH) image ({int(bad.sum())} point(s) outside)"
        )
    return pts


def read_mask(path: str, shape: tuple[int, int], what: str = "mask") -> np.ndarray:
    """(H, W) bool mask from an image (non-zero = measure) or a ``.npy`` array."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} {path}: file not found")
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{what} {path}: cannot read: {exc}") from exc
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = load_series(p)
        arr = m.numpy(0)
    arr = np.squeeze(arr)
    if arr.shape != tuple(shape):
        h, w = shape
        raise MismatchError(
            f"{what} {path}: mask is {arr.shape[0] if arr.ndim else 0}x"
            f"{arr.shape[1] if arr.ndim > 1 else 0} (HxW) but the images are {h}x{w}"
        )
    mask = arr > 0 if arr.dtype != bool else arr
    if not mask.any():
        raise InputError(f"{what} {path}: no non-zero pixel, no point to measure")
    return mask
