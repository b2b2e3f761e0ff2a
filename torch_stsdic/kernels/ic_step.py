"""The torch code of one joint inverse-compositional Gauss-Newton right-hand side over all
frames of a point: warp (Eq. 9), B-spline sampling, criterion and reduction in plain tensor
code, so torch.compile can fuse it. The fused C++ kernel (``native.ic_rhs``) and the Triton
kernel (:mod:`.triton_ic`) compute the same; :mod:`.fused_step` chooses among them."""

from __future__ import annotations

import torch

from torch_stsdic.kernels.bspline import sample_kernel

__all__ = ["linear_displacement", "ic_rhs_kernel", "ic_rhs_compiled", "frames_in_use"]


def linear_displacement(p: torch.Tensor, spatial_t: torch.Tensor, dt: torch.Tensor, ks: int,
                        k: int, has_time: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, v), each (N, T, S) (or (N, 1, S) without time): Eq. 9 for a shape function whose
    parameters are (spatial terms, then the time term) per component.

    p (N, 2k); spatial_t (Ks, S) the transposed spatial basis; dt (N, T). Plain tensor code
    (no module state) so that compiled kernels can inline it; :meth:`ShapeFunction.
    displacement` is the entry point for everything else."""
    us = p[:, :ks] @ spatial_t  # (N, S)
    vs = p[:, k : k + ks] @ spatial_t
    if has_time:
        u = us.unsqueeze(1) + (p[:, k - 1 : k] * dt).unsqueeze(-1)
        v = vs.unsqueeze(1) + (p[:, 2 * k - 1 :] * dt).unsqueeze(-1)
    else:
        u, v = us.unsqueeze(1), vs.unsqueeze(1)
    return u, v


def ic_rhs_kernel(flat, p, px, py, dx, dy, spatial_t, dt, frame_off, ft, fnorm, gx, gy, w,
                  wp: int, x_lo: float, x_hi: float, y_lo: float, y_hi: float, shift: int,
                  w_img: int, h: int, ks: int, k: int, has_time: bool, znssd: bool,
                  order: int, motion=None, count=None):
    """F(p) = sum_t J_t^T W e_t (N, P), per-frame-mean ZNCC (N,) and the outside flag (N,):
    warp (Eq. 9), sample, criterion and reduction in one function of plain tensor code, so
    torch.compile can fuse it into a few loops over (N, T, S) without temporaries. The fused
    C++ kernel (``native.ic_rhs``) computes the same; the tests compare the two. ``motion``
    (N, T, 2): a known displacement added to the warp of every frame (None: none);
    ``count`` (N,): each row's frames in use, its first ``count[i]`` (the others padding,
    left out of every sum; None: all T)."""
    u, v = linear_displacement(p, spatial_t, dt, ks, k, has_time)
    if motion is not None:
        u = u + motion[..., 0:1]
        v = v + motion[..., 1:2]
    xs = (px.unsqueeze(-1) + dx + u).expand(-1, dt.shape[1], -1)
    ys = (py.unsqueeze(-1) + dy + v).expand(-1, dt.shape[1], -1)
    use = None if count is None else frames_in_use(count, dt.shape[1])  # (N, T)
    if use is None:
        outside = (
            (xs.amin(dim=(1, 2)) < 0) | (xs.amax(dim=(1, 2)) > w_img - 1)
            | (ys.amin(dim=(1, 2)) < 0) | (ys.amax(dim=(1, 2)) > h - 1)
        )
    else:  # the frames in use only
        outside = (((xs.amin(-1) < 0) | (xs.amax(-1) > w_img - 1) | (ys.amin(-1) < 0)
                    | (ys.amax(-1) > h - 1)) & use).any(1)
    g = sample_kernel(flat, xs, ys, frame_off.unsqueeze(-1), wp, x_lo, x_hi, y_lo, y_hi,
                       shift, order, False)
    if znssd:
        g = g - ((g * w).sum(-1) / w.sum()).unsqueeze(-1)
    gg = (g * g * w).sum(-1).clamp(min=1e-30)
    zn = (ft.unsqueeze(1) * g * w).sum(-1) / (fnorm.unsqueeze(1) * gg.sqrt())
    if znssd:
        e = ft.unsqueeze(1) - (fnorm.unsqueeze(1) / gg.sqrt()).unsqueeze(-1) * g  # Pan's scale
    else:
        e = ft.unsqueeze(1) - g
    e = e * w
    if use is not None:
        e = e * use.unsqueeze(-1).to(e.dtype)
        zn = torch.where(use, zn, 0.0).sum(1, keepdim=True) / use.sum(1, keepdim=True)
    e1 = e.sum(1)  # (N, S)
    bx = (gx * e1) @ spatial_t.T
    by = (gy * e1) @ spatial_t.T
    if has_time:
        e2 = (e * dt.unsqueeze(-1)).sum(1)
        b = torch.cat([bx, (gx * e2).sum(1, keepdim=True), by, (gy * e2).sum(1, keepdim=True)], 1)
    else:
        b = torch.cat([bx, by], 1)
    return b, zn.mean(1), outside


def frames_in_use(count: torch.Tensor, t: int) -> torch.Tensor:
    """(N, T) bool: frame t of a row is in use, ``t < count`` (``count`` (N,) the frames in
    use of each row's window, clamped to [1, T]; the later columns are padding)."""
    return (torch.arange(t, device=count.device).unsqueeze(0)
            < count.clamp(1, t).unsqueeze(1))


def ic_rhs_compiled(*args):
    """The same as :func:`ic_rhs_kernel` (a separate function: the key of its compiled
    version)."""
    return ic_rhs_kernel(*args)
