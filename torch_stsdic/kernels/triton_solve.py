"""The whole joint IC-GN stage in one Triton launch: every point iterated to its end.

The GPU twin of the C++ per-point solver (``sts_ic_solve`` in ``native/dic_kernels.cpp``,
``native.ic_solve``): one program per point holds its subset (S pixels in ``next_pow2(S)``
lanes), its inverse Hessian (P x P, float64) and its parameters, and loops

    b, zn, outside = joint IC right-hand side at p     (warp, cubic B-spline sampling of every
                                                        frame, ZNSSD/SSD residual, J^T r)
    dp = -(Hinv b)   (float64, then the data's dtype)
    p_new = p o dp^-1                                  (AffineShape.compose_inverse)
    norm = |dp * scale|;  finite = norm and p_new finite;  bad = !finite or norm > div_norm
    rate = clamp(prev > 0 ? norm / prev : 1, rate_floor, 1)
    converged = finite and norm * rate < tol and !outside;  prev = norm;  p = p_new if finite

until converged, bad or outside (statuses converged / diverged / outside) or ``max_iter``
iterations (status max_iter, p the last iterate). Nothing leaves the device between
iterations: one launch per stage instead of a right-hand-side launch, a dozen torch ops and a
host check per iteration (:mod:`torch_stsdic.core.gauss_newton`'s batched loop).

The arithmetic follows the C++ kernel's order (warp origin in float64, tap weights, frame sums
of the right-hand side in float64; IEEE-rounded divisions and square roots where float32
``/`` and ``tl.sqrt`` would compile to approximate ones) so that both give the same
iterations and statuses and
parameters equal to float rounding (``tests/test_triton_solve.py``, through Triton's
interpreter). Affine shapes (Ks = 3, with or without the time term), cubic splines, float32 or
float64. Imported only where Triton is installed; ``TRITON_INTERPRET=1`` before the first
import runs it on CPU tensors (slow: tests only).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torch_stsdic.kernels.triton_ic import MAX_SUBSET_PIXELS, tap_row

__all__ = ["ic_solve_triton", "MAX_SUBSET_PIXELS"]


@triton.jit
def _weights(f, sixth, two3):
    """Cubic B-spline tap weights at fraction f, written as the C++ kernel's cubic_weights
    (``sixth`` = 1/6 and ``two3`` = 2/3 in the data's dtype: a Python float constant would
    be rounded to float32 first)."""
    f2 = f * f
    f3 = f2 * f
    g = 1.0 - f
    return (g * g * g * sixth, (0.5 * f3 - f2) + two3, ((-0.5 * f3 + 0.5 * f2) + 0.5 * f) + sixth,
            f3 * sixth)


@triton.jit
def _finite(x):
    return (x == x) & (tl.abs(x) < float("inf"))


@triton.jit
def _div(a, b):
    """a / b rounded as IEEE (float32 ``/`` compiles to an approximate division on CUDA)."""
    if a.dtype == tl.float32:
        return tl.div_rn(a, b)
    else:
        return a / b


@triton.jit
def _sqrt(x):
    """sqrt(x) rounded as IEEE (float32 ``tl.sqrt`` is an approximate one on CUDA)."""
    if x.dtype == tl.float32:
        return tl.sqrt_rn(x)
    else:
        return tl.sqrt(x)


@triton.jit
def _pick(vec, idx, a):
    """Element ``a`` of a small vector (a scalar)."""
    return tl.sum(tl.where(idx == a, vec, 0.0), axis=0)


@triton.jit
def _frame(flat_ptr, ox, oy, dxu, dyv, m, foff, x_lo, x_hi, y_lo, y_hi, shift, wp, sixth,
           two3, w, ft, gx, gy, b0, b1, b2, fn, inv_wsum, ZNSSD: tl.constexpr,
           HAS_TIME: tl.constexpr):
    """One frame of a point's right-hand side: the subset sampled at origin (ox, oy) (float64)
    plus (dxu, dyv), its ZNSSD/SSD residual against ft, and the frame's sums (float64):
    spatial b (x0s, x1s, x2s, y0s, y1s, y2s), the time column's sums (sx, sy; 0 without time)
    and the frame's ZNCC."""
    xs = ox.to(dxu.dtype) + dxu
    ys = oy.to(dxu.dtype) + dyv
    xs = tl.minimum(tl.maximum(xs, x_lo), x_hi)
    ys = tl.minimum(tl.maximum(ys, y_lo), y_hi)
    x0 = tl.floor(xs)
    y0 = tl.floor(ys)
    wx0, wx1, wx2, wx3 = _weights(xs - x0, sixth, two3)
    wy0, wy1, wy2, wy3 = _weights(ys - y0, sixth, two3)
    base = (y0.to(tl.int64) + shift) * wp + (x0.to(tl.int64) + shift) + foff
    g = tap_row(flat_ptr, base, m, wx0, wx1, wx2, wx3) * wy0
    g += tap_row(flat_ptr, base + wp, m, wx0, wx1, wx2, wx3) * wy1
    g += tap_row(flat_ptr, base + 2 * wp, m, wx0, wx1, wx2, wx3) * wy2
    g += tap_row(flat_ptr, base + 3 * wp, m, wx0, wx1, wx2, wx3) * wy3
    if ZNSSD:
        g = g - tl.sum(w * g, axis=0) * inv_wsum
    g = tl.where(m, g, 0.0)
    sgg = tl.sum(w * g * g, axis=0)
    sfg = tl.sum(w * ft * g, axis=0)
    gn = tl.sqrt(tl.maximum(sgg.to(tl.float64), 1e-30))  # float64: IEEE
    zt = sfg.to(tl.float64) / (fn * gn)
    if ZNSSD:
        a = (fn / gn).to(g.dtype)
        e = w * (ft - a * g)
    else:
        e = w * (ft - g)
    ex = gx * e
    ey = gy * e
    if HAS_TIME:
        sx = tl.sum(ex, axis=0).to(tl.float64)
        sy = tl.sum(ey, axis=0).to(tl.float64)
    else:
        sx = zt * 0.0
        sy = zt * 0.0
    return (tl.sum(ex * b0, axis=0).to(tl.float64), tl.sum(ex * b1, axis=0).to(tl.float64),
            tl.sum(ex * b2, axis=0).to(tl.float64), tl.sum(ey * b0, axis=0).to(tl.float64),
            tl.sum(ey * b1, axis=0).to(tl.float64), tl.sum(ey * b2, axis=0).to(tl.float64),
            sx, sy, zt)


