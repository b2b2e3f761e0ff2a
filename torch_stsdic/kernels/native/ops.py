"""The native twins of the torch sampling and IC-GN kernels, called like the torch code.

Each wrapper checks the sizes the C code indexes by (ValueError ``native.<fn>: ...``),
makes the tensors contiguous in the image's dtype, allocates the outputs and runs the
kernel over its rows (:func:`.rows.run_rows`). Callers decide with :func:`.loader.usable`
whether to take this path.
"""

from __future__ import annotations

import torch

from torch_stsdic.kernels.native.loader import kernel
from torch_stsdic.kernels.native.rows import run_rows, run_shared, threads

__all__ = ["sample", "subsets", "windows", "ic_rhs", "ic_solve", "gram", "spd_inverse", "param_std",
           "nanmedian", "prefilter", "neighbour_own_gradient", "neighbour_test", "splat",
           "splat_add", "splat_fused", "splat_finish", "sobel_counts", "flat_sums"]


def _geo(img_args: tuple, order: int) -> dict:
    """The geometry arguments shared by the sampling kernels: padded width, clamp range, tap
    shift, spline order (the coefficients go as ``flat``)."""
    _, wp, x_lo, x_hi, y_lo, y_hi, shift, _plane = img_args
    return dict(wp=wp, x_lo=x_lo, x_hi=x_hi, y_lo=y_lo, y_hi=y_hi, shift=shift, order=order)


def _broadcast(*shapes: torch.Size) -> torch.Size:
    """The broadcast of ``shapes`` (numpy rules). ``torch.broadcast_shapes`` imports sympy
    (through torch's symbolic shapes) on its first call: 0.3 s of every run's first sample."""
    k = max(len(s) for s in shapes)
    out = []
    for dims in zip(*[(1,) * (k - len(s)) + tuple(s) for s in shapes]):
        big = max((d for d in dims if d != 1), default=1)
        if any(d not in (1, big) for d in dims):
            raise ValueError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
        out.append(big)
    return torch.Size(out)


def _require(fn: str, ok: bool, what: str) -> None:
    """The wrappers' size checks: the kernels index their arrays by these sizes (the
    declarations check kinds and dtypes, not sizes)."""
    if not ok:
        raise ValueError(f"native.{fn}: {what}")


def _check_planes(fn: str, img_args: tuple, off: torch.Tensor) -> None:
    """Plane offsets (int64) within the coefficient array."""
    if off.numel():
        lo, hi = (int(v) for v in torch.aminmax(off))
        last = img_args[0].numel() - img_args[-1]
        _require(fn, 0 <= lo and hi <= last,
                 f"plane offsets [{lo}, {hi}] outside the image's [0, {last}]")


def _check_count(fn: str, count: torch.Tensor | None, n: int) -> None:
    """A window's frames in use per data row: (N,) (the kernels clamp it to [1, T])."""
    _require(fn, count is None or tuple(count.shape) == (n,),
             f"count must be (N,) = ({n},) frames in use per row")


def _count(count: torch.Tensor | None) -> torch.Tensor | None:
    return None if count is None else count.to(torch.int64).contiguous()


def sample(img_args: tuple, order: int, x: torch.Tensor, y: torch.Tensor,
           frame_off: torch.Tensor, grad: bool):
    """Native twin of interpolation.sample_kernel: values (shape of x) and, with grad, d/dx
    and d/dy. ``frame_off`` (int64 plane offsets) broadcasts against x (e.g. (N, 1) for
    (N, S) points)."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    shape = _broadcast(x.shape, y.shape, frame_off.shape)
    xc = x.to(dtype).expand(shape).contiguous()
    yc = y.to(dtype).expand(shape).contiguous()
    off = frame_off.to(torch.int64)
    # the offset array is indexed as off[i // period]: possible when off's shape is shape's
    # leading dims followed by ones; otherwise materialise it
    lead = off.dim() - len(shape)
    oshape = (1,) * max(0, -lead) + tuple(off.shape)
    k = len(shape)
    while k > 0 and oshape[k - 1] == 1:
        k -= 1
    if off.numel() == 1:
        off_c, period = off.reshape(1).contiguous(), 0
    elif tuple(oshape[:k]) == tuple(shape[:k]):
        off_c = off.reshape(-1).contiguous()
        period = int(torch.Size(shape[k:]).numel())
    else:
        off_c, period = off.expand(shape).contiguous().reshape(-1), 1
    _check_planes("sample", img_args, off_c)
    n = xc.numel()
    val = torch.empty(shape, dtype=dtype)
    gx = torch.empty(shape, dtype=dtype) if grad else None
    gy = torch.empty(shape, dtype=dtype) if grad else None
    run_rows(kernel("sts_sample", dtype), n, 1,
              dict(flat=flat, **_geo(img_args, order), x=xc, y=yc, off=off_c,
                   off_period=period, val=val, gx=gx, gy=gy))
    return (val, gx, gy) if grad else val


def subsets(img_args: tuple, order: int, px, py, dx, dy, frame_off, grad: bool):
    """Samples of whole subsets: (px[i] + dx[s], py[i] + dy[s]) in the plane at frame_off[i];
    px, py, frame_off (N,) (or (N, 1)), dx, dy (S,). Returns values (N, S) (and d/dx, d/dy)."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    n, ns = px.numel(), dx.numel()
    tens = {k: t.to(dtype).reshape(-1).contiguous()
            for k, t in dict(px=px, py=py, dx=dx, dy=dy).items()}
    _require("subsets", tens["py"].numel() == n and tens["dy"].numel() == ns
             and frame_off.numel() in (1, n), "px, py, frame_off (N,) and dx, dy (S,)")
    off = frame_off.to(torch.int64).reshape(-1).expand(n).contiguous()
    _check_planes("subsets", img_args, off)
    val = torch.empty(n, ns, dtype=dtype)
    gx = torch.empty(n, ns, dtype=dtype) if grad else None
    gy = torch.empty(n, ns, dtype=dtype) if grad else None
    run_rows(kernel("sts_subsets", dtype), n, ns,
              dict(flat=flat, **_geo(img_args, order), ns=ns, **tens, off=off, val=val, gx=gx,
                   gy=gy))
    return (val, gx, gy) if grad else val


