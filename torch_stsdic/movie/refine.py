"""Refined reference: lift the single-reference noise floor by re-zeroing every trajectory.

With a noisy reference ``f = f0 + n_ref`` every Gauss-Newton solve of a point sees the same
reference subset, so to first order its error is ``P (n_t - n_ref)``: a part ``c = -P n_ref``
that is the *same* for every frame and window of the point (a constant offset in time), and
the frames' part ``s_t = P n_t`` that the STS window averages. The window cannot remove the
offset; averaging warped frames into a new reference does not either (such a template
inherits the offset it was warped with). What removes it is the definition of zero
displacement: the truth is 0 at the reference time, so the offset is the value a *fit over
many frames* of the point's own trajectory takes at the reference time.

:func:`measure_offsets` runs classical DIC (every frame alone against the reference) on up to
``max_frames`` frames around the reference -- the reference itself left out: matched against
itself it gives exactly 0, which says nothing about ``c`` -- then per point fits polynomials in
time to the per-frame values over nested windows and keeps the fit with the smallest predicted
intercept variance among those whose next-higher term is not significant (|t| below Student's
t quantile of the normal's 3 at the degrees of freedom of the noise, which comes from the
trajectory's own third differences): long linear fits where the motion is smooth, short or
quadratic ones where it is not. The intercepts are then shrunk towards 0 by
``rho / (rho + d)`` (``d``: the fit's intercept variance in units of the per-frame variance;
``rho``: var(c) / var(s_t), estimated over all points), the least-squares estimate of ``c``
given that the offsets are zero-mean with that variance (empirical Bayes; rho ~ 1 where every
image has the same noise, large where the frames are much cleaner than the reference).

:func:`apply_offsets` subtracts the intercepts (u, v and the displacement gradients;
velocities have no offset) from result rows, sets the reference frame's own row to the
truth (zero displacement and gradients, and their predicted std; the velocity as measured),
and scales the other rows' u_std, v_std by :func:`std_factor` (the first-order ratio of the
refined to the unrefined error at that frame).

What remains is ``s_bar(t) - dc`` (``s_bar``: the window's average of the frames' errors, ``dc``:
the intercept's error), which is *not* the same at every frame: ``dc`` is a weighted sum of
the same frames' errors (positive weights near the reference, negative at the far end of a
line's span), so its covariance with ``s_bar(t)`` lowers the error near the reference and
raises it far from it; per point the remainder is ``db t + (local residual)``, ``db`` the fitted
slope's error. Measured on renders, this first-order profile is the whole story (no term in
the displacement from the noisy reference gradient): ``docs/accuracy.md``,
``scripts/refine_drift.py``.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.frames import window_frames
from torch_stsdic.movie.plan import RunPlan

__all__ = ["ReferenceOffsets", "check_refinable", "fit_frames", "measure_offsets",
           "fit_intercepts", "apply_offsets", "predicted_profile", "std_factor",
           "set_refinement",
           "DEFAULT_MAX_FRAMES"]

DEFAULT_MAX_FRAMES = 41
_T_LIMIT = 3.0  # |t| of the next polynomial term above which a fit is rejected
_BIAS_SPAN = 0.5  # px a component must move over a window for the sub-pixel bias terms
_BIAS_CHI2 = 2.0  # mean (coefficient / std)^2 of the bias terms above which they are used
_RATES = ("ut", "vt")


@dataclass
class ReferenceOffsets:
    """Per-point offsets of a noisy reference (subtract them from every row).

    Attributes:
        values: name -> (N,) float64 intercepts at the reference time (u, v px; gradients).
        frames: (N,) frames of the fit kept per point (0: not refined, no usable fit).
        degree: (N,) polynomial degree of that fit (1 linear, 2 quadratic; 0 none).
        sigma: (N,) per-frame scatter of u (px) estimated from the trajectory.
        seconds: wall time of the measurement.
        bias_terms: whether the sub-pixel interpolation-bias terms were fitted.
        shrink: (N,) factor the fitted intercepts were multiplied by (``rho / (rho + d)``; 1
            where not refined).
        rho: estimated var(offset) / var(per-frame error) over all points (inf: no shrink).
        reference_frame: series index of the reference (its row is set to zero displacement
            by :func:`apply_offsets`); -1 when unknown.
        t_fit: (L,) times of the fitted frames minus the reference time; min_frames: the
            shortest window tried (with ``frames``, they give each point's fitted window).
        fit: (L,) series indices of the fitted frames; times: (T,) series times; m: the run's
            window half-width (set by :func:`measure_offsets`; used to rescale u_std, v_std).
        excess: variance of the intercepts beyond the reference's noise and the fits' errors,
            in units of the per-frame variance (0: none): motion near the reference that no
            accepted fit describes (:func:`_shrink`); the subtracted share of it is error.
        rho_images: var(offset) / var(per-frame error) the images' noise allows
            (:func:`images_rho`; NaN: not measured), the cap on ``rho``.
    """

    values: dict[str, np.ndarray]
    frames: np.ndarray
    degree: np.ndarray
    sigma: np.ndarray
    seconds: float
    bias_terms: bool = False
    shrink: np.ndarray | None = None
    rho: float = float("inf")
    reference_frame: int = -1
    t_fit: np.ndarray | None = None
    min_frames: int = 5
    fit: np.ndarray | None = None
    times: np.ndarray | None = None
    m: int = 0
    excess: float = 0.0
    rho_images: float = float("nan")

    def summary(self) -> dict[str, float | int]:
        """JSON-friendly summary for ``TrackResult.info["refine_reference"]``."""
        ok = self.frames > 0
        return {"points": int(ok.size), "refined": int(ok.sum()),
                "frames_median": float(np.median(self.frames[ok])) if ok.any() else 0.0,
                "linear_fraction": float((self.degree[ok] == 1).mean()) if ok.any() else 0.0,
                "bias_terms": bool(self.bias_terms),
                "rho": round(self.rho, 3) if np.isfinite(self.rho) else None,
                "rho_images": (round(self.rho_images, 3) if np.isfinite(self.rho_images)
                               else None),
                "excess": round(self.excess, 3) if np.isfinite(self.excess) else None,
                "shrink": (round(float(np.median(self.shrink[ok])), 4)
                           if ok.any() and self.shrink is not None else 1.0),
                "seconds": round(self.seconds, 3)}


def check_refinable(plan: RunPlan) -> None:
    """Raise ValueError where the refined reference cannot apply: the reference must be one
    frame of the series (its time is where displacement is zero), without reference updates,
    and the series needs at least 5 frames."""
    if plan.reference_image is not None or plan.reference_frame < 0:
        raise ValueError(
            f"refine_reference: needs a reference that is one frame of the series (its time "
            f"defines zero displacement); got {plan.reference_desc!r}. Pass reference=<frame "
            "index>, or refine_reference=False")
    if plan.options.get("reference_update") is not None:
        raise ValueError("refine_reference: cannot be combined with reference_update (each "
                         "updated reference would carry its own noise offset)")
    if len(plan.series) < 5:
        raise ValueError(f"refine_reference: needs >= 5 frames in the series, got "
                         f"{len(plan.series)}")


def fit_frames(plan: RunPlan, max_frames: int) -> list[int]:
    """The (up to) ``max_frames`` series frames nearest the reference in time, contiguous
    (centred on it, shifted at the ends of the series)."""
    n = len(plan.series)
    count = min(int(max_frames), n)
    start = min(max(plan.reference_frame - count // 2, 0), n - count)
    return list(range(start, start + count))


def measure_offsets(plan: RunPlan, max_frames: int = DEFAULT_MAX_FRAMES,
                    shared: SharedMotion | None = None, *,
                    run: Callable[..., TrackResult]) -> ReferenceOffsets:
    """Classical DIC of the frames around the reference, then :func:`fit_intercepts`.

    With the specimen's ``shared`` motion (:mod:`torch_stsdic.core.shared_motion`) the fits are
    of each trajectory *minus* it: a specimen that shakes as a whole leaves smooth
    trajectories, so the long fits pass their test; the shared motion is zero at the
    reference, so the intercepts are the same offsets."""
    check_refinable(plan)
    if int(max_frames) < 5:
        raise ValueError(f"refine_frames: must be >= 5, got {max_frames!r}")
    t0 = time.perf_counter()
    # the reference against itself gives exactly 0, whatever its offset: left out of the fit
    # (and any frame stamped with the reference's time, which fit_intercepts drops too)
    t_ref = plan.times[plan.reference_frame]
    frames = [k for k in fit_frames(plan, max_frames)
              if k != plan.reference_frame and plan.times[k] != t_ref]
    cfg = plan.config.replace(m=0)
    opts = {**plan.options, "smoothing": None, "reference_update": None,
            "shared_motion": None}
    opts.pop("refine_reference", None)
    opts["series_reference"] = None  # a sub-run: against the plan's reference image
    names = tuple(nm for nm in plan.param_names if nm not in _RATES)
    sub = dataclasses.replace(plan, config=cfg, targets=frames, options=opts,
                              param_names=names)
    res = run(sub, progress=False)
    vals = {"u": res.u, "v": res.v, **res.gradients}
    ys = {k: np.asarray(v.detach().cpu().numpy(), dtype=np.float64) for k, v in vals.items()}
    usable = (res.status <= USABLE).cpu().numpy()
    for k in ys:
        ys[k] = np.where(usable, ys[k], np.nan)
    if shared is not None:
        _remove_shared(ys, shared, plan, frames)
    t = plan.times[frames] - plan.times[plan.reference_frame]
    pred = {k: np.where(usable, np.asarray(res.std[k].detach().cpu().numpy(), np.float64) ** 2,
                        np.nan) for k in ("u", "v") if k in res.std}
    rho_img = images_rho(t, ys, pred) if len(pred) == 2 else float("nan")
    out = fit_intercepts(t, ys, min_frames=max(5, plan.config.n_frames), rho_images=rho_img)
    if out.excess > 0:
        warnings.warn(
            f"refine_reference: the intercepts of the trajectories vary "
            f"{out.rho + out.excess:.3g} per-frame variances, the images' noise allows "
            f"{rho_img:.3g}: the motion next to the reference is not what the fits say "
            f"(it decelerates, or moves in load steps), so little is subtracted (median shrink "
            f"{float(np.median(out.shrink[out.frames > 0])) if (out.frames > 0).any() else 1:.3g})",
            RuntimeWarning, stacklevel=2)
    out.seconds = time.perf_counter() - t0
    out.reference_frame = int(plan.reference_frame)
    out.fit = np.asarray(frames, dtype=np.int64)
    out.times = np.asarray(plan.times, dtype=np.float64)
    out.m = int(plan.config.m)
    return out


def images_rho(t: np.ndarray, ys: dict[str, np.ndarray], pred: dict[str, np.ndarray],
               nearest: int = 5) -> float:
    """var(offset) / var(per-frame error) as the images' noise gives it, without the fits.

    Classical DIC's predicted variance (``u_std^2`` of the classical pass, from each
    solution's residual: the reference's and the frame's noise together, ``(rho + 1) a^2``
    whatever their split) over the trajectory's per-frame variance ``a^2`` (third
    differences, as :func:`fit_intercepts`), minus 1: the median over the points and both
    components, at the ``nearest`` frames nearest the reference (the residual holds the least
    deformation misfit there), times the median of chi-square(nu) / nu (Wilson-Hilferty; nu
    the degrees of freedom of ``a^2``, as in :func:`fit_intercepts`) for the spread of ``a^2``.
    About 1 with the same noise on every image (0.8-1.4 measured: the prediction is ~5 %
    high), 25 with a 5x noisier reference; 0 or more.

    Args:
        t: (L,) frame times minus the reference time; ys: name -> (L, N) trajectories ("u",
            "v"); pred: "u", "v" -> (L, N) predicted classical variances (NaN: not usable).
    """
    t = np.asarray(t, dtype=np.float64)
    keep = t != 0
    near = np.argsort(np.abs(t[keep]), kind="stable")[:max(int(nearest), 1)]
    ratios = []
    for comp in ("u", "v"):
        y = np.asarray(ys[comp])[keep]
        sig2 = _noise_var(y)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
            p2 = np.nanmedian(np.asarray(pred[comp])[keep][near], axis=0)
        r = p2 / sig2
        ratios.append(r[np.isfinite(r) & (r > 0)])
    r = np.concatenate(ratios)
    if r.size < 8:
        return float("nan")
    n3 = np.isfinite(np.diff(np.asarray(ys["u"])[keep], n=3, axis=0)).sum(0)
    nu = float(np.median(n3)) / _D3_VAR_FACTOR if n3.size else 0.0
    med_chi2 = (1.0 - 2.0 / (9.0 * nu)) ** 3 if nu > 0.5 else 1.0
    return max(float(np.median(r)) * med_chi2 - 1.0, 0.0)


def _remove_shared(ys: dict[str, np.ndarray], shared: SharedMotion, plan: RunPlan,
                   frames: list[int]) -> None:
    """Subtract the shared motion (displacement and its gradients) of ``frames`` at the
    plan's points from the (F, N) trajectories ``ys`` in place."""
    pts = plan.points.double()
    g = shared.displacement(pts, torch.as_tensor(frames)).numpy()  # (F, N, 2)
    ys["u"] = ys["u"] - g[..., 0]
    ys["v"] = ys["v"] - g[..., 1]
    grad = shared.gradient(pts, torch.as_tensor(frames)).numpy()  # (F, N, 4)
    for j, nm in enumerate(("ux", "uy", "vx", "vy")):
        if nm in ys:
            ys[nm] = ys[nm] - grad[..., j]


