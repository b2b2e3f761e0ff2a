"""Image-series input: lazy, memory-bounded frames from TIFF stacks, folders, globs, camera
movies or arrays.

:func:`load_series` turns a multi-page TIFF, a directory, a glob pattern, a list of image
files, a camera movie (Photron ``.cih``/``.cihx``/``.mraw``, Phantom ``.cine``, a video
file; :mod:`.movies`) or a ``(T, H, W)`` array/tensor into an :class:`ImageSeries`. Only
image *headers* are read up front (sizes, dtypes, page counts); pixels are decoded one frame
at a time when asked for, so memory is bounded by what is requested, not by the movie
length. Frames come back as ``(H, W)`` float tensors in their native grey-level scale (8-bit:
0..255, 16-bit: 0..65535); colour images are converted to grey. One file's header and
pixels: :mod:`.imagefile`. A movie's frame rate becomes the series' times in seconds
(``k / fps``) unless timestamps are given.
"""

from __future__ import annotations

import copy
import glob as _glob
import os
import re
import threading
import warnings
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import torch

from torch_stsdic.io.imagefile import (
    GREY_RULE,
    LUMA_WEIGHTS,
    FileInfo,
    probe_file,
    read_pil,
    read_tiff_page,
    to_grey,
)
from torch_stsdic.io.movies import is_movie, probe_movie
from torch_stsdic.io.specs import InputError, natural_sort_key, parse_frame_spec

__all__ = [
    "IMAGE_EXTENSIONS",
    "LUMA_WEIGHTS",
    "ImageSeries",
    "expand_source",
    "InputError",
    "load_series",
    "natural_sort_key",
    "parse_frame_spec",
]

IMAGE_EXTENSIONS: tuple[str, ...] = (".tif", ".tiff", ".png", ".bmp", ".jpg", ".jpeg")
_OPEN_TIFF_CACHE = 4  # multi-page TIFF handles kept open per series

#: where a frame goes: a torch device, its name, or None (stays on the CPU)
Device = torch.device | str | None

# ----------------------------------------------------------------------------------------
# image series
# ----------------------------------------------------------------------------------------


_TORCH_FLOAT = {torch.float32: np.float32, torch.float64: np.float64}


def _np_float(dtype: torch.dtype) -> type:
    """The numpy type of a float torch ``dtype`` (ValueError for others)."""
    try:
        return _TORCH_FLOAT[dtype]
    except KeyError:
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}") from None


def _tensor(a: np.ndarray, device: Device) -> torch.Tensor:
    """``a`` as a tensor (sharing its memory), moved to ``device`` unless that is None."""
    t = torch.from_numpy(a)
    return t if device is None else t.to(device)


