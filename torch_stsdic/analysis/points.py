"""Points of interest (POIs): a regular grid inside a region of interest and a mask, or the
user's own points filtered by them. Coordinates (x, y) px, x = column, y = row, 0-based."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from torch_stsdic.io import InputError, load_series

__all__ = ["grid_points", "filter_points", "check_roi", "load_mask", "nearest_points",
           "nearest_among"]


def check_roi(roi: Any, shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) px of a region of interest, validated against an (H, W) image."""
    h, w = shape
    try:
        x0, y0, x1, y1 = (float(c) for c in roi)
    except (TypeError, ValueError):
        raise ValueError(f"roi: expected (x0, y0, x1, y1) in px, got {roi!r}") from None
    if not all(math.isfinite(c) for c in (x0, y0, x1, y1)) or x1 < x0 or y1 < y0:
        raise ValueError(f"roi: expected finite (x0, y0, x1, y1) with x0 <= x1, y0 <= y1, "
                         f"got {roi!r}")
    if x1 < 0 or y1 < 0 or x0 > w - 1 or y0 > h - 1:
        raise ValueError(
            f"roi {tuple(roi)} is off the image (x 0..{w - 1}, y 0..{h - 1} for {h}x{w} HxW)"
        )
    return x0, y0, x1, y1


def load_mask(mask: Any, shape: tuple[int, int]) -> torch.Tensor:
    """(H, W) bool tensor from a mask array/tensor or image path (non-zero = measure)."""
    if isinstance(mask, (str, os.PathLike)):
        try:
            m = load_series(mask).numpy(0, np.float64)
        except (InputError, OSError) as exc:
            raise ValueError(f"mask: cannot read {mask}: {exc}") from exc
        arr = torch.from_numpy(m != 0)
    else:
        arr = torch.as_tensor(np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor)
                                         else mask))
        if arr.dim() == 3 and arr.shape[0] == 1:
            arr = arr[0]
        arr = arr != 0
    if tuple(arr.shape) != tuple(shape):
        raise ValueError(
            f"mask: shape {tuple(arr.shape)} does not match the images {tuple(shape)} (H, W)"
        )
    return arr


