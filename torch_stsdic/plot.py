"""Matplotlib figures for DIC results: fields over the image, time histories, validation curves.

All functions build a :class:`matplotlib.figure.Figure` directly (no ``pyplot`` state, no display,
nothing to close; the Agg canvas renders it), return it, and save it as PNG (or any format
matplotlib infers from the suffix) when ``path`` is given. In Jupyter the returned figure displays
itself.

Conventions: axes in pixels (labelled in mm etc. with a calibration, ``units``), ``x`` =
column to the right, ``y`` = row **down** (image orientation); NaN values are drawn
transparent (the image shows through: the quality mask). Every colour bar is labelled with
its quantity and unit; displacement-like fields use a sequential map with robust limits
(0.5 .. 99.5 percentiles of the drawn points), errors, strains and gradients a diverging map
centred on 0 (99th percentile of |value|, within Tukey's far-out fence Q3 + 3 IQR of
|value|) where their values reach both signs, else the sequential map on their range; panels
that are compared share their limits (``share``). Colour bars are as tall as their panel.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator, ScalarFormatter

from torch_stsdic.analysis.strain import detect_grid
from torch_stsdic.core.shared_motion import carried_note
from torch_stsdic.core.signatures import POSITIONAL, bind, param, signature_like
from torch_stsdic.core.status import Status
from torch_stsdic.io.run_record import written_atomically
from torch_stsdic.io.units import Units

__all__ = [
    "animate_field",
    "is_diverging",
    "label_axes",
    "plot_error_vs_noise",
    "plot_field",
    "plot_fields",
    "plot_history",
    "plot_shared_motion",
    "plot_status",
    "plot_xy",
    "save_figure",
    "straddles_zero",
]

#: default labels (units) for the usual result fields
FIELD_LABELS: dict[str, str] = {
    "u": "u (px)",
    "v": "v (px)",
    "ut": "ut (px / frame)",
    "vt": "vt (px / frame)",
    "exx": "exx (-)",
    "eyy": "eyy (-)",
    "exy": "exy (-, tensor shear)",
    "exx_rate": "exx rate (1 / frame)",
    "eyy_rate": "eyy rate (1 / frame)",
    "exy_rate": "exy rate (1 / frame)",
    "status": "status",
}

_SYMMETRIC = ("exx", "eyy", "exy", "exx_rate", "eyy_rate", "exy_rate", "ux", "uy", "vx", "vy")


def is_diverging(name: str) -> bool:
    """Whether field ``name`` is drawn on a diverging map centred on 0: strains, their rates,
    displacement gradients and errors (names with "error" or "err")."""
    low = name.lower()
    return name in _SYMMETRIC or "error" in low or low.startswith("err") or low.endswith("_err")


def _np(a: Any) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor, without importing torch here
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def save_figure(fig: Figure, path: str | Path | None, *, dpi: int = 120) -> Figure:
    """Save ``fig`` to ``path`` (parent folders created) if ``path`` is not None; return ``fig``.
    The file is written whole or not at all (a full disk leaves no truncated PNG and raises
    an OSError naming ``path``)."""
    if path is not None:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        with written_atomically(p) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    return fig


class _ScaledLocator(MaxNLocator):
    """Ticks at round values of the scaled unit (e.g. 0, 2, 4 mm) on an axis drawn in px."""

    def __init__(self, scale: float) -> None:
        super().__init__(nbins="auto", steps=[1, 2, 2.5, 5, 10])
        self.scale = scale

    def tick_values(self, vmin: float, vmax: float) -> np.ndarray:
        return super().tick_values(vmin * self.scale, vmax * self.scale) / self.scale


def label_axes(ax: Axes, units: Units | None = None) -> None:
    """Label the image axes x, y in the calibrated length unit (px without a scale): the
    drawing stays in px, the ticks sit at round values of the unit."""
    unit = "px" if units is None or units.scale is None else units.unit
    if unit != "px":
        scale = float(units.scale)  # type: ignore[union-attr]
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_locator(_ScaledLocator(scale))
            axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{round(v * scale, 9):g}"))
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")


def straddles_zero(values: np.ndarray, share: float = 0.2) -> bool:
    """Whether the robust range (0.5 .. 99.5 percentiles) of the finite ``values`` reaches
    both signs, the smaller side at least ``share`` of the larger: only then does a
    diverging map centred on 0 use its colours (eyy all positive would leave half unused)."""
    fin = np.asarray(values, dtype=np.float64)
    fin = fin[np.isfinite(fin)]
    if fin.size == 0:
        return True
    lo, hi = (float(v) for v in np.percentile(fin, [0.5, 99.5]))
    return lo < 0 < hi and min(-lo, hi) >= share * max(-lo, hi)


def colour_norm(values: np.ndarray, vmin: float | None, vmax: float | None,
                symmetric: bool) -> Normalize:
    """Colour limits: robust percentiles of the finite ``values`` (any shape: pass every panel
    that shares the limits), symmetric about 0 when ``symmetric``."""
    values = np.asarray(values, dtype=np.float64)
    fin = values[np.isfinite(values)]
    if fin.size == 0:
        lo, hi = 0.0, 1.0
    elif symmetric:
        # robust limits: a few wild points (specimen edges, holes) must not wash out the map:
        # the 99th percentile of |v|, but not beyond Tukey's far-out fence (Q3 + 3 IQR) of
        # |v| unless the 95th percentile is (a cluster of edge points is often > 1 %)
        a = np.abs(fin)
        q1, q3, p95, p99 = np.percentile(a, [25.0, 75.0, 95.0, 99.0])
        m = max(float(p95), min(float(p99), float(q3 + 3.0 * (q3 - q1))))
        m = m or float(np.max(a)) or 1.0
        lo, hi = -m, m
    else:
        lo, hi = (float(v) for v in np.percentile(fin, [0.5, 99.5]))
        if lo == hi:
            lo, hi = lo - 0.5, hi + 0.5
    return Normalize(vmin=lo if vmin is None else vmin, vmax=hi if vmax is None else vmax)


def _draw_field(
    ax: Axes,
    image: Any,
    points: np.ndarray,
    values: np.ndarray,
    *,
    cmap: str,
    alpha: float,
    norm: Normalize,
    marker_size: float | None,
    units: Units | None = None,
) -> Any:
    """Draw the image (grey) and the field on ``ax`` (axes in ``units``' length unit);
    return the mappable for the colour bar."""
    if image is not None:
        img = _np(image)
        if img.ndim != 2:
            raise ValueError(f"image must have shape (H, W), got {img.shape}")
        h, w = img.shape
        ax.imshow(img, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest")
    grid = detect_grid(points) if len(points) else None
    if grid is not None and grid.nx > 1 and grid.ny > 1:
        z = np.ma.masked_invalid(grid.to_image(values.astype(np.float64)))
        x1 = grid.x0 + (grid.nx - 1) * grid.sx
        y1 = grid.y0 + (grid.ny - 1) * grid.sy
        extent = (grid.x0 - grid.sx / 2, x1 + grid.sx / 2, y1 + grid.sy / 2,
                  grid.y0 - grid.sy / 2)
        mappable = ax.imshow(z, cmap=cmap, norm=norm, alpha=alpha, extent=extent,
                             interpolation="nearest")
    else:
        fin = np.isfinite(values)
        mappable = ax.scatter(points[fin, 0], points[fin, 1], c=values[fin], cmap=cmap,
                              norm=norm, alpha=alpha, linewidths=0,
                              s=marker_size if marker_size is not None else 12.0)
    if image is not None:
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
    elif len(points):
        pad = 0.5 * (grid.sx if grid is not None else 1.0)
        pady = 0.5 * (grid.sy if grid is not None else 1.0)
        ax.set_xlim(points[:, 0].min() - pad, points[:, 0].max() + pad)
        ax.set_ylim(points[:, 1].max() + pady, points[:, 1].min() - pady)  # y down
    ax.set_aspect("equal")
    label_axes(ax, units)
    return mappable


def _check_points(points: Any, values: Any) -> tuple[np.ndarray, np.ndarray]:
    p = _np(points).astype(np.float64)
    v = _np(values).astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2) as (x, y), got {p.shape}")
    if v.shape != (p.shape[0],):
        raise ValueError(f"values must have shape (N,) = ({p.shape[0]},), got {v.shape}")
    return p, v


def plot_field(
    image: Any,
    points: Any,
    values: Any,
    *,
    title: str | None = None,
    cmap: str = "viridis",
    label: str | None = None,
    alpha: float = 0.7,
    vmin: float | None = None,
    vmax: float | None = None,
    symmetric: bool = False,
    marker_size: float | None = None,
    norm: Normalize | None = None,
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 120,
    units: Units | None = None,
    sequential_cmap: str = "viridis",
) -> Figure:
    """One scalar field drawn over the reference image, with a colour bar as tall as the
    panel.

    Args:
        image: (H, W) grey image to draw underneath, or None.
        points: (N, 2) point coordinates ``(x, y)`` in pixels.
        values: (N,) field values (NaN = transparent, e.g. invalid points).
        title: axes title; ``label``: colour-bar label (put the units here, e.g. ``"u (px)"``).
        cmap, alpha, vmin, vmax: colour map, opacity over the image and colour limits.
        symmetric: colour limits ``[-a, a]`` with a the 99th percentile of |v| (good for
            strains with a diverging cmap) where the values reach both signs
            (:func:`straddles_zero`); else, and without ``symmetric``, the 0.5 .. 99.5
            percentiles (robust to a few wild points) on ``sequential_cmap`` (for a one-signed
            field) unless vmin / vmax are given.
        units: the calibration: x, y axes labelled in its length unit (default px).
        marker_size: scatter marker size (scattered points only).
        norm: colour limits to use as they are (e.g. shared by several panels).
        ax: draw into this axes (its figure is returned, not saved unless ``path``).
        path: save the figure there (PNG by suffix).

    Points on a regular grid (holes allowed) are drawn as an image of grid cells centred on the
    points; scattered points as a scatter plot.
    """
    p, v = _check_points(points, values)
    if symmetric and norm is None and vmin is None and vmax is None and not straddles_zero(v):
        symmetric, cmap = False, sequential_cmap
    if ax is None:
        fig = Figure(figsize=(6.4, 4.8), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.get_figure()
    m = _draw_field(ax, image, p, v, cmap=cmap, alpha=alpha, marker_size=marker_size,
                    norm=norm if norm is not None else colour_norm(v, vmin, vmax, symmetric),
                    units=units)
    cb = colorbar(fig, ax, m)
    if label:
        cb.set_label(label)
    if title:
        ax.set_title(title)
    return save_figure(fig, path, dpi=dpi)


def colorbar(fig: Figure, ax: Axes, mappable: Any, **kwargs: Any) -> Any:
    """A colour bar exactly as tall as the drawn panel (an inset beside the axes, which follows
    the panel's aspect-ratio box, so a tall specimen gets no taller bar)."""
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    aspect = abs(x1 - x0) / max(abs(y1 - y0), 1e-12)  # panel width / height (equal aspect)
    width = float(np.clip(0.05 / min(aspect, 1.0), 0.05, 0.2))
    cax = ax.inset_axes((1.0 + 0.4 * width, 0.0, width, 1.0))
    cb = fig.colorbar(mappable, cax=cax, **kwargs)
    if "format" not in kwargs:  # small values (strains) as "-2 ... x 10^-4", not "-0.00020":
        fmt = ScalarFormatter(useMathText=True)  # long tick labels ran into the next panel
        fmt.set_powerlimits((-3, 4))
        cb.formatter = fmt
        cb.update_ticks()
    return cb


def panel_extent(image: Any, points: np.ndarray) -> tuple[float, float]:
    """(width, height) in px of what a panel shows: the image, else the points' box."""
    if image is not None:
        h, w = _np(image).shape[-2:]
        return float(w), float(h)
    if len(points) == 0:
        return 1.0, 1.0
    span = points.max(axis=0) - points.min(axis=0)
    grid = detect_grid(points)
    pad = (grid.sx, grid.sy) if grid is not None else (1.0, 1.0)
    return float(span[0] + pad[0]), float(span[1] + pad[1])


def panel_layout(n: int, aspect: float, ncols: int | None = None, *, height: float = 3.6,
                 max_width: float = 17.5) -> tuple[int, int, tuple[float, float]]:
    """(rows, columns, figure size in inches) for ``n`` panels of data ``aspect`` (width /
    height) so that the page is filled: tall specimens side by side, wide ones stacked;
    every panel ``height`` inches tall plus room for its colour bar and labels."""
    panel_w = height * aspect + 1.9  # + axis labels, colour bar and its label
    if ncols is None:  # as many as fit, then balanced rows (4 panels: 2 x 2, not 3 + 1)
        fit = max(1, min(n, int(max_width // panel_w)))
        ncols = -(-n // -(-n // fit))
    ncols = max(1, min(ncols, n))
    nrows = -(-n // ncols)
    return nrows, ncols, (panel_w * ncols, (height + 0.7) * nrows + 0.5)


def plot_fields(
    image: Any,
    points: Any,
    fields: Mapping[str, Any],
    path: str | Path | None = None,
    *,
    ncols: int | None = None,
    labels: Mapping[str, str] | None = None,
    units: Units | None = None,
    cmap: str = "viridis",
    diverging_cmap: str = "RdBu_r",
    diverging: Collection[str] = (),
    share: Sequence[Sequence[str]] = (),
    alpha: float = 0.75,
    suptitle: str | None = None,
    panel_height: float = 3.6,
    dpi: int = 120,
    notes: Mapping[str, str] | None = None,
) -> Figure:
    """Multi-panel figure, one panel (with a colour bar as tall as the panel) per field.

    Args:
        image: (H, W) grey image under every panel, or None.
        points: (N, 2) ``(x, y)`` pixels.
        fields: ordered mapping name -> (N,) values (NaN: not drawn, e.g. unusable points),
            e.g. ``{"u": u[f], "v": v[f], "exx": ...}``, already in ``units``.
        path: save there if given.
        labels: colour-bar labels by name (default: ``units.label(name)`` -- quantity and
            unit, px without ``units`` -- else :data:`FIELD_LABELS`, else the name).
        units: the calibration the values are in (:class:`~torch_stsdic.io.units.Units`).
        cmap: colour map of displacement-like fields; :func:`is_diverging` names and those in
            ``diverging`` get ``diverging_cmap`` with limits symmetric about 0 where their
            values reach both signs (:func:`straddles_zero`), else ``cmap`` with the values'
            range. The x, y axes are in ``units``' length unit.
        share: groups of names whose panels share their colour limits (compared panels).
        ncols: panels per row (default: as many as fill about 17 inches of width).
        notes: a line under a panel's title by name (e.g. why a velocity is missing).
    """
    if not fields:
        raise ValueError("fields is empty")
    pts = _np(points).astype(np.float64)
    n = len(fields)
    w, h = panel_extent(image, pts)
    nrows, ncols, size = panel_layout(n, w / h, ncols, height=panel_height)
    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    units = units or Units()
    labels = dict(labels or {})
    sym = {nm: (is_diverging(nm) or nm in diverging) and straddles_zero(_np(v))
           for nm, v in fields.items()}
    norms: dict[str, Normalize] = {}
    for group in share:
        names = [nm for nm in group if nm in fields]
        if names:
            both = np.concatenate([np.ravel(_np(fields[nm])) for nm in names])
            shared = any(is_diverging(nm) or nm in diverging for nm in names) and \
                straddles_zero(both)
            norms.update({nm: colour_norm(both, None, None, shared) for nm in names})
            sym.update({nm: shared for nm in names})
    for ax, (name, vals) in zip(axes, fields.items()):
        default = units.label(name) if units.dims(name) is not None else None
        plot_field(image, pts, vals, title=name, ax=ax, alpha=alpha, symmetric=sym[name],
                   norm=norms.get(name), cmap=diverging_cmap if sym[name] else cmap,
                   label=labels.get(name) or default or FIELD_LABELS.get(name, name),
                   units=units)
        if notes and notes.get(name):  # wrapped to the panel's width (not over the next bar)
            chars = max(12, int((size[0] / ncols - 1.0) * 72 / (9 * 0.6)))  # 9 pt font
            ax.set_title(f"{name}\n" + textwrap.fill(notes[name], chars), fontsize=9)
    for ax in axes[n:]:
        fig.delaxes(ax)
    if suptitle:
        fig.suptitle(suptitle)
    return save_figure(fig, path, dpi=dpi)


#: colours of the status codes (usable ones green/olive, failures warm, not computed grey)
STATUS_COLOURS = {
    Status.CONVERGED: "#1a9850", Status.MAX_ITER: "#a6d96a", Status.DIVERGED: "#d73027",
    Status.OUTSIDE: "#7b3294", Status.LOW_TEXTURE: "#fdae61", Status.NOT_COMPUTED: "#bdbdbd",
    Status.POOR_FIT: "#f46d43", Status.INCONSISTENT: "#4575b4",
}  # fmt: skip


def plot_status(
    image: Any,
    points: Any,
    status: Any,
    *,
    title: str | None = "status",
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 120,
    units: Units | None = None,
) -> Figure:
    """The quality map: every point coloured by its :class:`~torch_stsdic.core.status.Status`
    over the image, with a colour bar naming the codes and the share of points with each
    (x, y axes in ``units``' length unit)."""
    p = _np(points).astype(np.float64)
    st = _np(status).astype(np.int64)
    codes = list(Status)
    if ax is None:
        w, h = panel_extent(image, p)
        _, _, size = panel_layout(1, w / h, 1, height=4.2)
        fig = Figure(figsize=(size[0] + 1.2, size[1]), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.get_figure()
    cmap = ListedColormap([STATUS_COLOURS[c] for c in codes])
    norm = BoundaryNorm(np.arange(len(codes) + 1) - 0.5, len(codes))
    m = _draw_field(ax, image, p, st.astype(np.float64), cmap=cmap, alpha=0.85, norm=norm,
                    marker_size=None, units=units)  # fmt: skip
    cb = colorbar(fig, ax, m, ticks=np.arange(len(codes)))
    total = max(1, st.size)
    cb.ax.set_yticklabels([f"{c.name.lower()} {100.0 * (st == int(c)).sum() / total:.1f} %"
                           for c in codes])  # fmt: skip
    cb.ax.tick_params(labelsize=8)
    if title:
        ax.set_title(title)
    return save_figure(fig, path, dpi=dpi)


def plot_xy(
    x: Any,
    series: Mapping[str, Any],
    *,
    xlabel: str = "",
    ylabel: str = "",
    title: str | None = None,
    logx: bool = False,
    logy: bool = False,
    marker: str | None = "o",
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 120,
    counts: Any = None,
    min_count: float = 0.0,
    count_label: str = "points",
) -> Figure:
    """Line plot of several series against one x (validation curves: error vs sigma, vs m ...).

    ``x`` (K,); ``series`` label -> (K,) values (NaN = gap). A legend is drawn when there is
    more than one series or a non-empty label. ``counts`` (K,): how many points each value
    (an aggregate, e.g. a mean over points) rests on, drawn in a panel below (``count_label``
    on its axis); values resting on fewer than ``min_count`` are left out (a gap, not a line).
    """
    xs = _np(x).astype(np.float64)
    n = None if counts is None else _np(counts).astype(np.float64)
    if n is not None and n.shape != xs.shape:
        raise ValueError(f"counts has shape {n.shape}, x has {xs.shape}")
    below = n is not None and ax is None  # the counts get their own panel
    if ax is None:
        tall = 4.0 + (0.3 * (-(-len(series) // 2)) + 0.3 if len(series) > 2 else 0.0)
        fig = Figure(figsize=(6.4, tall + (1.6 if below else 0.0)), layout="constrained")
        if n is None:
            ax = fig.add_subplot()
        else:
            ax, cax = fig.subplots(2, 1, sharex=True, height_ratios=(tall, 1.6))
            _draw_counts(cax, xs, n, min_count, count_label, xlabel)
    else:
        fig = ax.get_figure()
    for name, y in series.items():
        yv = _np(y).astype(np.float64)
        if yv.shape != xs.shape:
            raise ValueError(f"series {name!r} has shape {yv.shape}, x has {xs.shape}")
        if n is not None:
            yv = np.where(n >= min_count, yv, np.nan)
        ax.plot(xs, yv, marker=marker, label=name)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("" if below else xlabel)  # under the counts' panel instead
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if len(series) > 2:  # under the axes: a legend inside would hide curves
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8,
                  frameon=False)  # fmt: skip
    elif len(series) > 1 or any(series):
        ax.legend()
    return save_figure(fig, path, dpi=dpi)


def _draw_counts(ax: Axes, xs: np.ndarray, n: np.ndarray, min_count: float, label: str,
                 xlabel: str) -> None:
    """The panel under an aggregate: how many points each value rests on, the threshold
    below which it is left out, and those values marked."""
    ax.plot(xs, n, marker=".", color="0.3")
    low = n < min_count
    if min_count > 0:
        ax.axhline(min_count, color="#d73027", linestyle="--", linewidth=1,
                   label=f"fewer than {min_count:g}: left out")
        ax.plot(xs[low], n[low], "x", color="#d73027")
        ax.legend(fontsize=7, loc="best")
    ax.set_ylim(0, max(float(np.nanmax(n, initial=0.0)), min_count, 1.0) * 1.1)
    ax.set_ylabel(label, fontsize=8)
    ax.set_xlabel(xlabel)
    ax.grid(True, alpha=0.3)


def plot_history(*args: Any, **kwargs: Any) -> Figure:
    """Time history of scalar quantities, e.g. ``u`` of one point or its mean over points,
    classical DIC vs STS-DIC vs the true motion: :func:`plot_xy` without markers.

    ``times`` (F,); ``series`` label -> (F,) values (NaN = gap, e.g. failed frames).
    """
    arg = bind(_HISTORY_SIGNATURE, *args, **kwargs)
    return plot_xy(arg.pop("times"), arg.pop("series"), marker=None, **arg)


_HISTORY_SIGNATURE = signature_like(
    plot_xy, replace={"x": param("times", kind=POSITIONAL)}, drop=["logx", "logy", "marker"],
    defaults={"xlabel": "time (frame)"})
plot_history.__signature__ = _HISTORY_SIGNATURE  # type: ignore[attr-defined]


def plot_shared_motion(
    times: Any,
    params: Any,
    *,
    applied: bool = True,
    velocity_m: int | None = None,
    smoothed_frames: int | None = None,
    jumps: Any = None,
    title: str | None = None,
    time_label: str = "time (frame)",
    length_unit: str = "px",
    scale: float = 1.0,
    path: str | Path | None = None,
    dpi: int = 120,
) -> Figure:
    """The specimen's shared motion per frame (:mod:`torch_stsdic.core.shared_motion`): its
    translation at the POIs' centre (``scale`` ``length_unit`` per px) and, below, its
    rotation and normal strains (the affine gradient), in 1e-3.

    ``times`` (T,); ``params`` (T, 6) or (T, 12): columns ``shared_motion.PARAM_NAMES``;
    ``applied``, ``velocity_m``, ``smoothed_frames``, ``jumps`` (marked): how the run carried
    it (the title's note: :func:`~torch_stsdic.core.shared_motion.carried_note`)."""
    t = _np(times).astype(np.float64)
    p = _np(params).astype(np.float64)
    if p.ndim != 2 or p.shape[0] != t.shape[0] or p.shape[1] not in (6, 12):
        raise ValueError(f"params must be (T, 6) or (T, 12) with T = {t.shape[0]}, got "
                         f"{p.shape}")
    fig = Figure(figsize=(6.4, 6.0), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, p[:, 0] * scale, label="translation x")
    ax1.plot(t, p[:, 1] * scale, label="translation y")
    ax1.set_ylabel(f"shared translation ({length_unit})")
    ax1.legend(fontsize=8)
    ax1.grid(True, alpha=0.3)
    ax2.plot(t, 0.5 * (p[:, 4] - p[:, 3]) * 1e3, label="rotation (mrad)")
    ax2.plot(t, p[:, 2] * 1e3, label="du/dx (1e-3)")
    ax2.plot(t, p[:, 5] * 1e3, label="dv/dy (1e-3)")
    ax2.set_ylabel("shared gradient (1e-3)")
    ax2.set_xlabel(time_label)
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    for ax, k in ((ax, k) for k in jumps or () for ax in (ax1, ax2)):  # where it jumps
        ax.axvline(t[int(k)], color="0.5", ls="--", lw=0.8)
    note = carried_note(applied, velocity_m, smoothed_frames, jumps)
    ax1.set_title(title + f"\n{note}" if title else note, fontsize=10)
    return save_figure(fig, path, dpi=dpi)


def plot_error_vs_noise(*args: Any, **kwargs: Any) -> Figure:
    """Error against image-noise level, one curve per method (e.g. ``"DIC"``, ``"STS m=2"``):
    :func:`plot_xy` with noise labels.

    ``sigmas`` (K,) noise standard deviations; ``errors`` label -> (K,) errors.
    """
    arg = bind(_NOISE_PLOT_SIGNATURE, *args, **kwargs)
    return plot_xy(arg.pop("sigmas"), arg.pop("errors"), **arg)


_NOISE_PLOT_SIGNATURE = signature_like(
    plot_xy, replace={"x": param("sigmas", kind=POSITIONAL),
                      "series": param("errors", annotation="Mapping[str, Any]", kind=POSITIONAL)},
    drop=["logx", "marker", "ax", "counts", "min_count", "count_label"],
    defaults={"ylabel": "RMS error (px)", "xlabel": "noise sigma (grey levels)"})
plot_error_vs_noise.__signature__ = _NOISE_PLOT_SIGNATURE  # type: ignore[attr-defined]


def animate_field(
    frame_image: Callable[[int], Any] | None,
    points: Any,
    values: Any,
    path: str | Path,
    *,
    stamps: Sequence[str] | None = None,
    displacement: tuple[Any, Any] | None = None,
    label: str = "",
    symmetric: bool = False,
    cmap: str | None = None,
    title: str = "",
    fps: float = 4.0,
    dpi: int = 100,
    units: Units | None = None,
) -> Path:
    """An animation of a field over the movie: GIF (matplotlib's PillowWriter), or MP4 when
    ``path`` ends in ``.mp4`` and ffmpeg is installed (else a GIF beside it).

    Args:
        frame_image: row -> (H, W) image of that row's frame (the movie), or None.
        points: (N, 2) reference positions (x, y) px.
        values: (F, N) field per row (NaN: not drawn), already in the unit of ``label``.
        displacement: (u, v), each (F, N) px: the points are drawn where they moved to
            (so the field stays on the material over the moving images).
        stamps: (F,) texts after the title, e.g. "frame 3" or "t = 0.5 s" (default: "row k").
        symmetric: diverging map centred on 0 where the values reach both signs
            (:func:`straddles_zero`). The colour limits are fixed over all frames.
        units: the calibration: x, y axes in its length unit (default px).

    Returns:
        the path written.
    """
    from matplotlib import animation

    p = _np(points).astype(np.float64)
    vals = _np(values).astype(np.float64)
    if vals.ndim != 2 or vals.shape[1] != len(p):
        raise ValueError(f"values must have shape (F, N) = (F, {len(p)}), got {vals.shape}")
    n_rows = vals.shape[0]
    symmetric = symmetric and straddles_zero(vals)
    norm = colour_norm(vals, None, None, symmetric)
    cmap = cmap or ("RdBu_r" if symmetric else "viridis")
    first = None if frame_image is None else _np(frame_image(0))
    w, h = panel_extent(first, p)
    _, _, size = panel_layout(1, w / h, 1, height=4.5)
    fig = Figure(figsize=size, layout="constrained")
    ax = fig.add_subplot()
    img_artist = None
    if first is not None:
        img_artist = ax.imshow(first, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5),
                               interpolation="nearest")  # fmt: skip
    grid = detect_grid(p)
    size_pt = 12.0
    if grid is not None:  # squares about one grid cell wide
        ax_w_in = size[0] - 1.9
        cell_in = grid.sx / max(w, 1.0) * ax_w_in
        size_pt = float(np.clip((0.9 * cell_in * 72.0) ** 2, 4.0, 1e4))
    scat = ax.scatter(p[:, 0], p[:, 1], c=vals[0], cmap=cmap, norm=norm, s=size_pt,
                      marker="s", linewidths=0, alpha=0.8)  # fmt: skip
    if first is not None:
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
    else:
        ax.set_xlim(p[:, 0].min() - 0.05 * w, p[:, 0].max() + 0.05 * w)
        ax.set_ylim(p[:, 1].max() + 0.05 * h, p[:, 1].min() - 0.05 * h)
    ax.set_aspect("equal")
    label_axes(ax, units)
    cb = colorbar(fig, ax, scat)
    cb.set_label(label)
    stamps = list(stamps) if stamps is not None else [f"row {k}" for k in range(n_rows)]
    heading = ax.set_title("")

    def draw(k: int) -> tuple[Any, ...]:
        v = vals[k]
        xy = p.copy()
        if displacement is not None:
            du, dv = (np.nan_to_num(_np(d)[k].astype(np.float64)) for d in displacement)
            xy = p + np.column_stack([du, dv])
        ok = np.isfinite(v)
        scat.set_offsets(xy[ok])
        scat.set_array(v[ok])
        if img_artist is not None and k > 0:
            img_artist.set_data(_np(frame_image(k)))
        heading.set_text(f"{title} {stamps[k]}".strip())
        return (scat, heading) if img_artist is None else (scat, heading, img_artist)

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".mp4" and animation.FFMpegWriter.isAvailable():
        writer: Any = animation.FFMpegWriter(fps=fps)
    else:
        out = out.with_suffix(".gif")
        writer = animation.PillowWriter(fps=fps)
    anim = animation.FuncAnimation(fig, draw, frames=n_rows, blit=False)
    with written_atomically(out) as tmp:
        anim.save(tmp, writer=writer, dpi=dpi)
    return out
