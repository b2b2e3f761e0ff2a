"""Video files (AVI, MKV, MOV, MP4 ...) through PyAV (the ``cameras`` extra): the stream's
frame count, size, pixel format and frame rate from its headers, frames decoded when asked
for (sequential reads decode on; a jump seeks to the nearest key frame before it).

Grey and YUV pixel formats give their luma plane as stored (8-bit ``uint8``, deeper
``uint16``); RGB formats are read as RGB and converted to grey like colour images. Lossy
codecs (H.264, MPEG-4, MJPEG ...) blur and block speckle: they are read, with a warning.
:func:`write_video` writes a lossless FFV1 movie (``stsdic synth --format avi``).
"""

from __future__ import annotations

import itertools
import warnings
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.io.specs import InputError

__all__ = ["LOSSLESS_CODECS", "VIDEO_EXTENSIONS", "VideoHeader", "read_video_header",
           "write_video"]

VIDEO_EXTENSIONS = (".avi", ".mkv", ".mov", ".mp4", ".m4v", ".webm", ".nut", ".mj2")
#: codecs that store the pixels exactly
LOSSLESS_CODECS = frozenset({"ffv1", "huffyuv", "ffvhuff", "rawvideo", "png", "apng",
                             "utvideo", "magicyuv", "qtrle", "zlib", "zmbv", "tiff", "r210",
                             "jpegls", "lagarith", "v308", "v408", "v410"})
_CACHED = 16  # decoded frames kept by one reader (a window's frames are read again)


def _av() -> Any:
    """The ``av`` module, or InputError naming the extra to install."""
    try:
        import av
    except ImportError:
        raise InputError('reading video files needs PyAV: pip install "torch_stsdic[cameras]" '
                         '(or pip install av)') from None
    return av


def _grey_layout(fmt: Any) -> tuple[str, np.dtype, int]:
    """How frames of the pixel format ``fmt`` are read: ("luma" | "rgb", dtype, bits)."""
    name = fmt.name
    bits = max(int(c.bits) for c in fmt.components) if fmt.components else 8
    if name.startswith(("gray", "yuv", "nv12", "nv21", "y4", "ya")) and "rgb" not in name:
        return "luma", np.dtype(np.uint8 if bits <= 8 else np.uint16), bits
    return "rgb", np.dtype(np.uint8 if bits <= 8 else np.uint16), min(bits, 16)


@dataclass(frozen=True)
class VideoHeader:
    """One video stream: ``n_frames`` frames of ``shape`` (H, W), decoded as ``layout``
    ("luma": the grey/Y plane; "rgb": colour) of ``dtype``, ``bits`` per sample;
    ``frame_rate`` frames/s; ``codec`` its name."""

    path: Path
    n_frames: int
    shape: tuple[int, int]
    layout: str
    dtype: np.dtype
    bits: int
    frame_rate: float | None
    codec: str

    @property
    def colour(self) -> bool:
        return self.layout == "rgb"

    def open(self) -> VideoReader:
        return VideoReader(self)


