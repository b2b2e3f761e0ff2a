"""The solution of a batch of windows (:class:`WindowSolution`: parameters, ZNCC, status,
predicted std per POI) and the classical steps a solve may report beside it
(:func:`classical_step_info`, :func:`packed_classical_step`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from torch_stsdic.core.gauss_newton import classical_step_columns
from torch_stsdic.core.status import Status

__all__ = ["WindowSolution", "classical_step_info", "packed_classical_step"]


def _parameter(name: str, doc: str) -> property:
    """A read-only property: the (N,) column of parameter ``name``."""
    return property(lambda self: self.param(name), doc=doc)


@dataclass
class WindowSolution:
    """Per-POI results of one window, at the expansion time ``time``.

    Attributes:
        points: (N, 2) POI positions (x, y), px.
        params: (N, P) shape-function parameters (names in ``param_names``); NaN rows where
            ``status`` is DIVERGED, OUTSIDE, LOW_TEXTURE or NOT_COMPUTED.
        zncc: (N,) zero-normalised cross-correlation, mean over the window's frames.
        status: (N,) int8 :class:`Status` codes.
        iterations: (N,) Gauss-Newton iterations used (all stages).
        time: the time the displacement refers to (frame units unless times were given).
        std: (N, P) predicted standard deviation of every parameter (same units), from the
            image noise estimated from the point's own residual and its subset's gradients
            (:mod:`torch_stsdic.core.uncertainty`); NaN where the point failed.
        sigma: (N,) that noise, grey levels: the std of one reference/frame difference.
        info: extras: "stages" (the Gauss-Newton stages run), "first_stage_params" (N, P)
            (the joint solution before the "auto" refinement), "initial_params" (N, P),
            "initial_guess" (how the POIs started: "method" fft / seeded / given, with the
            number of seeds and FFT points and "fft_s", the seconds spent in FFT).
    """

    points: torch.Tensor
    params: torch.Tensor
    param_names: tuple[str, ...]
    zncc: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    time: float | torch.Tensor = 0.0
    info: dict = field(default_factory=dict)
    std: torch.Tensor | None = None
    sigma: torch.Tensor | None = None

    def param(self, name: str) -> torch.Tensor:
        """(N,) parameter ``name`` (e.g. "ux"; NaN if the shape function has none)."""
        if name in self.param_names:
            return self.params[:, self.param_names.index(name)]
        return torch.full_like(self.params[:, 0], float("nan"))

    u = _parameter("u", "(N,) displacement along x, px.")
    v = _parameter("v", "(N,) displacement along y, px.")
    ut = _parameter("ut", "(N,) velocity du/dt, px per frame (NaN for m = 0: one frame has no "
                    "velocity).")
    vt = _parameter("vt", "(N,) velocity dv/dt, px per frame (NaN for m = 0).")

    def std_of(self, name: str) -> torch.Tensor:
        """(N,) predicted standard deviation of parameter ``name`` (NaN if not estimated)."""
        if self.std is None or name not in self.param_names:
            return torch.full_like(self.params[:, 0], float("nan"))
        return self.std[:, self.param_names.index(name)]

    @property
    def ok(self) -> torch.Tensor:
        """(N,) bool: converged (or stopped at max_iter with usable parameters)."""
        return self.status <= int(Status.MAX_ITER)

    def __len__(self) -> int:
        return self.points.shape[0]

    def rows(self, idx: torch.Tensor) -> WindowSolution:
        """The solution of rows ``idx`` ((R,) long or (N,) bool): every per-row tensor,
        ``info``'s included, taken at those rows."""
        n = len(self)

        def take(a):
            return a[idx] if isinstance(a, torch.Tensor) and a.ndim and a.shape[0] == n else a
        return dataclasses.replace(
            self, points=self.points[idx], params=self.params[idx], zncc=self.zncc[idx],
            status=self.status[idx], iterations=self.iterations[idx], time=take(self.time),
            std=take(self.std), sigma=take(self.sigma),
            info={k: take(v) for k, v in self.info.items()})


#: info keys of a classical step's columns (gauss_newton.classical_step_columns)
_CSTEP_KEYS = {"params": "classical_step", "size": "classical_step_size",
               "zncc": "classical_step_zncc", "sigma": "classical_step_sigma",
               "std": "classical_step_std"}


def classical_step_info(packed: torch.Tensor) -> dict[str, torch.Tensor]:
    """The info entries of classical steps ``packed`` (N, 4 Ks + 3) (one value per row for
    the size, ZNCC and sigma)."""
    cols = classical_step_columns((packed.shape[1] - 3) // 4)
    return {key: packed[:, cols[part]].squeeze(1) if part in ("size", "zncc", "sigma")
            else packed[:, cols[part]] for part, key in _CSTEP_KEYS.items()}


def packed_classical_step(info: dict) -> torch.Tensor:
    """The classical steps of a solution's ``info`` as one (N, 4 Ks + 3) tensor."""
    return torch.cat([info[key].reshape(info[key].shape[0], -1)
                      for key in _CSTEP_KEYS.values()], 1)
