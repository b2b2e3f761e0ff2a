"""Solving one block of target frames: all POIs of several windows in one batched solve,
started from the carried guesses, with rescue of lost points and the trust checks.

A block is a few consecutive target frames of a movie. Every row (target frame x POI) starts
from the :class:`Carry` of the block before (the last stored row moved on by its velocity).
Points without a valid carry start from their grid neighbours' carried motion; rows whose
carried subset lies outside the image are OUTSIDE; the reference frame as its own classical
target is the identity. Rows that get lost (not converged, or ZNCC below ``lost_zncc``) are
rescued in time order from the solution of the previous target of the same block, then from
their neighbours' solutions, then by FFT cross-correlation; the better of the attempts is
kept. Then (``BlockContext.checks``) every row is checked
(:mod:`torch_stsdic.analysis.quality`): its window against the classical solution (shorter windows
where the motion is not affine in time, the classical solution where none fits), rows still
lost are solved classically, and poor fits and outliers among neighbours are flagged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.quality import (
    carried_neighbours,
    line_mismatch,
    median_test,
    model_mismatch,
    nanmedian_rows,
    neighbour_tolerance,
    neighbours,
    poor_fit,
    residual_mismatch,
)
from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.initial import linear_fit_in_time
from torch_stsdic.core.shared_motion import SharedMotion, window_offsets
from torch_stsdic.core.solver import (
    SubsetSolver,
    WindowSolution,
    classical_step_info,
    packed_classical_step,
    subset_inside,
)
from torch_stsdic.core.status import Status
from torch_stsdic.movie.frames import FrameCache, window_frames
from torch_stsdic.movie.reference import Reference, noise_ratio, to_relative, to_total
from torch_stsdic.movie.sample_guess import MeasuredSample

__all__ = ["BlockContext", "Carry", "solve_block", "rows_numpy", "make_carry", "STD_OF"]

#: Gauss-Newton steps of the model check's classical solutions (measured on a 2,500-point
#: movie: 26 % of rows had not converged after 3 steps, 0.8 % after 4; the rest are re-solved)
CHECK_ITER = 4

#: px: convergence threshold of the model check's classical solutions (the run's ``tol``,
#: 1e-4 px by default, where looser). The check compares the window with the classical
#: solution within 3 standard deviations of their difference (>= 0.015 px), so a classical
#: solution 1e-3 px from its minimum decides the same; the rows that keep the classical
#: solution (the check failed at every window) are converged to the run's ``tol`` first.
CHECK_TOL = 1e-3

#: The model check judges a row from its window's free classical step (``classical_step``:
#: the classical solution one Gauss-Newton step from the window, its ZNCC, noise and std
#: from the Gauss-Newton model; none where that step is large for the model,
#: ``gauss_newton.STEP_DROP``) where the row passes with room to spare: the displacement
#: test with SCREEN_SLACK times the step's size added to the difference (the classical
#: solution lies within that of the estimate where Gauss-Newton contracts at a rate <= 1/3)
#: and the residual test with the limit tightened by SCREEN_MARGIN. Other rows are solved
#: classically (CHECK_ITER steps from the step), as all were before; False: every row is.
#: Measured against solving every row (``scripts/real_time_model.py`` solves them all): the
#: 1024^2 pair 87 % of rows judged from the step, none that the solve fails; the muDIC
#: hourglass 86 %, one of 64,609 rows that the solve fails (z 3.11 against the limit 3);
#: sample 12 40 % / 12 % (its load step: most rows fail), none.
SCREEN = True
SCREEN_SLACK = 0.5
SCREEN_MARGIN = 0.98

#: rings of lost points filled from their neighbours' carried motion (Carry.from_neighbours)
FILL_ROUNDS = 8

#: px beyond the image border a carried prediction must put a subset before the row is
#: OUTSIDE without a solve
OUTSIDE_MARGIN = 2.0

#: the predicted-std field of each parameter stored with the results (px, px per time unit)
STD_OF = {"u": "u_std", "v": "v_std", "ut": "ut_std", "vt": "vt_std"}


@dataclass
class Carry:
    """Last stored row (total quantities, float32-rounded) and the velocity to extrapolate."""

    t: float
    vals: dict[str, torch.Tensor]  # name -> (N,)
    vel_u: torch.Tensor
    vel_v: torch.Tensor
    valid: torch.Tensor  # (N,) bool
    #: (N,) bool: the velocity was measured (ut, vt, or two rows); None: everywhere
    vel_known: torch.Tensor | None = None
    #: (N,) ZNCC of each point's last trusted row (NaN: none), the fit check's baseline
    fit_zncc: torch.Tensor | None = None

    def predict(self, tk: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted total parameters (B, N) at times ``tk`` (B,)."""
        d = (tk - self.t).unsqueeze(1)
        out = {k: v.unsqueeze(0).expand(tk.shape[0], -1) for k, v in self.vals.items()}
        out["u"] = self.vals["u"] + self.vel_u * d
        out["v"] = self.vals["v"] + self.vel_v * d
        return out

    def from_neighbours(self, nb: torch.Tensor, points: torch.Tensor,
                        rounds: int = FILL_ROUNDS) -> tuple[Carry, int]:
        """This carry with every point that has no valid carry (lost, or a poor fit) carried
        from its valid grid neighbours ``nb`` (N, k) instead (:func:`neighbour_guess`; points
        (N, 2) px in the first reference), ring by ring into a lost region (at most
        ``rounds``), so a lost point starts near the motion again rather than from FFT
        cross-correlation (or is seen to have left the image). Returns the carry and the
        points filled."""
        names = list(self.vals)
        stack = torch.stack([self.vals[nm] for nm in names] + [self.vel_u, self.vel_v], 1)
        ok = self.valid.clone()
        for _ in range(rounds):
            guess = neighbour_guess(stack.unsqueeze(0), ok.unsqueeze(0),
                                    names + ["vel_u", "vel_v"], nb, points)[0]
            fill = ~ok & torch.isfinite(guess).all(1)
            if not bool(fill.any()):
                break
            stack = torch.where(fill.unsqueeze(1), guess.to(stack.dtype), stack)
            ok |= fill
        filled = ok & ~self.valid
        if not bool(filled.any()):
            return self, 0
        vals = {nm: stack[:, i] for i, nm in enumerate(names)}
        known = None if self.vel_known is None else self.vel_known | filled
        return Carry(t=self.t, vals=vals, vel_u=stack[:, -2], vel_v=stack[:, -1],
                     valid=ok, vel_known=known, fit_zncc=self.fit_zncc), int(filled.sum())


