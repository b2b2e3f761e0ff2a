"""Gauss-Newton over one batch of POIs: reference subsets, the stages of the formulation(s),
convergence and status of every point, and the predicted uncertainty of the solutions.

:class:`~torch_stsdic.core.solver.SubsetSolver` splits a solve into batches within the memory
budget and calls :func:`solve_batch` on each; the linearised model itself (residual,
Jacobian, Hessian, update) is the formulation's (:mod:`torch_stsdic.core.formulations`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_stsdic.core import point_solve, uncertainty
from torch_stsdic.core.config import DICConfig, gpu_budget_mb
from torch_stsdic.core.formulations import (
    Formulation,
    Geometry,
    JointIC,
    SubsetData,
    gram_and_texture,
    ic_hessian,
    reference_subsets,
)
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.status import Status
from torch_stsdic.kernels import dispatch
from torch_stsdic.kernels.linalg import spd_inverse

__all__ = ["BatchContext", "KeptToken", "ReferenceCache", "keep_subsets", "missing_subsets",
           "solve_batch"]

#: the slowest convergence assumed when the next increment is predicted from the last two
#: (:func:`_next_increment`): at a faster observed rate the prediction uses this one. Chosen
#: on the 1024^2 benchmark pair and a sample-12 pair against solutions converged to 1e-7 px:
#: no floor let 2.3e-4 px through at tol 1e-4, 0.05 gives 1.8e-4 px at most (99 % of points
#: within 7e-5 px), for 2.7 instead of 3.7 iterations.
RATE_FLOOR = 0.05


class ReferenceCache:
    """The reference subsets of the points solved so far (values, gradients, norm and
    centred gram: :func:`_reference_data`), kept between the solves of one reference so that
    a point solved again (the next block of a movie, the model check's classical solve,
    a rescue, a shorter window) is not sampled again: the same numbers, computed once.

    Used by the solves of a run (:attr:`SubsetSolver.reference_cache
    <torch_stsdic.core.solver.SubsetSolver>`) whose points lie on the pixel grid. It belongs to
    one prepared reference and one subset geometry: another reference (an update) empties
    it, another geometry passes it by. It holds at most ``budget_mb`` MiB; a run whose points
    need more does without it (as before: sampled in every solve)."""

    def __init__(self, budget_mb: float, expected: int = 0) -> None:
        self.budget = float(budget_mb) * 2**20
        self.expected = int(expected)  # points a run expects to keep (first allocation)
        self.off = False  # over budget: not used again
        self.coeffs: torch.Tensor | None = None  # the reference's coefficients (identity)
        self.geo: tuple[torch.Tensor, ...] | None = None  # dx, dy, w, spatial
        self.geo_key: tuple | None = None  # their Geometry.key (None: compared as tensors)
        self.znssd = True
        #: (R*H*W + 1,) row of each pixel's subset, -1: none; the last entry a spare key that
        #: no pixel has (the padding of :func:`keep_subsets`'s ``capacity``)
        self.slot: torch.Tensor | None = None
        self.pixels = 0  # R*H*W: the spare key
        #: (start, end, generation) of the last padded :meth:`add` (:meth:`drop_padding`)
        self._padded: tuple[int, int, int] | None = None
        # ft, fnorm, gx, gy, gram, texture: (capacity, ...), the first ``count`` rows kept;
        # grown by doubling (not a concatenation per solve: that copied every kept row)
        self._store: dict[str, torch.Tensor] = {}
        self.count = 0
        #: bumped whenever the kept subsets are dropped (:meth:`token`)
        self.generation = 0

    @property
    def rows(self) -> dict[str, torch.Tensor]:
        """The kept subsets: ft, fnorm, gx, gy, gram, texture, each (count, ...)."""
        return {k: v[:self.count] for k, v in self._store.items()}

    def _empty(self) -> None:
        self._store, self.count = {}, 0
        self.generation += 1

    def token(self) -> tuple[ReferenceCache, int]:
        """What :func:`keep_subsets` returns: the cache and its generation, which a solve
        compares (``BatchContext.kept``) on the host: the same while nothing was dropped."""
        return (self, self.generation)

    def applies(self, ref: BSplineImage, geo: Geometry) -> bool:
        """The cache serves subsets of ``ref`` with ``geo`` (emptied first when ``ref`` is
        another reference than the one it holds)."""
        if self.off:
            return False
        if self.coeffs is not ref.coeffs:
            self.coeffs = ref.coeffs
            self._empty()
            self.pixels = ref.n_frames * ref.height * ref.width
            self.slot = torch.full((self.pixels + 1,), -1, dtype=torch.long,
                                   device=ref.coeffs.device)
            self.geo, self.znssd = (geo.dx, geo.dy, geo.w, geo.spatial), geo.znssd
            self.geo_key = geo.key
        if self.znssd != geo.znssd:
            return False
        if geo.key is not None and geo.key == self.geo_key:  # no read of the device
            return True
        return all(a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b)
                   for a, b in zip(self.geo, (geo.dx, geo.dy, geo.w, geo.spatial)))

    def fits(self, more: int, s: int, elem: int, pa: int) -> bool:
        """``more`` points of S samples (element size ``elem``; gram P' x P') fit the
        budget; if not, the cache is emptied and not used again."""
        per = 3 * s * elem + 2 * elem + pa * pa * 8
        if (self.count + more) * per <= self.budget:
            return True
        self.off, self.slot, self.coeffs = True, None, None
        self._empty()
        return False

    def add(self, keys: torch.Tensor, data: SubsetData) -> None:
        """Keep the subsets ``data`` of the reference pixels ``keys`` (M,) (not kept yet)."""
        new = {"ft": data.ft, "fnorm": data.fnorm, "gx": data.gx, "gy": data.gy,
               "gram": data.gram, "texture": data.texture}
        start, end = self.count, self.count + keys.shape[0]
        capacity = next(iter(self._store.values())).shape[0] if self._store else 0
        if capacity == 0 and end >= self.expected:
            # the first solve brings the run's points: keep its tensors, no copy (a pair:
            # 38,809 subsets, 0.03 s); they are read, never written, by the solves
            self._store = {k: v.contiguous() for k, v in new.items()}
        else:
            if end > capacity:  # grow: to the run's expected points, else double (in budget)
                per = sum(v[:1].numel() * v.element_size() for v in new.values())
                capacity = max(end, min(max(2 * capacity, self.expected),
                                        int(self.budget // max(per, 1))))
                store = {k: v.new_empty((capacity, *v.shape[1:])) for k, v in new.items()}
                for k, v in self._store.items():
                    store[k][:start] = v[:start]
                self._store = store
            for k, v in new.items():
                self._store[k][start:end] = v
        self.slot[keys] = torch.arange(start, end, device=keys.device)
        self.count = end

    def drop_padding(self, kept: int) -> None:
        """The last :meth:`add` of :func:`keep_subsets` with a ``capacity``: only its first
        ``kept`` rows (the distinct pixels that missed, read since) are subsets, the rest its
        padding (under the spare key) is dropped where nothing was kept after it."""
        if self._padded is not None:
            start, end, generation = self._padded
            if self.count == end and self.generation == generation:
                self.count = start + min(int(kept), end - start)
        self._padded = None


#: :meth:`ReferenceCache.token`: the cache and its generation
KeptToken = tuple[ReferenceCache, int]


@dataclass
class BatchContext:
    """What every batch of one solve shares: geometry, images, settings."""

    geo: Geometry
    ref: BSplineImage
    frames: BSplineImage
    cfg: DICConfig
    stages: list[Formulation]
    grey_range: float
    work: int = 0  # samples per iteration over all batches (decides torch.compile)
    noise_ratio: float = 1.0  # reference noise variance / one frame's
    cache: ReferenceCache | None = None  # the reference subsets kept between solves
    #: also each point's classical solution after one Gauss-Newton step from its window's
    #: solution at the target frame (dt = 0), from the last step's frame-by-frame
    #: right-hand sides (:func:`_classical_step`; the model check starts there)
    classical_step: bool = False
    #: the points are whole pixels (:meth:`SubsetSolver.solve
    #: <torch_stsdic.core.solver.SubsetSolver.solve>` snaps the others first): not tested
    #: on the host; False: tested
    on_grid: bool = False
    #: :func:`keep_subsets`'s token where the caller put every point's reference subsets in
    #: ``cache`` (the rows' misses are then not counted: no host read); None: counted
    kept: KeptToken | None = None

    def batch_size(self, t: int) -> int:
        """POIs per batch within ``cfg.memory_mb`` (not given: 256 MiB, and on a GPU at
        least :func:`~torch_stsdic.core.config.gpu_budget_mb`: a batch's rows do not depend
        on the batch, so fewer batches are the same answers for fewer launches)."""
        s, ks = self.geo.spatial.shape
        elem = self.geo.spatial.element_size()
        ic_only = all(f.inverse_compositional for f in self.stages)
        if ic_only and dispatch.fused_ic_step(self.frames.kernel_args(), self.frames.order, s,
                                              self.geo.spatial):
            # fused kernels: no (N, T, S) temporaries, only the per-point reference data
            per_point = s * elem * 12
        else:
            jac = 0 if ic_only else t * 2 * (ks + 1)
            per_point = s * elem * (t * 40 + jac + 8 * ks + 24)
        budget = self.cfg.budget_mb
        gpu_mb = gpu_budget_mb(self.geo.spatial.device)
        if gpu_mb is not None and self.cfg.gpu_floor:
            budget = max(budget, gpu_mb)
        return max(16, int(budget * 2**20 / per_point))


def solve_batch(ctx: BatchContext, pts, p0, dt, fidx, ridx, motion=None, step0=None,
                count=None, active=None):
    """Solve one batch of N POIs (all inside the image) from ``p0`` (N, P), with frame times
    ``dt`` (N, T), frame indices ``fidx`` (N, T), reference indices ``ridx`` (N,), the
    known motion of every frame ``motion`` (N, T, 2) (None: none) and the size of the step
    that gave ``p0`` (N,) (the first stage's previous increment for its convergence rate;
    None, 0 or NaN: none) and each row's frames in use ``count`` (N,) (its first ``count``
    columns, ``SubsetData.count``; None: all), and the rows to iterate ``active`` (N,) bool
    (None: all; the others NOT_COMPUTED, their parameters ``p0``, no host read).

    Returns params (N, P), zncc (N,), status (N,) int8, iterations (N,), the first stage's
    params (N, P), predicted std (N, P), noise std (N,) (grey levels) and, with
    ``ctx.classical_step``, the classical step (N, :func:`classical_step_width`)
    (:func:`_classical_step`; NaN where not known), else None."""
    cfg, geo = ctx.cfg, ctx.geo
    n = pts.shape[0]
    device, dtype = pts.device, pts.dtype
    data = _reference_data(ctx, pts, dt, fidx, ridx)
    data.motion = motion
    data.count = count
    status = torch.full((n,), int(Status.NOT_COMPUTED), dtype=torch.int8, device=device)
    low = data.texture < cfg.texture_threshold * ctx.grey_range**2
    low |= data.fnorm < 1e-6 * ctx.grey_range * math.sqrt(geo.w_sum)
    if active is not None:  # the rows not to solve: none of their facts either
        low &= active
    status.masked_fill_(low, int(Status.LOW_TEXTURE))  # no host sync (boolean indexing)
    params = p0.clone()
    zncc = torch.full((n,), float("nan"), dtype=dtype, device=device)
    iters = torch.zeros(n, dtype=torch.int32, device=device)
    live = ~low if active is None else active & ~low
    stage_params = []
    last = None
    for stage_i, form in enumerate(ctx.stages):
        final = stage_i == len(ctx.stages) - 1
        params, zn, st, used, last = _run_stage(ctx, form, params, data, live,
                                                frame_rhs=final and ctx.classical_step,
                                                step0=step0 if stage_i == 0 else None)
        stage_params.append(params)
        zncc = torch.where(live, zn, zncc)
        iters += used
        if stage_i == len(ctx.stages) - 1:
            status = torch.where(live, st, status)
        else:
            # a stage that failed ends the point; MAX_ITER in an early stage is not fatal
            failed = live & (st > int(Status.MAX_ITER))
            status = torch.where(failed, st, status)
            live = live & ~failed
    maxd = cfg.max_displacement if cfg.max_displacement is not None else float(cfg.subset_size)
    k = geo.k
    jump = torch.maximum((params[:, 0] - p0[:, 0]).abs(), (params[:, k] - p0[:, k]).abs())
    far = (status <= int(Status.MAX_ITER)) & ~(jump <= maxd)
    status.masked_fill_(far, int(Status.DIVERGED))
    std, sigma = _uncertainty(ctx, data, params, zncc, status <= int(Status.MAX_ITER))
    cstep = None
    if ctx.classical_step:
        cstep = torch.full((n, classical_step_width(geo.ks)), float("nan"), dtype=dtype,
                           device=device)
        if last is not None:
            cstep = _classical_step(ctx, data, *last).to(dtype)
        cstep.masked_fill_((status != int(Status.CONVERGED)).unsqueeze(1), float("nan"))
    return params, zncc, status, iters, stage_params[0], std, sigma, cstep


#: the classical step's ZNCC, noise and std (:func:`_classical_step`) are given where the
#: Gauss-Newton model's residual decrease of the step is at most this share of the residual
#: energy before it; a larger step (a window far from the classical minimum: 4 degrees a
#: frame of rotation, 1.7 px steps, the ZNCC estimate 0.02 too low) is left to a solve
STEP_DROP = 0.05


def classical_step_columns(ks: int) -> dict[str, slice]:
    """The columns of :func:`_classical_step`'s rows for a spatial shape of ``ks`` parameters
    a component: the classical parameters (2 Ks), the step's size (1, px), the ZNCC (1),
    the noise std (1, grey levels) and the parameters' predicted std (2 Ks) there."""
    return {"params": slice(0, 2 * ks), "size": slice(2 * ks, 2 * ks + 1),
            "zncc": slice(2 * ks + 1, 2 * ks + 2), "sigma": slice(2 * ks + 2, 2 * ks + 3),
            "std": slice(2 * ks + 3, 4 * ks + 3)}


