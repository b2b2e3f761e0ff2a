"""One image file: its header (size, pixel type, pages) read without decoding, and its
pixels decoded to an ``(H, W)`` grey array (colour -> luminance, alpha dropped).

:class:`~torch_stsdic.io.images.ImageSeries` keeps one :class:`FileInfo` per file and calls
:func:`read_pil` / :func:`read_tiff_page` for a frame, then :func:`to_grey`.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from PIL import Image, UnidentifiedImageError

from torch_stsdic.io.specs import InputError

#: ITU-R BT.601 luma weights used for colour -> grey (alpha is dropped).
LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)
#: how colour becomes grey, for the warnings that say so
GREY_RULE = (
    f"luminance {LUMA_WEIGHTS[0]}R + {LUMA_WEIGHTS[1]}G + {LUMA_WEIGHTS[2]}B, alpha dropped"
)

TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


@dataclass
class FileInfo:
    """Header information of one image file (nothing decoded)."""

    path: Path
    kind: str  # "tiff" | "pil" | "movie"
    n_frames: int
    shape: tuple[int, int]
    dtype: np.dtype
    bits: int
    colour: bool = False  # >= 3 samples: luminance of the first three
    extra: bool = False  # 2 samples (grey + alpha): first sample
    planar: bool = False  # TIFF planar-separate samples (S, H, W)
    pil_mode: str = ""
    planes: bool = False  # one planar RGB(A) page whose sample planes are the frames
    frame_rate: float | None = None  # frames per second, from a movie file's header
    movie: Any = None  # a movie file's header (torch_stsdic.io.movies): open() -> reader


def _is_tiff(path: Path) -> bool:
    """True if ``path`` starts with a TIFF or BigTIFF magic number."""
    try:
        with open(path, "rb") as fh:
            return fh.read(4) in TIFF_MAGIC
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


def _check_pil_complete(im: Image.Image, path: Path) -> None:
    """A file cut short is refused from its header and size, nothing decoded: a PNG must end
    with its IEND chunk, and uncompressed pixel data (BMP ...) must lie inside the file."""
    size = path.stat().st_size
    if im.format == "PNG":
        with open(path, "rb") as fh:
            fh.seek(max(0, size - 1024))
            if b"IEND" not in fh.read():
                raise InputError(f"PNG file {path} is truncated (no IEND chunk at its end): "
                                 "the file was probably cut short while it was written or "
                                 "copied; copy it again")
    for tile in im.tile:
        codec, extents, offset, args = tile[0], tile[1], tile[2], tile[3]
        stride = args[1] if codec == "raw" and isinstance(args, tuple) and len(args) > 1 else 0
        if stride and extents and offset + abs(stride) * (extents[3] - extents[1]) > size:
            raise InputError(f"image file {path} is truncated (its pixel data end at byte "
                             f"{offset + abs(stride) * (extents[3] - extents[1])}, the file has "
                             f"{size} bytes): copy it again")


def _probe_pil(path: Path) -> FileInfo:
    """Header of a PNG, BMP, JPEG ... file through PIL."""
    try:
        with Image.open(path) as im:
            w, h = im.size
            mode = im.mode
            _check_pil_complete(im, path)
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"cannot read image file {path}: {exc}") from exc
    dt, bits = _PIL_DTYPES.get(mode, ("uint8", 8))
    colour = mode not in _PIL_DTYPES or mode == "P"
    return FileInfo(
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


@contextlib.contextmanager
def _tifffile_log() -> Iterator[list[str]]:
    """Collect tifffile's log messages instead of printing them (the caller turns them into
    one error or warning line)."""
    log = logging.getLogger("tifffile")
    saved = (log.handlers[:], log.propagate, log.level)
    got: list[str] = []

    class _Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            msg = " ".join(record.getMessage().split())
            got.append(msg.split("> ", 1)[1] if msg.startswith("<") and "> " in msg else msg)

    log.handlers, log.propagate = [_Collect(logging.WARNING)], False
    log.setLevel(logging.WARNING)
    try:
        yield got
    finally:
        log.handlers, log.propagate = saved[0], saved[1]
        log.setLevel(saved[2])


def _truncated(path: Path, detail: str) -> InputError:
    return InputError(f"TIFF file {path} is truncated or corrupt ({detail}): the file was "
                      "probably cut short while it was written or copied; copy it again")


def _check_tiff_data(tif: tifffile.TiffFile, path: Path, log: list[str]) -> None:
    """Every page's directory and pixel data lie inside the file (nothing decoded)."""
    size = int(tif.filehandle.size)
    pages = list(tif.pages)  # reads every page directory: a broken chain is logged
    bad = [msg for msg in log if "offset" in msg or "truncat" in msg or "corrupt" in msg]
    if bad:
        raise _truncated(path, f"{bad[0]} after {len(pages)} readable page(s)")
    for page in pages:
        ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts)]
        if ends and max(ends) > size:
            raise _truncated(path, f"page {page.index}: its pixel data end at byte {max(ends)}, "
                             f"the file has {size} bytes")
    for k, s in enumerate(tif.series):  # pages without a directory (ImageJ > 4 GB)
        off = getattr(s, "dataoffset", None)
        if off is not None and s.nbytes and off + s.nbytes > size:
            raise _truncated(path, f"series {k}: its pixel data end at byte {off + s.nbytes}, "
                             f"the file has {size} bytes")