def _frame_array(frame: Any, head: VideoHeader) -> np.ndarray:
    """A decoded frame as ``(H, W)`` luma or ``(H, W, 3)`` RGB in ``head.dtype``."""
    h, w = head.shape
    if head.layout == "rgb":
        return frame.to_ndarray(format="rgb24" if head.dtype == np.uint8 else "rgb48le")
    plane = frame.planes[0]
    item = head.dtype.itemsize
    rows = np.frombuffer(plane, dtype=np.uint8 if item == 1 else "<u2")
    return rows.reshape(h, plane.line_size // item)[:, :w].astype(head.dtype)


class VideoReader:
    """Frames of one video stream, decoded on demand (``frame(j)``), the last few kept."""

    def __init__(self, head: VideoHeader) -> None:
        self.head = head
        self._container: Any = None
        self._frames: Any = None
        self._next = 0  # index of the frame the decoder gives next
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def _open(self) -> None:
        self.close()
        self._container = _av().open(str(self.head.path))
        stream = self._container.streams.video[0]
        stream.thread_type = "AUTO"
        self._stream = stream
        self._frames = self._container.decode(stream)
        self._next = 0
        # time stamps tell frames apart (seeking by them is safe): a tick of one frame or
        # less (Matroska's 1 ms ticks do not, at 30,000 frames/s)
        rate = self.head.frame_rate
        self._stamped = bool(rate) and float(stream.time_base) * rate <= 1.0 + 1e-9

    def _index(self, frame: Any) -> int | None:
        """The frame number of a decoded frame from its time stamp (None without one)."""
        pts = frame.pts if frame.pts is not None else frame.dts
        if pts is None:
            return None
        start = self._stream.start_time or 0
        return int(round(float((pts - start) * self._stream.time_base) * self.head.frame_rate))

    def _seek(self, j: int) -> None:
        """Position the decoder before frame ``j``: the key frame at or before it where the
        time stamps tell frames apart, else the start of the stream (backwards) or where the
        decoder is (forwards)."""
        if not self._stamped:
            if j < self._next:
                self._open()
            return
        stream = self._stream
        start = stream.start_time or 0
        target = start + int(Fraction(j) / Fraction(self.head.frame_rate).limit_denominator(
            10**6) / stream.time_base)
        self._container.seek(target, stream=stream, backward=True, any_frame=False)
        self._frames = self._container.decode(stream)
        self._next = -1  # known from the first decoded frame

    def frame(self, j: int) -> np.ndarray:
        if j in self._cache:
            self._cache.move_to_end(j)
            return self._cache[j]
        if self._container is None:
            self._open()
        if self._next < 0 or not 0 <= j - self._next <= 2 * _CACHED:  # not a short step on
            self._seek(j)
        for attempt in range(2):
            for frame in self._frames:
                k = self._next if self._next >= 0 else self._index(frame)
                if k is None or k > j:  # no stamp, or the seek went past: from the start
                    break
                self._next = k + 1
                if k >= j - _CACHED:
                    self._keep(k, _frame_array(frame, self.head))
                if k == j:
                    return self._cache[j]
            if attempt == 0:
                self._open()
        raise InputError(f"{self.head.path}: frame {j} could not be decoded (the stream ended "
                         f"after frame {self._next - 1})")

    def _keep(self, k: int, arr: np.ndarray) -> None:
        self._cache[k] = arr
        while len(self._cache) > _CACHED:
            self._cache.popitem(last=False)

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
            self._container = self._frames = None


def read_video_header(path: Path) -> VideoHeader:
    """The first video stream's header of ``path`` (frames counted by demuxing where the
    container does not say); InputError naming the file if it cannot be opened, a warning
    for a lossy codec."""
    av = _av()
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(f"{path}: the file holds no video stream")
            stream = container.streams.video[0]
            ctx = stream.codec_context
            n = int(stream.frames or 0)
            if n <= 0:
                n = sum(1 for p in container.demux(stream) if p.size)
            rate = stream.average_rate or stream.guessed_rate or stream.base_rate
            layout, dtype, bits = _grey_layout(ctx.format)
            head = VideoHeader(path=path, n_frames=n, shape=(int(ctx.height), int(ctx.width)),
                               layout=layout, dtype=dtype, bits=bits,
                               frame_rate=float(rate) if rate else None, codec=ctx.name)
    except InputError:
        raise
    except Exception as exc:  # PyAV raises its own error types for unreadable files
        raise InputError(f"cannot read video file {path}: {exc}") from exc
    if n < 1:
        raise InputError(f"{path}: the video stream holds no frame")
    if head.codec not in LOSSLESS_CODECS:
        warnings.warn(f"{path}: codec {head.codec!r} is lossy as usually set: its compression "
                      "blurs and blocks speckle and biases displacements; record or convert to "
                      "a lossless codec (FFV1, rawvideo, PNG) or image files", stacklevel=4)
    return head


def write_video(path: Path, frames: np.ndarray | Iterable[np.ndarray],
                frame_rate: float) -> Path:
    """Write ``frames`` ``(T, H, W)`` (uint8 or uint16; or an iterable of (H, W) frames,
    each encoded as it comes) to ``path`` losslessly (FFV1, grey 8 or 16 bit) at
    ``frame_rate`` frames/s."""
    av = _av()
    if isinstance(frames, np.ndarray) or not isinstance(frames, Iterable):
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"frames: expected (T, H, W) uint8 or uint16, got "
                             f"{frames.shape} {frames.dtype}")
    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError("frames: no frame to write")
    first = np.asarray(first)
    if first.ndim != 2 or first.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frames: expected (H, W) uint8 or uint16 frames, got "
                         f"{first.shape} {first.dtype}")
    fmt = "gray" if first.dtype == np.uint8 else "gray16le"
    rate = Fraction(frame_rate).limit_denominator(10**6)
    refused = ValueError(f"{path}: its container does not store {frame_rate:g} frames/s (the "
                         "AVI muxer takes rates up to 1000 /s): write a .mkv file instead")
    try:
        with av.open(str(path), "w") as container:
            stream = container.add_stream("ffv1", rate=rate)
            stream.width, stream.height = first.shape[1], first.shape[0]
            stream.pix_fmt = fmt
            for k, img in enumerate(itertools.chain([first], it)):
                img = np.asarray(img)
                if (img.shape, img.dtype) != (first.shape, first.dtype):
                    raise ValueError(f"frames: frame {k} is {img.shape} {img.dtype}, the "
                                     f"first {first.shape} {first.dtype}")
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format=fmt)
                frame.pts, frame.time_base = k, 1 / rate
                container.mux(stream.encode(frame))
            container.mux(stream.encode(None))
    except av.error.ArgumentError:
        path.unlink(missing_ok=True)
        raise refused from None
    with av.open(str(path)) as container:  # AVI stores some rates as others
        if container.streams.video[0].average_rate != rate:
            path.unlink(missing_ok=True)
            raise refused
    return path
