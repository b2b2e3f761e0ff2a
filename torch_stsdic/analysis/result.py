"""The result of tracking a movie: (F, N) fields of displacement, velocity and quality."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch

from torch_stsdic.analysis.strain import compute_strain
from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.core.status import Status

__all__ = ["TrackResult", "USABLE"]

USABLE = int(Status.MAX_ITER)  #: status <= USABLE: usable parameters


@dataclass
class TrackResult:
    """Displacement and velocity fields of a tracked movie.

    All displacements refer to the POIs ``points`` in the *first* reference image
    (Lagrangian), also after incremental reference updates.

    Attributes:
        points: (N, 2) POIs (x, y) in the reference image, px.
        frames: (F,) int64 target-frame indices into the series (ascending).
        times: (F,) float64 times of the target frames (series time unit).
        u, v: (F, N) displacement along x / y at the target frame's time, px.
        ut, vt: (F, N) velocity, px per time unit (NaN for classical DIC, m = 0).
        zncc: (F, N) zero-normalised cross-correlation (mean over the window's frames).
        status: (F, N) int8 :class:`~torch_stsdic.core.status.Status` codes.
        iterations: (F, N) int32 Gauss-Newton iterations (all stages, including a redo).
        gradients: name -> (F, N) displacement gradients ("ux", "uy", "vx", "vy"; with
            the quadratic shape also "uxx", ... relative to the current reference).
        reference_frames: (F,) int64 series index of the reference each row was measured
            against (-1: the initial reference was not a single frame).
        config: the :class:`DICConfig` used.
        m: (F, N) int8 half-width of the window each result was measured with (the run's
            ``config.m``, shorter where the model check found the motion not affine in time
            over the window, or where the point leaves the image within it; 0: classical,
            ut/vt NaN; -1: not solved).
        std: name -> (F, N) predicted standard deviation of "u", "v" (px) and "ut", "vt"
            (px per time unit) from the image noise and the subset's gradients
            (:mod:`torch_stsdic.core.uncertainty`); NaN where not solved.
        info: run details: "batch_frames", "blocks", "frames_read", "prefiltered",
            "max_cached_frames", "fft_rows", "redone_rows", "reference_updates", ...
    """

    points: torch.Tensor
    frames: torch.Tensor
    times: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    ut: torch.Tensor
    vt: torch.Tensor
    zncc: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    gradients: dict[str, torch.Tensor]
    reference_frames: torch.Tensor
    config: DICConfig
    info: dict[str, Any] = field(default_factory=dict)
    m: torch.Tensor | None = None
    std: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """F, the number of target frames."""
        return int(self.frames.shape[0])

    @property
    def n_points(self) -> int:
        """N, the number of POIs."""
        return int(self.points.shape[0])

    @property
    def ok(self) -> torch.Tensor:
        """(F, N) bool: usable results (CONVERGED or MAX_ITER)."""
        return self.status <= USABLE

    def field(self, name: str) -> torch.Tensor:
        """(F, N) values of a result field by its stored name: "u", "v", "ut", "vt", "zncc",
        "status", "iterations", "m", a gradient ("ux", ...) or a predicted std ("u_std",
        ...)."""
        if name in ("u", "v", "ut", "vt", "zncc", "status", "iterations"):
            return getattr(self, name)
        if name == "m" and self.m is not None:
            return self.m
        if name.endswith("_std") and name[:-4] in self.std:
            return self.std[name[:-4]]
        if name in self.gradients:
            return self.gradients[name]
        raise KeyError(f"no field {name!r} in this result")

    def row_of(self, frame: int) -> int:
        """Row holding series frame ``frame``."""
        hit = torch.nonzero(self.frames == int(frame)).flatten()
        if hit.numel() == 0:
            raise KeyError(f"frame {frame} is not a target frame of this result")
        return int(hit[0])

    def select(self, frames: list[int] | None = None, points: torch.Tensor | None = None
               ) -> TrackResult:
        """The rows of series ``frames`` (in that order; None: all) at ``points`` (POI
        indices; None: all), as a result of their own (the same tensors' entries, copied)."""
        rows = (slice(None) if frames is None
                else torch.as_tensor([self.row_of(k) for k in frames], dtype=torch.long))
        cols = slice(None) if points is None else torch.as_tensor(points, dtype=torch.long)

        def pick(a: torch.Tensor) -> torch.Tensor:
            return a[rows][:, cols]

        return dataclasses.replace(
            self, points=self.points[cols], frames=self.frames[rows], times=self.times[rows],
            u=pick(self.u), v=pick(self.v), ut=pick(self.ut), vt=pick(self.vt),
            zncc=pick(self.zncc), status=pick(self.status), iterations=pick(self.iterations),
            gradients={k: pick(a) for k, a in self.gradients.items()},
            reference_frames=self.reference_frames[rows], info=dict(self.info),
            m=None if self.m is None else pick(self.m),
            std={k: pick(a) for k, a in self.std.items()})

    @property
    def shared_motion(self) -> SharedMotion | None:
        """The run's shared motion (:mod:`torch_stsdic.core.shared_motion`): per series frame the
        specimen's affine motion (``.params`` (T_series, 6), ``.rotation``, ``.jitter()``,
        ``.applied``), or None when it was not measured."""
        rec = self.info.get("shared_motion")
        return None if rec is None else SharedMotion.from_summary(rec)

    def strain(self, window: int = 5, kind: str = "green", **kwargs: Any) -> dict[str, Any]:
        """Strain fields (F, N) by local plane fits (:func:`~torch_stsdic.analysis.strain.
        compute_strain`): ``exx, eyy, exy`` (+ ``*_rate`` per time unit when velocities
        exist). ``window``: grid points per side of the fit; ``kind``: "green" or "small"."""
        has_rate = bool(torch.isfinite(self.ut).any())
        return compute_strain(
            self.points, self.u, self.v, window=window, kind=kind, valid=self.ok,
            ut=self.ut if has_rate else None, vt=self.vt if has_rate else None, **kwargs,
        )

    def __repr__(self) -> str:
        return (
            f"<TrackResult {self.n_frames} frames x {self.n_points} points, "
            f"m={self.config.m}, ok={float(self.ok.float().mean()):.1%}>"
        )
