"""Movie files that cameras write, as one entry of an image series: Photron MRAW
(:mod:`.photron`), Phantom CINE (:mod:`.phantom`) and video files (:mod:`.video`), told apart
by their file extension. :func:`probe_movie` reads the header into a
:class:`~torch_stsdic.io.imagefile.FileInfo` whose ``movie`` opens a frame reader
(``open()`` -> ``frame(j)``, ``close()``); the file's frame rate comes with it.
"""

from __future__ import annotations

from pathlib import Path

from torch_stsdic.io.imagefile import FileInfo
from torch_stsdic.io.phantom import CINE_EXTENSIONS, read_cine_header
from torch_stsdic.io.photron import PHOTRON_EXTENSIONS, read_photron_header
from torch_stsdic.io.specs import InputError
from torch_stsdic.io.video import VIDEO_EXTENSIONS, read_video_header

__all__ = ["MOVIE_EXTENSIONS", "is_movie", "probe_movie"]

MOVIE_EXTENSIONS: tuple[str, ...] = PHOTRON_EXTENSIONS + CINE_EXTENSIONS + VIDEO_EXTENSIONS


def is_movie(path: Path) -> bool:
    """True if ``path``'s extension is a camera movie format read here."""
    return path.suffix.lower() in MOVIE_EXTENSIONS


def probe_movie(path: Path) -> FileInfo:
    """The header of the movie file ``path`` (format by extension) as a ``FileInfo`` of
    kind "movie"; InputError naming the file where it is missing or cannot be read."""
    if not path.exists():
        raise InputError(f"movie file not found: {path}")
    if path.is_dir():
        raise InputError(f"expected a movie file, got a directory: {path}")
    ext = path.suffix.lower()
    if ext in PHOTRON_EXTENSIONS:
        head = read_photron_header(path)
        name, colour = head.header, False
    elif ext in CINE_EXTENSIONS:
        head = read_cine_header(path)
        name, colour = path, head.colour
    else:
        head = read_video_header(path)
        name, colour = path, head.colour
    return FileInfo(path=name, kind="movie", n_frames=head.n_frames, shape=head.shape,
                    dtype=head.dtype, bits=head.bits, colour=colour,
                    frame_rate=head.frame_rate, movie=head)
