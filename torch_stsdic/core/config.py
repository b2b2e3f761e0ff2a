"""DICConfig: every solver setting in one validated place."""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import torch

from torch_stsdic.core.shape import ShapeFunction
from torch_stsdic.core.window import SubsetWindow

__all__ = ["DICConfig", "FORMULATIONS", "FORMULATION_HELP", "CRITERIA", "INITIAL_GUESSES",
           "DEFAULT_MEMORY_MB", "GPU_BUDGET_MB", "gpu_budget_mb"]

#: MiB of working memory a batch takes where ``DICConfig.memory_mb`` is not given (on a GPU
#: at least :func:`gpu_budget_mb`; a value given is taken as given on every device)
DEFAULT_MEMORY_MB = 256.0

#: MiB a GPU gives at least to a block's frames and to each batch of a solve where
#: ``memory_mb`` is not given, within a tenth of the device's memory (:func:`gpu_budget_mb`):
#: there a block's launches, not its arithmetic, set the pace, and 256 MiB would hold 6 megapixel
#: frames or split a block's solve into batches of ~5,800 rows (a masked solve over every
#: row of a 32-target block of 10,000 POIs into 55 batches, each with its own launches)
GPU_BUDGET_MB = 2048.0

FORMULATIONS = ("auto", "joint", "average", "joint+average")
#: The one description of the formulations (DICConfig docs, CLI help, README).
FORMULATION_HELP = (
    "joint: sum over the window's frames of each frame's residual against the reference "
    "(inverse compositional); joint+average: joint, then the spatial unknowns refined on the "
    "paper's averaged image at the joint velocity; average: deprecated, runs as "
    "joint+average (the averaged image alone does not fix the velocity); auto: joint")
CRITERIA = ("znssd", "ssd")
INITIAL_GUESSES = ("auto", "fft", "seeded")