def _candidates(t: np.ndarray, min_frames: int) -> list[np.ndarray]:
    """Nested windows (index arrays into ``t``) around t = 0: all, then halves ... down to
    ``min_frames`` frames."""
    order = np.argsort(np.abs(t), kind="stable")
    out, count = [], len(t)
    while True:
        idx = np.sort(order[:count])
        out.append(idx)
        if count <= min_frames:
            break
        count = max(min_frames, count // 2)
    return out


def fit_intercepts(t: np.ndarray, ys: dict[str, np.ndarray], *, min_frames: int = 5,
                   t_limit: float = _T_LIMIT, rho_images: float = np.nan) -> ReferenceOffsets:
    """Per point, the intercept at t = 0 of the best polynomial fit of its trajectory, shrunk
    towards 0 by ``rho / (rho + d)`` (:func:`_shrink`).

    Where the images show a sub-pixel interpolation bias (:func:`_bias_significant`) and a
    component moves by >= 0.5 px over a window, its fit also has the terms sin(2 pi w),
    sin(4 pi w) of the (polynomially smoothed) measured displacement w: that bias is odd and
    1-px periodic, so these absorb it (it would otherwise leak into the intercept of a line
    through a few periods) without touching the value at w = 0.

    Args:
        t: (L,) frame times minus the reference time; a frame at t = 0 (the reference
            matched against itself: 0 by construction) is left out.
        ys: name -> (L, N) per-frame values (NaN where not usable); "u" and "v" decide; the
            names starting with "v" use the v component's bias terms, the others u's.
        min_frames: the shortest window tried.
        t_limit: a fit of degree d over a window is accepted where the added term of degree
            d + 1 has |coefficient / standard error| below the Student-t quantile, at the
            trajectory noise estimate's degrees of freedom, of the normal's ``t_limit`` (3:
            two-sided 0.27 %; 3.5 for 40 frames, ~10 for 9, where the noise is known from
            6 third differences and the normal's threshold rejected 4-12 % of straight
            trajectories) in both u and v.
        rho_images: var(offset) / var(per-frame error) as the images' noise gives it
            (:func:`images_rho`; NaN: not known, rho from the intercepts alone). Where the
            intercepts' spread is far above it, the rest is motion the fits missed
            (:func:`_shrink`).

    Returns:
        :class:`ReferenceOffsets` (offset 0 and frames 0 where no window is usable).
    """
    t = np.asarray(t, dtype=np.float64)
    keep = t != 0
    t, ys = t[keep], {k: np.asarray(v)[keep] for k, v in ys.items()}
    n = next(iter(ys.values())).shape[1]
    scale = max(float(np.abs(t).max()), 1.0)
    sig2 = {k: _noise_var(ys[k]) for k in ("u", "v")}
    n3 = np.isfinite(np.diff(ys["u"], n=3, axis=0)).sum(0)  # third differences per point
    dof = float(np.median(n3)) / _D3_VAR_FACTOR if n3.size else 0.0
    t_crit = _t_quantile(t_limit, dof)
    bias = _bias_significant(t / scale, ys, sig2)
    min_frames = max(int(min_frames), _test_unknowns(1, bias) + 1)
    best_var = np.full(n, np.inf)
    best_d = np.full(n, np.nan)  # intercept variance / per-frame variance of the kept fit
    best = {k: np.zeros(n) for k in ys}
    frames = np.zeros(n, dtype=np.int64)
    degree = np.zeros(n, dtype=np.int64)
    fallback = None
    for idx in _candidates(t, min_frames):
        ts = t[idx] / scale
        for d in (1, 2):
            if len(idx) <= _test_unknowns(d, bias):  # the noise needs >= 1 dof
                continue
            fin = np.ones(n, dtype=bool)
            ok = np.ones(n, dtype=bool)
            coef: dict[str, np.ndarray] = {}
            var = np.zeros(n)
            d00 = np.zeros(n)
            for comp in ("u", "v"):
                y_c = np.nan_to_num(ys[comp][idx])
                fin &= np.isfinite(ys[comp][idx]).all(0)
                c_fit, cov_fit = _fit(ts, d + 1, y_c, bias=bias)
                c_test, cov_test = _fit(ts, d + 2, y_c, bias=bias)
                top = d + 1  # the added polynomial term (the bias terms follow it)
                ok &= np.abs(c_test[top]) < t_crit * np.sqrt(sig2[comp] * cov_test[:, top, top])
                if comp == "u":
                    var = sig2["u"] * cov_fit[:, 0, 0]
                    d00 = cov_fit[:, 0, 0]
                for k in ys:
                    if (k[0] == "v") == (comp == "v"):
                        coef[k] = _fit(ts, d + 1, y_c, np.nan_to_num(ys[k][idx]), bias=bias)[0][0]
            if fallback is None or len(idx) <= len(fallback[0]):
                fallback = (idx, d, coef, fin, d00)  # the shortest quadratic fit, if none passes
            take = fin & ok & np.isfinite(var) & (var < best_var)
            best_var = np.where(take, var, best_var)
            best_d = np.where(take, d00, best_d)
            for k in ys:
                best[k] = np.where(take, coef[k], best[k])
            frames = np.where(take, len(idx), frames)
            degree = np.where(take, d, degree)
    if fallback is not None:
        idx, d, coef, fin, d00 = fallback
        take = (frames == 0) & fin
        for k in ys:
            best[k] = np.where(take, coef[k], best[k])
        best_d = np.where(take, d00, best_d)
        frames = np.where(take, len(idx), frames)
        degree = np.where(take, d, degree)
    rho, shrink, excess = _shrink(best, sig2, best_d, frames > 0, dof, rho_images)
    return ReferenceOffsets(values={k: v * shrink for k, v in best.items()}, frames=frames,
                            degree=degree, sigma=np.sqrt(sig2["u"]), seconds=0.0,
                            bias_terms=bias, shrink=shrink, rho=rho, t_fit=t,
                            min_frames=int(min_frames), excess=excess,
                            rho_images=float(rho_images))


def _test_unknowns(degree: int, bias: bool) -> int:
    """Unknowns of the test fit of a degree-``degree`` fit: the polynomial of one degree more,
    plus the two sub-pixel bias terms with ``bias``."""
    return degree + 2 + (2 if bias else 0)


#: (sum over lags of the autocovariance^2 of a third difference of white noise) / its
#: variance^2 = (20^2 + 2 (15^2 + 6^2 + 1^2)) / 20^2: the noise variance from n third
#: differences has the spread of a chi-square with n / 2.31 degrees of freedom
_D3_VAR_FACTOR = 2.31


def _t_quantile(z: float, dof: float) -> float:
    """Student-t quantile with ``dof`` degrees of freedom at the tail probability of the normal
    quantile ``z`` (Cornish-Fisher expansion, three terms; dof clamped to >= 2; z for
    dof -> inf)."""
    if not np.isfinite(dof) or dof > 1e6:
        return float(z)
    nu = max(float(dof), 2.0)
    return float(z + (z**3 + z) / (4 * nu) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * nu**2)
                 + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * nu**3))


