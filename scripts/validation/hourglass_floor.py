"""What holds the muDIC hourglass's predicted error (issue 47, item 3): the windows chosen,
the template's noise, or its registration?

Measures the run-level estimates of ``stsdic run ../shared/data/mudic-hourglass --roi 150 20
1120 734 --subset 31 --step 20`` (no ``--m``: the windows chosen from the data, m <= 6; the
template made from the series) without the main pass, and evaluates per point and target
frame the predicted variance of the displacement in units of one image's share ``s^2``
(:func:`~torch_stsdic.core.uncertainty.shared_frame_factors`, "Predicted error" of
docs/validation/window_length.md):

    sum a^2 + sum c^2 - 2 sum a c  +  phi' (1 - 2 c_0 - sum a^2 + 2 sum a c)
    (template noise, window noise, shared)   (registration to the reference frame)

(``a`` the template's weights of the frames at the point, ``c`` the window's line weights at
the target, ``phi' = REGISTRATION_GAIN phi`` the registration's variance factor), against
classical DIC with the single reference image, ``2 s^2`` (reference and frame equally noisy).
Reported: the median over the targets 1.. and points of the square root of that ratio (the
run's predicted error over classical DIC's, as ``real_summary.py`` takes medians), with the
windows chosen, with every window at its longest (m = 6 where the movie allows), without the
registration term, and with a template of equal weights over all frames; and how many
frames entered the template at each POI.

    python scripts/validation/hourglass_floor.py [--data ../shared/data]
        [--neighbours 25] [--plane-z 5]

``--neighbours``, ``--plane-z``: the template's smallest local fits made over that many POIs
(the larger ones of ``NEIGHBOURHOODS`` beyond it), and the z limit of their tests (the
library's ``DEFAULT_NEIGHBOURS``, ``PLANE_Z``), for a study of what lets more frames into the
template; the library is not changed.
"""

from __future__ import annotations

import argparse
import functools
import sys
import warnings
from pathlib import Path

import torch

import torch_stsdic as sts
from torch_stsdic.core.uncertainty import intercept_weights
from torch_stsdic.io.images import load_series
from torch_stsdic.movie import estimates, series_reference
from torch_stsdic.movie.estimates import measure_run
from torch_stsdic.movie.frames import window_frames
from torch_stsdic.movie.plan import plan_run
from torch_stsdic.movie.series import run_plan, set_reference_mode, set_window_length
from torch_stsdic.movie.template_noise import REGISTRATION_GAIN, TemplateShares

ROOT = Path(__file__).resolve().parents[2]


