"""Exports of result files for other tools: one CSV per frame."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .results import CSV_COLUMNS, field_names, open_results

__all__ = ["export_csv"]


def _fmt(a: np.ndarray, spec: str) -> np.ndarray:
    s = np.char.mod(spec, a)
    if a.dtype.kind == "f":
        s[~np.isfinite(a)] = ""
    return s


def export_csv(
    path_h5: str | os.PathLike[str],
    out_dir_or_pattern: str | os.PathLike[str],
    frames: int | Sequence[int] | None = None,
    *,
    comment: bool = True,
) -> list[Path]:
    """Write one CSV per frame; return the paths written.

    ``out_dir_or_pattern``: a directory (files ``<h5 stem>_frame<frame:05d>.csv``) or a pattern
    with ``{frame}`` (also ``{row}``, ``{time}``), e.g. ``"csv/f{frame:04d}.csv"``.
    ``frames``: image frame indices to export (default: all completed rows).
    Columns: ``x, y, u, v, ut, vt, exx, eyy, exy, zncc, status`` then any other stored field;
    missing fields and NaN are empty cells. With ``comment`` a first line
    ``# torch_stsdic ... frame=<f> time=<t>`` precedes the header line.
    """
    p = Path(path_h5)
    out = os.fspath(out_dir_or_pattern)
    written: list[Path] = []
    with open_results(p) as f:
        all_frames = f["frames"][()]
        times = f["times"][()]
        completed = f["completed"][()]
        if frames is None:
            rows = np.flatnonzero(completed).tolist()
        else:
            wanted = [frames] if isinstance(frames, (int, np.integer)) else list(frames)
            rows = []
            for fr in wanted:
                hit = np.flatnonzero(all_frames == int(fr))
                if not hit.size:
                    raise KeyError(f"frame {fr} is not in {p} (frames {all_frames.tolist()})")
                rows.append(int(hit[0]))
        names = field_names(f)
        columns = list(CSV_COLUMNS) + [n for n in names if n not in CSV_COLUMNS]
        pts = f["points"][()]
        n_p = len(pts)
        is_pattern = "{" in out
        if not is_pattern:
            Path(out).mkdir(parents=True, exist_ok=True)
        fixed = {"x": _fmt(pts[:, 0], "%.10g"), "y": _fmt(pts[:, 1], "%.10g")}
        empty = np.full(n_p, "", dtype=object)
        seen: set[Path] = set()
        for r in rows:
            fr, t = int(all_frames[r]), float(times[r])
            if is_pattern:
                target = Path(out.format(frame=fr, row=r, time=t))
            else:
                target = Path(out) / f"{p.stem}_frame{fr:05d}.csv"
            if target in seen:
                raise ValueError(f"output pattern {out!r} gives the same file {target} twice")
            seen.add(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            cols = []
            for c in columns:
                if c in fixed:
                    cols.append(fixed[c])
                elif c in names:
                    a = f[c][r]
                    cols.append(_fmt(a, "%d" if a.dtype.kind in "iu" else "%.9g"))
                else:
                    cols.append(empty)
            with open(target, "w", encoding="utf-8", newline="") as fh:
                if comment:
                    fh.write(
                        f"# torch_stsdic results {p.name}: frame={fr} time={t!r} row={r} "
                        f"completed={bool(completed[r])}\n"
                    )
                fh.write(",".join(columns) + "\n")
                for line in zip(*cols):
                    fh.write(",".join(line) + "\n")
            written.append(target)
    return written