def classical_step_width(ks: int) -> int:
    """The number of :func:`classical_step_columns`."""
    return 4 * ks + 3


def _classical_step(ctx: BatchContext, data: SubsetData, p_last: Tensor, frame: Tensor
                    ) -> Tensor:
    """(N, :func:`classical_step_width`) each point's classical solution (the shape without
    time, ``geo.shape``'s spatial parameters) after one inverse-compositional Gauss-Newton
    step from its window's warp at the target frame (dt = 0), and what the classical solve
    would report there (:func:`classical_step_columns`).

    ``p_last`` (N, P): the parameters at which the window's last step was taken; ``frame``
    (N, T, 2 Ks + 1): that step's frame-by-frame spatial right-hand sides and ZNCCs (NaN
    rows: none). At dt = 0 the window's warp is its spatial parameters (the shared motion's
    known part is zero there), and frame t's right-hand side ``b`` and the classical Hessian
    ``H`` (the spatial block of the centred gram) are exactly what a classical solve's first
    step from there computes: the step ``dp = -H^-1 b`` is free. Its size ``|dp * scale|``
    px is the convergence test's measure (a classical solve started from the step takes it as
    its previous increment, ``SubsetSolver.solve``'s ``init_step``). With ZNSSD and a 0/1
    window, the ZNCC after the step is the frame's ZNCC before it plus the Gauss-Newton
    model's decrease ``b^T H^-1 b`` of the residual energy ``2 |f~|^2 (1 - ZNCC)``; the noise
    and the predicted std follow from it as a classical solve's (:func:`_uncertainty`), so
    the model check can judge a row without solving it (NaN where that decrease exceeds
    :data:`STEP_DROP` of the energy before the step, or the criterion or window differ). NaN
    rows where the window has no frame at dt = 0 or no step was recorded."""
    geo = ctx.geo
    ks, k, n = geo.ks, geo.k, p_last.shape[0]
    at0 = data.dt == 0  # (N, T), a frame in use (padding, dt 0, is not one)
    at0 = at0 if data.count is None else at0 & data.in_use()
    t0 = at0.to(torch.int8).argmax(1)
    rows = torch.arange(n, device=frame.device)
    fr = frame[rows, t0]  # (N, 2 Ks + 1)
    b, zf = fr[:, : 2 * ks], fr[:, 2 * ks]
    classical = dataclasses.replace(geo, shape=geo.shape.spatial())
    hinv, singular = spd_inverse(ic_hessian(classical, data.gx, data.gy, data.dt[:, :1],
                                            g=data.gram))
    dp = -(hinv @ b.unsqueeze(-1)).squeeze(-1)
    pc = torch.cat([p_last[:, :ks], p_last[:, k:k + ks]], 1).double()
    out = classical.shape.compose_inverse(pc, dp)
    size = (dp * classical.shape.increment_scale(geo.spatial, data.dt[:, :1])).norm(dim=1)
    cols = classical_step_columns(ks)
    est = torch.full((n, classical_step_width(ks)), float("nan"), dtype=torch.float64,
                     device=out.device)
    est[:, cols["params"]] = out
    est[:, cols["size"]] = size.unsqueeze(1)
    if geo.znssd and geo.w_binary:
        # the model's decrease and the energy before the step, both over 2 |f~|^2
        drop = (-(b * dp).sum(1)) / (2.0 * data.fnorm.double().square().clamp(min=1e-30))
        zncc = zf + drop
        # trusted only where the step is small for the model: a decrease of at most
        # STEP_DROP of the residual energy (further steps then change it by ~rate^2 of that)
        zncc = torch.where(drop <= STEP_DROP * (1.0 - zf).clamp(min=0.0), zncc, float("nan"))
        cdata = dataclasses.replace(  # the classical problem: the target frame alone
            data, dt=torch.zeros_like(data.dt[:, :1]), fidx=data.fidx[rows, t0].unsqueeze(1),
            motion=None if data.motion is None else data.motion[rows, t0].unsqueeze(1),
            hinv=None, count=None)
        noise, _ = uncertainty.solution_noise(classical, ctx.frames, cdata, out.to(p_last.dtype),
                                              ctx.noise_ratio, ctx.frames.order, zncc=zncc)
        est[:, cols["zncc"]] = zncc.unsqueeze(1)
        est[:, cols["sigma"]] = noise.total.sqrt().double().unsqueeze(1)
        est[:, cols["std"]] = uncertainty.predicted_std(classical, cdata, noise,
                                                        ctx.frames.order).double()
    bad = singular | ~at0.any(1) | ~torch.isfinite(est[:, : cols["size"].stop]).all(1)
    return est.masked_fill(bad.unsqueeze(1), float("nan"))


