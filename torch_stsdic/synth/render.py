"""Analytic rendering of a speckle pattern under a motion (pixel-area integration, no
interpolation), noise, quantisation, series and their ground truth."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torch_stsdic.synth.motion import Motion, Translation
from torch_stsdic.synth.pattern import DTYPE, ArrayLike, SpecklePattern, as_float64, make_speckle

__all__ = ["render", "add_noise", "quantize", "render_series", "iter_series", "ground_truth",
           "Movie", "synthetic_movie", "synthetic_images"]



_SQRT2 = math.sqrt(2.0)
_SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_CHUNK = 1 << 20  # max elements of the largest temporary per chunk (8 MiB in float64)


def _erf_profile(edges: Tensor, c: Tensor, s: Tensor) -> Tensor:
    """Integrals of ``exp(-(x - c)^2 / (2 s^2))`` over consecutive intervals of ``edges``.

    edges (K, P+1), c and s (K,) -> (K, P).
    """
    e = torch.erf((edges - c[:, None]) / (_SQRT2 * s[:, None]))
    return (e[:, 1:] - e[:, :-1]) * (_SQRT_PI_2 * s[:, None])


def _check_coverage(pattern: SpecklePattern, shape: tuple[int, int], motion: Motion | None,
                    t: float) -> None:
    if pattern.bounds is None or motion is None:
        return
    H, W = shape
    rmax = float(pattern.radius.max()) if len(pattern) else 0.0
    xs = torch.linspace(-0.5, W - 0.5, max(2, W // 16 + 2), dtype=DTYPE)
    ys = torch.linspace(-0.5, H - 0.5, max(2, H // 16 + 2), dtype=DTYPE)
    bx = torch.cat([xs, xs, torch.full_like(ys, -0.5), torch.full_like(ys, W - 0.5)])
    by = torch.cat([torch.full_like(xs, -0.5), torch.full_like(xs, H - 0.5), ys, ys])
    u, v = motion.displacement(bx, by, t)
    px, py = bx - u, by - v  # first-order inverse: material point seen at the image border
    x0, x1, y0, y1 = pattern.bounds
    m = 2.0 * rmax
    if bool(((px < x0 + m) | (px > x1 - m) | (py < y0 + m) | (py > y1 - m)).any()):
        warnings.warn(
            f"synth.render: at t={t} the motion moves the pattern's edge into the image "
            f"(max |u|={float(u.abs().max()):.3g}, |v|={float(v.abs().max()):.3g} px); "
            "use a larger margin in make_speckle", stacklevel=3)


def render(
    pattern: SpecklePattern,
    shape: tuple[int, int],
    motion: Motion | None = None,
    t: float = 0.0,
    *,
    quadrature: int = 4,
    cutoff: float = 6.0,
    check_coverage: bool = True,
) -> Tensor:
    """Render the pattern deformed by ``motion`` at time ``t``; exact pixel-area integration.

    Each spot centre ``c`` is moved to ``c + U(c, t)`` and its shape mapped by
    ``F = I + grad U(c, t)`` (exact for affine motion). Pixel values are means over the unit
    pixel square: exact (``erf``) along x; along y exact where ``F F^T`` is diagonal, else
    Gauss-Legendre with ``quadrature`` nodes. Vectorised over spots (``index_add_`` of local
    patches of half-width ``ceil(cutoff * sigma)``, spots grouped by patch size).

    Args:
        pattern: the speckle pattern (undeformed configuration).
        shape: (H, W) of the image [px].
        motion: displacement field; None = undeformed.
        t: time at which the motion is evaluated.
        quadrature: Gauss-Legendre nodes per pixel along y for sheared/rotated spots.
        cutoff: spots are truncated beyond ``cutoff`` standard deviations (6: relative
            truncation error < 2e-8 of the spot amplitude).
        check_coverage: warn if the motion pulls the pattern's margin into the image.

    Returns:
        (H, W) float64 tensor of grey levels.

    Raises:
        ValueError: if ``det F <= 0`` for some spot (folding motion).
    """
    H, W = int(shape[0]), int(shape[1])
    if quadrature < 1:
        raise ValueError("quadrature must be >= 1")
    dev = pattern.x.device
    img = torch.full((H, W), float(pattern.background), dtype=DTYPE, device=dev)
    if len(pattern) == 0:
        return img
    cx, cy = pattern.x.to(DTYPE), pattern.y.to(DTYPE)
    r, a = pattern.radius.to(DTYPE), pattern.amplitude.to(DTYPE)
    n = cx.shape[0]
    if motion is None:
        f00 = torch.ones(n, dtype=DTYPE, device=dev)
        f11 = f00.clone()
        f01 = torch.zeros(n, dtype=DTYPE, device=dev)
        f10 = f01.clone()
    else:
        if check_coverage:
            _check_coverage(pattern, (H, W), motion, t)
        u, v = motion.displacement(cx, cy, t)
        g = motion.gradient(cx, cy, t)
        u, v = torch.broadcast_to(u, (n,)).to(dev), torch.broadcast_to(v, (n,)).to(dev)
        dudx, dudy, dvdx, dvdy = (torch.broadcast_to(q, (n,)).to(dev) for q in g)
        cx, cy = cx + u, cy + v
        f00, f01, f10, f11 = 1.0 + dudx, dudy, dvdx, 1.0 + dvdy
    det = f00 * f11 - f01 * f10
    if bool((det <= 0).any()) or not bool(torch.isfinite(det).all()):
        raise ValueError("motion folds the material (det F <= 0) or is not finite at some spot")
    # Covariance of the deformed spot: r^2 F F^T.
    sxx = r * r * (f00 * f00 + f01 * f01)
    syy = r * r * (f10 * f10 + f11 * f11)
    sxy = r * r * (f00 * f10 + f01 * f11)
    sx, sy = torch.sqrt(sxx), torch.sqrt(syy)
    h = torch.ceil(cutoff * torch.maximum(sx, sy)).clamp(min=1).to(torch.long)
    jc = torch.floor(cx + 0.5).to(torch.long)
    ic = torch.floor(cy + 0.5).to(torch.long)
    keep = (jc + h >= 0) & (jc - h <= W - 1) & (ic + h >= 0) & (ic - h <= H - 1)
    if not bool(keep.any()):
        return img
    hmax = int(h[keep].max())
    pad = 2 * hmax + 1  # patch rows span ic +- h with ic in [-h, H - 1 + h]
    Wp = W + 2 * pad
    canvas = torch.zeros((H + 2 * pad) * Wp, dtype=DTYPE, device=dev)
    sep = sxy == 0
    xi_np, wq_np = np.polynomial.legendre.leggauss(int(quadrature))
    xi = torch.as_tensor(xi_np * 0.5, dtype=DTYPE, device=dev)  # nodes on [-1/2, 1/2]
    wq = torch.as_tensor(wq_np * 0.5, dtype=DTYPE, device=dev)  # weights sum to 1

    for separable in (True, False):
        sel_mask = keep & (sep if separable else ~sep)
        if not bool(sel_mask.any()):
            continue
        for hv in torch.unique(h[sel_mask]).tolist():
            idx = torch.nonzero(sel_mask & (h == hv)).squeeze(1)
            P = 2 * hv + 1
            per_spot = P * (P + 1) * (1 if separable else quadrature)
            step = max(1, _CHUNK // per_spot)
            off = torch.arange(-hv, hv + 1, device=dev)
            edge_off = torch.arange(-hv, hv + 2, device=dev, dtype=DTYPE) - 0.5
            for s0 in range(0, idx.numel(), step):
                k = idx[s0:s0 + step]
                jk, ik = jc[k], ic[k]
                xe = jk[:, None].to(DTYPE) + edge_off  # (K, P+1) pixel column edges
                if separable:
                    px = _erf_profile(xe, cx[k], sx[k])
                    ye = ik[:, None].to(DTYPE) + edge_off
                    py = _erf_profile(ye, cy[k], sy[k])
                    patch = (a[k][:, None] * py)[:, :, None] * px[:, None, :]
                else:
                    patch = _sheared_patch(xe, ik, off, xi, wq, cx[k], cy[k], sxx[k], syy[k],
                                           sxy[k], a[k])
                rows = ik[:, None] + off + pad  # (K, P)
                cols = jk[:, None] + off + pad
                flat = (rows[:, :, None] * Wp + cols[:, None, :]).reshape(-1)
                canvas.index_add_(0, flat, patch.reshape(-1))
    img += canvas.view(H + 2 * pad, Wp)[pad:pad + H, pad:pad + W]
    return img


def _sheared_patch(xe: Tensor, ik: Tensor, off: Tensor, xi: Tensor, wq: Tensor, cx: Tensor,
                   cy: Tensor, sxx: Tensor, syy: Tensor, sxy: Tensor, a: Tensor) -> Tensor:
    """Pixel integrals of general (correlated) Gaussian spots -> (K, P, P).

    With ``M = Sigma^{-1} = [[A, B], [B, C]]`` the exponent is
    ``A (dx + B/A dy)^2 + (C - B^2/A) dy^2``: for every y node the x-profile is a 1-D Gaussian
    of std ``1/sqrt(A)`` centred at ``cx - B/A dy``, integrated exactly with erf.
    """
    det = sxx * syy - sxy * sxy
    A, B, C = syy / det, -sxy / det, sxx / det
    sa = 1.0 / torch.sqrt(A)  # conditional std along x
    cyy = C - B * B / A  # = 1 / syy
    yn = (ik[:, None].to(DTYPE) + off.to(DTYPE))[:, :, None] + xi  # (K, P, Q) y nodes
    dy = yn - cy[:, None, None]
    mu = cx[:, None, None] - (B / A)[:, None, None] * dy  # (K, P, Q)
    e = torch.erf((xe[:, None, None, :] - mu[..., None]) / (_SQRT2 * sa)[:, None, None, None])
    ix = (e[..., 1:] - e[..., :-1]) * (_SQRT_PI_2 * sa)[:, None, None, None]  # (K, P, Q, P)
    wy = wq * torch.exp(-0.5 * cyy[:, None, None] * dy * dy) * a[:, None, None]  # (K, P, Q)
    return (wy[..., None] * ix).sum(2)


# --------------------------------------------------------------------------------------------
# Noise, quantisation, series
# --------------------------------------------------------------------------------------------


def _generator(seed: int | torch.Generator | None) -> torch.Generator:
    if isinstance(seed, torch.Generator):
        return seed
    g = torch.Generator()
    if seed is None:
        g.seed()
    else:
        g.manual_seed(int(seed))
    return g


def add_noise(
    img: Tensor,
    sigma: float,
    seed: int | torch.Generator | None = None,
    *,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Return ``img`` plus i.i.d. zero-mean Gaussian noise of std ``sigma`` [grey levels].

    ``seed`` may be an int or a ``torch.Generator`` (``generator=`` is an alias); None draws a
    random seed. The input is not modified. Output float64, same shape.
    """
    img = img.to(DTYPE)
    if sigma < 0:
        raise ValueError("sigma must be >= 0")
    if sigma == 0:
        return img.clone()
    g = generator if generator is not None else _generator(seed)
    noise = torch.randn(img.shape, generator=g, dtype=DTYPE)
    return img + float(sigma) * noise.to(img.device)


