"""A Gauss-Newton stage point by point: every point iterated to its end in one kernel call.

:func:`torch_stsdic.core.gauss_newton.solve_batch` runs each stage either as a batched loop
(one step of all live points at a time, then the update, the convergence test and the
compaction in torch: a parallel region and its barrier per iteration) or, where
:func:`torch_stsdic.kernels.dispatch.ic_solve` allows (the joint IC formulation with an
affine shape, no autograd), through :func:`solve_stage`: on the CPU threads take chunks of
points and iterate each one to convergence with no barrier between iterations (C++
``sts_ic_solve``), so one descheduled thread no longer stalls the others every iteration; on
CUDA one Triton launch runs the whole stage, a program per point
(:mod:`torch_stsdic.kernels.triton_solve`), instead of a launch, a dozen torch ops and a host
check per iteration.
The same steps, update, convergence rule, statuses and iteration counts as the batched loop;
the results equal it to float rounding (``tests/test_native_solve.py``,
``tests/test_triton_solve.py``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_stsdic.core.formulations import JointIC, SubsetData
from torch_stsdic.core.shape import AffineShape
from torch_stsdic.core.status import Status
from torch_stsdic.kernels import dispatch, fused_step, native

__all__ = ["applies", "solve_stage"]

#: the statuses the kernel reports, in its order: converged, max_iter, diverged, outside
CODES = (int(Status.CONVERGED), int(Status.MAX_ITER), int(Status.DIVERGED),
         int(Status.OUTSIDE))


def applies(ctx, form, params: Tensor, data: SubsetData) -> bool:
    """Whether :func:`solve_stage` runs this stage (else the batched loop)."""
    return _backend(ctx, form, params, data) != "torch"


def _backend(ctx, form, params: Tensor, data: SubsetData) -> str:
    """Which solver runs the stage point by point: "native" (C++, CPU), "triton" (CUDA) or
    "torch" (none: the batched loop)."""
    geo = ctx.geo
    if not (type(form) is JointIC and isinstance(geo.shape, AffineShape)):
        return "torch"
    return dispatch.ic_solve(ctx.frames.kernel_args(), params, data.ft, geo.ks,
                             geo.shape.inverse_compositional, ctx.frames.order)


def start_stage(form, geo, params: Tensor, data: SubsetData, live: Tensor):
    """What a Gauss-Newton stage of the batched loop of :mod:`torch_stsdic.core.gauss_newton`
    starts with (:func:`solve_stage` starts with :func:`_start_every_row`, which chooses no
    rows): the (N,) status (MAX_ITER
    until decided), ZNCC and iteration counts, the live rows' data prepared by the
    formulation (Hessian), rows whose Hessian is singular LOW_TEXTURE and dropped. Returns
    params (a copy), zncc, status, used, rows (the rows to iterate), data (theirs); data is
    None where no row is live (params then the given tensor). The formulation prepares
    every row (a row's numbers do not depend on the others: in a stage all rows are
    usually live), so the rows to iterate are chosen by one index (one host
    synchronisation), not one for the live rows and another for the singular ones."""
    n = params.shape[0]
    status, zncc, alive = _prepare_rows(form, geo, params, data, live)
    used = torch.zeros(n, dtype=torch.int32, device=params.device)
    rows = torch.nonzero(alive).flatten()  # one index for all (one sync)
    if rows.numel() == 0:
        return params, zncc, status, used, rows, None
    params = params.clone()
    if rows.numel() < n:
        data = data.take(rows)
    return params, zncc, status, used, rows, data


def solve_stage(ctx, form, params: Tensor, data: SubsetData, live: Tensor, frame_rhs: bool,
                step0: Tensor | None, rate_floor: float):
    """``_run_stage`` of :mod:`torch_stsdic.core.gauss_newton` point by point, where
    :func:`applies`; None where it does not (the caller runs the batched loop). The same
    arguments (``ctx`` a ``BatchContext``, ``rate_floor`` the convergence rule's
    ``RATE_FLOOR``) and returns: params, zncc (N,), status (N,), iterations (N,) and, with
    ``frame_rhs``, (the parameters of each converged point's last step, that step's
    frame-by-frame spatial right-hand sides and ZNCCs (N, T, 2 Ks + 1); NaN rows: none)."""
    backend = _backend(ctx, form, params, data)
    if backend == "torch":
        return None
    cfg, geo, frames = ctx.cfg, ctx.geo, ctx.frames
    n = params.shape[0]
    dtype = params.dtype
    if n == 0:
        return start_stage(form, geo, params, data, live)[:4] + (None,)
    params, zncc, status, alive, data = _start_every_row(form, geo, params, data, live)
    scale = geo.shape.increment_scale(geo.spatial, data.dt)
    prev = (torch.zeros_like(params[:, 0]) if step0 is None
            else step0.to(dtype).nan_to_num(0.0))
    ka = frames.kernel_args()
    solve = native.ic_solve if backend == "native" else fused_step.ic_solve
    # a row not iterated starts at zero (its own POI: finite numbers for the kernel)
    start = torch.where(alive.unsqueeze(1), params, 0.0)
    p, zn, st, it, last = solve(
        ka, frames.order, start, data.px, data.py, geo.dx, geo.dy, geo.spatial,
        data.dt, data.fidx * ka[-1], data.ft, data.fnorm, data.gx, data.gy, geo.w,
        frames.width, frames.height, geo.k, geo.shape.has_time, geo.znssd, data.hinv, scale,
        prev, cfg.tol, cfg.max_iter, 4.0 * geo.half, rate_floor, CODES, motion=data.motion,
        ref_rows=data.ref_rows, frame_rhs=frame_rhs, count=data.count)
    # the rows not iterated (not live, or a singular Hessian) as start_stage leaves them
    params = torch.where(alive.unsqueeze(1), p.to(dtype), params)
    zncc = torch.where(alive, zn.to(dtype), zncc)
    status = torch.where(alive, st, status)
    used = torch.where(alive, it, 0)
    if frame_rhs:
        last = (torch.where(alive.unsqueeze(1), last[0].to(dtype), float("nan")),
                torch.where(alive.view(-1, 1, 1), last[1], float("nan")))
    return params, zncc, status, used, last


def _start_every_row(form, geo, params: Tensor, data: SubsetData, live: Tensor):
    """:func:`start_stage` for a kernel that iterates every row, with no host
    synchronisation (no index of the rows to iterate): the rows not to iterate (not
    ``live``, or their Hessian singular: LOW_TEXTURE) get a zero inverse Hessian, so their
    one step is zero (they stop at once, their parameters unchanged, their numbers dropped
    by the caller: :func:`solve_stage`). A row's numbers do not depend on the others', so
    the rows iterated give what they give alone. Returns params (a copy), zncc (NaN), status
    (MAX_ITER until decided; LOW_TEXTURE where singular), the (N,) bool rows iterated and
    data (every row, its Hessian prepared)."""
    status, zncc, alive = _prepare_rows(form, geo, params, data, live)
    data.hinv.masked_fill_(~alive.view(-1, 1, 1), 0.0)  # (its own: just prepared)
    return params.clone(), zncc, status, alive, data


def _prepare_rows(form, geo, params: Tensor, data: SubsetData, live: Tensor):
    """What both starts share: every row's data prepared by the formulation (Hessian),
    the (N,) status (MAX_ITER until decided; LOW_TEXTURE where ``live`` and the Hessian is
    singular), ZNCC (NaN) and the (N,) bool rows to iterate (live, not singular)."""
    n = params.shape[0]
    status = torch.full((n,), int(Status.MAX_ITER), dtype=torch.int8, device=params.device)
    zncc = torch.full((n,), float("nan"), dtype=params.dtype, device=params.device)
    sing = form.prepare(geo, data)
    status.masked_fill_(live & sing, int(Status.LOW_TEXTURE))
    return status, zncc, live & ~sing
