"""The summary ``stsdic run`` prints at the end of a run: points, frames, statuses, windows,
the shared motion, the reference (template, refinement), the time model, time and
throughput."""

from __future__ import annotations

import argparse
from typing import Any

from torch_stsdic.cli.common import fmt_time, to_numpy
from torch_stsdic.core.shared_motion import carried_note


def shared_motion_lines(rec: dict[str, Any] | None) -> list[str]:
    """The summary's lines on the shared motion (``TrackResult.info["shared_motion"]``)."""
    if not rec:
        return []
    shake = (f"shake median {rec['jitter_px_median']:.3f} px, max {rec['jitter_px_max']:.3f} px"
             if rec.get("jitter_px_median") is not None else "shake not measured")
    how = carried_note(bool(rec.get("applied")), *map(rec.get, ("velocity_m", "smoothed_frames",
                                                               "jumps")))
    if rec.get("refused"):
        how = (f"REFUSED, not carried: {rec['refused']}; the points may include background "
               "or a second body (choose them with --roi/--mask)")
    lines = [f"shared motion: {rec['kind']}, {how} ({shake})"]
    steps = rec.get("steps") or []
    if steps:
        which = f"frame{'s' if len(steps) > 1 else ''} {', '.join(map(str, steps))}"
        lines.append(f"load steps before {which}: windows stay inside each load state")
    return lines


def _status_summary(counts: dict[str, int]) -> dict[str, float]:
    """Percent of the (frame, point) results with each status, by lower-case status name
    (``counts``: results by status code, as in ``info["row_counts"]["status"]``)."""
    from torch_stsdic.core.status import Status

    total = max(1, sum(counts.values()))
    return {st.name.lower(): 100.0 * counts.get(str(int(st)), 0) / total for st in Status}


def _pct(share: float) -> str:
    """A percentage with one decimal, never '-0.0' (a difference rounding below zero)."""
    return f"{max(0.0, share):.1f}"


