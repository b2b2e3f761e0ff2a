"""The paper's simulated experiment as one function: classical DIC vs STS-DIC.

A speckle movie (reference + N frames) translates by u = t/20 px, with Gaussian noise on
every image. It is measured with classical DIC (m = 0) and with STS-DIC (2m+1 frames per
solve), both against the reference image, which is given apart so that no STS window
contains it. Optionally both runs are repeated with a reference averaged from K noisy still
frames. :func:`run_demo` returns the RMS errors against the exact motion, the run times and
throughputs (:class:`DemoResult`), and writes figures and ``demo.json`` when given a folder.

Units: px for u, v and their errors; px per frame for ut; seconds for times.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["UT_TRUE", "DemoResult", "DemoSettings", "MethodResult", "check_settings", "run_demo"]

#: the velocity of the demo's translation, px per frame (u = t/20 px)
UT_TRUE = 1.0 / 20.0
#: the files :func:`run_demo` writes into its folder
FILES = ("error_per_frame.png", "fields.png", "history.png", "demo.json")


@dataclass(frozen=True)
class DemoSettings:
    """One demo's settings (every size in px, noise in 8-bit grey levels)."""

    size: int = 301  #: image width = height, px
    frames: int = 9  #: deformed frames after the reference (t = 1..frames)
    noise: float = 5.0  #: Gaussian noise std on every image, grey levels
    m: int = 2  #: STS-DIC half window (2m+1 frames per solve)
    subset: int = 21  #: subset width, px (odd)
    step: int = 20  #: grid spacing of the points, px
    formulation: str = "auto"  #: STS-DIC formulation (see DICConfig)
    still_frames: int = 8  #: K: also run with the reference = mean of K stills (0: skip)
    refined: bool = True  #: also run STS-DIC with the refined reference (docs/accuracy.md)
    seed: int = 0  #: speckle and noise seed
    device: str = "cpu"  #: torch device

    @classmethod
    def create(cls, quick: bool = False, **changes: Any) -> DemoSettings:
        """The defaults, or with ``quick`` a small and fast demo (101 px, 7 frames, step 25 px,
        no still frames, no refined reference), with ``changes``; a change of None keeps the
        default."""
        base = ({"size": 101, "frames": 7, "step": 25, "still_frames": 0, "refined": False}
                if quick else {})
        return cls(**{**base, **{k: v for k, v in changes.items() if v is not None}})


def check_settings(s: DemoSettings, name: Callable[[str], str] = str) -> None:
    """ValueError if the settings cannot make a demo; ``name`` turns a field into its label."""
    if s.m < 1:
        raise ValueError(f"{name('m')} {s.m}: the STS-DIC half window must be >= 1")
    if s.frames < 2 * s.m + 1:
        raise ValueError(
            f"{name('frames')} {s.frames}: STS-DIC with {name('m')} {s.m} needs at least "
            f"{2 * s.m + 1} frames"
        )
    if s.subset > s.size:
        raise ValueError(f"{name('subset')} {s.subset} is larger than the image ({s.size} px)")
    if _grid(s).size == 0:
        raise ValueError(f"{name('size')} {s.size} is too small for {name('subset')} {s.subset}")


@dataclass
class MethodResult:
    """The errors of one method against the exact motion (px, px per frame) and its speed."""

    method: str  #: label, e.g. "STS-DIC" or "classical DIC, ref=mean of 8"
    m: int  #: half window (0: classical DIC)
    rms_u: float  #: RMS error of u over every valid (frame, point), px
    rms_v: float  #: RMS error of v, px
    rms_ut: float  #: RMS error of the velocity ut, px per frame
    ut_from_finite_differences: bool  #: ut from finite differences of u (classical DIC)
    bias_u: float  #: mean error of u, px
    std_u: float  #: standard deviation of the error of u, px
    valid_percent: float  #: converged (or max-iter) results, %
    time_s: float  #: tracking time, s
    poi_per_s: float  #: (frame, point) results per second
    rms_u_per_frame: list[float]  #: RMS error of u in each frame, px
    mean_u_per_frame: list[float]  #: mean u over the points in each frame, px
    u: np.ndarray = field(repr=False)  #: (F, N) measured u, px (NaN: failed)
    error_u: np.ndarray = field(repr=False)  #: (F, N) u minus the exact u, px
    #: (F, N) ut minus the exact ut, px per frame (finite differences for classical DIC)
    error_ut: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))

    def summary(self) -> dict[str, Any]:
        """The numbers (no arrays), as in ``demo.json``."""
        arrays = ("u", "error_u", "error_ut")
        return {k: v for k, v in asdict(self).items() if k not in arrays}