def _f1_median(dof: float) -> float:
    """Median of F(1, dof) (the square of Student's t upper quartile; Cornish-Fisher
    expansion, within 0.5 % for dof >= 2; chi-square(1)'s 0.4549 for dof -> inf)."""
    return _t_quantile(0.67449, dof) ** 2  # 0.67449: upper quartile of N(0, 1)


def _shrink(coef: dict[str, np.ndarray], sig2: dict[str, np.ndarray], d: np.ndarray,
            fitted: np.ndarray, dof: float = np.inf, rho_images: float = np.nan
            ) -> tuple[float, np.ndarray, float]:
    """``rho``, the per-point factor ``rho / (rho + excess + d)`` (1 where not fitted) and
    ``excess``.

    Model: the fitted intercept of a point is ``c + dc``, ``c`` its offset (zero-mean over
    points, variance ``rho * sigma^2``, sigma^2 the point's per-frame variance, because the
    reference's and the frames' noise go through the same projection) and ``dc`` the fit's
    error (variance ``d * sigma^2``). So ``z = intercept^2 / (sigma^2 (rho + d))`` is chi-square
    with 1 degree of freedom, or F(1, dof) with sigma^2 estimated from the trajectory (``dof``:
    that estimate's degrees of freedom; without this, short fits overestimate rho by ~40 %);
    rho is solved from its median over the points and both components (robust to a few bad
    trajectories), and ``rho / (rho + d)`` times the intercept is
    the least-squares estimate of ``c`` (the Bayes estimate for Gaussian offsets). With every
    image equally noisy rho ~ 1 (0.6-1.2 measured on renders and real speckle); with clean
    frames rho -> inf and nothing is shrunk; with a clean reference rho -> 0 and nothing is
    subtracted.

    The intercepts' spread is the offsets' only where the motion near the reference is what
    the kept fit says. Where it is not (a deceleration: a 6-frame line through frames 1..6
    extrapolates it to t = 0 with an error proportional to the velocity, and the test of
    the next term cannot see it over so few frames), the spread also holds that motion, and
    the rho solved from it is far above what the images' noise allows (46 on the muDIC
    hourglass, 41 on a decelerating render, against ~1.2 from the noise: ``rho_images``,
    :func:`images_rho`). Where the intercepts' rho exceeds ``rho_images``, rho is
    ``rho_images`` and the rest, ``excess`` (per-frame variances), an error of the intercept
    that the offset does not share: the least-squares factor is then
    ``rho / (rho + excess + d)`` (~0.03 there: next to nothing is subtracted, instead of the
    extrapolation error), and the predicted std counts the subtracted share of it
    (:func:`_error_var`). ``rho_images`` runs ~0.3 high (the noise prediction is ~5 % high
    in std), so with the premise met (rho 1.03 from the intercepts, 1.36 from the images on
    the test render) nothing changes; where it binds by a little, the factor changes by as
    little.
    """
    n = d.shape[0]
    target = _f1_median(dof)
    zs = [coef[k] ** 2 / sig2[k] for k in ("u", "v")]
    ds = np.concatenate([d, d])
    z = np.concatenate(zs)
    use = np.concatenate([fitted, fitted]) & np.isfinite(z) & np.isfinite(ds) & (ds > 0)
    shrink = np.ones(n)
    if use.sum() < 8:  # too few points to estimate rho
        return float("inf"), shrink, 0.0
    z, ds = z[use], ds[use]

    def med(rho: float) -> float:
        return float(np.median(z / (rho + ds)))

    known = rho_images is not None and np.isfinite(rho_images)
    cap = max(float(rho_images), 0.0) if known else np.inf
    if med(1e6) >= target:  # offsets dwarf the fits' errors: no shrink (unless capped)
        if np.isinf(cap):
            return float("inf"), shrink, 0.0
        ok = fitted & np.isfinite(d) & (d > 0)
        shrink[ok] = 0.0
        return float(rho_images), shrink, float("inf")
    if med(0.0) <= target:  # intercepts no larger than the fits' errors: no offsets
        rho = 0.0
    else:  # med decreases with rho: bisection on a log scale
        lo, hi = 1e-9, 1e6
        for _ in range(50):
            mid = float(np.sqrt(lo * hi))
            lo, hi = (mid, hi) if med(mid) > target else (lo, mid)
        rho = float(np.sqrt(lo * hi))
    excess = 0.0
    if rho > cap:  # the intercepts hold more than the offsets: the rest is missed motion
        rho, excess = float(rho_images), rho - float(rho_images)
    ok = fitted & np.isfinite(d) & (d > 0)
    shrink[ok] = rho / (rho + excess + d[ok])
    return float(rho), shrink, float(excess)


