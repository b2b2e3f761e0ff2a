"""Image-series input (lazy, memory bounded) and HDF5 result files (written frame by frame).

Inputs
    :func:`load_series` turns a multi-page TIFF, a directory, a glob pattern, a list of image
    files or a ``(T, H, W)`` array/tensor into an :class:`ImageSeries`. Only image *headers*
    are read up front (sizes, dtypes, page counts); pixels are decoded one frame at a time
    when asked for, so memory is bounded by what is requested, not by the movie length.
    Frames come back as ``(H, W)`` float tensors in their native grey-level scale
    (8-bit: 0..255, 16-bit: 0..65535); colour images are converted to grey.

Results
    :class:`ResultWriter` writes an HDF5 file row by row (one row = one output frame) and
    flushes after every :meth:`ResultWriter.write_rows`, so a killed run leaves a readable
    file holding every finished row (``completed`` flags). ``resume=True`` continues such a
    file. :func:`read_results` loads one; :func:`export_csv` writes one CSV per frame.
"""

from __future__ import annotations

import copy
import datetime as _dt
import glob as _glob
import json
import os
import re
import threading
import warnings
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import tifffile
import torch
from PIL import Image, UnidentifiedImageError

from torch_stsdic.status import Status

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_FIELDS",
    "IMAGE_EXTENSIONS",
    "RESULTS_FORMAT",
    "RESULTS_FORMAT_VERSION",
    "STRAIN_FIELDS",
    "ImageSeries",
    "InputError",
    "ResultFileError",
    "ResultWriter",
    "Results",
    "export_csv",
    "load_series",
    "natural_sort_key",
    "parse_frame_spec",
    "read_results",
]

#: File extensions picked up when a *directory* is given (globs and lists take any file).
IMAGE_EXTENSIONS: tuple[str, ...] = (".tif", ".tiff", ".png", ".bmp", ".jpg", ".jpeg")
#: ITU-R BT.601 luma weights used for colour -> grey (alpha is dropped).
LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)

_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_OPEN_TIFF_CACHE = 4  # multi-page TIFF handles kept open per series


class InputError(ValueError):
    """Bad input images, arrays, timestamps or frame specifications (message names the culprit)."""


class ResultFileError(ValueError):
    """A result file is not a torch_stsdic file, or does not match the run that resumes it."""


# ----------------------------------------------------------------------------------------
# frame specifications and natural sort
# ----------------------------------------------------------------------------------------


def natural_sort_key(s: str | os.PathLike[str]) -> tuple[Any, ...]:
    """Sort key putting ``frame_2`` before ``frame_10`` (digit runs compare as integers)."""
    parts = re.split(r"(\d+)", os.fspath(s))
    return tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts))


def parse_frame_spec(spec: str | int, n: int) -> list[int]:
    """Parse a CLI frame specification into frame indices in ``0..n-1``.

    Accepts a single index (``"0"``, ``"-1"``), Python-style slices (``"0:5"``, ``"10:100:2"``,
    ``"-5:"``, ``":"``), ``"all"``, and comma-separated combinations (``"3,7,9"``,
    ``"0:5,10"``). Negative indices count from the end. Slices follow Python semantics
    (bounds are clipped to the series); single indices out of range are an error. The result
    keeps the given order with duplicates dropped; an empty result is an error.
    """
    if isinstance(spec, (int, np.integer)):
        spec = str(int(spec))
    if not isinstance(spec, str):
        raise InputError(f"frame spec must be a string, got {type(spec).__name__}")
    n = int(n)
    if n < 0:
        raise InputError(f"number of frames must be >= 0, got {n}")
    text = spec.strip()
    if not text:
        raise InputError("empty frame spec")
    out: list[int] = []
    seen: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise InputError(f"frame spec {spec!r}: empty item")
        if part.lower() == "all":
            idx = list(range(n))
        elif ":" in part:
            bits = [b.strip() for b in part.split(":")]
            if len(bits) > 3:
                raise InputError(f"frame spec {spec!r}: bad slice {part!r}")
            try:
                vals = [int(b) if b else None for b in bits]
            except ValueError:
                raise InputError(f"frame spec {spec!r}: bad slice {part!r}") from None
            if len(vals) == 3 and vals[2] == 0:
                raise InputError(f"frame spec {spec!r}: slice step cannot be 0")
            idx = list(range(n))[slice(*vals)]
        else:
            try:
                i = int(part)
            except ValueError:
                raise InputError(f"frame spec {spec!r}: {part!r} is not an integer") from None
            if not -n <= i < n:
                raise InputError(f"frame spec {spec!r}: index {i} out of range for {n} frames")
            idx = [i % n]
        for i in idx:
            if i not in seen:
                seen.add(i)
                out.append(i)
    if not out:
        raise InputError(f"frame spec {spec!r} selects no frame out of {n}")
    return out


# ----------------------------------------------------------------------------------------
# image series
# ----------------------------------------------------------------------------------------


@dataclass
class _FileInfo:
    """Header information of one image file (nothing decoded)."""

    path: Path
    kind: str  # "tiff" | "pil"
    n_frames: int
    shape: tuple[int, int]
    dtype: np.dtype
    bits: int
    colour: bool = False  # >= 3 samples: luminance of the first three
    extra: bool = False  # 2 samples (grey + alpha): first sample
    planar: bool = False  # TIFF planar-separate samples (S, H, W)
    pil_mode: str = ""