def print_summary(res: Any, args: argparse.Namespace, elapsed: float, ref: str,
                   kept: int = 0) -> None:
    """Points, frames, status percentages, time and throughput of a finished run; ``ref``:
    the reference's file (and page), or how it was made; ``kept``: frames a ``--resume``
    found finished (the throughput counts only the frames solved now)."""
    import torch

    from torch_stsdic.kernels import dispatch
    from torch_stsdic.movie.sinks import row_counts

    counts = res.info.get("row_counts")  # the run's own count: no (F, N) field read
    if counts is None:  # counted from the result's fields
        status = to_numpy(res.status)
        n_f, n_p = status.shape
        counts = row_counts(status, None if res.m is None else to_numpy(res.m))
    else:
        n_f, n_p = res.n_frames, res.n_points
    st = _status_summary(counts["status"])
    bad = sum(v for k, v in st.items() if k not in ("converged", "max_iter"))
    m_text = (f"<= {args.m} (chosen)" if getattr(args, "window_length", "fixed") == "auto"
              else str(args.m))
    print(f"points: {n_p}   frames: {n_f}   reference: {args.reference} ({ref})   m: {m_text}")
    print(
        f"converged: {_pct(st['converged'])} %   max-iter: {_pct(st['max_iter'])} %   "
        f"not trusted: {_pct(bad)} % "
        f"(diverged {_pct(st['diverged'])}, outside {_pct(st['outside'])}, "
        f"low texture {_pct(st['low_texture'])}, not computed {_pct(st['not_computed'])}, "
        f"poor fit {_pct(st['poor_fit'])}, inconsistent {_pct(st['inconsistent'])})"
    )
    m_ok = {int(k): c for k, c in counts["m_usable"].items()}
    usable = sum(m_ok.values())
    if args.m and usable and getattr(args, "window_length", "fixed") == "auto":
        share = ", ".join(f"{m}: {_pct(100.0 * m_ok.get(m, 0) / usable)} %"
                          for m in range(args.m, -1, -1))
        print(f"window: chosen per point and frame up to m = {args.m}, of the trusted "
              f"results at m = {share} (shorter where the measured motion is not affine "
              "in time over a longer window; classical at m = 0: no velocity there)")
    elif args.m and usable:
        print(f"window: m = {args.m} at {_pct(100.0 * m_ok.get(args.m, 0) / usable)} % of the "
              f"trusted results, shorter where the motion is not affine in time or the "
              f"point leaves the image within the window (classical at "
              f"{_pct(100.0 * m_ok.get(0, 0) / usable)} %: no velocity there, ut and vt are "
              "NaN)")
    off = int(res.info.get("off_centre_rows", 0) or 0)
    if off:
        print(f"border: {_pct(100.0 * off / max(1, n_f * n_p))} % of the point-frames solved "
              "with the subset moved inside the image (the point near the border; its result "
              "carried by the subset's gradients, u_std and v_std with it)")
    for line in shared_motion_lines(res.info.get("shared_motion")):
        print(line)
    spec = res.info.get("specimen")
    if spec and spec.get("left_out"):
        print(f"specimen: {spec['left_out']} of {spec['points']} grid points left out, their "
              "subsets not on speckle (background, holes, featureless or saturated areas; "
              "--keep-background keeps them)")
    sref = res.info.get("series_reference")
    single = res.info.get("single_reference")
    if single and not sref:
        print(f"reference: the reference image alone ({single}"
              + ("; --series-reference is off" if single == "asked for" else
                 "; the reference made from the series does not apply") + ")")
    from torch_stsdic.movie.estimates import FROM_FILE

    source = res.info.get("run_estimates")  # set on resumed runs only
    from_file = source == FROM_FILE
    if sref:
        added = sref.get("added_std_px")
        made = (f"{FROM_FILE}, made in {sref['seconds']:.1f} s" if from_file
                else f"{sref['seconds']:.1f} s")
        print(f"reference: a template of {len(sref['frames'])} frames, {sref['iterations']} "
              f"round(s) ({made}); its noise {sref['noise_ratio']:.3f} of a "
              "frame's" + (f", its registration +{added:.4f} px in u_std and v_std"
                           if added else ""))
    refined = res.info.get("refine_reference")
    if refined:
        print(_refined_line(refined))

    classical = (sref or {}).get("classical_points") or (
        res.info.get("time_model") or {}).get("classical_points")
    if classical:
        where = "the template's frames" if sref else "the sampled frames"
        print(f"time model: {classical} of {n_p} points solved classically (in {where} their "
              "windows missed a line, or bent it by more than the window saves: no velocity "
              "there)")
    solved = n_f - kept
    if args.resume:
        print(f"resumed: {kept} of {n_f} frames were finished in the file and kept, "
              f"{solved} solved now" + (f"; the run's estimates {source}" if source else ""))
    device = args.device
    on_cpu = str(device).startswith("cpu")
    kernels = dispatch.describe("cpu" if on_cpu else "cuda")
    threads = f", {torch.get_num_threads()} threads" if on_cpu else ""
    rate = (f"{solved * n_p / max(elapsed, 1e-9):.0f} POI/s" + (" (frames solved now)"
            if kept else "")) if solved else "no frame left to solve"
    print(f"time: {fmt_time(elapsed)} (strains included)   {rate}   ({device}, {kernels}"
          f"{threads})")


def _refined_line(rr: dict) -> str:
    """The summary line of ``--refine-reference`` (``info["refine_reference"]``): where the
    template's zero was refined, over how many frames, and how much of the fits was kept."""
    rho, cap = rr.get("rho"), rr.get("rho_images")
    why = ""
    if rho is not None and cap is not None:
        why = (f": the offsets' variance the images allow is {cap:.3g}x a frame's error, "
               f"the fits' {rho:.3g}x")
    return (f"refined reference: the template's zero from the trajectories at {rr['refined']} "
            f"of {rr['points']} points (fits over {rr['frames_median']:.0f} frames, median), "
            f"each kept at {rr['shrink']:.3g} of its fit{why} ({rr['seconds']:.1f} s)")