@dataclass
class DemoResult:
    """Everything :func:`run_demo` measured, and the files it wrote."""

    settings: DemoSettings
    points: np.ndarray  #: (N, 2) points x, y, px
    times: np.ndarray  #: (F,) frame times, frames
    u_true: np.ndarray  #: (F, N) exact u, px
    v_true: np.ndarray  #: (F, N) exact v, px
    methods: list[MethodResult]  #: classical, STS-DIC[, both with the averaged reference]
    synth_time_s: float  #: time to render the movie, s
    motion: str  #: the motion's repr
    files: list[Path] = field(default_factory=list)  #: figures and demo.json written

    @property
    def classical(self) -> MethodResult:
        return self.methods[0]

    @property
    def sts(self) -> MethodResult:
        return self.methods[1]

    def ratios(self, a: int = 0, b: int = 1) -> dict[str, float]:
        """RMS error of method ``a`` over that of method ``b`` (default classical DIC over
        STS-DIC), for u, v and ut (> 1: ``b`` wins)."""
        c, s = self.methods[a], self.methods[b]
        return {k: _ratio(getattr(c, f"rms_{k}"), getattr(s, f"rms_{k}")) for k in ("u", "v", "ut")}

    def header(self) -> str:
        """One line: the movie and the points."""
        s = self.settings
        return (
            f"STS-DIC demo: {s.size}x{s.size} px speckle, reference + {s.frames} frames, "
            f"u = t/20 px, noise sigma {s.noise:g} grey levels, subset {s.subset}, "
            f"{len(self.points)} points "
            f"(synthesised in {self.synth_time_s:.1f} s)"
        )

    def table(self) -> str:
        """The errors, times and ratios as a text table, with its notes."""
        return _table(self)

    def to_json(self) -> dict[str, Any]:
        """The contents of ``demo.json``: settings, every number, the ratios."""
        s = self.settings
        settings = {
            "size": s.size, "frames": s.frames, "noise_sigma": s.noise, "m": s.m,
            "subset": s.subset, "step": s.step, "points": len(self.points),
            "formulation": s.formulation, "still_frames": s.still_frames, "seed": s.seed,
            "device": s.device, "motion": self.motion,
        }  # fmt: skip
        return {
            "settings": settings,
            "results": [r.summary() for r in self.methods],
            "ratio_classical_over_sts": self.ratios(),
        }


# ----------------------------------------------------------------------------------------
# the experiment
# ----------------------------------------------------------------------------------------


