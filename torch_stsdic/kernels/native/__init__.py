"""Fused CPU kernels (C++), built on first use and loaded with ctypes.

On a CPU the Gauss-Newton iteration is bound by B-spline sampling: every subset pixel of
every frame is 16 (cubic) or 36 (quintic) gathered coefficients, and a chain of torch
operations writes each intermediate (N, T, S) tensor to memory. The kernels in
``_native/dic_kernels.cpp`` do warp + sample + criterion + reduction of one IC-GN step in
one pass per point (double accumulators across frames), a few ns per sample and thread
(measured by ``scripts/bench_kernels.py``, recorded in ``docs/bench/kernels-cpu.json``);
also the reference subsets with gradients, the IC Hessian's moments, the inverses of small
symmetric positive definite matrices, medians of short rows, the recursive B-spline
prefilter and the samples of the template made from the series (map, sample, grey levels
matched, weights: one pass per frame and POI).

* Built with the system C++ compiler (``$CXX``, else ``c++``/``g++``/``clang++``; the same
  one torch.compile needs on a CPU) into ``$TORCH_STSDIC_CACHE`` (default
  ``~/.cache/torch_stsdic``; a temp directory if that is not writable), keyed by source,
  compiler and CPU; about 3 s, once. The build targets the CPU it runs on
  (``-march=native``: AVX2 where present); ``TORCH_STSDIC_NATIVE_MARCH`` names another
  target (e.g. ``x86-64-v2``) or, empty, the compiler's portable default.
* Plain C ABI, no torch headers; tensors are passed as pointers.
* One declaration per kernel, in C++: each kernel's parameter list is written once, in its
  ``STS_KERNEL`` definition; the loader reads the library's declarations, checks them
  against the compiled kinds and builds each ctypes prototype from them (this package holds
  no signature). Every call goes through a :class:`Kernel`, with each parameter by name, and
  is checked before any C code runs: no name missing or unknown, pointers get contiguous CPU
  tensors of the declared element dtype (None only where nullable), integers get ints in
  the C type's range, floating-point parameters real numbers. A mismatch raises TypeError
  (ValueError for a range) naming the kernel, the parameter's index, name and declaration.
  Not checked: that the tensors are as large as the kernel assumes.
* Threads: ctypes releases the GIL, so a call's rows are split over
  ``torch.get_num_threads()`` threads of the library's own pool (idle threads block); a call
  returns or raises (KeyboardInterrupt included) only once no helper thread is inside the
  kernel. A CPU solve runs in :func:`.rows.own_threads`: torch on one thread, the pool with
  the thread count torch had (issue 46: no OpenMP thread spins in the solve).
* Used for CPU tensors of float32/float64 outside autograd (nothing requiring gradients
  while grad mode is on). Everything else (CUDA, autograd through the sampler) uses the
  torch code, which the tests compare with these kernels. Without a compiler the torch code
  is used, with one warning.

Control: the environment variable ``TORCH_STSDIC_NATIVE`` ("auto" default, "0" off) or
:func:`set_native`.

Modules, one job each: ``builder`` (compiler, cache directory, :func:`build`),
``declarations`` (the library's signatures, :class:`Kernel` and its checked call),
``loader`` (the switch, loading once, :func:`usable`), ``rows`` (the row-parallel runner),
``ops`` (the wrappers :func:`sample`, :func:`subsets`, :func:`ic_rhs`, :func:`gram`,
:func:`spd_inverse`, :func:`nanmedian`, :func:`neighbour_own_gradient`,
:func:`neighbour_test`, :func:`prefilter`, :func:`splat`, :func:`splat_add`,
:func:`splat_fused`, :func:`splat_finish`, :func:`windows`, :func:`sobel_counts`,
:func:`flat_sums`).
"""

from __future__ import annotations

from torch_stsdic.kernels.native.builder import build
from torch_stsdic.kernels.native.declarations import Kernel, Param
from torch_stsdic.kernels.native.loader import (
    available,
    kernels,
    native_enabled,
    per_point_enabled,
    set_native,
    usable,
    usable_image,
)
from torch_stsdic.kernels.native.ops import (
    flat_sums,
    gram,
    ic_rhs,
    ic_solve,
    nanmedian,
    neighbour_own_gradient,
    neighbour_test,
    param_std,
    prefilter,
    sample,
    sobel_counts,
    spd_inverse,
    splat,
    splat_add,
    splat_finish,
    splat_fused,
    subsets,
    windows,
)

__all__ = ["available", "set_native", "native_enabled", "sample", "subsets", "ic_rhs",
           "ic_solve", "gram",
           "spd_inverse", "param_std", "nanmedian", "neighbour_own_gradient", "neighbour_test",
           "prefilter", "splat", "splat_add", "splat_fused", "splat_finish", "windows",
           "sobel_counts", "flat_sums",
           "build", "kernels", "Kernel", "Param", "usable", "usable_image",
           "per_point_enabled"]
