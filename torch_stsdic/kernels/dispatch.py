"""Which backend runs each operation: the one place where the C++ kernels (CPU), the Triton
kernel (CUDA) and the torch code are chosen among, one function per operation.

Each function returns ``"native"``, ``"triton"`` or ``"torch"`` for a call on the given
tensors; the caller runs that backend. The rules (device, dtype, no autograd graph, sizes)
live in :func:`torch_stsdic.kernels.native.usable` / ``usable_image`` and
:func:`torch_stsdic.kernels.fused_step.usable`; this module only combines them per
operation, so that a change of rule is made once.
"""

from __future__ import annotations

from torch import Tensor

from torch_stsdic.kernels import fused_step, native

__all__ = ["prefilter", "sample", "windows", "gram", "ic_step", "fused_ic_step", "param_std",
           "spd_inverse", "nanmedian", "neighbour_test", "noise", "describe"]

NATIVE, TRITON, TORCH = "native", "triton", "torch"


def prefilter(images: Tensor) -> str:
    """B-spline prefilter of images (..., H, W)."""
    return NATIVE if images.dim() >= 2 and native.usable(images) else TORCH


def sample(kernel_args: tuple, *tensors: Tensor) -> str:
    """B-spline sampling (points, or whole subsets) of an image's flat coefficients
    (``BSplineImage.kernel_args()``) at the given coordinate tensors."""
    return NATIVE if native.usable_image(kernel_args, *tensors) else TORCH


def windows(*tensors: Tensor) -> str:
    """Whole-pixel windows gathered from per-pixel images (the reference subsets of POIs on
    the pixel grid)."""
    return NATIVE if native.usable(*tensors) else TORCH


def splat(kernel_args: tuple, *tensors: Tensor) -> str:
    """The template's samples of a frame (``movie.template_image.splat``): map, sample,
    grey levels matched, weights."""
    return NATIVE if native.usable_image(kernel_args, *tensors) else TORCH


def gram(*tensors: Tensor) -> str:
    """Moments of the steepest-descent images of a batch of subsets."""
    return NATIVE if native.usable(*tensors) else TORCH


def ic_step(kernel_args: tuple, order: int, p: Tensor, ft: Tensor, gx: Tensor, gy: Tensor
            ) -> str:
    """One joint IC-GN right-hand side (warp, sampling, criterion, J^T r over all frames):
    the C++ kernel on the CPU, the Triton kernel on CUDA, else the torch code (all three take
    the shared motion, a known displacement per point and frame)."""
    if native.usable_image(kernel_args, p, ft):
        return NATIVE
    if fused_step.usable(kernel_args[0], order, ft.shape[1], p, ft, gx, gy):
        return TRITON
    return TORCH


def fused_ic_step(kernel_args: tuple, order: int, n_subset: int, spatial: Tensor) -> bool:
    """Whether a fused kernel (C++ or Triton) will run the IC steps of a solve, judged before
    its data exist (batch sizing: no (N, T, S) temporaries then)."""
    return native.usable(spatial) or fused_step.usable(kernel_args[0], order, n_subset)


def param_std(n_cols: int, *tensors: Tensor) -> str:
    """The predicted std of ``n_cols`` parameters per row from per-point moments."""
    return NATIVE if native.usable(*tensors) and 1 <= n_cols <= 16 else TORCH


def spd_inverse(h: Tensor) -> str:
    """Batched inverse of small SPD matrices (N, P, P)."""
    return NATIVE if h.dim() == 3 and 1 <= h.shape[-1] <= 16 and native.usable(h) else TORCH


def nanmedian(x: Tensor) -> str:
    """The NaN-ignoring median of short rows (..., n)."""
    ok = x.dim() and 1 <= x.shape[-1] <= 64 and x.numel() and native.usable(x)
    return NATIVE if ok else TORCH


def noise(frames: Tensor) -> str:
    """Immerkaer's noise estimate of frames (F, H, W) (``core.noise.immerkaer_sigmas``; the
    native path takes whole-number grey levels only, which its caller checks)."""
    ok = frames.dim() == 3 and frames.shape[-1] >= 3 and frames.shape[-2] >= 3
    return NATIVE if ok and frames.is_floating_point() and native.usable(frames) else TORCH


def neighbour_test(v: Tensor, eps: Tensor, n_neighbours: int, points: Tensor | None,
                   gradients: Tensor | None) -> str:
    """One round of the neighbour consistency test over (B, N, C) values."""
    ok = (native.usable(v, eps) and n_neighbours <= 64 and v.shape[-1] <= 8
          and (points is None or gradients is None or native.usable(points, gradients)))
    return NATIVE if ok else TORCH


def describe(device: str) -> str:
    """What runs the Gauss-Newton steps on ``device``, in words (the run summary's)."""
    if device == "cpu":
        return "fused C++ kernels" if native.available() else "torch kernels"
    if fused_step.available() and fused_step.triton_mode() != "0":
        # affine stages: the whole-stage solver, unless TORCH_STSDIC_PER_POINT=0
        return "fused Triton solver" if native.per_point_enabled() else "fused Triton kernel"
    return "torch kernels"


def ic_solve(kernel_args: tuple, p: Tensor, ft: Tensor, ks: int, affine: bool, order: int = 3
             ) -> str:
    """A whole joint IC-GN stage (every point iterated to its end) for affine shapes (``ks`` =
    3 spatial terms) outside autograd, with the image's dtype: the C++ per-point solver on the
    CPU (threads take chunks of points and run each to convergence, no barrier per iteration),
    the Triton solver on CUDA (one launch per stage, a program per point iterating to its end:
    :mod:`torch_stsdic.kernels.triton_solve`; cubic splines, :func:`fused_step.usable`); else
    ``"torch"``: the batched loop, one step of all points at a time (autograd, other shapes).
    ``TORCH_STSDIC_PER_POINT=0`` keeps the batched loop (on CUDA with the fused Triton step)."""
    if not (affine and ks == 3 and native.per_point_enabled()
            and p.dtype == kernel_args[0].dtype):
        return TORCH
    if native.usable_image(kernel_args, p, ft):
        return NATIVE
    if fused_step.usable(kernel_args[0], order, ft.shape[1], p, ft):
        return TRITON
    return TORCH