class ImageSeries:
    """A lazily read series of T grey images of identical size (H, W).

    Build it with :func:`load_series`. ``series[i]`` decodes frame ``i`` only and returns an
    ``(H, W)`` float32 tensor in the native grey scale. ``times`` is ``(T,)`` float64 (the
    timestamps given, else ``k / fps`` s from a movie file's frame rate, else ``0..T-1``).
    Safe to share between threads and picklable (open file handles are not pickled).
    """

    def __init__(
        self,
        *,
        files: list[FileInfo] | None = None,
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
        self._frame_rate = _common_rate(self._files)
        self._times_from_rate = timestamps is None and self._frame_rate is not None
        if self._times_from_rate:
            timestamps = np.arange(self._n, dtype=np.float64) / self._frame_rate
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
    def frame_rate(self) -> float | None:
        """Frames per second from the movie file(s) header (None for images and arrays, or
        movies of different rates)."""
        return self._frame_rate

    @property
    def time_unit(self) -> str | None:
        """"s" where :attr:`times` come from the movie's frame rate, else None (frame indices,
        or timestamps given in the user's unit)."""
        return "s" if self._times_from_rate else None

    @property
    def time_source(self) -> str | None:
        """Where the times come from when a movie's frame rate gives them, for summaries and
        result files (e.g. "frame rate 30000 /s of ball.cihx"), else None."""
        if not self._times_from_rate:
            return None
        return f"frame rate {self._frame_rate:g} /s of {self._files[0].path.name}"

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
            what = "frame" if f.kind == "movie" else "page"
            return f"{f.path} ({what} {i - int(self._offsets[k])})"
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
        if len(t) and self._times_from_rate:
            tr += f" s ({self.time_source})"
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
                return read_pil(info)
            return self._read_open(info, j)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"cannot decode {self.frame_name(i)}: {exc}") from exc

    def _read_open(self, info: FileInfo, j: int) -> np.ndarray:
        """Frame ``j`` of a TIFF or movie file, through a cache of open files."""
        if self._pid != os.getpid():  # forked worker: never share file offsets with the parent
            self._lock = threading.RLock()
            self._handles = OrderedDict()
            self._pid = os.getpid()
        with self._lock:
            tif = self._handles.get(info.path)
            if tif is None:
                tif = info.movie.open() if info.kind == "movie" else tifffile.TiffFile(info.path)
                if info.n_frames > 1:
                    self._handles[info.path] = tif
                    while len(self._handles) > _OPEN_TIFF_CACHE:
                        self._handles.popitem(last=False)[1].close()
            else:
                self._handles.move_to_end(info.path)
            try:
                return tif.frame(j) if info.kind == "movie" else read_tiff_page(tif, info, j)
            finally:
                if info.n_frames <= 1:
                    tif.close()

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
        arr = to_grey(arr, self.frame_name(i))
        out = np.asarray(arr, dtype=dtype)
        if out.dtype.kind == "f" and arr.dtype.kind in "fc" and not np.isfinite(out).all():
            bad = int(np.size(out) - np.count_nonzero(np.isfinite(out)))
            raise InputError(f"{self.frame_name(i)} (frame {i}) has {bad} non-finite pixel(s)")
        return out

    def get(
        self, i: int, dtype: torch.dtype = torch.float32, device: Device = None
    ) -> torch.Tensor:
        """Frame ``i`` as an ``(H, W)`` tensor (float32 or float64), native grey scale."""
        return _tensor(self.numpy(i, _np_float(dtype)), device)

    def __getitem__(self, i: Any) -> torch.Tensor:
        """``series[i]`` -> ``(H, W)`` float32; ``series[a:b]`` / lists -> ``(k, H, W)``."""
        if isinstance(i, (int, np.integer)) or (isinstance(i, torch.Tensor) and i.ndim == 0):
            return self.get(i)
        return self.read(i)

    def __iter__(self) -> Iterator[torch.Tensor]:
        for i in range(self._n):
            yield self.get(i)

    def read(
        self, indices: Any, dtype: torch.dtype = torch.float32, device: Device = None
    ) -> torch.Tensor:
        """Frames ``indices`` (see :meth:`resolve`) stacked as a ``(k, H, W)`` tensor."""
        idx = self.resolve(indices)
        npd = _np_float(dtype)
        out = np.empty((len(idx), *self._shape), dtype=npd)
        for k, i in enumerate(idx):
            out[k] = self.numpy(i, npd)
        return _tensor(out, device)

    def mean_of(
        self, indices: Any, dtype: torch.dtype = torch.float32, device: Device = None
    ) -> torch.Tensor:
        """Pixel-wise mean of frames ``indices`` as ``(H, W)`` (e.g. ``"0:5"``), memory O(H*W)."""
        idx = self.resolve(indices)
        if not idx:
            raise InputError(f"mean_of: no frames selected by {indices!r}")
        acc = np.zeros(self._shape, dtype=np.float64)
        for i in idx:
            acc += self.numpy(i, np.float64)
        acc /= len(idx)
        return _tensor(acc.astype(_np_float(dtype), copy=False), device)

    # -- resources ------------------------------------------------------------------------
    def close(self) -> None:
        """Close cached TIFF and movie file handles (they reopen on demand)."""
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


def _common_rate(files: list[FileInfo]) -> float | None:
    """The frame rate all ``files`` share (movies of one rate), else None."""
    rates = {f.frame_rate for f in files}
    if not files or len(rates) != 1:
        return None
    (rate,) = rates
    return float(rate) if rate else None


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


def expand_source(source: str | os.PathLike[str]) -> list[Path]:
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


#: a file name that says "reference" ("Sample5_Reference.tif", "ref_000.png", "REF.tif")
_REFERENCE_NAME = re.compile(r"(?:^|[^a-z])ref(?:erence)?(?:[^a-z]|$)", re.IGNORECASE)