def run_demo(
    out_dir: str | Path | None = None,
    *,
    quick: bool = False,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
    **changes: Any,
) -> DemoResult:
    """Measure the demo movie with classical DIC and STS-DIC; errors against the exact motion.

    Args:
        out_dir: folder for ``error_per_frame.png``, ``fields.png``, ``history.png`` and
            ``demo.json`` (created); None writes nothing.
        quick: a small movie with few points and no still frames (about a second).
        progress: tqdm progress bars (on stderr) while tracking.
        log: called with :meth:`DemoResult.header` once the movie is made.
        **changes: any :class:`DemoSettings` field, e.g. ``noise=10.0, m=3`` (default: the
            paper's experiment).

    Returns:
        :class:`DemoResult`; ``result.table()`` is the text the ``stsdic demo`` command prints.

    Raises:
        ValueError: settings that cannot make a demo (see :func:`check_settings`).
    """
    import torch

    from torch_stsdic import synth
    from torch_stsdic.io import load_series

    s = DemoSettings.create(quick, **changes)
    check_settings(s)
    t0 = time.perf_counter()
    motion = synth.Translation(ut=UT_TRUE)
    movie = synth.synthetic_movie((s.size, s.size), s.frames, motion, noise_sigma=s.noise,
                                  seed=s.seed)  # fmt: skip
    times = np.arange(1, s.frames + 1, dtype=np.float64)
    # the deformed frames only: the reference image is given apart, so that no STS window
    # contains the reference itself (whose noise would match exactly)
    series = load_series(movie.frames.float(), timestamps=times)
    references = [("", movie.ref.float())]
    if s.still_frames:
        clean = synth.synthetic_movie((s.size, s.size), 1, motion, seed=s.seed).ref
        stills = torch.stack([
            synth.add_noise(clean, s.noise, seed=10_000 + s.seed * 100 + k)
            for k in range(s.still_frames)
        ])  # fmt: skip
        references.append((f", ref=mean of {s.still_frames}", stills.mean(0).float()))
    gx, gy = np.meshgrid(_grid(s), _grid(s))
    pts = np.stack([gx.ravel(), gy.ravel()], 1)
    truth = synth.ground_truth(motion, pts, times)
    result = DemoResult(s, pts, times, _np(truth["u"]), _np(truth["v"]), [],
                        time.perf_counter() - t0, repr(motion))  # fmt: skip
    if log is not None:
        log(result.header())
    for tag, reference in references:
        for name, m in (("classical DIC", 0), ("STS-DIC", s.m)):
            result.methods.append(
                _measure(f"{name}{tag}", m, series, reference, result, progress=progress)
            )
    with_ref = load_series(torch.cat([movie.ref[None], movie.frames]).float(),
                           timestamps=np.arange(s.frames + 1, dtype=np.float64))
    if s.refined and s.frames + 1 >= 5:  # the reference as series frame 0, offset fitted away
        result.methods.append(_measure("STS-DIC, refined ref", s.m, with_ref, 0, result,
                                       progress=progress, refine=True))
    if len(pts) >= 25:  # the reference as series frame 0, the template made from the series
        result.methods.append(_measure("STS-DIC, series ref", s.m, with_ref, 0, result,
                                       progress=progress, series_ref=True))
    if out_dir is not None:
        result.files = _write_files(result, _np(movie.ref), Path(out_dir))
    return result


def _grid(s: DemoSettings) -> np.ndarray:
    """Grid coordinates along x (and y), px: every ``step``, centred, clear of the border."""
    margin = s.subset // 2 + 3
    xs = np.arange(margin, s.size - margin, s.step, dtype=np.float64)
    if xs.size == 0:
        return xs
    return xs + np.floor(((s.size - 1 - margin) - xs[-1]) / 2.0)


def _measure(
    label: str, m: int, series: Any, reference: Any, demo: DemoResult, *, progress: bool,
    refine: bool = False, series_ref: bool = False,
) -> MethodResult:
    """Track the movie with half window ``m`` against ``reference``; errors and speed."""
    from torch_stsdic.core.config import DICConfig
    from torch_stsdic.core.status import Status
    from torch_stsdic.movie.series import track

    s = demo.settings
    cfg = DICConfig(subset_size=s.subset, m=m, formulation=s.formulation, search_radius=2)
    t1 = time.perf_counter()
    # with the reference as series frame 0 (refined, or the series reference) the targets
    # are frames 1..; the other rows measure against the reference image alone
    first = 1 if refine or series_ref else 0
    res = track(series, reference=reference, frames=list(range(first, first + s.frames)),
                points=demo.points, config=cfg, device=s.device, progress=progress,
                refine_reference=refine, series_reference=series_ref or refine)  # fmt: skip
    el = time.perf_counter() - t1
    ok = _np(res.status) <= int(Status.MAX_ITER)
    u, v, ut = (np.where(ok, _np(a).astype(np.float64), np.nan) for a in (res.u, res.v, res.ut))
    fd = m == 0 or not np.isfinite(ut).any()
    if fd and s.frames > 1:
        ut = np.gradient(u, demo.times, axis=0)
    eu = u - demo.u_true
    return MethodResult(
        method=label,
        m=m,
        rms_u=_rms(eu),
        rms_v=_rms(v - demo.v_true),
        rms_ut=_rms(ut - UT_TRUE),
        ut_from_finite_differences=fd,
        bias_u=float(np.nanmean(eu)),
        std_u=float(np.nanstd(eu)),
        valid_percent=100.0 * float(ok.mean()),
        time_s=el,
        poi_per_s=ok.size / max(el, 1e-9),
        rms_u_per_frame=[_rms(e) for e in eu],
        mean_u_per_frame=np.nanmean(u, axis=1).tolist(),
        u=u,
        error_u=eu,
        error_ut=ut - UT_TRUE,
    )


