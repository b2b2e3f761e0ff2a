"""Matplotlib figures for DIC results: fields over the image, time histories, validation curves.

All functions build a :class:`matplotlib.figure.Figure` directly (no ``pyplot`` state, no display,
nothing to close; the Agg canvas renders it), return it, and save it as PNG (or any format
matplotlib infers from the suffix) when ``path`` is given. In Jupyter the returned figure displays
itself.

Conventions: axes in pixels, ``x`` = column to the right, ``y`` = row **down** (image
orientation); NaN values are drawn transparent.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from .strain import detect_grid

__all__ = [
    "plot_error_vs_noise",
    "plot_field",
    "plot_fields",
    "plot_history",
    "plot_xy",
    "save_figure",
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


def _np(a: Any) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor, without importing torch here
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def save_figure(fig: Figure, path: str | Path | None, *, dpi: int = 120) -> Figure:
    """Save ``fig`` to ``path`` (parent folders created) if ``path`` is not None; return ``fig``."""
    if path is not None:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(p, dpi=dpi, bbox_inches="tight")
    return fig


def _norm(values: np.ndarray, vmin: float | None, vmax: float | None, symmetric: bool) -> Normalize:
    fin = values[np.isfinite(values)]
    if fin.size == 0:
        lo, hi = 0.0, 1.0
    elif symmetric:
        # robust limits: a few wild points (specimen edges, holes) must not wash out the map
        m = float(np.percentile(np.abs(fin), 99.0)) or float(np.max(np.abs(fin))) or 1.0
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
) -> Any:
    """Draw the image (grey) and the field on ``ax``; return the mappable for the colour bar."""
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
        extent = (
            grid.x0 - grid.sx / 2,
            x1 + grid.sx / 2,
            y1 + grid.sy / 2,
            grid.y0 - grid.sy / 2,
        )
        mappable = ax.imshow(
            z, cmap=cmap, norm=norm, alpha=alpha, extent=extent, interpolation="nearest"
        )
    else:
        fin = np.isfinite(values)
        mappable = ax.scatter(
            points[fin, 0],
            points[fin, 1],
            c=values[fin],
            cmap=cmap,
            norm=norm,
            alpha=alpha,
            s=marker_size if marker_size is not None else 12.0,
            linewidths=0,
        )
    if image is not None:
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
    elif len(points):
        pad = 0.5 * (grid.sx if grid is not None else 1.0)
        pady = 0.5 * (grid.sy if grid is not None else 1.0)
        ax.set_xlim(points[:, 0].min() - pad, points[:, 0].max() + pad)
        ax.set_ylim(points[:, 1].max() + pady, points[:, 1].min() - pady)  # y down
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
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
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 120,
) -> Figure:
    """One scalar field drawn over the reference image, with a colour bar.

    Args:
        image: (H, W) grey image to draw underneath, or None.
        points: (N, 2) point coordinates ``(x, y)`` in pixels.
        values: (N,) field values (NaN = transparent, e.g. invalid points).
        title: axes title; ``label``: colour-bar label (put the units here, e.g. ``"u (px)"``).
        cmap, alpha, vmin, vmax: colour map, opacity over the image and colour limits.
        symmetric: colour limits ``[-a, a]`` with a the 99th percentile of |v| (good for
            strains with a diverging cmap); otherwise the 0.5 .. 99.5 percentiles (robust to a
            few wild points) unless vmin / vmax are given.
        marker_size: scatter marker size (scattered points only).
        ax: draw into this axes (its figure is returned, not saved unless ``path``).
        path: save the figure there (PNG by suffix).

    Points on a regular grid (holes allowed) are drawn as an image of grid cells centred on the
    points; scattered points as a scatter plot.
    """
    p, v = _check_points(points, values)
    if ax is None:
        fig = Figure(figsize=(6.4, 4.8), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.get_figure()
    m = _draw_field(
        ax,
        image,
        p,
        v,
        cmap=cmap,
        alpha=alpha,
        norm=_norm(v, vmin, vmax, symmetric),
        marker_size=marker_size,
    )
    cb = fig.colorbar(m, ax=ax)
    if label:
        cb.set_label(label)
    if title:
        ax.set_title(title)
    return save_figure(fig, path, dpi=dpi)


def plot_fields(
    image: Any,
    points: Any,
    fields: Mapping[str, Any],
    path: str | Path | None = None,
    *,
    ncols: int = 3,
    labels: Mapping[str, str] | None = None,
    cmap: str = "viridis",
    diverging_cmap: str = "RdBu_r",
    alpha: float = 0.7,
    suptitle: str | None = None,
    panel_size: tuple[float, float] = (4.2, 3.4),
    dpi: int = 120,
) -> Figure:
    """Multi-panel figure, one panel (with its colour bar) per field.

    Args:
        image: (H, W) grey image under every panel, or None.
        points: (N, 2) ``(x, y)`` pixels.
        fields: ordered mapping name -> (N,) values, e.g. ``{"u": u[f], "v": v[f], "exx": ...}``.
        path: save there if given.
        labels: colour-bar labels by name (default: :data:`FIELD_LABELS`, else the name).
        cmap: colour map of displacement-like fields; strain-like names (``exx``, ``exy_rate``...)
            get ``diverging_cmap`` with symmetric limits.
    """
    if not fields:
        raise ValueError("fields is empty")
    n = len(fields)
    ncols = max(1, min(ncols, n))
    nrows = -(-n // ncols)
    fig = Figure(figsize=(panel_size[0] * ncols, panel_size[1] * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    labels = dict(labels or {})
    for ax, (name, vals) in zip(axes, fields.items()):
        sym = name in _SYMMETRIC
        plot_field(
            image,
            points,
            vals,
            title=name,
            ax=ax,
            alpha=alpha,
            symmetric=sym,
            cmap=diverging_cmap if sym else cmap,
            label=labels.get(name, FIELD_LABELS.get(name, name)),
        )
    for ax in axes[n:]:
        fig.delaxes(ax)
    if suptitle:
        fig.suptitle(suptitle)
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
) -> Figure:
    """Line plot of several series against one x (validation curves: error vs sigma, vs m ...).

    ``x`` (K,); ``series`` label -> (K,) values (NaN = gap). A legend is drawn when there is
    more than one series or a non-empty label.
    """
    xs = _np(x).astype(np.float64)
    if ax is None:
        fig = Figure(figsize=(6.0, 4.0), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.get_figure()
    for name, y in series.items():
        yv = _np(y).astype(np.float64)
        if yv.shape != xs.shape:
            raise ValueError(f"series {name!r} has shape {yv.shape}, x has {xs.shape}")
        ax.plot(xs, yv, marker=marker, label=name)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if len(series) > 1 or any(series):
        ax.legend()
    return save_figure(fig, path, dpi=dpi)


def plot_history(
    times: Any,
    series: Mapping[str, Any],
    *,
    ylabel: str = "",
    xlabel: str = "time (frame)",
    title: str | None = None,
    ax: Axes | None = None,
    path: str | Path | None = None,
    dpi: int = 120,
) -> Figure:
    """Time history of scalar quantities, e.g. ``u`` of one point or its mean over points,
    classical DIC vs STS-DIC vs the true motion.

    ``times`` (F,); ``series`` label -> (F,) values (NaN = gap, e.g. failed frames).
    """
    return plot_xy(
        times,
        series,
        xlabel=xlabel,
        ylabel=ylabel,
        title=title,
        marker=None,
        ax=ax,
        path=path,
        dpi=dpi,
    )


def plot_error_vs_noise(
    sigmas: Any,
    errors: Mapping[str, Any],
    *,
    ylabel: str = "RMS error (px)",
    xlabel: str = "noise sigma (grey levels)",
    title: str | None = None,
    logy: bool = False,
    path: str | Path | None = None,
    dpi: int = 120,
) -> Figure:
    """Error against image-noise level, one curve per method (e.g. ``"DIC"``, ``"STS m=2"``).

    ``sigmas`` (K,) noise standard deviations; ``errors`` label -> (K,) errors.
    """
    return plot_xy(
        sigmas, errors, xlabel=xlabel, ylabel=ylabel, title=title, logy=logy, path=path, dpi=dpi
    )