def _pixel_keys(ref: BSplineImage, ij: Tensor, ridx: Tensor) -> Tensor:
    """(N,) one integer per (reference, pixel): of whole-pixel points ``ij`` (N, 2) in
    references ``ridx`` (N,) of ``ref`` (the reference cache's slots are indexed by it).
    A point off the image takes the key of the nearest pixel on its border (no subset of a
    point there lies inside the image: no solve reads those keys' subsets)."""
    x = ij[:, 0].long().clamp(0, ref.width - 1)
    y = ij[:, 1].long().clamp(0, ref.height - 1)
    return (ridx * ref.height + y) * ref.width + x


def _reference_data(ctx: BatchContext, pts, dt, fidx, ridx) -> SubsetData:
    """The reference subsets of a batch and their centred gram (for the Hessian and the
    uncertainty), sampled once per distinct (point, reference) pair: a block of B targets
    repeats every point B times."""
    geo = ctx.geo
    n = pts.shape[0]
    # points are on the pixel grid here (solve snaps off-grid points): one integer key each
    ij = pts.detach().round()
    key = _pixel_keys(ctx.ref, ij, ridx)
    on_grid = ctx.on_grid or bool((ij == pts).all())
    if on_grid and ctx.cache is not None and ctx.cache.applies(ctx.ref, geo):
        data = _cached_reference_data(ctx, pts, dt, fidx, ridx, key)
        if data is not None:
            return data
    uniq, inv = torch.unique(key, return_inverse=True)
    # few repeats: sampling them is cheaper than the gather
    repeats = uniq.shape[0] <= 0.75 * n and on_grid
    sel = _first_rows(inv, uniq.shape[0]) if repeats else slice(None)
    data = _sampled(ctx, pts, dt, fidx, ridx, sel)
    if repeats:
        data = _rows_of(ctx, data, inv, pts, dt, fidx)
    return data