@dataclass
class DICConfig:
    """Settings of the subset / STS-DIC solver.

    Attributes:
        subset_size: odd subset width in px (default 21).
        m: half window: each solve uses 2m + 1 adjacent frames; m = 0 is classical DIC.
        shape: "affine" (u, ux, uy, ut, v, vx, vy, vt; the paper's Eq. 9) or "quadratic"
            (second-order spatial + linear temporal), or a ShapeFunction module.
        window: "square", "circular", "gaussian" or a SubsetWindow module.
        criterion: "znssd" (zero-normalised SSD, insensitive to intensity offset and scale)
            or "ssd" (the paper's Eq. 14).
        formulation: "joint" (sum over frames of each frame's residual against the reference,
            inverse compositional), "joint+average" (joint, then the spatial unknowns refined
            on the paper's averaged image, Eqs. 2 and 11, at the joint velocity) or "auto"
            (the default: "joint", the most accurate and the fastest; see the README).
            "average" (the paper's averaged image alone) is deprecated: its velocity does not
            converge (the Jacobian columns of ut, vt vanish at the solution; on real images
            it converged at 1.7 % of the points), so it runs as "joint+average" with a
            DeprecationWarning.
        interpolation: "cubic" or "quintic" B-spline.
        max_iter: Gauss-Newton iteration cap per stage.
        tol: convergence threshold in px: the largest displacement change of any subset pixel
            in any frame of the window caused by the last increment, or by the next one as
            predicted from the last two (linear convergence at the observed rate, taken as
            at least ``gauss_newton.RATE_FLOOR``): one increment fewer; the solution is then
            within about tol of the converged one (measured: 1.8e-4 px at most at 1e-4).
        search_radius: FFT cross-correlation search radius in px for the initial guess.
        initial_guess: how points without an initial guess start: "fft" (FFT
            cross-correlation at every POI), "seeded" (FFT only at one seed POI per
            ``seed_spacing`` cell; the others start from their seed's solution carried over
            by its displacement gradient, and fall back to FFT where that fails) or "auto"
            (the default: "seeded" when the POIs are dense, >= 4 per cell on average).
        seed_spacing: cell width in px for "seeded" (default: the subset size).
        texture_threshold: a subset whose mean squared intensity gradient is below
            ``texture_threshold * (image grey range)^2`` is flagged LOW_TEXTURE.
        max_displacement: a point whose displacement moves more than this (px) away from its
            initial guess is flagged DIVERGED (default: subset_size).
        batch_points: POIs solved together per batch (None: sized from ``memory_mb``).
        memory_mb: working-memory budget per batch in MiB (None: 256, and on a GPU at
            least :func:`gpu_budget_mb`, 2 GiB within a tenth of its memory, for a solve's
            batches and a block's frames: the same answers in fewer launches). A value given
            is taken as given on every device (a GPU shared with a training job).
        dtype: "float32", "float64" or None (None: the input's float dtype; float32 for integers).
    """

    subset_size: int = 21
    m: int = 2
    shape: str | ShapeFunction = "affine"
    window: str | SubsetWindow = "square"
    criterion: str = "znssd"
    formulation: str = "auto"
    interpolation: str = "cubic"
    max_iter: int = 50
    tol: float = 1e-4
    search_radius: int = 10
    initial_guess: str = "auto"
    seed_spacing: float | None = None
    texture_threshold: float = 1e-5
    max_displacement: float | None = None
    batch_points: int | None = None
    memory_mb: float | None = None
    dtype: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.formulation == "average":
            warnings.warn(
                'DICConfig.formulation="average" is deprecated: the averaged image alone does '
                "not determine the velocity and rarely converges on real images; running "
                '"joint+average" (joint, then refined on the averaged image)',
                DeprecationWarning, stacklevel=3)
            self.formulation = "joint+average"
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first bad setting."""

        def bad(name: str, msg: str) -> None:
            raise ValueError(f"DICConfig.{name}: {msg}, got {getattr(self, name)!r}")

        size = self.subset_size
        if not isinstance(size, int) or size < 5 or size % 2 == 0:
            bad("subset_size", "must be an odd integer >= 5")
        if not isinstance(self.m, int) or self.m < 0:
            bad("m", "must be an integer >= 0")
        if self.criterion not in CRITERIA:
            bad("criterion", f"must be one of {CRITERIA}")
        if self.formulation not in FORMULATIONS:
            bad("formulation", f"must be one of {FORMULATIONS}")
        if self.interpolation not in ("cubic", "quintic"):
            bad("interpolation", "must be 'cubic' or 'quintic'")
        if not isinstance(self.max_iter, int) or self.max_iter < 1:
            bad("max_iter", "must be an integer >= 1")
        if not (self.tol > 0):
            bad("tol", "must be > 0")
        if not isinstance(self.search_radius, int) or self.search_radius < 0:
            bad("search_radius", "must be an integer >= 0")
        if self.initial_guess not in INITIAL_GUESSES:
            bad("initial_guess", f"must be one of {INITIAL_GUESSES}")
        if self.seed_spacing is not None and not (self.seed_spacing >= 1):
            bad("seed_spacing", "must be >= 1 px or None")
        if self.memory_mb is not None and not (0 < self.memory_mb < math.inf):
            bad("memory_mb", "must be > 0 and finite, or None")
        if self.batch_points is not None and self.batch_points < 1:
            bad("batch_points", "must be >= 1 or None")
        if self.dtype not in (None, "float32", "float64"):
            bad("dtype", "must be None, 'float32' or 'float64'")
        if isinstance(self.shape, str) and self.shape not in ("affine", "quadratic"):
            bad("shape", "must be 'affine', 'quadratic' or a ShapeFunction")
        if isinstance(self.window, str) and self.window not in ("square", "circular", "gaussian"):
            bad("window", "must be 'square', 'circular', 'gaussian' or a SubsetWindow")

    @property
    def n_frames(self) -> int:
        """Frames per window, 2m + 1."""
        return 2 * self.m + 1

    @property
    def interpolation_order(self) -> int:
        return 3 if self.interpolation == "cubic" else 5

    @property
    def budget_mb(self) -> float:
        """MiB of working memory: ``memory_mb``, or :data:`DEFAULT_MEMORY_MB` where it is not
        given (there a GPU takes at least :func:`gpu_budget_mb` for a solve's batches and a
        block's frames)."""
        return DEFAULT_MEMORY_MB if self.memory_mb is None else float(self.memory_mb)

    @property
    def gpu_floor(self) -> bool:
        """Whether a GPU may take more than :attr:`budget_mb` (at least
        :func:`gpu_budget_mb` for a solve's batches, a block's frames and the FFT search):
        where ``memory_mb`` is not given; a budget given is kept to on every device."""
        return self.memory_mb is None

    def replace(self, **changes: Any) -> DICConfig:
        """A copy with some settings changed."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict (modules given as objects are stored by class name)."""
        d = dataclasses.asdict(self)
        for k in ("shape", "window"):
            v = getattr(self, k)
            if not isinstance(v, str):
                d[k] = type(v).__name__
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DICConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def gpu_budget_mb(device: Any, device_mb: float | None = None) -> float | None:
    """MiB a run on ``device`` gives at least to a block's frames and to each batch of a
    solve: :data:`GPU_BUDGET_MB` within a tenth of the device's memory (``device_mb`` MiB,
    read from the device where not given) on a CUDA device; None elsewhere (the CPU takes
    ``memory_mb`` as it is: its batches stay in its caches)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return None
    if device_mb is None:
        device_mb = _cuda_total_mb(dev.index if dev.index is not None
                                   else torch.cuda.current_device())
    return min(GPU_BUDGET_MB, 0.1 * float(device_mb))


@functools.cache
def _cuda_total_mb(index: int) -> float:
    return torch.cuda.get_device_properties(index).total_memory / 2**20
