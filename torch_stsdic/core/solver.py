"""Batched subset / STS-DIC solver: Gauss-Newton over all POIs of a window at once.

Notation (the paper's Eqs. 1-18): f is the reference image, g_t the 2m+1 deformed frames of
the window, (dx, dy) a subset pixel's offset from its POI, dt = t - t_c the frame time minus
the time the results refer to, and p the shape-function parameters, e.g.
(u, ux, uy, ut, v, vx, vy, vt). Every subset pixel of every POI in every frame is warped and
sampled in one batched interpolation call per iteration; the P x P normal equations of all
POIs are solved together.

Formulations:

* ``joint``: minimise sum_t C(f, g_t(W(x; p, t))) by inverse-compositional Gauss-Newton
  (IC-GN). The Jacobian uses the reference gradient, so the Hessian is formed and
  Cholesky-factored once per POI; each iteration only samples the frames' values.
* ``average``: the paper's own model, C(f, G) with G the average of the 2m+1 warped frames
  (Eqs. 2, 11, 14), forward-additive Gauss-Newton with the Jacobian of Eq. 16 and the
  Gauss-Newton Hessian of Eq. 18.
* ``joint+average``: ``joint`` first (it finds the velocity), then the spatial unknowns are
  refined with ``average`` at the joint velocity.
* ``auto`` (default): ``joint``. It measured the most accurate of the three (the forward-
  additive ``average`` uses the gradient of the noisy warped frames, whose correlation with
  the interpolated noise biases u by ~1e-2 px at sigma = 5) and the fastest (the Hessian is
  factored once). See the README for the measurements behind this choice.

The ZNSSD criterion is solved in its variable-projection form: the residual is
f~ - a g~ with f~, g~ the zero-mean subsets and a the least-squares scale, which makes the
fixed point exactly the ZNCC maximum.
"""

from __future__ import annotations

import time as _time
import weakref

import torch

from torch_stsdic.core import choices, formulations
from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.formulations import Formulation, Geometry
from torch_stsdic.core.gauss_newton import (
    BatchContext,
    KeptToken,
    ReferenceCache,
    classical_step_width,
    keep_subsets,
    missing_subsets,
    solve_batch,
)
from torch_stsdic.core.initial import (
    carry_from_seed,
    fft_cross_correlation,
    linear_fit_in_time,
    retry_weak_peaks,
    seed_cells,
    walk_weak_frames,
)
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.offgrid import carry_params, carry_solution, snap_points
from torch_stsdic.core.pyramid import PyramidStack
from torch_stsdic.core.shape import ShapeFunction, make_shape
from torch_stsdic.core.solution import (
    WindowSolution,
    classical_step_info,
    packed_classical_step,
)
from torch_stsdic.core.solve_inputs import (
    active_rows,
    checked_centres,
    expand_init,
    frame_counts,
    per_point,
    per_point_motion,
)
from torch_stsdic.core.status import Status
from torch_stsdic.core.window import SubsetWindow, make_window
from torch_stsdic.kernels.native.rows import in_own_threads, own_threads

__all__ = ["WindowSolution", "SubsetSolver", "subset_inside"]