def quantize(img: Tensor, bits: int = 8, *, dtype: torch.dtype | None = None) -> Tensor:
    """Digitise an 8-bit-scale image to ``bits`` bits: scale, round, clip.

    The image is multiplied by ``(2^bits - 1) / 255`` (1 for 8 bits, 257 for 16 bits, so the
    same pattern fills the same fraction of the range), rounded to integers and clipped to
    ``0 .. 2^bits - 1``. Returns float64 (integer values) unless ``dtype`` is given.
    """
    if not 1 <= int(bits) <= 32:
        raise ValueError("bits must be in 1..32")
    top = float(2 ** int(bits) - 1)
    out = torch.clamp(torch.round(img.to(DTYPE) * (top / 255.0)), 0.0, top)
    return out if dtype is None else out.to(dtype)


def render_series(
    pattern: SpecklePattern,
    shape: tuple[int, int],
    motion: Motion | None,
    times: ArrayLike,
    *,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int | torch.Generator | None = 0,
    reference_time: float | None = 0.0,
    quadrature: int = 4,
) -> tuple[Tensor, Tensor]:
    """Render a reference image and a time series of deformed frames.

    The reference is rendered at ``reference_time`` (None: the undeformed pattern, i.e. no
    motion), every frame at its time; then independent Gaussian noise of std ``noise_sigma``
    [8-bit grey levels] is added to *all* images (reference first, then frames in order, from
    one generator seeded with ``seed``), and finally, if ``bits`` is given, they are quantised
    with :func:`quantize` (16 bits: values scaled by 257). :func:`iter_series` gives the same
    images one at a time (a long movie).

    The ground truth relative to the reference is ``ground_truth(motion, X, times)`` when
    ``U(X, reference_time) = 0`` (true at t = 0 for every time-dependent motion here); otherwise
    pass ``reference_time`` to :func:`ground_truth` as well (or use ``reference_time=None``).

    Returns:
        ``(ref, frames)``: ``(H, W)`` and ``(T, H, W)`` float64.
    """
    images = iter_series(pattern, shape, motion, times, noise_sigma=noise_sigma, bits=bits,
                         seed=seed, reference_time=reference_time, quadrature=quadrature)
    ref = next(images)
    frames = list(images)
    return ref, torch.stack(frames) if frames else torch.empty((0, *shape), dtype=DTYPE)


