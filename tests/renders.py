"""Renders the tests share: a 121 px speckle (seed 4) moved by a motion, noise on every
image (sigma 2, seed 5), the reference first (tests/ on the path, as ``repo_scripts``)."""

from __future__ import annotations

import torch

from torch_stsdic.synth import Motion, make_speckle, render_series


def speckle_movie(motion: Motion, times: torch.Tensor, size: int = 121) -> torch.Tensor:
    """(T, size, size) the reference (at ``times[0]``, unmoved) and the frames of
    ``motion`` at ``times[1:]``."""
    ref, frames = render_series(make_speckle((size, size), seed=4), (size, size), motion,
                                times[1:], noise_sigma=2.0, seed=5)
    return torch.cat([ref[None], frames])
