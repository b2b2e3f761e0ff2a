"""Process memory: keep freed memory for reuse instead of handing it back page by page.

The solver allocates and frees large temporaries (reference subsets, FFT regions, Gauss-Newton
buffers: tens of MB each) many times a run. glibc's ``malloc`` serves every block above its
mmap threshold (at most 32 MB) with a fresh ``mmap`` and unmaps it on ``free``, so each such
block is faulted in again, page by page, the next time: on the 1024x1024 benchmark pair
(38,809 POIs) ``stsdic run`` took ~205,000 page faults and 0.63 s, with large blocks kept in
the heap ~100,000 and 0.53 s, at the same peak RSS (the high-water mark is the same; only
the memory between the peaks stays mapped).

:func:`keep_freed_memory` sets that for the whole process (``mallopt``: no mmap for large
blocks, trim the heap only above 1 GiB free, and two malloc arenas at most: a thread of its
own, the run's writer, kept what it freed in an arena of its own, +27 MB at the peak of a
256 x 256 movie's run; with two, 368 MB against 382 MB before the writer). The ``stsdic``
command calls it at start; ``TORCH_STSDIC_MALLOC=0`` switches it off. A Python program that
uses the library can call it once itself, first: it changes the process, so the library
never does so on import (the same from the environment, for any program: ``MALLOC_MMAP_MAX_=0
MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_ARENA_MAX=2``; the first two together, either alone
leaves most of the faults). Where glibc is not the C library (macOS, Windows, musl) it does
nothing.

Memory kept so is fragmented by a run's passes (the shared-motion pass over every frame,
the template's rounds, the window-length pass), each freeing what it held in pieces that the
next pass's blocks do not fit exactly: :func:`release_freed_memory` hands the free pages
back to the system (``malloc_trim``) before a run's blocks, so that they start from what is
in use; a long movie's passes left more behind (``stsdic run``, 2 threads, one run each on a
loaded machine: 1,200 frames of 256 x 256 peaked at 404 MB without it, 390 MB with it; 120
frames at 389 and 386 MB).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["keep_freed_memory", "release_freed_memory"]

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
#: malloc arenas at most: the main one and one for every other thread (the writer thread,
#: the kernels' workers), so that what one thread frees another reuses
ARENAS = 2
TRIM_BYTES = 1 << 30  #: free memory at the top of the heap above which it is given back

_done: bool | None = None
_trim = None  # glibc's malloc_trim, once looked up (False: not available)


def keep_freed_memory() -> bool:
    """Serve large allocations from the heap and keep freed memory for reuse (glibc, once
    per process; see the module docstring). Returns whether the setting is in force.
    ``TORCH_STSDIC_MALLOC=0`` in the environment: do nothing."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if os.environ.get("TORCH_STSDIC_MALLOC", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        if not hasattr(libc, "gnu_get_libc_version"):  # musl has mallopt but ignores it
            return False
        mallopt = libc.mallopt
        mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        _done = (bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES))
                 and bool(mallopt(_M_ARENA_MAX, ARENAS)))
    except (OSError, AttributeError):
        _done = False
    return _done


def release_freed_memory() -> bool:
    """Give the free pages of the process's heap back to the system (glibc's
    ``malloc_trim(0)``: every free chunk's whole pages, not only the heap's top), e.g.
    between a run's passes; a few ms. Returns whether any memory was released; does nothing
    where glibc is not the C library."""
    global _trim
    if _trim is None:
        _trim = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                if hasattr(libc, "gnu_get_libc_version"):
                    _trim = libc.malloc_trim
                    _trim.argtypes, _trim.restype = [ctypes.c_size_t], ctypes.c_int
            except (OSError, AttributeError):
                _trim = False
    return bool(_trim(0)) if _trim else False
