"""Cross-camera matching: left reference -> right reference, with no manual seed.

1. **Epipolar search** (:func:`epipolar_search`): every left point's ray is sampled in depth
   (log-spaced), projected into the right image (distortion included, so the search follows
   the curved epipolar line), resampled to about one candidate per pixel along the line, and
   the left subset is compared with the right subset at every candidate by ZNCC, all points
   and candidates in batched ``grid_sample`` calls. The best candidate, refined by a parabola
   through its neighbours, is the point's coarse match.
2. **Consistency** (:func:`robust_homography`, :func:`repair_outliers`): a homography fitted
   robustly to the coarse matches gives every point the local affine map left -> right (its
   Jacobian), and points whose match disagrees with the median of their neighbours' offsets
   from it (a wrong peak: repeated texture, occlusion) restart from that median.
3. **Sub-pixel match** (:func:`match_stereo`): the batched subset solver
   (:class:`torch_stsdic.SubsetSolver` through :func:`torch_stsdic.solve_window`, m = 0),
   the right reference treated as "the deformed frame" of the left reference under a
   first-order (or second-order) subset warp started from steps 1-2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.solution import WindowSolution
from torch_stsdic.core.status import Status
from torch_stsdic.core.window_solve import solve_window

from .calibration import StereoCalibration
from .triangulation import project, undistort

__all__ = ["epipolar_candidates", "epipolar_search", "robust_homography", "repair_outliers",
           "match_stereo", "CrossMatch", "epipolar_offsets", "calibration_mismatch"]

DTYPE = torch.float64


def _undistorted_box(cam, shape) -> tuple[float, float, float, float]:
    """Bounding box (x0, x1, y0, y1) of the image in undistorted normalised coordinates."""
    h, w = (int(v) for v in shape[-2:])
    xs = torch.linspace(-0.5, w - 0.5, 65, dtype=DTYPE)
    ys = torch.linspace(-0.5, h - 0.5, 65, dtype=DTYPE)
    border = torch.cat([torch.stack([xs, torch.full_like(xs, -0.5)], 1),
                        torch.stack([xs, torch.full_like(xs, h - 0.5)], 1),
                        torch.stack([torch.full_like(ys, -0.5), ys], 1),
                        torch.stack([torch.full_like(ys, w - 0.5), ys], 1)])
    q = undistort(border, cam)
    lo, hi = q.min(0).values, q.max(0).values
    pad = 0.05 * (hi - lo)
    return (float(lo[0] - pad[0]), float(hi[0] + pad[0]), float(lo[1] - pad[1]),
            float(hi[1] + pad[1]))


def epipolar_candidates(rig: StereoCalibration, left_pts: Tensor, right_shape, margin: float,
                        step: float = 1.0, depth_range: tuple[float, float] | None = None
                        ) -> tuple[Tensor, Tensor]:
    """Right-image candidates (N, C, 2) along each left point's epipolar curve, about ``step``
    px apart, inside the right image by ``margin`` px, and their mask (N, C).

    The points of a left ray at depths ``depth_range`` (mm along the left optical axis;
    default 0.05 baselines to infinity) form a straight segment in undistorted right
    coordinates (from the point at the nearest depth to the ray's vanishing point); it is
    clipped to the right image, sampled, distorted and projected (so the candidates follow
    the curved epipolar line of the distorted image), then thinned to ``step`` px."""
    pts = torch.as_tensor(left_pts, dtype=DTYPE)
    h, w = (int(v) for v in right_shape[-2:])
    n = undistort(pts, rig.left)
    d = torch.cat([n, torch.ones_like(n[:, :1])], 1)  # X = Z d
    R = torch.as_tensor(rig.R, dtype=DTYPE)
    T = torch.as_tensor(rig.T, dtype=DTYPE)
    rd = d @ R.T  # (N, 3): X_R = Z rd + T
    z0, z1 = depth_range if depth_range is not None else (0.05 * rig.baseline, math.inf)
    # the nearest depth in front of the right camera too
    zfront = torch.where(rd[:, 2] > 0, (-T[2] / rd[:, 2]).clamp(min=0) * 1.0001 + 1e-9,
                         torch.full_like(rd[:, 2], math.inf))
    za = torch.maximum(torch.full_like(zfront, float(z0)), zfront)

    def at(z):
        if math.isinf(float(z1)) and z is None:  # the vanishing point
            return rd[:, :2] / rd[:, 2:3]
        zz = za if z is True else torch.full_like(za, float(z1))
        xr = zz[:, None] * rd + T
        return xr[:, :2] / xr[:, 2:3]
    qa = at(True)
    qb = at(None) if math.isinf(float(z1)) else at(False)
    # Liang-Barsky clip of qa + tau (qb - qa), tau in [0, 1], to the image's undistorted box
    bx0, bx1, by0, by1 = _undistorted_box(rig.right, right_shape)
    dq = qb - qa
    t0 = torch.zeros(len(pts), dtype=DTYPE)
    t1 = torch.ones(len(pts), dtype=DTYPE)
    for p_, q_ in ((-dq[:, 0], qa[:, 0] - bx0), (dq[:, 0], bx1 - qa[:, 0]),
                   (-dq[:, 1], qa[:, 1] - by0), (dq[:, 1], by1 - qa[:, 1])):
        r = q_ / torch.where(p_ == 0, torch.full_like(p_, 1e-300), p_)
        t0 = torch.where(p_ < 0, torch.maximum(t0, r), t0)
        t1 = torch.where(p_ > 0, torch.minimum(t1, r), t1)
        t1 = torch.where((p_ == 0) & (q_ < 0), torch.full_like(t1, -1.0), t1)
    ok = (t1 > t0) & torch.isfinite(qa).all(1) & torch.isfinite(qb).all(1) & (za < float(z1))
    f = max(rig.right.fx, rig.right.fy)
    length = (f * dq.norm(dim=1) * (t1 - t0)).where(ok, torch.zeros_like(t0))
    m = int(min(max(8.0, 3.0 * float(length.max()) / step), 4.0 * (h + w) / step + 8))
    tau = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, m, dtype=DTYPE)[None]
    q = qa[:, None, :] + tau[..., None] * dq[:, None, :]  # (N, M, 2) undistorted normalised
    Xr = torch.cat([q, torch.ones_like(q[..., :1])], -1)
    px = project(Xr, rig.right)  # the right camera's own frame: no pose
    inside = ok[:, None] & (px[..., 0] >= margin) & (px[..., 0] <= w - 1 - margin) & \
        (px[..., 1] >= margin) & (px[..., 1] <= h - 1 - margin) & torch.isfinite(px).all(-1)
    seg = torch.linalg.norm(torch.diff(px, dim=1), dim=-1).nan_to_num(0.0)
    seg = torch.cat([torch.zeros_like(seg[:, :1]), seg], 1)
    k = torch.floor(torch.cumsum(seg, 1) / step).long()
    prev_k = torch.cat([torch.full_like(k[:, :1], -1), k[:, :-1]], 1)
    prev_in = torch.cat([torch.zeros_like(inside[:, :1]), inside[:, :-1]], 1)
    keep = inside & ((k != prev_k) | ~prev_in)
    slot = torch.cumsum(keep.long(), 1) - 1
    C = max(1, int(keep.sum(1).max()))
    cand = torch.full((pts.shape[0], C, 2), float("nan"), dtype=DTYPE)
    valid = torch.zeros(pts.shape[0], C, dtype=torch.bool)
    r, c = torch.nonzero(keep, as_tuple=True)
    cand[r, slot[r, c]] = px[r, c]
    valid[r, slot[r, c]] = True
    return cand, valid


def _sample(img: Tensor, xy: Tensor) -> Tensor:
    """Bilinear samples of (H, W) ``img`` at (..., 2) pixel positions (zeros outside)."""
    h, w = img.shape[-2:]
    g = torch.empty_like(xy)
    g[..., 0] = 2 * xy[..., 0] / (w - 1) - 1
    g[..., 1] = 2 * xy[..., 1] / (h - 1) - 1
    flat = g.reshape(1, 1, -1, 2).to(img.dtype)
    out = F.grid_sample(img[None, None], flat, mode="bilinear", padding_mode="zeros",
                        align_corners=True)
    return out.reshape(xy.shape[:-1])


def _znorm(a: Tensor) -> Tensor:
    a = a - a.mean(-1, keepdim=True)
    return a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def epipolar_search(rig: StereoCalibration, left_ref: Tensor, right_ref: Tensor,
                    left_pts: Tensor, subset_size: int = 21, step: float = 1.0,
                    depth_range: tuple[float, float] | None = None,
                    budget: int = 1 << 23, stride: int = 2) -> tuple[Tensor, Tensor]:
    """Coarse right matches (N, 2) of left points and their ZNCC (N,) by a 1-D search along
    the epipolar curves (see the module docstring), the subsets sampled every ``stride`` px.
    NaN where no candidate lies inside."""
    left = torch.as_tensor(left_ref, dtype=torch.float32)
    right = torch.as_tensor(right_ref, dtype=torch.float32)
    pts = torch.as_tensor(left_pts, dtype=DTYPE)
    half = subset_size // 2
    cand, valid = epipolar_candidates(rig, pts, right.shape, half + 1.0, step, depth_range)
    o = torch.arange(-half, half + 1, max(1, int(stride)), dtype=DTYPE)
    off = torch.stack(torch.meshgrid(o, o, indexing="xy"), -1).reshape(-1, 2)  # (S2, 2) x, y
    f = _znorm(_sample(left, pts[:, None, :] + off[None]))  # (N, S2)
    n, C = cand.shape[:2]
    score = torch.full((n, C), -2.0, dtype=torch.float32)
    per = max(1, budget // max(1, C * off.shape[0]))
    for s0 in range(0, n, per):
        c = cand[s0:s0 + per].nan_to_num(0.0)
        g = _znorm(_sample(right, c[:, :, None, :] + off[None, None]))  # (n', C, S2)
        score[s0:s0 + per] = (g * f[s0:s0 + per, None, :]).sum(-1)
    score[~valid] = -2.0
    best = score.argmax(1)
    idx = torch.arange(n)
    zb = score[idx, best]
    lo = (best - 1).clamp(min=0)
    hi = (best + 1).clamp(max=C - 1)
    s_lo, s_hi = score[idx, lo], score[idx, hi]
    ok = (lo < best) & (hi > best) & (s_lo > -2) & (s_hi > -2)
    den = (s_lo - 2 * zb + s_hi)
    delta = torch.where(ok & (den < 0), 0.5 * (s_lo - s_hi) / den, torch.zeros_like(den))
    delta = delta.clamp(-0.5, 0.5).to(DTYPE)
    p0 = cand[idx, best]
    nxt = torch.where((delta >= 0)[:, None], cand[idx, hi], cand[idx, lo])
    pos = p0 + delta.abs()[:, None] * (nxt - p0)
    pos = torch.where(torch.isfinite(pos), pos, p0)
    no = ~valid.any(1)
    pos[no] = float("nan")
    zb = zb.to(DTYPE)
    zb[no] = float("nan")
    return pos, zb


def epipolar_offsets(rig: StereoCalibration, left_ref: Tensor, right_ref: Tensor,
                     left_pts: Tensor, subset_size: int = 21, reach: int | None = None,
                     most: int = 32, min_zncc: float = 0.7, stride: int = 3,
                     budget: int = 1 << 23) -> tuple[Tensor, Tensor, Tensor]:
    """How far off the calibration's epipolar curves the right reference's matches lie: a
    2-D search free of the epipolar constraint, in a band ``reach`` px either side of each
    curve (default a quarter of the larger image side, 32..160 px), for up to ``most`` left
    points spread over ``left_pts``.

    Returns the points searched (K,) indices into ``left_pts``, their distance off the curve
    (K,) px (NaN where the band holds no subset) and the best ZNCC (K,); a match is a ZNCC
    of at least ``min_zncc``."""
    left = torch.as_tensor(left_ref, dtype=torch.float32)
    right = torch.as_tensor(right_ref, dtype=torch.float32)
    pts = torch.as_tensor(left_pts, dtype=DTYPE)
    idx = torch.unique(torch.linspace(0, len(pts) - 1, min(most, len(pts))).round().long())
    pts = pts[idx]
    h, w = right.shape[-2:]
    reach = 2 * (int(reach if reach is not None else min(160, max(32, max(h, w) // 4))) // 2)
    half = subset_size // 2
    cand, valid = epipolar_candidates(rig, pts, right.shape, 0.0, 2.0)  # on the curve, 2 px
    if cand.shape[1] < 2:  # a curve of one sample has no direction
        return idx, torch.full((len(idx),), float("nan"), dtype=DTYPE), \
            torch.full((len(idx),), float("nan"), dtype=DTYPE)
    tangent = torch.gradient(cand, dim=1)[0]
    normal = torch.stack([-tangent[..., 1], tangent[..., 0]], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    off = torch.arange(-reach, reach + 1, 2, dtype=DTYPE)  # (D,) px across the curve
    pos = cand[:, :, None, :] + off[None, None, :, None] * normal[:, :, None, :]  # (K,C,D,2)
    inside = valid[:, :, None] & torch.isfinite(pos).all(-1) & (pos[..., 0] >= half + 1) & \
        (pos[..., 0] <= w - 2 - half) & (pos[..., 1] >= half + 1) & (pos[..., 1] <= h - 2 - half)
    k, C, D = pos.shape[:3]
    pos, inside = pos.reshape(k, C * D, 2), inside.reshape(k, C * D)
    o = torch.arange(-half, half + 1, max(1, int(stride)), dtype=DTYPE)
    sub = torch.stack(torch.meshgrid(o, o, indexing="xy"), -1).reshape(-1, 2)
    f = _znorm(_sample(left, pts[:, None, :] + sub[None]))  # (K, S2)
    score = torch.full((k, C * D), -2.0, dtype=torch.float32)
    per = max(1, budget // max(1, C * D * sub.shape[0]))
    for s0 in range(0, k, per):
        c = pos[s0:s0 + per].nan_to_num(0.0)
        g = _znorm(_sample(right, c[:, :, None, :] + sub[None, None]))
        score[s0:s0 + per] = (g * f[s0:s0 + per, None, :]).sum(-1)
    score[~inside] = -2.0
    best = score.argmax(1)
    zncc = score[torch.arange(k), best].to(DTYPE)
    dist = off[best % D].abs()
    none = ~inside.any(1)
    dist[none], zncc[none] = float("nan"), float("nan")
    return idx, dist, zncc


def calibration_mismatch(rig: StereoCalibration, left_ref: Tensor, right_ref: Tensor,
                         left_pts: Tensor, subset_size: int = 21, tol: float = 3.0,
                         min_zncc: float = 0.6) -> str | None:
    """The one-line diagnosis of a calibration that does not fit the images, from
    :func:`epipolar_offsets`: the matches found (ZNCC at least ``min_zncc`` and within 0.1 of
    the best tenth's) lie more than ``tol`` px (median) off their epipolar curves, or the
    curves miss the right image. None where the matches lie on the curves (the calibration
    fits) or no match is found at all."""
    idx, dist, z = epipolar_offsets(rig, left_ref, right_ref, left_pts, subset_size)
    if bool(torch.isnan(dist).all()):
        return ("the calibration does not fit these images: the epipolar lines of the left "
                "points miss the right image (check that the calibration belongs to this "
                "set-up and the image order)")
    zf = z[torch.isfinite(z)]
    floor = max(min_zncc, float(torch.quantile(zf, 0.9)) - 0.1)
    found = torch.isfinite(z) & (z >= floor)
    if int(found.sum()) < 3:
        return None
    d = dist[found]
    if float(d.median()) <= tol:
        return None
    lo, hi = (float(torch.quantile(d, q)) for q in (0.1, 0.9))
    span = f"{lo:.0f}" if round(lo) == round(hi) else f"{lo:.0f}-{hi:.0f}"
    return (f"the calibration does not fit these images: matches lie {span} px off "
            f"its epipolar lines (median {float(d.median()):.0f} px, {int(found.sum())} of "
            f"{len(idx)} points found by a search free of the epipolar constraint); check "
            "that the calibration belongs to this set-up and the image order")


def robust_homography(src: Tensor, dst: Tensor, weights: Tensor | None = None,
                      iterations: int = 10) -> Tensor:
    """Homography H (3, 3) with dst ~ H src, by normalised DLT with iteratively reweighted
    (Cauchy) least squares, so a few wrong matches do not pull it."""
    ok = torch.isfinite(src).all(1) & torch.isfinite(dst).all(1)
    s, d = src[ok].to(DTYPE), dst[ok].to(DTYPE)
    w0 = torch.ones(s.shape[0], dtype=DTYPE) if weights is None else weights[ok].to(DTYPE)
    if s.shape[0] < 4:
        raise ValueError(f"cross-camera match: {s.shape[0]} usable points, at least 4 needed")

    def norm(p):
        c = p.mean(0)
        sc = math.sqrt(2) / (p - c).norm(dim=1).mean().clamp_min(1e-12)
        return torch.tensor([[sc, 0, -sc * c[0]], [0, sc, -sc * c[1]], [0, 0, 1]], dtype=DTYPE)
    Ts, Td = norm(s), norm(d)
    sh = torch.cat([s, torch.ones_like(s[:, :1])], 1) @ Ts.T
    dh = torch.cat([d, torch.ones_like(d[:, :1])], 1) @ Td.T
    z = torch.zeros_like(sh)
    a1 = torch.cat([-sh, z, dh[:, :1] * sh], 1)
    a2 = torch.cat([z, -sh, dh[:, 1:2] * sh], 1)
    w = w0.clone()
    H = torch.eye(3, dtype=DTYPE)
    for _ in range(iterations):
        A = torch.cat([a1 * w[:, None], a2 * w[:, None]])
        _, _, Vh = torch.linalg.svd(A, full_matrices=False)
        H = torch.linalg.solve(Td, Vh[-1].reshape(3, 3) @ Ts)
        H = H / H[2, 2]
        res = (_apply_h(H, s) - d).norm(dim=1)
        scale = 2.5 * res.median().clamp_min(0.05)
        w = w0 / (1 + (res / scale) ** 2).sqrt()
    return H


def _apply_h(H: Tensor, p: Tensor) -> Tensor:
    q = torch.cat([p, torch.ones_like(p[:, :1])], 1) @ H.T
    return q[:, :2] / q[:, 2:]


def _h_jacobian(H: Tensor, p: Tensor) -> Tensor:
    q = torch.cat([p, torch.ones_like(p[:, :1])], 1) @ H.T
    x, y, wq = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], q[:, 2]
    j = torch.stack([torch.stack([H[0, 0] - x * H[2, 0], H[0, 1] - x * H[2, 1]], -1),
                     torch.stack([H[1, 0] - y * H[2, 0], H[1, 1] - y * H[2, 1]], -1)], -2)
    return j / wq[:, None, None]


def repair_outliers(pts: Tensor, coarse: Tensor, predicted: Tensor,
                    trusted: Tensor | None = None, k: int = 8, tol: float = 2.0
                    ) -> tuple[Tensor, Tensor]:
    """Points whose match departs more than ``tol`` px from ``predicted`` + the median
    offset (match - predicted) of their ``k`` nearest *trusted* neighbours (default: all
    points) are moved there. Returns the repaired matches (N, 2) and the mask of moved
    points."""
    off = coarse - predicted
    n = pts.shape[0]
    trusted = torch.ones(n, dtype=torch.bool) if trusted is None else \
        trusted & torch.isfinite(off).all(1)
    idx = torch.nonzero(trusted).flatten()
    if idx.numel() < 2:
        return coarse, torch.zeros(n, dtype=torch.bool)
    kk = min(k, idx.numel() - 1)
    dist = torch.cdist(pts.to(DTYPE), pts[idx].to(DTYPE))
    dist[idx, torch.arange(idx.numel())] = math.inf  # not its own neighbour
    nb = idx[dist.topk(kk, largest=False).indices]  # (N, kk)
    med = off[nb].median(dim=1).values  # (N, 2)
    bad = ~((off - med).norm(dim=1) <= tol)
    out = coarse.clone()
    out[bad] = predicted[bad] + med[bad]
    return out, bad


def _trusted(z: Tensor, usable: Tensor) -> Tensor:
    """Matches whose ZNCC is within 0.1 of the median of the usable ones (and >= 0.5)."""
    ok = usable & torch.isfinite(z)
    if not bool(ok.any()):
        return ok
    return ok & (z >= max(0.5, float(z[ok].median()) - 0.1))


@dataclass
class CrossMatch:
    """The left reference -> right reference match.

    Attributes:
        left: (N, 2) left reference points px. right: (N, 2) matched right points px (NaN where
            the match failed). std: (N, 2) predicted std of the right point (px).
        zncc: (N,) ZNCC of the match. status: (N,) int8 :class:`torch_stsdic.Status`.
        solution: the :class:`torch_stsdic.WindowSolution` of the subset solver.
        coarse: (N, 2) the epipolar search's matches; repaired: (N,) bool, restarted from
            the neighbours' offset; homography: (3, 3) the robust left -> right homography.
    """

    left: Tensor
    right: Tensor
    std: Tensor
    zncc: Tensor
    status: Tensor
    solution: WindowSolution
    coarse: Tensor
    repaired: Tensor
    homography: Tensor


def match_stereo(rig: StereoCalibration, left_ref, right_ref, left_pts, config: DICConfig,
                 *, shape: str = "affine", depth_range=None, search_step: float = 1.0,
                 repair_tol: float = 2.0, min_zncc: float = 0.6) -> CrossMatch:
    """Match left reference points into the right reference (see the module docstring).

    Args:
        rig: the calibration. left_ref, right_ref: (H, W) images. left_pts: (N, 2) px.
        config: the run's :class:`DICConfig` (its subset size, criterion, interpolation,
            iterations; m is set to 0 here). shape: "affine" (first order) or "quadratic".
        depth_range: (min, max) depth mm for the epipolar search (default 0.05 baselines to
            infinity). search_step: candidate spacing px along the epipolar line.
        repair_tol: px between a coarse match and its neighbours' consensus above which it is
            restarted from the consensus; a solution more than max(3, 2 repair_tol) px from
            its start is INCONSISTENT. min_zncc: below it the match is POOR_FIT.
    """
    lref = torch.as_tensor(np.asarray(left_ref) if not isinstance(left_ref, Tensor)
                           else left_ref).to(DTYPE)
    rref = torch.as_tensor(np.asarray(right_ref) if not isinstance(right_ref, Tensor)
                           else right_ref).to(DTYPE)
    pts = torch.as_tensor(np.asarray(left_pts) if not isinstance(left_pts, Tensor)
                          else left_pts).to(DTYPE)
    coarse, zc = epipolar_search(rig, lref, rref, pts, config.subset_size, search_step,
                                 depth_range)
    good = torch.isfinite(zc) & (zc > 0.5)
    H = robust_homography(pts, coarse, weights=torch.where(good, zc, torch.zeros_like(zc)))
    pred = _apply_h(H, pts)
    start, moved = repair_outliers(pts, torch.where(good[:, None], coarse, pred), pred,
                                   _trusted(zc, good), tol=repair_tol)
    J = _h_jacobian(H, pts)
    d = start - pts
    init = torch.stack([d[:, 0], J[:, 0, 0] - 1, J[:, 0, 1], d[:, 1], J[:, 1, 0],
                        J[:, 1, 1] - 1], 1)
    init = torch.where(torch.isfinite(init), init, torch.zeros_like(init))
    cfg = replace(config, m=0, shape=shape)
    sol = solve_window(lref, rref[None], pts, cfg, init=init)
    right = pts + torch.stack([sol.u, sol.v], 1).to(DTYPE)
    std = torch.stack([sol.std_of("u"), sol.std_of("v")], 1).to(DTYPE)
    status = sol.status.clone()
    # a start whose subset is not inside the right image: the point is not seen there
    h, w = rref.shape[-2:]
    half = config.subset_size // 2
    out = ~((start[:, 0] >= half) & (start[:, 0] <= w - 1 - half) & (start[:, 1] >= half)
            & (start[:, 1] <= h - 1 - half))
    status[out] = int(Status.OUTSIDE)
    # a solution that wandered off its start, or that fits poorly: a wrong match
    far = (right - start).norm(dim=1) > max(3.0, 2.0 * repair_tol)
    status[(status <= int(Status.MAX_ITER)) & far] = int(Status.INCONSISTENT)
    poor = ~(sol.zncc >= min_zncc)
    status[(status <= int(Status.MAX_ITER)) & poor] = int(Status.POOR_FIT)
    # the disparity field is smooth: a match off its trusted neighbours' consensus is wrong
    usable = status <= int(Status.MAX_ITER)
    zf = sol.zncc.to(DTYPE)
    _, off = repair_outliers(pts, torch.where(usable[:, None], right, pred), pred,
                             _trusted(zf, usable), tol=max(3.0, 2.0 * repair_tol))
    status[usable & off] = int(Status.INCONSISTENT)
    right[status > int(Status.MAX_ITER)] = float("nan")
    return CrossMatch(pts, right, std, sol.zncc.to(DTYPE), status, sol, coarse, moved, H)
