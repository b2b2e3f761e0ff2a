"""The shared motion's part of a reported velocity.

A window that carries the shared motion (:mod:`torch_stsdic.core.shared_motion`) solves for
the specimen's own slope ``s`` over its frames plus the shared motion's least-squares slope
``beta_m`` over the same frames (``ut = s + beta_m``: the line through the total motion).
Where the shared motion is carried because it bends over the windows (a relaxing stretch, a
decelerating drift: :meth:`SharedMotion.departure`), ``beta_m`` over a long window misses
its velocity at the target by its curvature (a relaxing stretch's first frames: 9e-3 px per
frame at m = 6); the windows themselves grow there, as the specimen's own motion is a line.
Such a run reports ``s`` plus the shared motion's slope over ``SharedMotion.velocity_m``
frames about the target (2: five frames; :meth:`SharedMotion.velocity_window`), its noise
added to ut_std, vt_std; a shaking
specimen's (carried for its jitter: ``velocity_m`` None) keeps the window's slope, which
averages the shake. Where such a motion jumps (a load step of a uniform strain, which the
fit takes: :attr:`SharedMotion.jumps`), the slope's frames stay on the target's side of the
jump, at any window length (a window's own slope across it gave the velocity the jump over
its frames: the steps render's velocity error 6.05e-3 -> 0.76e-3 px/frame). The carry's
velocity is read in the same terms (:meth:`~torch_stsdic.movie.carry.Carry.shared_slope`,
given ``run.velocity_segments``)."""

from __future__ import annotations

from typing import Any

import torch

from torch_stsdic.core.shared_motion import window_slope
from torch_stsdic.movie.frames import half_widths, window_frames

#: a :class:`~torch_stsdic.movie.block.Block` (not imported: the block imports this module)
Block = Any

__all__ = ["report_velocity"]


def report_velocity(blk: Block, out: dict[str, torch.Tensor]) -> torch.Tensor | None:
    """The block's velocities ``out["ut"]``, ``out["vt"]`` ((B, N), as solved: ``s +
    beta_m``) in the reported terms (module docstring), in place; returns (B, N, 2) px^2
    per time unit^2 the variance this adds to them: the shorter slope's noise (``p se^2 /
    (2 sum dt^2)`` over its frames, ``p`` the kind's terms: the fitted displacement's mean
    variance over the sample points is ``p se^2``, of which the reference image's half is
    common to every frame and leaves a slope alone). Where the motion jumps
    (``run.velocity_segments``: :attr:`SharedMotion.jumps`) the slope's frames stay on
    the target's side of the jump (shifted, as windows are at load steps), at any window
    length. None (nothing changed) where the run's shared motion keeps the windows'
    slopes."""
    run = blk.run
    shared = run.shared
    vm = None if shared is None else shared.velocity_m
    vseg = run.velocity_segments
    if vm is None or "ut" not in out or (run.m <= vm and vseg is None):
        return None
    b, n = out["ut"].shape
    se2 = torch.as_tensor(shared.se, dtype=torch.float64).nan_to_num(0.0).square()
    vel = torch.stack([out["ut"].reshape(-1), out["vt"].reshape(-1)], 1)  # (B*N, 2)
    var = torch.zeros(b * n, 2, dtype=torch.float64, device=vel.device)
    for m in half_widths(blk.m_used, blk.m_used > 0, run.m):
        mv = min(int(m), int(vm))
        if vseg is None and m <= vm:
            continue
        # (B, T) the slope's frames: 2 vm + 1 about the target, within its side of any jump
        win = (blk.windows(mv) if vseg is None
               else window_frames(blk.k, mv, run.n_series, vseg.to(blk.k.device)))
        dt = (run.ts[win] - run.ts[blk.k].unsqueeze(1)).double()
        if vseg is None:
            short = blk.shared_slope(mv)  # (B*N, 2)
            differs = torch.ones(b, dtype=torch.bool, device=vel.device)
        else:
            g = shared.displacement(blk.ref.points, win.reshape(-1)).view(
                b, win.shape[1], n, 2).transpose(1, 2)  # (B, N, T, 2)
            short = window_slope(g, dt.to(g.dtype).unsqueeze(1)).reshape(-1, 2)
            differs = (win != blk.windows(int(m))).any(1) if m <= vm else torch.ones(
                b, dtype=torch.bool, device=vel.device)
        dc = dt - dt.mean(1, keepdim=True)
        noise = (0.5 * shared.terms * se2.to(dt.device)[win].mean(1)
                 / dc.square().sum(1).clamp(min=1e-30))  # (B,)
        sel = ((blk.m_used == m) & differs.repeat_interleave(n)).unsqueeze(1)
        vel += torch.where(sel, (short - blk.shared_slope(int(m))).to(vel), 0.0)
        var += torch.where(sel, noise.repeat_interleave(n).unsqueeze(1).to(var), 0.0)
    out["ut"], out["vt"] = vel[:, 0].reshape(b, n), vel[:, 1].reshape(b, n)
    return var.view(b, n, 2)
