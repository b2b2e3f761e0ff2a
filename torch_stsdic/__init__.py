"""torch_stsdic: short-time-series digital image correlation (STS-DIC) in PyTorch.

Main entry points: :class:`DICConfig`, :func:`solve_window` (one window of 2m+1 frames),
:func:`track` (a whole movie), :func:`load_series` (lazy image series) and the ``stsdic``
command. See the README for the conventions (x = column, y = row, g_t(x + U) = f(x)).
"""

from .config import DICConfig
from .interpolation import BSplineImage, bspline_prefilter
from .noise import estimate_noise_sigma, predicted_std
from .io import ImageSeries, InputError, ResultWriter, export_csv, load_series, read_results
from .series import (
    TrackResult,
    classical_smoothed,
    grid_points,
    smooth_in_time,
    temporal_smoothing,
    track,
)
from .shape import AffineShape, QuadraticShape, ShapeFunction, make_shape
from .solver import SubsetSolver, WindowSolution, solve_window
from .status import Status
from .strain import compute_strain
from .window import CircularWindow, GaussianWindow, SquareWindow, SubsetWindow, make_window

__version__ = "0.1.0"

__all__ = [
    "DICConfig",
    "BSplineImage",
    "bspline_prefilter",
    "ShapeFunction",
    "AffineShape",
    "QuadraticShape",
    "make_shape",
    "SubsetWindow",
    "SquareWindow",
    "CircularWindow",
    "GaussianWindow",
    "make_window",
    "SubsetSolver",
    "WindowSolution",
    "solve_window",
    "Status",
    "track",
    "TrackResult",
    "grid_points",
    "smooth_in_time",
    "temporal_smoothing",
    "classical_smoothed",
    "load_series",
    "ImageSeries",
    "InputError",
    "ResultWriter",
    "read_results",
    "export_csv",
    "compute_strain",
    "predicted_std",
    "estimate_noise_sigma",
]
