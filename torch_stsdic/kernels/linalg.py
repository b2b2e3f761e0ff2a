"""Small dense linear algebra shared by the solver and the uncertainty: batched inverses of
symmetric positive definite matrices (the Gauss-Newton Hessians, 6 to 12 parameters) and
pseudo-inverses of symmetric 2 x 2 ones, with no host synchronisation on a GPU (torch's
``linalg.inv``, ``solve``, ``pinv`` check their LAPACK / cuSOLVER results on the host)."""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.kernels import dispatch, native

__all__ = ["spd_inverse", "sym2_pinv"]


def spd_inverse(h: Tensor) -> tuple[Tensor, Tensor]:
    """The inverses (N, P, P) of symmetric positive definite matrices ``h`` (N, P, P) (their
    lower triangle read), by Cholesky, and (N,) bool: where ``h`` is not positive definite
    (its inverse NaN). On the CPU the native kernel (P <= 16; torch's batched Cholesky
    calls cost ~15x more for 6x6 matrices), elsewhere torch."""
    if dispatch.spd_inverse(h) == "native":
        return native.spd_inverse(h)
    chol, info = torch.linalg.cholesky_ex(h)
    bad = info != 0  # singular rows replaced by the identity (no host synchronisation)
    eye = torch.eye(h.shape[-1], dtype=h.dtype, device=h.device)
    inv = torch.cholesky_inverse(torch.where(bad.view(-1, 1, 1), eye, chol))
    return inv.masked_fill(bad.view(-1, 1, 1), float("nan")), bad


def sym2_pinv(m: Tensor, rtol: float) -> Tensor:
    """The pseudo-inverses (..., 2, 2) of symmetric positive semi-definite 2 x 2 matrices
    ``m`` (..., 2, 2): their eigenvalues below ``rtol`` times the largest taken as 0 (as
    ``torch.linalg.pinv(m, rtol=rtol)``, whose singular values these are, to rounding;
    0 for a zero matrix), in closed form: the eigenvectors at the angle ``atan2(2 b,
    a - c) / 2``; NaN where ``m`` is not finite. Element-wise operations only: no host
    synchronisation on a GPU (``pinv``'s decomposition checks its result on the host)."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
    finite = torch.isfinite(m).all(-1).all(-1)  # (NaN where m is not finite)
    theta = 0.5 * torch.atan2(2.0 * b, a - c)
    cs, sn = torch.cos(theta), torch.sin(theta)
    l1 = a * cs * cs + 2.0 * b * sn * cs + c * sn * sn  # along (cs, sn): the larger
    l2 = a * sn * sn - 2.0 * b * sn * cs + c * cs * cs  # along (-sn, cs)
    top = torch.maximum(l1.abs(), l2.abs())
    keep1, keep2 = l1.abs() > rtol * top, l2.abs() > rtol * top
    i1 = torch.where(keep1, 1.0 / torch.where(keep1, l1, 1.0), 0.0)
    i2 = torch.where(keep2, 1.0 / torch.where(keep2, l2, 1.0), 0.0)
    v = torch.stack([torch.stack([cs, -sn], -1), torch.stack([sn, cs], -1)], -2)  # columns
    out = v @ torch.diag_embed(torch.stack([i1, i2], -1)) @ v.transpose(-1, -2)
    return torch.where(finite[..., None, None], out, float("nan"))