def _is_tiff(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(4) in _TIFF_MAGIC
    except OSError as exc:
        raise InputError(f"cannot open image file {path}: {exc}") from exc


_PIL_DTYPES: dict[str, tuple[str, int]] = {
    "1": ("uint8", 8),
    "L": ("uint8", 8),
    "P": ("uint8", 8),
    "LA": ("uint8", 8),
    "La": ("uint8", 8),
    "I;16": ("uint16", 16),
    "I;16L": ("uint16", 16),
    "I;16B": ("uint16", 16),
    "I;16N": ("uint16", 16),
    "I": ("int32", 32),
    "F": ("float32", 32),
}


def _probe_pil(path: Path) -> _FileInfo:
    try:
        with Image.open(path) as im:
            w, h = im.size
            mode = im.mode
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"cannot read image file {path}: {exc}") from exc
    dt, bits = _PIL_DTYPES.get(mode, ("uint8", 8))
    colour = mode not in _PIL_DTYPES or mode == "P"
    return _FileInfo(
        path=path,
        kind="pil",
        n_frames=1,
        shape=(h, w),
        dtype=np.dtype(dt),
        bits=bits,
        colour=colour,
        extra=mode in ("LA", "La"),
        pil_mode=mode,
    )


_EXTRA_AXES_OK = set("YXS")


def _probe_tiff(path: Path) -> _FileInfo:
    try:
        with tifffile.TiffFile(path) as tif:
            series = tif.series
            if not series:
                raise InputError(f"TIFF file {path} contains no image")
            s0 = series[0]
            nonyx = [(a, n) for a, n in zip(s0.axes, s0.shape) if a not in _EXTRA_AXES_OK]
            if sum(1 for _, n in nonyx if n > 1) > 1:
                raise InputError(
                    f"TIFF file {path} has axes {s0.axes!r} with shape {tuple(s0.shape)}: "
                    "only one stacking axis (time) is supported; extract one channel/slice first"
                )
            page = s0.keyframe
            h, w = int(page.imagelength), int(page.imagewidth)
            spp = int(page.samplesperpixel)
            n = len(s0)
            dtype = np.dtype(s0.dtype)
            bits = int(page.bitspersample)
            # further series of the same page size are treated as more frames
            for k, s in enumerate(series[1:], start=1):
                kf = s.keyframe
                if (int(kf.imagelength), int(kf.imagewidth)) != (h, w):
                    first = s[0]
                    where = f"page {first.index}" if first is not None else f"series {k}"
                    raise InputError(
                        f"mixed image sizes in {path}: {where} is "
                        f"{int(kf.imagelength)}x{int(kf.imagewidth)} (HxW) but page 0 is "
                        f"{h}x{w}"
                    )
                n += len(s)
            return _FileInfo(
                path=path,
                kind="tiff",
                n_frames=n,
                shape=(h, w),
                dtype=dtype,
                bits=bits,
                colour=spp >= 3,
                extra=spp == 2,
                planar=spp > 1 and int(page.planarconfig) == 2,
            )
    except InputError:
        raise
    except Exception as exc:  # tifffile raises various types on corrupt files
        raise InputError(f"cannot read TIFF file {path}: {exc}") from exc


def _probe_file(path: Path) -> _FileInfo:
    if not path.exists():
        raise InputError(f"image file not found: {path}")
    if path.is_dir():
        raise InputError(f"expected an image file, got a directory: {path}")
    return _probe_tiff(path) if _is_tiff(path) else _probe_pil(path)


def _to_grey(arr: np.ndarray, name: str) -> np.ndarray:
    """(H, W, C) -> (H, W): luminance for C >= 3 (alpha dropped), first sample for C == 2."""
    if arr.ndim == 2:
        return arr
    if arr.ndim != 3:
        raise InputError(f"{name}: expected a 2-D image, got shape {arr.shape}")
    c = arr.shape[-1]
    if c == 1:
        return arr[..., 0]
    if c == 2:
        return arr[..., 0]
    a = arr[..., :3].astype(np.float64)
    return a[..., 0] * LUMA_WEIGHTS[0] + a[..., 1] * LUMA_WEIGHTS[1] + a[..., 2] * LUMA_WEIGHTS[2]


_TORCH_FLOAT = {torch.float32: np.float32, torch.float64: np.float64}


def _np_float(dtype: torch.dtype) -> type:
    try:
        return _TORCH_FLOAT[dtype]
    except KeyError:
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}") from None


