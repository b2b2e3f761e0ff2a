"""What every formulation shares: the subset geometry, the per-point reference data, and the
interface of one linearised model.

A *formulation* is one way of writing the STS-DIC criterion and its Gauss-Newton
linearisation (the paper's Eqs. 12-18). It provides, for a batch of points of interest (POIs):

* :meth:`Formulation.prepare`: per-point work done once before iterating (e.g. the
  inverse-compositional Hessian from the reference, factored);
* :meth:`Formulation.step`: one Gauss-Newton increment ``dp`` at parameters ``p``, the mean
  ZNCC over the window's frames and the "warped subset left the image" flag;
* :meth:`Formulation.update`: the new parameters from ``p`` and ``dp`` (additive or
  compositional);
* :meth:`Formulation.stationarity`: the condition ``F(p, theta) = 0`` that the iteration
  converges to, written with differentiable torch operations (used by
  :mod:`torch_stsdic.nn` for the implicit gradient);
* :meth:`Formulation.jacobian` / :meth:`Formulation.hessian` where the Jacobian depends only on
  the reference (used by :mod:`torch_stsdic.core.noise` for the covariance).

The solver (:mod:`torch_stsdic.core.solver`) iterates whichever formulation the configuration
names; a new formulation is one new module here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.shape import AffineShape, QuadraticShape, ShapeFunction
from torch_stsdic.core.window import BUILT_IN_WINDOWS, SubsetWindow, weight_stats
from torch_stsdic.kernels.ic_step import frames_in_use

__all__ = ["Geometry", "SubsetData", "Formulation", "reference_subsets", "wsum"]


def wsum(x: Tensor, w: Tensor) -> Tensor:
    """Window-weighted sum over the last (subset) dimension: one matrix-vector product."""
    return x @ w


@dataclass
class Geometry:
    """The subset geometry shared by all POIs of a solve.

    Attributes:
        shape: the shape function (with or without temporal terms).
        spatial: (S, Ks) spatial basis at the subset offsets.
        dx, dy: (S,) subset pixel offsets from the POI, px.
        w: (S,) window weights.
        znssd: criterion is ZNSSD (else SSD).
        half: subset half size, px.
    """

    shape: ShapeFunction
    spatial: Tensor
    dx: Tensor
    dy: Tensor
    w: Tensor
    znssd: bool
    half: float
    #: (sum w, w binary, effective pixels) on the host, worked out once by the window
    #: (:meth:`~torch_stsdic.core.window.SubsetWindow.weight_stats`: read without waiting
    #: for the device); None: from ``w``
    w_stats: tuple[float, bool, float] | None = None
    #: the host facts the tensors are made from where they alone make them (a built-in
    #: window and shape: their kinds and settings, the dtype and device): equal keys, equal
    #: tensors (compared without reading the device); None: compare the tensors
    key: tuple | None = None

    @classmethod
    def make(cls, shape: ShapeFunction, window: SubsetWindow, criterion: str,
             dtype: torch.dtype, device: torch.device | str | None) -> Geometry:
        """The geometry of ``window``'s subset for ``shape`` in ``dtype`` on ``device``."""
        offsets, weights = window.offsets_and_weights(dtype, device)
        spatial = shape.spatial()
        known = type(window) in BUILT_IN_WINDOWS and type(spatial) in (AffineShape,
                                                                       QuadraticShape)
        key = ((type(window).__name__, window.extra_repr(), type(spatial).__name__,
                tuple(spatial.terms), str(dtype), str(torch.device(device or "cpu")))
               if known else None)
        return cls(shape=shape, spatial=shape.spatial_basis(offsets[:, 0], offsets[:, 1]),
                   dx=offsets[:, 0], dy=offsets[:, 1], w=weights,
                   znssd=criterion == "znssd", half=float(window.half),
                   w_stats=window.weight_stats(), key=key)

    def _stats(self) -> tuple[float, bool, float]:
        return self.w_stats if self.w_stats is not None else weight_stats(self.w)

    @property
    def w_sum(self) -> float:
        """The sum of the window's weights (a host number)."""
        return self._stats()[0]

    @property
    def w_binary(self) -> bool:
        """Whether the weights are 0 or 1 (their squares are themselves)."""
        return self._stats()[1]

    @property
    def w_effective(self) -> float:
        """``(sum w)^2 / sum w^2`` (:func:`~torch_stsdic.core.window.effective_pixels`)."""
        return self._stats()[2]

    @property
    def ks(self) -> int:
        """Ks, spatial basis terms per displacement component."""
        return self.spatial.shape[1]

    @property
    def k(self) -> int:
        """K, basis terms per component (spatial + temporal)."""
        return self.shape.n_basis

    def centred(self, x: Tensor) -> Tensor:
        """x minus its window-weighted subset mean (ZNSSD), or x itself (SSD)."""
        if not self.znssd:
            return x
        return x - (wsum(x, self.w) / self.w.sum()).unsqueeze(-1)