def iter_series(
    pattern: SpecklePattern,
    shape: tuple[int, int],
    motion: Motion | None,
    times: ArrayLike,
    *,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int | torch.Generator | None = 0,
    reference_time: float | None = 0.0,
    quadrature: int = 4,
) -> Iterator[Tensor]:
    """The images of :func:`render_series` one at a time, each rendered, given its noise and
    quantised as it is asked for: the reference, then the frame of every time of ``times``,
    each (H, W) float64, the very numbers of :func:`render_series` (its noise drawn from one
    generator in the same order) with one image in memory."""
    tt = as_float64(times).reshape(-1)
    g = _generator(seed) if noise_sigma > 0 else None

    def finish(img: Tensor) -> Tensor:
        if g is not None:
            img = add_noise(img, noise_sigma, generator=g)
        return img if bits is None else quantize(img, bits)

    if reference_time is None:
        ref = render(pattern, shape, None, quadrature=quadrature)
    else:
        if motion is not None:
            H, W = shape
            gy, gx = torch.meshgrid(torch.linspace(0, H - 1, 5, dtype=DTYPE),
                                    torch.linspace(0, W - 1, 5, dtype=DTYPE), indexing="ij")
            u0, v0 = motion.displacement(gx, gy, float(reference_time))
            if float(torch.maximum(u0.abs(), v0.abs()).max()) > 1e-12:
                warnings.warn(
                    f"synth.render_series: U(X, reference_time={reference_time}) != 0, so the "
                    "reference image is itself deformed; the truth relative to it is "
                    f"ground_truth(..., reference_time={reference_time}) (or pass "
                    "reference_time=None to use the undeformed pattern as reference)",
                    stacklevel=3)
        ref = render(pattern, shape, motion, float(reference_time), quadrature=quadrature)
    yield finish(ref)
    for ti in tt:
        yield finish(render(pattern, shape, motion, float(ti), quadrature=quadrature))