def bracket(shares: TemplateShares, ks: torch.Tensor, m_used: torch.Tensor, n_series: int,
            registration: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """(B, N) each term of the predicted variance (units of s^2) of targets ``ks`` (B,) at
    half-widths ``m_used`` (B, N) (frame units: times = frame indices)."""
    b, n = m_used.shape
    out = {k: torch.zeros(b, n, dtype=torch.float64) for k in ("template", "window", "shared",
                                                                 "registration")}
    for m in torch.unique(m_used).tolist():
        win = window_frames(ks, int(m), n_series)  # (B, T)
        bi, ni = torch.nonzero(m_used == m, as_tuple=True)
        dt = (win - ks[:, None]).double()[bi]
        c = intercept_weights(dt)  # (R, T)
        a = shares.of(win)[bi, ni]  # (R, T)
        asq = shares.share_sq[ni]
        ac = (a * c).sum(1)
        out["template"][bi, ni] = asq
        out["window"][bi, ni] = (c * c).sum(1)
        out["shared"][bi, ni] = -2 * ac
        if registration is not None:
            c0 = (c * (win[bi] == shares.reference_frame).double()).sum(1)
            out["registration"][bi, ni] = (REGISTRATION_GAIN * registration[ni]
                                           * (1 - 2 * c0 - asq + 2 * ac))
    return out


def diagnose(plan) -> None:
    """Per sampled frame, which of the template's fit tests keeps it out at the POIs: the
    plane's value against the quadratic's, the plane's largest residual, and the same of the
    quadratic against the cubic (z against the noise the solver predicts; shares of the POIs
    above ``PLANE_Z``), and the median residual z (~1 where the noise is what the solver
    says and the fit describes the field)."""
    from torch_stsdic.analysis.local_fit import local_fit_weights
    from torch_stsdic.movie.series_reference import (
        _all_warps,
        _matched,
        _unit_variance,
        measure_classical,
        sample_frames,
    )

    frames = sample_frames(plan)
    res = measure_classical(plan, frames, run_plan)
    warps, trusted = _all_warps(plan, res)
    ok = trusted & _matched(res, frames, plan.reference_frame)
    unit = _unit_variance(res)
    fit = local_fit_weights(plan.points.double().cpu(), series_reference.DEFAULT_NEIGHBOURS,
                            plan.config.subset_size, degrees=(1, 2, 3))
    lim = series_reference.PLANE_Z
    print(f"\n| frame | trusted | plane: value z > {lim:g} | plane: residual z > {lim:g} | "
          f"quadratic: value z > {lim:g} | quadratic: residual z > {lim:g} | median plane "
          "residual z |\n|---:|---:|---:|---:|---:|---:|---:|")
    for j, k in enumerate(frames):
        vals = torch.where(ok[j][:, None], warps[j][:, [0, 3]], 0.0).T  # (2, N)
        var = (2.0 * unit).expand(2, -1)
        good = ok[j][fit.index].all(-1) & fit.posed[1] & fit.posed[2]
        row = [f"{float(good.double().mean()):.2f}"]
        for d in (1, 2):
            diff = fit.apply(d, vals) - fit.apply(d + 1, vals)
            var_d = fit.variance_factor(fit.weights[d] - fit.weights[d + 1]).clamp(min=1e-12)
            z = (diff.abs() / (var_d * var[:, fit.index].mean(-1)).sqrt()).amax(0)
            rz = fit.residual_z(d, vals, var).amax(0)
            row += [f"{float((z[good] > lim).double().mean()):.2f}",
                    f"{float((rz[good] > lim).double().mean()):.2f}"]
            if d == 1:
                med = float(rz[good].median()) if bool(good.any()) else float("nan")
        print(f"| {k} | " + " | ".join(row) + f" | {med:.1f} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--neighbours", type=int, default=series_reference.DEFAULT_NEIGHBOURS)
    ap.add_argument("--plane-z", type=float, default=series_reference.PLANE_Z)
    ap.add_argument("--diagnose", action="store_true",
                    help="only which fit test keeps each sampled frame out (no estimates)")
    args = ap.parse_args(argv)
    series_reference.PLANE_Z = args.plane_z
    estimates.build_series_reference = functools.partial(
        series_reference.build_series_reference, neighbours=args.neighbours)
    folder = args.data / "mudic-hourglass"
    if not folder.is_dir():
        print(f"skipped: {folder} not found")
        return 0
    series = load_series(str(folder))
    plan = plan_run(series, 0, None, None, (150, 20, 1120, 734), None, 20,
                    sts.DICConfig(subset_size=31, m=6))
    set_reference_mode(plan, False, None, "auto", None)
    set_window_length(plan, "auto")
    if args.diagnose:
        diagnose(plan)
        return 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = measure_run(plan, run=run_plan)
    ref = est.series_reference
    n_series = len(plan.series)
    shares = TemplateShares.make(ref.frames, ref.shares, n_series, plan.reference_frame,
                                 ref.registration)
    ks = torch.arange(1, n_series)
    chosen = est.window_m[1:].long()
    longest = torch.full_like(chosen, min(6, (n_series - 1) // 2))
    flat = TemplateShares.make(list(range(n_series)),
                               torch.full((n_series, plan.n_points), 1.0 / n_series),
                               n_series, plan.reference_frame, ref.registration)
    cases = {"windows chosen": (shares, chosen, ref.registration),
             "every window m = 6": (shares, longest, ref.registration),
             "windows chosen, no registration": (shares, chosen, None),
             "m = 6, no registration": (shares, longest, None),
             f"windows chosen, template of all {n_series} frames": (flat, chosen,
                                                                     ref.registration)}
    print(f"{plan.n_points} points, {n_series} frames; template: {len(ref.frames)} frames, "
          f"noise ratio {ref.noise_ratio:.3f}; median sum a^2 "
          f"{float(shares.share_sq.median()):.3f}; median phi' "
          f"{float(REGISTRATION_GAIN * ref.registration.median()):.3f}; chosen m shares: "
          + " ".join(f"{k}:{float((chosen == k).double().mean()):.2f}" for k in range(7)))
    entered = (ref.shares > 0).sum(0).double()  # frames entering the template at each POI
    print(f"frames entering the template at a POI: median {float(entered.median()):.0f} of "
          f"{len(ref.frames)}, effective (1 / sum a^2) median "
          f"{float((1 / shares.share_sq).median()):.1f}; registered by a plane / a fit: "
          f"{ref.plane_share:.2f} / {ref.fit_share:.2f} of the frames x POIs; coverage "
          f"{ref.coverage:.2f}")
    print("\n| case | predicted / classical (median) | template | window | shared | "
          "registration |\n|---|---:|---:|---:|---:|---:|")
    for name, (sh, mu, reg) in cases.items():
        terms = bracket(sh, ks, mu, n_series, reg)
        total = sum(terms.values()).clamp(min=0)
        ratio = float((total / 2).sqrt().median())
        print(f"| {name} | {ratio:.3f} | "
              + " | ".join(f"{float(v.median()):.3f}" for v in terms.values()) + " |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