@dataclass
class SubsetData:
    """Per-point data of one batch of POIs (rows can be dropped as points finish).

    Attributes:
        px, py: (N, 1) POI positions, px.
        dt: (N, T) frame times minus the time the results refer to.
        fidx: (N, T) frame indices into the prepared frames.
        ft: (N, S) reference subset (grey levels), zero-mean for ZNSSD.
        fnorm: (N,) weighted norm of ``ft``.
        gx, gy: (N, S) reference gradient, grey levels per px.
        hinv: (N, P, P) float64 inverse of a Hessian prepared once (inverse compositional).
        gram: (N, P', P') the centred moments of the reference gradients
            (:func:`~torch_stsdic.core.formulations.joint_ic.centred_gram`) when computed once for
            both the Hessian and the uncertainty.
        motion: (N, T, 2) known displacement (u, v) px of every frame added to the warp (the
            specimen's shared motion, :mod:`torch_stsdic.core.shared_motion`), or None.
        texture: (N,) window-weighted mean of ``gx^2 + gy^2`` (the texture test) when computed
            with the subsets, or None.
        ref_rows: (N,) where the rows share their points' reference subsets: the row of
            ``ft``, ``gx``, ``gy`` (then (R, S), one per distinct point) of every row, read
            through it by the native joint IC kernel (:meth:`direct`: one row each); None:
            row i is row i.
        count: (N,) int64 each row's frames in use where the rows' windows differ in length:
            its first ``count[i]`` columns of ``dt``, ``fidx`` and ``motion`` (the later
            columns padding: dt 0, left out of every sum over the frames; :meth:`in_use`);
            None: all T.
    """

    px: Tensor
    py: Tensor
    dt: Tensor
    fidx: Tensor
    ft: Tensor
    fnorm: Tensor
    gx: Tensor
    gy: Tensor
    hinv: Tensor | None = None
    gram: Tensor | None = None
    motion: Tensor | None = None
    texture: Tensor | None = None
    ref_rows: Tensor | None = None
    count: Tensor | None = None

    def in_use(self) -> Tensor | None:
        """(N, T) bool the frames in use (:attr:`count`), or None: all of them."""
        return None if self.count is None else frames_in_use(self.count, self.dt.shape[1])

    def take(self, idx: Tensor) -> SubsetData:
        """The rows ``idx`` (index or boolean mask)."""
        shared = () if self.ref_rows is None else ("ft", "gx", "gy")
        return SubsetData(**{
            k: (v[idx] if isinstance(v, Tensor) and k not in shared else v)
            for k, v in self.__dict__.items()
        })

    def direct(self) -> SubsetData:
        """These rows with reference subsets of their own (``ref_rows`` None)."""
        if self.ref_rows is None:
            return self
        r = self.ref_rows
        return SubsetData(**{**self.__dict__, "ft": self.ft[r], "gx": self.gx[r],
                             "gy": self.gy[r], "ref_rows": None})


