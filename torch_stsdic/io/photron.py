"""Photron FASTCAM movies: an ``.mraw`` file of raw frames and its ``.cih`` (text) or
``.cihx`` (XML) header, read without any extra package.

The header gives the frame count, size, the stored bits per sample (8, 12 packed, 16), the
effective bit depth and the record rate (frames per second). Frames are read one at a time
by offset (:mod:`.rawframes`); 12-bit packed frames are unpacked to ``uint16``. Grey values
are the stored samples, as pyMRAW's ``load_video`` gives them. :func:`write_mraw` writes an
8- or 16-bit movie with a ``.cih`` header (``stsdic synth --format mraw``).
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.io.rawframes import RawFrameReader, check_length, unpack_12bit
from torch_stsdic.io.specs import InputError

__all__ = ["PHOTRON_EXTENSIONS", "PhotronHeader", "read_photron_header", "write_mraw"]

PHOTRON_EXTENSIONS = (".cih", ".cihx", ".mraw")


@dataclass(frozen=True)
class PhotronHeader:
    """One Photron movie: ``mraw`` holds ``n_frames`` frames of ``shape`` (H, W), ``stored``
    bits per sample (8, 12 packed or 16), ``bits`` effective; ``frame_rate`` in frames/s;
    ``first_frame``: the camera's number of the file's first frame."""

    header: Path
    mraw: Path
    n_frames: int
    shape: tuple[int, int]
    stored: int
    bits: int
    frame_rate: float | None
    first_frame: int
    colour: str

    @property
    def frame_bytes(self) -> int:
        return self.shape[0] * self.shape[1] * self.stored // 8

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.stored == 8 else np.uint16)

    def open(self) -> PhotronReader:
        return PhotronReader(self)


class PhotronReader:
    """Frames of one Photron movie, decoded one at a time (``frame(j)``: ``(H, W)``)."""

    def __init__(self, head: PhotronHeader) -> None:
        self.head = head
        self._raw = RawFrameReader(head.mraw)

    def frame(self, j: int) -> np.ndarray:
        h = self.head
        data = self._raw.read(j * h.frame_bytes, h.frame_bytes)
        if h.stored == 8:
            px = data.copy()
        elif h.stored == 16:
            px = data.view("<u2").astype(np.uint16)
        else:
            px = unpack_12bit(data)
        return px.reshape(h.shape)

    def close(self) -> None:
        self._raw.close()


def _cih_text(path: Path) -> dict[str, str]:
    """``Key : Value`` lines of a text ``.cih`` header (up to its first empty line)."""
    out: dict[str, str] = {}
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if not line.strip():
                if out:
                    break
                continue
            key, sep, value = line.rstrip("\r\n").partition(" : ")
            if sep:
                out[key.strip()] = value.strip()
    return out


def _cihx_fields(path: Path) -> dict[str, str]:
    """The fields of a ``.cihx`` header (the ``<cih>`` XML after a binary preamble) under the
    names of a text ``.cih``."""
    data = path.read_bytes()
    i, j = data.find(b"<cih>"), data.rfind(b"</cih>")
    if i < 0 or j < 0:
        raise InputError(f"{path}: no <cih> header found (not a Photron .cihx file?)")
    try:
        root = ET.fromstring(data[i:j + len(b"</cih>")].decode("utf-8", errors="replace"))
    except ET.ParseError as exc:
        raise InputError(f"{path}: its <cih> header is not valid XML ({exc})") from None
    names = {
        "Record Rate(fps)": "recordInfo/recordRate",
        "Total Frame": "frameInfo/totalFrame",
        "Start Frame": "frameInfo/startFrame",
        "Image Width": "imageDataInfo/resolution/width",
        "Image Height": "imageDataInfo/resolution/height",
        "Color Bit": "imageDataInfo/colorInfo/bit",
        "Color Type": "imageDataInfo/colorInfo/type",
        "EffectiveBit Depth": "imageDataInfo/effectiveBit/depth",
        "EffectiveBit Side": "imageDataInfo/effectiveBit/side",
        "File Format": "imageFileInfo/fileFormat",
    }
    out = {}
    for key, where in names.items():
        node = root.find(where)
        if node is not None and node.text is not None:
            out[key] = node.text.strip()
    return out


def _header_file(path: Path) -> tuple[Path, Path]:
    """(header, mraw) for a ``.cih``/``.cihx``/``.mraw`` path (the header found beside an
    ``.mraw``)."""
    if path.suffix.lower() == ".mraw":
        for ext in (".cihx", ".cih", ".CIHX", ".CIH"):
            if path.with_suffix(ext).exists():
                return path.with_suffix(ext), path
        raise InputError(f"{path}: its header {path.with_suffix('.cihx').name} or "
                         f"{path.with_suffix('.cih').name} is missing (it gives the frame "
                         "size and count)")
    for ext in (".mraw", ".MRAW"):
        if path.with_suffix(ext).exists():
            return path, path.with_suffix(ext)
    raise InputError(f"{path}: its frames {path.with_suffix('.mraw').name} are missing "
                     "(a Photron header needs the .mraw file of the same name beside it)")


def _int(fields: dict[str, str], key: str, path: Path, default: int | None = None) -> int:
    if key not in fields:
        if default is not None:
            return default
        raise InputError(f"{path}: header field '{key}' is missing")
    try:
        return int(float(fields[key]))
    except ValueError:
        raise InputError(f"{path}: header field '{key}' is {fields[key]!r}, not a "
                         "number") from None


def read_photron_header(path: Path) -> PhotronHeader:
    """The header of the Photron movie ``path`` (``.cih``, ``.cihx`` or its ``.mraw``);
    InputError naming the file for a missing part, an unsupported layout, or an ``.mraw``
    shorter than its header says."""
    head, mraw = _header_file(path)
    fields = _cihx_fields(head) if head.suffix.lower() == ".cihx" else _cih_text(head)
    fmt = fields.get("File Format", "MRaw")
    if fmt.lower() != "mraw":
        raise InputError(f"{head}: File Format is {fmt!r}; only MRAW frames are read (export "
                         "the movie as MRAW, or read its TIFF frames as images)")
    n = _int(fields, "Total Frame", head)
    w, h = _int(fields, "Image Width", head), _int(fields, "Image Height", head)
    stored = _int(fields, "Color Bit", head)
    if stored not in (8, 12, 16):
        raise InputError(f"{head}: Color Bit {stored}: only 8, 12 (packed) and 16 bits per "
                         "sample (monochrome) are read; colour movies are not")
    if (h * w * stored) % 8:
        raise InputError(f"{head}: {w}x{h} px at {stored} bits is not a whole number of bytes")
    bits = _int(fields, "EffectiveBit Depth", head, default=stored)
    if fields.get("EffectiveBit Side", "Lower").lower() == "higher":
        bits = stored  # the samples sit in the high bits: their range is the word's
    rate = fields.get("Record Rate(fps)")
    fps = float(rate) if rate not in (None, "") else None
    colour = fields.get("Color Type", "Mono")
    out = PhotronHeader(header=head, mraw=mraw, n_frames=n, shape=(h, w), stored=stored,
                        bits=min(bits, stored), frame_rate=fps if fps and fps > 0 else None,
                        first_frame=_int(fields, "Start Frame", head, default=0),
                        colour=colour)
    if n < 1:
        raise InputError(f"{head}: Total Frame is {n}: no frame to read")
    check_length(mraw, n * out.frame_bytes, f"its {n} frames of {w}x{h} px at {stored} bits")
    if any(c in colour.lower() for c in ("color", "colour", "bayer")):
        warnings.warn(f"{head}: Color Type {colour!r}: the frames are read as the sensor's raw "
                      "samples (a colour mosaic is not demosaiced)", stacklevel=4)
    return out


def write_mraw(path: Path, frames: np.ndarray | Iterable[np.ndarray], frame_rate: float,
               info: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Write ``frames`` ``(T, H, W)`` (uint8 or uint16; or an iterable of (H, W) frames,
    each written as it comes) as ``path`` (``.mraw``) and its text ``.cih`` header (16-bit:
    12 effective bits unless a sample needs more) at ``frame_rate`` frames/s; returns
    (mraw, cih)."""
    mraw, cih = path.with_suffix(".mraw"), path.with_suffix(".cih")
    if isinstance(frames, np.ndarray) or not isinstance(frames, Iterable):
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"frames: expected (T, H, W) uint8 or uint16, got "
                             f"{frames.shape} {frames.dtype}")
        n, h, w = frames.shape
        dtype = frames.dtype
    n, top, first = 0, 0, None
    with open(mraw, "wb") as fh:
        for img in frames:
            img = np.asarray(img)
            if first is None:
                first = (img.shape, img.dtype)
                if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
                    raise ValueError(f"frames: expected (H, W) uint8 or uint16 frames, got "
                                     f"{img.shape} {img.dtype}")
            elif (img.shape, img.dtype) != first:
                raise ValueError(f"frames: frame {n} is {img.shape} {img.dtype}, the first "
                                 f"{first[0]} {first[1]}")
            img.astype(img.dtype.newbyteorder("<"), copy=False).tofile(fh)
            top = max(top, int(img.max(initial=0)))
            n += 1
    if first is not None:
        (h, w), dtype = first
    elif not isinstance(frames, np.ndarray):
        raise ValueError("frames: no frame to write")
    stored = dtype.itemsize * 8
    eff = 8 if stored == 8 else (12 if top < 4096 else 16)
    fields = {"Record Rate(fps)": f"{frame_rate:g}", "Shutter Speed(s)": f"{frame_rate:g}",
              "Total Frame": n, "Original Total Frame": n, "Start Frame": 0,
              "Image Width": w, "Image Height": h, "Color Type": "Mono", "Color Bit": stored,
              "File Format": "MRaw", "EffectiveBit Depth": eff, "EffectiveBit Side": "Lower",
              **(info or {})}
    cih.write_text("#Camera Information Header\n"
                   + "".join(f"{k} : {v}\n" for k, v in fields.items()), encoding="utf-8")
    return mraw, cih