def _first_rows(inv: torch.Tensor, n_points: int) -> torch.Tensor:
    """(n_points,) the first row of each distinct point, from the rows' point ``inv`` (N,)."""
    n = inv.shape[0]
    first = torch.full((n_points,), n, dtype=torch.long, device=inv.device)
    return first.scatter_reduce(0, inv, torch.arange(n, device=inv.device), "amin")


def _sampled(ctx: BatchContext, pts, dt, fidx, ridx, rows, inside: bool = False
             ) -> SubsetData:
    """The reference subsets of the rows ``rows`` (one per distinct point), sampled, with
    their centred gram and texture (``inside``: :func:`reference_subsets`'s)."""
    geo = ctx.geo
    data = reference_subsets(geo, ctx.ref, pts[rows], ridx[rows], dt[rows], fidx[rows],
                             inside=inside)
    data.gram, data.texture = gram_and_texture(geo, data.gx, data.gy)
    return data


def _shared_subsets(ctx: BatchContext) -> bool:
    """Rows may read their points' reference subsets through ``SubsetData.ref_rows`` (no copy
    per row): every use of them in the solve does (the native joint IC step; the Hessian,
    texture and uncertainty come from per-point moments: ZNSSD, a 0/1 window)."""
    w = ctx.geo.w
    return (ctx.geo.znssd and all(isinstance(f, JointIC) for f in ctx.stages)
            and dispatch.sample(ctx.frames.kernel_args(), w) == "native"
            and ctx.geo.w_binary)


