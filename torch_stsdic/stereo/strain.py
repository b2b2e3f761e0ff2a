"""Surface strain on the 3D points of a stereo result: the Green-Lagrange strain of the
specimen's surface in its own tangent plane, for flat and curved surfaces alike.

The points sit on a grid of the left reference image, so the surface is parameterised by the
image coordinates (s, t) px. At every point the local plane fit over its ``k`` nearest points
(:func:`~torch_stsdic.analysis.local_fit.local_fit_weights`, the slopes) gives the tangent
vectors of the reference surface ``J0 = dX0/d(s, t)`` (3, 2) and of the deformed one
``J = d(X0 + U)/d(s, t)``. In an orthonormal basis (b1, b2) of the reference tangent plane
(b1: the plane frame's X axis, or the camera's x, projected onto it; b2 = n x b1) the tangent
vectors have components ``A = B^T J0`` (2, 2), the right Cauchy-Green tensor is
``C = A^-T (J^T J) A^-1`` and the strain ``E = (C - I) / 2``: exx = E11, eyy = E22 and exy =
E12 (tensor shear, half the engineering shear), dimensionless.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.analysis.local_fit import local_fit_weights

__all__ = ["surface_strain", "STRAIN_FIELDS"]

#: the surface strain fields of a stereo result and their unit
STRAIN_FIELDS = {"exx": "1", "eyy": "1", "exy": "1"}


def surface_strain(points: Tensor, X0: Tensor, U: Tensor, subset_size: float, *,
                   axis: Tensor | None = None, k: int = 9, U_std: Tensor | None = None,
                   U_cov: Tensor | None = None) -> dict[str, Tensor]:
    """Green-Lagrange surface strain at every point and frame.

    Args:
        points: (N, 2) left reference px (the surface's parameters).
        X0: (N, 3) reference shape mm (NaN: not triangulated).
        U: (F, N, 3) displacement mm (NaN: not usable in that frame).
        subset_size: px, for the local fits' neighbour correlation (weights only).
        axis: (3,) the direction b1 follows (projected onto each tangent plane; default the
            camera's x, (1, 0, 0)).
        k: points per local fit (the point and its nearest neighbours; 9: a 3 x 3 block).
        U_std: (F, N, 3) the displacement's predicted std per component, mm (optional).
        U_cov: (F, N, 3, 3) its predicted covariance, mm^2 (optional; used instead of
            ``U_std``: a point's error along b1 or b2 is ``b^T C b``).

    Returns:
        "exx", "eyy", "exy": (F, N) float64; NaN where the point or a neighbour is not
        usable in that frame, or its neighbourhood is degenerate. With ``U_std`` also
        "exx_std", "eyy_std", "exy_std": to first order in the strain, each is a weighted
        sum of the neighbours' displacements along b1 or b2; its variance is ``w^T R w``
        (R: the neighbours' error correlation, their subsets' overlap) times the
        neighbourhood's mean variance along that direction (``b^T C b`` with ``U_cov``, else
        the components taken independent).
    """
    pts = points.double().cpu()
    x0 = X0.double().cpu()
    u = U.double().cpu()
    ok0 = torch.isfinite(x0).all(1)
    fit = local_fit_weights(pts, k, subset_size, valid=ok0, degrees=(1, 2))
    slopes = fit.slopes[1]  # (N, k, 2): d/ds, d/dt of a field from its neighbours' values
    used = fit.used > 0  # (N, k)
    x0n = torch.where(used[..., None], x0[fit.index], 0.0)  # (N, k, 3)
    j0 = torch.einsum("nkc,nkd->ncd", x0n, slopes)  # (N, 3, 2)
    un = u[:, fit.index]  # (F, N, k, 3)
    bad = (~torch.isfinite(un).all(-1) & used).any(-1)  # (F, N) a usable neighbour's U missing
    un = torch.where(used[None, ..., None], torch.nan_to_num(un), 0.0)
    j = j0 + torch.einsum("fnkc,nkd->fncd", un, slopes)  # (F, N, 3, 2)
    n = torch.linalg.cross(j0[..., 0], j0[..., 1])
    n = n / n.norm(dim=-1, keepdim=True)
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) if axis is None else \
        torch.as_tensor(axis, dtype=torch.float64)
    b1 = a - (n @ a)[:, None] * n
    b1 = b1 / b1.norm(dim=-1, keepdim=True)
    b2 = torch.linalg.cross(n, b1)
    basis = torch.stack([b1, b2], -1)  # (N, 3, 2)
    comp = basis.transpose(1, 2) @ j0  # (N, 2, 2) = A
    good = fit.posed[1] & ok0 & torch.isfinite(comp).all((1, 2))
    good &= torch.linalg.det(torch.where(good[:, None, None], comp, torch.eye(2))).abs() > 1e-12
    inv = torch.linalg.inv(torch.where(good[:, None, None], comp, torch.eye(2, dtype=comp.dtype)))
    c = inv.transpose(1, 2) @ (j.transpose(-1, -2) @ j) @ inv  # (F, N, 2, 2)
    e = 0.5 * (c - torch.eye(2, dtype=c.dtype))
    keep = good[None] & ~bad & torch.isfinite(u).all(-1)
    nan = torch.tensor(float("nan"), dtype=torch.float64)
    out = {"exx": torch.where(keep, e[..., 0, 0], nan),
           "eyy": torch.where(keep, e[..., 1, 1], nan),
           "exy": torch.where(keep, e[..., 0, 1], nan)}
    if U_std is not None or U_cov is not None:
        # E ~ sym(B^T dU/d(s,t) A^-1): E11 = sum_j (b1 . U_j) w1_j, w_i = slopes_j @ A^-1[:, i]
        w = slopes @ inv  # (N, k, 2)
        f1 = fit.variance_factor(w[..., 0])  # (N,) w1^T R w1
        f2 = fit.variance_factor(w[..., 1])
        if U_cov is not None:  # b^T C b
            cov = torch.nan_to_num(U_cov.double().cpu(), nan=0.0)  # (F, N, 3, 3)
            along = torch.einsum("nci,fncd,ndi->fni", basis, cov, basis)
        else:  # the components taken independent
            var = torch.nan_to_num(U_std.double().cpu() ** 2, nan=0.0)  # (F, N, 3)
            along = torch.einsum("fnc,nci->fni", var, basis ** 2)
        # along: (F, N, 2) the variance along b1, b2
        # (F, N, 2) the mean over the neighbours the fit uses (one without a 3D point has
        # no tangent basis: NaN, and no weight)
        usedf = used.double()[None, ..., None]
        nb = (torch.nan_to_num(along[:, fit.index]) * usedf).sum(2) / usedf.sum(2).clamp(min=1)
        out["exx_std"] = torch.where(keep, (f1 * nb[..., 0]).sqrt(), nan)
        out["eyy_std"] = torch.where(keep, (f2 * nb[..., 1]).sqrt(), nan)
        out["exy_std"] = torch.where(keep, (0.25 * (f2 * nb[..., 0] + f1 * nb[..., 1])).sqrt(),
                                     nan)
    return out
