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
from torch_stsdic.movie.frames import window_frames, window_half_widths

#: a :class:`~torch_stsdic.movie.block.Block` (not imported: the block imports this module)
Block = Any

__all__ = ["report_velocity", "target_slope", "CURVATURE_Z"]


#: standard errors of the shared motion's curvature over a shifted window (a window at the
#: movie's ends or next to a load step) above which its velocity at the target is taken
#: from the local quadratic, not the window's line (:func:`target_slope`)
CURVATURE_Z = 3.0
#: the same false-alarm rate (0.27 %) where the curvature is tested against the window's own
#: residuals: Student's t quantiles for 1 .. 20 degrees of freedom (a 5-frame window has 2:
#: 19.2, where 3 would pass one window in ten without a bend), scaled with CURVATURE_Z
_T_LIMITS = (235.78, 19.21, 9.22, 6.62, 5.51, 4.90, 4.53, 4.28, 4.09, 3.96, 3.85, 3.76, 3.69,
             3.64, 3.59, 3.54, 3.51, 3.48, 3.45, 3.42)


def _curvature_limit(dof: int | None) -> float:
    """The curvature's z limit: :data:`CURVATURE_Z` for a known noise (``dof`` None), else
    the t quantile of its false-alarm rate for ``dof`` residual degrees of freedom."""
    if dof is None:
        return CURVATURE_Z
    z = _T_LIMITS[dof - 1] if dof <= len(_T_LIMITS) else 3.0 * (1 + 10.0 / (4 * dof))
    return z * CURVATURE_Z / 3.0


