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

from .frames import FrameCache, window_frames
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


class _Block:
    """The rows (target frame x POI, row = target * N + point) of one block being solved:
    parameters relative to the current reference, ZNCC, status, iterations."""

    def __init__(self, run: BlockContext, ks: list[int], ref: Reference) -> None:
        self.run, self.ks, self.ref = run, ks, ref
        dev = run.device
        self.k = torch.tensor(ks, dtype=torch.long, device=dev)
        win = self.windows(run.m)
        self.needed = torch.unique(win)  # sorted; only the windows' frames
        self.raw, self.img = run.cache.load(self.needed.tolist())
        ref.ensure(run.cache)
        self.b, self.n = len(ks), ref.points.shape[0]
        self.pts = ref.points.repeat(self.b, 1)  # (B*N, 2)
        self.fidx, self.dt = self.frames_of(win)
        rows, p_count = self.b * self.n, len(run.names)
        self.params = torch.full((rows, p_count), float("nan"), dtype=run.dtype, device=dev)
        self.zncc = torch.full((rows,), float("nan"), dtype=run.dtype, device=dev)
        self.status = torch.full((rows,), int(Status.NOT_COMPUTED), dtype=torch.int8,
                                 device=dev)
        self.iters = torch.zeros(rows, dtype=torch.int32, device=dev)

    def windows(self, m: int) -> torch.Tensor:
        """(B, 2m+1) series frames of every target's window, shifted (not shrunk) at the
        ends of the series."""
        return window_frames(self.k, m, self.run.n_series)

    def frames_of(self, win: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per row: indices into the loaded frames (B*N, T) and dt (B*N, T)."""
        run = self.run
        fidx = torch.searchsorted(self.needed, win).repeat_interleave(self.n, 0)
        dt = (run.ts[win] - run.ts[self.k].unsqueeze(1)).to(run.dtype)
        return fidx, dt.repeat_interleave(self.n, 0)

    def solve(self, idx: torch.Tensor, init: torch.Tensor | None) -> WindowSolution:
        ref = self.ref
        return self.run.solver.solve(
            ref.img, self.img, self.pts[idx], self.dt[idx], frame_index=self.fidx[idx],
            init=init, ref_pixels=ref.raw.unsqueeze(0), frame_pixels=self.raw,
        )

    def keep(self, idx: torch.Tensor, sol: WindowSolution, only_better: bool) -> None:
        """Store ``sol`` at rows ``idx`` (with ``only_better``: where it is usable and the
        stored result is not, or its ZNCC is higher)."""
        self.iters[idx] += sol.iterations
        take = torch.ones_like(idx, dtype=torch.bool)
        if only_better:
            new_ok = sol.status <= USABLE
            old_ok = self.status[idx] <= USABLE
            take = new_ok & (~old_ok | (sol.zncc.to(self.run.dtype) > self.zncc[idx]))
            take |= self.status[idx] == int(Status.NOT_COMPUTED)  # a reason beats none
        r = idx[take]
        self.params[r] = sol.params[take].to(self.run.dtype)
        self.zncc[r] = sol.zncc[take].to(self.run.dtype)
        self.status[r] = sol.status[take]

    def lost(self) -> torch.Tensor:
        """(B*N,) bool: rows without a trustworthy solution (not converged, or a ZNCC below
        ``lost_zncc``), other than those that cannot be solved at all (LOW_TEXTURE)."""
        st = self.status
        return (
            (st == int(Status.MAX_ITER)) | (st == int(Status.DIVERGED))
            | (st == int(Status.OUTSIDE)) | (st == int(Status.NOT_COMPUTED))
            | ((st <= USABLE) & ~(self.zncc >= self.run.lost_zncc))
        )

    def init_rows(self, values: dict[str, torch.Tensor]) -> torch.Tensor:
        """(R, P) initial parameters from relative values by name (missing ones zero)."""
        some = next(iter(values.values()))
        return torch.stack([values[nm] if nm in values else torch.zeros_like(some)
                            for nm in self.run.names], 1)

    def rescue(self, carry: Carry | None, carried: torch.Tensor) -> tuple[int, int, int]:
        """Lost rows, target by target in time order: start again from the solution of the
        previous target of the block (same point) moved on by its velocity, then, where
        still lost, from FFT cross-correlation; keep the better result. ``carried``: rows
        that started from the carried guess. Returns the rows restarted from a neighbour
        target, by FFT, and by FFT after a carried start."""
        run, n = self.run, self.n
        names = run.names
        from_prev = by_fft = redone = 0
        for j in range(self.b):
            rows = torch.arange(j * n, (j + 1) * n, device=run.device)
            if j > 0:
                prev = rows - n
                cand = self.lost()[rows] & (self.status[prev] <= USABLE) & ~self.lost()[prev]
                if bool(cand.any()):
                    r, pr = rows[cand], prev[cand]
                    d = (run.ts[self.k[j]] - run.ts[self.k[j - 1]]).to(run.dtype)
                    vals = {nm: self.params[pr, i] for i, nm in enumerate(names)}
                    vel_u, vel_v = self._velocity(j, cand, carry)
                    vals["u"] = vals["u"] + vel_u * d
                    vals["v"] = vals["v"] + vel_v * d
                    init = self.init_rows(vals)
                    ok = torch.isfinite(init).all(1)
                    if bool(ok.any()):
                        self.keep(r[ok], self.solve(r[ok], init[ok]), only_better=True)
                        from_prev += int(ok.sum())
            r = rows[self.lost()[rows]]
            if r.numel():
                self.keep(r, self.solve(r, None), only_better=True)
                by_fft += int(r.numel())
                redone += int(carried[r].sum())
        return from_prev, by_fft, redone

    def _velocity(self, j: int, cand: torch.Tensor, carry: Carry | None):
        """Velocity (u, v) of target j-1 for the rows ``cand`` of a target: the measured
        ut, vt, else the finite difference to target j-2 (or the carried row)."""
        run, n = self.run, self.n
        names = run.names
        prev = torch.arange((j - 1) * n, j * n, device=run.device)[cand]
        if "ut" in names:
            return self.params[prev, names.index("ut")], self.params[prev, names.index("vt")]
        iu, iv = names.index("u"), names.index("v")
        if j >= 2:
            pp = prev - n
            span = (run.ts[self.k[j - 1]] - run.ts[self.k[j - 2]]).to(run.dtype)
            du = (self.params[prev, iu] - self.params[pp, iu]) / span
            dv = (self.params[prev, iv] - self.params[pp, iv]) / span
        elif carry is not None:
            du, dv = carry.vel_u[cand], carry.vel_v[cand]
        else:
            du = dv = torch.zeros_like(self.params[prev, iu])
        return torch.nan_to_num(du), torch.nan_to_num(dv)


def solve_block(run: BlockContext, ks: list[int], ref: Reference, carry: Carry | None):
    """Solve all POIs of target frames ``ks`` (B,) in one batched solve, then rescue lost
    rows (from the previous target of the block, then by FFT cross-correlation).

    Returns a dict of (B, N) tensors: total parameters by name, "zncc", "status",
    "iterations"."""
    blk = _Block(run, ks, ref)
    b, n, dev = blk.b, blk.n, run.device
    rows = b * n
    if carry is None:
        carried = torch.zeros(rows, dtype=torch.bool, device=dev)
    else:
        pred = to_relative(carry.predict(run.ts[blk.k].to(run.dtype)), ref.acc)
        init = blk.init_rows({nm: v.reshape(-1) for nm, v in pred.items()})
        carried = carry.valid.repeat(b) & torch.isfinite(init).all(1)
    idx_c = torch.nonzero(carried).flatten()
    if idx_c.numel():
        blk.keep(idx_c, blk.solve(idx_c, init[idx_c]), only_better=False)
    from_prev, by_fft, redone = blk.rescue(carry, carried)
    run.stats["rescued_rows"] = run.stats.get("rescued_rows", 0) + from_prev
    run.stats["fft_rows"] += by_fft
    run.stats["redone_rows"] += redone
    rel = {nm: blk.params[:, j].reshape(b, n) for j, nm in enumerate(run.names)}
    out = to_total(rel, ref.acc)
    out["zncc"] = blk.zncc.reshape(b, n)
    out["status"] = blk.status.reshape(b, n)
    out["iterations"] = blk.iters.reshape(b, n)
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