def _rows_of(ctx: BatchContext, data: SubsetData, rows: torch.Tensor, pts, dt, fidx
             ) -> SubsetData:
    """The subsets ``data`` of distinct points (their gram and texture included) for rows that
    are points ``rows`` (N,) of them, at ``pts``, ``dt``, ``fidx``: shared through
    ``ref_rows`` where the solve allows (:func:`_shared_subsets`), else copied per row."""
    out = SubsetData(px=pts[:, 0:1], py=pts[:, 1:2], dt=dt, fidx=fidx, ft=data.ft,
                     fnorm=data.fnorm[rows], gx=data.gx, gy=data.gy, gram=data.gram[rows],
                     texture=data.texture[rows], ref_rows=rows)
    return out if _shared_subsets(ctx) else out.direct()


def _cached_reference_data(ctx: BatchContext, pts, dt, fidx, ridx, key):
    """:func:`_reference_data` through ``ctx.cache``: the distinct points not kept yet are
    sampled (as there) and kept, then every row takes its point's kept subsets. None where
    they would exceed the cache's budget (the cache is then off). One host read where every
    point is kept (the rows' count of misses; none where the caller kept them all,
    ``ctx.kept``: :func:`keep_subsets`); the distinct points only where some miss."""
    cache = ctx.cache
    if ctx.kept != cache.token() and not _keep_missing(ctx, pts, dt, fidx, ridx, key):
        return None
    kept = cache.rows
    data = SubsetData(px=pts, py=pts, dt=dt, fidx=fidx, ft=kept["ft"], fnorm=kept["fnorm"],
                      gx=kept["gx"], gy=kept["gy"], gram=kept["gram"], texture=kept["texture"])
    # (a pixel not kept only where a caller's capacity was too small, a guess it finds
    # wrong and solves again: its row reads the first kept subset meanwhile, not past them)
    return _rows_of(ctx, data, cache.slot[key].clamp(min=0), pts, dt, fidx)


