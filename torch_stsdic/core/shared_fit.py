"""The robust fit of a shared motion to the displacements of a sample of points in every
frame (:func:`fit_frame_motion`; :mod:`torch_stsdic.core.shared_motion` carries it): a series
is fitted as a whole (the same points with the same weights in every frame, a point's
roughness in time, wrong peaks against its neighbouring frames), taken frame chunk by frame
chunk so that a long movie's fit holds, besides its measurements, one (F, N) float64 array at a
time, with the very numbers of the fit over whole arrays."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["fit_frame_motion", "frame_chunks", "SHARED_MOTION_KINDS", "FIT_CHUNK",
           "WLS_FRAMES"]

#: kinds of shared motion: a translation per frame (2 numbers), an affine motion (6), or a
#: quadratic one (12: also the second derivatives, as a tilt of the specimen out of the
#: image plane or a bending shake gives)
SHARED_MOTION_KINDS = ("translation", "affine", "quadratic")
_HUBER = 2.0  # Huber threshold in robust (MAD) standard deviations
_IRLS_STEPS = 8
_MIN_POINTS = 8  # fewer usable points in a frame: no estimate there (interpolated)
_VALID_SHARE = 0.9  # a series' fit uses the points valid in at least this share of frames
_GROSS_PX = 0.5  # an entry this far (or 10x the median) from its neighbours: a wrong peak


def fit_frame_motion(points: Tensor, disp: Tensor, valid: Tensor, kind: str = "affine",
                     origin: Tensor | None = None, noise: Tensor | None = None
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Robust per-frame fit of a shared motion to measured displacements.

    Args:
        points: (N, 2) POIs (x, y) px.
        disp: (F, N, 2) displacements (u, v) px of every point in every frame (float32 or
            float64; the fit is in float64, frame chunk by frame chunk).
        valid: (F, N) bool, the measurements to use (NaN displacements are never used).
        kind: "translation", "affine" or "quadratic".
        origin: (2,) the point the translation refers to (default: the points' mean).
        noise: (F, N) each measurement's noise std per component, px (e.g. the classical
            predicted std), for the standard error; None: the fit's robust scatter (which
            also counts the deformation's departure from the affine motion).

    Returns:
        params (F, 6) float64, (F, 12) for "quadratic" (columns ``PARAM_NAMES``; NaN where a
        frame has fewer than 8 valid points, 18 for "quadratic"), robust scatter (F,) px,
        points used (F,), and the standard error (F,) px of the translation (per component:
        from ``noise`` or the scatter, through the weighted least-squares factor).
    """
    if kind not in SHARED_MOTION_KINDS:
        raise ValueError(f"shared motion kind must be one of {SHARED_MOTION_KINDS}, got "
                         f"{kind!r}")
    p = points.double()
    # a float32 pass's displacements stay float32, made float64 frame chunk by frame chunk
    d = disp if disp.dtype in (torch.float32, torch.float64) else disp.double()
    ok = valid.bool() & torch.isfinite(d).all(-1)
    o = p.mean(0) if origin is None else torch.as_tensor(origin, dtype=torch.float64,
                                                          device=p.device)
    rel = p - o
    scale = float(rel.abs().max().clamp(min=1.0))  # conditioning: columns of order 1
    xs, ys = rel[:, 0] / scale, rel[:, 1] / scale
    cols = [torch.ones_like(xs)]
    if kind in ("affine", "quadratic"):
        cols += [xs, ys]
    if kind == "quadratic":
        cols += [0.5 * xs * xs, xs * ys, 0.5 * ys * ys]
    x = torch.stack(cols, 1)  # (N, C)
    f, c = d.shape[0], x.shape[1]
    eye = 1e-12 * torch.eye(c, dtype=torch.float64, device=p.device)
    if f >= 3:
        coef, w, ok = _consistent_fit(x, d, ok, eye)
    else:
        coef, w = _frame_fit(x, d, ok, eye)
    s, var0 = _spread(x, d, ok, coef, w, eye, noise)
    used = torch.count_nonzero(ok, dim=1)  # (a sum would copy ok as int64)
    se = var0.clamp(min=0).sqrt()
    out = torch.zeros(f, 12 if kind == "quadratic" else 6, dtype=torch.float64, device=p.device)
    out[:, 0], out[:, 1] = coef[:, 0, 0], coef[:, 0, 1]
    if c >= 3:
        out[:, 2], out[:, 3] = coef[:, 1, 0] / scale, coef[:, 2, 0] / scale
        out[:, 4], out[:, 5] = coef[:, 1, 1] / scale, coef[:, 2, 1] / scale
    if c == 6:
        s2 = scale * scale
        out[:, 6], out[:, 7], out[:, 8] = (coef[:, 3, 0] / s2, coef[:, 4, 0] / s2,
                                           coef[:, 5, 0] / s2)
        out[:, 9], out[:, 10], out[:, 11] = (coef[:, 3, 1] / s2, coef[:, 4, 1] / s2,
                                             coef[:, 5, 1] / s2)
    few = used < max(_MIN_POINTS, 3 * c)
    out[few] = float("nan")
    s = torch.where(few, torch.nan, s)
    return out, s, used, torch.where(few, torch.nan, se)


