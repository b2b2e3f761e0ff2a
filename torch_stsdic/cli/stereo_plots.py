"""The figures of a stereo result file's frame for ``stsdic plot`` (:mod:`.plot`): the field
maps, the quality map and the 3D shape. ``res`` is the stereo file as the plot command reads
it (``points``, ``frames``, ``fields``, ``n_points``, ``label(name)``, ``when(row)``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["stereo_frame_figures", "stereo_shape_figure"]

STRAINS = ("exx", "eyy", "exy")


def stereo_frame_figures(args: argparse.Namespace, res: Any, row: int, names: list[str],
                         valid: np.ndarray, image: np.ndarray | None, out: Path) -> list[Path]:
    """The field maps and the quality map (status, reprojection error) of one row."""
    from matplotlib.figure import Figure

    from torch_stsdic.plot import (
        panel_extent,
        panel_layout,
        plot_field,
        plot_fields,
        plot_status,
        save_figure,
    )

    frame, name, when = int(res.frames[row]), Path(args.result).name, res.when(row)
    maps, notes = {}, {}
    for nm in names:
        vals = np.asarray(res.fields[nm][row], dtype=np.float64)
        maps[nm] = vals if nm == "status" else np.where(valid[row], vals, np.nan)
        if nm != "status" and not np.isfinite(maps[nm]).any():
            notes[nm] = ("no value at any usable point" + (": classical DIC (--m 0) has no "
                         "velocity" if nm.removesuffix("_std") in ("Ut", "Vt", "Wt") else ""))
    written = []
    if maps:
        path = out / f"fields_frame{frame:05d}.png"
        plot_fields(image, res.points, maps, path, dpi=args.dpi,
                    labels={nm: res.label(nm) for nm in maps}, notes=notes,
                    suptitle=f"{name}: {when}, on the left reference points (mm"
                    f"{', strains dimensionless' if any(n in maps for n in STRAINS) else ''}; "
                    "axes in px); unusable points not drawn")
        written.append(path)
    w, h = panel_extent(image, res.points)
    _, _, (fw, fh) = panel_layout(2, w / h, 2, height=4.2 if w <= h else 3.2)
    fig = Figure(figsize=(fw + 1.3, fh), layout="constrained")  # + the status names
    axes = fig.subplots(1, 2, squeeze=False).ravel()
    plot_status(image, res.points, res.fields["status"][row], ax=axes[0],
                title="status (usable: converged, max_iter)")
    err = np.asarray(res.fields["reprojection_error"][row], dtype=np.float64)
    plot_field(image, res.points, err, ax=axes[1], title="reprojection error",
               label=res.label("reprojection_error", "reprojection error"))
    fig.suptitle(f"{name}: quality at {when}")
    path = out / f"quality_frame{frame:05d}.png"
    save_figure(fig, path, dpi=args.dpi)
    written.append(path)
    return written


def stereo_shape_figure(args: argparse.Namespace, res: Any, row: int, valid: np.ndarray,
                        out: Path) -> Path:
    """``shape_frameNNNNN.png``: the usable points at their 3D position (X, Y, Z mm, left
    camera frame, Y down) of one row, coloured by W, on equal axes."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FixedLocator, MaxNLocator

    from torch_stsdic.plot import colour_norm, save_figure

    frame = int(res.frames[row])
    ok = valid[row]
    xyz = np.stack([res.fields[k][row][ok] for k in ("X", "Y", "Z")], -1)
    w = np.asarray(res.fields["W"][row][ok], dtype=np.float64)
    fig = Figure(figsize=(7.0, 5.6), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    if len(xyz):
        sc = ax.scatter(xyz[:, 0], xyz[:, 2], xyz[:, 1], c=w, cmap="viridis",
                        norm=colour_norm(w, None, None, False), s=18, depthshade=False)
        fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.06, label=res.label("W"))
        ax.set_aspect("equal")
        if not getattr(res, "plane_frame", False):
            ax.invert_zaxis()  # the camera's Y points down
    else:
        ax.text2D(0.5, 0.5, "no usable point at this frame", transform=ax.transAxes,
                  ha="center")
    # Z (depth) is short; in the plane frame it is the flatness alone (hundredths of a mm
    # on equal axes): one tick there, or the labels run into each other
    extent = np.ptp(xyz, 0) if len(xyz) else np.ones(3)
    for axis, n in ((ax.xaxis, 4), (ax.yaxis, 3), (ax.zaxis, 4)):
        axis.set_major_locator(MaxNLocator(n))
    if len(xyz) and extent[2] < 0.1 * max(extent[0], extent[1]):
        ax.yaxis.set_major_locator(FixedLocator([float(np.round(np.median(xyz[:, 2]), 2))]))
    ax.set_xlabel(res.label("X"))
    ax.set_ylabel(res.label("Z"), labelpad=8)
    ax.set_zlabel(res.label("Y"))
    ax.view_init(elev=25, azim=-50)
    ax.set_title(f"{Path(args.result).name}: 3D points at {res.when(row)}\n"
                 f"{int(ok.sum())} of {res.n_points} usable, coloured by W; "
                 f"{'best-fit plane' if getattr(res, 'plane_frame', False) else 'left camera'}"
                 " frame, equal axes", fontsize=10)
    path = out / f"shape_frame{frame:05d}.png"
    save_figure(fig, path, dpi=args.dpi)
    return path