def _missing_marks(cache: ReferenceCache, key: Tensor) -> tuple[Tensor, Tensor]:
    """For the rows' pixel keys ``key`` (N,): each row's key where ``cache`` misses its
    subset, else one past the last pixel (N,), and the (pixels + 1,) bool marks of the keys
    that miss (the last entry: the rows that do not). No host read."""
    n_px = cache.pixels
    km = torch.where(cache.slot[key] < 0, key, n_px)
    mark = torch.zeros(n_px + 1, dtype=torch.bool, device=key.device)
    mark[km] = True
    return km, mark


def missing_subsets(ctx: BatchContext, pts: torch.Tensor) -> Tensor | None:
    """(0-d int64, on the device, not read) how many distinct pixels of the points ``pts``
    (N, 2) (reference 0, at the pixels a solve snaps them to) ``ctx.cache`` misses: what
    :func:`keep_subsets` would sample (a caller reads it with its own numbers and hands it
    back, ``missing=``). None where the cache does not serve them."""
    cache = ctx.cache
    if cache is None or not cache.applies(ctx.ref, ctx.geo):
        return None
    pts = pts.detach().round()
    ridx = torch.zeros(pts.shape[0], dtype=torch.long, device=pts.device)
    return _missing_marks(cache, _pixel_keys(ctx.ref, pts, ridx))[1][:-1].sum()


def _keep_missing(ctx: BatchContext, pts, dt, fidx, ridx, key,
                  missing: int | None = None, inside: bool = False,
                  capacity: int | None = None) -> bool:
    """The reference subsets of the rows ``key`` (N,) (pixel keys of ``pts``) that
    ``ctx.cache`` misses, sampled and kept (one host read: how many distinct keys miss;
    none where the caller read it, ``missing``: :func:`missing_subsets`; nor of the
    points' facts where it knows them, ``inside``: :func:`reference_subsets`'s); False
    where they would exceed its budget (the cache is then off). ``capacity`` (count not
    known): the first ``capacity`` distinct keys that miss kept, padded to that many rows
    (:meth:`ReferenceCache.drop_padding` once the count is read; more is the caller's to
    find)."""
    cache, geo = ctx.cache, ctx.geo
    if missing == 0:
        return True
    km, mark = _missing_marks(cache, key)
    if capacity is None:
        missing = int(mark[:-1].sum()) if missing is None else missing
        if missing == 0:
            return True
    size = missing if capacity is None else capacity
    if not cache.fits(size, int(geo.w.numel()), ctx.ref.coeffs.element_size(),
                      2 * (geo.ks + 1)):
        return False
    # the distinct keys that miss, ascending, and the first row of each (the rows sorted
    # by key, stably: a search, not a scatter over every pixel of the image); padding: the
    # spare key, sampled at a row of the points (any: its subset is not read)
    uniq = torch.nonzero_static(mark[:-1], size=size, fill_value=cache.pixels).flatten()
    order = torch.argsort(km, stable=True)
    first = order[torch.searchsorted(km[order], uniq).clamp(max=key.numel() - 1)]
    start = cache.count
    cache.add(uniq, _sampled(ctx, pts, dt, fidx, ridx, first, inside))
    cache._padded = None if capacity is None else (start, cache.count, cache.generation)
    return True


