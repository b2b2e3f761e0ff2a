"""Vision Research Phantom ``.cine`` movies: the file's headers parsed here, frames read one at
a time by their offsets (:mod:`.rawframes`).

Layouts read: uncompressed 8- and 16-bit grey (rows stored bottom-up, as the bitmap header
says), 24/48-bit colour (BGR, converted to grey like colour images), and packed 10-bit
(``biCompression`` 256: 10-bit words through Phantom's linearisation table to 12 bits, the
table and the scaling as pycine applies them; that one needs pycine, the ``cameras`` extra).
Uncompressed grey values are the stored samples: pycine additionally stretches them from the
setup's black level to its white level, a linear map that changes no DIC result. A colour
sensor's raw mosaic (a colour filter array) is read as stored, with a warning.
"""

from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torch_stsdic.io.rawframes import RawFrameReader, check_length, unpack_10bit
from torch_stsdic.io.specs import InputError

__all__ = ["CINE_EXTENSIONS", "PhantomHeader", "read_cine_header"]

CINE_EXTENSIONS = (".cine",)

_FILE_HEADER = struct.Struct("<2s3H i I i 4I 2I")  # CINEFILEHEADER, 44 bytes
_BITMAP_HEADER = struct.Struct("<I 2i 2H 2I 2i 2I")  # BITMAPINFOHEADER, 40 bytes
#: byte offsets in the SETUP block of the fields read (Vision Research's cine file format)
_SETUP = {"FrameRate16": (0, "<H"), "Length": (142, "<H"), "FrameRate": (768, "<I"),
          "bEnableColor": (788, "<i"), "CFA": (808, "<I"), "RealBPP": (896, "<I"),
          "BlackLevel": (5732, "<i"), "WhiteLevel": (5736, "<i")}
PACKED_10BIT = 256


@dataclass(frozen=True)
class PhantomHeader:
    """One cine movie: ``n_frames`` frames of ``shape`` (H, W) at the byte offsets
    ``offsets`` (each to the frame's annotation block), ``bit_count`` bits per pixel as
    stored, ``compression`` (0 or 256), ``bits`` the effective depth, ``frame_rate``
    frames/s; ``first_frame``: the camera's number of the first frame (0: the trigger)."""

    path: Path
    n_frames: int
    shape: tuple[int, int]
    bit_count: int
    compression: int
    bits: int
    bottom_up: bool
    frame_rate: float | None
    first_frame: int
    offsets: tuple[int, ...]
    frame_bytes: int

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bit_count in (8, 24) else np.uint16)

    @property
    def colour(self) -> bool:
        return self.bit_count in (24, 48)

    def open(self) -> PhantomReader:
        return PhantomReader(self)


def _packed_lut() -> np.ndarray:
    """Phantom's 10-bit -> 12-bit linearisation table (pycine's ``linLUT``)."""
    try:
        from pycine.linLUT import linLUT
    except ImportError:
        raise InputError('packed 10-bit Phantom cine frames need pycine (its linearisation '
                         'table): pip install "torch_stsdic[cameras]"') from None
    return np.asarray(linLUT, dtype=np.float64)


class PhantomReader:
    """Frames of one cine movie, decoded one at a time (``frame(j)``: ``(H, W)`` or
    ``(H, W, 3)`` RGB)."""

    def __init__(self, head: PhantomHeader) -> None:
        self.head = head
        self._raw = RawFrameReader(head.path)
        self._lut = _packed_lut() if head.compression == PACKED_10BIT else None

    def frame(self, j: int) -> np.ndarray:
        hd = self.head
        (annotation,) = struct.unpack("<I", self._raw.read(hd.offsets[j], 4).tobytes())
        data = self._raw.read(hd.offsets[j] + annotation, hd.frame_bytes)
        h, w = hd.shape
        if hd.compression == PACKED_10BIT:
            lin = self._lut[unpack_10bit(data)].astype(np.uint16)  # as pycine: 12-bit values
            return np.interp(lin, [64, 4064], [0, 4095]).astype(np.uint16).reshape(h, w)
        if hd.bit_count in (8, 16):
            px = data.copy() if hd.bit_count == 8 else data.view("<u2").astype(np.uint16)
            px = px.reshape(h, w)
        else:  # BGR triplets
            px = (data.copy() if hd.bit_count == 24 else data.view("<u2").astype(np.uint16))
            px = px.reshape(h, w, 3)[..., ::-1]
        return np.ascontiguousarray(px[::-1] if hd.bottom_up else px)

    def close(self) -> None:
        self._raw.close()


