"""Small dense linear algebra shared by the solver and the uncertainty: batched inverses of
symmetric positive definite matrices (the Gauss-Newton Hessians, 6 to 12 parameters)."""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.kernels import dispatch, native

__all__ = ["spd_inverse"]


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