def target_slope(g: torch.Tensor, dt: torch.Tensor, frame_var: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The shared motion's velocity at the target from its displacement ``g`` (..., T, 2)
    over a window's frame times ``dt`` (..., T; broadcast against g's leading dimensions):
    the least-squares line's slope, which is the derivative at the window's mean time;
    where the window is shifted (its mean time is not the target's: the movie's first and
    last frames, a load step) and the motion's curvature over it is significant (a local
    quadratic's ``c2`` beyond :data:`CURVATURE_Z` standard errors, or the t quantile of the
    same false-alarm rate where they come from the residuals), the quadratic's
    derivative at dt = 0 (an accelerating motion's line over frames 0..12 gives its
    velocity at frame 6 to frame 0). ``frame_var`` (...,): the variance of one frame's
    displacement about the motion (default: the quadratic's residuals, T >= 4).

    Returns (slope (..., 2), used (..., 2) bool: the quadratic's derivative taken, var
    (..., 2) its variance where taken, else 0)."""
    g = g.double()
    t = dt.to(torch.float64)  # the design depends on the times alone: made at their shape
    line = window_slope(g, t)
    n = t.shape[-1]
    zero = torch.zeros_like(line)
    shifted = t.mean(-1).abs() > 1e-9  # (t's leading shape)
    if n < 3 or (frame_var is None and n < 4):
        return line, torch.zeros_like(line, dtype=torch.bool), zero
    # the quadratic at every window, shifted or not (no host read of whether any is: a
    # centred window's is not used); inv_ex: a singular design (two distinct times) keeps
    # the line there instead of raising
    a = torch.stack([torch.ones_like(t), t, t * t], -1)  # (..., T, 3)
    inv, info = torch.linalg.inv_ex(a.transpose(-1, -2) @ a)  # (..., 3, 3)
    shifted = shifted & (info == 0)
    coef = inv @ (a.transpose(-1, -2) @ g)  # (..., 3, 2)
    if frame_var is None:
        fv = (g - a @ coef).square().sum(-2) / (n - 3)  # (..., 2) the residuals'
    else:
        fv = frame_var.to(torch.float64).unsqueeze(-1)
    z = coef[..., 2, :].abs() / (fv * inv[..., 2, 2].unsqueeze(-1)).sqrt().clamp(min=1e-30)
    used = shifted.unsqueeze(-1) & (z > _curvature_limit(None if frame_var is not None
                                                        else n - 3))
    slope = torch.where(used, coef[..., 1, :], line)
    var = torch.where(used, fv * inv[..., 1, 1].unsqueeze(-1), 0.0)
    return slope, used, var


def report_velocity(blk: Block, out: dict[str, torch.Tensor]) -> torch.Tensor | None:
    """The block's velocities ``out["ut"]``, ``out["vt"]`` ((B, N), as solved: ``s +
    beta_m``) in the reported terms (module docstring), in place; returns (B, N, 2) px^2
    per time unit^2 the variance this adds to them: the shorter slope's noise (``p se^2 /
    (2 sum dt^2)`` over its frames, ``p`` the kind's terms: the fitted displacement's mean
    variance over the sample points is ``p se^2``, of which the reference image's half is
    common to every frame and leaves a slope alone). Where the motion jumps
    (``run.velocity_segments``: :attr:`SharedMotion.jumps`) the slope's frames stay on
    the target's side of the jump (shifted, as windows are at load steps), at any window
    length. Where a window is shifted (the movie's ends, a load step) the shared motion's
    velocity is taken at the target, not at the window's mean time, where it bends
    significantly over the frames (:func:`target_slope`; a shaking specimen's from the
    row's own window, the jitter the noise). None (nothing changed) where nothing is."""
    run = blk.run
    shared = run.shared
    if shared is None or "ut" not in out:
        return None
    vm = shared.velocity_m
    vseg = run.velocity_segments
    b, n = out["ut"].shape
    se2 = torch.as_tensor(shared.se, dtype=torch.float64).nan_to_num(0.0).square()
    vel = torch.stack([out["ut"].reshape(-1), out["vt"].reshape(-1)], 1)  # (B*N, 2)
    var = torch.zeros(b * n, 2, dtype=torch.float64, device=vel.device)
    changed = False
    # the half-widths the rows take, or on a GPU every one, masked
    for m in window_half_widths(blk.m_used, blk.m_used > 0, run.m):
        m = int(m)
        own = blk.windows(m)  # (B, T) the rows' windows
        if vm is None or (vseg is None and m <= vm):
            # the window's own slope of the motion, at the target where the window is shifted
            if run.segments is None and all(m <= k <= run.n_series - 1 - m for k in blk.ks):
                continue  # every window centred on its target (told without a host read)
            dt = (run.ts[own] - run.ts[blk.k].unsqueeze(1)).double()
            g = shared.displacement(blk.ref.points, own.reshape(-1)).view(
                b, own.shape[1], n, 2).transpose(1, 2)  # (B, N, T, 2)
            slope, used, add = target_slope(g, dt.unsqueeze(1))
            sel = (blk.m_used == m).unsqueeze(1) & used.reshape(-1, 2)
            vel += torch.where(sel, (slope.reshape(-1, 2)
                                     - blk.shared_slope(m).double()).to(vel), 0.0)
            var += torch.where(sel, add.reshape(-1, 2).to(var), 0.0)
            changed = True
            continue
        mv = min(m, int(vm))
        # (B, T) the slope's frames: 2 vm + 1 about the target, within its side of any jump
        win = (blk.windows(mv) if vseg is None
               else window_frames(blk.k, mv, run.n_series, vseg.to(blk.k.device)))
        dt = (run.ts[win] - run.ts[blk.k].unsqueeze(1)).double()
        differs = ((win != own).any(1) if m <= vm
                   else torch.ones(b, dtype=torch.bool, device=vel.device))
        g = shared.displacement(blk.ref.points, win.reshape(-1)).view(
            b, win.shape[1], n, 2).transpose(1, 2)  # (B, N, T, 2)
        dc = dt - dt.mean(1, keepdim=True)
        frame = 0.5 * shared.terms * se2.to(dt.device)[win].mean(1)  # (B,) a frame's share
        short, used, qvar = target_slope(g, dt.unsqueeze(1), frame.unsqueeze(1))
        if vseg is not None:  # the target's velocity at the movie's ends only (a load
            # state's own frames shifted by a jump: the motion is a line there, and a
            # false alarm of the 5-frame quadratic costs more than it mends)
            ends = window_frames(blk.k, mv, run.n_series, None)
            at_end = (run.ts[ends] - run.ts[blk.k].unsqueeze(1)).double().mean(1).abs() > 1e-9
            keep = at_end.view(b, 1, 1)
            short = torch.where(used & ~keep, window_slope(g, dt.unsqueeze(1).to(g)), short)
            qvar = torch.where(used & ~keep, 0.0, qvar)
            used = used & keep
        noise = (frame / dc.square().sum(1).clamp(min=1e-30)).view(b, 1, 1)  # (B, 1, 1)
        noise = torch.where(used, qvar, noise)  # (B, N, 2)
        sel = ((blk.m_used == m) & differs.repeat_interleave(n)).unsqueeze(1)
        vel += torch.where(sel, (short.reshape(-1, 2)
                                 - blk.shared_slope(m).double()).to(vel), 0.0)
        var += torch.where(sel, noise.reshape(-1, 2).to(var), 0.0)
        changed = True
    if not changed:
        return None
    out["ut"], out["vt"] = vel[:, 0].reshape(b, n), vel[:, 1].reshape(b, n)
    return var.view(b, n, 2)
