"""The template image: the sampled frames mapped back to the reference configuration by each
POI's local map, brought to the reference's grey levels over the POI's window and averaged with
tent weights and the inverse of each frame's noise variance (:mod:`.series_reference` decides
which frame enters where and makes the maps). Every frame is sampled from the run's prepared
frames (:class:`~torch_stsdic.movie.frames.FrameCache`: B-spline coefficients made once per run),
a group of frames at a time in one batch, the sums scattered on the run's device in a fixed
order (:func:`~torch_stsdic.kernels.scatter.scatter_add_`; the CPU's C++ path samples and
adds them in one pass, in the same order, :func:`~torch_stsdic.kernels.native.ops.
splat_fused`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.noise import interpolation_variance_factor
from torch_stsdic.kernels import dispatch
from torch_stsdic.kernels import native as native_ops
from torch_stsdic.kernels.scatter import scatter_add_
from torch_stsdic.movie.frames import FrameCache
from torch_stsdic.movie.plan import RunPlan

__all__ = ["template_image", "splat", "frame_groups", "window_pixels", "TemplateWindows"]

#: the points whose warps feed the template (grey levels of the pixels: memory per chunk)
_CHUNK_SAMPLES = 1_000_000


def _shifted(warp: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """(n, 6) coefficients of a quadratic ``a + b ox + c oy + q1 ox^2 + q2 ox oy + q3 oy^2``
    re-expanded about ``delta`` (n, 2) (so that ``o = delta + d``): its value, slopes and the
    same second-order terms at ``delta``."""
    a, b, c, q1, q2, q3 = warp.unbind(1)
    dx, dy = delta.unbind(1)
    return torch.stack([a + b * dx + c * dy + q1 * dx * dx + q2 * dx * dy + q3 * dy * dy,
                        b + 2 * q1 * dx + q2 * dy, c + q2 * dx + 2 * q3 * dy, q1, q2, q3], 1)


def _masked(a: torch.Tensor, inside: torch.Tensor | None) -> torch.Tensor:
    """``a`` where ``inside`` (None: everywhere), else 0."""
    return a if inside is None else torch.where(inside, a, 0.0)


def window_pixels(pts: torch.Tensor, half: int, height: int, width: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The pixels the POIs' windows (half-width ``half`` px about each rounded POI of ``pts``
    (N, 2)) reach, as :func:`splat` indexes them (flat, clamped to the image; a window over
    the border reaches pixels it masks out): (C,) their flat indices, sorted, and (N, S)
    each window pixel's position among them."""
    flat = _window_index(pts.round(), half, width, height * width)  # (N, S)
    # torch.unique's answer without its sort: the pixels marked on the image, in order,
    # each window pixel's rank among them
    mark = torch.zeros(height * width, dtype=torch.bool, device=flat.device)
    mark[flat] = True
    rank = torch.cumsum(mark, 0) - 1
    return torch.nonzero(mark).flatten(), rank[flat]