def ground_truth(
    motion: Motion,
    points: ArrayLike,
    times: ArrayLike,
    *,
    reference_time: float | None = None,
    iterations: int = 20,
) -> dict[str, Tensor]:
    """Exact displacements, velocities and gradients at reference points.

    Args:
        motion: the motion used to render the frames.
        points: (N, 2) reference-image coordinates ``(x, y)`` [px].
        times: (T,) frame times.
        reference_time: None (default): the reference image is the undeformed pattern (or
            ``U(X, reference_time) = 0``), so the truth is ``U(X, t)``. A float: the
            reference was rendered at that time; points are then mapped back to the material
            (solve ``X = C + U(C, t_ref)`` by Newton) and displacements are relative:
            ``U(C, t) - U(C, t_ref)``, gradients w.r.t. reference-image coordinates.
        iterations: Newton iterations for the inversion.

    Returns:
        dict of float64 tensors, each (T, N): ``u, v`` [px], ``ut, vt`` [px / time unit],
        ``dudx, dudy, dvdx, dvdy`` [-].
    """
    pts = as_float64(points).reshape(-1, 2)
    tt = as_float64(times).reshape(-1)
    x, y = pts[:, 0], pts[:, 1]
    T, N = tt.numel(), x.numel()
    grad_ref = None
    if reference_time is not None:
        t0 = float(reference_time)
        cx, cy = x.clone(), y.clone()
        for _ in range(int(iterations)):
            u0, v0 = motion.displacement(cx, cy, t0)
            a, b, c, d = motion.gradient(cx, cy, t0)
            rx, ry = cx + u0 - x, cy + v0 - y
            a, b, c, d = 1.0 + a, b, c, 1.0 + d
            det = a * d - b * c
            cx, cy = cx - (d * rx - b * ry) / det, cy - (-c * rx + a * ry) / det
        u0, v0 = motion.displacement(cx, cy, t0)
        grad_ref = motion.gradient(cx, cy, t0)
        x, y = cx, cy
    X, Y, TT = x[None, :].expand(T, N), y[None, :].expand(T, N), tt[:, None].expand(T, N)
    u, v = motion.displacement(X, Y, TT)
    ut, vt = motion.velocity(X, Y, TT)
    g = motion.gradient(X, Y, TT)
    if grad_ref is not None:
        u, v = u - u0, v - v0
        # d(U(C,t) - U(C,t0))/dX = (G(t) - G(t0)) (I + G(t0))^-1
        a0, b0, c0, d0 = (torch.broadcast_to(q, (N,)) for q in grad_ref)
        e00, e01, e10, e11 = g[0] - a0, g[1] - b0, g[2] - c0, g[3] - d0
        f00, f01, f10, f11 = 1.0 + a0, b0, c0, 1.0 + d0
        det = f00 * f11 - f01 * f10
        i00, i01, i10, i11 = f11 / det, -f01 / det, -f10 / det, f00 / det
        g = (e00 * i00 + e01 * i10, e00 * i01 + e01 * i11,
             e10 * i00 + e11 * i10, e10 * i01 + e11 * i11)
    out = {"u": u, "v": v, "ut": ut, "vt": vt,
           "dudx": g[0], "dudy": g[1], "dvdx": g[2], "dvdy": g[3]}
    return {k: torch.broadcast_to(val.to(DTYPE), (T, N)).clone() for k, val in out.items()}


