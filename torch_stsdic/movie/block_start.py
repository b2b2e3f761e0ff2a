"""Where a block's carried rows start, beyond the carry's own prediction
(:meth:`~torch_stsdic.movie.carry.Carry.predict`, :func:`~torch_stsdic.movie.block.solve_block`):
each row's window velocity with the shake's slope over its own frames
(:func:`window_shake`), and, in a classical block without a shared motion, every target's
common move measured first at a few pilot points (:func:`pilot_shift`)."""

from __future__ import annotations

from typing import Any

import torch

from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.choices import masked_groups
from torch_stsdic.movie.frames import window_half_widths

#: a :class:`~torch_stsdic.movie.block.Block` (not imported: the block imports this module)
Block = Any

__all__ = ["pilot_shift", "window_shake", "PILOT_POINTS", "PILOT_MIN"]

#: points a target whose carried rows a classical block solves first (:func:`pilot_shift`)
PILOT_POINTS = 48
#: trusted pilot rows a target needs for its common shift (fewer: none)
PILOT_MIN = 8


def pilot_shift(blk: Block, init: torch.Tensor, rows: torch.Tensor) -> torch.Tensor | None:
    """A classical block without a shared motion (a plain classical run, the measuring pass
    that finds the shared motion): ``PILOT_POINTS`` points spread over the POIs are solved
    first at every target from their carried guesses ``init`` (B*N, P) (the rows ``rows``
    (B*N,) bool that start from them), and every other carried row of the target starts
    moved by the median of their solutions minus their guesses (with ``PILOT_MIN`` trusted
    pilots): a specimen that shakes moves each frame by the shake, which the carried
    velocity does not predict (hourglass: the carry missed by 0.38 px, median; 0.03-0.09
    px once each frame's common move is taken out). Returns the pilot rows (solved and
    kept; the caller solves the others), None where the POIs are too few to spare them."""
    run = blk.run
    b, n, dev = blk.b, blk.n, run.device
    if n < 8 * PILOT_POINTS:
        return None
    pts = torch.linspace(0, n - 1, PILOT_POINTS, device=dev).round().long()
    cand = (torch.arange(b, device=dev)[:, None] * n + pts[None]).reshape(-1)
    on = rows[cand]  # (B * PILOT_POINTS,) the pilots that start carried
    if masked_groups(dev):  # every candidate, those not carried masked (no read; with
        # fewer than PILOT_MIN no target's shift is taken: the same rows as none at all)
        slot, sel = torch.arange(cand.numel(), device=dev), cand  # (slot: among cand)
        sol = blk.solve_masked(sel, init[sel], on)
        blk.keep(sel, sol, only_better=False, where=on)
    else:
        slot = torch.nonzero(on).flatten()  # (one read)
        sel = cand[slot]
        if sel.numel() < PILOT_MIN:
            return None
        sol = blk.solve(sel, init[sel])
        blk.keep(sel, sol, only_better=False)
    iu, iv = run.names.index("u"), run.names.index("v")
    su, sv = sol.param_names.index("u"), sol.param_names.index("v")
    good = (sol.status <= USABLE) & (sol.zncc.to(run.dtype) >= run.lost_zncc) & on[slot]
    moved = torch.stack([sol.params[:, su] - init[sel, iu], sol.params[:, sv] - init[sel, iv]],
                        1).to(run.dtype)
    # (B, PILOT_POINTS, 2) each target's pilots' moves, NaN where not trusted or not carried
    per = torch.full((b * PILOT_POINTS, 2), float("nan"), dtype=run.dtype, device=dev)
    per[slot] = torch.where(good.unsqueeze(1), moved, float("nan"))
    per = per.view(b, PILOT_POINTS, 2)
    enough = torch.isfinite(per[..., 0]).sum(1) >= PILOT_MIN  # (B,)
    shift = torch.where(enough.unsqueeze(1), per.nanmedian(1).values.nan_to_num(0.0), 0.0)
    pilot = torch.zeros_like(rows)
    pilot[sel] = on[slot]
    rest = rows & ~pilot
    step = shift.repeat_interleave(n, 0)  # (B*N, 2)
    init[:, iu] += torch.where(rest, step[:, 0], 0.0).to(init)
    init[:, iv] += torch.where(rest, step[:, 1], 0.0).to(init)
    return pilot


def window_shake(blk: Block, init: torch.Tensor, rows: torch.Tensor,
                  shake_vel: torch.Tensor) -> None:
    """The carried ut, vt of ``rows`` ((B*N,) bool) in ``init`` (B*N, P) with the shared
    motion's slope over the carry's window (``shake_vel`` (B*N, 2)) replaced by its slope
    over each row's own window (half-width ``blk.window_m``, the run's m where None): a
    window's velocity holds the shake's slope over its frames, which changes from window to
    window (hourglass: the carried ut missed the next block's by 0.035 px per frame,
    median)."""
    run = blk.run
    iu, iv = run.names.index("ut"), run.names.index("vt")
    wm = blk.window_m
    # the half-widths the rows take, or on a GPU every one, masked (m = 0 has no slope)
    for m in ([run.m] if wm is None else window_half_widths(wm, rows, run.m)):
        sel = rows if wm is None else rows & (wm == m)
        slope = blk.shared_slope(int(m))
        if slope is None:
            continue
        d = torch.where(sel.unsqueeze(1), slope.to(init) - shake_vel.to(init), 0.0)
        init[:, iu] += d[:, 0]
        init[:, iv] += d[:, 1]
