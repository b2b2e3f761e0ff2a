"""Solving one block of target frames: all POIs of several windows in one batched solve,
started from the carried guesses, with rescue of lost points.

A block is a few consecutive target frames of a movie. Every row (target frame x POI) starts
from the :class:`Carry` of the block before (the last stored row moved on by its velocity).
Rows that get lost (not converged, or ZNCC below ``lost_zncc``) are rescued in time order
from the solution of the previous target of the same block, then by FFT cross-correlation;
the better of the attempts is kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .frames import FrameCache
from .reference import Reference, to_relative, to_total
from .result import USABLE
from .solver import SubsetSolver, WindowSolution
from .status import Status

__all__ = ["BlockContext", "Carry", "solve_block", "rows_numpy", "make_carry"]


@dataclass
class Carry:
    """Last stored row (total quantities, float32-rounded) and the velocity to extrapolate."""

    t: float
    vals: dict[str, torch.Tensor]  # name -> (N,)
    vel_u: torch.Tensor
    vel_v: torch.Tensor
    valid: torch.Tensor  # (N,) bool

    def predict(self, tk: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted total parameters (B, N) at times ``tk`` (B,)."""
        d = (tk - self.t).unsqueeze(1)
        out = {k: v.unsqueeze(0).expand(tk.shape[0], -1) for k, v in self.vals.items()}
        out["u"] = self.vals["u"] + self.vel_u * d
        out["v"] = self.vals["v"] + self.vel_v * d
        return out



@dataclass
class BlockContext:
    solver: SubsetSolver
    cache: FrameCache
    ts: torch.Tensor  # (T_s,) series times, float64
    n_series: int
    m: int
    dtype: torch.dtype
    device: torch.device
    lost_zncc: float
    names: tuple[str, ...]  # parameter names of the run's shape
    stats: dict[str, int]


def solve_block(run: BlockContext, ks: list[int], ref: Reference, carry: Carry | None):
    """Solve all POIs of target frames ``ks`` (B,) in one batched solve.

    Returns a dict of (B, N) tensors: total parameters by name, "zncc", "status",
    "iterations"."""
    solver, dev = run.solver, run.device
    n_win = 2 * run.m + 1
    k = torch.tensor(ks, dtype=torch.long, device=dev)
    start = (k - run.m).clamp(0, run.n_series - n_win)  # shifted (not shrunk) at the ends
    win = start.unsqueeze(1) + torch.arange(n_win, device=dev)  # (B, T)
    needed = torch.unique(win)  # sorted; only the windows' frames (sparse targets: gaps)
    raw, img = run.cache.load(needed.tolist())
    ref.ensure(run.cache)
    b, n = len(ks), ref.points.shape[0]
    pts = ref.points.repeat(b, 1)  # (B*N, 2), row = target * N + point
    fidx = torch.searchsorted(needed, win).repeat_interleave(n, 0)
    dt = (run.ts[win] - run.ts[k].unsqueeze(1)).to(run.dtype).repeat_interleave(n, 0)
    names = run.names
    p_count = len(names)
    rows = b * n
    params = torch.full((rows, p_count), float("nan"), dtype=run.dtype, device=dev)
    zncc = torch.full((rows,), float("nan"), dtype=run.dtype, device=dev)
    status = torch.full((rows,), int(Status.NOT_COMPUTED), dtype=torch.int8, device=dev)
    iters = torch.zeros(rows, dtype=torch.int32, device=dev)
    ref_pix = ref.raw.unsqueeze(0)

    def solve(idx: torch.Tensor, init: torch.Tensor | None) -> WindowSolution:
        return solver.solve(
            ref.img, img, pts[idx], dt[idx], frame_index=fidx[idx], init=init,
            ref_pixels=ref_pix, frame_pixels=raw,
        )

    def put(idx: torch.Tensor, sol: WindowSolution) -> None:
        params[idx] = sol.params.to(run.dtype)
        zncc[idx] = sol.zncc.to(run.dtype)
        status[idx] = sol.status
        iters[idx] += sol.iterations

    if carry is None:
        carried = torch.zeros(rows, dtype=torch.bool, device=dev)
    else:
        pred = to_relative(carry.predict(run.ts[k].to(run.dtype)), ref.acc)
        init = torch.stack(
            [pred[nm].reshape(-1) if nm in pred else torch.zeros(rows, dtype=run.dtype,
                                                                 device=dev) for nm in names],
            1,
        )
        carried = carry.valid.repeat(b) & torch.isfinite(init).all(1)
    idx_c = torch.nonzero(carried).flatten()
    redo = idx_c[:0]
    if idx_c.numel():
        sol = solve(idx_c, init[idx_c])
        put(idx_c, sol)
        st = sol.status
        lost = (
            (st == int(Status.MAX_ITER)) | (st == int(Status.DIVERGED))
            | (st == int(Status.OUTSIDE))
            | ((st <= USABLE) & ~(sol.zncc >= run.lost_zncc))
        )
        redo = idx_c[lost]
    idx_f = torch.cat([torch.nonzero(~carried).flatten(), redo])
    if idx_f.numel():
        sol = solve(idx_f, None)
        nf = int((~carried).sum())
        first = idx_f[:nf]
        params[first] = sol.params[:nf].to(run.dtype)
        zncc[first] = sol.zncc[:nf].to(run.dtype)
        status[first] = sol.status[:nf]
        iters[first] += sol.iterations[:nf]
        if redo.numel():
            new_ok = sol.status[nf:] <= USABLE
            old_ok = status[redo] <= USABLE
            better = new_ok & (~old_ok | (sol.zncc[nf:].to(run.dtype) > zncc[redo]))
            iters[redo] += sol.iterations[nf:]
            r = redo[better]
            params[r] = sol.params[nf:][better].to(run.dtype)
            zncc[r] = sol.zncc[nf:][better].to(run.dtype)
            status[r] = sol.status[nf:][better]
    run.stats["fft_rows"] += int(idx_f.numel())
    run.stats["redone_rows"] += int(redo.numel())
    rel = {nm: params[:, j].reshape(b, n) for j, nm in enumerate(names)}
    out = to_total(rel, ref.acc)
    out["zncc"] = zncc.reshape(b, n)
    out["status"] = status.reshape(b, n)
    out["iterations"] = iters.reshape(b, n)
    return out