class Movie(NamedTuple):
    """Result of :func:`synthetic_movie` (unpacks as ``ref, frames, times, motion``)."""

    ref: Tensor  #: (H, W) reference image
    frames: Tensor  #: (T, H, W) deformed frames
    times: Tensor  #: (T,) frame times
    motion: Motion  #: the motion, for :func:`ground_truth`


def synthetic_movie(
    shape: tuple[int, int] = (301, 301),
    n_frames: int = 9,
    motion: Motion | None = None,
    *,
    times: ArrayLike | None = None,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int = 0,
    radius: float = 2.0,
    density: float | None = None,
    margin: float | None = None,
) -> Movie:
    """One-call demo series; defaults reproduce the paper's simulated experiment.

    Default: a 301 x 301 speckle, reference at t = 0 and 9 frames at t = 1..9 moving by
    ``u = t / 20`` px (``Translation(ut=0.05)``), noise ``noise_sigma`` on all 10 images.
    The pattern uses ``seed``; the noise uses an independent seed derived from it.
    :func:`synthetic_images` gives the same images one at a time (a long movie).

    Returns:
        ``Movie(ref, frames, times, motion)``; truth via ``ground_truth(movie.motion, pts,
        movie.times)``.
    """
    motion, tt, images = synthetic_images(shape, n_frames, motion, times=times,
                                          noise_sigma=noise_sigma, bits=bits, seed=seed,
                                          radius=radius, density=density, margin=margin)
    ref = next(images)
    frames = list(images)
    return Movie(ref, torch.stack(frames) if frames else torch.empty((0, *shape), dtype=DTYPE),
                 tt, motion)


def synthetic_images(
    shape: tuple[int, int] = (301, 301),
    n_frames: int = 9,
    motion: Motion | None = None,
    *,
    times: ArrayLike | None = None,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int = 0,
    radius: float = 2.0,
    density: float | None = None,
    margin: float | None = None,
) -> tuple[Motion, Tensor, Iterator[Tensor]]:
    """:func:`synthetic_movie`'s images one at a time (``stsdic synth`` writes each as it is
    rendered): its motion, its frames' times (T,) and an iterator of the reference and then
    the T frames, each (H, W) float64, the very numbers of :func:`synthetic_movie`."""
    if motion is None:
        motion = Translation(ut=1.0 / 20.0)
    if times is None:
        tt = torch.arange(1, n_frames + 1, dtype=DTYPE)
    else:
        tt = as_float64(times).reshape(-1)
    pattern = make_speckle(shape, density=density, radius=radius, seed=seed, margin=margin)
    noise_seed = (int(seed) * 1_000_003 + 7_919) % (2**63)
    return motion, tt, iter_series(pattern, shape, motion, tt, noise_sigma=noise_sigma,
                                   bits=bits, seed=noise_seed)
