"""The point a window's velocity refers to.

The spatio-temporal affine shape function holds the velocity (ut, vt) constant over the
subset. Where the velocity varies in space (a strain rate), the Gauss-Newton solution's ut,
vt are the velocity at the subset's gradient-weighted centroid, not at the POI: over a
window centred on its target, the misfit ``(a dx + b dy) dt`` of a velocity gradient
(``a = d ut / dx`` ...) projects onto the ut, vt columns only (the frames' ``sum dt = 0``
keeps it off u and the gradients), through the subset's gradient moments

    [ut, vt] bias = M^-1 [[Xxx, Yxx, Xxy, Yxy], [Xxy, Yxy, Xyy, Yyy]] [a, b, c, d]

with ``M = [[Sxx, Sxy], [Sxy, Syy]]``, ``Sxx = sum w gx^2``, ``Xxx = sum w gx^2 dx``,
``Yxx = sum w gx^2 dy``, ``Xxy = sum w gx gy dx`` ... over the reference subset (``w`` the
subset window, ``gx``, ``gy`` the reference's gradients, ``dx``, ``dy`` the pixel offsets)
and ``(a, b, c, d) = (d ut/dx, d ut/dy, d vt/dx, d vt/dy)``. On a speckle the centroid lies
about 1 px from the centre (21 px subsets), so a strain rate of 4e-4 per frame gave every
point a velocity error of ~4e-4 px/frame, constant in time and independent of the window's
length (the linear render's m = 6 velocity: random / predicted 1.32).
:func:`velocity_maps` works the map out once per POI (the run's reference is fixed);
:func:`refer_to_points` takes the bias out of a block's velocities, the velocity gradients
from plane fits of the block's own ut, vt over the grid neighbours (as the strain rates)."""

from __future__ import annotations

from typing import Any

import torch

from torch_stsdic.analysis.result import USABLE
from torch_stsdic.analysis.strain import compute_strain
from torch_stsdic.kernels.linalg import sym2_pinv
from torch_stsdic.movie.frames import true_rows

#: a :class:`~torch_stsdic.movie.block.Block` (not imported: the block imports this module)
Block = Any

__all__ = ["velocity_maps", "map_offsets", "refer_to_points", "refer_velocities", "MAP_CHUNK"]

#: POIs whose subsets :func:`velocity_maps` samples at once
MAP_CHUNK = 2048


def velocity_maps(img: Any, points: torch.Tensor, offsets: torch.Tensor,
                  weights: torch.Tensor, inside: bool = False) -> torch.Tensor:
    """(N, 2, 4) float64 per POI: the (ut, vt) bias a velocity gradient (d ut/dx, d ut/dy,
    d vt/dx, d vt/dy) gives a window's solution (module docstring), from the reference
    ``img`` (a :class:`~torch_stsdic.core.interpolation.BSplineImage`) at ``points`` (N, 2)
    px, the subset's ``offsets`` (S, 2) px (dx, dy) and ``weights`` (S,) (``M``'s
    pseudo-inverse: zero where the subset has no texture, along an axis without it).
    ``inside``: every point is a whole pixel whose subset lies inside the image (known to
    the caller: not read)."""
    return _maps(img, points, *map_offsets(img, points.device, offsets, weights), inside)