def _bias_significant(ts: np.ndarray, ys: dict[str, np.ndarray],
                      sig2: dict[str, np.ndarray]) -> bool:
    """Whether the images show a sub-pixel interpolation bias worth fitting: over all points
    that move >= _BIAS_SPAN px, the mean squared t-statistic of the bias terms of a quadratic
    fit of the whole trajectory exceeds _BIAS_CHI2 (1 expected without a bias). Fitting them
    where there is no bias only adds variance to the intercepts."""
    stats = []
    if len(ts) <= _test_unknowns(1, True):  # too few frames to fit the bias terms at all
        return False
    for comp in ("u", "v"):
        y = ys[comp]
        fin = np.isfinite(y).all(0) & np.isfinite(sig2[comp])
        if not fin.any():
            continue
        coef, cov, use = _fit(ts, 3, y[:, fin], bias=True, with_use=True)
        se2 = sig2[comp][fin][:, None] * np.diagonal(cov, axis1=1, axis2=2)[:, 3:]
        stats.append((coef[3:].T ** 2 / se2)[use])
    if not stats:
        return False
    chi2 = np.concatenate(stats)
    return bool(chi2.size) and float(np.mean(chi2)) > _BIAS_CHI2


def _fit(ts: np.ndarray, n_poly: int, disp: np.ndarray, y: np.ndarray | None = None, *,
         bias: bool = True, with_use: bool = False):
    """Per-point least squares of y (L, N) (default ``disp``) on ``n_poly`` powers of ``ts``
    plus, with ``bias`` and where ``disp`` (L, N) spans >= _BIAS_SPAN px, sin(2 pi w) and
    sin(4 pi w), w the polynomial fit of ``disp``.
    Returns (coefficients (n_poly + 2, N), (X^T X)^-1 (N, n_poly + 2, n_poly + 2))."""
    y = disp if y is None else y
    length, n = disp.shape
    vand = np.vander(ts, n_poly, increasing=True)
    poly = np.broadcast_to(vand[None], (n, length, n_poly))
    # the phase from the polynomial fit of disp, not from disp itself: a regressor holding
    # the response's own noise would bias the fit
    smooth = vand @ np.linalg.lstsq(vand, disp, rcond=None)[0]
    use = bias & ((smooth.max(0) - smooth.min(0)) >= _BIAS_SPAN)  # (N,)
    harm = np.stack([np.sin(2 * np.pi * smooth.T), np.sin(4 * np.pi * smooth.T)], -1)
    harm = harm * use[:, None, None]
    x = np.concatenate([poly, harm], -1)  # (N, L, K)
    xtx = np.einsum("nlk,nlj->nkj", x, x)
    xtx[:, n_poly:, n_poly:] += np.where(use, 0.0, 1.0)[:, None, None] * np.eye(2)
    try:
        cov = np.linalg.inv(xtx)
    except np.linalg.LinAlgError:  # a degenerate point (e.g. repeated displacements)
        cov = np.linalg.pinv(xtx, hermitian=True)
    coef = np.einsum("nkj,nlj,ln->kn", cov, x, y)
    return (coef, cov, use) if with_use else (coef, cov)