def rows_numpy(block: dict[str, torch.Tensor], fields: Sequence[str]) -> dict[str, np.ndarray]:
    """(B, N) numpy rows per field (float64; ut/vt NaN when absent)."""
    b, n = block["status"].shape
    out = {}
    for nm in fields:
        if nm in block:
            out[nm] = block[nm].detach().cpu().numpy()
        else:
            out[nm] = np.full((b, n), np.nan)
    out["status"] = out["status"].astype(np.int8)
    out["iterations"] = out["iterations"].astype(np.int64)
    return out



def make_carry(rows: dict[str, np.ndarray], times: np.ndarray, names, prev: Carry | None,
                dtype, device) -> Carry:
    """Carry from the last stored row (velocity from ut/vt, else from the last two rows)."""

    def col(nm: str, i: int = -1) -> torch.Tensor:
        return torch.from_numpy(rows[nm][i].astype(np.float64)).to(device=device, dtype=dtype)

    vals = {nm: col(nm) for nm in names}
    ok = torch.from_numpy(rows["status"][-1] <= USABLE).to(device)
    ok &= torch.isfinite(vals["u"]) & torch.isfinite(vals["v"])
    t_last = float(times[-1])
    if "ut" in names:
        vel_u, vel_v = vals["ut"], vals["vt"]
        ok &= torch.isfinite(vel_u) & torch.isfinite(vel_v)
    else:
        if len(times) >= 2:
            t_prev, u_prev, v_prev = float(times[-2]), col("u", -2), col("v", -2)
        elif prev is not None:
            t_prev, u_prev, v_prev = prev.t, prev.vals["u"], prev.vals["v"]
        else:
            t_prev, u_prev, v_prev = t_last, vals["u"], vals["v"]
        span = t_last - t_prev
        if span > 0:
            vel_u, vel_v = (vals["u"] - u_prev) / span, (vals["v"] - v_prev) / span
            fin = torch.isfinite(vel_u) & torch.isfinite(vel_v)
            vel_u = torch.where(fin, vel_u, torch.zeros_like(vel_u))
            vel_v = torch.where(fin, vel_v, torch.zeros_like(vel_v))
        else:
            vel_u, vel_v = torch.zeros_like(vals["u"]), torch.zeros_like(vals["v"])
    return Carry(t=t_last, vals=vals, vel_u=vel_u, vel_v=vel_v, valid=ok)