def reference_window_stats(ref: torch.Tensor, cover: tuple[torch.Tensor, torch.Tensor]
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 1) the mean and (N, 1) the root of the summed squared deviations of the
    reference's pixels ``ref`` (H*W,) over each POI's whole window (``cover``:
    :func:`window_pixels`; as :func:`splat` reads them where no window of a chunk crosses a
    border): the same for every frame."""
    pixels, local = cover
    own = ref[pixels[local]]  # (N, S)
    mean = own.sum(1, keepdim=True) / float(own.shape[1])
    return mean, ((own - mean) ** 2).sum(1, keepdim=True).sqrt()


def _window_index(c: torch.Tensor, half: int, width: int, size: int) -> torch.Tensor:
    """(n, S) flat pixel indices of the windows about the whole-pixel centres ``c`` (n, 2),
    row-major offsets, clamped to ``[0, size)``."""
    d = torch.arange(-half, half + 1, device=c.device)
    offset = (d[:, None] * width + d[None, :]).reshape(-1)
    return ((c[:, 1] * width + c[:, 0]).long()[:, None] + offset).clamp(0, size - 1)


def splat(acc: torch.Tensor, img: BSplineImage, planes: torch.Tensor, ref: torch.Tensor,
          pts: torch.Tensor, warp: torch.Tensor, ok: torch.Tensor, half: int,
          weight: torch.Tensor, level: torch.Tensor,
          cover: tuple[torch.Tensor, torch.Tensor] | None = None,
          ref_stats: tuple[torch.Tensor, torch.Tensor] | None = None,
          scratch: torch.Tensor | None = None) -> None:
    """Add G frames, planes ``planes`` (G,) of the stack ``img``, each mapped back by each
    trusted POI's map (``warp``: (G, N, 12), the local fits' of the series reference;
    ``ok``: (G, N)) over its window of half-width ``half`` px, to ``acc``: weighted
    values, weights, and the frames' noise variance share, either (3, H*W) over the image or
    (3, C) over the C pixels the windows cover (``cover``'s; no scatter into the image: a
    template of many frames adds them up there and maps the sums to the image once). All
    frames' POIs in one batch (chunks of ``_CHUNK_SAMPLES`` samples), no loop over the
    frames.

    A POI's samples are its window's pixels moved by its map (a polynomial of the offsets:
    one matrix product for all pixels), brought to the reference's grey levels over the
    window (``ref``: (H*W,) its pixels; mean and standard deviation matched, as the ZNCC
    criteria ignore them: a frame that is brighter does not make a patchy template;
    ``level`` (G,): each frame's contrast over the reference's, over the whole image), and
    weighted by a tent and ``weight`` (G,) (the inverse of the frame's noise variance in the
    reference's grey levels). The POIs whose windows cover a pixel sample the frame at
    (nearly) the same place, so their noise is one and the same: a frame's share is
    ``W (sum_i w_i f_i) / weight`` (``W`` the frame's weight sum at the pixel, ``f_i`` the
    interpolated noise's variance factor at the POI's sub-pixel shift, times its gain
    squared), not ``sum_i w_i^2 f_i / weight``: it is summed per frame (a (G, C) pair over
    the C pixels the windows cover, ``cover``: :func:`window_pixels` of ``pts``; the
    reference's statistics over whole windows ``ref_stats``:
    :func:`reference_window_stats`; each made here where not given)
    before the frames are added up. ``scratch``: (2, C) float64 zeros for one frame's sums,
    given back as zeros (a caller splatting frame after frame reuses it; the C++ path of one
    frame, else unused)."""
    h, w = img.height, img.width
    g_count, n = ok.shape
    dev = acc.device
    d = torch.arange(-half, half + 1, dtype=torch.float64, device=dev)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    dx, dy = dx.reshape(-1), dy.reshape(-1)
    mono = torch.stack([torch.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], 1)  # (S, 6)
    tent = (1.0 - dx.abs() / (half + 1)) * (1.0 - dy.abs() / (half + 1))
    sel = torch.nonzero(ok.reshape(-1)).flatten()  # (frame, POI) pairs, frame-major
    cover = window_pixels(pts, half, h, w) if cover is None else cover
    pixels, local = cover
    if ref_stats is None:
        ref_stats = reference_window_stats(ref, cover)
    n_px = pixels.numel()
    # (3, C): add in place, else sums mapped to the image (C = H*W only where the windows
    # cover every pixel: then the covered pixels, sorted, are the image's, the same layout)
    on_cover = acc.shape[1] == n_px
    sums = acc if on_cover else torch.zeros(3, n_px, dtype=torch.float64, device=dev)
    ka = img.kernel_args()
    native = dispatch.splat(ka, warp) == dispatch.NATIVE
    reuse = (native and g_count == 1 and scratch is not None
             and tuple(scratch.shape) == (2, n_px))
    per_frame = (scratch if reuse else
                 torch.zeros(2, g_count * n_px, dtype=torch.float64, device=dev))
    # (the C++ path keeps no (rows, S) arrays: every row at once)
    chunk = max(1, sel.numel() if native else _CHUNK_SAMPLES // dx.numel())
    for s0 in range(0, sel.numel(), chunk):
        f, i = sel[s0: s0 + chunk] // n, sel[s0: s0 + chunk] % n
        c = pts[i].round()
        delta = c - pts[i]
        # the window's pixels moved by the map: one matrix product a coordinate, the
        # window's centre and offset folded into the polynomial's value and slope
        px_map, py_map = _shifted(warp[f, i, 0:6], delta), _shifted(warp[f, i, 6:12], delta)
        px_map[:, 0] += c[:, 0]
        px_map[:, 1] += 1.0
        py_map[:, 0] += c[:, 1]
        py_map[:, 2] += 1.0
        u0, v0 = warp[f, i, 0], warp[f, i, 6]
        fac = interpolation_variance_factor(u0 - u0.floor(), v0 - v0.floor(),
                                            img.order)  # (n,)
        if native:  # the samples' values, weights and noise shares formed and added to
            # the sums in one C++ pass (each covered pixel's rows in their order:
            # scatter_add_'s numbers), the pixels split over the threads
            native_ops.splat_fused(
                ka, img.order, dx, dy, tent, torch.cat([px_map, py_map], 1), c,
                planes[f] * ka[-1], weight[f], level[f], fac,
                (ref_stats[0][i].reshape(-1), ref_stats[1][i].reshape(-1)), ref, w, h,
                sums[0], per_frame[0], per_frame[1], i, f, local)
            continue
        px = local[i]  # (n, S) the window pixels among the covered ones
        at = px if g_count == 1 else f[:, None] * n_px + px  # the pixel in its frame's share
        xs, ys = px_map @ mono.T, py_map @ mono.T  # (n, S) px in the frame
        # a window wholly inside the image (both configurations) needs no mask: most do
        (xlo, xhi), (ylo, yhi) = torch.aminmax(xs), torch.aminmax(ys)
        whole = bool((c.amin() >= half) & (c[:, 0].amax() <= w - 1 - half)
                     & (c[:, 1].amax() <= h - 1 - half) & (xlo >= 0) & (xhi <= w - 1)
                     & (ylo >= 0) & (yhi <= h - 1))
        inside = None
        if not whole:
            x, y = c[:, :1] + dx, c[:, 1:] + dy  # (n, S) reference-configuration pixels
            inside = ((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & (xs >= 0)
                      & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1))
        vals = torch.nan_to_num(img.sample(xs.to(img.dtype), ys.to(img.dtype),
                                           frame=planes[f].unsqueeze(1)).double())
        cnt = (torch.full((len(i), 1), float(dx.numel()), dtype=torch.float64, device=dev)
               if inside is None else inside.sum(1, keepdim=True).clamp(min=1))
        m_f = _masked(vals, inside).sum(1, keepdim=True) / cnt
        vals -= m_f  # centred over the window
        s_f = torch.linalg.vector_norm(_masked(vals, inside), dim=1, keepdim=True)
        if inside is None:  # whole windows: the reference's statistics, frame-independent
            m_r, s_r = ref_stats[0][i], ref_stats[1][i]
        else:
            own = ref[pixels[local[i]]]  # (n, S) the reference's pixels of the windows
            m_r = _masked(own, inside).sum(1, keepdim=True) / cnt
            s_r = _masked((own - m_r) ** 2, inside).sum(1, keepdim=True).sqrt()
        gain = torch.where(s_f > 0, s_r / s_f.clamp(min=1e-12), 1.0)
        wt = _masked(tent * weight[f, None], inside)
        vals.mul_(gain).add_(m_r).mul_(wt)  # in the reference's grey levels, weighted
        share = wt * (fac[:, None] * (gain * level[f, None]) ** 2)
        # summed in a fixed order (the same template on every run and device)
        scatter_add_(sums[0], px, vals)
        scatter_add_(per_frame[0], at, wt)
        scatter_add_(per_frame[1], at, share)
    _fold_frames(sums, per_frame.view(2, g_count, n_px), weight, native)
    if not on_cover:
        acc[:, pixels] += sums


def _fold_frames(sums: torch.Tensor, per_frame: torch.Tensor, weight: torch.Tensor,
                 native: bool) -> None:
    """The G frames' own sums ``per_frame`` (2, G, C: weights, noise factors) folded into
    the template's ``sums`` (3, C): the weights added, and each frame's share of the noise
    (its noise factors over its ``weight`` (G,) times its weights). ``native``: one frame's
    in one C++ pass, ``per_frame`` left as zeros."""
    weights, shares = per_frame.unbind(0)
    if native and weights.shape[0] == 1:
        native_ops.splat_finish(sums[1], sums[2], weights[0], shares[0], weight)
        return
    shares.div_(weight[:, None]).mul_(weights)
    if weights.shape[0] == 1:
        sums[1] += weights[0]
        sums[2] += shares[0]
    else:
        sums[1] += weights.sum(0)
        sums[2] += shares.sum(0)


#: MiB of the per-frame sums a group of the template's frames holds (:func:`frame_groups`)
_GROUP_MB = 64.0


def frame_groups(frames: int, pixels: int, batched: bool = True) -> list[list[int]]:
    """The template's frames (0 .. ``frames`` - 1) in the groups that :func:`splat` takes at
    once: with ``batched``, each frame's two sums (float64) over the ``pixels`` the windows
    cover within ``_GROUP_MB``; else one frame a group (the CPU: there a batch of frames
    is no faster, measured on the hourglass, and its stack is a copy of the frames)."""
    size = max(1, int(_GROUP_MB * 2**20 // (16 * max(pixels, 1)))) if batched else 1
    return [list(range(a, min(a + size, frames))) for a in range(0, frames, size)]


def _group_frames(cache: FrameCache, frames: list[int], dev: torch.device,
                  pixels: bool = True) -> tuple[BSplineImage, torch.Tensor, torch.Tensor | None]:
    """The prepared ``frames``: their coefficients as one stack, each frame's plane in it
    (G,), and (``pixels``; else None) their pixels (G, H, W) float64 on ``dev`` (a single
    frame: its own image, no copy; several: the cache's
    :meth:`~torch_stsdic.movie.frames.FrameCache.in_ring`)."""
    if len(frames) == 1:
        prepared = cache.frame(frames[0])  # the run's: read and prefiltered once
        return (prepared.prep, torch.zeros(1, dtype=torch.long, device=dev),
                prepared.raw.to(dev).double().unsqueeze(0) if pixels else None)
    view = cache.in_ring(frames)
    planes = torch.as_tensor(view.planes, device=dev)
    return view.img, planes, (view.raw[planes.to(view.raw.device)].to(dev).double()
                              if pixels else None)


@dataclass
class TemplateWindows:
    """What every round of one template shares (:func:`template_image`): the reference's
    grey-level spread, the pixels the POIs' windows cover (:func:`window_pixels`), the
    reference's statistics over them (:func:`reference_window_stats`) and each sampled
    frame's contrast over the reference's (series frame -> 0-d tensor, filled as read)."""

    spread: float
    cover: tuple[torch.Tensor, torch.Tensor]
    ref_stats: tuple[torch.Tensor, torch.Tensor]
    level: dict[int, torch.Tensor] = field(default_factory=dict)

    @classmethod
    def make(cls, plan: RunPlan, ref_raw: torch.Tensor) -> TemplateWindows:
        """Those of ``plan``'s POIs and its reference image ``ref_raw`` (H, W)."""
        h, w = plan.series.shape
        dev = torch.device(plan.device)
        ref = ref_raw.double().to(dev).reshape(-1)
        cover = window_pixels(plan.points.double().to(dev), (plan.config.subset_size - 1) // 2,
                              h, w)
        return cls(spread=float(ref.std().clamp(min=1e-12)), cover=cover,
                   ref_stats=reference_window_stats(ref, cover))


def template_image(plan: RunPlan, warps: torch.Tensor, oks: torch.Tensor, frames: list[int],
                   sigmas: list[float], ref_raw: torch.Tensor, cache: FrameCache,
                   windows: TemplateWindows | None = None
                   ) -> tuple[torch.Tensor, float, float, torch.Tensor]:
    """The template from the maps (F, N, 12) (the local fits' of the series reference) and
    trust (F, N) of ``frames`` (noise ``sigmas``; prepared by ``cache``): image (H, W), its
    noise variance over one frame's (median over the covered pixels), coverage, and (N,) that
    ratio at each POI (1 where no frame covers it: the reference image's pixels).
    ``windows``: what the rounds of one template share (default: made here)."""
    h, w = plan.series.shape
    dev = torch.device(plan.device)
    pts = plan.points.double().to(dev)
    half = (plan.config.subset_size - 1) // 2
    ref = ref_raw.double().to(dev).reshape(-1)
    windows = TemplateWindows.make(plan, ref_raw) if windows is None else windows
    spread, cover, ref_stats, levels = (windows.spread, windows.cover, windows.ref_stats,
                                        windows.level)
    norm = []  # each frame's noise in the reference's grey levels (read once, at the end)
    sig = torch.as_tensor(sigmas, dtype=torch.float64).to(dev)  # (F,) one copy
    # the sums over the covered pixels, on the run's device, mapped to the image at the end
    on_cover = torch.zeros(3, cover[0].numel(), dtype=torch.float64, device=dev)
    scratch = torch.zeros(2, cover[0].numel(), dtype=torch.float64, device=dev)  # (reused)
    for group in frame_groups(len(frames), cover[0].numel(), batched=dev.type != "cpu"):
        img, planes, raw = _group_frames(cache, [frames[j] for j in group], dev,
                                         pixels=any(frames[j] not in levels for j in group))
        if raw is not None:  # (G,) contrast ratios
            levels.update(zip((frames[j] for j in group),
                              raw.flatten(1).std(1).clamp(min=1e-12) / spread))
        level = torch.stack([levels[frames[j]] for j in group])
        g = slice(group[0], group[-1] + 1)  # (a group: consecutive frames)
        g_norm = sig[g] / level
        norm.append(g_norm)
        splat(on_cover, img, planes, ref, pts, warps[g].to(dev), oks[g].to(dev),
              half, 1.0 / g_norm ** 2, level, cover, ref_stats, scratch)
    norm = torch.cat(norm).tolist()
    # what follows is per covered pixel, once (the sums' pixels, ascending flat indices)
    px, sums = cover[0].cpu(), on_cover.cpu()
    ref, pts = ref.cpu(), pts.cpu()
    covered = sums[1] > 0  # (C,)
    weight_sum = sums[1][covered]
    image = ref.clone()  # the reference's pixels where no frame covers one
    image[px[covered]] = sums[0][covered] / weight_sum.clamp(min=1e-300)
    # noise variance of a pixel: sum over frames of the frame's share (sums[2]) over the
    # squared weight sum, over one frame's median s^2 (1 where no frame covers it)
    s2 = float(np.median(norm)) ** 2
    pix = torch.where(covered, sums[2] / sums[1].clamp(min=1e-300) ** 2 / s2, 1.0)  # (C,)
    some = weight_sum.numel() > 0
    ratio = float(pix[covered].median()) if some else 1.0
    wmax = weight_sum.max() if some else torch.tensor(1.0)
    multi = (weight_sum > 1.5 * wmax / max(len(frames), 1)).double()
    coverage = float(multi.mean()) if multi.numel() else 0.0
    c = pts.round().long()
    c[:, 0].clamp_(0, w - 1)
    c[:, 1].clamp_(0, h - 1)
    at = c[:, 1] * w + c[:, 0]  # each POI's centre pixel, and its place among the covered
    pos = torch.searchsorted(px, at).clamp(max=max(px.numel() - 1, 0))
    known = (px[pos] == at) if px.numel() else torch.zeros_like(at, dtype=torch.bool)
    at_poi = torch.where(known, pix[pos] if px.numel() else 1.0, 1.0)
    return image.reshape(h, w), ratio, coverage, at_poi
