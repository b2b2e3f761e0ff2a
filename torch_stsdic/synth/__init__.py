"""Synthetic speckle images with exactly known motion (for testing and benchmarking DIC).

The speckle pattern is a sum of Gaussian spots on a constant background. Frames are rendered
*analytically*: no image is ever interpolated. For a motion ``U(X, t)`` each spot centre ``c``
moves to ``c' = c + U(c, t)`` and its shape is mapped by the local deformation gradient
``F = I + grad U(c, t)``::

    I(x) = background + sum_k a_k * exp(-|F_k^{-1} (x - c'_k)|^2 / (2 r_k^2))

This is exact for affine motion (translation, homogeneous strain) and a close approximation
(error of second order in the spot size) for smooth non-uniform fields. Every pixel value is the
*mean of I over the pixel area* (pixel ``(row i, col j)`` is the unit square centred on
``(x, y) = (j, i)``): the integral along x is done exactly with ``erf`` and, where ``F F^T`` is
diagonal (no motion, translation, normal strain without shear/rotation), along y too; otherwise
along y by Gauss-Legendre quadrature (``quadrature`` nodes per pixel, default 4; error
< 1e-6 grey levels for spots with r >= 1.2 px). The pixel integration is part of the known
truth. Spots are truncated at ``cutoff`` = 6 standard deviations (relative error ~1e-8).

Conventions: x = column (right), y = row (down), pixel centres at integer coordinates, 0-based;
``u`` along x, ``v`` along y. Motion is Lagrangian: ``g_t(X + U(X, t)) = f(X)``, where ``X`` are
coordinates of the undeformed pattern. Intensities are grey levels on an 8-bit scale (0..255),
stored as float64 (see :func:`quantize` for integer images).

Typical use::

    pattern = make_speckle((301, 301), seed=0)
    motion = Translation(ut=1 / 20)                     # u = t / 20 px, the paper's test
    times = torch.arange(1.0, 10.0)
    ref, frames = render_series(pattern, (301, 301), motion, times, noise_sigma=5.0, seed=1)
    truth = ground_truth(motion, points, times)         # dict of (T, N) tensors

Modules: :mod:`.pattern` (speckle), :mod:`.motion` (exact motions), :mod:`.render`
(rendering, noise, series, ground truth).
"""

from torch_stsdic.synth.motion import (
    MOTION_FAMILIES,
    Custom,
    HomogeneousStrain,
    Jump,
    Motion,
    QuadraticInTime,
    RigidJitter,
    Rotation,
    Sinusoidal,
    Sum,
    Translation,
    motion_family,
)
from torch_stsdic.synth.pattern import SpecklePattern, make_speckle
from torch_stsdic.synth.render import (
    Movie,
    add_noise,
    ground_truth,
    iter_series,
    quantize,
    render,
    render_series,
    synthetic_images,
    synthetic_movie,
)

__all__ = [
    "SpecklePattern",
    "make_speckle",
    "Motion",
    "MOTION_FAMILIES",
    "motion_family",
    "Translation",
    "HomogeneousStrain",
    "QuadraticInTime",
    "Rotation",
    "RigidJitter",
    "Sinusoidal",
    "Jump",
    "Custom",
    "Sum",
    "render",
    "add_noise",
    "quantize",
    "render_series",
    "iter_series",
    "ground_truth",
    "Movie",
    "synthetic_movie",
    "synthetic_images",
]
