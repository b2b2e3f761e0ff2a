"""The per-row inputs of a solve, checked and brought to one form: every row's frame times
(N, T), frame indices (N, T) and reference index (N,), its known motion (N, T, 2), and where
the rows' windows differ in length, the frames each row uses (its first ``count``; the later
columns padding).

:meth:`~torch_stsdic.core.solver.SubsetSolver.solve` passes every call through here; the
checks read host facts only (shapes, kinds), never the device."""

from __future__ import annotations

import torch

from torch_stsdic.core.shape import ShapeFunction
from torch_stsdic.kernels.ic_step import frames_in_use

__all__ = ["active_rows", "checked_centres", "expand_init", "frame_counts", "per_point",
           "per_point_motion"]


def frame_counts(count, points: torch.Tensor, init, mixed: bool, formulation: str
                 ) -> torch.Tensor:
    """A solve's ``frame_count`` (N,) checked: integers, one a row, with an ``init`` (the FFT
    guess reads whole windows) and a formulation that takes windows of mixed length
    (``mixed``: :meth:`~torch_stsdic.core.solver.SubsetSolver.mixed_windows`; its name
    ``formulation`` for the message). Returns it as int64 on the points' device."""
    count = torch.as_tensor(count)
    n = points.shape[0]
    if tuple(count.shape) != (n,) or count.is_floating_point() or count.is_complex():
        raise ValueError(f"frame_count must be (N,) = ({n},) integers, got "
                         f"{tuple(count.shape)} {count.dtype}")
    if init is None:
        raise ValueError("frame_count (windows of mixed length) needs init: the FFT "
                         "initial guess reads whole windows")
    if not mixed:
        raise ValueError(f"frame_count (windows of mixed length) needs the joint "
                         f"inverse-compositional formulation; {formulation!r} takes one "
                         f"window length a call")
    return count.to(device=points.device, dtype=torch.int64)


def active_rows(active, points: torch.Tensor, init, capacity: int | None = None
                ) -> torch.Tensor | None:
    """A solve's ``active`` (:meth:`~torch_stsdic.core.solver.SubsetSolver.solve`) checked:
    (N,) bool, with an ``init`` (the FFT guess chooses its own rows), and its ``capacity``
    (a positive int, with ``active``). Returns it on the points' device (None: None)."""
    if capacity is not None and (active is None or isinstance(capacity, bool)
                                 or not isinstance(capacity, int) or capacity < 1):
        raise ValueError(f"capacity must be a positive int with active rows, got "
                         f"{capacity!r}" + ("" if active is not None else " without active"))
    if active is None:
        return None
    active = torch.as_tensor(active)
    n = points.shape[0]
    if tuple(active.shape) != (n,) or active.dtype != torch.bool:
        raise ValueError(f"active must be (N,) = ({n},) bool, got {tuple(active.shape)} "
                         f"{active.dtype}")
    if init is None:
        raise ValueError("active (rows to solve) needs init: the FFT initial guess chooses "
                         "its own rows")
    return active.to(points.device)


def checked_centres(centres, points: torch.Tensor
                    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """A solve's off-centre subsets ``centres`` checked: (N, 2) like ``points``. Returns them
    on the points' device and dtype and (N, 1) bool where they are off the points (None,
    None: none)."""
    if centres is None:
        return None, None
    centres = torch.as_tensor(centres).to(device=points.device, dtype=points.dtype)
    if tuple(centres.shape) != tuple(points.shape):
        raise ValueError(f"centres must be (N, 2) like points {tuple(points.shape)}, "
                         f"got {tuple(centres.shape)}")
    return centres, (centres != points).any(1, keepdim=True)


def per_point(points: torch.Tensor, dt: torch.Tensor, frame_index: torch.Tensor | None,
              ref_index: torch.Tensor | None, count: torch.Tensor | None = None):
    """Each POI's frame times (N, T) in the points' dtype, frame indices (N, T) (default
    0..T-1) and reference index (N,) (default 0), on the points' device; with ``count`` (N,)
    (:func:`frame_counts`) each row's padding columns set to time 0 in its first frame (not
    read by the kernels; harmless to whatever reads every column)."""
    n, device = points.shape[0], points.device
    dt = dt.to(device=device, dtype=points.dtype)
    t_count = dt.shape[-1]
    dt = dt.expand(n, t_count) if dt.dim() == 1 else dt
    if frame_index is None:
        frame_index = torch.arange(t_count, device=device)
    frame_index = frame_index.to(device).long().expand(n, t_count)
    if count is not None:
        use = frames_in_use(count, t_count)
        dt = torch.where(use, dt, 0.0)
        frame_index = torch.where(use, frame_index, frame_index[:, :1])
    if ref_index is None:
        return dt, frame_index, torch.zeros(n, dtype=torch.long, device=device)
    return dt, frame_index, ref_index.to(device).long().expand(n)


def per_point_motion(motion: torch.Tensor | None, n: int, t_count: int,
                     points: torch.Tensor) -> torch.Tensor | None:
    """Each POI's known motion (N, T, 2) from (T, 2) or (N, T, 2), in the points' dtype
    (None: none). Its values are the caller's to check (every solve of a run passes here)."""
    if motion is None:
        return None
    motion = torch.as_tensor(motion).detach().to(device=points.device, dtype=points.dtype)
    if motion.dim() == 2:
        motion = motion.unsqueeze(0).expand(n, -1, -1)
    if tuple(motion.shape) != (n, t_count, 2):
        raise ValueError(f"motion must be (T, 2) or (N, T, 2) = ({n}, {t_count}, 2), got "
                         f"{tuple(motion.shape)}")
    return motion.contiguous()


def expand_init(p0: torch.Tensor, shape: ShapeFunction, full: ShapeFunction) -> torch.Tensor:
    """Map a short initial guess ((N,2) u,v; (N,4) u,v,ut,vt; or the full/spatial parameter
    set of the other shape variant) onto ``shape``'s parameters."""
    n = p0.shape[0]
    out = torch.zeros(n, shape.n_params, dtype=p0.dtype, device=p0.device)
    names = shape.param_names
    if p0.shape[1] in (2, 4):
        src = ("u", "v", "ut", "vt")[: p0.shape[1]]
    elif p0.shape[1] == full.n_params:
        src = full.param_names
    elif p0.shape[1] == full.spatial().n_params:
        src = full.spatial().param_names
    else:
        raise ValueError(
            f"init must be (N, 2) (u, v), (N, 4) (u, v, ut, vt) or (N, {shape.n_params}) "
            f"parameters {names}, got {tuple(p0.shape)}"
        )
    for j, nm in enumerate(src):
        if nm in names:
            out[:, names.index(nm)] = p0[:, j]
    return out