def _setup_field(block: bytes, name: str) -> int | None:
    """A SETUP field by name, None where the file's (older, shorter) SETUP ends before it."""
    off, fmt = _SETUP[name]
    size = struct.calcsize(fmt)
    return struct.unpack(fmt, block[off:off + size])[0] if len(block) >= off + size else None


def read_cine_header(path: Path) -> PhantomHeader:
    """The headers of the cine file ``path``; InputError naming the file for a file that is
    not a cine, an unsupported layout, or frames beyond its end."""
    with open(path, "rb") as fh:
        raw = fh.read(_FILE_HEADER.size + _BITMAP_HEADER.size)
        if len(raw) < _FILE_HEADER.size + _BITMAP_HEADER.size or raw[:2] != b"CI":
            raise InputError(f"{path}: not a Phantom cine file (no 'CI' header)")
        (_, _, _, _, _, _, first_no, count, off_bmp, off_setup, off_offsets,
         _, _) = _FILE_HEADER.unpack_from(raw, 0)
        (_, width, height, _, bit_count, compression, _, _, _, _,
         _) = _BITMAP_HEADER.unpack_from(raw, off_bmp)
        fh.seek(off_setup)
        setup = fh.read(6000)
        (length,) = struct.unpack("<H", setup[142:144]) if len(setup) >= 144 else (0,)
        setup = setup[:length] if length else setup
        fh.seek(off_offsets)
        table = fh.read(8 * count)
    if count < 1:
        raise InputError(f"{path}: the cine file holds no frame (ImageCount 0)")
    if len(table) < 8 * count:
        raise InputError(f"{path} is truncated: its table of {count} frame offsets is cut short")
    h, w = abs(height), width
    if compression == PACKED_10BIT:
        frame_bytes, bits = w * h * 10 // 8, 12
    elif compression == 0 and bit_count in (8, 16, 24, 48):
        frame_bytes = w * h * bit_count // 8
        real = _setup_field(setup, "RealBPP")
        bits = real if real and real <= (8 if bit_count in (8, 24) else 16) else (
            8 if bit_count in (8, 24) else 16)
    else:
        raise InputError(f"{path}: cine frames of {bit_count} bits with compression "
                         f"{compression} are not read (uncompressed 8/16-bit and packed 10-bit "
                         "are): save the cine uncompressed in the camera software")
    fps = _setup_field(setup, "FrameRate") or _setup_field(setup, "FrameRate16")
    offsets = struct.unpack(f"<{count}q", table)
    head = PhantomHeader(path=path, n_frames=count, shape=(h, w), bit_count=bit_count,
                         compression=compression, bits=bits, bottom_up=height > 0 and
                         compression == 0, frame_rate=float(fps) if fps else None,
                         first_frame=first_no, offsets=tuple(offsets), frame_bytes=frame_bytes)
    check_length(path, max(offsets) + 8 + frame_bytes, f"its {count} frame(s)")
    cfa = _setup_field(setup, "CFA")
    if bit_count in (8, 16) and _setup_field(setup, "bEnableColor") and cfa and cfa & 0xFF:
        warnings.warn(f"{path}: a colour sensor's raw frames (colour filter array code "
                      f"{cfa & 0xFF}): read as stored, the mosaic is not demosaiced", stacklevel=4)
    return head
