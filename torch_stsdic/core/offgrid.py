"""Points off the pixel grid at the error of points on it.

A subset centred between pixels samples the reference's B-spline at sub-pixel positions; the
prefilter amplifies the reference's high-frequency noise there, so the part of the error that
the reference's noise causes grows (by ~1/3 for cubic B-splines). Like OpenCorr and Ncorr,
the solver therefore solves the subset centred on the nearest pixel and carries the result to
the requested point with the measured shape function (a Taylor shift of the polynomial:
exact for the affine and quadratic shapes). All operations are plain differentiable torch.

The same carry serves a subset centred away from its point on purpose: one moved inside the
image where the point nears the border (``SubsetSolver.solve(centres=)``), the point's
displacement then extrapolated from the subset's gradients, its predicted std with them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

__all__ = ["snap_points", "carry_params", "carry_std", "carry_solution"]


def snap_points(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) points (x, y) px -> (nearest pixel centres (N, 2), offsets point - pixel (N, 2))
    (the pixel centres carry no gradient)."""
    grid = torch.round(points.detach())
    return grid, points - grid


def carry_params(params: torch.Tensor, names: Sequence[str], offset: torch.Tensor) -> torch.Tensor:
    """Shape-function parameters (..., N, P) measured at pixel centres, carried to the points
    at ``offset`` (N, 2) px from them: every component's spatial polynomial re-expanded about
    the new centre (u += ux dx + uy dy + uxx dx^2/2 + uxy dx dy + uyy dy^2/2; ux += uxx dx +
    uxy dy; uy += uxy dx + uyy dy; second-order and temporal terms unchanged)."""
    idx = {nm: i for i, nm in enumerate(names)}
    dx, dy = offset[:, 0].to(params.dtype), offset[:, 1].to(params.dtype)
    out = params.clone()  # only the changed columns written (few operations a call: a
    # solve carries four parameter sets, and each operation is a launch on a GPU)

    def col(nm: str) -> torch.Tensor | None:
        return params[..., idx[nm]] if nm in idx else None

    for c in ("u", "v"):
        if c not in idx:
            continue
        gx, gy, gxx, gxy, gyy = (col(c + t) for t in ("x", "y", "xx", "xy", "yy"))
        # the terms in a fixed order, absent coefficients (zero) left out
        terms = [(gx, dx), (gy, dy), (None if gxx is None else 0.5 * gxx * dx, dx),
                 (None if gxy is None else gxy * dx, dy),
                 (None if gyy is None else 0.5 * gyy * dy, dy)]
        val = params[..., idx[c]]
        for g, d in terms:
            if g is not None:
                val = val + g * d
        out[..., idx[c]] = val
        for t, (ga, da), (gb, db) in (("x", (gxx, dx), (gxy, dy)), ("y", (gxy, dx), (gyy, dy))):
            if c + t in idx and (ga is not None or gb is not None):
                val = params[..., idx[c + t]]
                for g, d in ((ga, da), (gb, db)):
                    if g is not None:
                        val = val + g * d
                out[..., idx[c + t]] = val
    return out


def carry_std(std: torch.Tensor, names: Sequence[str], offset: torch.Tensor) -> torch.Tensor:
    """Predicted standard deviations (N, P) carried with :func:`carry_params` by ``offset``
    (N, 2) px: u's becomes sqrt(sd_u^2 + (dx sd_ux)^2 + (dy sd_uy)^2) (v alike), the
    covariance of a centred subset's displacement and gradients neglected (zero for a
    symmetric window over an isotropic texture); the others unchanged."""
    idx = {nm: i for i, nm in enumerate(names)}
    dx, dy = offset[:, 0].to(std.dtype), offset[:, 1].to(std.dtype)
    out = std.clone()  # only the changed columns written
    for c in ("u", "v"):
        if c not in idx:
            continue
        var = std[:, idx[c]] ** 2
        for t, d in (("x", dx), ("y", dy)):
            if c + t in idx:
                var = var + (d * std[:, idx[c + t]]) ** 2
        out[:, idx[c]] = var.sqrt()
    return out


def carry_solution(sol, points: torch.Tensor, offset: torch.Tensor,
                   snapped: int | None = None):
    """A :class:`~torch_stsdic.core.solver.WindowSolution` solved at subset centres, carried to
    ``points`` (N, 2) = centres + ``offset``: parameters (also the first-stage and initial
    ones in ``info``) re-expanded, the predicted std carried (:func:`carry_std`; for a
    snap to the pixel grid, |offset| <= 0.5 px, a second-order share). ``snapped``: the
    count of points snapped to a pixel (``info["snapped_to_pixels"]``) where the caller
    knows it (None: the points with an offset, read on the host)."""
    names = sol.param_names
    info = dict(sol.info)
    # the solution's and the info's parameter sets carried together (one pass of operations)
    keys = [k for k in ("first_stage_params", "initial_params")
            if isinstance(info.get(k), torch.Tensor) and info[k].shape == sol.params.shape
            and info[k].dtype == sol.params.dtype]
    carried = carry_params(torch.stack([sol.params, *(info[k] for k in keys)]), names, offset)
    for key, val in zip(keys, carried[1:]):
        info[key] = val
    for key in ("first_stage_params", "initial_params"):  # (of another dtype: apart)
        val = info.get(key)
        if key not in keys and isinstance(val, torch.Tensor) and val.shape == sol.params.shape:
            info[key] = carry_params(val, names, offset)
    info["snapped_to_pixels"] = (int((offset != 0).any(1).sum()) if snapped is None
                                 else int(snapped))
    std = None if sol.std is None else carry_std(sol.std, names, offset)
    return dataclasses.replace(sol, points=points, params=carried[0], std=std, info=info)