@triton.jit
def _rhs(flat_ptr, dt_ptr, mo_ptr, foff_ptr, bf_ptr, i, NT, NTI, px, py, ut, vt, dxu, dyv, m,
         w_img, h, x_lo, x_hi, y_lo, y_hi, shift, wp, sixth, two3, w, ft, gx, gy, b0, b1, b2,
         fn, inv_wsum, ZNSSD: tl.constexpr, HAS_TIME: tl.constexpr, HAS_MOTION: tl.constexpr,
         FRAME_RHS: tl.constexpr):
    """The joint right-hand side of point ``i`` over its first NTI of NT frames (the later
    columns padding of a shorter window; float64: u terms, then v,
    each spatial then time), the sum of the frames' ZNCC and whether a warped subset leaves
    the image; with FRAME_RHS each frame's own spatial b and ZNCC into ``bf_ptr``."""
    big = 3.0e38
    xmn = tl.min(tl.where(m, dxu, big), axis=0).to(tl.float64)
    xmx = tl.max(tl.where(m, dxu, -big), axis=0).to(tl.float64)
    ymn = tl.min(tl.where(m, dyv, big), axis=0).to(tl.float64)
    ymx = tl.max(tl.where(m, dyv, -big), axis=0).to(tl.float64)
    zero = fn * 0.0
    bu0, bu1, bu2, but, bv0, bv1, bv2, bvt = zero, zero, zero, zero, zero, zero, zero, zero
    zsum = zero
    outside = zero < 0  # false
    for t in range(NTI):
        dti = tl.load(dt_ptr + i * NT + t).to(tl.float64)
        ox = px + ut * dti
        oy = py + vt * dti
        if HAS_MOTION:  # the known (shared) motion of this row's frame t
            ox += tl.load(mo_ptr + (i * NT + t) * 2).to(tl.float64)
            oy += tl.load(mo_ptr + (i * NT + t) * 2 + 1).to(tl.float64)
        outside = (outside | (ox + xmn < 0) | (ox + xmx > w_img - 1) | (oy + ymn < 0)
                   | (oy + ymx > h - 1))
        x0s, x1s, x2s, y0s, y1s, y2s, sx, sy, zt = _frame(
            flat_ptr, ox, oy, dxu, dyv, m, tl.load(foff_ptr + i * NT + t), x_lo, x_hi, y_lo,
            y_hi, shift, wp, sixth, two3, w, ft, gx, gy, b0, b1, b2, fn, inv_wsum, ZNSSD,
            HAS_TIME)
        zsum += zt
        bu0 += x0s
        bu1 += x1s
        bu2 += x2s
        bv0 += y0s
        bv1 += y1s
        bv2 += y2s
        if FRAME_RHS:  # frame t's own spatial right-hand side and its ZNCC
            bf = bf_ptr + (i * NT + t) * 7
            tl.store(bf, x0s)
            tl.store(bf + 1, x1s)
            tl.store(bf + 2, x2s)
            tl.store(bf + 3, y0s)
            tl.store(bf + 4, y1s)
            tl.store(bf + 5, y2s)
            tl.store(bf + 6, zt)
        if HAS_TIME:
            but += dti * sx
            bvt += dti * sy
    return bu0, bu1, bu2, but, bv0, bv1, bv2, bvt, zsum, outside