def _reference_first(paths: list[Path], reorder: bool) -> list[Path]:
    """Put the one file whose name says "reference" first (frame 0, the default reference)
    when ``reorder`` (a folder or glob, whose order is ours); warn either way."""
    hits = [p for p in paths if _REFERENCE_NAME.search(p.stem)]
    if len(paths) < 2 or len(hits) != 1 or hits[0] == paths[0]:
        return paths
    ref = hits[0]
    if not reorder:
        warnings.warn(
            f"{ref.name} is named as a reference but is frame {paths.index(ref)} of the files "
            "given, which are kept in the given order (frame 0 is the default reference)",
            stacklevel=3,
        )
        return paths
    warnings.warn(
        f"{ref.name} is named as a reference: it is taken as frame 0 (the default reference), "
        f"the other {len(paths) - 1} files follow in natural order; list the files "
        "explicitly to choose another order",
        stacklevel=3,
    )
    return [ref] + [p for p in paths if p != ref]


def load_series(source: Any, *, timestamps: Any = None) -> ImageSeries:
    """Open an image series lazily.

    ``source``: a (multi-page) TIFF or other image path, a directory (image files in
    natural order), a glob pattern (``"frames/*.tif"``, natural order; in both, the one file
    whose name says "reference", e.g. ``Sample5_Reference.tif``, comes first, with a
    warning), a list of paths (kept in the given order; multi-page TIFFs contribute all their
    pages; a single-page TIFF of 3 or 4 separate planes is read as that many grey frames,
    with a warning), a ``(T, H, W)``
    or ``(T, H, W, 3|4)`` numpy array / torch tensor (a 2-D array is one frame), or an
    existing :class:`ImageSeries` (returned as is, with new timestamps if given).
    A camera movie (Photron ``.cih``/``.cihx``/``.mraw``, Phantom ``.cine``, a video file
    such as ``.avi``) is read lazily, frame by frame; its frame rate gives the times.
    ``timestamps``: ``(T,)`` strictly increasing times, default ``k / fps`` seconds for a
    movie with a frame rate, else ``0..T-1``.

    Headers are checked up front (existence, readability, equal sizes); pixels are decoded
    on demand. Raises :class:`InputError` naming the offending file or argument.
    """
    if isinstance(source, ImageSeries):
        if timestamps is None:
            return source
        new = copy.copy(source)
        new._times = _check_times(timestamps, len(source))
        new._times_from_rate = False
        return new
    if isinstance(source, (np.ndarray, torch.Tensor)):
        return _series_from_array(source, timestamps)
    if isinstance(source, (str, os.PathLike)):
        paths = _reference_first(expand_source(source), reorder=True)
    elif isinstance(source, Iterable):
        paths = []
        for item in source:
            if not isinstance(item, (str, os.PathLike)):
                raise InputError(f"list of images must hold file paths, got {type(item).__name__}")
            paths.append(Path(item).expanduser())
        if not paths:
            raise InputError("empty list of image files")
        paths = _reference_first(paths, reorder=False)
    else:
        raise InputError(
            f"unsupported image source of type {type(source).__name__}: give a path, "
            "a directory, a glob pattern, a list of paths, or a (T, H, W) array"
        )
    infos: list[FileInfo] = []
    warned_dtype = False
    for p in paths:
        info = probe_movie(p) if is_movie(p) else probe_file(p)
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
    for f in infos:
        if f.planes:
            warnings.warn(
                f"{f.path} is one TIFF page of {f.n_frames} separate planes (marked colour, "
                f"as tifffile stores a ({f.n_frames}, H, W) array written without "
                f"photometric): read as {f.n_frames} grey frames; save colour images "
                "interleaved (photometric='rgb', planarconfig='contig') to have them "
                "converted to grey instead",
                stacklevel=2,
            )
    label = os.fspath(source) if isinstance(source, (str, os.PathLike)) else ""
    series = ImageSeries(files=infos, timestamps=timestamps, label=label)
    if series.is_colour or any(f.extra for f in infos):
        which = next(f for f in infos if f.colour or f.extra)
        warnings.warn(
            f"colour images (e.g. {which.path}) are converted to grey ({GREY_RULE})",
            stacklevel=2,
        )
    return series


def _series_from_array(arr: np.ndarray | torch.Tensor, timestamps: Any) -> ImageSeries:
    from torch_stsdic.core.validation import check_pixel_dtype

    try:  # the pixels' finiteness is checked frame by frame, as they are read
        check_pixel_dtype(arr, "image array")
    except (TypeError, ValueError) as exc:
        raise InputError(str(exc)) from None
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
            f"colour image array {tuple(arr.shape)} is converted to grey ({GREY_RULE})",
            stacklevel=3,
        )
    return series


