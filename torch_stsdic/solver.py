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
* ``auto`` (default): ``joint`` first (it finds the velocity), then the spatial unknowns are
  refined with ``average`` at the joint velocity (it averages the frames' noise before
  matching). See the README for the measurements behind this choice.

The ZNSSD criterion is solved in its variable-projection form: the residual is
f~ - a g~ with f~, g~ the zero-mean subsets and a the least-squares scale, which makes the
fixed point exactly the ZNCC maximum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .config import DICConfig
from .initial import fft_cross_correlation, linear_fit_in_time
from .interpolation import BSplineImage
from .shape import ShapeFunction, make_shape
from .status import Status
from .validation import as_image, as_points, as_series, as_times, check_init
from .window import make_window

__all__ = ["WindowSolution", "SubsetSolver", "solve_window"]


@dataclass
class WindowSolution:
    """Per-POI results of one window, at the expansion time ``time``.

    Attributes:
        points: (N, 2) POI positions (x, y), px.
        params: (N, P) shape-function parameters (names in ``param_names``); NaN rows where
            ``status`` is DIVERGED, OUTSIDE, LOW_TEXTURE or NOT_COMPUTED.
        zncc: (N,) zero-normalised cross-correlation, mean over the window's frames.
        status: (N,) int8 :class:`Status` codes.
        iterations: (N,) Gauss-Newton iterations used (all stages).
        time: the time the displacement refers to (frame units unless times were given).
    """

    points: torch.Tensor
    params: torch.Tensor
    param_names: tuple[str, ...]
    zncc: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    time: float = 0.0
    info: dict = field(default_factory=dict)

    def _get(self, name: str) -> torch.Tensor:
        if name in self.param_names:
            return self.params[:, self.param_names.index(name)]
        return torch.full_like(self.params[:, 0], float("nan"))

    @property
    def u(self) -> torch.Tensor:
        """(N,) displacement along x, px."""
        return self._get("u")

    @property
    def v(self) -> torch.Tensor:
        """(N,) displacement along y, px."""
        return self._get("v")

    @property
    def ut(self) -> torch.Tensor:
        """(N,) velocity du/dt, px per frame (NaN for m = 0: one frame has no velocity)."""
        return self._get("ut")

    @property
    def vt(self) -> torch.Tensor:
        """(N,) velocity dv/dt, px per frame (NaN for m = 0)."""
        return self._get("vt")

    @property
    def ok(self) -> torch.Tensor:
        """(N,) bool: converged (or stopped at max_iter with usable parameters)."""
        return self.status <= int(Status.MAX_ITER)

    def __len__(self) -> int:
        return self.points.shape[0]