#: (frame, point) entries of the intermediate arrays of a series' fit at a time: a long
#: movie's fit (every frame measured) works through its frames, or its points, in pieces of
#: this size, each as the whole series would be (the same numbers, bounded memory)
FIT_CHUNK = 1 << 16


def frame_chunks(f: int, n: int) -> list[slice]:
    """Consecutive frames, about ``FIT_CHUNK`` entries of ``n`` points each."""
    step = max(1, FIT_CHUNK // max(n, 1))
    return [slice(i, min(i + step, f)) for i in range(0, f, step)]


def _point_chunks(f: int, n: int) -> list[slice]:
    """Consecutive points, about ``FIT_CHUNK`` entries of ``f`` frames each."""
    step = max(1, FIT_CHUNK // max(f, 1))
    return [slice(i, min(i + step, n)) for i in range(0, n, step)]


#: the normal equations of a long series are made over chunks of at least this many frames:
#: each chunk's batched product then rounds as the whole series' does (below ~100 frames a
#: BLAS takes its small-matrix path, which rounds differently; checked on every shape of
#: tests/test_long_movies.py::test_fit_in_chunks_equals_the_whole_series)
WLS_FRAMES = 256


def _wls_chunks(f: int) -> list[slice]:
    """Consecutive frames in chunks of ``WLS_FRAMES`` to ``2 * WLS_FRAMES - 1`` (one chunk
    where ``f`` is shorter than two)."""
    if f < 2 * WLS_FRAMES:
        return [slice(0, f)]
    cuts = list(range(0, f, WLS_FRAMES))
    if f - cuts[-1] < WLS_FRAMES:
        cuts.pop()
    return [slice(a, b) for a, b in zip(cuts, cuts[1:] + [f])]


def _spread(x: Tensor, d: Tensor, ok: Tensor, coef: Tensor, w: Tensor, eye: Tensor,
            noise: Tensor | None) -> tuple[Tensor, Tensor]:
    """Per frame: the robust scatter of the residuals (F,) px (frame chunk by frame chunk)
    and the variance (F,) of the translation coefficient (sandwich with ``noise``, else from
    the scatter; chunks of :data:`WLS_FRAMES`)."""
    f = d.shape[0]
    s = torch.empty(f, dtype=torch.float64, device=d.device)
    for sl in frame_chunks(f, d.shape[1]):
        okc = ok[sl]
        dc = _rows(d, sl)
        d0 = torch.where(okc.unsqueeze(-1), dc, torch.zeros_like(dc))
        r = (d0 - x @ coef[sl]).norm(dim=-1)
        # 2-D residuals of std s per component: |r| is Rayleigh, median 1.1774 s
        s[sl] = torch.nanmedian(torch.where(okc, r, torch.nan), dim=1).values / 1.1774
    var0 = torch.empty_like(s)
    for sl in _wls_chunks(f):
        xwt = x.T.unsqueeze(0) * w[sl].unsqueeze(1)  # (F, C, N): (x w)^T, made contiguous
        inv = torch.linalg.inv(xwt @ x + eye)
        if noise is None:
            var0[sl] = (inv @ (xwt @ xwt.transpose(1, 2)) @ inv)[:, 0, 0] * s[sl] * s[sl]
        else:  # sandwich with each row's own noise variance
            nv = torch.where(ok[sl], torch.nan_to_num(noise[sl].double(), nan=0.0) ** 2,
                             torch.zeros_like(w[sl]))
            xwt *= nv.sqrt().unsqueeze(1)  # (x_n)^T
            var0[sl] = (inv @ (xwt @ xwt.transpose(1, 2)) @ inv)[:, 0, 0]
    return s, var0


def _wls(x: Tensor, d: Tensor, w: Tensor, eye: Tensor) -> Tensor:
    """(F, C, 2) per-frame weighted least squares of d (F, N, 2) on x (N, C), weights w
    (F, N) or (N,)."""
    # (x w)^T made contiguous (F, C, N), as the product would copy it (the same numbers),
    # chunks of frames that round as the whole series (:data:`WLS_FRAMES`)
    w = w.expand(d.shape[0], -1) if w.dim() == 1 else w
    out = torch.empty(d.shape[0], x.shape[1], d.shape[2], dtype=d.dtype, device=d.device)
    for sl in _wls_chunks(d.shape[0]):
        xwt = x.T.unsqueeze(0) * w[sl].unsqueeze(1)
        out[sl] = torch.linalg.solve(xwt @ x + eye, xwt @ d[sl])
    return out


def _rows(d: Tensor, sl: slice) -> Tensor:
    """Rows ``sl`` of the displacements ``d`` (F, N, 2) in float64 (a float32 pass's values
    exactly: a long movie's fit holds its measurements at their own precision)."""
    return d[sl].double()


def _frame_fit(x: Tensor, d: Tensor, ok: Tensor, eye: Tensor, weights: bool = True
               ) -> tuple[Tensor, Tensor | None]:
    """Huber IRLS per frame: coefficients (F, C, 2) and, with ``weights``, the weights
    (F, N); each chunk of :func:`_wls_chunks` on its own (a frame's fit is its own)."""
    f, n = ok.shape
    coef = torch.empty(f, x.shape[1], 2, dtype=torch.float64, device=ok.device)
    w_all = torch.empty(f, n, dtype=torch.float64, device=ok.device) if weights else None
    for ch in _wls_chunks(f):
        okc, dc = ok[ch], _rows(d, ch)
        d0 = torch.where(okc.unsqueeze(-1), dc, torch.zeros_like(dc))
        w = okc.double()
        cf = _wls(x, d0, w, eye)
        for _ in range(_IRLS_STEPS):
            w = torch.empty(okc.shape, dtype=d0.dtype, device=d0.device)
            for sl in frame_chunks(*okc.shape):  # the weights frame chunk by frame chunk
                oks = okc[sl]
                r = (d0[sl] - x @ cf[sl]).norm(dim=-1)
                s = torch.nanmedian(torch.where(oks, r, torch.nan), dim=1).values / 1.1774
                k = (_HUBER * s).clamp(min=1e-6).unsqueeze(1)
                w[sl] = torch.where(oks, torch.clamp(k / r.clamp(min=1e-12), max=1.0),
                                    torch.zeros_like(r))
            cf = _wls(x, d0, w, eye)
        coef[ch] = cf
        if w_all is not None:
            w_all[ch] = w
    return coef, w_all


#: the frames around a chunk that its gap filling and neighbours' line read (2: the line
#: at the series' first frame is extrapolated from the next two)
_HALO = 2


def _blocks(sls: list[slice], f: int) -> list[tuple[int, int]]:
    """The frames (lo, hi) each chunk of ``sls`` reads: itself and ``_HALO`` around it."""
    return [(max(0, sl.start - _HALO), min(f, sl.stop + _HALO)) for sl in sls]


def _bounds(mask: Tensor, blocks: list[tuple[int, int]]) -> list[tuple[Tensor, Tensor]]:
    """Per block (lo, hi): (N,) each point's last frame before ``lo`` where ``mask`` (F, N)
    holds (-1: none) and its first frame from ``hi`` on (F: none); one scan forward and one
    backward, frame chunk by frame chunk."""
    f, n = mask.shape
    t_all = torch.arange(f, device=mask.device)
    before: dict[int, Tensor] = {0: torch.full((n,), -1, dtype=torch.long)}
    after: dict[int, Tensor] = {f: torch.full((n,), f, dtype=torch.long)}
    los, his = {lo for lo, _ in blocks}, {hi for _, hi in blocks}
    chunks = frame_chunks(f, n)
    last = before[0]
    for sl in chunks:  # last[p - 1 - start]: the last frame <= p - 1 where it holds
        t = t_all[sl].unsqueeze(1)
        upto = torch.maximum(torch.where(mask[sl], t, -1).cummax(0).values, last)
        for p in los:
            if sl.start < p <= sl.stop:
                before[p] = upto[p - 1 - sl.start].clone()
        last = upto[-1].clone()
    first = after[f]
    for sl in reversed(chunks):
        t = t_all[sl].unsqueeze(1)
        onward = torch.minimum(torch.where(mask[sl], t, f).flip(0).cummin(0).values.flip(0),
                               first)
        for p in his:
            if sl.start <= p < sl.stop:
                after[p] = onward[p - sl.start].clone()
        first = onward[0].clone()
    return [(before[lo], after[hi]) for lo, hi in blocks]


def _residual_at(x: Tensor, d: Tensor, coef: Tensor, at: Tensor) -> Tensor:
    """(N, 2) each point's residual ``d - x coef`` at its own frame ``at`` (N,) (0 where
    ``at`` is outside the series: -1 or F)."""
    f, n = d.shape[0], d.shape[1]
    inside = (at >= 0) & (at < f)
    k = at.clamp(0, f - 1)
    frames, which = torch.unique(k, return_inverse=True)
    pts = torch.arange(n, device=at.device)
    fit = (x @ coef[frames])[which, pts]
    r = d[k, pts].double() - fit
    return torch.where(inside.unsqueeze(-1), r, torch.zeros_like(r))


def _filled(x: Tensor, d: Tensor, coef: Tensor, mask: Tensor, lo: int, hi: int,
            bounds: tuple[Tensor, Tensor], alive: Tensor) -> Tensor:
    """(hi - lo, N, 2) frames lo..hi-1 of the residuals ``d - x coef`` where ``mask`` (F, N)
    holds, linearly interpolated in time elsewhere between the point's nearest frames where
    it holds (the nearest one before its first or after its last; 0 where ``alive`` (N,) is
    False: it never holds). ``bounds``: each point's last frame before ``lo`` and first from
    ``hi`` where ``mask`` holds (:func:`_bounds`), so a chunk reads as the whole series."""
    f = mask.shape[0]
    m = mask[lo:hi]
    r = torch.where(m.unsqueeze(-1), _rows(d, slice(lo, hi)) - x @ coef[lo:hi],
                    torch.zeros(1, dtype=torch.float64, device=m.device))
    t = torch.arange(lo, hi, device=m.device).unsqueeze(1).expand_as(m)
    before, after = bounds
    prev = torch.maximum(torch.where(m, t, -1).cummax(0).values, before)
    nxt = torch.minimum(torch.where(m, t, f).flip(0).cummin(0).values.flip(0), after)
    a = torch.where(prev >= 0, prev, nxt).clamp(0, f - 1)
    b = torch.where(nxt < f, nxt, prev).clamp(0, f - 1)
    ext = torch.cat([_residual_at(x, d, coef, before).unsqueeze(0), r,
                     _residual_at(x, d, coef, after).unsqueeze(0)])

    def row(k: Tensor) -> Tensor:  # a frame's row of ``ext``
        at = torch.where(k < lo, 0, torch.where(k >= hi, hi - lo + 1, k - lo + 1))
        return torch.gather(ext, 0, at.unsqueeze(-1).expand(-1, -1, 2))

    ra, rb = row(a), row(b)
    span = (b - a).clamp(min=1).to(r.dtype)
    frac = ((t - a).to(r.dtype) / span).clamp(0, 1).unsqueeze(-1)
    out = ra + (rb - ra) * frac
    return torch.where(alive.view(1, -1, 1), out, torch.zeros_like(out))


def _neighbours_line(rf: Tensor, lo: int, sl: slice, f: int) -> Tensor:
    """(len(sl), N, 2) each frame of ``sl`` as its neighbours predict it, from ``rf`` (frames
    lo.. of a series of ``f`` >= 3 frames): the mean of the frames before and after,
    extrapolated from the next two (previous two) at the first (last) frame; a wrong peak
    in one frame stands out, a trend or an acceleration does not."""
    a, b = sl.start, sl.stop
    out = torch.empty(b - a, *rf.shape[1:], dtype=rf.dtype, device=rf.device)
    i, j = max(a, 1), min(b, f - 1)
    if i < j:
        out[i - a:j - a] = 0.5 * (rf[i - 1 - lo:j - 1 - lo] + rf[i + 1 - lo:j + 1 - lo])
    if a == 0:
        out[0] = 2 * rf[1 - lo] - rf[2 - lo]
    if b == f:
        out[f - 1 - a] = 2 * rf[f - 2 - lo] - rf[f - 3 - lo]
    return out


def _valid_share(ok: Tensor) -> Tensor:
    """(N,) the share of frames where each point is valid (``ok`` (F, N)), point chunk by
    point chunk."""
    out = torch.empty(ok.shape[1], dtype=torch.float64, device=ok.device)
    for sl in _point_chunks(*ok.shape):
        out[sl] = ok[:, sl].double().mean(0)
    return out


def _lower_median(v: Tensor) -> Tensor:
    """``torch.nanmedian(v)`` of values >= 0 (or NaN): the lower median of the non-NaN
    entries, NaN where none (0-d float64 on ``v``'s device); without a copy of ``v`` (a
    bisection on the float64 bit patterns, which order values >= 0 as the values: 63 counts
    over ``v``) and without a host read (the bisection's bounds stay on the device: the 63
    steps halve any range of +0.0 .. +inf, a step once they meet changes nothing)."""
    n_ok = torch.count_nonzero(v >= 0)
    rank = (n_ok - 1) // 2
    lo = torch.zeros((), dtype=torch.int64, device=v.device)  # +0.0
    hi = torch.full((), 0x7FF0000000000000, dtype=torch.int64, device=v.device)  # +inf
    for _ in range(63):
        mid = lo + (hi - lo) // 2  # (lo + hi) // 2 without overflowing int64
        above = torch.count_nonzero(v <= mid.view(torch.float64)) > rank
        hi = torch.where(above, mid, hi)
        lo = torch.where(above, lo, mid + 1)
    return torch.where(n_ok > 0, lo.view(torch.float64), torch.nan)


def _consistent_fit(x: Tensor, d: Tensor, ok: Tensor, eye: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """The fit of :func:`fit_frame_motion` for a series (>= 3 frames): the same points with
    the same weights in every frame, so the shared motion does not jump from frame to frame
    where the deformation departs from it (a per-frame robust fit re-weights the points of a
    non-uniform field differently in each frame: on the hourglass its 5-frame line misfit
    was 7x that of this fit).

    The points are those valid in every frame (a point lost in some frames is usually wrong
    in others: on the hourglass, adding the 3 % valid in >= 90 % of the frames, with their
    gaps interpolated, doubled the misfit); where fewer than half the valid points are, those
    valid in >= 90 % of the frames, gaps interpolated in time (where even those are fewer
    than 3 per coefficient: the robust fit frame by frame). Each point's weight is a
    Huber weight (3x the median; 0 beyond 10x) on the roughness in time of its residual
    from the shared motion (median |second difference|): a wrong or background point
    jitters on its own; an entry's weight is 0 where it is far (10x the median, at least
    0.5 px) from what the point's neighbouring frames predict: a wrong peak in one frame.

    Whole-series statistics (a point's median over all frames, the median over all
    entries), taken frame chunk by frame chunk: besides ``d`` and ``ok`` it holds one
    (F, N) float64 array at a time (the roughness terms, then the deviations). Returns
    coefficients (F, C, 2), weights (F, N) and the entries used (F, N)."""
    f, n = ok.shape
    valid_pts = ok.any(0)
    keep = ok.all(0)
    if int(keep.sum()) < max(3 * x.shape[1], int(0.5 * int(valid_pts.sum()))):
        keep = _valid_share(ok) >= _VALID_SHARE
    if int(keep.sum()) < 3 * x.shape[1]:  # too few points tracked throughout: per frame
        coef, w = _frame_fit(x, d, ok, eye)
        return coef, w, ok
    use = ok & keep
    coef, _ = _frame_fit(x, d, use, eye, weights=False)  # a robust start, frame by frame
    w = keep.double().expand(f, -1)
    fr = frame_chunks(f, n)
    blocks = _blocks(fr, f)
    alive = use.any(0)
    bounds = _bounds(use, blocks)
    for _ in range(3):
        # per point (its frames in time): the roughness of its residual (gaps filled)
        d2 = torch.empty(f - 2, n, dtype=torch.float64, device=ok.device)
        for sl, (lo, hi), bd in zip(fr, blocks, bounds):
            a, b = max(sl.start, 1), min(sl.stop, f - 1)  # frames with a second difference
            if a < b:
                c = _filled(x, d, coef, use, lo, hi, bd, alive)[a - 1 - lo:b + 1 - lo]
                d2[a - 1:b - 1] = (c[2:] - 2 * c[1:-1] + c[:-2]).norm(dim=-1)
        rough = torch.empty(n, dtype=torch.float64, device=ok.device)
        for sl in _point_chunks(f, n):
            rough[sl] = d2[:, sl].median(0).values
        del d2
        s_r = torch.nanmedian(torch.where(keep, rough, torch.nan)).clamp(min=1e-9)
        w_pt = torch.where(keep & (rough <= 10.0 * s_r),
                           torch.clamp(3.0 * s_r / rough.clamp(min=1e-12), max=1.0),
                           torch.zeros_like(rough))
        # a wrong peak in single frames: how far each frame is from what its neighbouring
        # frames predict, less what all points share there (the shared motion's own error)
        dev = torch.empty(f, n, dtype=torch.float64, device=ok.device)
        for sl, (lo, hi), bd in zip(fr, blocks, bounds):
            rf = _filled(x, d, coef, use, lo, hi, bd, alive)
            jump = rf[sl.start - lo:sl.stop - lo] - _neighbours_line(rf, lo, sl, f)
            shared = torch.nanmedian(torch.where(use[sl].unsqueeze(-1), jump, torch.nan),
                                     1).values
            dev[sl] = torch.where(use[sl], (jump - torch.nan_to_num(shared).unsqueeze(1))
                                  .norm(dim=-1), torch.nan)
        scale = _lower_median(dev).clamp(min=1e-9)
        limit = torch.clamp(10.0 * scale, min=_GROSS_PX)
        # such an entry is filled in from the point's other frames, as a gap is, and keeps
        # its point's weight: a weight that changed from frame to frame would move the fit
        # by the deformation's departure from it (px on the hourglass without a region)
        good = use & (dev <= limit)
        del dev
        w = w_pt.expand(f, -1)
        coef = _refit(x, d, coef, good, w, eye, fr)
    return coef, w, use


def _refit(x: Tensor, d: Tensor, coef: Tensor, good: Tensor, w: Tensor, eye: Tensor,
           fr: list[slice]) -> Tensor:
    """(F, C, 2) the weighted least squares (weights ``w`` (F, N)) of the displacements
    ``d`` where ``good`` (F, N) holds, elsewhere the fit ``x coef`` plus the residual filled
    in time from the point's good frames: chunks of :func:`_wls_chunks`, each assembled from
    the frame chunks ``fr`` within it (bounded work arrays)."""
    f, n = good.shape
    alive = good.any(0)
    wls = _wls_chunks(f)
    parts = [[slice(max(ch.start, sl.start), min(ch.stop, sl.stop)) for sl in fr
              if sl.start < ch.stop and sl.stop > ch.start] for ch in wls]
    bounds = iter(_bounds(good, [(p.start, p.stop) for ps in parts for p in ps]))
    new = torch.empty_like(coef)
    for ch, ps in zip(wls, parts):
        full = torch.empty(ch.stop - ch.start, n, 2, dtype=torch.float64, device=good.device)
        for sl in ps:
            filled = _filled(x, d, coef, good, sl.start, sl.stop, next(bounds), alive)
            full[sl.start - ch.start:sl.stop - ch.start] = torch.nan_to_num(torch.where(
                good[sl].unsqueeze(-1), _rows(d, sl), x @ coef[sl] + filled))
        new[ch] = _wls(x, full, w[ch], eye)
    return new