class ImageSeries:
    """A lazily read series of T grey images of identical size (H, W).

    Build it with :func:`load_series`. ``series[i]`` decodes frame ``i`` only and returns an
    ``(H, W)`` float32 tensor in the native grey scale. ``times`` is ``(T,)`` float64 (the
    timestamps given, else ``0..T-1``). Safe to share between threads and picklable (open
    file handles are not pickled).
    """

    def __init__(
        self,
        *,
        files: list[_FileInfo] | None = None,
        array: np.ndarray | torch.Tensor | None = None,
        timestamps: Any = None,
        label: str = "",
    ) -> None:
        self._files = files or []
        self._array = array
        self._label = label
        if array is not None:
            shp = tuple(array.shape)
            self._n = int(shp[0])
            self._shape = (int(shp[1]), int(shp[2]))
            self._colour = len(shp) == 4 and shp[3] >= 3
            if isinstance(array, torch.Tensor):
                self._dtype_name = str(array.dtype).replace("torch.", "")
                self._bits = int(array.element_size() * 8)
                self._float = array.is_floating_point()
            else:
                self._dtype_name = array.dtype.name
                self._bits = int(array.dtype.itemsize * 8)
                self._float = array.dtype.kind == "f"
            self._offsets = np.array([0, self._n])
        else:
            first = self._files[0]
            self._n = int(sum(f.n_frames for f in self._files))
            self._shape = first.shape
            self._colour = any(f.colour for f in self._files)
            self._dtype_name = first.dtype.name
            self._bits = first.bits
            self._float = first.dtype.kind == "f"
            self._offsets = np.cumsum([0] + [f.n_frames for f in self._files])
        self._times = _check_times(timestamps, self._n)
        self._lock = threading.RLock()
        self._handles: OrderedDict[Path, tifffile.TiffFile] = OrderedDict()
        self._pid = os.getpid()

    # -- basic properties ---------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    @property
    def shape(self) -> tuple[int, int]:
        """Image size ``(H, W)``."""
        return self._shape

    @property
    def dtype_name(self) -> str:
        """Native pixel dtype of the (first) input, e.g. ``"uint8"``, ``"uint16"``."""
        return self._dtype_name

    @property
    def bit_depth(self) -> int:
        """Bits per sample from the file header (e.g. 12 for 12-bit TIFF in uint16)."""
        return self._bits

    @property
    def max_value(self) -> float | None:
        """Largest representable grey level for integer data (``2**bits - 1``), else None."""
        return None if self._float else float(2**self._bits - 1)

    @property
    def is_colour(self) -> bool:
        """True if (some) frames are colour and are converted to grey on read."""
        return self._colour

    @property
    def times(self) -> np.ndarray:
        """``(T,)`` float64 frame times (timestamps if given, else frame indices)."""
        return self._times.copy()

    @property
    def sources(self) -> list[str]:
        """Input names for result-file attributes: one per file, or an array description."""
        if self._array is not None:
            return [self._label or self._array_label()]
        return [str(f.path) for f in self._files]

    def _array_label(self) -> str:
        kind = "tensor" if isinstance(self._array, torch.Tensor) else "array"
        return f"<{kind} {tuple(self._array.shape)} {self._dtype_name}>"

    def frame_name(self, i: int) -> str:
        """Human-readable origin of frame ``i`` (file name and page), for messages."""
        i = self._index(i)
        if self._array is not None:
            return f"{self._label or self._array_label()}[{i}]"
        k = int(np.searchsorted(self._offsets, i, side="right") - 1)
        f = self._files[k]
        if f.n_frames > 1:
            return f"{f.path} (page {i - int(self._offsets[k])})"
        return str(f.path)

    def describe(self) -> str:
        """One-line summary (frames, size, dtype, origin, time range)."""
        h, w = self._shape
        if self._array is not None:
            origin = self.sources[0]
        elif len(self._files) == 1:
            origin = str(self._files[0].path)
        else:
            origin = f"{len(self._files)} files, {self._files[0].path} .. {self._files[-1].path}"
        col = ", colour->grey" if self._colour else ""
        t = self._times
        tr = f", t={t[0]:g}..{t[-1]:g}" if len(t) else ""
        return (
            f"ImageSeries: {self._n} frames of {h}x{w} (HxW), {self._dtype_name} "
            f"({self._bits}-bit){col}{tr}; from {origin}"
        )

    def __repr__(self) -> str:
        return f"<{self.describe()}>"

    # -- reading --------------------------------------------------------------------------
    def _index(self, i: int) -> int:
        if isinstance(i, torch.Tensor):
            i = int(i.item())
        i = int(i)
        if not -self._n <= i < self._n:
            raise IndexError(f"frame {i} out of range for a series of {self._n} frames")
        return i % self._n

    def resolve(self, indices: Any) -> list[int]:
        """Frame indices from an int, slice, range, sequence/array, or a spec string."""
        if isinstance(indices, str):
            return parse_frame_spec(indices, self._n)
        if isinstance(indices, slice):
            return list(range(self._n))[indices]
        if isinstance(indices, (int, np.integer)):
            return [self._index(int(indices))]
        if isinstance(indices, torch.Tensor):
            indices = indices.detach().cpu().numpy()
        arr = np.asarray(list(indices) if isinstance(indices, range) else indices)
        if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
            raise InputError(f"frame indices must be a 1-D list of integers, got {indices!r}")
        return [self._index(int(i)) for i in arr]

    def _raw(self, i: int) -> np.ndarray:
        """Native pixels of frame i: (H, W) or (H, W, C); no type conversion."""
        if self._array is not None:
            x = self._array[i]
            if isinstance(x, torch.Tensor):
                x = x.detach().cpu()
                if x.dtype in (torch.float16, torch.bfloat16):
                    x = x.float()
                return x.numpy()
            return np.asarray(x)
        k = int(np.searchsorted(self._offsets, i, side="right") - 1)
        info = self._files[k]
        j = i - int(self._offsets[k])
        try:
            if info.kind == "pil":
                return self._read_pil(info)
            return self._read_tiff(info, j)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"cannot decode {self.frame_name(i)}: {exc}") from exc

    @staticmethod
    def _read_pil(info: _FileInfo) -> np.ndarray:
        with Image.open(info.path) as im:
            im.load()
            mode = im.mode
            if mode == "1":
                im = im.convert("L")
            elif mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif mode not in _PIL_DTYPES and mode not in ("RGB", "RGBA", "RGBX", "RGBa"):
                im = im.convert("RGB")
            return np.asarray(im)

    def _read_tiff(self, info: _FileInfo, j: int) -> np.ndarray:
        if self._pid != os.getpid():  # forked worker: never share file offsets with the parent
            self._lock = threading.RLock()
            self._handles = OrderedDict()
            self._pid = os.getpid()
        with self._lock:
            tif = self._handles.get(info.path)
            if tif is None:
                tif = tifffile.TiffFile(info.path)
                if info.n_frames > 1:
                    self._handles[info.path] = tif
                    while len(self._handles) > _OPEN_TIFF_CACHE:
                        self._handles.popitem(last=False)[1].close()
            else:
                self._handles.move_to_end(info.path)
            try:
                arr = None
                for k, s in enumerate(tif.series):
                    if j < len(s):
                        page = s[j]
                        if page is not None:
                            arr = page.asarray()
                        else:  # missing IFDs (e.g. ImageJ raw > 4 GB): memory-map
                            mm = tifffile.memmap(info.path, series=k, mode="r")
                            arr = np.array(mm.reshape(-1, *mm.shape[-len(s.keyframe.shape) :])[j])
                        break
                    j -= len(s)
                if arr is None:
                    raise InputError(f"{info.path}: page {j} not found")
            finally:
                if info.n_frames <= 1:
                    tif.close()
        if info.planar and arr.ndim == 3:
            arr = np.moveaxis(arr, 0, -1)
        return arr

    def numpy(self, i: int, dtype: type = np.float32) -> np.ndarray:
        """Frame ``i`` as an ``(H, W)`` numpy array of ``dtype`` (grey, native scale)."""
        i = self._index(i)
        arr = self._raw(i)
        if arr.ndim == 3 and arr.shape[-1] == 1:
            arr = arr[..., 0]
        if arr.shape[:2] != self._shape or arr.ndim not in (2, 3):
            h, w = self._shape
            raise InputError(
                f"mixed image sizes: {self.frame_name(i)} is {arr.shape[0]}x{arr.shape[1]} "
                f"(HxW) but the series is {h}x{w}"
            )
        arr = _to_grey(arr, self.frame_name(i))
        out = np.asarray(arr, dtype=dtype)
        if out.dtype.kind == "f" and arr.dtype.kind in "fc" and not np.isfinite(out).all():
            bad = int(np.size(out) - np.count_nonzero(np.isfinite(out)))
            raise InputError(f"{self.frame_name(i)} (frame {i}) has {bad} non-finite pixel(s)")
        return out

    def get(
        self,
        i: int,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Frame ``i`` as an ``(H, W)`` tensor (float32 or float64), native grey scale."""
        t = torch.from_numpy(self.numpy(i, _np_float(dtype)))
        return t if device is None else t.to(device)

    def __getitem__(self, i: Any) -> torch.Tensor:
        """``series[i]`` -> ``(H, W)`` float32; ``series[a:b]`` / lists -> ``(k, H, W)``."""
        if isinstance(i, (int, np.integer)) or (isinstance(i, torch.Tensor) and i.ndim == 0):
            return self.get(i)
        return self.read(i)

    def __iter__(self) -> Iterator[torch.Tensor]:
        for i in range(self._n):
            yield self.get(i)

    def read(
        self,
        indices: Any,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Frames ``indices`` (see :meth:`resolve`) stacked as a ``(k, H, W)`` tensor."""
        idx = self.resolve(indices)
        h, w = self._shape
        out = torch.empty((len(idx), h, w), dtype=dtype)
        npd = _np_float(dtype)
        for k, i in enumerate(idx):
            out[k] = torch.from_numpy(self.numpy(i, npd))
        return out if device is None else out.to(device)

    def mean_of(
        self,
        indices: Any,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Pixel-wise mean of frames ``indices`` as ``(H, W)`` (e.g. ``"0:5"``), memory O(H*W)."""
        idx = self.resolve(indices)
        if not idx:
            raise InputError(f"mean_of: no frames selected by {indices!r}")
        acc = np.zeros(self._shape, dtype=np.float64)
        for i in idx:
            acc += self.numpy(i, np.float64)
        acc /= len(idx)
        t = torch.from_numpy(acc.astype(_np_float(dtype), copy=False))
        return t if device is None else t.to(device)

    # -- resources ------------------------------------------------------------------------
    def close(self) -> None:
        """Close cached TIFF file handles (they reopen on demand)."""
        with self._lock:
            while self._handles:
                self._handles.popitem()[1].close()

    def __enter__(self) -> ImageSeries:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_lock"] = None
        state["_handles"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()
        self._handles = OrderedDict()
        self._pid = os.getpid()


def _check_times(timestamps: Any, n: int) -> np.ndarray:
    if timestamps is None:
        return np.arange(n, dtype=np.float64)
    if isinstance(timestamps, torch.Tensor):
        timestamps = timestamps.detach().cpu().numpy()
    try:
        t = np.asarray(timestamps, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"timestamps must be numbers: {exc}") from exc
    if t.ndim != 1 or t.shape[0] != n:
        raise InputError(f"timestamps must have shape ({n},) (one per frame), got {t.shape}")
    if not np.isfinite(t).all():
        raise InputError("timestamps contain non-finite values")
    if n > 1 and not (np.diff(t) > 0).all():
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(
            f"timestamps must be strictly increasing: t[{k}]={t[k]:g} >= t[{k + 1}]={t[k + 1]:g}"
        )
    return t


def _expand_source(source: str | os.PathLike[str]) -> list[Path]:
    s = os.fspath(source)
    p = Path(s).expanduser()
    if p.is_dir():
        files = [
            q
            for q in p.iterdir()
            if q.is_file() and not q.name.startswith(".") and q.suffix.lower() in IMAGE_EXTENSIONS
        ]
        if not files:
            raise InputError(
                f"directory {p} contains no image file ({', '.join(IMAGE_EXTENSIONS)})"
            )
        return sorted(files, key=natural_sort_key)
    if p.exists():
        return [p]
    if _glob.has_magic(s):
        matches = [Path(m) for m in _glob.glob(os.path.expanduser(s), recursive=True)]
        files = [m for m in matches if m.is_file()]
        if not files:
            raise InputError(f"glob pattern {s!r} matches no file")
        return sorted(files, key=natural_sort_key)
    raise InputError(f"image file or directory not found: {s}")


def load_series(source: Any, *, timestamps: Any = None) -> ImageSeries:
    """Open an image series lazily.

    ``source``: a (multi-page) TIFF or other image path, a directory (image files in
    natural order), a glob pattern (``"frames/*.tif"``, natural order), a list of paths
    (kept in the given order; multi-page TIFFs contribute all their pages), a ``(T, H, W)``
    or ``(T, H, W, 3|4)`` numpy array / torch tensor (a 2-D array is one frame), or an
    existing :class:`ImageSeries` (returned as is, with new timestamps if given).
    ``timestamps``: ``(T,)`` strictly increasing times, default ``0..T-1``.

    Headers are checked up front (existence, readability, equal sizes); pixels are decoded
    on demand. Raises :class:`InputError` naming the offending file or argument.
    """
    if isinstance(source, ImageSeries):
        if timestamps is None:
            return source
        new = copy.copy(source)
        new._times = _check_times(timestamps, len(source))
        return new
    if isinstance(source, (np.ndarray, torch.Tensor)):
        return _series_from_array(source, timestamps)
    if isinstance(source, (str, os.PathLike)):
        paths = _expand_source(source)
    elif isinstance(source, Iterable):
        paths = []
        for item in source:
            if not isinstance(item, (str, os.PathLike)):
                raise InputError(f"list of images must hold file paths, got {type(item).__name__}")
            paths.append(Path(item).expanduser())
        if not paths:
            raise InputError("empty list of image files")
    else:
        raise InputError(
            f"unsupported image source of type {type(source).__name__}: give a path, "
            "a directory, a glob pattern, a list of paths, or a (T, H, W) array"
        )
    infos: list[_FileInfo] = []
    warned_dtype = False
    for p in paths:
        info = _probe_file(p)
        if infos and info.shape != infos[0].shape:
            (h0, w0), (h, w) = infos[0].shape, info.shape
            raise InputError(
                f"mixed image sizes: {p} is {h}x{w} (HxW) but {infos[0].path} is {h0}x{w0}"
            )
        if infos and info.dtype != infos[0].dtype and not warned_dtype:
            warnings.warn(
                f"mixed pixel types: {p} is {info.dtype.name} but {infos[0].path} is "
                f"{infos[0].dtype.name}; grey levels are not rescaled",
                stacklevel=2,
            )
            warned_dtype = True
        infos.append(info)
    label = os.fspath(source) if isinstance(source, (str, os.PathLike)) else ""
    series = ImageSeries(files=infos, timestamps=timestamps, label=label)
    if series.is_colour or any(f.extra for f in infos):
        which = next(f for f in infos if f.colour or f.extra)
        hint = (
            " (a 3- or 4-frame stack written by tifffile without photometric='minisblack' "
            "is stored as RGB planes: rewrite it with photometric='minisblack')"
            if which.planar
            else ""
        )
        warnings.warn(
            f"colour images (e.g. {which.path}) are converted to grey "
            f"(luminance {LUMA_WEIGHTS[0]}R + {LUMA_WEIGHTS[1]}G + {LUMA_WEIGHTS[2]}B, "
            f"alpha dropped){hint}",
            stacklevel=2,
        )
    return series


def _series_from_array(arr: np.ndarray | torch.Tensor, timestamps: Any) -> ImageSeries:
    if isinstance(arr, np.ndarray) and arr.dtype.kind not in "biuf":
        raise InputError(f"image array has unsupported dtype {arr.dtype}")
    if isinstance(arr, torch.Tensor) and (arr.is_complex() or arr.dtype == torch.bool):
        raise InputError(f"image tensor has unsupported dtype {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[None]
    colour = arr.ndim == 4 and arr.shape[-1] in (3, 4)
    if arr.ndim != 3 and not colour:
        raise InputError(
            f"image array must be (T, H, W) (or (T, H, W, 3|4) colour, or one (H, W) image), "
            f"got shape {tuple(arr.shape)}"
        )
    if min(arr.shape[:3]) == 0:
        raise InputError(f"image array is empty: shape {tuple(arr.shape)}")
    series = ImageSeries(array=arr, timestamps=timestamps)
    if colour:
        warnings.warn(
            f"colour image array {tuple(arr.shape)} is converted to grey "
            f"(luminance {LUMA_WEIGHTS[0]}R + {LUMA_WEIGHTS[1]}G + {LUMA_WEIGHTS[2]}B, "
            "alpha dropped)",
            stacklevel=3,
        )
    return series


# ----------------------------------------------------------------------------------------
# HDF5 results
# ----------------------------------------------------------------------------------------

RESULTS_FORMAT = "torch_stsdic-results"
RESULTS_FORMAT_VERSION = 1
DEFAULT_FIELDS: tuple[str, ...] = ("u", "v", "ut", "vt", "zncc", "status")
STRAIN_FIELDS: tuple[str, ...] = ("exx", "eyy", "exy")
CSV_COLUMNS: tuple[str, ...] = (
    "x", "y", "u", "v", "ut", "vt", "exx", "eyy", "exy", "zncc", "status",
)  # fmt: skip
_RESERVED = {"points", "frames", "times", "completed"}
_INT_FIELDS: dict[str, tuple[type, int]] = {
    "status": (np.int8, int(Status.NOT_COMPUTED)),
    "iterations": (np.int16, -1),
}


def _field_dtype(name: str) -> tuple[type, float | int]:
    return _INT_FIELDS.get(name, (np.float32, np.nan))


def _software_version() -> str:
    try:
        from importlib.metadata import version

        return version("torch_stsdic")
    except Exception:
        return "unknown"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, torch.Tensor):
        return o.detach().cpu().tolist()
    if isinstance(o, (Path, torch.dtype, torch.device)):
        return str(o)
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    raise TypeError(f"config value of type {type(o).__name__} is not JSON serialisable")


def _config_json(config: Mapping[str, Any]) -> str:
    return json.dumps(dict(config), sort_keys=True, default=_json_default, allow_nan=True)


def _as_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _chunks(n_rows: int, n_cols: int, itemsize: int) -> tuple[int, int] | None:
    if n_rows == 0 or n_cols == 0:
        return None
    cols = min(n_cols, max(1, (4 << 20) // itemsize))  # <= 4 MiB per row chunk
    rows = max(1, min(n_rows, (64 << 10) // (cols * itemsize)))  # >= ~64 KiB when N small
    return rows, cols


def _diff_config(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        if k not in old:
            out.append(f"{k}: (absent) -> {new[k]!r}")
        elif k not in new:
            out.append(f"{k}: {old[k]!r} -> (absent)")
        elif old[k] != new[k]:
            out.append(f"{k}: {old[k]!r} -> {new[k]!r}")
    return [s if len(s) < 200 else s[:197] + "..." for s in out]


class ResultWriter:
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

        pts = np.asarray(_as_numpy(points), dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must have shape (N, 2), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("points must be finite")
        fr = np.asarray(_as_numpy(frames))
        if fr.ndim != 1 or (fr.size and fr.dtype.kind not in "iu"):
            raise ValueError(f"frames must be a 1-D integer array, got {fr.dtype} {fr.shape}")
        fr = fr.astype(np.int64)
        if len(np.unique(fr)) != len(fr):
            raise ValueError("frames must not contain duplicates")
        tm = np.asarray(_as_numpy(times), dtype=np.float64)
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
        self.config: dict[str, Any] = json.loads(_config_json(config))
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
        target.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(target, mode)
        try:
            f.attrs["format"] = RESULTS_FORMAT
            f.attrs["version"] = RESULTS_FORMAT_VERSION
            f.attrs["software_version"] = _software_version()
            f.attrs["created"] = _now()
            f.attrs["config"] = _config_json(self.config)
            f.attrs["inputs"] = json.dumps(self.inputs)
            f.attrs["fields"] = json.dumps(list(self.fields + self.extra_fields))
            f.attrs["status_codes"] = Status.describe()
            for k, v in self._attrs.items():
                f.attrs[k] = v
            n_f, n_p = len(self.frames), len(self.points)
            f.create_dataset("points", data=self.points)
            f.create_dataset("frames", data=self.frames)
            f.create_dataset("times", data=self.times)
            for name in self.fields + self.extra_fields:
                dt, fill = _field_dtype(name)
                f.create_dataset(
                    name,
                    shape=(n_f, n_p),
                    dtype=dt,
                    fillvalue=fill,
                    chunks=_chunks(n_f, n_p, np.dtype(dt).itemsize),
                )
            f.create_dataset("completed", data=np.zeros(n_f, dtype=bool))
            f.flush()
        except BaseException:
            f.close()
            target.unlink(missing_ok=True)
            raise
        self._file = f
        self._target = target

    def _check_match(self, f: h5py.File, where: Path) -> list[str]:
        problems: list[str] = []
        if f.attrs.get("format") != RESULTS_FORMAT:
            return [f"{where} is not a {RESULTS_FORMAT} file"]
        for name in ("points", "frames", "times", "completed", *self.fields, *self.extra_fields):
            if name not in f:
                problems.append(f"dataset {name!r} missing")
        if problems:
            return problems
        pts = f["points"][()]
        if pts.shape != self.points.shape:
            problems.append(f"points: {pts.shape[0]} in file, {len(self.points)} now")
        elif not np.array_equal(pts, self.points):
            problems.append("points: same count but different coordinates")
        fr = f["frames"][()]
        if not np.array_equal(fr, self.frames):
            problems.append(f"frames differ ({len(fr)} in file, {len(self.frames)} now)")
        elif not np.allclose(f["times"][()], self.times, rtol=1e-12, atol=0, equal_nan=True):
            problems.append("times differ")
        try:
            old = json.loads(f.attrs.get("config", "{}"))
        except json.JSONDecodeError:
            old = {}
        new = self.config
        ign = self._resume_ignore
        diff = _diff_config(
            {k: v for k, v in old.items() if k not in ign},
            {k: v for k, v in new.items() if k not in ign},
        )
        if diff:
            problems.append("config differs: " + "; ".join(diff))
        return problems

    def _open_resume(self) -> None:
        candidates = [p for p in (self._partial, self.path) if p.exists()]
        if not candidates:
            self._create(self.path, mode="x")
            return
        first_problems: list[str] | None = None
        for cand in candidates:
            try:
                f = h5py.File(cand, "r+")
            except OSError as exc:
                probs = [f"cannot open {cand}: {exc}"]
            else:
                probs = self._check_match(f, cand)
                if not probs:
                    self._file = f
                    self._target = cand
                    self._rename_on_close = cand == self._partial
                    old_inputs = json.loads(f.attrs.get("inputs", "[]"))
                    if old_inputs != self.inputs:
                        warnings.warn(
                            f"resuming {cand}: input files differ from the recorded ones",
                            stacklevel=3,
                        )
                    hist = json.loads(f.attrs.get("resumed", "[]"))
                    f.attrs["resumed"] = json.dumps([*hist, _now()])
                    f.flush()
                    return
                f.close()
            if first_problems is None:
                first_problems = [f"{cand}: {p}" for p in probs]
        raise ResultFileError(
            "cannot resume: "
            + " | ".join(first_problems or [])
            + " (use overwrite=True to start again)"
        )

    # -- writing --------------------------------------------------------------------------
    @property
    def n_rows(self) -> int:
        """F, the number of output frames (rows)."""
        return len(self.frames)

    @property
    def n_points(self) -> int:
        """N, the number of points."""
        return len(self.points)

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
        rows = np.atleast_1d(np.asarray(_as_numpy(row_indices)))
        if rows.ndim != 1 or (rows.size and rows.dtype.kind not in "iu"):
            raise ValueError(f"row_indices must be integers, got {row_indices!r}")
        rows = rows.astype(np.int64)
        nf, n_p = self.n_rows, self.n_points
        if rows.size and (rows.min() < -nf or rows.max() >= nf):
            raise IndexError(f"row index out of range for {nf} rows: {rows.tolist()}")
        rows = rows % max(nf, 1)
        if len(np.unique(rows)) != len(rows):
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
            a = _as_numpy(val)
            if a.ndim == 1 and k == 1:
                a = a[None]
            if a.shape != (k, n_p):
                raise ValueError(f"field {name!r}: expected shape ({k}, {n_p}), got {a.shape}")
            data[name] = a.astype(_field_dtype(name)[0], copy=False)
        if k == 0:
            return
        order = np.argsort(rows)
        srows = rows[order]
        contiguous = bool(np.all(np.diff(srows) == 1))
        for name, a in data.items():
            a = a[order]
            ds = f[name]
            if contiguous:
                ds[int(srows[0]) : int(srows[-1]) + 1] = a
            else:
                for j, r in enumerate(srows):
                    ds[int(r)] = a[j]
        f.flush()
        if mark_completed:
            f["completed"][srows] = True
            f.flush()

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
            f.flush()
        finally:
            f.close()
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
class Results:
    """Contents of a result file. Fields are attributes: ``res.u`` is ``(F, N)``."""

    path: Path
    points: np.ndarray  # (N, 2) float64, columns x, y
    frames: np.ndarray  # (F,) int64 image indices
    times: np.ndarray  # (F,) float64
    completed: np.ndarray  # (F,) bool
    fields: dict[str, np.ndarray]  # name -> (F, N)
    config: dict[str, Any]
    inputs: list[str]
    attrs: dict[str, Any] = field(default_factory=dict)

    def __getattr__(self, name: str) -> np.ndarray:
        fields = self.__dict__.get("fields")
        if fields is not None and name in fields:
            return fields[name]
        raise AttributeError(
            f"{type(self).__name__} has no attribute or field {name!r}"
            + (f" (fields: {sorted(fields)})" if fields is not None else "")
        )

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def n_points(self) -> int:
        return len(self.points)

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


def _open_read(path: Path) -> h5py.File:
    if not path.exists():
        partial = path.with_name(path.name + ".partial")
        hint = f" ({partial} exists: an unfinished overwrite run)" if partial.exists() else ""
        raise FileNotFoundError(f"result file not found: {path}{hint}")
    try:
        f = h5py.File(path, "r", locking=False)
    except OSError as exc:
        raise ResultFileError(f"{path} is not a readable HDF5 result file: {exc}") from exc
    if f.attrs.get("format") != RESULTS_FORMAT:
        f.close()
        raise ResultFileError(f"{path} is not a {RESULTS_FORMAT} file")
    return f


def _py(v: Any) -> Any:
    return v.item() if isinstance(v, np.generic) else v


def _field_names(f: h5py.File) -> list[str]:
    try:
        return list(json.loads(f.attrs["fields"]))
    except (KeyError, json.JSONDecodeError):
        skip = _RESERVED
        return [k for k in f if k not in skip and f[k].ndim == 2]


def read_results(path: str | os.PathLike[str], fields: Sequence[str] | None = None) -> Results:
    """Load a result file (all fields, or only ``fields``). Works on a file still being
    written or left by a killed run: rows with ``completed`` False hold NaN / NOT_COMPUTED."""
    p = Path(path)
    with _open_read(p) as f:
        names = _field_names(f)
        if fields is not None:
            bad = [n for n in fields if n not in names]
            if bad:
                raise KeyError(f"field(s) {bad} not in {p} (has {names})")
            names = list(fields)
        attrs = {k: _py(f.attrs[k]) for k in f.attrs}
        return Results(
            path=p,
            points=f["points"][()],
            frames=f["frames"][()],
            times=f["times"][()],
            completed=f["completed"][()].astype(bool),
            fields={n: f[n][()] for n in names},
            config=json.loads(attrs.pop("config", "{}")),
            inputs=list(json.loads(attrs.pop("inputs", "[]"))),
            attrs=attrs,
        )


def _fmt(a: np.ndarray, spec: str) -> np.ndarray:
    s = np.char.mod(spec, a)
    if a.dtype.kind == "f":
        s[~np.isfinite(a)] = ""
    return s


def export_csv(
    path_h5: str | os.PathLike[str],
    out_dir_or_pattern: str | os.PathLike[str],
    frames: int | Sequence[int] | None = None,
    *,
    comment: bool = True,
) -> list[Path]:
    """Write one CSV per frame; return the paths written.

    ``out_dir_or_pattern``: a directory (files ``<h5 stem>_frame<frame:05d>.csv``) or a pattern
    with ``{frame}`` (also ``{row}``, ``{time}``), e.g. ``"csv/f{frame:04d}.csv"``.
    ``frames``: image frame indices to export (default: all completed rows).
    Columns: ``x, y, u, v, ut, vt, exx, eyy, exy, zncc, status`` then any other stored field;
    missing fields and NaN are empty cells. With ``comment`` a first line
    ``# torch_stsdic ... frame=<f> time=<t>`` precedes the header line.
    """
    p = Path(path_h5)
    out = os.fspath(out_dir_or_pattern)
    written: list[Path] = []
    with _open_read(p) as f:
        all_frames = f["frames"][()]
        times = f["times"][()]
        completed = f["completed"][()]
        if frames is None:
            rows = np.flatnonzero(completed).tolist()
        else:
            wanted = [frames] if isinstance(frames, (int, np.integer)) else list(frames)
            rows = []
            for fr in wanted:
                hit = np.flatnonzero(all_frames == int(fr))
                if not hit.size:
                    raise KeyError(f"frame {fr} is not in {p} (frames {all_frames.tolist()})")
                rows.append(int(hit[0]))
        names = _field_names(f)
        columns = list(CSV_COLUMNS) + [n for n in names if n not in CSV_COLUMNS]
        pts = f["points"][()]
        n_p = len(pts)
        is_pattern = "{" in out
        if not is_pattern:
            Path(out).mkdir(parents=True, exist_ok=True)
        fixed = {"x": _fmt(pts[:, 0], "%.10g"), "y": _fmt(pts[:, 1], "%.10g")}
        empty = np.full(n_p, "", dtype=object)
        seen: set[Path] = set()
        for r in rows:
            fr, t = int(all_frames[r]), float(times[r])
            if is_pattern:
                target = Path(out.format(frame=fr, row=r, time=t))
            else:
                target = Path(out) / f"{p.stem}_frame{fr:05d}.csv"
            if target in seen:
                raise ValueError(f"output pattern {out!r} gives the same file {target} twice")
            seen.add(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            cols = []
            for c in columns:
                if c in fixed:
                    cols.append(fixed[c])
                elif c in names:
                    a = f[c][r]
                    cols.append(_fmt(a, "%d" if a.dtype.kind in "iu" else "%.9g"))
                else:
                    cols.append(empty)
            with open(target, "w", encoding="utf-8", newline="") as fh:
                if comment:
                    fh.write(
                        f"# torch_stsdic results {p.name}: frame={fr} time={t!r} row={r} "
                        f"completed={bool(completed[r])}\n"
                    )
                fh.write(",".join(columns) + "\n")
                for line in zip(*cols):
                    fh.write(",".join(line) + "\n")
            written.append(target)
    return written