@triton.jit
def _step(hinv, pidx, bu0, bu1, bu2, but, bv0, bv1, bv2, bvt, HAS_TIME: tl.constexpr):
    """dp = -(Hinv b) (8,) in float64, b in the parameters' order (padded with zeros)."""
    if HAS_TIME:
        bvec = tl.where(pidx == 0, bu0, tl.where(pidx == 1, bu1, tl.where(
            pidx == 2, bu2, tl.where(pidx == 3, but, tl.where(pidx == 4, bv0, tl.where(
                pidx == 5, bv1, tl.where(pidx == 6, bv2, bvt)))))))
    else:
        bvec = tl.where(pidx == 0, bu0, tl.where(pidx == 1, bu1, tl.where(
            pidx == 2, bu2, tl.where(pidx == 3, bv0, tl.where(pidx == 4, bv1, tl.where(
                pidx == 5, bv2, bu0 * 0.0))))))
    return -tl.sum(hinv * bvec[None, :], axis=1)


@triton.jit
def _compose(pu0, pu1, pu2, put, pv0, pv1, pv2, pvt, dpv, pidx, K: tl.constexpr,
             HAS_TIME: tl.constexpr):
    """p o dp^-1 of the affine warp (the C++ affine_compose, AffineShape.compose_inverse):
    M = (I + D)(I + dD)^-1, b' = b - M db, bt' = bt - M dbt."""
    du0 = _pick(dpv, pidx, 0)
    dv0 = _pick(dpv, pidx, K)
    a00 = 1.0 + _pick(dpv, pidx, 1)
    a01 = _pick(dpv, pidx, 2)
    a10 = _pick(dpv, pidx, K + 1)
    a11 = 1.0 + _pick(dpv, pidx, K + 2)
    det = a00 * a11 - a01 * a10
    i00 = _div(a11, det)
    i01 = _div(-a01, det)
    i10 = _div(-a10, det)
    i11 = _div(a00, det)
    e00 = 1.0 + pu1
    e11 = 1.0 + pv2
    m00 = e00 * i00 + pu2 * i10
    m01 = e00 * i01 + pu2 * i11
    m10 = pv1 * i00 + e11 * i10
    m11 = pv1 * i01 + e11 * i11
    nu0 = pu0 - (m00 * du0 + m01 * dv0)
    nv0 = pv0 - (m10 * du0 + m11 * dv0)
    if HAS_TIME:
        dut = _pick(dpv, pidx, 3)
        dvt = _pick(dpv, pidx, 2 * K - 1)
        nut = put - (m00 * dut + m01 * dvt)
        nvt = pvt - (m10 * dut + m11 * dvt)
    else:
        nut = put
        nvt = pvt
    return nu0, m00 - 1.0, m01, nut, nv0, m10, m11 - 1.0, nvt


@triton.jit
def _store_params(ptr, pu0, pu1, pu2, put, pv0, pv1, pv2, pvt, K: tl.constexpr,
                  HAS_TIME: tl.constexpr):
    """The parameters (u terms, then v; each spatial then time) at ``ptr``."""
    tl.store(ptr, pu0)
    tl.store(ptr + 1, pu1)
    tl.store(ptr + 2, pu2)
    tl.store(ptr + K, pv0)
    tl.store(ptr + K + 1, pv1)
    tl.store(ptr + K + 2, pv2)
    if HAS_TIME:
        tl.store(ptr + 3, put)
        tl.store(ptr + K + 3, pvt)