def grid_points(
    shape: tuple[int, int],
    step: int = 10,
    roi: Sequence[float] | None = None,
    mask: Any = None,
    subset_size: int = 21,
    margin: float = 0.0,
) -> torch.Tensor:
    """A regular grid of POIs (N, 2) float64 as (x, y) px.

    The grid has spacing ``step`` px, lies inside ``roi = (x0, y0, x1, y1)`` (inclusive,
    default the whole image) and keeps ``subset_size // 2 + margin`` px from the image
    border so that every subset fits, also after moving by ``margin`` px (the run's
    :func:`~torch_stsdic.movie.plan.grid_margin`: interpolation support + expected motion; less
    where the image is too small to keep it all); it is centred in the available range.
    ``mask``: (H, W) bool/number array or an image path; points where the mask is zero are
    dropped (only the POI itself is tested). Raises ValueError naming ``roi``, ``mask`` or ``step``.
    """
    h, w = int(shape[0]), int(shape[1])
    if not isinstance(step, (int, np.integer)) or step < 1:
        raise ValueError(f"step: must be an integer >= 1 (px), got {step!r}")
    if not (isinstance(margin, (int, float, np.integer, np.floating)) and 0 <= margin < 1e9):
        raise ValueError(f"margin: must be a number >= 0 (px), got {margin!r}")
    # as much of the margin as leaves a point on a small image
    margin = min(int(math.ceil(margin)), max(0, (min(h, w) - 1) // 2 - subset_size // 2))
    half = subset_size // 2 + margin
    x0, y0, x1, y1 = (0.0, 0.0, w - 1.0, h - 1.0) if roi is None else check_roi(roi, (h, w))
    lo_x, hi_x = math.ceil(max(x0, half)), math.floor(min(x1, w - 1 - half))
    lo_y, hi_y = math.ceil(max(y0, half)), math.floor(min(y1, h - 1 - half))
    if lo_x > hi_x or lo_y > hi_y:
        where = "the image" if roi is None else f"roi {tuple(roi)}"
        why = f" (subset/2 + {margin} px for motion)" if margin else ""
        raise ValueError(
            f"no points inside {where}: a subset of {subset_size} px needs a margin of {half} "
            f"px{why} from the {h}x{w} image border"
        )
    xs = torch.arange(lo_x + ((hi_x - lo_x) % step) // 2, hi_x + 1, step, dtype=torch.float64)
    ys = torch.arange(lo_y + ((hi_y - lo_y) % step) // 2, hi_y + 1, step, dtype=torch.float64)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)
    if mask is not None:
        m = load_mask(mask, (h, w))
        pts = pts[m[pts[:, 1].long(), pts[:, 0].long()]]
        if pts.shape[0] == 0:
            raise ValueError(f"no points inside roi/mask: the mask is zero at every grid point "
                             f"(step {step} px)")
    return pts


def filter_points(points: Any, shape, roi, mask) -> torch.Tensor:
    """User POIs (N, 2), kept where inside ``roi`` and ``mask``."""
    pts = torch.as_tensor(np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor)
                                     else points, dtype=np.float64))
    if pts.dim() == 1 and pts.shape[0] == 2:
        pts = pts.unsqueeze(0)
    if pts.dim() != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
        raise ValueError(f"points: expected a non-empty (N, 2) array of (x, y), got shape "
                         f"{tuple(pts.shape)}")
    if not bool(torch.isfinite(pts).all()):
        raise ValueError("points: contains non-finite coordinates")
    h, w = shape
    keep = torch.ones(pts.shape[0], dtype=torch.bool)
    if roi is not None:
        x0, y0, x1, y1 = check_roi(roi, shape)
        keep &= (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    if mask is not None:
        m = load_mask(mask, shape)
        ix = pts[:, 0].round().long().clamp(0, w - 1)
        iy = pts[:, 1].round().long().clamp(0, h - 1)
        keep &= m[iy, ix]
    if not bool(keep.any()):
        raise ValueError("points: no point inside roi/mask")
    return pts[keep]


def nearest_points(points: torch.Tensor, k: int, chunk: int = 4096
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances and indices (N, k) of the ``k`` nearest points of every point of (N, 2)
    ``points`` (itself first, at distance 0), nearest first (:func:`nearest_among` of the
    set among itself)."""
    return nearest_among(points, points, k, chunk)


def nearest_among(query: torch.Tensor, points: torch.Tensor, k: int, chunk: int = 4096
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances and indices (M, k) of the ``k`` points of ``points`` (N, 2) nearest each of
    ``query`` (M, 2), nearest first (``k`` at most N).

    ``points`` are binned into square cells sized so that a 3 x 3 block of cells holds
    ``k`` points at their average density; each query's candidates are the points of the
    block around it, and a query whose k-th candidate lies farther than the block reaches (a
    sparse region, an edge, a query outside the points' extent) is searched among all points
    (the full distance matrix by chunks of ``chunk`` rows). Time and memory O(M k), not
    O(M N): 38,809 POIs among themselves in milliseconds instead of 27 s and 600 MB; among a
    1,000-point sample 13 ms instead of 0.17 s."""
    m, n = query.shape[0], points.shape[0]
    k = min(k, n)
    q, p = query.double(), points.double()
    if m == 0 or k < 1 or n <= 64:
        return _nearest_brute(q, p, k, chunk, points.dtype)
    lo = p.amin(0)
    span = (p.amax(0) - lo).clamp(min=1e-9)
    density = n / float(span[0] * span[1]) if float(span.min()) > 1e-6 else 0.0
    if density <= 0.0:  # all points on a line: the full search
        return _nearest_brute(q, p, k, chunk, points.dtype)
    h = 1.2 * math.sqrt((k + 1) / (math.pi * density))  # k-th neighbour within one cell
    cell = ((p - lo) / h).floor().long()
    gx, gy = int(cell[:, 0].max()) + 1, int(cell[:, 1].max()) + 1
    cid = cell[:, 1] * gx + cell[:, 0]
    order = torch.argsort(cid, stable=True)
    counts = torch.bincount(cid, minlength=gx * gy)
    start = torch.cumsum(counts, 0) - counts
    cmax = int(counts.max())
    if 9 * cmax > 64 * max(k, 8):  # clustered points: cells too full for blocks
        return _nearest_brute(q, p, k, chunk, points.dtype)
    rel = (q - lo) / h
    qcell = rel.floor().clamp(-(2 ** 40), 2 ** 40).long()  # a query's cell (may be off the grid)
    off = torch.tensor([-1, 0, 1], device=p.device)
    ox, oy = torch.meshgrid(off, off, indexing="xy")
    nx = qcell[:, :1] + ox.reshape(1, -1)  # (M, 9)
    ny = qcell[:, 1:] + oy.reshape(1, -1)
    inside = (nx >= 0) & (nx < gx) & (ny >= 0) & (ny < gy)
    ncell = (ny.clamp(0, gy - 1) * gx + nx.clamp(0, gx - 1))
    slot = torch.arange(cmax, device=p.device)
    have = inside.unsqueeze(-1) & (slot < counts[ncell].unsqueeze(-1))  # (M, 9, cmax)
    pos = (start[ncell].unsqueeze(-1) + slot).clamp(max=n - 1)
    cand = torch.where(have, order[pos], -1).reshape(m, -1)  # (M, 9 cmax)
    c = cand.clamp(min=0)
    px, py = p[:, 0].contiguous(), p[:, 1].contiguous()
    d2 = (q[:, :1] - px[c]).square_() + (q[:, 1:] - py[c]).square_()
    d2.masked_fill_(cand < 0, torch.inf)
    dk, pick = torch.topk(d2, min(k, d2.shape[1]), dim=1, largest=False, sorted=True)
    dk = dk.sqrt_()
    ik = torch.gather(cand, 1, pick)
    # exact only where the k-th neighbour is nearer than the block's edge
    frac = rel - qcell.double()  # position in its cell, 0..1
    reach = h * torch.minimum(frac, 1.0 - frac).amin(1) + h
    redo = ~(dk[:, -1] <= reach) if dk.shape[1] == k else torch.ones(m, dtype=torch.bool,
                                                                      device=p.device)
    if bool(redo.any()):
        r = torch.nonzero(redo).flatten()
        dr, ir = _nearest_brute(q[r], p, k, chunk, torch.float64)
        if dk.shape[1] < k:
            dk = torch.full((m, k), torch.inf, dtype=torch.float64, device=p.device)
            ik = torch.full((m, k), -1, dtype=torch.long, device=p.device)
        dk[r], ik[r] = dr, ir
    return dk.to(points.dtype), ik


def _nearest_brute(query: torch.Tensor, points: torch.Tensor, k: int, chunk: int, dtype
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`nearest_among` by the full distance matrix, by chunks of ``chunk`` query rows:
    distances (as ``dtype``) and indices (M, k)."""
    dist, idx = [], []
    for i in range(0, query.shape[0], chunk):
        d = torch.cdist(query[i : i + chunk], points)
        dk, ik = torch.topk(d, k, dim=1, largest=False)
        dist.append(dk)
        idx.append(ik)
    if not dist:
        return (torch.zeros(0, k, dtype=dtype, device=points.device),
                torch.zeros(0, k, dtype=torch.long, device=points.device))
    return torch.cat(dist, 0).to(dtype), torch.cat(idx, 0)