class SubsetSolver:
    """The solver with its configuration resolved into modules (shape, window).

    ``prepare`` does the per-image work (B-spline prefilter) once; ``solve`` does the
    per-point work for one window. :func:`solve_window` wraps both.
    """

    def __init__(self, config: DICConfig | None = None) -> None:
        self.config = config if config is not None else DICConfig()
        self.config.validate()
        self.shape = make_shape(self.config.shape)
        self.window = make_window(self.config.window, self.config.subset_size)

    def prepare(self, images: torch.Tensor) -> BSplineImage:
        """Prefilter (T, H, W) or (H, W) images into B-spline coefficients."""
        return BSplineImage(images, order=self.config.interpolation_order)

    # ------------------------------------------------------------------------------------
    def solve(
        self,
        ref: BSplineImage,
        frames: BSplineImage,
        points: torch.Tensor,
        times: torch.Tensor,
        *,
        center: int,
        init: torch.Tensor | None = None,
        ref_pixels: torch.Tensor | None = None,
        frame_pixels: torch.Tensor | None = None,
        frame_index: torch.Tensor | None = None,
    ) -> WindowSolution:
        """Solve one window.

        Args:
            ref: prepared reference (1 frame).
            frames: prepared frames; the window uses ``frame_index`` (T,) of them (default all).
            points: (N, 2) POIs (x, y) in px, dtype of the computation.
            times: (T,) frame times; the results refer to ``times[center]``.
            init: (N, P) initial parameters, or None for FFT cross-correlation (which then
                needs ``ref_pixels`` (H, W) and ``frame_pixels`` (T, H, W)).
        """
        cfg = self.config
        device, dtype = points.device, points.dtype
        n = points.shape[0]
        t_count = times.shape[0]
        if frame_index is None:
            frame_index = torch.arange(t_count, device=device)
        dt = times - times[center]
        shape = self.shape if t_count > 1 and float(dt.abs().max()) > 0 else self.shape.spatial()
        p_count = shape.n_params
        offsets, weights = self.window.offsets_and_weights(dtype, device)
        dx, dy = offsets[:, 0], offsets[:, 1]
        basis = shape.basis(dx, dy, dt)  # (T, S, K)
        half = float(self.window.half)
        h, w = ref.height, ref.width
        status = torch.full((n,), int(Status.NOT_COMPUTED), dtype=torch.int8, device=device)
        params = torch.full((n, p_count), float("nan"), dtype=dtype, device=device)
        zncc = torch.full((n,), float("nan"), dtype=dtype, device=device)
        iters = torch.zeros(n, dtype=torch.int32, device=device)

        # reference subsets inside the image?
        inside = (
            (points[:, 0] - half >= 0) & (points[:, 0] + half <= w - 1)
            & (points[:, 1] - half >= 0) & (points[:, 1] + half <= h - 1)
        )
        status[~inside] = int(Status.OUTSIDE)

        # initial guess
        if init is None:
            if ref_pixels is None or frame_pixels is None:
                raise ValueError("solve needs init or the raw images for the FFT initial guess")
            p0 = torch.zeros(n, p_count, dtype=dtype, device=device)
            if inside.any():
                d, score = fft_cross_correlation(
                    ref_pixels, frame_pixels, points[inside], cfg.subset_size, cfg.search_radius
                )
                d = d.to(dtype)
                d0, vel = linear_fit_in_time(d, dt, weights=(score.to(dtype) + 1.0))
                k = shape.n_basis
                p0[inside, 0] = d0[:, 0]
                p0[inside, k] = d0[:, 1]
                if "ut" in shape.param_names:
                    p0[inside, shape.index("ut")] = vel[:, 0]
                    p0[inside, shape.index("vt")] = vel[:, 1]
        else:
            p0 = init.to(device=device, dtype=dtype)
            if p0.shape[1] != p_count:
                p0 = _expand_init(p0, shape, self.shape)

        todo = torch.nonzero(inside).flatten()
        ctx = _Context(
            shape=shape, basis=basis, dx=dx, dy=dy, w=weights, dt=dt, half=half, h=h, w_img=w,
            ref=ref, frames=frames, frame_index=frame_index, cfg=cfg,
            grey_range=_grey_range(ref_pixels if ref_pixels is not None else ref.coeffs),
        )
        batch = cfg.batch_points or ctx.batch_size()
        for s0 in range(0, todo.numel(), batch):
            idx = todo[s0 : s0 + batch]
            pr, zr, sr, ir = _solve_batch(ctx, points[idx], p0[idx])
            params[idx], zncc[idx], status[idx], iters[idx] = pr, zr, sr, ir

        bad = status > int(Status.MAX_ITER)
        params[bad] = float("nan")
        zncc[bad] = float("nan")
        return WindowSolution(
            points=points, params=params, param_names=shape.param_names, zncc=zncc,
            status=status, iterations=iters, time=float(times[center]),
            info={"formulation": cfg.formulation, "n_frames": t_count},
        )


