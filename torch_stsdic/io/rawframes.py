"""Frames stored uncompressed at known byte offsets of one file (Photron MRAW, Phantom CINE):
each frame is read on its own by offset (``os.pread``), so a long movie costs the frames in
flight, never the movie; the operating system's page cache does the rest. (A memory map of
the whole file would count every page touched in the process's resident memory.)

The camera readers (:mod:`.photron`, :mod:`.phantom`) describe a file by its frame offsets
and their decoder; :class:`RawFrameReader` reads the bytes, :func:`unpack_12bit` and
:func:`unpack_10bit` turn packed words into ``uint16``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from torch_stsdic.io.specs import InputError

__all__ = ["RawFrameReader", "unpack_10bit", "unpack_12bit", "check_length"]


def unpack_12bit(data: np.ndarray) -> np.ndarray:
    """Packed big-endian 12-bit words (3 bytes -> 2 samples: ``AB CD EF`` -> ``ABC``,
    ``DEF``) as ``uint16``; ``data`` is 1-D ``uint8`` of a length divisible by 3."""
    b = data.reshape(-1, 3).astype(np.uint16)
    out = np.empty((b.shape[0], 2), dtype=np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] >> 4)
    out[:, 1] = ((b[:, 1] & 0x0F) << 8) | b[:, 2]
    return out.reshape(-1)


def unpack_10bit(data: np.ndarray) -> np.ndarray:
    """Packed big-endian 10-bit words (5 bytes -> 4 samples) as ``uint16``; ``data`` is 1-D
    ``uint8`` of a length divisible by 5."""
    b = data.reshape(-1, 5).astype(np.uint16)
    out = np.empty((b.shape[0], 4), dtype=np.uint16)
    out[:, 0] = (b[:, 0] << 2) | (b[:, 1] >> 6)
    out[:, 1] = ((b[:, 1] & 0x3F) << 4) | (b[:, 2] >> 4)
    out[:, 2] = ((b[:, 2] & 0x0F) << 6) | (b[:, 3] >> 2)
    out[:, 3] = ((b[:, 3] & 0x03) << 8) | b[:, 4]
    return out.reshape(-1)


def check_length(path: Path, end: int, what: str) -> None:
    """InputError if ``path`` is shorter than ``end`` bytes (``what`` ends there)."""
    size = path.stat().st_size
    if size < end:
        raise InputError(f"{path} is truncated: {what} end at byte {end}, the file has {size} "
                         "bytes (it was probably cut short while it was written or copied)")


class RawFrameReader:
    """Reads ``nbytes`` at a frame's byte offset from one open file (thread-safe: ``pread``
    moves no shared file position). ``close`` releases the file; it reopens on demand."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def read(self, offset: int, nbytes: int) -> np.ndarray:
        """``nbytes`` bytes at ``offset`` as a 1-D ``uint8`` array (InputError if short)."""
        if self._fd is None:
            try:
                self._fd = os.open(self.path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
            except OSError as exc:
                raise InputError(f"cannot open {self.path}: {exc.strerror}") from exc
        buf = os.pread(self._fd, nbytes, offset)
        if len(buf) != nbytes:
            raise InputError(f"{self.path} is truncated: {nbytes} bytes expected at byte "
                             f"{offset}, {len(buf)} found")
        return np.frombuffer(buf, dtype=np.uint8)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