@triton.jit
def _ic_solve_kernel(flat_ptr, p_ptr, px_ptr, py_ptr, dx_ptr, dy_ptr, basis_ptr, dt_ptr,
                     foff_ptr, ft_ptr, fnorm_ptr, gx_ptr, gy_ptr, w_ptr, ref_ptr, mo_ptr,
                     cnt_ptr, hinv_ptr, scale_ptr, prev_ptr, consts_ptr, zn_ptr, st_ptr, used_ptr,
                     bf_ptr, plast_ptr,
                     NT, S, wp, shift, w_img, h, max_iter,
                     C_CONV: tl.constexpr, C_MAXIT: tl.constexpr, C_DIV: tl.constexpr,
                     C_OUT: tl.constexpr, K: tl.constexpr, HAS_TIME: tl.constexpr,
                     ZNSSD: tl.constexpr, HAS_REF: tl.constexpr, HAS_MOTION: tl.constexpr,
                     FRAME_RHS: tl.constexpr, BLOCK_S: tl.constexpr):
    NP: tl.constexpr = 2 * K
    i = tl.program_id(0).to(tl.int64)
    nti = tl.minimum(tl.maximum(tl.load(cnt_ptr + i), 1), NT).to(tl.int32)  # frames in use
    if HAS_REF:
        r = tl.load(ref_ptr + i).to(tl.int64)
    else:
        r = i
    offs = tl.arange(0, BLOCK_S)
    m = offs < S
    w = tl.load(w_ptr + offs, mask=m, other=0.0)
    dx = tl.load(dx_ptr + offs, mask=m, other=0.0)
    dy = tl.load(dy_ptr + offs, mask=m, other=0.0)
    b0 = tl.load(basis_ptr + offs * 3, mask=m, other=0.0)
    b1 = tl.load(basis_ptr + offs * 3 + 1, mask=m, other=0.0)
    b2 = tl.load(basis_ptr + offs * 3 + 2, mask=m, other=0.0)
    ft = tl.load(ft_ptr + r * S + offs, mask=m, other=0.0)
    gx = tl.load(gx_ptr + r * S + offs, mask=m, other=0.0)
    gy = tl.load(gy_ptr + r * S + offs, mask=m, other=0.0)
    # tol, divergence bound, rate floor, 1 / sum(w), tap-origin clamp range, 1/6, 2/3: in the
    # data's dtype (as the C++ kernel compares and computes them)
    tol = tl.load(consts_ptr)
    div_norm = tl.load(consts_ptr + 1)
    rate_floor = tl.load(consts_ptr + 2)
    fn = tl.load(fnorm_ptr + i).to(tl.float64)
    px = tl.load(px_ptr + i).to(tl.float64)
    py = tl.load(py_ptr + i).to(tl.float64)
    # the inverse Hessian (P x P in an 8 x 8 tile) and the increments' scale
    pidx = tl.arange(0, 8)
    hmask = (pidx[:, None] < NP) & (pidx[None, :] < NP)
    hinv = tl.load(hinv_ptr + i * NP * NP + pidx[:, None] * NP + pidx[None, :], mask=hmask,
                   other=0.0)
    sc = tl.load(scale_ptr + i * NP + pidx, mask=pidx < NP, other=0.0)
    pj = p_ptr + i * NP
    # the parameters: u = (u, ux, uy[, ut]), v likewise
    pu0, pu1, pu2 = tl.load(pj), tl.load(pj + 1), tl.load(pj + 2)
    pv0, pv1, pv2 = tl.load(pj + K), tl.load(pj + K + 1), tl.load(pj + K + 2)
    if HAS_TIME:
        put = tl.load(pj + 3)
        pvt = tl.load(pj + K + 3)
    else:
        put = pu0 * 0.0
        pvt = pu0 * 0.0
    # the parameters of the last step: values of their own before the loop, never another
    # variable's (Triton's compiler finds a loop's carried variables by whether a name's value
    # changes in the loop body: ``ou0 = pu0`` inside the loop, with ou0 = pu0 before it, reads
    # as unchanged, and after the loop ou0 would be the parameters the solve started from; the
    # interpreter runs Python and does not show it). Every point takes at least one step.
    nan = pu0 * float("nan")
    ou0, ou1, ou2, out_, ov0, ov1, ov2, ovt = nan, nan, nan, nan, nan, nan, nan, nan
    prev = tl.load(prev_ptr + i)
    zn = prev * float("nan")
    st = tl.full([], C_MAXIT, tl.int32)
    it = tl.full([], 0, tl.int32)
    going = it < max_iter
    while going:
        # warp of the subset without its origin (as the C++ kernel: basis sum, then dx)
        dxu = pu0 * b0
        dxu += pu1 * b1
        dxu += pu2 * b2
        dyv = pv0 * b0
        dyv += pv1 * b1
        dyv += pv2 * b2
        dxu += dx
        dyv += dy
        bu0, bu1, bu2, but, bv0, bv1, bv2, bvt, zsum, outside = _rhs(
            flat_ptr, dt_ptr, mo_ptr, foff_ptr, bf_ptr, i, NT, nti, px, py, put.to(tl.float64),
            pvt.to(tl.float64), dxu, dyv, m, w_img, h, tl.load(consts_ptr + 4),
            tl.load(consts_ptr + 5), tl.load(consts_ptr + 6), tl.load(consts_ptr + 7), shift,
            wp, tl.load(consts_ptr + 8), tl.load(consts_ptr + 9), w, ft, gx, gy, b0, b1, b2,
            fn, tl.load(consts_ptr + 3), ZNSSD, HAS_TIME, HAS_MOTION, FRAME_RHS)
        zn = (zsum / nti).to(zn.dtype)
        # dp = -(Hinv b) in float64, then the data's dtype; p o dp^-1
        dpv = _step(hinv, pidx, bu0, bu1, bu2, but, bv0, bv1, bv2, bvt, HAS_TIME).to(pu0.dtype)
        nu0, nu1, nu2, nut, nv0, nv1, nv2, nvt = _compose(pu0, pu1, pu2, put, pv0, pv1, pv2,
                                                          pvt, dpv, pidx, K, HAS_TIME)
        it += 1
        d = dpv * sc
        norm = _sqrt(tl.sum(d * d, axis=0))
        finite = (_finite(norm) & _finite(nu0) & _finite(nu1) & _finite(nu2) & _finite(nut)
                  & _finite(nv0) & _finite(nv1) & _finite(nv2) & _finite(nvt))
        bad = (~finite) | (norm > div_norm)
        rate = tl.where(prev > 0, _div(norm, tl.where(prev > 0, prev, 1.0)), 1.0)
        rate = tl.minimum(tl.maximum(rate, rate_floor), 1.0)
        conv = finite & (norm * rate < tol) & (~outside)
        prev = norm
        ou0, ou1, ou2, out_ = pu0, pu1, pu2, put
        ov0, ov1, ov2, ovt = pv0, pv1, pv2, pvt
        pu0, pu1, pu2 = tl.where(finite, nu0, pu0), tl.where(finite, nu1, pu1), tl.where(
            finite, nu2, pu2)
        pv0, pv1, pv2 = tl.where(finite, nv0, pv0), tl.where(finite, nv1, pv1), tl.where(
            finite, nv2, pv2)
        put, pvt = tl.where(finite, nut, put), tl.where(finite, nvt, pvt)
        ended = conv | bad | outside
        st = tl.where(ended, tl.where(bad, C_DIV, tl.where(outside, C_OUT, C_CONV)), st)
        going = (~ended) & (it < max_iter)
    _store_params(pj, pu0, pu1, pu2, put, pv0, pv1, pv2, pvt, K, HAS_TIME)
    tl.store(zn_ptr + i, zn)
    tl.store(st_ptr + i, st.to(tl.int8))
    tl.store(used_ptr + i, it)
    if FRAME_RHS:  # the last step's parameters; NaN (and NaN right-hand sides) at max_iter
        ran_out = st == C_MAXIT
        _store_params(plast_ptr + i * NP, tl.where(ran_out, nan, ou0),
                      tl.where(ran_out, nan, ou1), tl.where(ran_out, nan, ou2),
                      tl.where(ran_out, nan, out_), tl.where(ran_out, nan, ov0),
                      tl.where(ran_out, nan, ov1), tl.where(ran_out, nan, ov2),
                      tl.where(ran_out, nan, ovt), K, HAS_TIME)
        fidx = tl.arange(0, 8)
        for t in range(NT):  # and at a shorter window's padding columns
            tl.store(bf_ptr + (i * NT + t) * 7 + fidx, tl.full([8], float("nan"), tl.float64),
                     mask=(fidx < 7) & ((fidx * 0 + st == C_MAXIT) | (fidx * 0 + t >= nti)))