class SubsetSolver:
    """The solver with its configuration resolved into modules (shape, window).

    ``prepare`` does the per-image work (B-spline prefilter) once; ``solve`` does the
    per-point work. :func:`solve_window` wraps both for one window. ``solve`` is general:
    every POI can use its own reference (``ref_index``), its own frames (``frame_index``)
    and its own frame times (``dt``), so several windows of a movie, or a batch of
    sequences, are solved as one set of tensor operations.
    """

    def __init__(self, config: DICConfig | None = None) -> None:
        self.config = config if config is not None else DICConfig()
        self.config.validate()
        self.shape = make_shape(self.config.shape)
        self.window = make_window(self.config.window, self.config.subset_size)
        #: the reference subsets kept between this solver's solves
        #: (:class:`~torch_stsdic.core.gauss_newton.ReferenceCache`; set by a run, None: none)
        self.reference_cache: ReferenceCache | None = None
        self._grey_memo: tuple | None = None  # (weakref to the pixels, their version, range)
        #: :meth:`_geometry`'s geometries by their host facts (no tensors made again a solve)
        self._geometries: dict[tuple, tuple[SubsetWindow, Geometry]] = {}

    def prepare(self, images: torch.Tensor) -> BSplineImage:
        """Prefilter (T, H, W) or (H, W) images into B-spline coefficients."""
        with own_threads(images.device):
            return BSplineImage(images, order=self.config.interpolation_order)

    def __getstate__(self) -> dict:
        # a weak reference does not pickle; the geometries are made again where needed
        return {**self.__dict__, "_grey_memo": None, "_geometries": {}}

    def _geometry(self, shape: ShapeFunction, dtype: torch.dtype,
                  device: torch.device | str) -> Geometry:
        """:meth:`Geometry.make` of this solver's window and criterion for ``shape``, kept
        for the next solve with the same host facts (built-in window and shape: their kinds,
        settings, dtype and device; others made every time). Read, not written, by the
        solves."""
        key = (id(self.window), self.window.extra_repr(), self.config.criterion,
               type(shape).__name__,
               tuple(shape.param_names), str(dtype), str(torch.device(device)))
        held = self._geometries.get(key)
        if held is not None and held[0] is self.window:
            return held[1]
        geo = Geometry.make(shape, self.window, self.config.criterion, dtype, device)
        if geo.key is not None:  # a built-in window and shape: its tensors are its facts'
            self._geometries[key] = (self.window, geo)
        return geo

    def _grey_range_of(self, grey: torch.Tensor) -> float:
        """:func:`_grey_range` of the reference's pixels, kept while they are the same
        unchanged pixels (a run solves hundreds of times against one reference, each time
        with a new view of it: 1 ms a call on 1 Mpx)."""
        root = grey if grey._base is None else grey._base
        key = (root._version, tuple(grey.shape), grey.stride(), grey.storage_offset())
        memo = self._grey_memo
        if memo is not None and memo[0]() is root and memo[1] == key:
            return memo[2]
        value = _grey_range(grey)
        self._grey_memo = (weakref.ref(root), key, value)
        return value

    def stages_for(self, shape: ShapeFunction) -> list[Formulation]:
        """The Gauss-Newton stages (formulations) run for ``shape`` (see :func:`shape_for`)."""
        return formulations.stages(self.config.formulation, shape)

    def mixed_windows(self, shape: ShapeFunction) -> bool:
        """Whether :meth:`solve` takes windows of different lengths in one call
        (``frame_count``) for ``shape``: every stage is the joint inverse-compositional one
        (its Hessian, kernels and uncertainty sum over each row's own frames)."""
        return all(isinstance(f, formulations.JointIC) for f in self.stages_for(shape))

    def keep_reference_subsets(self, ref: BSplineImage, points: torch.Tensor,
                               missing: int | None = None, inside: bool = False,
                               capacity: int | None = None) -> KeptToken | None:
        """Put the reference subsets of ``points`` (N, 2) (their dtype the solves'; at the
        whole pixels a solve snaps them to) of ``ref`` (reference 0) in
        :attr:`reference_cache` (one host read; none with ``missing``, the count of
        :meth:`missing_reference_subsets` read by the caller), and return the token that lets
        a later :meth:`solve` of any of them (``kept=``) read them there with no host read;
        None where the cache does not serve them. ``inside``: every point is a whole pixel
        whose subset lies inside ``ref`` (known to the caller: not read). ``capacity``: the
        count not read, at most that many kept (``ReferenceCache.drop_padding`` after)."""
        ctx = self._cache_context(ref, points)
        return None if ctx is None else keep_subsets(ctx, points, missing, inside, capacity)

    def missing_reference_subsets(self, ref: BSplineImage, points: torch.Tensor
                                  ) -> torch.Tensor | None:
        """(0-d int64 on the device, not read) the distinct pixels of ``points`` whose
        subsets :meth:`keep_reference_subsets` would sample; None where the cache does not
        serve them."""
        ctx = self._cache_context(ref, points)
        return None if ctx is None else missing_subsets(ctx, points)

    def _cache_context(self, ref: BSplineImage, points: torch.Tensor) -> BatchContext | None:
        if self.reference_cache is None or points.shape[0] == 0:
            return None
        geo = self._geometry(self.shape, points.dtype, points.device)
        return BatchContext(geo=geo, ref=ref, frames=ref, cfg=self.config,
                            stages=self.stages_for(self.shape), grey_range=1.0,
                            cache=self.reference_cache, on_grid=True)

    def shape_for(self, dt: torch.Tensor, has_time: bool | None = None) -> ShapeFunction:
        """The shape function used for frame offsets ``dt``: without temporal terms when all
        frames are at the same time (one frame, m = 0: classical DIC). ``has_time``: that
        answer known to the caller (a movie's window of 2m+1 frames has distinct times
        where m > 0), so ``dt`` is not read on the host (None: read)."""
        if has_time is None:
            has_time = dt.shape[-1] > 1 and float(dt.abs().max()) > 0
        return self.shape if has_time else self.shape.spatial()

    # ------------------------------------------------------------------------------------
    @in_own_threads(3, "points")  # on the CPU: torch on one thread, the work on the pool
    def solve(
        self,
        ref: BSplineImage,
        frames: BSplineImage,
        points: torch.Tensor,
        dt: torch.Tensor,
        *,
        frame_index: torch.Tensor | None = None,
        ref_index: torch.Tensor | None = None,
        init: torch.Tensor | None = None,
        ref_pixels: torch.Tensor | None = None,
        frame_pixels: torch.Tensor | None = None,
        time: float | torch.Tensor = 0.0,
        noise_ratio: float = 1.0,
        motion: torch.Tensor | None = None,
        centres: torch.Tensor | None = None,
        classical_step: bool = False,
        init_step: torch.Tensor | None = None,
        pyramids: tuple[PyramidStack, PyramidStack] | None = None,
        on_grid: bool = False,
        has_time: bool | None = None,
        all_inside: bool = False,
        kept: KeptToken | None = None,
        frame_count: torch.Tensor | None = None,
        active: torch.Tensor | None = None,
        capacity: int | None = None,
    ) -> WindowSolution:
        """Solve many POIs, each against its own window of frames.

        Args:
            ref: prepared reference image(s) (R frames).
            frames: prepared deformed frames (F frames).
            points: (N, 2) POIs (x, y) in px; its dtype is the computation's.
            dt: (T,) or (N, T) frame times minus the time the results refer to.
            frame_index: (T,) or (N, T) indices into ``frames`` (default 0..T-1).
            ref_index: (N,) indices into ``ref`` (default 0).
            init: (N, P) initial parameters, or None for FFT cross-correlation (which needs
                ``ref_pixels`` (R, H, W) and ``frame_pixels`` (F, H, W)).
            time: reported as ``WindowSolution.time``.
            noise_ratio: the reference's noise variance over one frame's (1 for a single
                frame, 1/K for a mean of K frames), for the predicted uncertainty.
            motion: (T, 2) or (N, T, 2) a known displacement (u, v) px of every frame added
                to the warp (shared motion): the parameters are the motion besides it.
            centres: (N, 2) px where each POI's subset is centred (default: the POI): an
                off-centre subset, e.g. one kept inside the image where its point nears the
                border. ``init`` and ``motion`` are the POI's and the centre's; the solution is
                carried to the POI by the subset's own gradients (:mod:`~torch_stsdic.core.offgrid`:
                u += ux dx + uy dy, its std with it).
            classical_step: also ``info["classical_step"]`` (N, 2 Ks): each converged POI's
                classical solution (the parameters of :meth:`shape_for` one frame) after one
                Gauss-Newton step from its solution at dt = 0, taken from the last step's
                frame-by-frame right-hand sides at no cost (the model check starts there);
                NaN where not known (another path than the native CPU kernel, no frame at
                dt = 0, an off-grid or off-centre subset, not converged); with it
                ``info["classical_step_size"]`` (N,) that step's size ``|dp * scale|`` px,
                and what a classical solve would report there: ``"classical_step_zncc"``,
                ``"classical_step_sigma"`` (grey levels), ``"classical_step_std"``
                (:func:`~torch_stsdic.core.gauss_newton.classical_step_columns`).
            init_step: (N,) the size of the Gauss-Newton step that gave ``init`` (e.g.
                ``info["classical_step_size"]`` with ``init`` the classical step; NaN or 0:
                none): the first step's convergence test predicts the next increment from the
                rate between the two (a point whose first step shrank enough stops).
            pyramids: the Gaussian pyramids (:class:`~torch_stsdic.core.pyramid.PyramidStack`)
                of ``ref_pixels`` and ``frame_pixels`` for the search of weak peaks, kept by
                a caller that solves the same images again (default: built when needed).
            on_grid: the caller knows that ``points`` (and ``centres``) are whole pixels
                (a run's grid of POIs): they are not tested on the host; with ``centres``
                every POI goes the off-centre way (a zero offset carries a solution
                unchanged). False: tested.
            has_time: the shape has temporal terms (:meth:`shape_for`), as the caller
                knows; None: decided from ``dt``'s values.
            all_inside: the caller knows that every subset (at ``centres`` where given)
                lies inside ``ref`` (:func:`subset_inside`): the rows are not chosen on the
                host. False: the subsets outside are found and left OUTSIDE.
            kept: :meth:`keep_reference_subsets`'s token for these points (and
                ``centres``): their reference subsets are read from the cache with no host
                read of its misses. None: the misses are counted (one host read a batch).
            frame_count: (N,) int, windows of mixed length: row i's first ``frame_count[i]``
                columns of ``dt``, ``frame_index``, ``motion``. Needs ``init``, temporal
                terms, :meth:`mixed_windows`. None: all T.
            active: (N,) bool, the rows to solve; the others are not iterated (a zero inverse
                Hessian in the per-point kernels: next to no work on a GPU), NOT_COMPUTED
                with NaN parameters, with no host read (a caller's data-chosen rows of a
                fixed set: fixed shapes). Needs ``init``. None: every row.
            capacity: with ``active``, only the first ``capacity`` active rows solved
                (``nonzero_static``: no read; the others as rows not active: the caller
                checks the count), the masked rows not prepared. None: all prepared.
        """
        active = active_rows(active, points, init, capacity)
        frame_count = self._frame_counts(frame_count, points, dt, init, has_time)
        centres, moved = checked_centres(centres, points)
        if on_grid and centres is None:  # the caller's fact: no offset to test
            return self._solve_on_grid(ref, frames, points, dt, frame_index, ref_index, init,
                                       ref_pixels, frame_pixels, time, noise_ratio, motion,
                                       classical_step, init_step, pyramids, has_time,
                                       all_inside, kept, frame_count, active, capacity)
        grid, _ = snap_points(points if centres is None else centres)
        offset = points - grid
        # off the pixel grid (known where the caller says so): solve on it, carry the result
        if on_grid or bool((offset != 0).any()):
            if moved is not None and init is not None and (on_grid or bool(moved.any())):
                init = self._init_at(init, dt, torch.where(moved, grid - points, 0.0),
                                     has_time)
            sol = self.solve(ref, frames, grid, dt, frame_index=frame_index,
                             ref_index=ref_index, init=init, ref_pixels=ref_pixels,
                             frame_pixels=frame_pixels, time=time, noise_ratio=noise_ratio,
                             motion=motion, classical_step=classical_step,
                             init_step=init_step, pyramids=pyramids, on_grid=True,
                             has_time=has_time, all_inside=all_inside, kept=kept,
                             frame_count=frame_count, active=active, capacity=capacity)
            if classical_step:  # known at the subset centre only
                off = (offset != 0).any(1, keepdim=True)
                sol.info.update(classical_step_info(packed_classical_step(sol.info).masked_fill(
                    off, float("nan"))))
            # points on the grid moved to off-centre subsets: none snapped to a pixel
            return carry_solution(sol, points, offset, snapped=0 if on_grid else None)
        return self._solve_on_grid(ref, frames, points, dt, frame_index, ref_index, init,
                                   ref_pixels, frame_pixels, time, noise_ratio, motion,
                                   classical_step, init_step, pyramids, has_time, all_inside,
                                   kept, frame_count, active, capacity)

    def _frame_counts(self, count, points, dt, init, has_time) -> torch.Tensor | None:
        """:meth:`solve`'s ``frame_count`` checked (:func:`frame_counts`; None: None)."""
        if count is None:
            return None
        shape = self.shape if has_time is None else self.shape_for(dt, has_time)
        return frame_counts(count, points, init, self.mixed_windows(shape),
                            self.config.formulation)

    def _solve_on_grid(self, ref: BSplineImage, frames: BSplineImage, points: torch.Tensor,
                       dt, frame_index, ref_index, init, ref_pixels, frame_pixels, time,
                       noise_ratio: float, motion, classical_step: bool, init_step,
                       pyramids=None, has_time: bool | None = None,
                       all_inside: bool = False, kept: KeptToken | None = None,
                       frame_count: torch.Tensor | None = None,
                       active: torch.Tensor | None = None,
                       capacity: int | None = None) -> WindowSolution:
        """:meth:`solve` for POIs on the pixel grid with centred subsets."""
        n = points.shape[0]
        dt, frame_index, ref_index = per_point(points, dt, frame_index, ref_index, frame_count)
        motion = per_point_motion(motion, n, dt.shape[-1], points)
        shape = self.shape_for(dt, has_time)
        inside = subset_inside(points, float(self.window.half), ref.height, ref.width)
        if init is None:
            if ref_pixels is None or frame_pixels is None:
                raise ValueError("solve needs init or the raw images for the FFT initial guess")
            plan = self._seed_plan(points, inside, dt, frame_index, ref_index)
            if plan is not None:
                return self._solve_seeded(
                    plan, ref, frames, points, dt, frame_index, ref_index, ref_pixels,
                    frame_pixels, time, inside, noise_ratio, motion, classical_step, pyramids,
                )
        p0, t_fft = self._initial_params(shape, init, inside, points, dt, frame_index,
                                         ref_index, ref_pixels, frame_pixels, motion, pyramids)
        if init_step is not None:
            init_step = torch.as_tensor(init_step).to(device=points.device, dtype=points.dtype)
            if init_step.numel() != n:
                raise ValueError(f"init_step must be (N,) with a value for each of the {n} "
                                 f"points, got {tuple(init_step.shape)}")
            init_step = init_step.reshape(n)
        guess = {"method": "fft" if init is None else "given", "fft_s": t_fft}
        return self._solve_batches(ref, frames, shape, points, dt, frame_index, ref_index,
                                   inside, p0, motion, init_step, ref_pixels, time,
                                   noise_ratio, classical_step, guess, all_inside, kept,
                                   frame_count, active, capacity)

    def _initial_params(self, shape: ShapeFunction, init, inside: torch.Tensor,
                        points: torch.Tensor, dt: torch.Tensor, frame_index: torch.Tensor,
                        ref_index: torch.Tensor, ref_pixels, frame_pixels, motion,
                        pyramids=None) -> tuple[torch.Tensor, float]:
        """The starting parameters (N, P) of a solve, and the seconds the FFT guess took:
        ``init`` checked and expanded to ``shape``, or FFT cross-correlation (init None) at
        the rows ``inside`` (on a GPU at every row, the others' answers dropped: no read,
        :data:`~torch_stsdic.core.choices.SEARCH_READS`)."""
        device, dtype = points.device, points.dtype
        n, p_count = points.shape[0], shape.n_params
        if init is None:
            p0 = torch.zeros(n, p_count, dtype=dtype, device=device)
            t_fft = _clock(device)
            if not choices.search_reads(device):  # every row searched, no read of which
                # are inside; the others' answers dropped (a row's answer is its own)
                p = self.initial_guess(shape, ref_pixels, frame_pixels, points, dt,
                                       frame_index, ref_index, motion=motion,
                                       pyramids=pyramids)
                return torch.where(inside.unsqueeze(1), p, p0), _clock(device) - t_fft
            if inside.any():
                p0[inside] = self.initial_guess(
                    shape, ref_pixels, frame_pixels, points[inside], dt[inside],
                    frame_index[inside], ref_index[inside],
                    motion=None if motion is None else motion[inside], pyramids=pyramids,
                )
            return p0, _clock(device) - t_fft
        p0 = torch.as_tensor(init).to(device=device, dtype=dtype)
        if p0.dim() != 2 or p0.shape[0] != n:
            raise ValueError(f"init must be (N, P) with a row for each of the {n} points, "
                             f"got {tuple(p0.shape)}")
        if p0.shape[1] != p_count:
            p0 = expand_init(p0, shape, self.shape)
        return p0, 0.0

    def _solve_batches(self, ref: BSplineImage, frames: BSplineImage, shape: ShapeFunction,
                       points: torch.Tensor, dt: torch.Tensor, frame_index: torch.Tensor,
                       ref_index: torch.Tensor, inside: torch.Tensor, p0: torch.Tensor,
                       motion, init_step, ref_pixels, time, noise_ratio: float,
                       classical_step: bool, guess: dict, all_inside: bool = False,
                       kept: KeptToken | None = None,
                       frame_count: torch.Tensor | None = None,
                       active: torch.Tensor | None = None,
                       capacity: int | None = None) -> WindowSolution:
        """Gauss-Newton from ``p0`` for the POIs ``inside`` (and ``active``, at most
        ``capacity`` of them: :meth:`solve`), in batches within the memory budget
        (:func:`~torch_stsdic.core.gauss_newton.solve_batch`); the others OUTSIDE."""
        cfg = self.config
        device, dtype = points.device, points.dtype
        n, p_count, t_count = points.shape[0], shape.n_params, dt.shape[-1]
        # every row where the caller knows all subsets inside (no host synchronisation); at
        # most ``capacity``: the first rows to solve, -1 the padding (into a spare row)
        if capacity is None:
            todo = None if all_inside else torch.nonzero(inside).flatten()
        else:
            todo = torch.nonzero_static(active if all_inside else active & inside,
                                        size=capacity, fill_value=-1).flatten()
        spare = int(capacity is not None)
        grey = ref_pixels if ref_pixels is not None else ref.coeffs
        geo = self._geometry(shape, dtype, device)
        ctx = BatchContext(
            geo=geo, ref=ref, frames=frames, cfg=cfg, stages=self.stages_for(shape),
            grey_range=self._grey_range_of(grey),
            work=(n if todo is None else int(todo.numel())) * t_count * int(geo.w.numel()),
            noise_ratio=float(noise_ratio), cache=self.reference_cache,
            classical_step=classical_step, on_grid=True,  # reached with grid points only
            kept=kept,
        )
        batch = cfg.batch_points or ctx.batch_size(t_count)
        if todo is None and 0 < n <= batch:  # one batch of every row: its answers as they
            # are (no buffers to gather the rows from and scatter them into: launches)
            pr, zr, status, iters, p1, sd, sg, cs = solve_batch(
                ctx, points, p0, dt, frame_index, ref_index, motion, init_step, frame_count,
                active)
            params, zncc, first_stage = pr.to(dtype), zr.to(dtype), p1.to(dtype)
            std, sigma = sd.to(dtype), sg.to(dtype)
            cstep = cs.to(dtype) if classical_step else None
        else:
            if todo is None:
                todo = torch.arange(n, device=device)
            rows = n + spare  # (the results of a padding row go to the spare row, dropped)
            status = torch.full((rows,), int(Status.NOT_COMPUTED), dtype=torch.int8,
                                device=device)
            params = torch.full((rows, p_count), float("nan"), dtype=dtype, device=device)
            zncc = torch.full((rows,), float("nan"), dtype=dtype, device=device)
            iters = torch.zeros(rows, dtype=torch.int32, device=device)
            # no host sync (and the rows not to solve: none of their facts)
            status[:n].masked_fill_(~inside if active is None else ~inside & active,
                                    int(Status.OUTSIDE))
            first_stage = torch.full_like(params, float("nan"))
            std = torch.full_like(params, float("nan"))
            sigma = torch.full_like(zncc, float("nan"))
            cstep = (torch.full((rows, classical_step_width(geo.ks)), float("nan"), dtype=dtype,
                                device=device) if classical_step else None)
            for s0 in range(0, todo.numel(), batch):
                dest = todo[s0 : s0 + batch]
                idx = dest.clamp(min=0) if spare else dest
                pr, zr, sr, ir, p1, sd, sg, cs = solve_batch(
                    ctx, points[idx], p0[idx], dt[idx], frame_index[idx], ref_index[idx],
                    None if motion is None else motion[idx],
                    None if init_step is None else init_step[idx],
                    None if frame_count is None else frame_count[idx],
                    dest >= 0 if spare else None if active is None else active[idx],
                )
                if spare:
                    dest = torch.where(dest >= 0, dest, n)
                params[dest], zncc[dest], status[dest], iters[dest] = pr, zr, sr, ir
                first_stage[dest], std[dest], sigma[dest] = p1, sd, sg
                if cstep is not None:
                    cstep[dest] = cs
            if spare:
                params, zncc, status, iters = params[:n], zncc[:n], status[:n], iters[:n]
                first_stage, std, sigma = first_stage[:n], std[:n], sigma[:n]
                cstep = None if cstep is None else cstep[:n]

        bad = status > int(Status.MAX_ITER)  # (out of place: the first stage's may be these)
        params = params.masked_fill(bad.unsqueeze(1), float("nan"))
        zncc = zncc.masked_fill(bad, float("nan"))
        return WindowSolution(
            points=points, params=params, param_names=shape.param_names, zncc=zncc,
            status=status, iterations=iters, time=time, std=std, sigma=sigma,
            info={
                "formulation": cfg.formulation,
                "n_frames": t_count,
                "stages": [f.name for f in ctx.stages],
                "first_stage_params": first_stage,
                "initial_params": p0,
                "initial_guess": guess,
                **({} if cstep is None else classical_step_info(cstep)),
            },
        )

    def _init_at(self, init: torch.Tensor, dt: torch.Tensor, offset: torch.Tensor,
                 has_time: bool | None = None) -> torch.Tensor:
        """An initial guess (N, P') at the POIs carried by ``offset`` (N, 2) px to the
        subset centres (in the parameters of the shape solved for ``dt``)."""
        shape = self.shape_for(torch.as_tensor(dt), has_time)
        p0 = torch.as_tensor(init).to(offset)
        if p0.shape[1] != shape.n_params:
            p0 = expand_init(p0, shape, self.shape)
        return carry_params(p0, shape.param_names, offset)

    # ---- seeded initial guess --------------------------------------------------------------
    def _seed_plan(self, points, inside, dt, frame_index, ref_index):
        """(inside indices, cell of each, seed positions) for the seeded initial guess, or None
        when FFT cross-correlation at every POI is wanted (config, or sparse POIs)."""
        cfg = self.config
        n_in = int(inside.sum())
        if cfg.initial_guess == "fft" or n_in < 2:
            return None
        idx = torch.nonzero(inside).flatten()
        # POIs share a seed only when they see the same reference, frames and frame times
        key = torch.cat([ref_index[idx].unsqueeze(1).double(), frame_index[idx].double(),
                         dt[idx].double()], 1)
        if bool((key == key[:1]).all()):  # one window for all (the common case): no sort
            group = torch.zeros(idx.numel(), dtype=torch.long, device=idx.device)
        else:
            _, group = torch.unique(key, dim=0, return_inverse=True)
        spacing = float(cfg.seed_spacing or cfg.subset_size)
        cell, seeds = seed_cells(points[idx], group, spacing)
        if cfg.initial_guess == "auto" and seeds.numel() * 4 > n_in:
            return None
        return idx, cell, seeds

    def _solve_seeded(self, plan, ref, frames, points, dt, frame_index, ref_index, ref_pixels,
                      frame_pixels, time, inside, noise_ratio, motion=None,
                      classical_step=False, pyramids=None) -> WindowSolution:
        """Seeds by FFT cross-correlation and Gauss-Newton; every other POI starts from its
        cell's seed solution (:func:`carry_from_seed`); POIs that then fail (not converged, or
        ZNCC more than 0.1 below the best of their cell) are solved again from FFT cross-correlation
        and keep the better of the two results."""
        idx, cell, seeds_local = plan
        n = points.shape[0]
        shape = self.shape_for(dt)

        def rows_of(a, rows):
            return None if a is None else a[rows]

        def sub(rows, init):
            return self.solve(ref, frames, points[rows], dt[rows], frame_index=frame_index[rows],
                              ref_index=ref_index[rows], init=init, ref_pixels=ref_pixels,
                              frame_pixels=frame_pixels, time=time, noise_ratio=noise_ratio,
                              motion=rows_of(motion, rows), classical_step=classical_step,
                              pyramids=pyramids)

        fft_s = [0.0]

        def fft(rows):
            t0 = _clock(points.device)
            p0 = self.initial_guess(shape, ref_pixels, frame_pixels, points[rows], dt[rows],
                                    frame_index[rows], ref_index[rows],
                                    motion=rows_of(motion, rows), pyramids=pyramids)
            fft_s[0] += _clock(points.device) - t0
            return p0

        seeds = idx[seeds_local]
        sol_s = sub(seeds, fft(seeds))
        is_seed = torch.zeros(idx.numel(), dtype=torch.bool, device=idx.device)
        is_seed[seeds_local] = True
        others = idx[~is_seed]
        pos = cell[~is_seed]  # cell number == position of the cell's seed in `seeds`
        seed_ok = sol_s.ok[pos]
        init = carry_from_seed(shape, torch.nan_to_num(sol_s.params[pos]),
                               points[others] - points[seeds[pos]])
        orphans = ~seed_ok  # cells whose seed failed: FFT for their POIs
        if orphans.any():
            init[orphans] = fft(others[orphans])
        sol_o = sub(others, init)
        # a POI is suspect when its ZNCC is 0.1 below the best of its cell (its seed included):
        # it may have started from a seed across a discontinuity
        best = torch.nan_to_num(sol_s.zncc, nan=-1.0).clone()
        best = best.scatter_reduce(0, pos, torch.nan_to_num(sol_o.zncc, nan=-1.0), "amax")
        lost = ~sol_o.ok | (sol_o.status == int(Status.MAX_ITER)) | ~(
            sol_o.zncc >= best[pos] - 0.1
        )
        lost &= seed_ok  # orphans already started from FFT
        redo = others[lost]
        sol_r = sub(redo, fft(redo)) if redo.numel() else None

        p_count = shape.n_params
        dev, dtype = points.device, points.dtype
        out = {
            "params": torch.full((n, p_count), float("nan"), dtype=dtype, device=dev),
            "first": torch.full((n, p_count), float("nan"), dtype=dtype, device=dev),
            "init": torch.zeros(n, p_count, dtype=dtype, device=dev),
            "zncc": torch.full((n,), float("nan"), dtype=dtype, device=dev),
            "status": torch.full((n,), int(Status.OUTSIDE), dtype=torch.int8, device=dev),
            "iters": torch.zeros(n, dtype=torch.int32, device=dev),
            "std": torch.full((n, p_count), float("nan"), dtype=dtype, device=dev),
            "sigma": torch.full((n,), float("nan"), dtype=dtype, device=dev),
        }
        if classical_step:
            packed = packed_classical_step(sol_s.info)
            out["cstep"] = packed.new_full((n, packed.shape[1]), float("nan"))

        def put(rows, sol, mask=None):
            if mask is not None:
                rows, pick = rows[mask], mask
            else:
                pick = slice(None)
            out["params"][rows] = sol.params[pick]
            out["first"][rows] = sol.info["first_stage_params"][pick]
            out["init"][rows] = sol.info["initial_params"][pick]
            out["zncc"][rows] = sol.zncc[pick]
            out["status"][rows] = sol.status[pick]
            out["std"][rows] = sol.std[pick]
            out["sigma"][rows] = sol.sigma[pick]
            if classical_step:
                out["cstep"][rows] = packed_classical_step(sol.info)[pick]

        put(seeds, sol_s)
        out["iters"][seeds] = sol_s.iterations
        put(others, sol_o)
        out["iters"][others] = sol_o.iterations
        if sol_r is not None:
            old_ok = sol_o.ok[lost]
            better = sol_r.ok & (~old_ok | (sol_r.zncc > sol_o.zncc[lost]))
            put(redo, sol_r, better)
            out["iters"][redo] += sol_r.iterations
        return WindowSolution(
            points=points, params=out["params"], param_names=shape.param_names,
            zncc=out["zncc"], status=out["status"], iterations=out["iters"], time=time,
            std=out["std"], sigma=out["sigma"],
            info={
                **{k: v for k, v in sol_s.info.items()
                   if k not in ("first_stage_params", "initial_params")},
                "first_stage_params": out["first"],
                "initial_params": out["init"],
                **(classical_step_info(out["cstep"]) if classical_step else {}),
                "initial_guess": {
                    "method": "seeded", "seeds": int(seeds.numel()),
                    "fft_points": int(seeds.numel() + orphans.sum() + redo.numel()),
                    "redone": int(redo.numel()), "points": int(idx.numel()),
                    "fft_s": fft_s[0],
                },
            },
        )

    def initial_guess(
        self, shape, ref_pixels, frame_pixels, points, dt, frame_index, ref_index, motion=None,
        pyramids: tuple[PyramidStack, PyramidStack] | None = None,
    ) -> torch.Tensor:
        """FFT cross-correlation on every frame of each POI's window, then a line in time:
        (N, P) parameters (displacement at dt = 0 and velocity; gradients zero) of the motion
        besides the known ``motion`` (N, T, 2) (None: none); ``pyramids`` as for
        :meth:`solve`."""
        cfg = self.config
        floor = cfg.gpu_floor
        d, score = fft_cross_correlation(
            ref_pixels, frame_pixels, points, cfg.subset_size, cfg.search_radius,
            frame_index=frame_index, ref_index=ref_index, gpu_floor=floor,
        )
        d, score = retry_weak_peaks(d, score, ref_pixels, frame_pixels, points, frame_index,
                                    ref_index, cfg.subset_size, cfg.search_radius, pyramids,
                                    gpu_floor=floor)
        if d.shape[1] > 1:
            d, score = walk_weak_frames(d, score, dt, ref_pixels, frame_pixels, points,
                                        frame_index, ref_index, cfg.subset_size,
                                        cfg.search_radius, gpu_floor=floor)
        d = d.to(points.dtype)
        if motion is not None:
            d = d - motion.to(d)
        p0 = torch.zeros(points.shape[0], shape.n_params, dtype=points.dtype,
                         device=points.device)
        k = shape.n_basis
        if shape.has_time:
            d0, vel = linear_fit_in_time(d, dt, weights=score.to(points.dtype) + 1.0)
            p0[:, k - 1] = vel[:, 0]
            p0[:, 2 * k - 1] = vel[:, 1]
        else:
            d0 = (d * (score.unsqueeze(-1) + 1.0)).sum(1) / (score + 1.0).sum(1, keepdim=True)
        p0[:, 0] = d0[:, 0]
        p0[:, k] = d0[:, 1]
        return p0


def _clock(device: torch.device) -> float:
    """Wall-clock seconds, after the device's queued work (CUDA) has finished."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return _time.perf_counter()


def _grey_range(img: torch.Tensor) -> float:
    """Intensity range of the reference (0.1 .. 99.9 percentile, from a subsample of at most
    ~65k pixels), for the texture threshold."""
    flat = img.reshape(-1)
    if flat.numel() > 65536:
        flat = flat[:: flat.numel() // 65536 + 1]
    flat = flat.float()
    k = max(1, int(0.001 * flat.numel()))
    lo = flat.kthvalue(k).values
    hi = flat.kthvalue(flat.numel() - k + 1).values
    return max(float(hi - lo), 1e-12)


def subset_inside(points: torch.Tensor, half: float, h: int, w: int) -> torch.Tensor:
    """(N,) bool: the subset of half-width ``half`` around each POI lies in an H x W image."""
    return ((points[:, 0] - half >= 0) & (points[:, 0] + half <= w - 1)
            & (points[:, 1] - half >= 0) & (points[:, 1] + half <= h - 1))