def ic_rhs(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
           gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool,
           rows: torch.Tensor | None = None, motion: torch.Tensor | None = None,
           ref_rows: torch.Tensor | None = None, frame_rhs: torch.Tensor | None = None,
           count: torch.Tensor | None = None):
    """Native twin of formulations.joint_ic.ic_rhs_kernel. Shapes: p (M, 2k), px/py (N, 1) or (N,),
    dx/dy/w (S,), basis (S, Ks), dt and frame_off (N, T), ft/gx/gy (N, S), fnorm (N,);
    ``rows`` (M,) picks the per-point data rows of p's rows (default: M = N, row j = j);
    ``motion`` (N, T, 2) a known displacement added to each row's warp of frame t (None: none);
    ``ref_rows`` (N,) the row of ft/gx/gy (then (R, S)) of each data row (a point repeated
    over targets: one copy of its reference subset; None: row i); ``frame_rhs`` a float64
    (M, T, 2 Ks + 1) tensor filled with each frame's own spatial part of b (the classical
    right-hand side of that frame at the row's warp), then that frame's ZNCC, or None
    (NaN at a row's padding frames); ``count`` (N,) each data row's frames in use, its
    first ``count[i]`` columns of dt and frame_off (the others padding, skipped; None: all
    T). Returns b (M, 2k) float64, per-POI mean ZNCC (M,) and the outside flag (M,) bool."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    n, (big_n, nt), (ns, ks) = p.shape[0], dt.shape, basis.shape
    _require("ic_rhs", tuple(p.shape) == (n, 2 * k) and k == ks + int(has_time),
             f"p must be (M, 2k) with k = Ks (+ 1 with time), got {tuple(p.shape)}, k={k}, "
             f"Ks={ks}")
    n_ref = big_n if ref_rows is None else ft.shape[0]
    _require("ic_rhs", all(tuple(t.shape) == (n_ref, ns) for t in (ft, gx, gy))
             and all(t.numel() == big_n for t in (px, py, fnorm))
             and all(t.numel() == ns for t in (dx, dy, w)) and frame_off.shape == dt.shape
             and ns > 0,
             "shapes: px/py/fnorm (N,), dx/dy/w (S,), basis (S, Ks), dt and frame_off "
             "(N, T), ft/gx/gy (N, S)")
    if rows is None:
        _require("ic_rhs", n == big_n, f"p has {n} rows for {big_n} points (pass rows)")
    else:
        _require("ic_rhs", rows.shape == (n,) and (n == 0 or 0 <= int(rows.min())
                                                  and int(rows.max()) < big_n),
                 f"rows must be (M,) = ({n},) indices into the {big_n} points")
    if ref_rows is not None:
        _require("ic_rhs", ref_rows.shape == (big_n,) and (big_n == 0 or 0 <= int(
            ref_rows.min()) and int(ref_rows.max()) < n_ref),
                 f"ref_rows must be (N,) = ({big_n},) indices into the {n_ref} subsets")
    frame_off = frame_off.to(torch.int64).contiguous()
    _check_planes("ic_rhs", img_args, frame_off)
    _require("ic_rhs", motion is None or tuple(motion.shape) == (big_n, nt, 2),
             f"motion must be (N, T, 2) = ({big_n}, {nt}, 2)")
    _require("ic_rhs", frame_rhs is None or (tuple(frame_rhs.shape) == (n, nt, 2 * ks + 1)
                                             and frame_rhs.dtype == torch.float64
                                             and frame_rhs.is_contiguous()),
             f"frame_rhs must be a contiguous float64 (M, T, 2 Ks + 1) = ({n}, {nt}, "
             f"{2 * ks + 1})")
    _check_count("ic_rhs", count, big_n)

    def c(t):
        return t.to(dtype).contiguous()

    b = torch.empty(n, 2 * k, dtype=torch.float64)
    zn = torch.empty(n, dtype=dtype)
    out = torch.empty(n, dtype=torch.uint8)
    run_rows(kernel("sts_ic_rhs", dtype), n, nt * ns,
              dict(flat=flat, **_geo(img_args, order), nt=nt, ns=ns, ks=ks, k=k,
                   has_time=int(has_time), znssd=int(znssd), p=c(p), px=c(px.reshape(-1)),
                   py=c(py.reshape(-1)), dx=c(dx), dy=c(dy), basis=c(basis), dt=c(dt),
                   frame_off=frame_off, ft=c(ft),
                   fnorm=c(fnorm.reshape(-1)), gx=c(gx), gy=c(gy), w=c(w),
                   rows=None if rows is None else rows.to(torch.int64).contiguous(),
                   ref_rows=None if ref_rows is None else ref_rows.to(torch.int64).contiguous(),
                   motion=None if motion is None else c(motion), count=_count(count),
                   w_img=float(w_img), h=float(h), b=b, zn=zn, outside=out,
                   bframe=frame_rhs))
    return b, zn, out.bool()


def ic_solve(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
             gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool, hinv, scale,
             prev, tol: float, max_iter: int, div_norm: float, rate_floor: float,
             codes: tuple[int, int, int, int], motion=None, ref_rows=None,
             frame_rhs: bool = False, count: torch.Tensor | None = None):
    """Every point's joint IC-GN solve to its end in one call (C++ ``sts_ic_solve``: threads
    take chunks of points from a shared counter and iterate each one to convergence, with no
    barrier per iteration). The arguments are :func:`ic_rhs`'s (the rows of ``p`` (N, P) are
    the data rows), with ``hinv`` (N, P, P) the inverse Hessians, ``scale`` (N, P) the
    increments' scale, ``prev`` (N,) the previous increments (0: none), the convergence
    tolerance, iteration limit, divergence bound of the increment and rate floor, and
    ``codes`` the statuses (converged, max_iter, diverged, outside). Affine shapes (Ks = 3).

    Returns p (N, P) (the end of each point's iteration), the last step's mean ZNCC (N,),
    status (N,) int8, iterations (N,) int32 and, with ``frame_rhs``, (the parameters (N, P)
    of each point's last step, that step's frame-by-frame right-hand sides and ZNCCs
    (N, T, 2 Ks + 1) float64; NaN where the point ran out of iterations), else None."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    (n, nt), (ns, ks) = dt.shape, basis.shape
    n_ref = n if ref_rows is None else ft.shape[0]
    _require("ic_solve", ks == 3 and k == ks + int(has_time) and tuple(p.shape) == (n, 2 * k),
             f"affine shapes only: p (N, 2k) with k = 3 (+ 1 with time), got "
             f"{tuple(p.shape)}, k={k}, Ks={ks}")
    _require("ic_solve", all(tuple(t.shape) == (n_ref, ns) for t in (ft, gx, gy))
             and all(t.numel() == n for t in (px, py, fnorm, prev))
             and all(t.numel() == ns for t in (dx, dy, w)) and frame_off.shape == dt.shape
             and tuple(hinv.shape) == (n, 2 * k, 2 * k) and tuple(scale.shape) == (n, 2 * k)
             and ns > 0, "shapes: px/py/fnorm/prev (N,), dx/dy/w (S,), dt and frame_off "
             "(N, T), ft/gx/gy (N, S), hinv (N, P, P), scale (N, P)")
    if ref_rows is not None:
        _require("ic_solve", ref_rows.shape == (n,) and (n == 0 or 0 <= int(ref_rows.min())
                                                        and int(ref_rows.max()) < n_ref),
                 f"ref_rows must be (N,) = ({n},) indices into the {n_ref} subsets")
    _require("ic_solve", motion is None or tuple(motion.shape) == (n, nt, 2),
             f"motion must be (N, T, 2) = ({n}, {nt}, 2)")
    _check_count("ic_solve", count, n)
    frame_off = frame_off.to(torch.int64).contiguous()
    _check_planes("ic_solve", img_args, frame_off)

    def c(t):
        return t.to(dtype).contiguous()

    out_p = c(p).clone()
    zn = torch.empty(n, dtype=dtype)
    status = torch.empty(n, dtype=torch.uint8)
    used = torch.empty(n, dtype=torch.int32)
    bframe = torch.empty(n, nt, 2 * ks + 1, dtype=torch.float64) if frame_rhs else None
    plast = torch.empty(n, 2 * k, dtype=dtype) if frame_rhs else None
    n_threads = threads()
    chunk = max(1, min(16, n // max(1, 32 * n_threads)))
    run_shared(kernel("sts_ic_solve", dtype), n, 3 * nt * ns,
               dict(flat=flat, **_geo(img_args, order), counter=torch.zeros(1, dtype=torch.int64),
                    chunk=chunk, nt=nt, ns=ns, ks=ks, k=k, has_time=int(has_time),
                    znssd=int(znssd), px=c(px.reshape(-1)), py=c(py.reshape(-1)), dx=c(dx),
                    dy=c(dy), basis=c(basis), dt=c(dt), frame_off=frame_off, ft=c(ft),
                    fnorm=c(fnorm.reshape(-1)), gx=c(gx), gy=c(gy), w=c(w),
                    ref_rows=None if ref_rows is None else ref_rows.to(torch.int64).contiguous(),
                    motion=None if motion is None else c(motion), count=_count(count),
                    w_img=float(w_img), h=float(h), hinv=hinv.to(torch.float64).contiguous(),
                    scale=c(scale),
                    p=out_p, prev=c(prev.reshape(-1)), tol=float(tol), max_iter=int(max_iter),
                    div_norm=float(div_norm), rate_floor=float(rate_floor),
                    codes=torch.tensor(codes, dtype=torch.int64), zn=zn, status=status,
                    used=used, bframe=bframe, plast=plast), n_threads)
    last = (plast, bframe) if frame_rhs else None
    return out_p, zn, status.to(torch.int8), used, last


def gram(gx: torch.Tensor, gy: torch.Tensor, basis: torch.Tensor, w: torch.Tensor):
    """Native twin of formulations.joint_ic.gram: G (N, P', P') and m (N, P') in float64 for
    the augmented steepest-descent images [gx B, gx, gy B, gy] (P' = 2 (Ks + 1)) weighted by
    w (S,)."""
    dtype = gx.dtype
    n, ns = gx.shape
    ks = basis.shape[1]
    _require("gram", gy.shape == gx.shape and tuple(basis.shape) == (ns, ks)
             and w.numel() == ns, "gx, gy (N, S), basis (S, Ks), w (S,)")
    npa = 2 * (ks + 1)
    tens = {k: t.to(dtype).contiguous()
            for k, t in dict(gx=gx, gy=gy, basis=basis, w=w).items()}
    g = torch.empty(n, npa, npa, dtype=torch.float64)
    m = torch.empty(n, npa, dtype=torch.float64)
    run_rows(kernel("sts_gram", dtype), n, ns * npa, dict(ns=ns, ks=ks, **tens, G=g, m=m))
    return g, m


def spd_inverse(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Native inverse of symmetric positive definite matrices ``h`` (N, P, P), P <= 16, by
    Cholesky (the lower triangle read): the inverses (N, P, P) in h's dtype (NaN where not
    positive definite) and that mask (N,) bool."""
    _require("spd_inverse", h.dim() == 3 and h.shape[1] == h.shape[2] and 1 <= h.shape[1] <= 16,
             f"h must be (N, P, P) with 1 <= P <= 16, got {tuple(h.shape)}")
    n, p = h.shape[0], h.shape[1]
    hc = h.contiguous()
    inv = torch.empty_like(hc)
    bad = torch.empty(n, dtype=torch.uint8)
    run_rows(kernel("sts_spd_inverse", h.dtype), n, p * p * p,
             dict(np=p, h=hc, inv=inv, bad=bad))
    return inv, bad.bool()


def param_std(cols: torch.Tensor, dt: torch.Tensor, has_time: bool, ks: int, g1: torch.Tensor,
              g2: torch.Tensor | None, bw: torch.Tensor, b2: torch.Tensor, f2: torch.Tensor,
              g2n: torch.Tensor, kappa: float, count: torch.Tensor | None = None
              ) -> torch.Tensor:
    """Native :func:`~torch_stsdic.core.uncertainty.std_of` of
    :func:`~torch_stsdic.core.uncertainty.response`: (N, P) predicted std of the parameters at
    the augmented columns ``cols`` (P,) of N rows with frame times ``dt`` (N, T), centred
    grams ``g1`` (N, P', P') and ``g2`` (its w^2 moments; None: ``g1``), basis moments
    ``bw``, ``b2`` (P', P'), reference and frame noise variances ``f2``, ``g2n`` (N,) and
    gradient noise factor ``kappa``; in g1's dtype (float32/float64, computed in double),
    P <= 16; ``count`` (N,) each row's frames in use (:func:`ic_rhs`; None: all T)."""
    n, npa = g1.shape[0], g1.shape[-1]
    p = cols.numel()
    _require("param_std", g1.shape == (n, npa, npa) and 1 <= p <= 16 and p <= npa,
             f"g1 must be (N, P', P') with P = {p} <= min(P', 16), got {tuple(g1.shape)}")
    _require("param_std", dt.dim() == 2 and dt.shape[0] == n and dt.shape[1] >= 1,
             f"dt must be (N={n}, T), got {tuple(dt.shape)}")
    _require("param_std", g2 is None or tuple(g2.shape) == tuple(g1.shape),
             f"g2 must be like g1 {tuple(g1.shape)}")
    _require("param_std", tuple(bw.shape) == (npa, npa) and tuple(b2.shape) == (npa, npa),
             f"bw, b2 must be ({npa}, {npa})")
    _require("param_std", f2.shape == (n,) and g2n.shape == (n,), f"f2, g2n must be ({n},)")
    _check_count("param_std", count, n)
    dbl = g1.dtype

    def c(t):
        return t.to(dbl).contiguous()
    std = torch.empty(n, p, dtype=dbl)
    run_rows(kernel("sts_param_std", dbl), n, 4 * p * p * p,
             dict(npa=npa, np=p, nt=dt.shape[1], ks=ks, has_time=int(has_time),
                  cols=cols.to(torch.int64).contiguous(), dt=c(dt), count=_count(count),
                  g1=c(g1),
                  g2=None if g2 is None else c(g2), bw=c(bw), b2=c(b2), f2=c(f2), g2n=c(g2n),
                  kappa=float(kappa), std=std))
    return std


def windows(sources: tuple[torch.Tensor, ...], base: torch.Tensor, wy: int, wx: int
            ) -> tuple[torch.Tensor, ...]:
    """Per image of ``sources`` (each (F, H, W), all one shape): (N, wy * wx) its ``wy`` x
    ``wx`` windows whose top-left pixels are at the flat indices ``base`` (N,) (row-major,
    as ``interpolation.window_view(src, wy, wx)[f, y, x]`` gathers them): one copy a window
    row."""
    shape = sources[0].shape if sources else ()
    _require("windows", len(shape) == 3 and all(s.shape == shape for s in sources)
             and 1 <= wy <= shape[1] and 1 <= wx <= shape[2], f"images (F, H, W) of one "
             f"shape and a window inside a frame, got {[tuple(s.shape) for s in sources]} and "
             f"{wy} x {wx}")
    b = base.to(torch.int64).reshape(-1).contiguous()
    n, (f, h, w) = b.numel(), shape
    if n:  # every window wholly inside one frame: its first row in the frame's first
        # h - wy + 1 rows, at most w - wx columns in (one host read for all the images)
        ok = ((b >= 0) & (b < f * h * w) & (b % w <= w - wx) & ((b // w) % h <= h - wy)).all()
        _require("windows", bool(ok), "every window inside its frame")
    out = []
    for src in sources:
        o = torch.empty(n, wy * wx, dtype=src.dtype)
        run_rows(kernel("sts_windows", src.dtype), n, wy * wx,
                 dict(src=src.contiguous(), ws=w, base=b, wy=wy, wx=wx, out=o))
        out.append(o)
    return tuple(out)


def nanmedian(x: torch.Tensor) -> torch.Tensor:
    """Native twin of ``torch.nanmedian(x, dim=-1).values`` for rows of at most 64 values
    (float32/float64): the median over the values that are not NaN (the lower middle one for
    an even count), NaN where a row has none; shape ``x.shape[:-1]``."""
    k = x.shape[-1] if x.dim() else 0
    _require("nanmedian", 1 <= k <= 64, f"rows of 1 to 64 values, got {tuple(x.shape)}")
    xc = x.contiguous()
    out = torch.empty(x.shape[:-1], dtype=x.dtype)
    n = out.numel()
    run_rows(kernel("sts_nanmedian", x.dtype), n, 4 * k, dict(k=k, x=xc, out=out))
    return out


def _frames(fn: str, x: torch.Tensor) -> torch.Tensor:
    """Frames (F, H, W), H, W >= 3, contiguous (the noise kernels' input)."""
    _require(fn, x.dim() == 3 and x.shape[1] >= 3 and x.shape[2] >= 3,
             f"frames must be (F, H >= 3, W >= 3), got {tuple(x.shape)}")
    return x.contiguous()


def sobel_counts(x: torch.Tensor, step: int, bins: int) -> torch.Tensor:
    """(F, bins) int64: each frame's histogram of Sobel's ``|d/dx| + |d/dy|`` (the "valid"
    (H - 2) x (W - 2) pixels, row-major, every ``step``-th from the first) of frames ``x``
    (F, H, W) of whole-number grey levels, Sobel's magnitude below ``bins`` (8 x their range
    at most; the caller checks both): ``core.noise``'s histogram of its magnitudes, one pass
    a frame, no (F, H, W) arrays."""
    xc = _frames("sobel_counts", x)
    _require("sobel_counts", step >= 1 and bins >= 1, f"step, bins >= 1, got {step}, {bins}")
    f, h, w = xc.shape
    out = torch.zeros(f, bins, dtype=torch.int64)
    run_rows(kernel("sts_sobel_counts", xc.dtype), f, h * w // step,
             dict(x=xc, h=h, w=w, step=int(step), bins=int(bins), counts=out), parts=f)
    return out


def flat_sums(x: torch.Tensor, cut: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(F,) float64 and (F,) int64: the Laplacian difference's magnitudes of frames ``x``
    (F, H, W) of whole-number grey levels summed, and counted, over the "valid" pixels whose
    Sobel magnitude is at most the frame's ``cut`` (F,) (Immerkaer's flat pixels; exact)."""
    xc = _frames("flat_sums", x)
    f, h, w = xc.shape
    _require("flat_sums", tuple(cut.shape) == (f,), f"cut must be ({f},), got "
             f"{tuple(cut.shape)}")
    sums = torch.zeros(f, dtype=torch.float64)
    kept = torch.zeros(f, dtype=torch.int64)
    run_rows(kernel("sts_flat_sums", xc.dtype), f, h * w,
             dict(x=xc, h=h, w=w, cut=cut.to(xc.dtype).contiguous(), sums=sums, kept=kept),
             parts=f)
    return sums, kept


def _neighbour_args(fn: str, nb: torch.Tensor, valid: torch.Tensor) -> dict:
    """The neighbour kernels' shared arguments: nb (N, k) int64 (-1: none), valid (B, N)."""
    _require(fn, nb.dim() == 2 and 1 <= nb.shape[1] <= 64, f"nb must be (N, k <= 64), got "
             f"{tuple(nb.shape)}")
    _require(fn, valid.dim() == 2 and valid.shape[1] == nb.shape[0],
             f"valid must be (B, N={nb.shape[0]}), got {tuple(valid.shape)}")
    return dict(n=nb.shape[0], k=nb.shape[1], nb=nb.to(torch.int64).contiguous(),
                valid=valid.to(torch.uint8).contiguous())


def neighbour_own_gradient(nb: torch.Tensor, valid: torch.Tensor, g: torch.Tensor,
                           tol: float) -> torch.Tensor:
    """Native twin of the "own gradient" mask of quality.carried_neighbours: (B, N, C, 2) bool,
    a valid point's gradient component within 3 median absolute deviations (+ ``tol``) of
    the median of its valid neighbours' ``g`` (B, N, C, 2) float64."""
    a = _neighbour_args("neighbour_own_gradient", nb, valid)
    b, n = valid.shape
    _require("neighbour_own_gradient", g.dim() == 4 and tuple(g.shape[:2]) == (b, n)
             and g.shape[3] == 2, f"g must be (B, N, C, 2), got {tuple(g.shape)}")
    gc = g.contiguous()
    own = torch.empty(g.shape, dtype=torch.uint8)
    ne = g.shape[2] * 2
    run_rows(kernel("sts_nb_own", g.dtype), b * n, ne * a["k"] * 8,
             dict(a, ne=ne, g=gc, tol=float(tol), own=own))
    return own.bool()


def neighbour_test(nb: torch.Tensor, valid: torch.Tensor, values: torch.Tensor,
                   points: torch.Tensor, eps: torch.Tensor, gradients: torch.Tensor | None,
                   at: torch.Tensor | None):
    """Native twin of one round of quality.median_test: the ``valid`` neighbours' ``values``
    (B, N, C) carried to each point (``gradients`` and the gradient at the point ``at``,
    (B, N, C, 2), or neither), and per point the normalised residual r (B, N) (NaN where a
    component has no neighbour), the neighbours' scatter rm (B, N, C) and their count (B, N)
    int64. ``eps`` (B, N) px; float64 throughout."""
    fn = "neighbour_test"
    a = _neighbour_args(fn, nb, valid)
    b, n = valid.shape
    _require(fn, values.dim() == 3 and tuple(values.shape[:2]) == (b, n)
             and 1 <= values.shape[2] <= 8, f"values must be (B, N, C <= 8), got "
             f"{tuple(values.shape)}")
    c = values.shape[2]
    _require(fn, tuple(points.shape) == (n, 2), f"points must be (N, 2), got "
             f"{tuple(points.shape)}")
    _require(fn, tuple(eps.shape) == (b, n), f"eps must be (B, N), got {tuple(eps.shape)}")
    _require(fn, (gradients is None) == (at is None), "gradients and at go together")
    for nm, t in (("gradients", gradients), ("at", at)):
        _require(fn, t is None or tuple(t.shape) == (b, n, c, 2),
                 f"{nm} must be (B, N, C, 2), got {None if t is None else tuple(t.shape)}")
    dt = values.dtype
    r = torch.empty(b, n, dtype=dt)
    rm = torch.empty(b, n, c, dtype=dt)
    count = torch.empty(b, n, dtype=torch.int64)
    run_rows(kernel("sts_nb_test", dt), b * n, c * a["k"] * 12,
             dict(a, nc=c, v=values.contiguous(), p=points.to(dt).contiguous(),
                  g=None if gradients is None else gradients.to(dt).contiguous(),
                  at=None if at is None else at.to(dt).contiguous(),
                  eps=eps.to(dt).contiguous(), out_r=r, out_rm=rm, out_count=count))
    return r, rm, count


def prefilter(images: torch.Tensor, order: int) -> torch.Tensor:
    """Native twin of interpolation.bspline_prefilter for (..., H, W) float32/float64 CPU
    tensors: the recursive filter (two passes per pole and axis), mirror boundary. Returns a
    new tensor."""
    h, w = images.shape[-2:]
    out = images.clone(memory_format=torch.contiguous_format)  # filtered in place
    planes = out.numel() // max(1, h * w)
    fn = kernel("sts_prefilter", out.dtype)
    args = dict(data=out, planes=planes, h=h, w=w, order=order)
    if w >= 2:
        run_rows(fn, planes * h, w * 4, dict(args, axis=1))
    if h >= 2:
        blocks = planes * ((w + 63) // 64)
        run_rows(fn, blocks, h * 64 * 4, dict(args, axis=0))
    return out


def splat(img_args: tuple, order: int, dx: torch.Tensor, dy: torch.Tensor, tent: torch.Tensor,
          maps: torch.Tensor, centres: torch.Tensor, frame_off: torch.Tensor,
          weight: torch.Tensor, level: torch.Tensor, fac: torch.Tensor,
          ref_stats: tuple[torch.Tensor, torch.Tensor], ref: torch.Tensor, w: int, h: int
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Native twin of the per-sample part of ``movie.template_image.splat``: for N rows
    (frame, POI), the window's S pixels (offsets ``dx``, ``dy`` (S,), tent weights ``tent``
    (S,)) about the whole-pixel ``centres`` (N, 2) mapped by ``maps`` (N, 12) (x then y: a
    quadratic of the offsets, centre folded in) into the frame at plane offset ``frame_off``
    (N,), sampled, matched to the reference's grey levels (``ref_stats``: mean and norm (N,)
    over whole windows; else from ``ref`` (H*W,) over the pixels inside both images) and
    weighted (``weight``, ``level``, ``fac`` (N,)). Returns (N, S) float64 the weighted
    values, (N, S) float64 the weights and (N,) float64 each row's noise factor (a sample's
    noise share is its weight times it: :func:`splat_add` forms it)."""
    n, ns = maps.shape[0], dx.numel()
    flat, args = _splat_inputs("splat", img_args, order, dx, dy, tent, maps, centres,
                               frame_off, weight, level, fac, ref_stats, ref, w, h)
    out = [torch.empty(n, ns, dtype=torch.float64) for _ in range(2)]
    out.append(torch.empty(n, dtype=torch.float64))
    run_rows(kernel("sts_splat", flat.dtype), n, 8 * ns,
             dict(args, a=out[0], wt=out[1], rs=out[2]))
    return out[0], out[1], out[2]


def _splat_inputs(name: str, img_args: tuple, order: int, dx: torch.Tensor, dy: torch.Tensor,
                  tent: torch.Tensor, maps: torch.Tensor, centres: torch.Tensor,
                  frame_off: torch.Tensor, weight: torch.Tensor, level: torch.Tensor,
                  fac: torch.Tensor, ref_stats: tuple[torch.Tensor, torch.Tensor],
                  ref: torch.Tensor, w: int, h: int) -> tuple[torch.Tensor, dict]:
    """The template's rows as the sampling kernels take them (:func:`splat`'s arguments,
    checked, ``name`` in the message): the coefficients and the kernel's arguments."""
    flat = img_args[0].contiguous()
    n, ns = maps.shape[0], dx.numel()
    _require(name, tuple(maps.shape) == (n, 12) and tuple(centres.shape) == (n, 2)
             and all(t.numel() == n for t in (frame_off, weight, level, fac, *ref_stats))
             and dy.numel() == ns and tent.numel() == ns and ref.numel() == w * h,
             "maps (N, 12), centres (N, 2), frame_off/weight/level/fac/ref_stats (N,), "
             "dx/dy/tent (S,), ref (H*W,)")
    off = frame_off.to(torch.int64).reshape(-1).contiguous()
    _check_planes(name, img_args, off)

    def d(t):
        return t.to(torch.float64).reshape(-1).contiguous()

    c = centres.to(torch.float64)
    return flat, dict(flat=flat, **_geo(img_args, order), ns=ns, dx=d(dx), dy=d(dy),
                      tent=d(tent), pm=maps.to(torch.float64).contiguous(), cx=d(c[:, 0]),
                      cy=d(c[:, 1]), off=off, wf=d(weight), lv=d(level), fac=d(fac),
                      mr=d(ref_stats[0]), sr=d(ref_stats[1]), ref=d(ref), w=int(w), h=int(h))


def _splat_bins(name: str, sums: torch.Tensor, pf_w: torch.Tensor, pf_n: torch.Tensor,
                poi: torch.Tensor, frame: torch.Tensor, local: torch.Tensor, n: int, ns: int,
                dtype: torch.dtype) -> dict:
    """The sums the template's rows are added to (:func:`splat_add`'s ``sums``, ``pf_w``,
    ``pf_n`` of ``dtype``, and each of the N rows' ``poi``, ``frame`` among ``local``'s
    (P, S) windows), checked (``name`` in the message), as the adding kernels take them."""
    n_px = sums.numel()
    _require(name, all(t.dtype == dtype and t.is_contiguous() for t in (sums, pf_w, pf_n))
             and poi.numel() == n and frame.numel() == n and local.dim() == 2
             and local.shape[1] == ns and pf_w.numel() == pf_n.numel()
             and pf_w.numel() % max(n_px, 1) == 0,
             f"sums (C,), pf_w/pf_n (G*C,) contiguous {dtype}, poi/frame (N,), local (P, S)")
    poi, frame = poi.to(torch.int64).contiguous(), frame.to(torch.int64).contiguous()
    if n:
        _require(name, bool((poi >= 0).all() & (poi < local.shape[0]).all()
                            & (frame >= 0).all() & (frame < pf_w.numel() // n_px).all()),
                 "poi within local's rows, frame within pf_w's frames")
    return dict(n_px=n_px, poi=poi, frame=frame, local=local.to(torch.int64).contiguous(),
                sums=sums, pf_w=pf_w, pf_n=pf_n)


def splat_add(sums: torch.Tensor, pf_w: torch.Tensor, pf_n: torch.Tensor, a: torch.Tensor,
              wt: torch.Tensor, rs: torch.Tensor, poi: torch.Tensor, frame: torch.Tensor,
              local: torch.Tensor) -> None:
    """Add :func:`splat`'s rows (``a``, ``wt`` (N, S) and ``rs`` (N,), each a (frame, POI)
    pair: ``frame`` (N,), ``poi`` (N,)) to the sums over the C pixels the windows cover, in
    place: ``sums`` (C,) += a and the row's frame's ``pf_w``, ``pf_n`` (G*C,) += wt, wt rs
    (the product rounded, then added), at pixel ``local[poi, s]`` (``local`` (P, S): each
    POI's window pixels among the C). Each
    bin's values added in row order on one thread: the numbers of
    :func:`~torch_stsdic.kernels.scatter.scatter_add_` on the CPU, without the (N, S)
    index. Every value tensor of one dtype (float64 for the template; float32 too)."""
    n, ns = a.shape
    _require("splat_add", a.dtype in (torch.float32, torch.float64)
             and all(t.dtype == a.dtype and t.is_contiguous() for t in (a, wt, rs))
             and wt.shape == a.shape and tuple(rs.shape) == (n,),
             "a/wt (N, S), rs (N,) contiguous, one float dtype")
    bins = _splat_bins("splat_add", sums, pf_w, pf_n, poi, frame, local, n, ns, a.dtype)
    if n == 0:
        return
    fn = kernel("sts_splat_add", a.dtype)
    raw, keep = fn.bind(dict(bins, i0=0, i1=n, ns=ns, a=a, wt=wt, rs=rs))
    rc = fn.fn(*raw)
    del keep
    if rc:
        raise RuntimeError(f"sts_splat_add returned {rc}")


def splat_fused(img_args: tuple, order: int, dx: torch.Tensor, dy: torch.Tensor,
                tent: torch.Tensor, maps: torch.Tensor, centres: torch.Tensor,
                frame_off: torch.Tensor, weight: torch.Tensor, level: torch.Tensor,
                fac: torch.Tensor, ref_stats: tuple[torch.Tensor, torch.Tensor],
                ref: torch.Tensor, w: int, h: int, sums: torch.Tensor, pf_w: torch.Tensor,
                pf_n: torch.Tensor, poi: torch.Tensor, frame: torch.Tensor,
                local: torch.Tensor) -> None:
    """:func:`splat` then :func:`splat_add` in one pass, to the bit: the N rows (the
    arguments of :func:`splat`) sampled and added to ``sums``, ``pf_w``, ``pf_n`` (float64,
    those of :func:`splat_add`) with no (N, S) arrays between. The covered pixels are split
    over the threads (one range each), each adding every row that reaches its range in row
    order (a row across two ranges sampled twice). A window's first and last pixels in
    ``local`` are its least and greatest (``window_pixels``' row-major offsets, clamped to
    the image, ranked: monotone), even where the window is wider than the image."""
    n, ns = maps.shape[0], dx.numel()
    flat, args = _splat_inputs("splat_fused", img_args, order, dx, dy, tent, maps, centres,
                               frame_off, weight, level, fac, ref_stats, ref, w, h)
    bins = _splat_bins("splat_fused", sums, pf_w, pf_n, poi, frame, local, n, ns,
                       torch.float64)
    if n == 0:
        return
    n_px = bins["n_px"]
    run_rows(kernel("sts_splat_fused", flat.dtype), n_px, max(1, 8 * n * ns // max(n_px, 1)),
             dict(args, **bins, n=n), parts=threads())


def splat_finish(sums_w: torch.Tensor, sums_n: torch.Tensor, pf_w: torch.Tensor,
                 pf_n: torch.Tensor, weight: float | torch.Tensor) -> None:
    """One frame's sums over the C covered pixels (``pf_w``, ``pf_n`` (C,): :func:`splat_add`'s
    with one frame) folded into the template's, in place: ``sums_w`` += pf_w, ``sums_n`` +=
    pf_n / ``weight`` * pf_w (the frame's noise share; the numbers of torch's ``div_``,
    ``mul_``, ``add_``), and ``pf_w``, ``pf_n`` set to 0 (ready for the next frame). One pass
    over the pixels, split over the threads (each pixel on its own: the same numbers).
    ``weight``: a number or a 1-element tensor (read here)."""
    n_px = sums_w.numel()
    _require("splat_finish", sums_w.dtype in (torch.float32, torch.float64)
             and all(t.dtype == sums_w.dtype and t.is_contiguous() and t.numel() == n_px
                     for t in (sums_w, sums_n, pf_w, pf_n)),
             "sums_w, sums_n, pf_w, pf_n (C,) contiguous, one float dtype")
    run_rows(kernel("sts_splat_finish", sums_w.dtype), n_px, 8,
             dict(wf=float(weight), pf_w=pf_w, pf_n=pf_n, sums_w=sums_w, sums_n=sums_n))
