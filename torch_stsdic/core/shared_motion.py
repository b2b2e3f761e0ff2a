"""Shared motion: the per-frame affine motion of the whole specimen, carried as a known term in
every window.

Real movies are not smooth in time the way a render is: the specimen (or the camera) shakes
as a whole by a fraction of a pixel from frame to frame, and machines move in load steps. A
window of 2m+1 frames with a displacement affine in time cannot describe such a jitter, so the
model check rejects it and the point falls back to classical DIC. But the jitter is the *same*
motion for every point: a rigid (or affine) motion of the whole field of view per frame. It is
measured once, from all points together, and carried as a known term:

    U(x, t) = G_t(x) + D(x, t),     G_t(x) = a_t + B_t (x - x0)

``G_t`` (6 numbers per frame: translation ``a_t`` and the 2x2 gradient ``B_t``) is fitted
robustly (Huber IRLS) to the classical displacements of a sample of points at every frame
(:func:`~torch_stsdic.movie.shared_pass.estimate_shared_motion`: one classical pass over the
frames at up to ``max_points`` POIs), so outliers, lost points and background move it by
at most a bounded share. ``D``, the deformation, is what the STS window has to describe;
it is smooth in time even where ``G`` jitters. In a window of target frame ``k``, the known
part of frame ``t`` is the jitter of ``G`` about its own line through the window
(:func:`window_offsets`):

    o_t(x_i) = G_t(x_i) - G_k(x_i) - beta_i (t - t_k)      (beta_i: the window's LS slope of G)

added to the warp of frame ``t`` (``SubsetSolver.solve(..., motion=)``), so the window's
parameters keep their meaning (u, v: the total displacement at the target frame; ut, vt: the
smooth velocity) and a window where ``G`` moves affinely in time is solved exactly as without
it (o = 0). Within a subset only the translation of ``o`` at the POI is carried: the jitter's
own rotation moves a subset's edge by ``|B_t - line| * half`` (1e-3 rad: 0.01 px at 10 px),
a zero-mean misfit that the window's gradients cannot absorb but that does not bias u, v.

The estimate's own error is the classical noise over the sample, ``sigma_c * sqrt(3 / n)`` for
n points (0.05 sigma_c at 1,000 independent points), far below the window's error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["SharedMotion", "SHARED_MOTION_KINDS", "PARAM_NAMES", "PARAM_UNITS",
           "fit_frame_motion", "window_offsets", "known_window_motion", "overlap_factor",
           "sample_points", "frame_chunks",
           "detect_steps", "step_increments", "steps_from_increments",
           "DEFAULT_MAX_POINTS", "SIGNIFICANT", "STEP_Z", "STEP_RATIO", "SE_FLOOR"]

#: kinds of shared motion: a translation per frame (2 numbers), an affine motion (6), or a
#: quadratic one (12: also the second derivatives, as a tilt of the specimen out of the
#: image plane or a bending shake gives)
SHARED_MOTION_KINDS = ("translation", "affine", "quadratic")
#: the columns of ``SharedMotion.params`` (px, px/px, px/px^2): u = a_x + du/dx dx + du/dy dy
#: + d2u/dx2 dx^2 / 2 + d2u/dxdy dx dy + d2u/dy2 dy^2 / 2 (dx, dy from the origin), v alike
PARAM_NAMES = ("a_x", "a_y", "du/dx", "du/dy", "dv/dx", "dv/dy", "d2u/dx2", "d2u/dxdy",
               "d2u/dy2", "d2v/dx2", "d2v/dxdy", "d2v/dy2")
PARAM_UNITS = ("px", "px", "px/px", "px/px", "px/px", "px/px", "px/px^2", "px/px^2",
               "px/px^2", "px/px^2", "px/px^2", "px/px^2")
#: POIs of the classical pass that measures the shared motion
DEFAULT_MAX_POINTS = 1000
_HUBER = 2.0  # Huber threshold in robust (MAD) standard deviations
_IRLS_STEPS = 8
_MIN_POINTS = 8  # fewer usable points in a frame: no estimate there (interpolated)
_VALID_SHARE = 0.9  # a series' fit uses the points valid in at least this share of frames
_GROSS_PX = 0.5  # an entry this far (or 10x the median) from its neighbours: a wrong peak
#: "auto" applies the shared motion where its significance (jitter variance over estimation
#: variance) exceeds this: a jitter of 5 times the estimate's standard error. (A motion
#: affine in time gives ~1, and up to ~6 where the sub-pixel interpolation bias, the same at
#: every point of a uniform translation, moves the estimate; a real shake gives 10^3-10^5.)
SIGNIFICANT = 25.0
#: load-step detection (:func:`detect_steps`): an increment above STEP_Z times its noise and
#: STEP_RATIO times the median increment of the frames around it starts a new load state
STEP_Z = 2.0
#: px added in quadrature to the shared motion's standard error in its significance: what
#: the noise model leaves out (the sub-pixel interpolation bias, the same at every point of a
#: uniform motion, ~1e-3 px); so noise-free images, whose noise is ~0, need a shake of
#: 5 x 0.002 = 0.01 px before it is carried
SE_FLOOR = 0.002
STEP_RATIO = 2.0


@dataclass
class SharedMotion:
    """The shared (whole-specimen) motion of every series frame relative to the reference.

    Attributes:
        kind: "translation", "affine" or "quadratic".
        params: (T_series, 6) float64 per frame, (T_series, 12) for "quadratic" (columns
            ``PARAM_NAMES``): a_x, a_y (px, the displacement at ``origin``), du/dx, du/dy,
            dv/dx, dv/dy there (px/px; zeros for "translation") and the second derivatives
            (px/px^2). Frames not measured: interpolated in time.
        origin: (2,) x0, y0 px, the point the translation refers to (centre of the POIs).
        scatter: (T_series,) robust std (px) of the points about the fitted motion (NaN where
            not measured): the deformation plus the noise.
        points: (T_series,) points that carried the fit per frame.
        measured: (T_series,) bool, frames with their own estimate.
        se: (T_series,) standard error of the translation per component, px (NaN where not
            measured; 0 at the reference).
        times: (T_series,) the series frames' times (None: frame indices).
        steps: series frames that begin a new load state (:func:`detect_steps`); windows stay
            inside a load state where it holds 2m+1 frames.
        applied: whether the windows carry it (``"auto"`` applies it only where the jitter is
            significant: :meth:`significance`).
        seconds: wall time of the measurement.
        sample: the pass's solutions at its sample points (the first block's initial guess).
    """

    kind: str
    params: np.ndarray
    origin: np.ndarray
    scatter: np.ndarray
    points: np.ndarray
    measured: np.ndarray
    se: np.ndarray | None = None
    times: np.ndarray | None = None
    steps: list[int] = field(default_factory=list)
    applied: bool = True
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    #: the measuring pass's trusted solutions at its sample of POIs
    #: (:class:`~torch_stsdic.movie.sample_guess.MeasuredSample`: the first block's initial guess);
    #: None where not measured by a pass (not written to results)
    sample: Any = field(default=None, repr=False)

    def significance(self) -> float:
        """How far the translation departs from a line in time, in units of its own
        estimation noise: the median over frames of ``|a_t+1 - 2 a_t + a_t-1|^2 / (6 se^2)``
        divided by its median without any jitter (ln 4), ``se`` including ``SE_FLOOR``. About
        1 for a motion that is affine in time (the estimate's noise alone); a jitter of std j
        gives about (j / se)^2. NaN when fewer than 3 measured frames."""
        if self.se is None or len(self.params) < 3:
            return float("nan")
        a = self.params[:, :2]
        d2 = np.linalg.norm(a[2:] - 2 * a[1:-1] + a[:-2], axis=1) ** 2
        se = np.sqrt(self.se ** 2 + SE_FLOOR ** 2)
        var = se[2:] ** 2 + 4 * se[1:-1] ** 2 + se[:-2] ** 2  # per component
        ok = (self.measured[2:] & self.measured[1:-1] & self.measured[:-2]
              & np.isfinite(var) & (var > 0))
        if not ok.any():
            return float("nan")
        return float(np.median(d2[ok] / var[ok]) / np.log(4.0))

    def _at(self, points: Tensor, frames: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        p = torch.as_tensor(self.params, dtype=torch.float64)[frames.long().cpu()]  # (K, P)
        p = p.to(device=points.device)
        d = points.double() - torch.as_tensor(self.origin, dtype=torch.float64,
                                              device=points.device)
        return p, d[:, 0], d[:, 1]

    def displacement(self, points: Tensor, frames: Tensor) -> Tensor:
        """(K, N, 2) the shared motion's displacement (u, v) px at ``points`` (N, 2) px in
        series frames ``frames`` (K,), in the points' dtype and device."""
        p, dx, dy = self._at(points, frames)
        u = p[:, 0:1] + p[:, 2:3] * dx + p[:, 3:4] * dy
        v = p[:, 1:2] + p[:, 4:5] * dx + p[:, 5:6] * dy
        if p.shape[1] == 12:
            u = u + 0.5 * p[:, 6:7] * dx * dx + p[:, 7:8] * dx * dy + 0.5 * p[:, 8:9] * dy * dy
            v = v + 0.5 * p[:, 9:10] * dx * dx + p[:, 10:11] * dx * dy + 0.5 * p[:, 11:12] * dy * dy
        return torch.stack([u, v], -1).to(points.dtype)

    def gradient(self, points: Tensor, frames: Tensor) -> Tensor:
        """(K, N, 4) du/dx, du/dy, dv/dx, dv/dy of the shared motion at ``points`` (N, 2) in
        series frames ``frames`` (K,)."""
        p, dx, dy = self._at(points, frames)
        g = [p[:, 2:3] + 0 * dx, p[:, 3:4] + 0 * dx, p[:, 4:5] + 0 * dx, p[:, 5:6] + 0 * dx]
        if p.shape[1] == 12:
            g[0] = g[0] + p[:, 6:7] * dx + p[:, 7:8] * dy
            g[1] = g[1] + p[:, 7:8] * dx + p[:, 8:9] * dy
            g[2] = g[2] + p[:, 9:10] * dx + p[:, 10:11] * dy
            g[3] = g[3] + p[:, 10:11] * dx + p[:, 11:12] * dy
        return torch.stack(g, -1).to(points.dtype)

    @property
    def rotation(self) -> np.ndarray:
        """(T_series,) small-angle rotation per frame, rad ((dv/dx - du/dy) / 2)."""
        return 0.5 * (self.params[:, 4] - self.params[:, 3])

    def jitter(self) -> np.ndarray:
        """(T_series,) px, the frame-to-frame jitter of the translation: |second difference|
        / sqrt(6) (a smooth motion gives ~0; independent jitter of std s gives ~s)."""
        a = self.params[:, :2]
        out = np.full(len(a), np.nan)
        if len(a) >= 3:
            d2 = a[2:] - 2 * a[1:-1] + a[:-2]
            out[1:-1] = np.linalg.norm(d2, axis=1) / np.sqrt(6.0)
        return out

    def summary(self) -> dict[str, Any]:
        """JSON-friendly record for ``TrackResult.info["shared_motion"]`` (per-frame arrays
        as lists, so the result file and ``TrackResult.shared_motion`` carry them)."""
        jit = self.jitter()
        fin = jit[np.isfinite(jit)]
        return {
            "kind": self.kind,
            "origin": [float(x) for x in self.origin],
            "params": np.round(self.params, 9).tolist(),
            "scatter": [None if not np.isfinite(s) else round(float(s), 6)
                        for s in self.scatter],
            "points": [int(n) for n in self.points],
            "measured": [bool(b) for b in self.measured],
            "jitter_px_median": round(float(np.median(fin)), 6) if fin.size else None,
            "jitter_px_max": round(float(np.max(fin)), 6) if fin.size else None,
            "se": [None if not np.isfinite(s) else round(float(s), 7)
                   for s in (self.se if self.se is not None else self.scatter * np.nan)],
            "significance": (round(self.significance(), 3)
                             if np.isfinite(self.significance()) else None),
            "applied": bool(self.applied),
            "steps": [int(k) for k in self.steps],
            "times": (None if self.times is None
                      else [float(t) for t in np.asarray(self.times, dtype=np.float64)]),
            "seconds": round(self.seconds, 3),
            **self.extra,
        }

    @classmethod
    def from_summary(cls, rec: dict[str, Any]) -> SharedMotion:
        """The inverse of :meth:`summary`."""
        known = {"kind", "origin", "params", "scatter", "points", "measured", "seconds",
                 "jitter_px_median", "jitter_px_max", "se", "significance", "applied",
                 "times", "steps"}
        se = rec.get("se")
        return cls(kind=rec["kind"], params=np.asarray(rec["params"], dtype=np.float64),
                   origin=np.asarray(rec["origin"], dtype=np.float64),
                   scatter=np.array([np.nan if s is None else s for s in rec["scatter"]],
                                    dtype=np.float64),
                   points=np.asarray(rec["points"], dtype=np.int64),
                   measured=np.asarray(rec["measured"], dtype=bool),
                   se=None if se is None else np.array([np.nan if s is None else s
                                                        for s in se], dtype=np.float64),
                   applied=bool(rec.get("applied", True)),
                   steps=[int(k) for k in rec.get("steps", [])],
                   times=(None if rec.get("times") is None
                          else np.asarray(rec["times"], dtype=np.float64)),
                   seconds=float(rec.get("seconds", 0.0)),
                   extra={k: v for k, v in rec.items() if k not in known})


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
    entries, NaN where none; without a copy of ``v`` (a bisection on the float64 bit
    patterns, which order values >= 0 as the values: 63 counts over ``v``)."""
    n_ok = int(torch.count_nonzero(v >= 0))
    if n_ok == 0:
        return torch.tensor(float("nan"), dtype=torch.float64)
    rank = (n_ok - 1) // 2
    lo, hi = 0, 0x7FF0000000000000  # +0.0 and +inf
    while lo < hi:
        mid = (lo + hi) // 2
        at = torch.tensor([mid], dtype=torch.int64).view(torch.float64).to(v.device)
        if int(torch.count_nonzero(v <= at)) > rank:
            hi = mid
        else:
            lo = mid + 1
    return torch.tensor([lo], dtype=torch.int64).view(torch.float64)[0]


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


def window_offsets(g: Tensor, dt: Tensor) -> Tensor:
    """The known motion of every frame of a window: the shared motion's jitter about its own
    line through the window (module docstring).

    Args:
        g: (..., T, 2) the shared motion's displacement at a point in the window's T frames.
        dt: (..., T) frame times minus the target's (0 at the target frame).

    Returns:
        (..., T, 2) ``o_t = g_t - g_k - beta dt_t`` (``beta`` the least-squares slope of g over
        the window; ``g_k`` its value at dt = 0), 0 where the window has one frame."""
    dt = dt.to(g.dtype)
    t_count = dt.shape[-1]
    if t_count < 2:
        return torch.zeros_like(g)
    dc = dt - dt.mean(-1, keepdim=True)
    den = (dc * dc).sum(-1, keepdim=True).clamp(min=1e-30)
    beta = ((dc.unsqueeze(-1) * (g - g.mean(-2, keepdim=True))).sum(-2)
            / den)  # (..., 2)
    at0 = (dt == 0).to(g.dtype)
    has0 = at0.sum(-1, keepdim=True) > 0
    g_k = (g * at0.unsqueeze(-1)).sum(-2) / at0.sum(-1, keepdim=True).clamp(min=1)
    line0 = g.mean(-2) - beta * dt.mean(-1, keepdim=True)  # the line's value at dt = 0
    g_k = torch.where(has0, g_k, line0)
    return g - g_k.unsqueeze(-2) - beta.unsqueeze(-2) * dt.unsqueeze(-1)


def detect_steps(residual: Tensor, valid: Tensor, sigma: Tensor, frames: Sequence[int],
                 z: float = STEP_Z, ratio: float = STEP_RATIO, reach: int = 5) -> list[int]:
    """Load steps: frames where the deformation jumps while it holds still around them.

    Args:
        residual: (F, N, 2) each point's displacement minus the shared motion (the
            deformation's own part), px, at series frames ``frames`` (F,) ascending.
        valid: (F, N) bool measurements to use.
        sigma: (F,) typical classical noise std of one displacement component, px.
        frames: the series index of each row.

    A frame ``t`` (following frame ``t - 1`` in the series) starts a new load state when the
    median increment ``s_t = med_i |r_i(t) - r_i(t-1)|`` exceeds both ``z`` times its noise
    level (1.18 sigma, the median length of the increment of two frames' noise: the
    reference's noise, half of sigma^2, cancels) and ``ratio`` times the median increment of
    the frames within ``reach`` of it: a jump among still frames (measured on renders: holds
    at 1.0 sigma, a 0.3 px sinusoidal step at 3 sigma). A steady motion (every increment
    alike) or one load state per image has no step.

    Returns:
        series frames that begin a new segment (ascending)."""
    if residual.shape[0] < 3:
        return []
    return steps_from_increments(step_increments(residual, valid), sigma, frames, z, ratio,
                                 reach)


def step_increments(residual: Tensor, valid: Tensor) -> Tensor:
    """(F - 1,) px the median over the points valid in both frames of each point's increment
    ``|r_i(t+1) - r_i(t)|`` into frames 1.. of ``residual`` (F, N, 2) (``valid`` (F, N));
    frame chunk by frame chunk (each increment's median is its own: a caller may give the
    rows of a long series a chunk at a time, each with one frame more)."""
    f = residual.shape[0]
    s = torch.empty(max(f - 1, 0), dtype=residual.dtype, device=residual.device)
    for sl in frame_chunks(f - 1, residual.shape[1]):  # bounded memory, the same numbers
        a, b = sl.start, sl.stop
        both = valid[a + 1:b + 1] & valid[a:b]
        inc = (residual[a + 1:b + 1] - residual[a:b]).norm(dim=-1)
        inc = torch.where(both & torch.isfinite(inc), inc, torch.nan)
        s[sl] = torch.nanmedian(inc, dim=1).values  # increment into frames[1:]
    return s


def steps_from_increments(s: Tensor, sigma: Tensor, frames: Sequence[int],
                          z: float = STEP_Z, ratio: float = STEP_RATIO, reach: int = 5
                          ) -> list[int]:
    """The load steps of :func:`detect_steps` from the median increments ``s`` (F - 1,)
    (:func:`step_increments`), the noise ``sigma`` (F,) and the series frames (F,)."""
    f = len(frames)
    if f < 3:
        return []
    fr = torch.as_tensor(list(frames))
    adjacent = (fr[1:] - fr[:-1]) == 1
    noise = 1.1774 * torch.maximum(sigma[1:], sigma[:-1])
    out = []
    for j in range(f - 1):
        if not bool(adjacent[j]) or not bool(torch.isfinite(s[j])):
            continue
        near = [i for i in range(max(0, j - reach), min(f - 1, j + reach + 1)) if i != j]
        base = torch.nanmedian(s[near]) if near else torch.tensor(float("nan"))
        if not bool(torch.isfinite(base)):
            continue
        if float(s[j]) > z * float(noise[j]) and float(s[j]) > ratio * float(base):
            out.append(int(fr[j + 1]))
    return out


def overlap_factor(points: Tensor, subset_size: int) -> float:
    """Standard-error factor for the errors of overlapping subsets: points closer than a
    subset share pixels, so their errors correlate and n points carry about
    ``n (spacing / subset)^2`` independent measurements: ``max(1, subset / spacing)``, the
    spacing being the median nearest-neighbour distance (measured: 2.0 at subset 21, step
    10; this gives 2.1)."""
    if points.shape[0] < 2:
        return 1.0
    d = torch.cdist(points.double(), points.double())
    d.fill_diagonal_(float("inf"))
    spacing = float(d.min(1).values.median())
    return max(1.0, float(subset_size) / max(spacing, 1e-9))


def known_window_motion(shared: Tensor, dt: Tensor, shape_hint: str = "") -> Tensor:
    """(N, T, 2) what a window carries of a known shared motion given by the user: ``shared``
    (T, 2) (the same at every point) or (N, T, 2) px per frame, ``dt`` (N, T) frame times
    minus the target's; checked (shape, finite values: ValueError naming
    ``shared_motion``), then :func:`window_offsets`, in ``dt``'s dtype and device.
    ``shape_hint``: the accepted shapes as the caller names them, for the error."""
    n, t_count = dt.shape
    g = torch.as_tensor(shared).detach().to(device=dt.device, dtype=dt.dtype)
    if g.dim() == 2:
        g = g.unsqueeze(0).expand(n, -1, -1)
    if tuple(g.shape) != (n, t_count, 2):
        hint = shape_hint or f"({t_count}, 2) or (N={n}, {t_count}, 2)"
        raise ValueError(f"shared_motion must be {hint}, got "
                         f"{tuple(torch.as_tensor(shared).shape)}")
    if not bool(torch.isfinite(g).all()):
        raise ValueError("shared_motion contains NaN or infinite values")
    return window_offsets(g, dt).contiguous()


def sample_points(points: Tensor, max_points: int) -> Tensor:
    """(n,) indices of at most ``max_points`` of the POIs, spread evenly over them."""
    n = points.shape[0]
    if n <= max_points:
        return torch.arange(n)
    return torch.linspace(0, n - 1, int(max_points)).round().long().unique()
