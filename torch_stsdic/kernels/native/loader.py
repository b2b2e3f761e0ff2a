"""The switch and the loaded library: whether a call takes the native path.

The library is built and loaded once per process, on first use (:func:`available`,
:func:`usable`, :func:`kernels`); when that fails the torch code is used, with one warning.
Control: the environment variable ``TORCH_STSDIC_NATIVE`` ("auto" default, "0" off) or
:func:`set_native`.
"""

from __future__ import annotations

import os
import threading
import warnings

import torch

from torch_stsdic.kernels.native.builder import build
from torch_stsdic.kernels.native.declarations import VARIANTS, Kernel, Library

__all__ = ["set_native", "native_enabled", "per_point_enabled", "available", "usable",
           "usable_image", "kernels", "kernel"]

_MODE = os.environ.get("TORCH_STSDIC_NATIVE", "auto").lower()
_LIB: Library | None = None
_FAILED: str | None = None
_LOCK = threading.Lock()


def set_native(mode: str | bool) -> None:
    """Use the fused C++ CPU kernels: "auto"/True (when they build) or False/"0" (never)."""
    global _MODE
    m = {True: "auto", False: "0"}.get(mode, str(mode).lower())  # type: ignore[arg-type]
    if m not in ("auto", "1", "0"):
        raise ValueError(f"native mode must be 'auto', True or False, got {mode!r}")
    _MODE = m


def native_enabled() -> bool:
    """Whether the native kernels are switched on (they may still fail to build)."""
    return _MODE != "0"


def per_point_enabled() -> bool:
    """Whether a CPU Gauss-Newton stage may run point by point in one C++ call
    (``sts_ic_solve``): on unless the environment variable ``TORCH_STSDIC_PER_POINT`` is
    "0" (then the batched loop, one step of all points at a time, as before; read per call)."""
    return os.environ.get("TORCH_STSDIC_PER_POINT", "1") != "0"


def kernels() -> dict[str, Kernel]:
    """The native kernels by name ("sts_sample_f32", ...), as the library declares them (empty
    when the kernels are unavailable)."""
    lib = _load()
    return dict(lib.kernels) if lib is not None else {}


def kernel(base: str, dtype: torch.dtype) -> Kernel:
    """The float32 or float64 variant of a kernel."""
    lib = _load()
    if lib is None:
        raise RuntimeError(f"native kernels unavailable ({_FAILED})")
    return lib.kernels[base + VARIANTS[dtype]]


def _load() -> Library | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is not None or _FAILED is not None:
            return _LIB
        try:
            _LIB = Library(build())
        except (RuntimeError, OSError, AttributeError) as exc:
            _FAILED = str(exc)
            warnings.warn(f"torch_stsdic: fused CPU kernels unavailable ({_FAILED}); using "
                          "the torch code (slower)", RuntimeWarning, stacklevel=3)
    return _LIB


def available() -> bool:
    """Whether the fused CPU kernels are switched on and built (builds them on first call)."""
    return native_enabled() and _load() is not None


def usable(*tensors: torch.Tensor) -> bool:
    """Whether a call with these tensors can take the native path: switched on, built, CPU,
    float32/float64, and no autograd graph wanted through them (nothing requiring gradients
    while grad mode is on)."""
    if _MODE == "0":
        return False
    grad_on = torch.is_grad_enabled()
    for t in tensors:
        if t.device.type != "cpu" or (grad_on and t.requires_grad):
            return False
        if t.is_floating_point() and t.dtype not in (torch.float32, torch.float64):
            return False
    return _load() is not None


def usable_image(img_args: tuple, *tensors: torch.Tensor) -> bool:
    """:func:`usable`, and the image's planes small enough for 32-bit tap indices."""
    return img_args[-1] < 2**31 - 1 and usable(img_args[0], *tensors)

