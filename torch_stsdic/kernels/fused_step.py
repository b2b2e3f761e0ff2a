"""Fused GPU kernels, registered as torch operators.

``torch.ops.torch_stsdic.ic_rhs`` is one joint IC-GN right-hand side (warp + cubic B-spline
sampling + ZNSSD/SSD residual + J^T r over all frames of a point; see
:mod:`torch_stsdic.kernels.triton_ic`). It is a ``torch.library`` custom op: torch calls it
like any operator (with a fake implementation for ``torch.compile``). On CUDA it runs the
Triton kernel where Triton is installed (``pip install torch_stsdic[gpu]``), elsewhere the
torch code (:func:`torch_stsdic.kernels.ic_step.ic_rhs_kernel`), which the tests compare
it with.

Selection (:func:`usable`): the environment variable ``TORCH_STSDIC_TRITON`` or
:func:`set_triton`: ``"auto"`` (default: CUDA tensors, Triton importable, cubic splines),
``"0"`` (never), ``"1"`` (also CPU tensors when ``TRITON_INTERPRET=1``, Triton's interpreter:
how the tests run the kernel without a GPU). On a CPU the C++ kernels
(:mod:`torch_stsdic.kernels.native`)
come first anyway.
"""

import functools
import importlib.util
import os

import torch
from torch import Tensor

from torch_stsdic.kernels.ic_step import ic_rhs_kernel

__all__ = ["available", "set_triton", "triton_mode", "triton_module", "usable", "ic_rhs",
           "ic_solve"]

_MODE = os.environ.get("TORCH_STSDIC_TRITON", "auto").lower()


def set_triton(mode) -> None:
    """Use the Triton kernels: "auto"/True (CUDA), "1" (also CPU under TRITON_INTERPRET=1),
    False/"0" (never)."""
    global _MODE
    m = {True: "auto", False: "0"}.get(mode, str(mode).lower())
    if m not in ("auto", "1", "0"):
        raise ValueError(f"triton mode must be 'auto', '1', True or False, got {mode!r}")
    _MODE = m


def triton_mode() -> str:
    """The current mode ("auto", "1" or "0")."""
    return _MODE


def _interpreting() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


@functools.lru_cache(maxsize=1)
def triton_module():
    """The Triton kernel module, or None when Triton is missing or fails to import."""
    if importlib.util.find_spec("triton") is None:
        return None
    try:
        from torch_stsdic.kernels import triton_ic
    except Exception:  # a broken Triton install: the torch code serves
        return None
    return triton_ic


def available() -> bool:
    """Whether Triton imports (the kernels can be launched on CUDA, or interpreted)."""
    return triton_module() is not None


def usable(flat: Tensor, order: int, n_subset: int, *tensors: Tensor) -> bool:
    """Whether the fused Triton step can serve a call on these tensors: switched on, Triton
    present, CUDA tensors (or CPU in mode "1" under the interpreter), float32/float64, cubic
    splines, a subset of at most ``MAX_SUBSET_PIXELS`` pixels, and no autograd graph wanted."""
    if _MODE == "0" or order != 3:
        return False
    if flat.device.type == "cuda":
        pass
    elif not (_MODE == "1" and flat.device.type == "cpu" and _interpreting()):
        return False
    if flat.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and any(t.requires_grad for t in (flat, *tensors)):
        return False
    mod = triton_module()
    return mod is not None and n_subset <= mod.MAX_SUBSET_PIXELS


def _torch_ic_rhs(flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w, rows,
                  wp, x_lo, x_hi, y_lo, y_hi, shift, w_img, h, k, has_time, znssd, order,
                  motion=None, count=None):
    """The torch code on the rows ``rows`` of the per-point data (None: all)."""
    if rows is not None:
        px, py, dt, frame_off = px[rows], py[rows], dt[rows], frame_off[rows]
        ft, fnorm, gx, gy = ft[rows], fnorm[rows], gx[rows], gy[rows]
        motion = None if motion is None else motion[rows]
        count = None if count is None else count[rows]
    b, zn, outside = ic_rhs_kernel(
        flat, p, px.reshape(-1, 1), py.reshape(-1, 1), dx, dy, basis.T.contiguous(), dt,
        frame_off, ft, fnorm.reshape(-1), gx, gy, w, wp, x_lo, x_hi, y_lo, y_hi, shift, w_img,
        h, basis.shape[1], k, has_time, znssd, order, motion, count)
    return b.double(), zn, outside


def _ic_rhs_impl(flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w, rows,
                 wp, x_lo, x_hi, y_lo, y_hi, shift, w_img, h, k, has_time, znssd, order,
                 motion=None, count=None):
    """The op's body: the Triton kernel where :func:`usable`, else the torch code."""
    args = (flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w, rows, wp,
            x_lo, x_hi, y_lo, y_hi, shift, w_img, h, k, has_time, znssd)
    if usable(flat, order, basis.shape[0], p, ft):
        return triton_module().ic_rhs_triton(*args, motion=motion, count=count)
    return _torch_ic_rhs(*args, order, motion, count)


@torch.library.custom_op("torch_stsdic::ic_rhs", mutates_args=())
def _ic_rhs_op(flat: Tensor, p: Tensor, px: Tensor, py: Tensor, dx: Tensor, dy: Tensor,
               basis: Tensor, dt: Tensor, frame_off: Tensor, ft: Tensor, fnorm: Tensor,
               gx: Tensor, gy: Tensor, w: Tensor, rows: Tensor | None, wp: int, x_lo: float,
               x_hi: float, y_lo: float, y_hi: float, shift: int, w_img: int, h: int, k: int,
               has_time: bool, znssd: bool, order: int,
               motion: Tensor | None = None, count: Tensor | None = None
               ) -> tuple[Tensor, Tensor, Tensor]:
    return _ic_rhs_impl(flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w,
                        rows, wp, x_lo, x_hi, y_lo, y_hi, shift, w_img, h, k, has_time, znssd,
                        order, motion, count)