def neighbour_guess(params: torch.Tensor, ok: torch.Tensor, names, nb: torch.Tensor,
                    points: torch.Tensor, min_count: int = 2) -> torch.Tensor:
    """(B, N, P) every point's parameters from its ``ok`` (B, N) grid neighbours ``nb``
    (N, k) in ``params`` (B, N, P) (names ``names``): the median over them, u and v first
    carried to the point by each neighbour's own gradients (positions ``points`` (N, 2) px,
    :func:`~torch_stsdic.analysis.quality.carried_neighbours`); NaN where fewer than ``min_count``
    neighbours are ``ok``. Parameters NaN at every neighbour (a classical row's ut) stay
    NaN."""
    vn = carried_neighbours(params, ok, nb)  # (B, N, k, P)
    iu, iv = names.index("u"), names.index("v")
    if all(nm in names for nm in ("ux", "uy", "vx", "vy")):
        b, n = params.shape[:2]
        gi = [names.index(nm) for nm in ("ux", "uy", "vx", "vy")]
        uv = carried_neighbours(params[..., [iu, iv]], ok, nb, points,
                                params[..., gi].reshape(b, n, 2, 2))
        vn[..., iu], vn[..., iv] = uv[..., 0], uv[..., 1]
    out = nanmedian_rows(vn.transpose(-1, -2))  # (B, N, P)
    few = (~torch.isnan(vn[..., iu])).sum(-1) < min_count
    return torch.where(few.unsqueeze(-1), torch.nan, out)



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
    checks: bool = True  # model, fit and neighbour checks (:mod:`torch_stsdic.analysis.quality`)
    noise_ratio: float | None = None  # reference noise variance / a frame's (None: measure
    reference_desc: Any = 0  # on the first block, reference.noise_ratio; the plan's desc)
    neighbours: torch.Tensor | None = None  # (N, k) grid neighbours, made on first use
    neighbour_reach: float | None = None  # px, their median distance, made with them
    shared: SharedMotion | None = None  # the specimen's per-frame motion (None: not used)
    segments: torch.Tensor | None = None  # (T_series, 2) load segment of every frame
    #: the measuring pass's solutions (:class:`~torch_stsdic.movie.sample_guess.MeasuredSample`):
    #: the initial guess of a block that has no carry (None: FFT cross-correlation)
    first_guess: MeasuredSample | None = None
    _checker: SubsetSolver | None = None

    def grid_neighbours(self, ref: Reference) -> torch.Tensor:
        """(N, k) the POIs' grid neighbours (:func:`~torch_stsdic.analysis.quality.neighbours`), made
        once per run (with :attr:`neighbour_reach`)."""
        if self.neighbours is None:
            nb = neighbours(ref.points)
            pts = ref.points.double()
            far = (pts.unsqueeze(1) - pts[nb.clamp(min=0)]).norm(dim=-1)[nb >= 0]
            self.neighbours = nb
            self.neighbour_reach = float(far.median()) if far.numel() else 0.0
        return self.neighbours

    def check_solver(self) -> SubsetSolver:
        """The solver of the model check's classical solutions: the run's, with at most
        ``CHECK_ITER`` Gauss-Newton steps (they start from the window's solution, a noise's
        width away; rows not converged in them are solved in full before they are judged)."""
        if self._checker is None:
            cfg = self.solver.config
            self._checker = SubsetSolver(cfg.replace(max_iter=min(cfg.max_iter, CHECK_ITER),
                                                     tol=max(cfg.tol, CHECK_TOL)))
            self._checker.reference_cache = self.solver.reference_cache  # the same subsets
        return self._checker


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
        if run.noise_ratio is None:
            run.noise_ratio = noise_ratio(run.reference_desc, ref.raw, self.raw)
        self.b, self.n = len(ks), ref.points.shape[0]
        self.pts = ref.points.repeat(self.b, 1)  # (B*N, 2)
        self.fidx, self.dt = self.frames_of(win)
        rows, p_count = self.b * self.n, len(run.names)
        self.params = torch.full((rows, p_count), float("nan"), dtype=run.dtype, device=dev)
        self.zncc = torch.full((rows,), float("nan"), dtype=run.dtype, device=dev)
        self.status = torch.full((rows,), int(Status.NOT_COMPUTED), dtype=torch.int8,
                                 device=dev)
        self.iters = torch.zeros(rows, dtype=torch.int32, device=dev)
        self.std = torch.full((rows, p_count), float("nan"), dtype=run.dtype, device=dev)
        self.sigma = torch.full((rows,), float("nan"), dtype=run.dtype, device=dev)
        self.m_used = torch.full((rows,), -1, dtype=torch.int8, device=dev)
        #: (B*N, 4 Ks + 3) each row's classical solution (the spatial shape's parameters)
        #: one Gauss-Newton step from its window's solution, that step's size and what a
        #: classical solve would report there (``gauss_newton.classical_step_columns``),
        #: where the window's solve gave it (``classical_step``), else NaN: the model check
        #: judges the row from it or starts its classical solve there (None: no solve gave
        #: one)
        self.check_start: torch.Tensor | None = None
        self.gone = torch.zeros(rows, dtype=torch.bool, device=dev)  # predicted outside
        self.identity: torch.Tensor | None = None  # (B*N,) rows known without a solve
        #: (B*N, 2) px where each row's subset is centred, or None: at its POI everywhere
        #: (:meth:`keep_outside` moves the subsets of points near the border inside)
        self.centres: torch.Tensor | None = None
        #: (B*N,) int8 the half-window a row is first solved with, or None: the run's m
        #: everywhere (:meth:`keep_outside` shortens it where the point leaves the image)
        self.window_m: torch.Tensor | None = None
        self._motion: dict[int, torch.Tensor] = {}

    def motion_of(self, m: int) -> torch.Tensor | None:
        """(B*N, 2m+1, 2) the shared motion's known part of every row's window frames
        (:func:`~torch_stsdic.core.shared_motion.window_offsets`), or None (no shared motion, or
        m = 0)."""
        run = self.run
        if run.shared is None or m == 0:
            return None
        if m not in self._motion:
            win = self.windows(m)  # (B, T)
            b, t = win.shape
            pts = self.ref.points
            g = run.shared.displacement(pts, win.reshape(-1)).to(run.dtype)  # (B*T, N, 2)
            g = g.reshape(b, t, -1, 2).permute(0, 2, 1, 3)  # (B, N, T, 2)
            if self.centres is not None:  # off-centre subsets: the motion at their centres
                moved = (self.centres != self.pts).any(1).reshape(b, -1)
                for j in torch.nonzero(moved.any(1)).flatten().tolist():
                    i = torch.nonzero(moved[j]).flatten()
                    c = self.centres.reshape(b, -1, 2)[j, i]
                    g[j, i] = run.shared.displacement(c, win[j]).to(run.dtype).transpose(0, 1)
            dt = (run.ts[win] - run.ts[self.k].unsqueeze(1)).to(run.dtype)  # (B, T)
            o = window_offsets(g, dt.unsqueeze(1).expand(-1, g.shape[1], -1))
            self._motion[m] = o.reshape(-1, t, 2).contiguous()
        return self._motion[m]

    def windows(self, m: int) -> torch.Tensor:
        """(B, 2m+1) series frames of every target's window, shifted (not shrunk) at the
        ends of the series."""
        seg = self.run.segments
        return window_frames(self.k, m, self.run.n_series,
                             None if seg is None else seg.to(self.k.device))

    def frames_of(self, win: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per row: indices into the loaded frames (B*N, T) and dt (B*N, T)."""
        run = self.run
        fidx = torch.searchsorted(self.needed, win).repeat_interleave(self.n, 0)
        dt = (run.ts[win] - run.ts[self.k].unsqueeze(1)).to(run.dtype)
        return fidx, dt.repeat_interleave(self.n, 0)

    def solve(self, idx: torch.Tensor, init: torch.Tensor | None, m: int | None = None,
              solver: SubsetSolver | None = None, init_step: torch.Tensor | None = None
              ) -> WindowSolution:
        """Solve rows ``idx`` from ``init`` (None: FFT) with windows of half-width ``m``
        (default the run's; m = 0: the target frame alone, classical shape), with ``solver``
        (default the run's); subsets at :attr:`centres` where :meth:`keep_outside` moved them
        inside the image (the results are the POIs')."""
        ref, run = self.ref, self.run
        if m is None or m == run.m:
            fidx, dt = self.fidx[idx], self.dt[idx]
        else:
            fidx, dt = self.frames_of(self.windows(m))
            fidx, dt = fidx[idx], dt[idx]
        if m == 0 and run.m > 0 and init is not None and init.shape[1] == len(run.names):
            spatial = run.solver.shape.spatial().param_names
            init = init[:, [run.names.index(nm) for nm in spatial]]
        motion = self.motion_of(run.m if m is None else m)
        return (solver or run.solver).solve(
            ref.img, self.img, self.pts[idx], dt, frame_index=fidx,
            init=init, ref_pixels=ref.raw.unsqueeze(0), frame_pixels=self.raw,
            noise_ratio=run.noise_ratio, motion=None if motion is None else motion[idx],
            centres=None if self.centres is None else self.centres[idx],
            # the model check's first classical step, from the window solve's last step
            classical_step=run.checks and (run.m if m is None else m) > 0 and solver is None,
            init_step=init_step,
        )

    def keep(self, idx: torch.Tensor, sol: WindowSolution, only_better: bool,
             m: int | None = None) -> None:
        """Store ``sol`` (solved with half-window ``m``, default the run's) at rows ``idx``
        (with ``only_better``: where it is usable and the stored result is not, or its ZNCC
        is higher). Parameters missing from ``sol`` (a classical solution has no ut, vt)
        are stored as NaN."""
        self.iters[idx] += sol.iterations
        if only_better:
            new_ok = sol.status <= USABLE
            old_ok = self.status[idx] <= USABLE
            take = new_ok & (~old_ok | (sol.zncc.to(self.run.dtype) > self.zncc[idx]))
            take |= self.status[idx] == int(Status.NOT_COMPUTED)  # a reason beats none

            def pick(a: torch.Tensor) -> torch.Tensor:
                return a[take]
        else:  # every row (no copies of the solution's rows)
            def pick(a: torch.Tensor) -> torch.Tensor:
                return a
        r = pick(idx)
        cols = [sol.param_names.index(nm) if nm in sol.param_names else -1
                for nm in self.run.names]
        p, sd = self._columns(pick(sol.params), cols), self._columns(
            pick(sol.std) if sol.std is not None else None, cols, rows=r.numel())
        self.params[r], self.std[r] = p, sd
        cstep = packed_classical_step(sol.info) if "classical_step" in sol.info else None
        if cstep is not None and self.check_start is None:
            self.check_start = torch.full((self.params.shape[0], cstep.shape[1]), float("nan"),
                                          dtype=self.params.dtype, device=self.params.device)
        if self.check_start is not None:
            self.check_start[r] = float("nan") if cstep is None else pick(cstep).to(
                self.params.dtype)
        self.zncc[r] = pick(sol.zncc).to(self.run.dtype)
        self.status[r] = pick(sol.status)
        if sol.sigma is not None:
            self.sigma[r] = pick(sol.sigma).to(self.run.dtype)
        self.m_used[r] = self.run.m if m is None else m

    def _columns(self, a: torch.Tensor | None, cols: list[int], rows: int = 0) -> torch.Tensor:
        """(R, P) the run's parameter columns taken from ``a`` (R, P') (NaN where ``cols``
        is -1 or ``a`` is None)."""
        dev, dt = self.run.device, self.run.dtype
        if a is None:
            return torch.full((rows, len(cols)), float("nan"), dtype=dt, device=dev)
        if cols == list(range(a.shape[1])) and a.shape[1] == len(cols):
            return a.to(dt)
        pad = torch.cat([a.to(dt), torch.full_like(a[:, :1], float("nan"), dtype=dt)], 1)
        return pad[:, torch.tensor([c if c >= 0 else a.shape[1] for c in cols], device=dev)]

    def keep_identity(self) -> torch.Tensor:
        """Rows whose whole window is the current reference frame itself (classical DIC with
        the reference frame as a target) are the identity, known without a solve: zero
        displacement and gradients, ZNCC 1, zero noise and std, CONVERGED (OUTSIDE where the
        subset leaves the image, as the solver says). Returns the (B*N,) bool mask of those
        rows (a pair through ``stsdic run``: half the work)."""
        run = self.run
        if run.m != 0:
            return torch.zeros(self.b * self.n, dtype=torch.bool, device=run.device)
        rows = (self.windows(0) == self.ref.frame).all(1).repeat_interleave(self.n)
        self.identity = rows
        if not bool(rows.any()):
            return rows
        inside = subset_inside(self.pts, float(run.solver.window.half), self.ref.img.height,
                               self.ref.img.width)
        idx = torch.nonzero(rows & inside).flatten()
        self.keep(idx, self.identity_solution(idx), only_better=False, m=0)
        out = rows & ~inside
        self.params[out] = float("nan")
        self.zncc[out] = float("nan")
        self.status[out] = int(Status.OUTSIDE)
        self.m_used[out] = 0
        return rows

    def identity_solution(self, idx: torch.Tensor) -> WindowSolution:
        """The classical solution of rows ``idx`` whose target is the current reference
        frame itself: zero displacement and gradients, ZNCC 1, zero noise and std,
        CONVERGED (the reference against itself, known without a solve)."""
        run, r = self.run, idx.numel()
        names = run.solver.shape.spatial().param_names
        zeros = torch.zeros(r, len(names), dtype=run.dtype, device=run.device)
        return WindowSolution(
            points=self.pts[idx], params=zeros, param_names=names,
            zncc=torch.ones(r, dtype=run.dtype, device=run.device),
            status=torch.full((r,), int(Status.CONVERGED), dtype=torch.int8,
                              device=run.device),
            iterations=torch.zeros(r, dtype=torch.int32, device=run.device),
            std=zeros.clone(), sigma=torch.zeros(r, dtype=run.dtype, device=run.device))

    def lost(self) -> torch.Tensor:
        """(B*N,) bool: rows without a trustworthy solution (not converged, a poor fit, or a
        ZNCC below ``lost_zncc``), other than those that cannot be solved at all
        (LOW_TEXTURE)."""
        st = self.status
        return (
            (st == int(Status.MAX_ITER)) | (st == int(Status.DIVERGED))
            | (st == int(Status.OUTSIDE)) | (st == int(Status.NOT_COMPUTED))
            | (st == int(Status.POOR_FIT)) | ((st <= USABLE) & ~(self.zncc >= self.run.lost_zncc))
        ) & ~self.gone

    def keep_outside(self, inits: Sequence[torch.Tensor], carried: torch.Tensor
                     ) -> torch.Tensor:
        """Carried rows near the image border. At every one of the predictions ``inits``
        ((B*N, P) relative parameters: the carry moved on by its velocity, and where it was
        last), over every frame of the row's window, the POI's predicted position is
        checked:

        * where, as predicted by the first (the carry moved on), the subset would come
          within ``OUTSIDE_MARGIN`` px of the border but the POI stays that far inside, the
          subset is moved inside the image by up to its half-size (an off-centre subset,
          :attr:`centres`; its solution is carried to the POI by its own gradients, the std
          with them): the point is measured while it is in view;
        * where that fails over the run's window but holds over a shorter one (the point
          leaves the image within the window), the row is solved with the longest such
          window (:attr:`window_m`);
        * where the POI is that close to the border, or beyond, by the first prediction even
          at the target frame alone, and the subset is by the others, the row is OUTSIDE,
          neither solved nor rescued: a specimen moving out of view (every rescue of such a
          point found some other peak inside the image, at low ZNCC, again in every block).

        Returns the (B*N,) bool mask of the OUTSIDE rows."""
        run = self.run
        rows = carried.shape[0]
        left = carried.clone()  # carried rows without a window that stays in view yet
        shift = torch.zeros_like(self.pts)
        for m in range(run.m, -1, -1):
            if not bool(left.any()):
                break
            if m == run.m:
                dt = self.dt
            else:
                dt = self.frames_of(self.windows(m))[1]
            fit, d = self._placement(inits, dt, self.motion_of(m))
            fit &= left
            shift = torch.where(fit.unsqueeze(1), d, shift)
            if m < run.m and bool(fit.any()):
                if self.window_m is None:
                    self.window_m = torch.full((rows,), run.m, dtype=torch.int8,
                                               device=run.device)
                self.window_m[fit] = m
            left &= ~fit
        out = left
        if bool(out.any()):
            self.status[out] = int(Status.OUTSIDE)
            self.gone |= out
        moved = (shift != 0).any(1) & ~out
        if bool(moved.any()):
            whole = torch.sign(shift) * shift.abs().ceil()  # whole px, away from the border
            self.centres = self.pts + torch.where(moved.unsqueeze(1), whole, 0.0)
            self._motion = {}  # the shared motion at the subsets' centres
            run.stats["off_centre_rows"] = run.stats.get("off_centre_rows", 0) \
                + int(moved.sum())
        return out

    def _placement(self, inits: Sequence[torch.Tensor], dt: torch.Tensor,
                   motion: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B*N,) bool: the row's subset can be placed in view over its window (frame times
        ``dt`` (B*N, T), known motion ``motion`` (B*N, T, 2) or None) by one of the
        predictions ``inits`` (:meth:`keep_outside`), and (B*N, 2) px the shift of its
        centre that this takes (the largest over the predictions that fit)."""
        run = self.run
        names = run.names
        iu, iv = names.index("u"), names.index("v")
        half = float(run.solver.window.half)
        h, w = self.ref.img.height, self.ref.img.width
        feasible = torch.zeros(self.pts.shape[0], dtype=torch.bool, device=run.device)
        shift = torch.zeros_like(self.pts)
        for i, init in enumerate(inits):
            pos = []
            for c, (iz, it) in enumerate(((iu, "ut"), (iv, "vt"))):
                z = self.pts[:, c:c + 1] + init[:, iz:iz + 1]
                if it in names:
                    z = z + init[:, names.index(it)].nan_to_num(0.0).unsqueeze(1) * dt
                if motion is not None:
                    z = z + motion[..., c]
                pos.append(z)  # (B*N, T)
            need = []
            reach = half if i == 0 else 0.0  # only the moved-on prediction moves a subset
            for z, size in zip(pos, (w, h)):
                lo = (half + OUTSIDE_MARGIN - z.amin(1)).clamp(min=0)  # move the subset in
                hi = (z.amax(1) - (size - 1 - half - OUTSIDE_MARGIN)).clamp(min=0)
                need.append((lo - hi, ((lo == 0) | (hi == 0)) & (torch.maximum(lo, hi) <= reach)))
            fit = need[0][1] & need[1][1] & torch.isfinite(pos[0]).all(1) \
                & torch.isfinite(pos[1]).all(1)
            d = torch.stack([need[0][0], need[1][0]], 1)
            shift = torch.where(fit.unsqueeze(1) & (d.abs() > shift.abs()), d, shift)
            feasible |= fit
        return feasible, shift

    def init_rows(self, values: dict[str, torch.Tensor]) -> torch.Tensor:
        """(R, P) initial parameters from relative values by name (missing ones zero)."""
        some = next(iter(values.values()))
        return torch.stack([values[nm] if nm in values else torch.zeros_like(some)
                            for nm in self.run.names], 1)

    def rescue(self, carry: Carry | None, carried: torch.Tensor, m: int | None = None
               ) -> tuple[int, int, int]:
        """Lost rows, target by target in time order: start again from the solution of the
        previous target of the block (same point) moved on by its velocity, then, where
        still lost, from FFT cross-correlation; keep the better result (windows of
        half-width ``m``, default the run's). ``carried``: rows that started from the
        carried guess. Returns the rows restarted from a neighbour target, by FFT, and by
        FFT after a carried start."""
        run, n = self.run, self.n
        names = run.names
        from_prev = by_fft = redone = from_nb = 0
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
                    if m == 0:
                        init = init.nan_to_num(0.0)  # a classical row has no ut, vt
                    ok = torch.isfinite(init).all(1)
                    if bool(ok.any()):
                        self.keep(r[ok], self.solve(r[ok], init[ok], m=m), only_better=True,
                                  m=m)
                        from_prev += int(ok.sum())
            from_nb += self._rescue_from_neighbours(rows, m)
            r = rows[self.lost()[rows]]
            if r.numel():
                self.keep(r, self.solve(r, None, m=m), only_better=True, m=m)
                by_fft += int(r.numel())
                redone += int(carried[r].sum())
        run.stats["neighbour_rescued_rows"] = run.stats.get("neighbour_rescued_rows", 0) + from_nb
        return from_prev, by_fft, redone

    def _rescue_from_neighbours(self, rows: torch.Tensor, m: int | None) -> int:
        """Lost rows among ``rows`` (one target) solved again from their trusted grid
        neighbours' solutions at the same target (:func:`neighbour_guess`); the better
        result is kept. Returns the rows tried."""
        lost = self.lost()[rows]
        if not bool(lost.any()):
            return 0
        ok = (self.status[rows] <= USABLE) & ~lost
        if int(ok.sum()) < 2:
            return 0
        guess = neighbour_guess(self.params[rows].unsqueeze(0), ok.unsqueeze(0),
                                self.run.names, self.run.grid_neighbours(self.ref),
                                self.ref.points)[0]
        for nm in ("ut", "vt"):  # a classical neighbour has no velocity: none
            if nm in self.run.names:
                i = self.run.names.index(nm)
                guess[:, i] = guess[:, i].nan_to_num(0.0)
        try_ = lost & torch.isfinite(guess).all(1)
        r = rows[try_]
        if r.numel():
            self.keep(r, self.solve(r, guess[try_], m=m), only_better=True, m=m)
        return int(r.numel())

    def _own(self, idx: torch.Tensor) -> torch.Tensor:
        """(R,) bool: rows ``idx`` whose target is the current reference frame itself (their
        classical solution is the identity)."""
        return self.k.repeat_interleave(self.n)[idx] == self.ref.frame

    def _classical(self, idx: torch.Tensor, solver: SubsetSolver) -> WindowSolution:
        """The classical solutions of rows ``idx`` from their window's solution (with
        ``solver``); where the target is the reference frame itself it is the
        :meth:`identity_solution`, not solved."""
        own = self._own(idx)
        # one classical step from the window's solution is known where its solve gave it:
        # the solve goes on from there, that step its previous increment
        start, step = self.params[idx], None
        if self.check_start is not None:
            known = classical_step_info(self.check_start[idx])
            spatial = [self.run.names.index(nm)
                       for nm in self.run.solver.shape.spatial().param_names]
            p0, size = known["classical_step"], known["classical_step_size"]
            have = (torch.isfinite(p0).all(1) & torch.isfinite(size)).unsqueeze(1)
            start = torch.where(have, p0, start[:, spatial])
            step = torch.where(have.squeeze(1), size, 0.0)
        if not bool(own.any()):
            return self.solve(idx, start, m=0, solver=solver, init_step=step)
        ident = self.identity_solution(idx)
        if bool(own.all()):
            return ident
        return _with_rows(ident, ~own, self.solve(
            idx[~own], start[~own], m=0, solver=solver,
            init_step=None if step is None else step[~own]))

    def _screen(self, idx: torch.Tensor) -> tuple[torch.Tensor | None, WindowSolution | None]:
        """(R,) bool: rows ``idx`` that pass the model check from their window's free
        classical step (:data:`SCREEN`), and the classical solutions estimated there (a
        :class:`WindowSolution` of R rows, CONVERGED, NaN where unknown); (None, None)
        where no solve gave one."""
        run = self.run
        if not SCREEN or self.check_start is None:
            return None, None
        names = run.solver.shape.spatial().param_names
        known = self.check_start[idx]
        step = classical_step_info(known)
        p_est, sd = step["classical_step"], step["classical_step_std"]
        size, zn = step["classical_step_size"], step["classical_step_zncc"]
        sig = step["classical_step_sigma"]
        cu, cv = names.index("u"), names.index("v")
        iu, iv = run.names.index("u"), run.names.index("v")
        ok = torch.isfinite(known).all(1) & ~self._own(idx)
        ok &= ~model_mismatch(self.params[idx][:, [iu, iv]], p_est[:, [cu, cv]],
                              self.std[idx][:, [iu, iv]], sd[:, [cu, cv]],
                              slack=SCREEN_SLACK * size)
        ok &= ~residual_mismatch(self.sigma[idx], sig, run.solver.window.effective_pixels(),
                                 self.zncc[idx], margin=SCREEN_MARGIN)
        r = idx.numel()
        est = WindowSolution(
            points=self.pts[idx], params=p_est.to(run.dtype), param_names=names,
            zncc=zn.to(run.dtype), status=torch.full((r,), int(Status.CONVERGED),
                                                     dtype=torch.int8, device=run.device),
            iterations=torch.zeros(r, dtype=torch.int32, device=run.device),
            std=sd.to(run.dtype), sigma=sig.to(run.dtype))
        return ok, est

    def _off_a_line(self, rows: torch.Tensor, m: int, disp: torch.Tensor, std: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(R,) bool: rows whose window of half-width ``m`` cannot pass the model check,
        judged from the classical solutions ``disp`` (B*N, 2) (std ``std``) of the block's
        rows at the window's frames (:func:`~torch_stsdic.analysis.quality.line_mismatch`; False
        where a frame of the window is not a target of the block); and (R, 2) the velocity
        of the line through them, px per time unit (NaN where a frame has none)."""
        run, n = self.run, self.n
        win = self.windows(m)  # (B, T)
        pos = torch.full((run.n_series,), -1, dtype=torch.long, device=run.device)
        pos[self.k] = torch.arange(self.b, device=run.device)
        j, i = rows // n, rows % n
        at = pos[win[j]]  # (R, T) the block target of each window frame, -1: none
        d = disp[(at * n + i.unsqueeze(1)).clamp(min=0)]  # (R, T, 2)
        d = torch.where((at >= 0).unsqueeze(-1), d, float("nan"))
        off = self.motion_of(m)
        if off is not None:
            d = d - off[rows]
        _, dt = self.frames_of(win)
        _, vel = linear_fit_in_time(d, dt[rows])
        return line_mismatch(d, dt[rows], disp[rows], std[rows]), vel

    def check_model(self) -> tuple[int, int]:
        """Model check (:func:`~torch_stsdic.analysis.quality.model_mismatch`) of every usable row
        against its classical solution at the target frame (started from the row's own
        solution: ``CHECK_ITER`` steps to ``CHECK_TOL``, in full where those do not converge
        or disagree; the identity where the target is the reference frame). Rows that fail
        are solved again with shorter windows (m - 1 .. 1) started from the classical
        solution and the velocity of the line through the block's classical solutions,
        except where those already miss a line (:func:`~torch_stsdic.analysis.quality.line_mismatch`);
        where no window fits they keep the classical solution, converged to the run's
        ``tol`` (ut, vt NaN, ``m_used`` 0). A usable row whose classical solution fails is
        POOR_FIT. Returns (rows shortened, rows left classical)."""
        run = self.run
        idx = torch.nonzero((self.status <= USABLE) & torch.isfinite(self.params).all(1)
                            ).flatten()
        if run.m == 0 or idx.numel() == 0:
            return 0, 0
        iu, iv = run.names.index("u"), run.names.index("v")
        # rows whose free classical step passes with room to spare are judged from it; the
        # others take a few classical steps from there; rows that do not converge in them,
        # or disagree, are solved classically in full before they are judged
        screened, quick = self._screen(idx)
        if screened is None or not bool(screened.all()):
            rest = None if screened is None else ~screened
            solved = self._classical(idx if rest is None else idx[rest], run.check_solver())
            quick = solved if rest is None else _with_rows(quick, rest, solved)
        cu, cv = quick.param_names.index("u"), quick.param_names.index("v")
        # every row's classical (u, v) and std (NaN: none), for the shorter windows below
        d_all = torch.full((self.b * self.n, 2), float("nan"), dtype=run.dtype,
                           device=run.device)
        s_all = d_all.clone()
        conv = quick.status == int(Status.CONVERGED)
        d_all[idx[conv]] = quick.params[conv][:, [cu, cv]].to(run.dtype)
        s_all[idx[conv]] = quick.std[conv][:, [cu, cv]].to(run.dtype)
        # the reference frame as target: its classical residual is round-off, no measure
        not_ref = ~self._own(idx)
        pixels = run.solver.window.effective_pixels()
        suspect = (quick.status != int(Status.CONVERGED)) | model_mismatch(
            self.params[idx][:, [iu, iv]], quick.params[:, [cu, cv]].to(run.dtype),
            self.std[idx][:, [iu, iv]], quick.std[:, [cu, cv]].to(run.dtype))
        suspect |= not_ref & residual_mismatch(self.sigma[idx], quick.sigma, pixels,
                                               self.zncc[idx])
        idx, not_ref = idx[suspect], not_ref[suspect]
        if idx.numel() == 0:
            return 0, 0
        # where the few steps converged they are the classical solution (the full solver
        # takes the same steps); only the others go on
        cls = _rows(quick, suspect)
        redo = cls.status != int(Status.CONVERGED)
        if bool(redo.any()):
            cls = _with_rows(cls, redo, self.solve(idx[redo], cls.params[redo].nan_to_num(0.0),
                                                   m=0))
        ok_c = cls.status <= USABLE
        d_all[idx] = torch.where(ok_c.unsqueeze(1), cls.params[:, [cu, cv]].to(run.dtype),
                                 float("nan"))
        s_all[idx] = torch.where(ok_c.unsqueeze(1), cls.std[:, [cu, cv]].to(run.dtype),
                                 float("nan"))
        self.status[idx[~ok_c]] = int(Status.POOR_FIT)
        idx, not_ref = idx[ok_c], not_ref[ok_c]
        p_cls = cls.params[ok_c]
        sig_cls = cls.sigma[ok_c]
        d_cls = p_cls[:, [cu, cv]].to(run.dtype)
        s_cls = cls.std[ok_c][:, [cu, cv]].to(run.dtype)
        fail = model_mismatch(self.params[idx][:, [iu, iv]], d_cls, self.std[idx][:, [iu, iv]],
                              s_cls)
        fail |= not_ref & residual_mismatch(self.sigma[idx], sig_cls, pixels, self.zncc[idx])
        init = self.params[idx].clone()  # shorter windows start from the classical solution
        for j, nm in enumerate(cls.param_names):
            init[:, run.names.index(nm)] = p_cls[:, j].to(run.dtype)
        shortened = 0
        for m in range(run.m - 1, 0, -1):
            if not bool(fail.any()):
                break
            sel = torch.nonzero(fail).flatten()
            # a window whose frames' classical solutions miss a line would fail: not solved
            off, vel = self._off_a_line(idx[sel], m, d_all, s_all)
            sel, vel = sel[~off], vel[~off]
            if sel.numel() == 0:
                continue
            start = init[sel]  # the velocity of the classical solutions' line, where known
            for c, nm in ((0, "ut"), (1, "vt")):
                if nm in run.names:
                    j = run.names.index(nm)
                    start[:, j] = torch.where(torch.isfinite(vel[:, c]), vel[:, c].to(start),
                                              start[:, j])
            sol = self.solve(idx[sel], start, m=m)
            good = sol.status <= USABLE
            d = sol.params[:, [iu, iv]].to(run.dtype)
            good &= ~model_mismatch(d, d_cls[sel], sol.std[:, [iu, iv]], s_cls[sel])
            good &= ~(not_ref[sel] & residual_mismatch(sol.sigma, sig_cls[sel], pixels,
                                                       sol.zncc))
            self.keep(idx[sel][good], _rows(sol, good), only_better=False, m=m)
            shortened += int(good.sum())
            fail[sel[good]] = False
        pick = torch.nonzero(ok_c).flatten()[fail]
        kept = _rows(cls, pick)
        loose = ~redo[pick] if bool(redo.any()) else torch.ones_like(pick, dtype=torch.bool)
        if bool(loose.any()):  # converged to CHECK_TOL only: on to the run's tol
            pol = self.solve(idx[fail][loose], kept.params[loose].nan_to_num(0.0), m=0)
            good = pol.status <= USABLE
            better = loose.clone()
            better[loose] = good
            kept = _with_rows(kept, better, _rows(pol, good))
        self.keep(idx[fail], kept, only_better=False, m=0)
        return shortened, int(fail.sum())

    def rescue_classical(self, guess: torch.Tensor | None, carry: Carry | None) -> int:
        """Rows a window could not solve (still lost after :meth:`rescue`) are solved
        classically (m = 0): from their carried ``guess`` (R, P) (NaN rows: none), then as
        in :meth:`rescue`. Returns the rows that became usable."""
        lost = self.lost()
        if not bool(lost.any()):
            return 0
        if guess is not None:
            r = torch.nonzero(lost & torch.isfinite(guess).all(1)).flatten()
            if r.numel():
                self.keep(r, self.solve(r, guess[r], m=0), only_better=True, m=0)
        self.rescue(carry, torch.zeros_like(lost), m=0)
        return int((lost & ~self.lost()).sum())

    def check_fit(self, carry: Carry | None = None) -> int:
        """Usable rows whose residual is not the image noise, or whose ZNCC is below the
        floor, become POOR_FIT (:func:`~torch_stsdic.analysis.quality.poor_fit`), each compared with
        the rows of its own target and with its point's last trusted row (``carry``, then
        the block's targets in time order). Returns their number."""
        n, count = self.n, 0
        run = self.run
        base = torch.full((n,), float("nan"), dtype=run.dtype, device=run.device)
        if carry is not None and carry.fit_zncc is not None:
            base = carry.fit_zncc.to(base)
        for j in range(self.b):
            sl = slice(j * n, (j + 1) * n)
            bad = poor_fit(self.sigma[sl], self.zncc[sl], self.status[sl] <= USABLE,
                           run.lost_zncc, baseline_zncc=base)
            self.status[sl][bad] = int(Status.POOR_FIT)
            count += int(bad.sum())
            base = torch.where(self.status[sl] <= USABLE, self.zncc[sl], base)
        return count

    def check_neighbours(self) -> int:
        """Usable rows that are outliers among their grid neighbours become INCONSISTENT
        (:func:`~torch_stsdic.analysis.quality.median_test` on u and v per target). Returns their
        number."""
        run = self.run
        nb = run.grid_neighbours(self.ref)
        b, n = self.b, self.n
        rows = torch.arange(b * n, device=run.device)
        if self.identity is not None and bool(self.identity.any()):
            # the reference frame as its own target (zero motion everywhere) has no outlier
            rows = rows[~self.identity]
            b = rows.numel() // n
            if b == 0:
                return 0
        iu, iv = run.names.index("u"), run.names.index("v")
        params, std = self.params[rows], self.std[rows]
        uv = params[:, [iu, iv]].reshape(b, n, 2)
        ok = (self.status[rows] <= USABLE).reshape(b, n)
        sd = std[:, [iu, iv]].reshape(b, n, 2)
        grads = sg = None
        reach = 0.0
        if all(nm in run.names for nm in ("ux", "uy", "vx", "vy")):
            gi = [run.names.index(nm) for nm in ("ux", "uy", "vx", "vy")]
            grads = params[:, gi].reshape(b, n, 2, 2)
            # the gradients' own noise, carried over the neighbours' distance
            sg = std[:, gi].reshape(b, n, 4).amax(-1)
            reach = run.neighbour_reach
        eps = neighbour_tolerance(sd, sg, ok, nb, reach)
        out = median_test(uv, ok, nb, eps, points=self.ref.points, gradients=grads)
        self.status[rows[out.reshape(-1)]] = int(Status.INCONSISTENT)
        return int(out.sum())

    def _velocity(self, j: int, cand: torch.Tensor, carry: Carry | None):
        """Velocity (u, v) of target j-1 for the rows ``cand`` of a target: the measured
        ut, vt where there is one, else the finite difference to target j-2 (or the carried
        row)."""
        run, n = self.run, self.n
        names = run.names
        prev = torch.arange((j - 1) * n, j * n, device=run.device)[cand]
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
        if "ut" in names:
            mu, mv = self.params[prev, names.index("ut")], self.params[prev, names.index("vt")]
            du = torch.where(torch.isfinite(mu), mu, du)
            dv = torch.where(torch.isfinite(mv), mv, dv)
        return torch.nan_to_num(du), torch.nan_to_num(dv)


def _rows(sol: WindowSolution, pick: torch.Tensor) -> WindowSolution:
    """The rows ``pick`` (bool mask or indices) of a solution."""
    return WindowSolution(
        points=sol.points[pick], params=sol.params[pick], param_names=sol.param_names,
        zncc=sol.zncc[pick], status=sol.status[pick], iterations=sol.iterations[pick],
        time=sol.time, std=None if sol.std is None else sol.std[pick],
        sigma=None if sol.sigma is None else sol.sigma[pick],
    )


def _with_rows(sol: WindowSolution, pick: torch.Tensor, new: WindowSolution) -> WindowSolution:
    """``sol`` with its rows ``pick`` (bool mask) replaced by the rows of ``new``."""

    def put(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
        if a is None or b is None:
            return a
        out = a.clone()
        out[pick] = b.to(a.dtype)
        return out

    return WindowSolution(
        points=sol.points, params=put(sol.params, new.params), param_names=sol.param_names,
        zncc=put(sol.zncc, new.zncc), status=put(sol.status, new.status),
        iterations=put(sol.iterations, sol.iterations[pick] + new.iterations), time=sol.time,
        std=put(sol.std, new.std), sigma=put(sol.sigma, new.sigma),
    )


def _only_identity(run: BlockContext, ref: Reference, carry: Carry) -> bool:
    """The carry is the classical row of the reference frame itself (the identity, no
    velocity): the next block starts as the first one, by FFT cross-correlation (at seed
    points: fewer Gauss-Newton steps than from zero motion; a pair: 3.7 instead of 6.1)."""
    return (run.m == 0 and ref.frame >= 0 and ref.acc is None
            and carry.t == float(run.ts[ref.frame])
            and carry.vel_known is not None and not bool(carry.vel_known.any()))


def solve_block(run: BlockContext, ks: list[int], ref: Reference, carry: Carry | None):
    """Solve all POIs of target frames ``ks`` (B,) in one batched solve, then rescue lost
    rows (from the previous target of the block, their neighbours, then by FFT
    cross-correlation) and check them (``run.checks``).

    Returns a dict of (B, N) tensors: total parameters by name, "zncc", "status",
    "iterations"."""
    blk = _Block(run, ks, ref)
    b, n, dev = blk.b, blk.n, run.device
    rows = b * n
    if carry is not None and _only_identity(run, ref, carry):
        carry = None  # the reference frame's own row, no velocity: it predicts nothing
    if carry is None and run.first_guess is not None and ref.acc is None:
        # no carry (the first block): start from the measuring pass's solutions
        init = blk.init_rows({nm: v.to(device=dev, dtype=run.dtype) for nm, v in
                              run.first_guess.guess(ref.points, blk.windows(run.m),
                                                    blk.dt[::n]).items()})
        carried = torch.isfinite(init).all(1)
        carried &= ~blk.keep_outside((init,), carried)
        run.stats["first_guess_rows"] = run.stats.get("first_guess_rows", 0) + int(
            carried.sum())
    elif carry is None:
        carried = torch.zeros(rows, dtype=torch.bool, device=dev)
    else:
        pts0 = ref.points if ref.acc is None else ref.points - torch.stack(
            [ref.acc["u"], ref.acc["v"]], 1)
        if not bool(carry.valid.all()):
            carry, filled = carry.from_neighbours(run.grid_neighbours(ref), pts0)
            run.stats["neighbour_rows"] = run.stats.get("neighbour_rows", 0) + filled * b
        pred = to_relative(carry.predict(run.ts[blk.k].to(run.dtype)), ref.acc)
        init = blk.init_rows({nm: v.reshape(-1) for nm, v in pred.items()})
        carried = carry.valid.repeat(b) & torch.isfinite(init).all(1)
        last = {nm: v.repeat(b) for nm, v in to_relative(dict(carry.vals), ref.acc).items()}
        carried &= ~blk.keep_outside((init, blk.init_rows(last)), carried)
        if carry.vel_known is not None:  # without a velocity the carry predicts only the
            later = torch.arange(b, device=dev).repeat_interleave(n) > 0  # first target:
            carried &= ~later | carry.vel_known.repeat(b)  # the later ones start from it
    ident = blk.keep_identity()
    carried &= ~ident
    guess = None
    if bool(carried.any()):
        guess = torch.where(carried.unsqueeze(1), init, torch.full_like(init, float("nan")))
    shorter = carried & (blk.window_m < run.m) if blk.window_m is not None else None
    if shorter is not None:  # points leaving the image within their window
        for m in torch.unique(blk.window_m[shorter]).tolist():
            r = torch.nonzero(shorter & (blk.window_m == m)).flatten()
            blk.keep(r, blk.solve(r, init[r], m=m), only_better=False, m=m)
        carried = carried & ~shorter
    idx_c = torch.nonzero(carried).flatten()
    if idx_c.numel():
        blk.keep(idx_c, blk.solve(idx_c, init[idx_c]), only_better=False)
    if shorter is not None:
        carried = carried | shorter
    from_prev, by_fft, redone = blk.rescue(carry, carried)
    run.stats["rescued_rows"] = run.stats.get("rescued_rows", 0) + from_prev
    run.stats["fft_rows"] += by_fft
    run.stats["redone_rows"] += redone
    if run.checks and not bool(ident.all()):  # the identity cannot fail
        shortened, classical = blk.check_model()
        classical += blk.rescue_classical(guess, carry) if run.m > 0 else 0
        stats = run.stats
        stats["shortened_rows"] = stats.get("shortened_rows", 0) + shortened
        stats["classical_rows"] = stats.get("classical_rows", 0) + classical
        stats["poor_fit_rows"] = stats.get("poor_fit_rows", 0) + blk.check_fit(carry)
        stats["inconsistent_rows"] = stats.get("inconsistent_rows", 0) + blk.check_neighbours()
    rel = {nm: blk.params[:, j].reshape(b, n) for j, nm in enumerate(run.names)}
    out = to_total(rel, ref.acc)
    out["zncc"] = blk.zncc.reshape(b, n)
    out["status"] = blk.status.reshape(b, n)
    out["iterations"] = blk.iters.reshape(b, n)
    out["m"] = blk.m_used.reshape(b, n)
    for j, nm in enumerate(run.names):
        if nm in STD_OF:
            out[STD_OF[nm]] = blk.std[:, j].reshape(b, n)
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
    if "m" in out:
        out["m"] = np.nan_to_num(out["m"], nan=-1).astype(np.int8)
    out["iterations"] = out["iterations"].astype(np.int64)
    return out



def make_carry(rows: dict[str, np.ndarray], times: np.ndarray, names, prev: Carry | None,
                dtype, device) -> Carry:
    """Carry from the last stored row (velocity from ut/vt, else from the last two rows).

    Valid are the usable rows and the INCONSISTENT ones: a point the neighbour test
    doubts fitted its own subset (it passed the fit check), so it goes on from its own
    solution; restarting it would lose the many good points a bad neighbour condemns."""

    def col(nm: str, i: int = -1) -> torch.Tensor:
        return torch.from_numpy(rows[nm][i].astype(np.float64)).to(device=device, dtype=dtype)

    vals = {nm: col(nm) for nm in names}
    st = rows["status"][-1]
    ok = torch.from_numpy((st <= USABLE) | (st == int(Status.INCONSISTENT))).to(device)
    ok &= torch.isfinite(vals["u"]) & torch.isfinite(vals["v"])
    t_last = float(times[-1])
    if len(times) >= 2:
        t_prev, u_prev, v_prev = float(times[-2]), col("u", -2), col("v", -2)
    elif prev is not None:
        t_prev, u_prev, v_prev = prev.t, prev.vals["u"], prev.vals["v"]
    else:
        t_prev, u_prev, v_prev = t_last, vals["u"], vals["v"]
    span = t_last - t_prev
    if span > 0:
        vel_u, vel_v = (vals["u"] - u_prev) / span, (vals["v"] - v_prev) / span
    else:
        vel_u, vel_v = torch.zeros_like(vals["u"]), torch.zeros_like(vals["v"])
    known = torch.full_like(ok, span > 0)  # two rows: a finite difference
    if "ut" in names:  # the measured velocity where the window had one (m > 0)
        vel_u = torch.where(torch.isfinite(vals["ut"]), vals["ut"], vel_u)
        vel_v = torch.where(torch.isfinite(vals["vt"]), vals["vt"], vel_v)
        known |= torch.isfinite(vals["ut"]) & torch.isfinite(vals["vt"])
    fin = torch.isfinite(vel_u) & torch.isfinite(vel_v)
    vel_u = torch.where(fin, vel_u, torch.zeros_like(vel_u))
    vel_v = torch.where(fin, vel_v, torch.zeros_like(vel_v))
    # where the row had no window velocity (classical, m = 0), the next window starts from
    # the finite difference, as its displacement does (not from zero velocity: sample 12's
    # rows left classical before a load step took 3.5 instead of 3.2 steps in the next block)
    for nm, vel in (("ut", vel_u), ("vt", vel_v)):
        if nm in vals:
            vals[nm] = torch.where(torch.isfinite(vals[nm]), vals[nm], vel)
    fit = None
    if "zncc" in rows:  # the last trusted row of every point, in time order
        fit = torch.full_like(vals["u"], float("nan")) if prev is None or \
            prev.fit_zncc is None else prev.fit_zncc.clone()
        for i in range(len(times)):
            trusted = torch.from_numpy(rows["status"][i] <= USABLE).to(device)
            fit = torch.where(trusted, col("zncc", i), fit)
    return Carry(t=t_last, vals=vals, vel_u=vel_u, vel_v=vel_v, valid=ok, vel_known=known,
                 fit_zncc=fit)