def _noise_var(y: np.ndarray) -> np.ndarray:
    """(N,) per-frame noise variance of (L, N) trajectories from third differences (var of
    a third difference of white noise is 20 sigma^2; smooth motion drops out)."""
    if y.shape[0] < 4:
        return np.full(y.shape[1], np.nan)
    d3 = np.diff(y, n=3, axis=0)
    fin = np.isfinite(d3)
    count = fin.sum(0)
    v = np.where(fin, d3 * d3, 0.0).sum(0) / np.maximum(count, 1) / 20.0
    v = np.where(count > 0, v, np.nan)
    return np.where(np.isfinite(v) & (v > 0), v, np.nan)


def apply_offsets(rows: dict[str, np.ndarray], offsets: ReferenceOffsets,
                  frames: Sequence[int] | None = None) -> dict[str, np.ndarray]:
    """Rows (name -> (B, N)) with the offsets subtracted (names without an offset, and the
    velocities, unchanged). With ``frames`` (B,) (the rows' series frames), the reference
    frame's row reports the truth where it was solved (status usable): displacement and
    gradients 0, and so their predicted std (u_std, v_std); the velocity stays as measured. The
    other rows' u_std, v_std (predicted for the unrefined solution, the reference's noise
    included) are scaled by :func:`std_factor`."""
    out = dict(rows)
    for k, off in offsets.values.items():
        if k in out and k not in _RATES:
            out[k] = out[k] - off[None, :]
    if frames is None:
        return out
    frames = [int(f) for f in frames]
    stds = [k for k in ("u_std", "v_std") if k in out]
    if stds and offsets.fit is not None and offsets.times is not None:
        m_rows = out["m"] if "m" in out else np.full(out[stds[0]].shape, offsets.m)
        for k in stds:
            out[k] = out[k].copy()
        for i, fr in enumerate(frames):
            if fr != offsets.reference_frame:
                factor = std_factor(offsets, fr, np.asarray(m_rows[i]))
                for k in stds:
                    out[k][i] = out[k][i] * factor
    if offsets.reference_frame not in frames:
        return out
    i = frames.index(offsets.reference_frame)
    ok = out["status"][i] <= USABLE if "status" in out else np.ones(
        next(iter(out.values())).shape[1], dtype=bool)
    for k in [*offsets.values, "u_std", "v_std"]:
        if k in out and k not in _RATES:
            out[k] = out[k].copy()
            out[k][i] = np.where(ok, 0.0, out[k][i])
    return out


