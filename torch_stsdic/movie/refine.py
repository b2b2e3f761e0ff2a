"""The template's zero displacement from the trajectories (``refine_reference=True``): a
setting of the reference made from the series (:mod:`~torch_stsdic.movie.series_reference`).

Measured against the template, a point's classical displacement at every frame carries one
and the same error: the template's registration (the local fits that mapped the sampled
frames back to the reference frame carry that frame's noise, smoothed over the fit's
neighbourhood) less the gauge the reference frame read for it. The window cannot remove a
constant; the truth is 0 at the reference time, so the constant is what a *fit over many
frames* of the point's own trajectory says at the reference time.

:func:`measure_trajectory_gauge` measures up to ``max_frames`` frames around the reference
classically against the template (the reference itself left out: its measurement is the
gauge), subtracts the template's gauge, and per point fits polynomials in time over nested
windows (:func:`fit_intercepts`): the fit with the smallest predicted intercept variance
among those whose next-higher term is not significant (|t| below Student's t quantile of the
normal's 3 at the degrees of freedom of the noise, which comes from the trajectory's own
third differences). The intercepts are shrunk towards 0 by ``rho / (rho + d)`` (``d``: the
fit's intercept variance in units of the per-frame variance; ``rho``: var(offset) /
var(per-frame error), estimated over all points, capped by what the images' noise and the
template's registration allow, :func:`images_rho`): the least-squares estimate of the
offset given its spread. The template's gauge plus these intercepts are subtracted from
every row (:func:`apply_offsets`); the reference frame's own row is set to the truth.

Where it pays: a long movie whose motion is smooth near the reference (41 frames, linear:
0.27x classical DIC against the template's 0.37x); where the trajectory is short (11
frames) the intercepts are noisier than the registration they correct (DIC Challenge sample
3: 0.29x against 0.25x), and where the motion decelerates next to the reference the shrink
leaves it as the template had it (docs/validation/reference_mechanism.md). The predicted
u_std, v_std stay the template's (they count the registration in full: high by up to the
share removed).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import USABLE, TrackResult
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.classical_pass import classical_subplan
from torch_stsdic.movie.plan import RunPlan
from torch_stsdic.movie.template_noise import REGISTRATION_GAIN

__all__ = ["ReferenceOffsets", "check_refinable", "fit_frames", "measure_trajectory_gauge",
           "fit_intercepts", "images_rho", "apply_offsets", "restore_offsets", "set_refinement",
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
            window half-width (set by :func:`measure_trajectory_gauge`).
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


def measure_trajectory_gauge(plan: RunPlan, template: Any,
                             max_frames: int = DEFAULT_MAX_FRAMES,
                             shared: SharedMotion | None = None, *,
                             run: Callable[..., TrackResult]) -> ReferenceOffsets:
    """The template's gauge from the trajectories: classical DIC of the frames around the
    reference against the ``template``'s image (a :class:`~torch_stsdic.movie.
    series_reference.SeriesReference`), its gauge subtracted, then
    :func:`fit_intercepts`; returned with the gauge added back (what every row has
    subtracted in its place). The images' cap on the offsets' spread (:func:`images_rho`)
    counts the template's registration noise beside the solver's predicted variance and the
    template's ``added_var``: ``REGISTRATION_GAIN`` times its fits' variance factor, in units
    of the reference frame's noise variance (the frames were registered to it;
    :func:`_reference_noise_ratio`).

    With the specimen's ``shared`` motion (:mod:`torch_stsdic.core.shared_motion`) the fits
    are of each trajectory *minus* it (zero at the reference: the same offsets)."""
    check_refinable(plan)
    if int(max_frames) < 5:
        raise ValueError(f"refine_frames: must be >= 5, got {max_frames!r}")
    t0 = time.perf_counter()
    # the reference's own measurement is the gauge: left out of the fit (and any frame
    # stamped with the reference's time, which fit_intercepts drops too)
    t_ref = plan.times[plan.reference_frame]
    frames = [k for k in fit_frames(plan, max_frames)
              if k != plan.reference_frame and plan.times[k] != t_ref]
    sub = dataclasses.replace(classical_subplan(plan, frames), reference_image=template.image,
                              reference_frame=-1, reference_desc="array:series-template")
    res = run(sub, progress=False)
    vals = {"u": res.u, "v": res.v, **res.gradients}
    ys = {k: np.asarray(v.detach().cpu().numpy(), dtype=np.float64) for k, v in vals.items()}
    usable = (res.status <= USABLE).cpu().numpy()
    base = {} if template.gauge is None else template.gauge.values
    for k in ys:
        ys[k] = np.where(usable, ys[k] - base.get(k, 0.0), np.nan)
    if shared is not None:
        _remove_shared(ys, shared, plan, frames)
    t = plan.times[frames] - plan.times[plan.reference_frame]
    added = (0.0 if template.added_var is None
             else template.added_var.double().cpu().numpy()[None])
    gain = (0.0 if template.registration is None else REGISTRATION_GAIN
            * template.registration.double().cpu().numpy()[None]
            * _reference_noise_ratio(template, plan.reference_frame)
            / (1 + template.noise_ratio))
    pred = {k: np.where(usable, np.asarray(res.std[k].detach().cpu().numpy(), np.float64) ** 2
                        * (1 + gain) + added, np.nan) for k in ("u", "v") if k in res.std}
    rho_img = images_rho(t, ys, pred) if len(pred) == 2 else float("nan")
    out = fit_intercepts(t, ys, min_frames=max(5, plan.config.n_frames), rho_images=rho_img)
    out.values = {k: v + base.get(k, 0.0) for k, v in out.values.items()}
    out.seconds = time.perf_counter() - t0
    out.reference_frame = int(plan.reference_frame)
    out.fit = np.asarray(frames, dtype=np.int64)
    out.times = np.asarray(plan.times, dtype=np.float64)
    out.m = int(plan.config.m)
    return out


def _reference_noise_ratio(template: Any, reference_frame: int) -> float:
    """The reference frame's image noise variance over the template's other frames' (their
    median), from the template's weights: each frame entered a POI with the inverse of its
    noise variance (``template.shares``); the median over the POIs where the reference frame
    and another frame entered. 1 where the template does not say."""
    shares, frames = template.shares, list(template.frames)
    if shares is None or reference_frame not in frames or len(frames) < 2:
        return 1.0
    i = frames.index(reference_frame)
    own = shares[i].double()
    rest = torch.cat([shares[:i], shares[i + 1:]]).double()
    rest = torch.where(rest > 0, rest, torch.nan).nanmedian(0).values  # (N,) entered only
    ratio = rest / torch.where(own > 0, own, torch.nan)
    ratio = ratio[torch.isfinite(ratio)]
    return float(ratio.median()) if ratio.numel() else 1.0


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


def apply_offsets(rows: dict[str, Any], offsets: ReferenceOffsets,
                  frames: Sequence[int] | None = None) -> dict[str, Any]:
    """Rows (name -> (B, N) numpy arrays, or tensors: the same numbers where they are) with
    the offsets subtracted (names without an offset, and the velocities, unchanged). With
    ``frames`` (B,) (the rows' series frames), the reference frame's row reports the truth
    where it was solved (status usable): displacement and gradients 0, and so their
    predicted std (u_std, v_std); the velocity stays as measured."""
    out = _shifted(rows, offsets, -1.0)
    if frames is None:
        return out
    frames = [int(f) for f in frames]
    if offsets.reference_frame not in frames:
        return out
    i = frames.index(offsets.reference_frame)
    first = next(iter(out.values()))
    ok = out["status"][i] <= USABLE if "status" in out else (
        torch.ones(first.shape[1], dtype=torch.bool, device=first.device)
        if isinstance(first, torch.Tensor) else np.ones(first.shape[1], dtype=bool))
    for k in [*offsets.values, "u_std", "v_std"]:
        if k in out and k not in _RATES:
            out[k] = out[k].clone() if isinstance(out[k], torch.Tensor) else out[k].copy()
            out[k][i] = (torch.where if isinstance(ok, torch.Tensor) else np.where)(
                ok, 0.0, out[k][i])
    return out


def restore_offsets(rows: dict[str, Any], offsets: ReferenceOffsets) -> dict[str, Any]:
    """Stored rows (name -> (B, N) numpy arrays or tensors) with the offsets added back
    (names without an offset, and the velocities, unchanged): the quantities the blocks'
    solves measure against their reference (the next block's carried guess starts there,
    not the stored rows' offset away)."""
    return _shifted(rows, offsets, 1.0)


def _shifted(rows: dict[str, Any], offsets: ReferenceOffsets, sign: float) -> dict[str, Any]:
    """Rows with ``sign`` times the offsets added (names without an offset, and the
    velocities, unchanged); a tensor's on its device, in float64 as numpy's would be."""
    out = dict(rows)
    for k, off in offsets.values.items():
        if k in out and k not in _RATES:
            a = out[k]
            if isinstance(a, torch.Tensor):
                out[k] = a + sign * _offset_on(offsets, k, a.device)[None, :]
            else:
                out[k] = a + sign * off[None, :]
    return out


def _offset_on(offsets: ReferenceOffsets, name: str, device: torch.device) -> torch.Tensor:
    """(N,) float64 the offset ``name`` on ``device``, copied there once a run (kept on the
    object, not among its recorded fields)."""
    held = offsets.__dict__.setdefault("_on_device", {})
    key = (name, str(device))
    if key not in held:
        held[key] = torch.from_numpy(np.asarray(offsets.values[name], dtype=np.float64)).to(
            device)
    return held[key]


def set_refinement(plan: RunPlan, max_frames: int | None = None) -> None:
    """Ask ``plan`` for the template's gauge from the trajectories (checked; recorded in
    ``plan.options["refine_reference"]``: the most frames of the fits). The template itself
    is set by :func:`~torch_stsdic.movie.series_reference.set_series_reference`."""
    check_refinable(plan)
    count = DEFAULT_MAX_FRAMES if max_frames is None else max_frames
    if not isinstance(count, (int, np.integer)) or count < 5:
        raise ValueError(f"refine_frames: must be an integer >= 5, got {max_frames!r}")
    plan.options["refine_reference"] = int(count)