@_ic_rhs_op.register_fake
def _(flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w, rows, wp, x_lo,
      x_hi, y_lo, y_hi, shift, w_img, h, k, has_time, znssd, order, motion=None, count=None):
    m = p.shape[0]
    return (p.new_empty(m, 2 * k, dtype=torch.float64), p.new_empty(m, dtype=flat.dtype),
            p.new_empty(m, dtype=torch.bool))


def ic_rhs(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
           gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool,
           rows: Tensor | None = None, frame_rhs: Tensor | None = None,
           motion: Tensor | None = None, count: Tensor | None = None):
    """``torch.ops.torch_stsdic.ic_rhs`` with the arguments of ``native.ic_rhs``: img_args
    from :meth:`BSplineImage.kernel_args`, p (M, 2k), basis (S, Ks), dt and frame_off (N, T)
    (frame offsets in coefficients), the per-point data (N, ...), ``rows`` (M,) the data row
    of each row of p (None: M = N). Returns b (M, 2k) float64, mean ZNCC (M,), outside (M,).

    Outside ``torch.compile`` the op's body is called directly: the first Triton launch
    through a ``torch.library`` op makes torch import its compiler stack (torch._dynamo,
    sympy, FSDP: 4.6 s of a fresh process's first ``stsdic run --device cuda`` on an H100,
    measured under cProfile); the op serves compiled graphs.

    ``frame_rhs``: a contiguous float64 (M, T, 2 Ks + 1) tensor filled with each frame's own
    spatial right-hand side and its ZNCC (as ``native.ic_rhs``), by the Triton kernel only
    (:func:`usable`; ValueError otherwise), outside ``torch.compile``.

    ``motion``: (N, T, 2) a known displacement (u, v) added to each data row's warp of frame
    t (the specimen's shared motion, as ``native.ic_rhs``), or None.

    ``count``: (N,) each data row's frames in use, its first ``count[i]`` columns of dt and
    frame_off (a shorter window padded to T; as ``native.ic_rhs``), or None (all)."""
    flat, wp, x_lo, x_hi, y_lo, y_hi, shift, _ = img_args
    args = (flat, p, px.reshape(-1), py.reshape(-1), dx, dy, basis.contiguous(), dt,
            frame_off.to(torch.int64), ft, fnorm.reshape(-1), gx, gy, w, rows, int(wp),
            float(x_lo), float(x_hi), float(y_lo), float(y_hi), int(shift), int(w_img), int(h),
            int(k), bool(has_time), bool(znssd))
    if motion is not None and tuple(motion.shape) != (*dt.shape, 2):
        raise ValueError(f"kernels.ic_rhs: motion must be (N, T, 2) = ({dt.shape[0]}, "
                         f"{dt.shape[1]}, 2), got {tuple(motion.shape)}")
    if frame_rhs is not None:
        n_t, ks = dt.shape[1], basis.shape[1]
        if not usable(flat, order, basis.shape[0], p, ft):
            raise ValueError("kernels.ic_rhs: frame_rhs needs the Triton kernel (usable)")
        if (tuple(frame_rhs.shape) != (p.shape[0], n_t, 2 * ks + 1)
                or frame_rhs.dtype != torch.float64 or not frame_rhs.is_contiguous()
                or frame_rhs.device != flat.device):
            raise ValueError(f"kernels.ic_rhs: frame_rhs must be a contiguous float64 "
                             f"({p.shape[0]}, {n_t}, {2 * ks + 1}) tensor on {flat.device}")
        return triton_module().ic_rhs_triton(*args, frame_rhs=frame_rhs, motion=motion,
                                             count=count)
    compiling = getattr(torch.compiler, "is_compiling", lambda: False)()  # torch >= 2.3
    call = torch.ops.torch_stsdic.ic_rhs if compiling else _ic_rhs_impl
    return call(*args, int(order), motion, count)


@functools.lru_cache(maxsize=1)
def _solve_module():
    """The Triton solver module (:mod:`torch_stsdic.kernels.triton_solve`), or None."""
    if triton_module() is None:
        return None
    try:
        from torch_stsdic.kernels import triton_solve
    except Exception:  # a broken Triton install: the batched loop serves
        return None
    return triton_solve


def ic_solve(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
             gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool, hinv, scale,
             prev, tol: float, max_iter: int, div_norm: float, rate_floor: float,
             codes: tuple[int, int, int, int], motion=None, ref_rows=None,
             frame_rhs: bool = False, count=None):
    """Every point's joint IC-GN stage to its end in one Triton launch
    (:func:`torch_stsdic.kernels.triton_solve.ic_solve_triton`): the arguments and results of
    ``native.ic_solve``. Where :func:`usable` (ValueError otherwise: the caller asks
    ``dispatch.ic_solve`` first)."""
    mod = _solve_module()
    if mod is None or not usable(img_args[0], order, basis.shape[0], p, ft):
        raise ValueError("kernels.ic_solve: the Triton solver does not serve this call "
                         "(CUDA tensors, Triton, cubic splines; dispatch.ic_solve decides)")
    return mod.ic_solve_triton(img_args, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx,
                               gy, w, w_img, h, k, has_time, znssd, hinv, scale, prev, tol,
                               max_iter, div_norm, rate_floor, codes, motion=motion,
                               ref_rows=ref_rows, frame_rhs=frame_rhs, count=count)
