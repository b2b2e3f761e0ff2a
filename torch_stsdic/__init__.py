"""torch_stsdic: short-time-series digital image correlation (STS-DIC) in PyTorch.

Main entry points: :class:`DICConfig`, :func:`solve_window` (one window of 2m+1 frames),
:func:`track` (a whole movie), :func:`load_series` (lazy image series) and the ``stsdic``
command. See the README for the conventions (x = column, y = row, g_t(x + U) = f(x)).
"""

import os as _os

# OpenMP threads that spin while waiting make torch 10-100x slower as soon as another process
# competes for the cores (measured here: a 15-point Gauss-Newton step took 0.2 s instead of
# 2 ms with 2 threads on a busy 2-core machine). Passive waiting costs next to nothing when
# the machine is idle. This only takes effect if torch_stsdic is imported before torch (the
# `stsdic` command is). A CPU solve does not depend on it: it runs torch on one thread and its
# parallel work on the library's own pool, whose idle threads block (issue 46,
# kernels/native/rows.own_threads); it still spares torch code outside the solve.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from torch_stsdic.allocator import keep_freed_memory  # noqa: E402
from torch_stsdic.analysis.export import export_csv
from torch_stsdic.analysis.points import grid_points
from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.analysis.smoothing import smooth_in_time, temporal_smoothing
from torch_stsdic.analysis.strain import compute_strain
from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.interpolation import BSplineImage, bspline_prefilter
from torch_stsdic.core.noise import estimate_noise_sigma, predicted_std
from torch_stsdic.core.shape import AffineShape, QuadraticShape, ShapeFunction, make_shape
from torch_stsdic.core.solver import SubsetSolver, WindowSolution
from torch_stsdic.core.status import Status, usable
from torch_stsdic.core.window import (
    CircularWindow,
    GaussianWindow,
    SquareWindow,
    SubsetWindow,
    make_window,
)
from torch_stsdic.core.window_solve import solve_window
from torch_stsdic.io import ImageSeries, InputError, ResultWriter, load_series, read_results
from torch_stsdic.kernels.native import set_native
from torch_stsdic.movie.plan import RunPlan, plan_run
from torch_stsdic.movie.series import classical_smoothed, run_plan, series_template, track
from torch_stsdic.movie.sinks import HDF5Sink, MemorySink

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
    "usable",
    "track",
    "run_plan",
    "series_template",
    "plan_run",
    "RunPlan",
    "MemorySink",
    "HDF5Sink",
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
    "set_native",
    "keep_freed_memory",
]
