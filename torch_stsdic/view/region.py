"""The region a run measures, drawn in ``stsdic view FRAMES...``: a box (``--roi``) and
polygons (the region, and holes left out), saved as the mask image ``--mask`` reads.

Rule (:func:`rasterise`): a pixel (x = column, y = row, its centre at integer coordinates) is
in the mask when it lies in a region polygon - or there is no region polygon - and in no
hole polygon; a polygon holds the pixels inside it and those its outline passes through
(Pillow's ``ImageDraw.polygon`` with an outline), so a region's outline is measured and a
hole's outline is left out. The page snaps every vertex to a pixel centre, so that a
polygon typed by hand with the same vertices gives the same mask.
"""

from __future__ import annotations

import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Region", "rasterise", "run_command"]

#: most vertices a polygon may have, most polygons a region may have (a request is refused
#: beyond: the page never sends that many)
MAX_VERTICES, MAX_POLYGONS = 10_000, 200


@dataclass
class Region:
    """What the page drew: ``roi`` (x0, y0, x1, y1) px inclusive or None; ``regions`` and
    ``holes``: polygons, each (K, 2) vertices (x, y) px, K >= 3."""

    roi: tuple[int, int, int, int] | None = None
    regions: list[np.ndarray] = field(default_factory=list)
    holes: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def from_json(cls, data: Mapping[str, Any], shape: tuple[int, int]) -> Region:
        """The page's request (``{"roi": [x0, y0, x1, y1] | null, "polygons": [{"kind":
        "region" | "hole", "points": [[x, y], ...]}]}``), checked against the (H, W) image:
        ValueError (one line) for anything malformed. Vertices are rounded to pixel centres
        and the box to whole pixels, clipped to the image."""
        h, w = shape
        if not isinstance(data, Mapping):
            raise ValueError("expected a JSON object")
        roi = data.get("roi")
        box = None
        if roi is not None:
            if not (isinstance(roi, Sequence) and len(roi) == 4
                    and all(isinstance(v, (int, float)) and np.isfinite(v) for v in roi)):
                raise ValueError("roi: expected [x0, y0, x1, y1]")
            x0, x1 = sorted((int(round(roi[0])), int(round(roi[2]))))
            y0, y1 = sorted((int(round(roi[1])), int(round(roi[3]))))
            x0, x1 = max(0, x0), min(w - 1, x1)
            y0, y1 = max(0, y0), min(h - 1, y1)
            if x1 <= x0 or y1 <= y0:
                raise ValueError("roi: the box is empty inside the image")
            box = (x0, y0, x1, y1)
        polys = data.get("polygons") or []
        if not isinstance(polys, Sequence) or len(polys) > MAX_POLYGONS:
            raise ValueError(f"polygons: expected a list of at most {MAX_POLYGONS}")
        out = cls(roi=box)
        for i, poly in enumerate(polys):
            if not isinstance(poly, Mapping) or poly.get("kind") not in ("region", "hole"):
                raise ValueError(f"polygon {i}: expected kind 'region' or 'hole'")
            try:
                pts = np.asarray(poly.get("points"), dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"polygon {i}: points must be [[x, y], ...]") from None
            if pts.ndim != 2 or pts.shape[1] != 2 or not 3 <= len(pts) <= MAX_VERTICES \
                    or not np.isfinite(pts).all():
                raise ValueError(f"polygon {i}: expected 3 to {MAX_VERTICES} finite [x, y]")
            pts = np.round(pts)
            (out.regions if poly["kind"] == "region" else out.holes).append(pts)
        return out

    @property
    def has_mask(self) -> bool:
        """Whether there are polygons (else the box alone says it: no mask file)."""
        return bool(self.regions or self.holes)


def rasterise(region: Region, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool mask of ``region``'s polygons (the rule in the module's docstring); the
    box is not part of it (it goes to ``--roi``)."""
    from PIL import Image, ImageDraw

    h, w = shape
    img = Image.new("L", (w, h), 0 if region.regions else 1)
    draw = ImageDraw.Draw(img)
    for fill, polys in ((1, region.regions), (0, region.holes)):
        for pts in polys:
            draw.polygon([(float(x), float(y)) for x, y in pts], fill=fill, outline=fill)
    return np.asarray(img, dtype=np.uint8) > 0


def save_mask(mask: np.ndarray, path: Path) -> None:
    """``mask`` as an 8-bit PNG (255 = measure, 0 = leave out), written whole or not at all."""
    from PIL import Image

    from torch_stsdic.io.run_record import written_atomically

    path.parent.mkdir(parents=True, exist_ok=True)
    with written_atomically(path) as tmp:
        Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(tmp, format="PNG")


def run_command(inputs: Sequence[str], roi: Sequence[int] | None, mask: str | None,
                out: str = "result.h5", options: Sequence[str] = ()) -> str:
    """The ``stsdic run`` command line measuring ``inputs`` inside ``roi`` and ``mask``
    (with ``options``, e.g. ``["--step", "5"]``)."""
    words = ["stsdic", "run", *inputs, *options]
    if roi is not None:
        words += ["--roi", *(str(int(v)) for v in roi)]
    if mask is not None:
        words += ["--mask", mask]
    words += ["--out", out]
    return shlex.join(words)