def keep_subsets(ctx: BatchContext, pts: torch.Tensor, missing: int | None = None,
                 inside: bool = False, capacity: int | None = None) -> KeptToken | None:
    """Put the reference subsets of the points ``pts`` (N, 2) (reference 0; at the pixels a
    solve snaps them to) in ``ctx.cache`` (those it misses sampled: one host read) and
    return its token (:meth:`ReferenceCache.token`): a solve of any of these points given it
    as ``BatchContext.kept`` reads their subsets from the cache with no host read. None
    where the cache does not serve them (none, another geometry, over its budget).
    ``missing``: :func:`missing_subsets`'s count, read by the caller (then no read here);
    ``inside``: every point a whole pixel whose subset lies inside the image (known);
    ``capacity``: :func:`_keep_missing`'s (no read: the caller checks the count)."""
    cache = ctx.cache
    if cache is None or not cache.applies(ctx.ref, ctx.geo):
        return None
    n = pts.shape[0]
    pts = pts.detach().round()  # the pixels a solve snaps its points to (those off the
    # image: the border pixel their key names, :func:`_pixel_keys`)
    pts = torch.stack([pts[:, 0].clamp(0, ctx.ref.width - 1),
                       pts[:, 1].clamp(0, ctx.ref.height - 1)], 1)
    zero = torch.zeros(n, 1, dtype=pts.dtype, device=pts.device)
    ridx = torch.zeros(n, dtype=torch.long, device=pts.device)
    key = _pixel_keys(ctx.ref, pts, ridx)
    if not _keep_missing(ctx, pts, zero, ridx.unsqueeze(1), ridx, key, missing, inside,
                         capacity):
        return None
    return cache.token()


def _uncertainty(ctx: BatchContext, data: SubsetData, params, zncc, ok):
    """Predicted std (N, P) of every parameter and noise std (N,) of the rows ``ok`` (NaN
    elsewhere): computed for every row (vectorised, no copy of the subsets), then masked."""
    dtype = params.dtype
    noise, _ = uncertainty.solution_noise(ctx.geo, ctx.frames, data, params, ctx.noise_ratio,
                                          ctx.frames.order, zncc=zncc)
    std = uncertainty.predicted_std(ctx.geo, data, noise, ctx.frames.order)
    # (NaN a scalar of the operation: no tensor copied to the device)
    std = torch.where(ok.unsqueeze(1), std.to(dtype), float("nan"))
    return std, torch.where(ok, noise.total.sqrt().to(dtype), float("nan"))


def _next_increment(norm: Tensor, prev: Tensor) -> Tensor:
    """(N,) the size of the increment after one of size ``norm`` that followed one of size
    ``prev`` (0: none), predicted by linear convergence at the observed rate ``norm / prev``
    but no less than :data:`RATE_FLOOR` (a first step from far away shrinks faster than the
    rate at the solution); ``norm`` itself where there is no previous increment or the
    prediction is larger. The solve stops once this is below ``tol``: one increment fewer
    than waiting for the next increment itself to be below ``tol``."""
    rate = torch.where(prev > 0, norm / prev, 1.0).clamp(min=RATE_FLOOR, max=1.0)
    return norm * rate


