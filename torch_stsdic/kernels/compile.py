"""torch.compile for the torch kernels: when a job is large enough to pay for the compile,
one compiled version per kernel and process, and a fall-back to eager mode for good when
compiling fails (no C++ compiler, unsupported platform).

"auto" mode compiles CPU jobs only. On CUDA the fused Triton step serves the Gauss-Newton
iterations, and what is left to the torch code (the reference subsets, the odd sampling)
runs a few times per block: there a compile (~45 s of imports and Inductor on an H200,
measured under cProfile for ``stsdic run --device cuda`` on the 40-frame hourglass) never
pays back. "1" compiles on any device."""

from __future__ import annotations

import os
import warnings

import torch

__all__ = ["set_compile", "compile_wanted", "maybe_compiled", "compile_failed"]


# "auto": compile for large jobs: >= _COMPILE_MIN samples per call, or per Gauss-Newton
# iteration over all batches of a solve (>= ~4 s per iteration in eager mode on one core);
# once compiled, the kernel serves every job of >= _COMPILED_MIN samples in the process.
# There the one-off compile time (~10-30 s; cached on disk by torch, ~7 s in a new process)
# pays back. "1"/"0": always / never. The environment variable TORCH_STSDIC_COMPILE sets the
# initial mode; see set_compile(). Fused, the sampler runs ~25x faster on a CPU.
_COMPILE_MODE = os.environ.get("TORCH_STSDIC_COMPILE", "auto").lower()
_COMPILE_MIN = 8_000_000
_COMPILED_MIN = 200_000
_COMPILED: dict = {}
_COMPILE_FAILED = False


def set_compile(mode: str | bool) -> None:
    """Use torch.compile for B-spline sampling: "auto" (large calls), True/"1", False/"0"."""
    global _COMPILE_MODE
    _COMPILE_MODE = {True: "1", False: "0"}.get(mode, str(mode).lower())  # type: ignore[arg-type]
    if _COMPILE_MODE not in ("auto", "1", "0"):
        raise ValueError(f"compile mode must be 'auto', True or False, got {mode!r}")


def _auto_device(device) -> bool:
    """Whether "auto" mode compiles at all for a job on ``device`` (a torch.device, a device
    string, a tensor, or None: unknown, taken as the CPU): CPU jobs only."""
    if isinstance(device, torch.Tensor):
        device = device.device
    return device is None or torch.device(device).type == "cpu"


def compile_wanted(work: int, device=None) -> bool:
    """Whether the policy compiles for a job of ``work`` samples in all (e.g. all POIs x
    frames x subset pixels of one Gauss-Newton iteration, over all batches) on ``device``
    (a device, a tensor, or None: the CPU): "1" always, "auto" for large CPU jobs only."""
    return _COMPILE_MODE == "1" or (_COMPILE_MODE == "auto" and work >= _COMPILE_MIN
                                    and _auto_device(device))


def maybe_compiled(fn, key, work: int, needs_autograd: bool = False, device=None):
    """``fn`` itself, or its torch.compile'd version (made once per ``key`` and process) when
    the compile policy (:func:`compile_wanted`) wants it for a job of ``work`` samples on
    ``device`` (a device, a tensor, or None: the CPU). A compile failure (no C++
    compiler, unsupported platform) warns once and falls back to ``fn`` for good."""
    use = compile_wanted(work, device) or (
        _COMPILE_MODE == "auto" and key in _COMPILED and work >= _COMPILED_MIN
        and _auto_device(device)
    )
    if not use or _COMPILE_FAILED or needs_autograd:
        return fn
    if key not in _COMPILED:
        compiled = torch.compile(fn, dynamic=True)

        def run(*args, _fn=compiled):
            global _COMPILE_FAILED
            try:
                return _fn(*args)
            except Exception as exc:  # no compiler, unsupported platform ...
                _COMPILE_FAILED = True
                first = str(exc).splitlines()[0] if str(exc) else ""
                warnings.warn(
                    f"torch.compile failed ({type(exc).__name__}: {first}); using eager mode",
                    RuntimeWarning, stacklevel=3,
                )
                return fn(*args)

        _COMPILED[key] = run
    return _COMPILED[key]


def compile_failed() -> bool:
    """Whether a torch.compile failed in this process (every kernel then runs eagerly)."""
    return _COMPILE_FAILED
