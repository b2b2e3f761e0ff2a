"""Gaussian image pyramids, built once per image and kept while the image is in use.

The coarse-to-fine search of the initial guess (:func:`~torch_stsdic.core.initial.coarse_to_fine`)
needs every image at 1/2, 1/4, ... resolution (kornia's ``pyrdown``: 5x5 Gaussian blur, then
decimation). A run asks for the same frames' pyramids again and again (the weak-peak rescue of
every block, the pre-passes); :class:`ImagePyramid` builds each level of one image on first use
and keeps it, and :class:`PyramidStack` serves the levels of a stack of frames (a block's, or
the reference) from their pyramids, stacking only the frames a search needs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

__all__ = ["ImagePyramid", "PyramidStack", "pyramid_dtype"]


def pyramid_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype pyramids are built in: float64 for float64 images, else float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


class ImagePyramid:
    """Gaussian pyramid of one image ``(H, W)``: level 0 the image (in :func:`pyramid_dtype`),
    level l the image halved l times by kornia's ``pyrdown``; each level built on first use.

    ``builds`` counts the ``pyrdown`` calls this pyramid made (one per level, ever), and
    ``on_build`` (if given) is called after each."""

    def __init__(self, image: torch.Tensor,
                 on_build: Callable[[], object] | None = None) -> None:
        if image.dim() != 2:
            raise ValueError(f"ImagePyramid: one (H, W) image, got {tuple(image.shape)}")
        self._levels = [image.to(pyramid_dtype(image.dtype))]
        self.builds = 0
        self._on_build = on_build

    def level(self, lev: int) -> torch.Tensor:
        """(H_l, W_l) level ``lev`` (0: the image)."""
        from kornia.geometry.transform import pyrdown

        while len(self._levels) <= lev:
            self._levels.append(pyrdown(self._levels[-1][None, None])[0, 0])
            self.builds += 1
            if self._on_build is not None:
                self._on_build()
        return self._levels[lev]

    @property
    def nbytes(self) -> int:
        """Bytes of the levels built beyond the image itself."""
        return sum(t.numel() * t.element_size() for t in self._levels[1:])


class PyramidStack:
    """The pyramids of a stack of images (one :class:`ImagePyramid` each, in stack order,
    e.g. the frames of a block, or the reference): :meth:`levels` stacks the levels of the
    frames a search reads."""

    def __init__(self, pyramids: Sequence[ImagePyramid]) -> None:
        self.pyramids = list(pyramids)

    @classmethod
    def of(cls, images: torch.Tensor) -> PyramidStack:
        """Fresh pyramids of ``images`` (F, H, W) or (H, W)."""
        images = images.unsqueeze(0) if images.dim() == 2 else images
        return cls([ImagePyramid(img) for img in images])

    def __len__(self) -> int:
        return len(self.pyramids)

    def levels(self, count: int, frames: torch.Tensor | None = None) -> list[torch.Tensor]:
        """[level 0, ..., level ``count``], each (len(frames), H_l, W_l): the levels of the
        images ``frames`` (indices into the stack, default all) stacked."""
        idx = range(len(self.pyramids)) if frames is None else frames.tolist()
        chosen = [self.pyramids[int(i)] for i in idx]
        return [torch.stack([p.level(lev) for p in chosen]) for lev in range(count + 1)]