def map_offsets(img: Any, device: torch.device, offsets: torch.Tensor, weights: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`velocity_maps`'s subset columns on ``device``: dx, dy (S,) in ``img``'s dtype
    and the weights (S,) float64 (kept by a caller that maps again: the same tensors let
    the image's sampling keep its facts of them)."""
    return (offsets[:, 0].to(device=device, dtype=img.dtype),
            offsets[:, 1].to(device=device, dtype=img.dtype),
            weights.to(device=device, dtype=torch.float64))


def _maps(img: Any, points: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor,
          w: torch.Tensor, inside: bool) -> torch.Tensor:
    """:func:`velocity_maps` from :func:`map_offsets`'s columns."""
    ox, oy = dx.double(), dy.double()
    out = torch.zeros(points.shape[0], 2, 4, dtype=torch.float64, device=points.device)
    for i0 in range(0, points.shape[0], MAP_CHUNK):
        p = points[i0:i0 + MAP_CHUNK].to(img.dtype)
        _, gx, gy = img.sample_subsets(p[:, 0], p[:, 1], dx, dy, inside=inside)
        gx, gy = gx.double(), gy.double()
        xx, xy, yy = w * gx * gx, w * gx * gy, w * gy * gy  # (n, S)
        m = torch.stack([torch.stack([xx.sum(1), xy.sum(1)], -1),
                         torch.stack([xy.sum(1), yy.sum(1)], -1)], -2)  # (n, 2, 2)
        rhs = torch.stack([
            torch.stack([xx @ ox, xx @ oy, xy @ ox, xy @ oy], -1),
            torch.stack([xy @ ox, xy @ oy, yy @ ox, yy @ oy], -1)], -2)  # (n, 2, 4)
        # a texture along one axis only: that component's map alone (none where flat)
        out[i0:i0 + MAP_CHUNK] = sym2_pinv(m, 1e-9) @ rhs  # (no wait for a GPU)
    return out


def refer_to_points(points: torch.Tensor, maps: torch.Tensor, ut: torch.Tensor,
                    vt: torch.Tensor, valid: torch.Tensor, shift: torch.Tensor | None = None,
                    window: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """The velocities ``ut``, ``vt`` (B, N) of windows at ``points`` (N, 2) referred to the
    points: each target's velocity gradients from plane fits of its ``valid`` (B, N) rows'
    ut, vt over ``window`` x ``window`` grid neighbours
    (:func:`~torch_stsdic.analysis.strain.compute_strain`), times each row's ``maps``
    ((N, 2, 4) or (B, N, 2, 4): :func:`velocity_maps`; plus ``shift`` (B, N, 2) px, the
    subset's centre minus the point where it was moved off it), taken off. Rows without a
    velocity (NaN) or a gradient (too few neighbours) are returned as they are."""
    ok = valid & torch.isfinite(ut) & torch.isfinite(vt)
    g = compute_strain(points, ut.double(), vt.double(), window=window, kind="small",
                       valid=ok, return_gradients=True)
    grad = torch.stack([g["ux"], g["uy"], g["vx"], g["vy"]], -1)  # (B, N, 4)
    bias = (maps.to(grad) @ grad.unsqueeze(-1)).squeeze(-1)  # (B, N, 2)
    if shift is not None:  # the subset's centre: the velocity there, not at the point
        s = shift.to(grad)
        bias = bias + torch.stack([grad[..., 0] * s[..., 0] + grad[..., 1] * s[..., 1],
                                   grad[..., 2] * s[..., 0] + grad[..., 3] * s[..., 1]], -1)
    bias = torch.where(torch.isfinite(bias), bias, 0.0)
    return ut - bias[..., 0].to(ut), vt - bias[..., 1].to(vt)


def refer_velocities(blk: Block, out: dict[str, torch.Tensor]) -> None:
    """A block's velocities ``out["ut"]``, ``out["vt"]`` (B, N) referred to its POIs, in
    place (:func:`refer_to_points`; the reference's maps worked out once, kept on it; rows
    whose subset :meth:`~torch_stsdic.movie.block_placement.BlockPlacement.keep_outside`
    moved off the POI take the maps at the subset's centre and the shift)."""
    run, ref = blk.run, blk.ref
    if "ut" not in out or run.m == 0 or ref.img is None:
        return
    if ref.map_offsets is None:  # (made once: the image's sampling keeps its facts)
        ref.map_offsets = map_offsets(ref.img, ref.points.device,
                                      *run.solver.window.offsets_and_weights())
    on_grid, inside = run.point_facts(ref)  # (known per run: not read)
    if ref.velocity_maps is None:
        ref.velocity_maps = _maps(ref.img, ref.points, *ref.map_offsets, on_grid and inside)
    b, n = out["ut"].shape
    maps, shift = ref.velocity_maps, None
    if blk.centres is not None and blk.off_count:  # (counted where they were moved)
        moved = true_rows((blk.centres != blk.pts).any(1), blk.off_count)
        maps = maps.repeat(b, 1, 1)
        # the moved centres are whole pixels where the POIs are (moved by whole pixels)
        maps[moved] = _maps(ref.img, blk.centres[moved], *ref.map_offsets,
                            on_grid and blk.centres_inside)
        maps = maps.view(b, n, 2, 4)
        shift = (blk.centres - blk.pts).view(b, n, 2)
    out["ut"], out["vt"] = refer_to_points(ref.points, maps, out["ut"], out["vt"],
                                           out["status"] <= USABLE, shift)
