"""Where the specimen is: the pixels of the reference image that carry a speckle pattern, and
the points of interest whose subsets lie on it.

A pixel carries speckle where the grey levels around it vary: its local standard deviation
(over a ``window`` px square) is at least ``contrast`` times the image's speckle contrast (the
95th percentile of the local standard deviations, so a specimen that fills a small part of the
image still sets it). Saturated background (all pixels at the sensor's maximum), dark holes
and backgrounds, and featureless areas fall below it; so do the flat parts of partly
saturated areas. A point is on the specimen when at least ``min_share`` of its subset's
pixels are. Used by :func:`torch_stsdic.movie.plan.plan_run` for the default grid, so that a
run with defaults on a real movie neither solves nor fits the background (the shared motion,
the neighbour checks)."""

from __future__ import annotations

from dataclasses import dataclass

import kornia
import torch

__all__ = ["speckle_mask", "on_specimen", "SpecimenReport", "CONTRAST", "MIN_SHARE"]

#: a pixel carries speckle where its local std is at least this share of the image's speckle
#: contrast (the hole of DIC Challenge sample 12 reads 0.03-0.05, its speckle 0.3-1; the
#: saturated background of the muDIC hourglass 0)
CONTRAST = 0.15
#: a point is on the specimen when at least this share of its subset's pixels carry speckle
MIN_SHARE = 0.97


@dataclass
class SpecimenReport:
    """What :func:`on_specimen` left out."""

    points: int  # points tested
    kept: int
    speckle_share: float  # share of the image's pixels that carry speckle

    @property
    def left_out(self) -> int:
        return self.points - self.kept

    def summary(self) -> dict:
        return {"points": self.points, "kept": self.kept, "left_out": self.left_out,
                "speckle_share": round(self.speckle_share, 4)}


def _integral(x: torch.Tensor, size: int) -> torch.Tensor:
    """(H + size, W + size) float64 the integral image (kornia's) of ``x`` (H, W) reflected
    by ``size // 2`` px at its borders (as kornia's box blur pads), a zero row and column
    first: the sum over any ``size`` x ``size`` square is four of its entries."""
    r = size // 2
    pad = torch.nn.functional.pad(x.double()[None, None], (r, r, r, r), mode="reflect")[0, 0]
    return torch.nn.functional.pad(kornia.enhance.integral_image(pad), (1, 0, 1, 0))


def _box_at(x: torch.Tensor, size: int, iy: torch.Tensor, ix: torch.Tensor) -> torch.Tensor:
    """Mean over a ``size`` x ``size`` square (``size`` odd) around the pixels (``iy``,
    ``ix``) (broadcast together) of ``x`` (reflected borders; kornia's box blur, by an
    integral image: O(1) a pixel at any size)."""
    s = _integral(x, size)
    return (s[iy + size, ix + size] - s[iy, ix + size] - s[iy + size, ix]
            + s[iy, ix]) / float(size * size)


def _box(x: torch.Tensor, size: int) -> torch.Tensor:
    """:func:`_box_at` every pixel of ``x`` (H, W)."""
    h, w = x.shape
    return _box_at(x, size, torch.arange(h)[:, None], torch.arange(w)[None, :])


def _square(op, mask: torch.Tensor, size: int) -> torch.Tensor:
    """kornia's morphology ``op`` (dilation or erosion) of ``mask`` (1, 1, H, W) with a flat
    ``size`` x ``size`` square, as a row then a column (the same max / min over the square's
    pixels inside the image: 2 size shifts instead of size^2; a float32 0/1 mask: exact)."""
    one = mask.new_ones(1, size)
    return op(op(mask, one), one.T)


def speckle_mask(image: torch.Tensor, window: int = 7, contrast: float = CONTRAST,
                 fill: int = 5) -> torch.Tensor:
    """(H, W) bool: the pixels of ``image`` (H, W) that carry a speckle pattern: textured
    within ``window`` px, then closed (kornia's morphology) with a ``2 fill + 1`` px square,
    so that the flat inside of a large speckle counts as speckle while a background or a hole
    larger than that stays out, then eroded by half a window (the local std of a pixel next
    to a flat area already sees the speckle)."""
    img = torch.as_tensor(image).double()
    if img.dim() != 2:
        raise ValueError(f"image: expected (H, W), got {tuple(img.shape)}")
    window = max(3, int(window) | 1)
    mean = _box(img, window)
    std = (_box(img * img, window) - mean * mean).clamp(min=0).sqrt()
    flat = std.reshape(-1)
    sample = flat[:: max(1, flat.numel() // 200_000)]
    level = float(torch.quantile(sample, 0.95))
    if level <= 0:
        return torch.zeros_like(img, dtype=torch.bool)
    mask = (std >= contrast * level).float()[None, None]
    if fill > 0:  # closing: dilation, then erosion
        size = 2 * int(fill) + 1
        mask = _square(kornia.morphology.erosion,
                       _square(kornia.morphology.dilation, mask, size), size)
    # the local std reaches half a window into a flat neighbour: pull the edge back
    return _square(kornia.morphology.erosion, mask, window)[0, 0] > 0.5


def on_specimen(points: torch.Tensor, image: torch.Tensor, subset_size: int,
                min_share: float = MIN_SHARE) -> tuple[torch.Tensor, SpecimenReport]:
    """(N,) bool: the points (N, 2) x, y px whose subset has at least ``min_share`` of its
    pixels on speckle (:func:`speckle_mask` of the reference ``image``), and a report."""
    img = torch.as_tensor(image).double()
    mask = speckle_mask(img, fill=max(3, int(subset_size) // 3))
    pts = torch.as_tensor(points).double()
    h, w = img.shape
    ix = pts[:, 0].round().long().clamp(0, w - 1)
    iy = pts[:, 1].round().long().clamp(0, h - 1)
    keep = _box_at(mask.double(), int(subset_size) | 1, iy, ix) >= min_share
    rep = SpecimenReport(points=int(pts.shape[0]), kept=int(keep.sum()),
                         speckle_share=float(mask.double().mean()))
    return keep, rep
