"""Initial guesses: batched FFT cross-correlation (integer + parabolic sub-pixel peak), and
seeds: one POI per cell whose solution starts its neighbours.

For every POI the reference subset is correlated with a search area of half-width
``search_radius`` around the same position in the deformed image, all POIs (and all frames)
at once with ``torch.fft``. The correlation is zero-normalised (ZNCC), so intensity offset
and scale between images do not matter.
"""

from __future__ import annotations

from functools import partial

import torch

from torch_stsdic.core import choices
from torch_stsdic.core.config import gpu_budget_mb
from torch_stsdic.core.interpolation import window_view
from torch_stsdic.core.pyramid import PyramidStack
from torch_stsdic.kernels.native.rows import own_threads, run_tasks, threads

#: MiB the FFT search's working arrays may take at once, over all threads
#: (:func:`fft_cross_correlation`; measured: about 6 padded search regions of float32 a
#: POI-frame pair in flight)
FFT_MEMORY_MB = 64.0
#: the padded search regions' bytes a POI-frame pair holds in flight, in element sizes
_PAIR_REGIONS = 6

__all__ = ["fft_cross_correlation", "coarse_to_fine", "linear_fit_in_time", "seed_cells",
           "carry_from_seed", "retry_weak_peaks", "walk_weak_frames"]


def _regions(
    img: torch.Tensor, index: torch.Tensor, cx: torch.Tensor, cy: torch.Tensor, size: int
) -> torch.Tensor:
    """Square regions (N, T, size, size) of images ``img[index]`` (img (F, H, W), index
    (N, T)), top-left at (cx, cy) ints, (N,) (the same for every frame) or (N, T), zero
    outside the image. Regions inside the image are gathered from a strided view of all
    size x size windows (no index arithmetic per pixel); the others by :func:`_regions_clamped`
    (the same numbers); on a GPU every one by it (no host read:
    :data:`~torch_stsdic.core.choices.SEARCH_READS`)."""
    _, h, w = img.shape
    n, t = index.shape
    x0 = cx.reshape(cx.shape[0], -1).expand(n, t)
    y0 = cy.reshape(cy.shape[0], -1).expand(n, t)
    if h < size or w < size or not choices.search_reads(img.device):
        return _regions_clamped(img, index, cx, cy, size)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + size <= w) & (y0 + size <= h)
    win = window_view(img, size, size)
    if bool(inside.all()):
        return win[index, y0, x0]
    out = img.new_empty(n, t, size, size)
    out[inside] = win[index[inside], y0[inside], x0[inside]]
    rest = ~inside
    out[rest] = _regions_clamped(img, index[rest].view(-1, 1), x0[rest], y0[rest], size)[:, 0]
    return out


def _regions_clamped(
    img: torch.Tensor, index: torch.Tensor, cx: torch.Tensor, cy: torch.Tensor, size: int
) -> torch.Tensor:
    """:func:`_regions` by index arithmetic on clamped coordinates, zero outside the image
    (cx, cy (N,) or (N, T) as there)."""
    _, h, w = img.shape
    r = torch.arange(size, device=img.device)
    cy = cy.reshape(cy.shape[0], -1)  # (N, 1) or (N, T)
    cx = cx.reshape(cx.shape[0], -1)
    rows = cy.unsqueeze(-1) + r  # (N, 1 or T, size)
    cols = cx.unsqueeze(-1) + r
    valid = ((rows >= 0) & (rows < h)).unsqueeze(-1) & ((cols >= 0) & (cols < w)).unsqueeze(-2)
    rows = rows.clamp(0, h - 1)
    cols = cols.clamp(0, w - 1)
    flat = rows.unsqueeze(-1) * w + cols.unsqueeze(-2)  # (N, 1 or T, size, size)
    flat = flat + (index * (h * w)).view(*index.shape, 1, 1)  # (N, T, size, size)
    out = img.reshape(-1).take(flat)
    return out * valid.to(out.dtype)