# ----------------------------------------------------------------------------------------
# output
# ----------------------------------------------------------------------------------------


def _table(d: DemoResult) -> str:
    """The text of ``stsdic demo``: errors, validity, time, POI/s, ratios, notes. The ratio
    lines put their u, v and ut ratios under the u, v and ut error columns."""
    rows = d.methods
    refined = [r for r in rows if r.method.endswith("refined ref")]
    templ = [r for r in rows if r.method.endswith("series ref")]
    base = [r for r in rows if r not in refined and r not in templ]
    ratio_rows = [("ratio classical / STS-DIC", d.ratios(0, 1))]
    if len(base) == 4:
        k = d.settings.still_frames
        ratio_rows += [(f"ratio, both with ref=mean of {k}", d.ratios(2, 3)),
                       (f"classical / STS-DIC ref=mean of {k}", d.ratios(0, 3))]  # fmt: skip
    width = max(16, *(len(r.method) + 1 for r in rows), *(len(lab) - 2 for lab, _ in ratio_rows))
    hdr = (
        f"{'method':<{width}}{'m':>3}{'RMS u err':>12}{'RMS v err':>12}{'RMS ut err':>13}"
        f"{'valid':>8}{'time':>9}{'POI/s':>9}"
    )
    units = (
        f"{'':<{width}}{'':>3}{'(px)':>12}{'(px)':>12}{'(px/frame)':>13}{'(%)':>8}{'(s)':>9}{'':>9}"
    )
    lines = ["", hdr, units, "-" * len(hdr)]
    for r in rows:
        star = "*" if r.ut_from_finite_differences else " "
        lines.append(
            f"{r.method:<{width}}{r.m:>3}{r.rms_u:>12.4f}{r.rms_v:>12.4f}{r.rms_ut:>12.4f}{star}"
            f"{r.valid_percent:>8.1f}{r.time_s:>9.2f}{r.poi_per_s:>9.0f}"
        )
    lines.append("-" * len(hdr))
    for lab, rat in ratio_rows:  # the x of each ratio where the column's last digit is
        lines.append(f"{lab:<{width + 3}}" + "".join(f"{rat[k]:>11.2f}x" for k in ("u", "v", "ut")))
    rows = base
    if len(rows) == 4:
        m = d.settings.m
        bound = 1.0 / math.sqrt((1 + 1 / (2 * m + 1)) / 2)
        lines.append(
            "STS-DIC averages the deformed frames' noise; the reference's noise is shared by "
            "every frame,\nso with one noisy reference the gain in u is bounded by "
            f"1 / sqrt((1 + 1/{2 * m + 1}) / 2) = {bound:.2f}x;\naveraging still frames into "
            "the reference lifts that bound."
        )
    if refined:
        lines.append(f"{'classical / STS-DIC refined ref':<{width + 3}}"
                     f"{_ratio(rows[0].rms_u, refined[0].rms_u):>11.2f}x")
        lines.append("The refined reference (the reference as frame 0 of the series, "
                     "refine_reference=True): the template\nmade from the series, its zero "
                     "displacement from the trajectory of every point.")
    if templ:
        lines.append(f"{'classical / STS-DIC series ref':<{width + 3}}"
                     f"{_ratio(rows[0].rms_u, templ[0].rms_u):>11.2f}x")
        lines.append("The series reference (the default of 'stsdic run' where the reference is "
                     "a frame of the series)\nmeasures every frame against a template averaged "
                     "from the series: no still frames needed.")
    if d.classical.ut_from_finite_differences:
        lines.append("* classical DIC measures no velocity: ut from finite differences of u")
    return "\n".join(lines)