def _run_stage(ctx: BatchContext, form: Formulation, params, data: SubsetData, live,
               frame_rhs: bool = False, step0: Tensor | None = None):
    """Iterate one Gauss-Newton stage over the live points, dropping finished points;
    ``step0`` (N,): the size of the increment that gave ``params`` (None, 0 or NaN: none),
    the previous increment of the first step's convergence test (:func:`_next_increment`).

    Returns params, zncc (N,), status (N,), iterations used (N,) and, with ``frame_rhs``
    where the formulation gives them, (the parameters (N, P) at which each converged point's
    last step was taken, that step's frame-by-frame spatial right-hand sides and ZNCCs
    (N, T, 2 Ks + 1); NaN rows: none), else None."""
    # on the CPU: every point iterated to its end in one C++ call (no barrier per iteration)
    solved = point_solve.solve_stage(ctx, form, params, data, live, frame_rhs, step0, RATE_FLOOR)
    if solved is not None:
        return solved
    cfg, geo = ctx.cfg, ctx.geo
    n = params.shape[0]
    device, dtype = params.device, params.dtype
    params, zncc, status, used, rows, data = point_solve.start_stage(form, geo, params, data,
                                                                     live)
    if data is None:
        return params, zncc, status, used, None
    scale = geo.shape.increment_scale(geo.spatial, data.dt)
    p = params[rows]
    # fused kernel: finished rows are skipped through an index (`sel`) instead of copying
    # the per-point data of the remaining rows
    sel = (torch.arange(rows.numel(), device=device)
           if form.uses_fused_kernel(ctx.frames, data, p) else None)
    last = None
    if frame_rhs and sel is not None and form.gives_frame_rhs(ctx.frames, data, p):
        t_count, ks = data.dt.shape[1], ctx.geo.ks
        last = (torch.full_like(params, float("nan")),
                torch.full((n, t_count, 2 * ks + 1), float("nan"), dtype=torch.float64,
                           device=device))
    active = torch.ones(rows.numel(), dtype=torch.bool, device=device)
    prev = (torch.zeros(rows.numel(), dtype=dtype, device=device) if step0 is None
            else step0[rows].to(dtype).nan_to_num(0.0))
    # On CUDA every boolean test or compaction waits for the GPU: look every few iterations.
    check_every = 1 if device.type == "cpu" else 4
    # filled on the device (a tensor from a Python number is a copy to it, which waits)
    conv_code = torch.full((), int(Status.CONVERGED), dtype=torch.int8, device=device)
    for it in range(cfg.max_iter):
        if rows.numel() == 0:
            break
        if last is None:
            dp, zn, outside = form.step(geo, ctx.frames, data, p, ctx.work, sel)
        else:
            buf = torch.empty(p.shape[0], *last[1].shape[1:], dtype=torch.float64,
                              device=device)
            dp, zn, outside = form.step(geo, ctx.frames, data, p, ctx.work, sel,
                                        frame_rhs=buf)
        p_new = form.update(geo, p, dp)
        used[rows] += active.to(used.dtype)
        norm = (dp * scale).norm(dim=1)
        finite = torch.isfinite(norm) & torch.isfinite(p_new).all(1)
        bad = ~finite | (norm > 4.0 * geo.half)
        # converged: the last increment, or the next one predicted from the last two, < tol
        conv = finite & (_next_increment(norm, prev) < cfg.tol) & ~outside
        prev = norm
        p_old = p
        p = torch.where((finite & active).unsqueeze(1), p_new, p)
        zncc[rows] = torch.where(active, zn.to(dtype), zncc[rows])
        done = (conv | bad | outside) & active
        # record finished points without boolean indexing (no host synchronisation)
        st = torch.where(bad, int(Status.DIVERGED), torch.where(outside, int(Status.OUTSIDE),
                                                                 conv_code)).to(torch.int8)
        if last is not None:  # where this step ends a point: the step's point and rhs
            if device.type == "cpu":
                ended = torch.nonzero(done).flatten()
                last[0][rows[ended]] = p_old[ended]
                last[1][rows[ended]] = buf[ended]
            else:  # without a host synchronisation
                d = done.unsqueeze(1)
                last[0][rows] = torch.where(d, p_old.to(last[0].dtype), last[0][rows])
                last[1][rows] = torch.where(d.unsqueeze(2), buf, last[1][rows])
        params[rows] = torch.where(done.unsqueeze(1), p, params[rows])
        status[rows] = torch.where(done, st, status[rows])
        active = active & ~done
        if (it + 1) % check_every == 0 or it + 1 == cfg.max_iter:
            n_active = int(active.sum())
            if n_active == 0:
                rows = rows[:0]
                break
            # drop finished rows once enough of them have piled up (copying costs too)
            if n_active < 0.7 * active.numel():
                keep = torch.nonzero(active).flatten()  # one index for all the tensors
                rows, p, scale, prev = rows[keep], p[keep], scale[keep], prev[keep]
                if sel is None:
                    data = data.take(keep)
                else:
                    sel = sel[keep]
                active = active[keep]
    if rows.numel():
        keep = torch.nonzero(active).flatten()
        rows, p = rows[keep], p[keep]
    if rows.numel():
        params[rows] = p  # MAX_ITER: the last iterate
    return params, zncc, status, used, last