def _grey_range(img: torch.Tensor) -> float:
    """Intensity range of the reference (robust to a few outliers), for texture thresholds."""
    flat = img.reshape(-1)
    if flat.numel() > 1_000_000:
        flat = flat[:: flat.numel() // 1_000_000 + 1]
    q = torch.quantile(flat.float(), torch.tensor([0.001, 0.999], device=flat.device))
    return max(float(q[1] - q[0]), 1e-12)


def _expand_init(p0: torch.Tensor, shape: ShapeFunction, full: ShapeFunction) -> torch.Tensor:
    """Map a short initial guess ((N,2) u,v; (N,4) u,v,ut,vt; or the full/spatial parameter
    set of the other shape variant) onto ``shape``'s parameters."""
    n = p0.shape[0]
    out = torch.zeros(n, shape.n_params, dtype=p0.dtype, device=p0.device)
    names = shape.param_names
    if p0.shape[1] in (2, 4):
        src = ("u", "v", "ut", "vt")[: p0.shape[1]]
    elif p0.shape[1] == full.n_params:
        src = full.param_names
    elif p0.shape[1] == full.spatial().n_params:
        src = full.spatial().param_names
    else:
        raise ValueError(
            f"init must be (N, 2) (u, v), (N, 4) (u, v, ut, vt) or (N, {shape.n_params}) "
            f"parameters {names}, got {tuple(p0.shape)}"
        )
    for j, nm in enumerate(src):
        if nm in names:
            out[:, names.index(nm)] = p0[:, j]
    return out


@dataclass
class _Context:
    shape: ShapeFunction
    basis: torch.Tensor  # (T, S, K)
    dx: torch.Tensor
    dy: torch.Tensor
    w: torch.Tensor  # (S,)
    dt: torch.Tensor  # (T,)
    half: float
    h: int
    w_img: int
    ref: BSplineImage
    frames: BSplineImage
    frame_index: torch.Tensor
    cfg: DICConfig
    grey_range: float

    def batch_size(self) -> int:
        t, s, k = self.basis.shape
        elem = self.basis.element_size()
        per_point = t * s * elem * (48 + 2 * k) + s * elem * (16 + 4 * k)
        return max(16, int(self.cfg.memory_mb * 2**20 / per_point))


def _wsum(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return (x * w).sum(-1)


def _solve_batch(ctx: _Context, pts: torch.Tensor, p0: torch.Tensor):
    """Solve one batch of POIs (all inside the image). Returns params, zncc, status, iters."""
    cfg = ctx.cfg
    n = pts.shape[0]
    device, dtype = pts.device, pts.dtype
    w = ctx.w
    wsum = w.sum()
    znssd = cfg.criterion == "znssd"
    px = pts[:, 0:1]
    py = pts[:, 1:2]
    # reference subsets: values and gradients (the per-point "prepare" work)
    f, fgx, fgy = ctx.ref.sample(px + ctx.dx, py + ctx.dy, grad=True)  # (N, S)
    status = torch.full((n,), int(Status.NOT_COMPUTED), dtype=torch.int8, device=device)
    grey_range = ctx.grey_range
    texture = _wsum(fgx * fgx + fgy * fgy, w) / wsum
    low = texture < cfg.texture_threshold * grey_range**2
    if znssd:
        fm = _wsum(f, w) / wsum
        ft = f - fm.unsqueeze(-1)
    else:
        ft = f
    fnorm = _wsum(ft * ft, w).sqrt()
    low |= fnorm < 1e-8 * grey_range * math.sqrt(float(wsum))
    status[low] = int(Status.LOW_TEXTURE)
    params = p0.clone()
    zncc = torch.full((n,), float("nan"), dtype=dtype, device=device)
    iters = torch.zeros(n, dtype=torch.int32, device=device)
    live = ~low
    ref_data = {"f": f, "ft": ft, "fnorm": fnorm, "gx": fgx, "gy": fgy, "px": px, "py": py}

    stages = _stages(ctx)
    for stage_i, (kind, free) in enumerate(stages):
        last = stage_i == len(stages) - 1
        params, zncc, st, used = _run_stage(ctx, kind, free, params, ref_data, live)
        iters += used
        if last:
            status = torch.where(live, st, status)
        else:
            # a stage that failed ends the point; MAX_ITER in an early stage is not fatal
            failed = live & (st > int(Status.MAX_ITER))
            status = torch.where(failed, st, status)
            live = live & ~failed
    # divergence from the initial guess
    maxd = cfg.max_displacement if cfg.max_displacement is not None else float(cfg.subset_size)
    k = ctx.shape.n_basis
    jump = torch.maximum((params[:, 0] - p0[:, 0]).abs(), (params[:, k] - p0[:, k]).abs())
    far = (status <= int(Status.MAX_ITER)) & ~(jump <= maxd)
    status[far] = int(Status.DIVERGED)
    return params, zncc, status, iters


def _stages(ctx: _Context) -> list[tuple[str, torch.Tensor | None]]:
    """(kind, free-parameter mask) per stage for the configured formulation."""
    shape = ctx.shape
    single = ctx.basis.shape[0] == 1
    form = ctx.cfg.formulation
    ic = shape.compose_inverse is not None and type(shape).compose_inverse is not (
        ShapeFunction.compose_inverse
    )
    joint = "joint_ic" if ic else "joint_fa"
    if single:
        return [(joint, None)]  # classical DIC: joint == average with one frame
    if form == "joint":
        return [(joint, None)]
    if form == "average":
        return [("average", None)]
    spatial = ~shape.temporal_mask().to(ctx.basis.device)
    return [(joint, None), ("average", spatial)]


def _take(d: dict, idx: torch.Tensor) -> dict:
    return {k: v[idx] for k, v in d.items()}


def _run_stage(ctx, kind, free, params, ref_data, live):
    """Iterate one Gauss-Newton stage over the live points with an active set.

    Returns params, zncc (N,), status (N,) for the live points, iterations used (N,)."""
    cfg = ctx.cfg
    n = params.shape[0]
    device, dtype = params.device, params.dtype
    status = torch.full((n,), int(Status.MAX_ITER), dtype=torch.int8, device=device)
    zncc = torch.full((n,), float("nan"), dtype=dtype, device=device)
    used = torch.zeros(n, dtype=torch.int32, device=device)
    p_count = params.shape[1]
    free_idx = torch.arange(p_count, device=device) if free is None else torch.nonzero(free)[:, 0]
    scale = ctx.shape.increment_scale(
        ctx.half, float(ctx.dt.abs().max()), dtype, device
    ) if ctx.basis.shape[0] > 1 else ctx.shape.increment_scale(ctx.half, 0.0, dtype, device)
    scale = scale[: p_count]
    rows = torch.nonzero(live).flatten()
    if rows.numel() == 0:
        return params, zncc, status, used
    params = params.clone()
    state = _take(ref_data, rows)
    if kind == "joint_ic":
        hess = _ic_hessian(ctx, state)
        chol, info = torch.linalg.cholesky_ex(hess.double())
        state["chol"] = chol
        sing = info > 0
        if sing.any():
            status[rows[sing]] = int(Status.DIVERGED)
            keep = ~sing
            rows = rows[keep]
            state = _take(state, keep)
    p = params[rows]
    for _ in range(cfg.max_iter):
        if rows.numel() == 0:
            break
        if kind == "joint_ic":
            dp, zn, outside = _step_joint_ic(ctx, state, p)
            p_new = ctx.shape.compose_inverse(p, dp)
        else:
            dp_free, zn, outside = _step_fa(ctx, state, p, free_idx, average=(kind == "average"))
            dp = torch.zeros_like(p)
            dp[:, free_idx] = dp_free
            p_new = p + dp
        used[rows] += 1
        norm = (dp * scale).norm(dim=1)
        finite = torch.isfinite(norm) & torch.isfinite(p_new).all(1)
        bad = ~finite | (norm > 4.0 * ctx.half)
        conv = finite & (norm < cfg.tol) & ~outside
        p = torch.where(finite.unsqueeze(1), p_new, p)
        zncc[rows] = zn.to(dtype)
        done = conv | bad | outside
        if done.any():
            r = rows[done]
            params[r] = p[done]
            st = torch.full_like(r, int(Status.CONVERGED), dtype=torch.int8)
            st = torch.where(outside[done], torch.full_like(st, int(Status.OUTSIDE)), st)
            st = torch.where(bad[done], torch.full_like(st, int(Status.DIVERGED)), st)
            status[r] = st
            keep = ~done
            rows = rows[keep]
            p = p[keep]
            state = _take(state, keep)
    if rows.numel():
        params[rows] = p  # MAX_ITER: last iterate
    return params, zncc, status, used


def _warp_coords(ctx, state, p):
    """Warped sample positions (N, T, S) of every subset pixel in every frame."""
    u, v = ctx.shape.displacement(p, ctx.basis)
    xs = state["px"].unsqueeze(-1) + ctx.dx + u
    ys = state["py"].unsqueeze(-1) + ctx.dy + v
    return xs, ys


def _outside(ctx, xs, ys) -> torch.Tensor:
    lo_x = xs.amin(dim=(1, 2))
    hi_x = xs.amax(dim=(1, 2))
    lo_y = ys.amin(dim=(1, 2))
    hi_y = ys.amax(dim=(1, 2))
    return (lo_x < 0) | (hi_x > ctx.w_img - 1) | (lo_y < 0) | (hi_y > ctx.h - 1)


def _ic_hessian(ctx, state) -> torch.Tensor:
    """Gauss-Newton Hessian of the joint IC problem, sum over frames (N, P, P).

    J_t = [f_x B_t, f_y B_t] (reference gradient times the basis); with ZNSSD the
    subset mean of J_t is removed (the mean of f(W(x; dp)) moves with dp too)."""
    w = ctx.w
    g = torch.stack([state["gx"], state["gy"]], -1)  # (N, S, 2)
    wg = g * w.view(1, -1, 1)
    bb = torch.einsum("tsk,tsl->skl", ctx.basis, ctx.basis)  # (S, K, K)
    n = g.shape[0]
    k = ctx.basis.shape[-1]
    hess = torch.einsum("nsc,nsd,skl->nckdl", wg, g, bb).reshape(n, 2 * k, 2 * k)
    if ctx.cfg.criterion == "znssd":
        wsum = w.sum()
        mj = torch.einsum("nsc,tsk->ntck", wg, ctx.basis).reshape(n, -1, 2 * k) / wsum
        hess = hess - wsum * torch.einsum("ntp,ntq->npq", mj, mj)
    return hess


def _frame_stats(ctx, state, g):
    """Zero-mean frames, scale of f~ against each frame, and per-frame ZNCC."""
    w = ctx.w
    wsum = w.sum()
    ft = state["ft"].unsqueeze(1)  # (N, 1, S)
    if ctx.cfg.criterion == "znssd":
        gt = g - (_wsum(g, w) / wsum).unsqueeze(-1)
    else:
        gt = g
    gg = _wsum(gt * gt, w)
    fg = _wsum(ft * gt, w)
    gn = gg.clamp(min=1e-30).sqrt()
    zn = fg / (state["fnorm"].unsqueeze(1) * gn)
    return gt, gg, fg, zn


def _step_joint_ic(ctx, state, p):
    """One IC-GN step of the joint formulation: dp solves H dp = -sum_t J_t^T e_t."""
    xs, ys = _warp_coords(ctx, state, p)
    outside = _outside(ctx, xs, ys)
    g = ctx.frames.sample(xs, ys, frame=ctx.frame_index.view(1, -1, 1))
    gt, gg, fg, zn = _frame_stats(ctx, state, g)
    ft = state["ft"].unsqueeze(1)
    if ctx.cfg.criterion == "znssd":
        s = state["fnorm"].unsqueeze(1) / gg.clamp(min=1e-30).sqrt()  # Pan et al. ZNSSD scale
        e = ft - s.unsqueeze(-1) * gt
    else:
        e = ft - gt
    e = e * ctx.w
    eb = torch.einsum("nts,tsk->nsk", e, ctx.basis)
    b = torch.cat(
        [(state["gx"].unsqueeze(-1) * eb).sum(1), (state["gy"].unsqueeze(-1) * eb).sum(1)], -1
    )
    dp = -torch.cholesky_solve(b.double().unsqueeze(-1), state["chol"]).squeeze(-1)
    return dp.to(p.dtype), zn.mean(1), outside


def _step_fa(ctx, state, p, free_idx, average: bool):
    """One forward-additive GN step on the averaged image (Eqs. 14-18) or on the sum of
    per-frame residuals (joint, for shape functions without an inverse composition)."""
    w = ctx.w
    wsum = w.sum()
    xs, ys = _warp_coords(ctx, state, p)
    outside = _outside(ctx, xs, ys)
    g, gx, gy = ctx.frames.sample(xs, ys, frame=ctx.frame_index.view(1, -1, 1), grad=True)
    _, _, _, zn = _frame_stats(ctx, state, g)
    znssd = ctx.cfg.criterion == "znssd"
    ft = state["ft"]
    basis = ctx.basis
    k = basis.shape[-1]
    if average:
        t = g.shape[1]
        big_g = g.mean(1)  # (N, S): G of Eq. 3
        jac = torch.cat(
            [torch.einsum("nts,tsk->nsk", gx, basis), torch.einsum("nts,tsk->nsk", gy, basis)],
            -1,
        ) / t  # Eq. 16
        jac = jac[..., free_idx]
        if znssd:
            gt = big_g - (_wsum(big_g, w) / wsum).unsqueeze(-1)
            jac = jac - ((jac * w.view(1, -1, 1)).sum(1) / wsum).unsqueeze(1)
            a = _wsum(ft * gt, w) / _wsum(gt * gt, w).clamp(min=1e-30)
            r = ft - a.unsqueeze(-1) * gt
        else:
            a = torch.ones_like(ft[:, 0])
            r = ft - big_g
        wj = jac * w.view(1, -1, 1)
        hess = wj.transpose(1, 2) @ jac  # Eq. 18
        rhs = (wj * r.unsqueeze(-1)).sum(1)  # Eq. 15
        rhs = rhs / a.clamp(min=1e-12).unsqueeze(-1)
    else:
        jac = torch.cat(
            [gx.unsqueeze(-1) * basis, gy.unsqueeze(-1) * basis], -1
        )[..., free_idx]  # (N, T, S, P)
        if znssd:
            gt = g - (_wsum(g, w) / wsum).unsqueeze(-1)
            jac = jac - ((jac * w.view(1, 1, -1, 1)).sum(2) / wsum).unsqueeze(2)
            a = _wsum(ft.unsqueeze(1) * gt, w) / _wsum(gt * gt, w).clamp(min=1e-30)  # (N, T)
            r = ft.unsqueeze(1) - a.unsqueeze(-1) * gt
        else:
            a = torch.ones_like(g[..., 0])
            r = ft.unsqueeze(1) - g
        wj = jac * w.view(1, 1, -1, 1) * a.view(*a.shape, 1, 1)
        hess = torch.einsum("ntsp,ntsq->npq", wj * a.view(*a.shape, 1, 1), jac)
        rhs = torch.einsum("ntsp,nts->np", wj, r)
    chol, info = torch.linalg.cholesky_ex(hess.double())
    dp = torch.cholesky_solve(rhs.double().unsqueeze(-1), chol).squeeze(-1)
    dp = torch.where((info > 0).unsqueeze(-1), torch.full_like(dp, float("nan")), dp)
    del k
    return dp.to(p.dtype), zn.mean(1), outside


# ---------------------------------------------------------------------------------------
def solve_window(
    ref,
    frames,
    points,
    config: DICConfig | None = None,
    times=None,
    init=None,
    center: int | None = None,
) -> WindowSolution:
    """Measure displacement and velocity at many POIs from one window of 2m+1 frames.

    Args:
        ref: reference image f, (H, W) tensor or array (grey; any real dtype).
        frames: the window's deformed frames g_t in time order, (2m+1, H, W); (H, W) is
            accepted when m = 0.
        points: (N, 2) POIs as (x, y) in px (x = column, y = row, 0-based).
        config: a :class:`DICConfig` (default DICConfig()).
        times: (2m+1,) frame times (default 0, 1, ..., 2m: frame units).
        init: optional initial guess per POI: (N, 2) (u, v), (N, 4) (u, v, ut, vt) or
            (N, P) full parameters; default: FFT cross-correlation within
            ``config.search_radius`` on every frame of the window, then a line fit in time.
        center: index of the frame the results refer to (default m, the window centre; a
            shifted window at the ends of a movie uses another index).

    Returns:
        :class:`WindowSolution` on the input's device: u, v, ut, vt (N,), params (N, P),
        zncc (N,), status (N,), iterations (N,).
    """
    cfg = config if config is not None else DICConfig()
    if not isinstance(cfg, DICConfig):
        raise TypeError(f"config must be a DICConfig, got {type(cfg).__name__}")
    ref_t = as_image(ref, "ref", dtype=cfg.dtype)
    frames_t = as_series(frames, "frames", dtype=ref_t.dtype, device=ref_t.device,
                         like=ref_t, m=cfg.m)
    n_frames = frames_t.shape[0]
    if n_frames != cfg.n_frames:
        raise ValueError(
            f"frames: config.m = {cfg.m} needs 2m+1 = {cfg.n_frames} frames, got {n_frames}"
            + (" (m is larger than the frames given)" if n_frames < cfg.n_frames else "")
        )
    if min(ref_t.shape) < cfg.subset_size:
        raise ValueError(
            f"subset_size {cfg.subset_size} is larger than the image {tuple(ref_t.shape)}"
        )
    pts = as_points(points, "points", dtype=ref_t.dtype, device=ref_t.device)
    t = as_times(times, n_frames, dtype=ref_t.dtype, device=ref_t.device)
    c = cfg.m if center is None else int(center)
    if not 0 <= c < n_frames:
        raise ValueError(f"center must be in 0..{n_frames - 1}, got {center}")
    init_t = check_init(init, pts.shape[0], dtype=ref_t.dtype, device=ref_t.device)
    solver = SubsetSolver(cfg)
    ref_img = solver.prepare(ref_t)
    frames_img = solver.prepare(frames_t)
    return solver.solve(
        ref_img, frames_img, pts, t, center=c, init=init_t, ref_pixels=ref_t,
        frame_pixels=frames_t,
    )
