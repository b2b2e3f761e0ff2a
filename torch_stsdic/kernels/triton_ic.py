"""The fused joint IC-GN step in Triton: warp + cubic B-spline sampling + ZNSSD/SSD residual
+ J^T r over all frames of a point, one program per point.

Same conventions and result as :func:`torch_stsdic.core.formulations.joint_ic.ic_rhs_kernel` (the
torch code) and ``native.ic_rhs`` (the C++ CPU kernel): for point ``j`` (data row ``i``),

    u_s,t = sum_q p_q B_sq + ut dt_t + mu_i,t,  x_s,t = px_i + dx_s + u_s,t   (likewise v, y)
    g_s,t = spline of frame t at (x_s,t, y_s,t)
    e_s,t = w_s (ft_s - |ft| / |g~_t| g~_t)   (ZNSSD, g~ zero-mean)   or   w_s (ft_s - g_s,t)
    b = [sum_s gx_s B_sq sum_t e_s,t, sum_s gx_s sum_t dt_t e_s,t, (same with gy)]

with ``mu_i,t`` (and ``mv_i,t``) the known displacement of data row ``i``'s frame ``t`` (the
specimen's shared motion, ``motion`` (N, T, 2); zero without it).

The subset (S pixels) lives in one block of ``next_pow2(S)`` lanes, so each frame is sampled
once (16 gathers per pixel); frames are a loop, so the Gauss-Newton right-hand side of a
point with T frames is one pass over T x S samples with nothing written to memory but b, the
mean ZNCC and the outside flag. Cubic splines only (order 3); float32 or float64.

Imported only where Triton is installed; set ``TRITON_INTERPRET=1`` before the first import
to run it on CPU tensors (Triton's interpreter: slow, for tests).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from torch_stsdic.kernels.ic_step import frames_in_use

__all__ = ["ic_rhs_triton", "tap_row", "MAX_SUBSET_PIXELS"]

#: largest subset (pixels) one program holds in registers (41x41 = 1681 fits in 2048 lanes)
MAX_SUBSET_PIXELS = 4096


@triton.jit
def _cubic_weights(f):
    """Cubic B-spline tap weights at fraction f (taps floor(x) - 1 .. floor(x) + 2)."""
    f2 = f * f
    f3 = f2 * f
    g = 1.0 - f
    return (g * g * g / 6.0, (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0,
            (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0, f3 / 6.0)


@triton.jit
def tap_row(flat_ptr, base, m, w0, w1, w2, w3):
    """One row of 4 taps of the coefficients at ``base`` (the block's lanes, mask ``m``)
    weighted by the x weights ``w0`` .. ``w3`` (shared with :mod:`.triton_solve`)."""
    c0 = tl.load(flat_ptr + base, mask=m, other=0.0)
    c1 = tl.load(flat_ptr + base + 1, mask=m, other=0.0)
    c2 = tl.load(flat_ptr + base + 2, mask=m, other=0.0)
    c3 = tl.load(flat_ptr + base + 3, mask=m, other=0.0)
    return c0 * w0 + c1 * w1 + c2 * w2 + c3 * w3


@triton.jit
def _ic_rhs_kernel(flat_ptr, p_ptr, px_ptr, py_ptr, dx_ptr, dy_ptr, basis_ptr, dt_ptr,
                   foff_ptr, ft_ptr, fnorm_ptr, gx_ptr, gy_ptr, w_ptr, rows_ptr,
                   b_ptr, zn_ptr, out_ptr, bf_ptr, mo_ptr, cnt_ptr,
                   NT, S, wp, x_lo, x_hi, y_lo, y_hi, shift, w_img, h,
                   KS: tl.constexpr, K: tl.constexpr, HAS_TIME: tl.constexpr,
                   ZNSSD: tl.constexpr, HAS_ROWS: tl.constexpr, BLOCK_S: tl.constexpr,
                   FRAME_RHS: tl.constexpr, HAS_MOTION: tl.constexpr,
                   HAS_COUNT: tl.constexpr):
    j = tl.program_id(0).to(tl.int64)
    if HAS_ROWS:
        i = tl.load(rows_ptr + j).to(tl.int64)
    else:
        i = j
    offs = tl.arange(0, BLOCK_S)
    m = offs < S
    w = tl.load(w_ptr + offs, mask=m, other=0.0)
    wsum = tl.sum(w, axis=0)
    dx = tl.load(dx_ptr + offs, mask=m, other=0.0)
    dy = tl.load(dy_ptr + offs, mask=m, other=0.0)
    ft = tl.load(ft_ptr + i * S + offs, mask=m, other=0.0)
    fn = tl.load(fnorm_ptr + i)
    px = tl.load(px_ptr + i)
    py = tl.load(py_ptr + i)
    pj = p_ptr + j * (2 * K)
    # spatial part of the warp (the same for every frame)
    xs0 = px + dx
    ys0 = py + dy
    for q in tl.static_range(KS):
        bq = tl.load(basis_ptr + offs * KS + q, mask=m, other=0.0)
        xs0 += tl.load(pj + q) * bq
        ys0 += tl.load(pj + K + q) * bq
    if HAS_TIME:
        ut = tl.load(pj + K - 1)
        vt = tl.load(pj + 2 * K - 1)
    gx = tl.load(gx_ptr + i * S + offs, mask=m, other=0.0)
    gy = tl.load(gy_ptr + i * S + offs, mask=m, other=0.0)
    e1 = tl.zeros([BLOCK_S], dtype=ft.dtype)
    e2 = tl.zeros([BLOCK_S], dtype=ft.dtype)
    zsum = tl.sum(e1, axis=0)  # a zero scalar of the data's dtype
    outside = tl.full([], 0, tl.int32)
    if HAS_COUNT:  # a shorter window: its first frames, the later columns padding
        nti = tl.minimum(tl.maximum(tl.load(cnt_ptr + i), 1), NT).to(tl.int32)
    else:
        nti = NT
    for t in range(nti):
        dtt = tl.load(dt_ptr + i * NT + t)
        if HAS_TIME:
            xs = xs0 + ut * dtt
            ys = ys0 + vt * dtt
        else:
            xs = xs0
            ys = ys0
        if HAS_MOTION:  # the known (shared) motion of this row's frame t
            xs = xs + tl.load(mo_ptr + (i * NT + t) * 2)
            ys = ys + tl.load(mo_ptr + (i * NT + t) * 2 + 1)
        big = 3.0e38
        lo_x = tl.min(tl.where(m, xs, big), axis=0)
        hi_x = tl.max(tl.where(m, xs, -big), axis=0)
        lo_y = tl.min(tl.where(m, ys, big), axis=0)
        hi_y = tl.max(tl.where(m, ys, -big), axis=0)
        leaves = (lo_x < 0) | (hi_x > w_img - 1) | (lo_y < 0) | (hi_y > h - 1)
        outside = outside | leaves.to(tl.int32)
        # cubic B-spline value at (xs, ys): 4 x 4 taps of the padded coefficients
        xc = tl.minimum(tl.maximum(xs, x_lo), x_hi)
        yc = tl.minimum(tl.maximum(ys, y_lo), y_hi)
        x0 = tl.floor(xc)
        y0 = tl.floor(yc)
        wx0, wx1, wx2, wx3 = _cubic_weights(xc - x0)
        wy0, wy1, wy2, wy3 = _cubic_weights(yc - y0)
        foff = tl.load(foff_ptr + i * NT + t)
        base = (y0.to(tl.int64) + shift) * wp + (x0.to(tl.int64) + shift) + foff
        g = tap_row(flat_ptr, base, m, wx0, wx1, wx2, wx3) * wy0
        g += tap_row(flat_ptr, base + wp, m, wx0, wx1, wx2, wx3) * wy1
        g += tap_row(flat_ptr, base + 2 * wp, m, wx0, wx1, wx2, wx3) * wy2
        g += tap_row(flat_ptr, base + 3 * wp, m, wx0, wx1, wx2, wx3) * wy3
        if ZNSSD:
            g = g - tl.sum(g * w, axis=0) / wsum
        gg = tl.maximum(tl.sum(g * g * w, axis=0), 1e-30)
        gn = tl.sqrt(gg)
        zt = tl.sum(ft * g * w, axis=0) / (fn * gn)
        zsum += zt
        if ZNSSD:
            e = (ft - (fn / gn) * g) * w
        else:
            e = (ft - g) * w
        e = tl.where(m, e, 0.0)
        e1 += e
        e2 += e * dtt
        if FRAME_RHS:  # frame t's own spatial right-hand side (a classical step's), its ZNCC
            bf = bf_ptr + (j * NT + t) * (2 * KS + 1)
            for q in tl.static_range(KS):
                bq = tl.load(basis_ptr + offs * KS + q, mask=m, other=0.0)
                tl.store(bf + q, tl.sum(gx * e * bq, axis=0).to(tl.float64))
                tl.store(bf + KS + q, tl.sum(gy * e * bq, axis=0).to(tl.float64))
            tl.store(bf + 2 * KS, zt.to(tl.float64))
    gxe = gx * e1
    gye = gy * e1
    bj = b_ptr + j * (2 * K)
    for q in tl.static_range(KS):
        bq = tl.load(basis_ptr + offs * KS + q, mask=m, other=0.0)
        tl.store(bj + q, tl.sum(gxe * bq, axis=0).to(tl.float64))
        tl.store(bj + K + q, tl.sum(gye * bq, axis=0).to(tl.float64))
    if HAS_TIME:
        tl.store(bj + K - 1, tl.sum(gx * e2, axis=0).to(tl.float64))
        tl.store(bj + 2 * K - 1, tl.sum(gy * e2, axis=0).to(tl.float64))
    tl.store(zn_ptr + j, zsum / nti)
    tl.store(out_ptr + j, outside.to(tl.int8))


def ic_rhs_triton(flat, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm, gx, gy, w, rows,
                  wp: int, x_lo: float, x_hi: float, y_lo: float, y_hi: float, shift: int,
                  w_img: int, h: int, k: int, has_time: bool, znssd: bool, frame_rhs=None,
                  motion=None, count=None):
    """Launch the kernel. Shapes: p (M, 2k), px/py/fnorm (N,) or (N, 1), dx/dy/w (S,), basis
    (S, Ks), dt and frame_off (N, T) (frame_off in coefficients, int64), ft/gx/gy (N, S),
    rows (M,) data row of each row of p or None (M = N); ``frame_rhs`` a contiguous float64
    (M, T, 2 Ks + 1) tensor on the device, filled with each frame's own spatial right-hand
    side and its ZNCC (as ``native.ic_rhs``), or None; ``motion`` (N, T, 2) the known
    displacement added to each data row's warp of frame t (as ``native.ic_rhs``), or None;
    ``count`` (N,) each data row's frames in use (as ``native.ic_rhs``: the later columns
    padding, skipped, NaN in ``frame_rhs``), or None. Returns b (M, 2k) float64, mean ZNCC
    (M,) in p's dtype and the outside flag (M,) bool."""
    dtype = flat.dtype
    m_rows = p.shape[0]
    n_t = dt.shape[1]
    s, ks = basis.shape
    dev = flat.device

    def c(t):
        return t.to(device=dev, dtype=dtype).contiguous()

    b = torch.empty(m_rows, 2 * k, dtype=torch.float64, device=dev)
    zn = torch.empty(m_rows, dtype=dtype, device=dev)
    out = torch.empty(m_rows, dtype=torch.int8, device=dev)
    if m_rows == 0:
        return b, zn, out.bool()
    block = max(16, triton.next_power_of_2(s))
    rows_t = (rows.to(device=dev, dtype=torch.int64).contiguous() if rows is not None
              else torch.zeros(1, dtype=torch.int64, device=dev))
    _ic_rhs_kernel[(m_rows,)](
        flat.contiguous(), c(p), c(px.reshape(-1)), c(py.reshape(-1)), c(dx), c(dy),
        c(basis), c(dt), frame_off.to(device=dev, dtype=torch.int64).contiguous(), c(ft),
        c(fnorm.reshape(-1)), c(gx), c(gy), c(w), rows_t, b, zn, out,
        b if frame_rhs is None else frame_rhs, b if motion is None else c(motion),
        rows_t if count is None else count.to(device=dev, dtype=torch.int64).contiguous(),
        n_t, s, int(wp), float(x_lo), float(x_hi), float(y_lo), float(y_hi), int(shift),
        float(w_img), float(h),
        KS=ks, K=k, HAS_TIME=bool(has_time), ZNSSD=bool(znssd), HAS_ROWS=rows is not None,
        BLOCK_S=block, FRAME_RHS=frame_rhs is not None, HAS_MOTION=motion is not None,
        HAS_COUNT=count is not None, num_warps=4 if block <= 512 else 8,
    )
    if frame_rhs is not None and count is not None:  # no right-hand side of a padding frame
        rows_c = count.to(dev) if rows is None else count.to(dev)[rows.to(dev)]
        frame_rhs.masked_fill_(~frames_in_use(rows_c, n_t).unsqueeze(-1), float("nan"))
    return b, zn, out.bool()
