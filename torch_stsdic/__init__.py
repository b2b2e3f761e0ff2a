"""torch_stsdic: short-time-series digital image correlation (STS-DIC) in PyTorch."""

from .config import DICConfig
from .interpolation import BSplineImage, bspline_prefilter
from .shape import AffineShape, QuadraticShape, ShapeFunction, make_shape
from .solver import SubsetSolver, WindowSolution, solve_window
from .status import Status
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
]
