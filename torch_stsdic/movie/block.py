"""Solving one block of target frames: all POIs of several windows in one batched solve,
started from the carried guesses, with rescue of lost points and the trust checks.

A block is a few consecutive target frames of a movie. Every row (target frame x POI) starts
from the :class:`Carry` of the block before (the last stored row moved on by its velocity).
Points without a valid carry start from their grid neighbours' carried motion; near the
border a carried subset is moved inside the image or its window shortened, and a row whose
point has left it is OUTSIDE (:mod:`~torch_stsdic.movie.block_placement`); the reference
frame as its own classical target is the identity. Rows that get lost (not converged, or
ZNCC below ``lost_zncc``) are rescued (:mod:`torch_stsdic.movie.rescue`) from the solution
of an earlier target of the same block, then from their neighbours' solutions, then by FFT
cross-correlation, all targets at once in each step; the better of the attempts is kept.
Then (``BlockContext.checks``) every row is checked (:mod:`torch_stsdic.analysis.quality`):
its window against the classical solution (shorter windows where the motion is not affine in
time, the classical solution where none fits), rows still lost are solved classically, and
poor fits and outliers among neighbours are flagged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.quality import neighbours
from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.choices import masked_groups, until_done
from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.core.solver import (
    SubsetSolver,
    WindowSolution,
    packed_classical_step,
    subset_inside,
)
from torch_stsdic.core.status import Status
from torch_stsdic.movie.block_guess import BlockGuesses, ReadGuesses, solve_guessing
from torch_stsdic.movie.block_motion import BlockMotion
from torch_stsdic.movie.block_placement import BlockPlacement
from torch_stsdic.movie.block_start import pilot_shift, window_shake
from torch_stsdic.movie.block_windows import BlockWindows
from torch_stsdic.movie.carry import Carry
from torch_stsdic.movie.checks import CHECK_ITER, CHECK_TOL, BlockChecks
from torch_stsdic.movie.frames import (
    FrameCache,
    block_frames,
    upload,
)
from torch_stsdic.movie.reference import Reference, noise_ratio, to_relative, to_total
from torch_stsdic.movie.rescue import BlockRescue
from torch_stsdic.movie.sample_guess import MeasuredSample
from torch_stsdic.movie.shared_velocity import report_velocity
from torch_stsdic.movie.template_noise import TemplateShares
from torch_stsdic.movie.velocity_point import refer_velocities

#: the predicted-std field of each parameter stored with the results (px, px per time unit)
STD_OF = {"u": "u_std", "v": "v_std", "ut": "ut_std", "vt": "vt_std"}


@dataclass
class BlockContext:
    solver: SubsetSolver
    cache: FrameCache
    ts: torch.Tensor  # (T_s,) series times, float64
    times: np.ndarray  # (T_s,) the same on the host (read there without a device read)
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
    segments_host: torch.Tensor | None = None  # the same on the host (None: none, or read)
    #: (T_series, 2) the segments a reported velocity's slope of the shared motion stays in:
    #: the load segments split where the motion itself jumps (SharedMotion.jumps); None: none
    velocity_segments: torch.Tensor | None = None
    #: the measuring pass's solutions (:class:`~torch_stsdic.movie.sample_guess.MeasuredSample`):
    #: the initial guess of a block that has no carry (None: FFT cross-correlation)
    first_guess: MeasuredSample | None = None
    #: every block starts from ``first_guess`` where it has a trusted solution there (an
    #: earlier round's of the same frames: the template's later rounds), not only the first
    guess_every_block: bool = False
    #: (N,) px^2 the variance the reference adds to u and to v of every row, beyond what the
    #: solver predicts (the registration of a template made from the series; None: none)
    reference_var: torch.Tensor | None = None
    #: the sampled frames' weights in that template (their noise is shared with the
    #: windows': :mod:`~torch_stsdic.movie.template_noise`; None: no template)
    template_shares: TemplateShares | None = None
    #: (N,) bool: points solved classically (m = 0, no window solve or check) because the
    #: time model failed there in the sampled frames (None: none)
    classical_points: torch.Tensor | None = None
    #: (T_series, N) int8: the longest half-width of each frame's window (as a target) at
    #: each point (:mod:`~torch_stsdic.movie.window_length`; None: ``m`` everywhere)
    window_lengths: torch.Tensor | None = None
    #: the blocks' counters on the device (name -> 0-d int64), summed block by block and
    #: added to :attr:`stats` by :meth:`read_counts` (one host read a run, not a block)
    pending: dict[str, torch.Tensor] = field(default_factory=dict)
    #: the blocks' answers "nothing to do" a next block may guess (a GPU's choice:
    #: :mod:`~torch_stsdic.movie.block_guess`)
    guesses: ReadGuesses = field(default_factory=ReadGuesses)
    _checker: SubsetSolver | None = None
    _on_grid: tuple[torch.Tensor, bool, bool] | None = None  # (points, whole px, inside)

    def read_counts(self) -> None:
        """The blocks' counters kept on the device (:attr:`pending`) added to :attr:`stats`
        in one read (those of ``_IF_ANY`` only where they count something)."""
        if not self.pending:
            return
        names = list(self.pending)
        values = torch.stack([self.pending[nm] for nm in names]).tolist()
        self.pending = {}
        for name, v in zip(names, values):
            if v or name not in _IF_ANY:
                self.stats[name] = self.stats.get(name, 0) + v

    def host_segments(self) -> torch.Tensor | None:
        """:attr:`segments` on the host: :attr:`segments_host` where kept, else a copy."""
        if self.segments_host is not None or self.segments is None:
            return self.segments_host
        return self.segments.cpu()

    def point_facts(self, ref: Reference) -> tuple[bool, bool]:
        """Whether the reference's POIs are whole pixels (a grid's) and their centred subsets
        all inside the reference image: read once per set of points, then every solve is
        told (:meth:`SubsetSolver.solve`'s ``on_grid``, ``all_inside``), not testing it."""
        if self._on_grid is None or self._on_grid[0] is not ref.points:
            pts = ref.points
            inside = subset_inside(pts, float(self.solver.window.half), ref.img.height,
                                   ref.img.width)
            grid, all_in = torch.stack([(pts == pts.round()).all(), inside.all()]).tolist()
            self._on_grid = (pts, bool(grid), bool(all_in))
        return self._on_grid[1], self._on_grid[2]

    def grid_neighbours(self, ref: Reference) -> torch.Tensor:
        """(N, k) the POIs' grid neighbours (:func:`~torch_stsdic.analysis.quality.neighbours`),
        made
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



class Block(BlockChecks, BlockRescue, BlockPlacement, BlockMotion, BlockWindows,
            BlockGuesses):
    """The rows (target frame x POI, row = target * N + point) of one block being solved:
    parameters relative to the current reference, ZNCC, status, iterations."""

    def __init__(self, run: BlockContext, ks: list[int], ref: Reference) -> None:
        self.run, self.ks, self.ref = run, ks, ref
        dev = run.device
        host_k = torch.tensor(ks, dtype=torch.long)
        self.k = upload(host_k, dev)
        self._col_index: dict[tuple, torch.Tensor] = {}  # :meth:`_columns`
        self._init_windows()
        # sorted; every half-width's windows' frames: from host facts (no read of a device)
        needed = block_frames(host_k, run.m, run.n_series, run.host_segments())
        self.needed = upload(torch.tensor(needed, dtype=torch.long), dev)
        ring = run.cache.in_ring(needed)  # only new frames copied
        # the frames' stack, addressed by plane (self.planes[j]: frame self.needed[j])
        # the pixels only where a solve asks for them (:attr:`RingView.raw`: the FFT guess)
        self.ring, self.img, self.pyramids = ring, ring.img, ring.pyramids
        self.planes = upload(torch.as_tensor(ring.planes, dtype=torch.long), dev)
        ref.ensure(run.cache)
        if run.noise_ratio is None:
            run.noise_ratio = noise_ratio(run.reference_desc, ref.raw, ring.frames_raw())
        self.b, self.n = len(ks), ref.points.shape[0]
        self.pts = ref.points.repeat(self.b, 1)  # (B*N, 2)
        self.fidx, self.dt = self.window_rows(run.m)
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
        self.has_identity = False  # whether any is (known on the host: no read)
        #: (B*N, 2) px where each row's subset is centred, or None: at its POI everywhere
        #: (:meth:`keep_outside` moves the subsets of points near the border inside)
        self.centres: torch.Tensor | None = None
        #: how many rows' subsets are off their POIs (at :attr:`centres`; read where they
        #: were moved, so that no later step reads it again)
        self.off_count = 0
        #: (B*N,) int8 the half-window a row is first solved with, or None: the run's m
        #: everywhere (:meth:`keep_outside` shortens it where the point leaves the image)
        self.window_m: torch.Tensor | None = None
        #: (B*N,) int8 the longest half-width a row may take at all (the measured motion's
        #: limit at its point and target, 0 where the time model failed), or None: the
        #: run's m; every row's :attr:`window_m` stays within it, a rescued row's too
        self.window_cap: torch.Tensor | None = None
        #: every row's subset (at :attr:`centres` where moved) lies inside the reference
        #: image: the solves need not find the others (made with the centres)
        self.centres_inside = True
        self.deferred = []  # the guessed answers not read yet (:class:`BlockGuesses`)
        self.heard_sites = set()  # the masked solves' sites whose counts it read
        self._init_motion()
        # the POIs' reference subsets kept for every solve of the block (one host read)
        self.kept = ref.kept_by(run.solver, inside=all(run.point_facts(ref)))

    def solve(self, idx: torch.Tensor, init: torch.Tensor | None,
              m: int | torch.Tensor | None = None, solver: SubsetSolver | None = None,
              init_step: torch.Tensor | None = None, for_check: bool = True,
              active: torch.Tensor | None = None, site: str | None = None) -> WindowSolution:
        """Solve rows ``idx`` from ``init`` (None: FFT) with windows of half-width ``m``
        (default the run's; m = 0: the target frame alone, classical shape; (R,) each row's
        own, 1 .. the run's, in one call: :meth:`mixed_rows`, needs ``init``), with ``solver``
        (default the run's); subsets at :attr:`centres` where :meth:`keep_outside` moved them
        inside the image (the results are the POIs'). ``for_check``: the model check will
        judge these rows (a window solve then gives it its first classical step); False
        for the check's own solves. ``active`` (R,) bool: only those rows solved, the others
        masked (no read: ``SubsetSolver.solve``'s; None: all); with ``site`` (the caller's
        name) at most a learned number of them solved where the block guesses
        (:meth:`~torch_stsdic.movie.block_guess.BlockGuesses.compact`: the same solution)."""
        capacity = None
        if active is not None and site is not None and init is not None:
            capacity = self.compact(site, active)
        ref, run = self.ref, self.run
        count = None
        if isinstance(m, torch.Tensor):  # windows of mixed length (1 .. run.m), one call
            fidx, dt, count = self.mixed_rows(idx, m)
            m_eff, motion = run.m, self.mixed_motion(idx, m)
        else:
            if m is None or m == run.m:
                fidx, dt = self.fidx[idx], self.dt[idx]
            else:
                fidx, dt = self.window_rows(m)
                fidx, dt = fidx[idx], dt[idx]
            if m == 0 and run.m > 0 and init is not None and init.shape[1] == len(run.names):
                spatial = run.solver.shape.spatial().param_names
                init = init[:, [run.names.index(nm) for nm in spatial]]
            m_eff = run.m if m is None else m
            motion = self.motion_of(m_eff)
            motion = None if motion is None else motion[idx]
        on_grid, inside = run.point_facts(ref)
        return (solver or run.solver).solve(
            ref.img, self.img, self.pts[idx], dt, frame_index=fidx,
            init=init, ref_pixels=ref.raw.unsqueeze(0),
            frame_pixels=self.ring.raw if init is None else None,  # (read by the FFT only)
            pyramids=(ref.pyramids(), self.pyramids),
            noise_ratio=run.noise_ratio, motion=motion,
            centres=None if self.centres is None else self.centres[idx],
            # the model check's first classical step, from the window solve's last step
            classical_step=run.checks and m_eff > 0 and solver is None and for_check,
            init_step=init_step,
            # known per run: the POIs' grid (the centres are whole pixels from them) and
            # the shape (a window of 2m+1 frames at distinct times has temporal terms)
            on_grid=on_grid, has_time=m_eff > 0, all_inside=inside and self.centres_inside,
            kept=self.kept, frame_count=count, active=active, capacity=capacity)

    def solve_masked(self, idx: torch.Tensor, init: torch.Tensor, active: torch.Tensor,
                     m: int | None = None, site: str | None = None) -> WindowSolution:
        """Rows ``idx`` (R,) solved from ``init`` (R, P) where ``active`` (R,) bool, the
        others masked (:meth:`solve`'s ``active``: no read of which; their guesses, NaN or
        not, are not used and go in as 0). A caller's data-chosen rows of a fixed set, on a
        GPU's choices (:data:`~torch_stsdic.core.choices.MASKED_GROUPS`); ``site``:
        :meth:`solve`'s."""
        return self.solve(idx, torch.where(active.unsqueeze(1), init, 0.0), m=m,
                          active=active, site=site)

    def keep(self, idx: torch.Tensor, sol: WindowSolution, only_better: bool,
             m: int | torch.Tensor | None = None, where: torch.Tensor | None = None) -> None:
        """Store ``sol`` (solved with half-window ``m``, default the run's; (R,): each
        row's own) at rows ``idx`` (with ``only_better``: where it is usable and the stored
        result is not, or its ZNCC is higher; ``where`` (R,) bool: those rows only, as if
        ``idx[where]`` were given).
        Parameters missing from ``sol`` (a classical solution has no ut, vt) are NaN."""
        self.iters[idx] += sol.iterations if where is None else torch.where(
            where, sol.iterations, 0)
        dt = self.run.dtype
        take = where  # (R,) bool the rows stored (None: every row)
        if only_better:
            old_ok = self.status[idx] <= USABLE
            take = (sol.status <= USABLE) & (~old_ok | (sol.zncc.to(dt) > self.zncc[idx]))
            take |= self.status[idx] == int(Status.NOT_COMPUTED)  # a reason beats none
            if where is not None:
                take &= where

        def put(dst: torch.Tensor, new: torch.Tensor | float) -> None:  # no host read
            dst[idx] = new if take is None else torch.where(
                take.view(-1, *([1] * (dst.dim() - 1))), new, dst[idx])
        cols = [sol.param_names.index(nm) if nm in sol.param_names else -1
                for nm in self.run.names]
        put(self.params, self._columns(sol.params, cols))
        put(self.std, self._columns(sol.std, cols, rows=idx.numel()))
        cstep = packed_classical_step(sol.info) if "classical_step" in sol.info else None
        if cstep is not None and self.check_start is None:
            self.check_start = torch.full((self.params.shape[0], cstep.shape[1]), float("nan"),
                                          dtype=self.params.dtype, device=self.params.device)
        if self.check_start is not None:
            put(self.check_start, float("nan") if cstep is None else cstep.to(dt))
        put(self.zncc, sol.zncc.to(dt))
        put(self.status, sol.status)
        if sol.sigma is not None:
            put(self.sigma, sol.sigma.to(dt))
        put(self.m_used, self.run.m if m is None else m)

    def _columns(self, a: torch.Tensor | None, cols: list[int], rows: int = 0) -> torch.Tensor:
        """(R, P) the run's parameter columns taken from ``a`` (R, P') (NaN where ``cols``
        is -1 or ``a`` is None)."""
        dev, dt = self.run.device, self.run.dtype
        if a is None:
            return torch.full((rows, len(cols)), float("nan"), dtype=dt, device=dev)
        if cols == list(range(a.shape[1])) and a.shape[1] == len(cols):
            return a.to(dt)
        pad = torch.cat([a.to(dt), torch.full_like(a[:, :1], float("nan"), dtype=dt)], 1)
        key = (tuple(cols), a.shape[1])  # the index on the device once a block (a copy)
        if key not in self._col_index:
            self._col_index[key] = upload(torch.tensor([c if c >= 0 else a.shape[1]
                                                        for c in cols]), dev)
        return pad[:, self._col_index[key]]

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
        self.has_identity = self.ref.frame in self.ks  # (a target's window at m = 0 is
        if not self.has_identity:                      # the target: no read)
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
        self.gone |= out  # final: not rescued (a rescue would move the subset inside)
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

    def init_rows(self, values: dict[str, torch.Tensor]) -> torch.Tensor:
        """(R, P) initial parameters from relative values by name (missing ones zero)."""
        some = next(iter(values.values()))
        return torch.stack([values[nm] if nm in values else torch.zeros_like(some)
                            for nm in self.run.names], 1)


def _only_identity(run: BlockContext, ref: Reference, carry: Carry) -> bool:
    """The carry is the classical row of the reference frame itself (the identity, no
    velocity): the next block starts as the first one, by FFT cross-correlation (at seed
    points: fewer Gauss-Newton steps than from zero motion; a pair: 3.7 instead of 6.1)."""
    return (run.m == 0 and ref.frame >= 0 and ref.acc is None
            and carry.t == float(run.times[ref.frame])
            and carry.vel_known is not None and not bool(carry.vel_known.any()))


#: counters of a block kept in the run's statistics only where they count something
_IF_ANY = ("neighbour_rows",)


def _window_cap(run: BlockContext, blk: Block) -> torch.Tensor | None:
    """(B*N,) int8 the longest half-width each row of ``blk`` may take: the measured
    motion's (``run.window_lengths`` at its target), 0 at the points where the time model
    failed (``run.classical_points``); None: the run's m everywhere."""
    if run.m == 0:
        return None
    cap = None if run.window_lengths is None else run.window_lengths[blk.k].reshape(-1).to(
        device=run.device, dtype=torch.int8)
    if run.classical_points is not None:  # the time model failed there
        cls = run.classical_points.to(run.device).repeat(blk.b)
        cap = torch.where(cls, 0, run.m if cap is None else cap).to(torch.int8)
    return cap


def _first_guess_rows(run: BlockContext, blk: Block, ref: Reference) -> torch.Tensor:
    """(B*N, P) the block's rows from ``run.first_guess`` (NaN rows where it has none)."""
    guess = run.first_guess.guess(ref.points, blk.windows(run.m), blk.dt[::blk.n])
    # (made on the host: its fields in one copy to the device, not waited for)
    fields = upload(torch.stack(list(guess.values())), run.device).to(run.dtype)
    return blk.init_rows(dict(zip(guess, fields.unbind(0))))


def _carried_start(run: BlockContext, blk: Block, ref: Reference, carry: Carry,
                   count: Callable[[str, torch.Tensor | int], None]
                   ) -> tuple[Carry, torch.Tensor, torch.Tensor, torch.Tensor | None,
                              torch.Tensor | None]:
    """The block's rows started from ``carry``: the carry with lost points filled from
    their neighbours (:meth:`Carry.from_neighbours`), (B*N, P) the guesses (its prediction, the
    shake between the frames added; an earlier round's solution where ``run`` has one for
    every block), (B*N,) bool the rows that start from them, (B*N,) bool those from the
    earlier round (None: none) and (B*N, 2) the shared motion's part of the carried window
    velocity (None: none; :func:`~torch_stsdic.movie.block_start.window_shake`).
    ``count``: the block's counter."""
    b, n, dev = blk.b, blk.n, run.device
    shake_vel = has = None
    pts0 = ref.points if ref.acc is None else ref.points - torch.stack(
        [ref.acc["u"], ref.acc["v"]], 1)
    # the CPU: one read, whether any point is missing and how many; a GPU fills every
    # point's ring by ring, no read (:data:`~torch_stsdic.core.choices.UNTIL_DONE`)
    missing = int((~carry.valid).sum()) if until_done(dev) else None
    if missing is None or missing:
        carry, filled = carry.from_neighbours(run.grid_neighbours(ref), pts0, missing=missing)
        count("neighbour_rows", filled * b)
        if carry.left is not None:  # left the view, no neighbour in view: stays out
            out = (carry.left & ~carry.valid).repeat(b)
            blk.status.masked_fill_(out, int(Status.OUTSIDE))
            blk.gone |= out
    pred = carry.predict(run.ts[blk.k].to(run.dtype))
    if run.shared is not None and ref.acc is None:  # the shake between the frames
        held = carry.shared_slope(run.shared, ref.points, run.ts,  # (N, 2)
                                  run.segments if run.velocity_segments is None
                                  else run.velocity_segments, m_max=run.m)
        step = carry.shared_step(run.shared, ref.points, blk.k, run.ts, run.segments, held)
        pred["u"] = pred["u"] + step[..., 0].to(pred["u"])
        pred["v"] = pred["v"] + step[..., 1].to(pred["v"])
        if "ut" in pred:  # the specimen's own velocity: the windows add their shake's
            shake_vel = held.repeat(b, 1).to(run.dtype)  # (B*N, 2)
    pred = to_relative(pred, ref.acc)
    init = blk.init_rows({nm: v.reshape(-1) for nm, v in pred.items()})
    carried = carry.valid.repeat(b) & torch.isfinite(init).all(1)
    if run.guess_every_block and run.first_guess is not None and ref.acc is None:
        # an earlier round's solution of the row's own frames: closer than the carry
        # moved on over the frames between (the template's sampled frames are apart)
        g = _first_guess_rows(run, blk, ref)
        has = torch.isfinite(g).all(1)
        init = torch.where(has.unsqueeze(1), g, init)
        carried |= has
        count("first_guess_rows", has.sum())
    last = {nm: v.repeat(b) for nm, v in to_relative(dict(carry.vals), ref.acc).items()}
    carried &= ~blk.keep_outside((init, blk.init_rows(last)), carried, guess=True)
    if carry.vel_known is not None:  # without a velocity the carry predicts only the
        later = torch.arange(b, device=dev).repeat_interleave(n) > 0  # first target:
        keep = ~later | carry.vel_known.repeat(b)  # the later ones start from it
        carried &= keep if has is None else keep | has
    return carry, init, carried, has, shake_vel


def solve_block(run: BlockContext, ks: list[int], ref: Reference, carry: Carry | None):
    """Solve all POIs of target frames ``ks`` (B,) in one batched solve, then rescue lost
    rows (from the previous target of the block, their neighbours, then by FFT
    cross-correlation) and check them (``run.checks``); on a GPU the answers "nothing to
    do" of the last block guessed, not read (:func:`~torch_stsdic.movie.block_guess.
    solve_guessing`: the block solved again where one was wrong).

    Returns a dict of (B, N) tensors: total parameters by name, "zncc", "status",
    "iterations"."""
    return solve_guessing(run, lambda guessing: _solve_block(run, ks, ref, carry, guessing))


def _rescue_and_check(run: BlockContext, blk: Block, ks: list[int], carry: Carry | None,
                      carried: torch.Tensor, guess: torch.Tensor | None,
                      count: Callable[[str, torch.Tensor | int], None]) -> None:
    """The block's lost rows rescued and every row checked (:func:`solve_block`, after its
    solve; ``carried``: the rows started from ``carry``, ``guess`` their guesses), its
    guessed answers settled; ``count``: the block's counter."""
    from_prev, by_fft, redone = blk.rescue(carry, carried)
    if isinstance(from_prev, torch.Tensor):  # (rescue waves taken unread: not read yet)
        count("rescued_rows", from_prev)
    else:
        run.stats["rescued_rows"] = run.stats.get("rescued_rows", 0) + from_prev
    run.stats["fft_rows"] += by_fft
    count("redone_rows", redone)
    # the identity cannot fail (rows are the identity only where m = 0: no read otherwise)
    if run.checks and not (run.m == 0 and all(k == blk.ref.frame for k in ks)):
        shortened, classical = blk.check_model()
        if run.m > 0:
            classical = classical + blk.rescue_classical(guess, carry)
        count("shortened_rows", shortened)  # read with the other counters
        count("classical_rows", classical)
        count("poor_fit_rows", blk.check_fit(carry))
        count("inconsistent_rows", blk.check_neighbours())
    blk.settle_guesses()  # (its one read where every answer was guessed)


def _solve_block(run: BlockContext, ks: list[int], ref: Reference, carry: Carry | None,
                 guessing: bool):
    """:func:`solve_block`, its reads guessed where ``guessing``."""
    blk = Block(run, ks, ref)
    b, n, dev = blk.b, blk.n, run.device
    rows = b * n
    blk.window_cap = _window_cap(run, blk)
    counts: dict[str, torch.Tensor] = {}  # run.stats counted on the device, read at the end

    def count(name: str, value: torch.Tensor | int) -> None:
        if not isinstance(value, torch.Tensor):  # (filled on the device: no copy to it)
            value = torch.full((), int(value), dtype=torch.int64, device=dev)
        counts[name] = counts[name] + value if name in counts else value
    shake_vel = has = None  # see _carried_start
    if carry is not None and _only_identity(run, ref, carry):
        carry = None  # the reference frame's own row, no velocity: it predicts nothing
    # a guess is "as in the last block": only a block started as the last one was, from a
    # carry whose velocity is known everywhere (two rows or more), takes one. The first
    # block after the reference frame's own row starts from rest or a first guess, and
    # one after a block of one target starts its later targets in the rescue's waves
    # where that row measured no velocity: both lose rows where the block before lost none
    blk.guessing = guessing and carry is not None and carry.vel_known is None
    if carry is None and run.first_guess is not None and ref.acc is None:
        # no carry (the first block): start from the measuring pass's solutions
        init = _first_guess_rows(run, blk, ref)
        carried = torch.isfinite(init).all(1)
        carried &= ~blk.keep_outside((init,), carried)
        count("first_guess_rows", carried.sum())
    elif carry is None:
        carried = torch.zeros(rows, dtype=torch.bool, device=dev)
        init = None
    else:
        carry, init, carried, has, shake_vel = _carried_start(run, blk, ref, carry, count)
    ident = blk.keep_identity()
    carried &= ~ident
    pilot = None  # (B*N,) bool the pilot rows, solved already (None: none)
    if init is not None and run.m == 0 and run.shared is None and carry is not None:
        pilot = pilot_shift(blk, init, carried if has is None else carried & ~has)
    guess = None  # the carried rows' guesses (NaN: none; no test whether there are any)
    if init is not None:
        guess = torch.where(carried.unsqueeze(1), init, torch.full_like(init, float("nan")))
    cap = blk.window_cap
    if cap is not None:  # every row's window within what its point's motion supports
        blk.window_m = cap.clone() if blk.window_m is None else torch.minimum(blk.window_m,
                                                                              cap)
    if shake_vel is not None:
        window_shake(blk, init, carried if has is None else carried & ~has, shake_vel)
    if blk.window_m is not None:  # windows shortened (points leaving the image, the
        # motion's limit): every row with its own (one call where the solver mixes them)
        every = torch.arange(rows, device=dev)
        pick = carried if pilot is None else carried & ~pilot
        for r, m, sol, where in blk.solve_windows(every, blk.window_m, init, pick=pick):
            blk.keep(r, sol, only_better=False, m=m, where=where)
    elif init is not None and masked_groups(dev):  # every row, those not carried masked
        every, pick = torch.arange(rows, device=dev), carried if pilot is None else \
            carried & ~pilot
        blk.keep(every, blk.solve_masked(every, init, pick, site="carried"), only_better=False,
                 where=pick)
    elif init is not None:
        idx_c = torch.nonzero(carried if pilot is None else carried & ~pilot).flatten()
        if idx_c.numel():
            blk.keep(idx_c, blk.solve(idx_c, init[idx_c]), only_better=False)
    blk.from_here(counts, lambda: _rescue_and_check(run, blk, ks, carry, carried, guess,
                                                    count))
    for name, v in counts.items():  # kept on the device: read once, at the run's end
        v = v.reshape(()).to(torch.int64)
        run.pending[name] = run.pending[name] + v if name in run.pending else v
    rel = {nm: blk.params[:, j].reshape(b, n) for j, nm in enumerate(run.names)}
    out = to_total(rel, ref.acc)
    out["zncc"] = blk.zncc.reshape(b, n)
    out["status"] = blk.status.reshape(b, n)
    out["iterations"] = blk.iters.reshape(b, n)
    out["m"] = blk.m_used.reshape(b, n)
    vel_var = report_velocity(blk, out)  # the shared motion's part, in the reported terms
    refer_velocities(blk, out)  # the velocity at the POI, not the subset's centroid
    fac = None if run.template_shares is None else run.template_shares.variance_factors(
        blk.k, out["m"], run.ts, float(run.noise_ratio or 1.0), run.segments, m_max=run.m)
    for j, nm in enumerate(run.names):
        if nm in STD_OF:
            std = blk.std[:, j].reshape(b, n)
            if fac is not None:  # the template's noise shared with the frames
                std = std * fac[..., int(nm in ("ut", "vt"))].sqrt().to(std)
            if run.reference_var is not None and nm in ("u", "v"):
                std = (std.pow(2) + run.reference_var.to(std)).sqrt()
            if vel_var is not None and nm in ("ut", "vt"):
                std = (std.pow(2) + vel_var[..., int(nm == "vt")].to(std)).sqrt()
            out[STD_OF[nm]] = std
    return out