def _write_files(d: DemoResult, ref_image: np.ndarray, out: Path) -> list[Path]:
    """The figures and ``demo.json`` in ``out``; their paths (in :data:`FILES` order)."""
    from torch_stsdic.plot import plot_xy

    out.mkdir(parents=True, exist_ok=True)
    paths = [out / name for name in FILES]
    s = d.settings
    noise = f"noise sigma {s.noise:g} grey levels"
    plot_xy(d.times, {f"{r.method} (m={r.m})": r.rms_u_per_frame for r in d.methods},
            xlabel="time (frame)", ylabel="RMS error of u over the points (px)",
            title=f"error per frame, {noise}", path=paths[0])  # fmt: skip
    _fields_figure(d, ref_image, paths[1])
    _history_figure(d, paths[2])
    paths[3].write_text(json.dumps(d.to_json(), indent=2) + "\n", encoding="utf-8")
    return paths


def _fields_figure(d: DemoResult, ref_image: np.ndarray, path: Path | None) -> Any:
    """Error maps at the middle frame over the reference: u (top) and ut (bottom), classical
    DIC (left) and STS-DIC (right); each row on one diverging scale centred on 0."""
    from torch_stsdic.plot import plot_fields

    c, sts, s = d.classical, d.sts, d.settings
    k = len(d.times) // 2
    t = d.times[k]
    fd = " (finite diff.)" if c.ut_from_finite_differences else ""
    maps = {
        "u error, classical DIC": c.error_u[k],
        f"u error, STS-DIC m={s.m}": sts.error_u[k],
        f"ut error, classical DIC{fd}": c.error_ut[k],
        f"ut error, STS-DIC m={s.m}": sts.error_ut[k],
    }
    names = list(maps)
    labels = {nm: ("u error (px)" if nm.startswith("u ") else "ut error (px/frame)")
              for nm in names}  # fmt: skip
    return plot_fields(ref_image, d.points, maps, path, ncols=2, labels=labels,
                share=(names[:2], names[2:]), diverging=names,
                suptitle=f"measured minus exact at t = {t:g} frames (exact u = {t * UT_TRUE:g} "
                f"px, ut = {UT_TRUE:g} px/frame), {s.noise:g} grey levels noise")  # fmt: skip


def _history_figure(d: DemoResult, path: Path | None) -> Any:
    """Error of u (top) and ut (bottom) against time, one column per method on shared axes:
    mean over the points (line) and +-1 standard deviation (band)."""
    from matplotlib.figure import Figure

    from torch_stsdic.plot import save_figure

    n = len(d.methods)
    fig = Figure(figsize=(3.2 * n + 0.8, 5.6), layout="constrained")
    axes = fig.subplots(2, n, sharex=True, sharey="row", squeeze=False)
    colours = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
    for j, (r, col) in enumerate(zip(d.methods, colours)):
        for i, (attr, unit) in enumerate((("error_u", "px"), ("error_ut", "px/frame"))):
            ax = axes[i, j]
            e = getattr(r, attr)
            with np.errstate(all="ignore"):
                mean, std = np.nanmean(e, axis=1), np.nanstd(e, axis=1)
            ax.fill_between(d.times, mean - std, mean + std, color=col, alpha=0.25, lw=0)
            ax.plot(d.times, mean, color=col, marker="o", ms=3)
            ax.axhline(0.0, color="k", lw=0.8)
            ax.grid(True, alpha=0.3)
            if j == 0:
                ax.set_ylabel(f"{attr.split('_')[1]} error ({unit})")
            if i == 1:
                ax.set_xlabel("time (frame)")
        fd = "\n(ut: finite differences)" if r.ut_from_finite_differences else "\n"
        axes[0, j].set_title(f"{r.method} (m={r.m}){fd}", fontsize=9)
    fig.suptitle("measured minus exact u and ut against time: line = mean over the points, "
                 f"band = +-1 std over the points; noise sigma {d.settings.noise:g} grey levels",
                 fontsize=11)  # fmt: skip
    return save_figure(fig, path)


def _np(a: Any) -> np.ndarray:
    """numpy view of a tensor or array-like (detached, on the CPU)."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def _rms(err: np.ndarray) -> float:
    """Root mean square of the finite values (NaN if none)."""
    e = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")