def _box_sum(a: torch.Tensor, k: int) -> torch.Tensor:
    """Sums over all k x k windows of a (..., L, L) -> (..., L-k+1, L-k+1)."""
    c = torch.nn.functional.pad(a.cumsum(-1).cumsum(-2), (1, 0, 1, 0))
    return c[..., k:, k:] - c[..., :-k, k:] - c[..., k:, :-k] + c[..., :-k, :-k]


def _fast_size(n: int) -> int:
    """Smallest m >= n whose prime factors are 2, 3 and 5 (fast FFT lengths)."""
    m = n
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def _batch_size(n: int, most: int, device: torch.device) -> int:
    """POIs per FFT batch: at most ``most``, and on the CPU, for the library's threads
    (:func:`~torch_stsdic.kernels.native.rows.run_tasks`), a multiple of that many batches of
    at least 64 POIs where ``most`` allows (each POI's numbers do not depend on its
    batch)."""
    k = threads() if device.type == "cpu" else 1
    if k == 1 or n < 128:
        return min(n, most) if n else most
    batches = -(-n // most)
    batches = min(-(-batches // k) * k, max(1, n // min(64, most)))
    return max(1, -(-n // batches))


def _at(flat, iy, ix, di: int, dj: int, k: int) -> torch.Tensor:
    """Correlation at the integer peak moved by (di, dj), clamped to the search grid."""
    yy = (iy + di).clamp(0, k - 1)
    xx = (ix + dj).clamp(0, k - 1)
    return flat.gather(-1, (yy * k + xx).unsqueeze(-1))[..., 0]


def _parabola(lo, mid, hi, i, k: int) -> torch.Tensor:
    """Sub-pixel offset of a 3-point parabola peak (0 at the search border)."""
    den = lo - 2.0 * mid + hi
    off = torch.where(den < -1e-12, 0.5 * (lo - hi) / den.clamp(max=-1e-12), 0.0 * den)
    edge = (i == 0) | (i == k - 1) | (lo < -1.5) | (hi < -1.5)
    return torch.where(edge, torch.zeros_like(off), off.clamp(-0.5, 0.5))


@torch.no_grad()
def fft_cross_correlation(
    ref: torch.Tensor,
    images: torch.Tensor,
    points: torch.Tensor,
    subset_size: int,
    search_radius: int,
    *,
    frame_index: torch.Tensor | None = None,
    ref_index: torch.Tensor | None = None,
    prior: torch.Tensor | None = None,
    batch: int = 4096,
    memory_mb: float = FFT_MEMORY_MB,
    gpu_floor: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Displacement of each POI from ``ref`` (H, W) to each of ``images`` (T, H, W), by
    batches of at most ``batch`` POI-frame pairs whose working arrays (all threads'
    batches at once) stay within ``memory_mb`` MiB (on a GPU at least
    :func:`~torch_stsdic.core.config.gpu_budget_mb` with ``gpu_floor``: False where the run
    was given a memory budget, ``DICConfig.memory_mb``).

    Args:
        points: (N, 2) POI positions (x, y) in px (rounded to the nearest pixel here).
        subset_size: odd subset width in px.
        search_radius: largest |u|, |v| searched, px.
        frame_index: optional (N, T) indices into ``images`` per POI (default: all frames).
        ref_index: optional (N,) index into ``ref`` given as (R, H, W) per POI.
        prior: optional (N, T, 2) displacement (px, rounded) around which to search.

    Returns:
        disp: (N, T, 2) displacement (u, v) in px, integer peak refined by a parabola fit.
        zncc: (N, T) ZNCC at the integer peak (-1 where nothing valid was found).
    """
    if images.dim() == 2:
        images = images.unsqueeze(0)
    if ref.dim() == 2:
        ref = ref.unsqueeze(0)
    n = points.shape[0]
    dev = images.device
    if frame_index is None:
        frame_index = torch.arange(images.shape[0], device=dev).expand(n, -1)
    if ref_index is None:
        ref_index = torch.zeros(n, dtype=torch.long, device=dev)
    dtype = torch.float32 if images.dtype != torch.float64 else torch.float64
    ref = ref.to(dtype)
    images = images.to(dtype)
    t_count = frame_index.shape[1]
    _, h, w = images.shape
    half = subset_size // 2
    rad = int(search_radius)
    size = subset_size + 2 * rad
    fast = _fast_size(size)  # zero padding beyond `size` leaves shifts 0..2R unwrapped
    npix = subset_size * subset_size
    cx = torch.round(points[:, 0]).long()
    cy = torch.round(points[:, 1]).long()
    if prior is not None:
        prior = torch.round(prior).long().expand(n, t_count, 2)
    disp = torch.zeros(n, t_count, 2, dtype=dtype, device=images.device)
    score = torch.full((n, t_count), -1.0, dtype=dtype, device=images.device)
    shifts = torch.arange(-rad, rad + 1, device=images.device)
    # the pairs in flight within FFT_MEMORY_MB (all threads' batches at once; a GPU's own
    # budget where larger: the same numbers in fewer batches, each with its launches)
    pair_bytes = _PAIR_REGIONS * fast * fast * torch.finfo(dtype).bits // 8
    in_flight = threads() if dev.type == "cpu" else 1
    gpu_mb = gpu_budget_mb(dev) if gpu_floor else None
    memory_mb = memory_mb if gpu_mb is None else max(memory_mb, gpu_mb)
    pairs = min(batch, max(1, int(memory_mb * 2**20 / (pair_bytes * in_flight))))
    per_batch = _batch_size(n, max(1, pairs // max(1, t_count)), dev)

    def one(sl: slice) -> None:
        bx, by = cx[sl], cy[sl]
        f = _regions(ref, ref_index[sl].view(-1, 1), bx - half, by - half, subset_size)[:, 0]
        f = f - f.mean(dim=(-1, -2), keepdim=True)
        fnorm = f.square().sum(dim=(-1, -2)).sqrt()  # (B,)
        # search centre: the prior per frame (B, T), or none: (B, 1) for all frames
        qx, qy = (0, 0) if prior is None else (prior[sl, :, 0], prior[sl, :, 1])
        ox, oy = bx.view(-1, 1) + qx, by.view(-1, 1) + qy
        g = _regions(images, frame_index[sl], ox - half - rad, oy - half - rad, size)
        ff = torch.fft.rfft2(f, s=(fast, fast))
        gg = torch.fft.rfft2(g, s=(fast, fast))
        corr = torch.fft.irfft2(torch.conj(ff).unsqueeze(1) * gg, s=(fast, fast))
        corr = corr[..., : 2 * rad + 1, : 2 * rad + 1]
        s1 = _box_sum(g, subset_size)
        s2 = _box_sum(g * g, subset_size)
        var = (s2 - s1 * s1 / npix).clamp(min=0.0)
        denom = fnorm.view(-1, 1, 1, 1) * var.sqrt()
        zn = torch.where(denom > 1e-12, corr / denom.clamp(min=1e-30), torch.full_like(corr, -1.0))
        # shifts whose subset leaves the image are invalid
        sx = ox.unsqueeze(-1) + shifts  # (B, T or 1, 2R+1)
        sy = oy.unsqueeze(-1) + shifts
        okx = ((sx - half) >= 0) & ((sx + half) < w)
        oky = ((sy - half) >= 0) & ((sy + half) < h)
        ok = oky.unsqueeze(-1) & okx.unsqueeze(-2)  # (B, T or 1, 2R+1 rows, 2R+1 cols)
        zn = torch.where(ok, zn, torch.full_like(zn, -2.0))
        k = 2 * rad + 1
        best = zn.reshape(zn.shape[0], t_count, -1).argmax(-1)  # (B, T)
        iy = best // k
        ix = best % k
        peak = zn.reshape(zn.shape[0], t_count, -1).gather(-1, best.unsqueeze(-1)).squeeze(-1)

        flat = zn.reshape(zn.shape[0], t_count, -1)
        sub_x = _parabola(_at(flat, iy, ix, 0, -1, k), peak, _at(flat, iy, ix, 0, 1, k), ix, k)
        sub_y = _parabola(_at(flat, iy, ix, -1, 0, k), peak, _at(flat, iy, ix, 1, 0, k), iy, k)
        disp[sl, :, 0] = (ix - rad + qx).to(dtype) + sub_x
        disp[sl, :, 1] = (iy - rad + qy).to(dtype) + sub_y
        score[sl] = torch.where(peak > -1.5, peak, torch.full_like(peak, -1.0))

    with own_threads(dev):
        run_tasks([partial(one, slice(s0, min(n, s0 + per_batch)))
                   for s0 in range(0, n, per_batch)])
    return disp, score


@torch.no_grad()
def coarse_to_fine(
    ref: torch.Tensor,
    images: torch.Tensor,
    points: torch.Tensor,
    subset_size: int,
    search_radius: int,
    levels: int,
    *,
    frame_index: torch.Tensor | None = None,
    ref_index: torch.Tensor | None = None,
    refine_radius: int = 3,
    pyramids: tuple[PyramidStack, PyramidStack] | None = None,
    gpu_floor: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`fft_cross_correlation` over an image pyramid, for large motions (``gpu_floor``
    as there).

    At the coarsest of ``levels`` halvings the subsets (``subset_size`` px there, i.e. a
    region 2^levels times wider) are searched within ``search_radius`` px, reaching
    ``search_radius * 2^levels`` px at full resolution; every finer level searches
    ``refine_radius`` px around the doubled estimate of the level above. ``pyramids``: the
    pyramids of ``ref`` and ``images`` (:class:`~torch_stsdic.core.pyramid.PyramidStack`, in
    their order) kept by the caller, so that an image's levels are built once however often
    it is searched; default: built here. Only the images the POIs read are stacked. Returns
    (disp (N, T, 2) px, zncc (N, T)) at full resolution, as :func:`fft_cross_correlation`.
    """
    if images.dim() == 2:
        images = images.unsqueeze(0)
    if ref.dim() == 2:
        ref = ref.unsqueeze(0)
    n, dev = points.shape[0], images.device
    if frame_index is None:
        frame_index = torch.arange(images.shape[0], device=dev).expand(n, -1)
    if ref_index is None:
        ref_index = torch.zeros(n, dtype=torch.long, device=dev)
    ref_pyr, img_pyr = pyramids if pyramids is not None else (PyramidStack.of(ref),
                                                               PyramidStack.of(images))
    if len(ref_pyr) != ref.shape[0] or len(img_pyr) != images.shape[0]:
        raise ValueError(f"coarse_to_fine: pyramids of {len(ref_pyr)} and {len(img_pyr)} "
                         f"images for {ref.shape[0]} and {images.shape[0]}")
    # the images read, once each, and the POIs' indices into them
    f_used, f_idx = torch.unique(frame_index, return_inverse=True)
    r_used, r_idx = torch.unique(ref_index, return_inverse=True)
    refs, imgs = ref_pyr.levels(levels, r_used), img_pyr.levels(levels, f_used)
    disp = None
    score = None
    for lev in range(levels, -1, -1):
        scale = 2.0**lev
        pts = (points + 0.5) / scale - 0.5  # pixel centres under pyrdown (align_corners off)
        prior = None if disp is None else torch.round(2.0 * disp)
        disp, score = fft_cross_correlation(
            refs[lev], imgs[lev], pts, subset_size, search_radius if disp is None else
            refine_radius, frame_index=f_idx, ref_index=r_idx, prior=prior,
            gpu_floor=gpu_floor)
    return disp, score


def linear_fit_in_time(
    disp: torch.Tensor, dt: torch.Tensor, weights: torch.Tensor | None = None,
    spread: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares line through per-frame displacements.

    disp (N, T, 2), dt (T,) or (N, T) frame times relative to the expansion time. Returns
    the displacement at dt = 0 (N, 2) and the velocity (N, 2) in px per time unit.
    ``spread``: the caller knows that every row's times differ (a window of distinct
    frames), so they are not tested on the host."""
    dt = dt.expand(disp.shape[0], -1) if dt.dim() == 1 else dt
    if disp.shape[1] == 1 or (not spread and float((dt.amax(1) - dt.amin(1)).min()) == 0.0):
        return disp[:, 0], torch.zeros_like(disp[:, 0])
    w = torch.ones_like(disp[..., 0]) if weights is None else weights.clamp(min=1e-6)
    sw = w.sum(1)
    tm = (w * dt).sum(1) / sw  # (N,)
    dm = (w.unsqueeze(-1) * disp).sum(1) / sw.unsqueeze(-1)  # (N, 2)
    dtc = dt - tm.view(-1, 1)  # (N, T)
    slope = (w.unsqueeze(-1) * dtc.unsqueeze(-1) * (disp - dm.unsqueeze(1))).sum(1) / (
        (w * dtc * dtc).sum(1).unsqueeze(-1)
    )
    return dm - slope * tm.unsqueeze(-1), slope


def seed_cells(
    points: torch.Tensor, group: torch.Tensor, spacing: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Split POIs into square cells of ``spacing`` px (separately per ``group``) and pick
    each cell's seed: the POI nearest the cell centre.

    Args:
        points: (N, 2) POIs (x, y), px.
        group: (N,) int64 group label (POIs of different groups never share a seed, e.g.
            different frames or references).

    Returns:
        cell: (N,) cell number of every POI, 0 .. C-1.
        seeds: (C,) index of each cell's seed POI.
    """
    cxy = torch.floor(points.double() / spacing).long()
    cxy = cxy - cxy.amin(0)
    span = cxy.amax(0) + 1
    key = (group.long() * span[1] + cxy[:, 1]) * span[0] + cxy[:, 0]
    _, cell = torch.unique(key, return_inverse=True)
    centre = (cxy.double() + 0.5) * spacing
    dist = (points.double() - centre).square().sum(1)
    order = torch.argsort(dist, stable=True)
    cell_sorted, order2 = torch.sort(cell[order], stable=True)
    perm = order[order2]
    first = torch.ones_like(cell_sorted, dtype=torch.bool)
    first[1:] = cell_sorted[1:] != cell_sorted[:-1]
    return cell, perm[first]


def carry_from_seed(shape, params: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Initial parameters (N, P) at POIs ``offset`` (N, 2) px away from seeds with solved
    ``params`` (N, P): the seed's displacement polynomial evaluated at the offset; gradients
    and velocities are the seed's."""
    b = shape.spatial_basis(offset[:, 0], offset[:, 1]).to(params.dtype)  # (N, Ks)
    ks, k = b.shape[1], shape.n_basis
    out = params.clone()
    out[:, 0] = (params[:, :ks] * b).sum(1)
    out[:, k] = (params[:, k : k + ks] * b).sum(1)
    return out


def retry_weak_peaks(d: torch.Tensor, score: torch.Tensor, ref_pixels: torch.Tensor,
                     frame_pixels: torch.Tensor, points: torch.Tensor,
                     frame_index: torch.Tensor, ref_index: torch.Tensor, subset_size: int,
                     search_radius: int,
                     pyramids: tuple[PyramidStack, PyramidStack] | None = None,
                     gpu_floor: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the full-resolution search found no clear peak (ZNCC < 0.8, or the peak on
    the border of the search area: the motion may be larger than ``search_radius``),
    search again over an image pyramid (:func:`~torch_stsdic.core.initial.coarse_to_fine`;
    ``pyramids`` those of the reference and frame images, as there) and keep the better
    peak of the two. ``d`` (N, T, 2) displacements, ``score`` (N, T) their ZNCC; returns
    both updated (``gpu_floor`` as for :func:`fft_cross_correlation`)."""
    rad = search_radius
    weak = (score < 0.8) | (d.abs() >= rad - 0.5).any(-1)
    h, w = frame_pixels.shape[-2:]
    levels = 0
    while levels < 3 and min(h, w) / 2 ** (levels + 1) >= 2 * (subset_size + 2 * rad):
        levels += 1
    rows = torch.nonzero(weak.any(1)).flatten()
    if levels == 0 or rows.numel() == 0 or rad == 0:
        return d, score
    d2, s2 = coarse_to_fine(ref_pixels, frame_pixels, points[rows], subset_size, rad,
                            levels, frame_index=frame_index[rows],
                            ref_index=ref_index[rows], pyramids=pyramids,
                            gpu_floor=gpu_floor)
    better = s2 > score[rows]
    d, score = d.clone(), score.clone()
    d[rows] = torch.where(better.unsqueeze(-1), d2.to(d.dtype), d[rows])
    score[rows] = torch.where(better, s2.to(score.dtype), score[rows])
    return d, score


def walk_weak_frames(d: torch.Tensor, score: torch.Tensor, dt: torch.Tensor,
                     ref_pixels: torch.Tensor, frame_pixels: torch.Tensor, points: torch.Tensor,
                     frame_index: torch.Tensor, ref_index: torch.Tensor, subset_size: int,
                     search_radius: int, gpu_floor: bool = True
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames of a window whose peak is still weak (ZNCC < 0.8) are searched again around
    the displacement extrapolated from the frames before them in time (the window's
    motion carried along it), in time order; the better peak is kept. ``dt`` (N, T) frame
    times; other shapes (and ``gpu_floor``) as :func:`retry_weak_peaks`. On a GPU every row
    is searched at every frame, the answers of those not weak dropped (no host read:
    :data:`~torch_stsdic.core.choices.SEARCH_READS`)."""
    order = torch.argsort(dt, dim=1)  # (N, T) frames in time order per POI
    d, score = d.clone(), score.clone()
    ar = torch.arange(d.shape[0], device=d.device)
    reads = choices.search_reads(d.device)
    for j in range(1, d.shape[1]):
        cur, p1 = order[:, j], order[:, j - 1]
        weak = (score[ar, cur] < 0.8) & (score[ar, p1] >= 0.8)
        if reads and not bool(weak.any()):
            continue
        rows = torch.nonzero(weak).flatten() if reads else ar
        prior = d[rows, p1[rows]]
        if j >= 2:
            p2 = order[rows, j - 2]
            step = (dt[rows, cur[rows]] - dt[rows, p1[rows]]) / (
                dt[rows, p1[rows]] - dt[rows, p2]).clamp(min=1e-9)
            good2 = score[rows, p2] >= 0.8
            prior = prior + torch.where(good2.unsqueeze(-1), (prior - d[rows, p2])
                                        * step.unsqueeze(-1).to(d.dtype), 0.0 * prior)
        if not reads:  # (a finite search centre at the rows not asked about)
            prior = torch.where(weak.unsqueeze(-1), prior, 0.0)
        d2, s2 = fft_cross_correlation(
            ref_pixels, frame_pixels, points[rows], subset_size,
            max(3, search_radius // 2), frame_index=frame_index[rows, cur[rows]].unsqueeze(1),
            ref_index=ref_index[rows], prior=prior.unsqueeze(1), gpu_floor=gpu_floor)
        better = s2[:, 0] > score[rows, cur[rows]]
        if not reads:  # every row searched: the weak ones' better peaks kept
            better &= weak
            d[ar, cur] = torch.where(better.unsqueeze(-1), d2[:, 0].to(d.dtype), d[ar, cur])
            score[ar, cur] = torch.where(better, s2[:, 0].to(score.dtype), score[ar, cur])
            continue
        rb = rows[better]
        d[rb, cur[rb]] = d2[better, 0].to(d.dtype)
        score[rb, cur[rb]] = s2[better, 0].to(score.dtype)
    return d, score