def ic_solve_triton(img_args: tuple, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx,
                    gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool, hinv, scale,
                    prev, tol: float, max_iter: int, div_norm: float, rate_floor: float,
                    codes: tuple[int, int, int, int], motion=None, ref_rows=None,
                    frame_rhs: bool = False, count=None):
    """Every point's joint IC-GN stage to its end in one launch: the arguments and results of
    :func:`torch_stsdic.kernels.native.ic_solve` (the C++ twin), on the image's device.

    ``img_args`` from :meth:`BSplineImage.kernel_args` (cubic coefficients); p (N, 2k) with
    k = 3 (+ 1 with time); px, py, fnorm, prev (N,) or (N, 1); dx, dy, w (S,); basis (S, 3);
    dt and frame_off (N, T) (frame offsets in coefficients); ft, gx, gy (R, S) reference
    subsets, row ``ref_rows[i]`` for point i (None: R = N, row i); hinv (N, P, P) the inverse
    Hessians; scale (N, P) the increments' scale; motion (N, T, 2) or None; count (N,) each
    point's frames in use (its first ``count[i]``, the later columns padding) or None.

    Returns p (N, 2k), the last step's mean ZNCC (N,), status (N,) int8, iterations (N,)
    int32 and, with ``frame_rhs``, (the parameters (N, P) of each point's last step, its
    frame-by-frame spatial right-hand sides and ZNCCs (N, T, 7) float64; NaN where a point ran
    out of iterations), else None."""
    flat, wp, x_lo, x_hi, y_lo, y_hi, shift, _ = img_args
    dtype, dev = flat.dtype, flat.device
    (n, nt), (s, ks) = dt.shape, basis.shape
    if ks != 3 or k != ks + int(has_time) or tuple(p.shape) != (n, 2 * k):
        raise ValueError(f"ic_solve_triton: affine shapes only: p (N, 2k) with k = 3 (+ 1 with "
                         f"time), got {tuple(p.shape)}, k={k}, Ks={ks}")
    if s > MAX_SUBSET_PIXELS:
        raise ValueError(f"ic_solve_triton: at most {MAX_SUBSET_PIXELS} subset pixels, got {s}")

    def c(t):
        return t.to(device=dev, dtype=dtype).contiguous()

    out_p = c(p).clone()
    zn = torch.empty(n, dtype=dtype, device=dev)
    status = torch.empty(n, dtype=torch.int8, device=dev)
    used = torch.empty(n, dtype=torch.int32, device=dev)
    bframe = (torch.empty(n, nt, 2 * ks + 1, dtype=torch.float64, device=dev) if frame_rhs
              else None)
    plast = torch.empty(n, 2 * k, dtype=dtype, device=dev) if frame_rhs else None
    last = (plast, bframe) if frame_rhs else None
    if n == 0:
        return out_p, zn, status, used, last
    consts = torch.tensor([tol, div_norm, rate_floor, 0.0, x_lo, x_hi, y_lo, y_hi,
                           1.0 / 6.0, 2.0 / 3.0], dtype=dtype, device=dev)
    consts[3] = 1.0 / w.to(device=dev, dtype=torch.float64).sum()  # on the device: no read
    block = max(16, triton.next_power_of_2(s))
    dummy = out_p
    _ic_solve_kernel[(n,)](
        flat.contiguous(), out_p, c(px.reshape(-1)), c(py.reshape(-1)), c(dx), c(dy),
        c(basis), c(dt), frame_off.to(device=dev, dtype=torch.int64).contiguous(), c(ft),
        c(fnorm.reshape(-1)), c(gx), c(gy), c(w),
        dummy if ref_rows is None else ref_rows.to(device=dev, dtype=torch.int64).contiguous(),
        dummy if motion is None else c(motion),
        (torch.full((n,), nt, dtype=torch.int64, device=dev) if count is None  # (filled there)
         else count.to(device=dev, dtype=torch.int64).contiguous()),
        hinv.to(device=dev, dtype=torch.float64).contiguous(), c(scale),
        c(prev.reshape(-1)), consts, zn, status, used,
        dummy if bframe is None else bframe, dummy if plast is None else plast,
        nt, s, int(wp), int(shift), float(w_img), float(h), int(max_iter),
        C_CONV=int(codes[0]), C_MAXIT=int(codes[1]), C_DIV=int(codes[2]), C_OUT=int(codes[3]),
        K=int(k), HAS_TIME=bool(has_time), ZNSSD=bool(znssd), HAS_REF=ref_rows is not None,
        HAS_MOTION=motion is not None, FRAME_RHS=bool(frame_rhs), BLOCK_S=block,
        num_warps=4 if block <= 512 else 8,
    )
    return out_p, zn, status, used, last