def reference_subsets(geo: Geometry, ref: BSplineImage, pts: Tensor, ridx: Tensor,
                      dt: Tensor, fidx: Tensor, motion: Tensor | None = None,
                      inside: bool = False) -> SubsetData:
    """Sample the reference subsets of POIs ``pts`` (N, 2) in reference images ``ridx`` (N,)
    with gradients and normalise them for the criterion. Differentiable in the reference
    pixels and the points when they require gradients (the native kernels are then skipped).
    ``inside``: the caller knows every POI is a whole pixel whose subset lies inside the
    image (:meth:`BSplineImage.sample_subsets`: not read)."""
    px, py = pts[:, 0:1], pts[:, 1:2]
    f, gx, gy = ref.sample_subsets(px, py, geo.dx, geo.dy, frame=ridx, inside=inside)
    # sums row by row (a matrix-vector product rounds a row by where it lies in the batch):
    # a point's subset is the same whatever points it is solved with, in a resumed run too
    ft = f - ((f * geo.w).sum(-1) / geo.w.sum()).unsqueeze(-1) if geo.znssd else f
    fnorm = (ft * ft).mul_(geo.w).sum(-1).sqrt()  # the same rounding, one temporary fewer
    return SubsetData(px=px, py=py, dt=dt, fidx=fidx, ft=ft, fnorm=fnorm, gx=gx, gy=gy,
                      motion=motion)


class Formulation:
    """One linearised STS-DIC model (see the module docstring). Subclasses set ``name`` and
    implement :meth:`step` and :meth:`stationarity`."""

    name: str = ""
    #: the Jacobian comes from the reference (inverse compositional): the Hessian is prepared
    #: once per point and :meth:`jacobian` / :meth:`hessian` exist
    inverse_compositional: bool = False

    def __init__(self, free: Tensor | None = None) -> None:
        #: (P,) bool mask of the parameters this stage solves for (None: all)
        self.free = free

    def __repr__(self) -> str:
        return f"{type(self).__name__}(free={None if self.free is None else self.free.tolist()})"

    def prepare(self, geo: Geometry, data: SubsetData) -> Tensor:
        """Per-point work before iterating; returns an (N,) bool mask of points that cannot be
        solved (singular system). Default: nothing to do."""
        return torch.zeros(data.dt.shape[0], dtype=torch.bool, device=data.dt.device)

    def step(self, geo: Geometry, frames: BSplineImage, data: SubsetData, p: Tensor,
             work: int, sel: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """One Gauss-Newton increment: ``dp`` (N, P) (zero outside ``free``), the mean ZNCC
        over the frames (N,) and the outside flag (N,) (a warped subset left the image).
        ``work`` is the number of samples per iteration of the whole solve (decides
        torch.compile); ``sel`` the rows of ``data`` that ``p``'s rows belong to (None: all)."""
        raise NotImplementedError

    def update(self, geo: Geometry, p: Tensor, dp: Tensor) -> Tensor:
        """New parameters after the increment ``dp`` (forward additive by default)."""
        return p + dp

    def stationarity(self, geo: Geometry, frames: BSplineImage, data: SubsetData,
                     p: Tensor) -> Tensor:
        """F(p, theta) (N, P): zero exactly where this formulation's Gauss-Newton increment is
        zero. Differentiable in ``p``, the frames' pixels and the reference data."""
        raise NotImplementedError

    def uses_fused_kernel(self, frames: BSplineImage, data: SubsetData, p: Tensor) -> bool:
        """Whether :meth:`step` takes a fused native path that indexes ``data`` rows through
        ``sel`` (so the solver need not copy the data of finished rows)."""
        return False

    def gives_frame_rhs(self, frames: BSplineImage, data: SubsetData, p: Tensor) -> bool:
        """Whether :meth:`step` (with ``sel``) fills a ``frame_rhs`` (M, T, 2 Ks + 1) float64
        buffer with each frame's own spatial right-hand side (a classical step's), then the
        frame's ZNCC."""
        return False