def _window_weights(t: np.ndarray, k: int, m: int) -> np.ndarray:
    """(T,) weights of the STS value at frame k on the frames: the line of its window
    (``window_frames``: k-m .. k+m, shifted at the ends) evaluated at ``t[k]``."""
    n = len(t)
    w = window_frames(torch.tensor([k]), int(m), n)[0].numpy()
    lam = np.zeros(n)
    lam[w] = np.linalg.pinv(np.stack([np.ones(len(w)), t[w] - t[k]], 1))[0]
    return lam


def _intercept_weights(t: np.ndarray, fit: np.ndarray, degree: int) -> np.ndarray:
    """(T,) weights of the intercept at t = 0 of a polynomial of ``degree`` fitted to the frames
    ``fit`` (series indices)."""
    om = np.zeros(len(t))
    om[fit] = np.linalg.pinv(np.vander(t[fit], degree + 1, increasing=True))[0]
    return om


def _error_var(lam: np.ndarray, om: np.ndarray, ref: int, rho: float,
               shrink: np.ndarray | float, excess: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """First-order variances, in units of a^2, of the STS value with weights ``lam`` minus
    ``shrink`` (k) times the intercept with weights ``om``, both on the classical errors
    ``e_j = c + s_j`` (``e_ref = 0``; var(c) = rho a^2, var(s_j) = a^2):
    ``rho (1 - lam_ref - k sum om)^2 + sum_j (lam_j - k om_j)^2`` (j != ref); and the unrefined
    variance *as* :mod:`torch_stsdic.core.uncertainty` *predicts it* (u_std): ``rho + sum_j
    lam_j^2``
    over all frames, i.e. a reference frame inside the window counted as one more independent
    frame (it is not: its ``n_t - n_ref`` is 0, so that prediction is too high for the first m
    rows; dividing by it keeps the rescaled u_std right there). rho = inf: both divided by
    rho. ``excess``: the intercept's variance that the offset does not share (motion next to
    the reference that the fit missed, :func:`_shrink`), ``k^2 excess`` more."""
    k = np.asarray(shrink, dtype=np.float64)
    rest = np.arange(len(lam)) != ref
    a, b, c = np.sum(lam[rest] ** 2), np.sum(lam[rest] * om[rest]), np.sum(om[rest] ** 2)
    coef = 1.0 - lam[ref] - k * om[rest].sum()
    frames_part = a - 2 * k * b + k * k * c
    if excess > 0:
        frames_part = frames_part + np.where(k > 0, k * k * excess, 0.0)
    if np.isinf(rho):
        return coef**2 + 0 * frames_part, 1.0 + 0 * k
    return rho * coef**2 + frames_part, rho + np.sum(lam**2) + 0 * k


def predicted_profile(times: np.ndarray, reference_frame: int, fit: Sequence[int], m: int,
                      rho: float, shrink: float = 1.0, excess: float = 0.0) -> np.ndarray:
    """(T,) first-order variance of the refined STS error at every frame of a series, in units
    of the per-frame variance ``a^2`` of classical DIC, for an offset from a straight line.

    Frame ``k``'s STS value is the line of its window (``window_frames``: k-m .. k+m, shifted at
    the ends) evaluated at ``t_k``, weights ``lam_k``, on the classical errors ``e_j = c + s_j``
    (``e_ref = 0``: the reference against itself); the offset subtracted is ``sum_j om_j e_j``
    (``om``: ``shrink`` times the intercept weights of the line through ``fit``). So the error is
    ``c (1 - lam_k,ref - sum om) + sum_j (lam_kj - om_j) s_j``, with ``var(c) = rho a^2`` and
    ``var(s_j) = a^2``; the reference's own row is exact (0).

    Args:
        times: (T,) series times; reference_frame: its index; fit: series indices of the fit's
        frames (the reference excluded); m: window half-width (0: classical); rho, shrink,
        excess: as in :class:`ReferenceOffsets`.
    """
    t = np.asarray(times, dtype=np.float64) - float(times[reference_frame])
    fit_idx = np.asarray([j for j in fit if j != reference_frame], dtype=np.int64)
    om = _intercept_weights(t, fit_idx, 1)
    out = np.zeros(len(t))
    for k in range(len(t)):
        if k != reference_frame:
            out[k] = float(_error_var(_window_weights(t, k, m), om, reference_frame, rho,
                                      shrink, excess)[0])
    return out


def std_factor(offsets: ReferenceOffsets, frame: int, m_row: np.ndarray) -> np.ndarray:
    """(N,) first-order std of the refined u (or v) at series ``frame`` over the unrefined
    one that u_std predicts (:func:`_error_var`), per point: its kept fit (window and degree;
    the bias terms left out) and shrink, the row's window half-width ``m_row`` (N,) (-1: not
    solved, factor 1), and rho. Multiplies the predicted u_std, v_std (which hold the
    reference's share) of refined rows: about 0.3-0.55 at 40 fitted frames, lowest near the
    reference, so the stored std follows the per-frame profile (``docs/accuracy.md``)."""
    n = len(m_row)
    out = np.ones(n)
    t = offsets.times - offsets.times[offsets.reference_frame]
    ref = offsets.reference_frame
    cands = {len(idx): offsets.fit[idx] for idx in _candidates(offsets.t_fit, offsets.min_frames)}
    shrink = offsets.shrink if offsets.shrink is not None else np.ones(n)
    for mm in np.unique(m_row[m_row >= 0]):
        lam = _window_weights(t, frame, int(mm))
        for count, fit in cands.items():
            for deg in (1, 2):
                sel = (m_row == mm) & (offsets.frames == count) & (offsets.degree == deg)
                if not sel.any() or len(fit) <= deg:
                    continue
                var, var0 = _error_var(lam, _intercept_weights(t, fit, deg), ref, offsets.rho,
                                       shrink[sel], offsets.excess)
                out[sel] = np.sqrt(np.where(var0 > 0, var / np.where(var0 > 0, var0, 1.0), 1.0))
    return out


def set_refinement(plan: RunPlan, max_frames: int | None = None) -> None:
    """Switch a plan to the refined reference (checked; recorded in ``plan.options``)."""
    check_refinable(plan)
    count = DEFAULT_MAX_FRAMES if max_frames is None else max_frames
    if not isinstance(count, (int, np.integer)) or count < 5:
        raise ValueError(f"refine_frames: must be an integer >= 5, got {max_frames!r}")
    plan.options["refine_reference"] = int(count)