def _probe_tiff(path: Path) -> FileInfo:
    """Header of a (multi-page, multi-series) TIFF file; InputError for stacks DIC cannot
    read as a time series, or a file cut short (every page's data checked against the file
    size; tifffile's log lines become the error, or warnings)."""
    with _tifffile_log() as log:
        info = _probe_tiff_header(path, log)
    for msg in log:
        warnings.warn(f"{path}: tifffile: {msg}", stacklevel=3)
    return info


def _probe_tiff_header(path: Path, log: list[str]) -> FileInfo:
    """:func:`_probe_tiff` with tifffile's log collected in ``log``."""
    try:
        with tifffile.TiffFile(path) as tif:
            _check_tiff_data(tif, path, log)
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
            planar = spp > 1 and int(page.planarconfig) == 2
            if planar and spp in (3, 4):
                if n > 1:
                    raise InputError(
                        f"TIFF file {path} holds {n} pages of {spp} separate sample planes: "
                        f"that is either {n} colour frames or {n * spp} grey frames; rewrite "
                        "it as grey pages (tifffile: photometric='minisblack') or as "
                        "interleaved colour (photometric='rgb', planarconfig='contig')"
                    )
                # one page of separate planes: how tifffile stores a (3|4, H, W) stack written
                # without photometric; DIC frames are grey, so the planes are the frames
                return FileInfo(path=path, kind="tiff", n_frames=spp, shape=(h, w),
                                 dtype=dtype, bits=bits, planar=True, planes=True)
            return FileInfo(
                path=path,
                kind="tiff",
                n_frames=n,
                shape=(h, w),
                dtype=dtype,
                bits=bits,
                colour=spp >= 3,
                extra=spp == 2,
                planar=planar,
            )
    except InputError:
        raise
    except Exception as exc:  # tifffile raises various types on corrupt files
        raise InputError(f"cannot read TIFF file {path}: {exc}") from exc


def probe_file(path: Path) -> FileInfo:
    """The header of the image file ``path`` (TIFF by its magic bytes, else PIL); InputError
    naming the file if it is missing, a directory or unreadable. (Camera movies:
    :func:`torch_stsdic.io.movies.probe_movie`.)"""
    if not path.exists():
        raise InputError(f"image file not found: {path}")
    if path.is_dir():
        raise InputError(f"expected an image file, got a directory: {path}")
    return _probe_tiff(path) if _is_tiff(path) else _probe_pil(path)


def read_pil(info: FileInfo) -> np.ndarray:
    """Native pixels of a PIL-read file: (H, W) or (H, W, C); bilevel and palette images are
    expanded to grey / RGB(A)."""
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


def read_tiff_page(tif: tifffile.TiffFile, info: FileInfo, j: int) -> np.ndarray:
    """Native pixels of frame ``j`` of the open TIFF ``tif`` (described by ``info``): (H, W)
    or (H, W, C), planar samples moved last."""
    if info.planes:  # the page's sample planes are the frames
        return np.asarray(tif.pages[0].asarray())[j]
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
    if info.planar and arr.ndim == 3:
        arr = np.moveaxis(arr, 0, -1)
    return arr


def to_grey(arr: np.ndarray, name: str) -> np.ndarray:
    """(H, W, C) -> (H, W): luminance for C >= 3 (alpha dropped), first sample for C == 2."""
    if arr.ndim == 2:
        return arr
    if arr.ndim != 3:
        raise InputError(f"{name}: expected a 2-D image, got shape {arr.shape}")
    if arr.shape[-1] <= 2:  # grey, or grey + alpha
        return arr[..., 0]
    a = arr[..., :3].astype(np.float64)
    return a[..., 0] * LUMA_WEIGHTS[0] + a[..., 1] * LUMA_WEIGHTS[1] + a[..., 2] * LUMA_WEIGHTS[2]
