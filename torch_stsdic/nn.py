"""STS-DIC as a differentiable ``torch.nn.Module``, and dense <-> point field helpers.

:class:`STSDIC` measures the displacement (and velocity) at points of interest (POIs) for a
batch of B short sequences (a reference image and a window of 2m+1 frames each) with the
batched Gauss-Newton solver of :mod:`torch_stsdic.core.solver`: the B sequences are solved as one
set of tensor operations (every POI row carries its own reference and frame indices).

Gradients are obtained by **implicit differentiation** at the converged solution, not by
back-propagating through the Gauss-Newton iterations. The solver stops where a stationarity
condition ``F(p, theta) = 0`` holds (``p`` the shape-function parameters of a POI, ``theta``
the reference pixels, frame pixels and POI positions). By the implicit function theorem

    dp/dtheta = -(dF/dp)^-1 dF/dtheta,

so the backward pass re-evaluates ``F`` once, differentiably (B-spline prefilter by FFT,
B-spline sampling, ZNSSD/SSD residuals), at the converged ``p``; forms the exact P x P
Jacobian ``dF/dp`` of every POI by reverse-mode autograd; solves one small transposed
system per POI; and takes one vector-Jacobian product of ``F`` with respect to ``theta``.

``F`` is exactly the condition the solver's iteration converges to:

* ``joint`` (inverse-compositional GN, affine shape): ``F = sum_t J_ref,t^T W e_t`` with
  ``J_ref,t`` the reference-gradient Jacobian and ``e_t = f~ - (|f~| / |g~_t|) g~_t`` (Pan's
  ZNSSD scale) or ``f - g_t`` (SSD); the GN step is ``-H^-1 F`` so the fixed point is
  ``F = 0``. (Not the gradient of a scalar criterion, but a valid implicit equation.)
* ``joint`` with a shape function without inverse composition (quadratic):
  ``F = sum_t a_t J~_t^T W (f~ - a_t g~_t)`` (forward-additive, LS scale ``a_t``).
* ``average``: ``F = J~^T W (f~ - a G~) / a``, the gradient of the variable-projection ZNSSD
  of the averaged warped image ``G`` (the ZNCC maximum).
* ``joint+average``: the two-stage composite. The velocity comes from the joint stationarity
  ``F_J(p1) = 0``; the spatial parameters from the average stationarity restricted to them,
  ``F_A,s(p2_s, p1_t) = 0``, at the joint velocity. The implicit system is block
  triangular and the backward pass solves it exactly (see :func:`_implicit_vjp`).

``auto`` is what the solver resolves it to (currently ``joint``): the backward pass follows
the stages the solver actually ran (``WindowSolution.info["stages"]``).

The initial guess ``init`` gets a zero gradient: a converged solution does not depend on
where the iteration started. POIs whose status is not ``CONVERGED``, or whose re-evaluated
stationarity residual (a Newton step at the solution) exceeds ``residual_tol``, get a zero
gradient and are reported (a warning, and ``STSDICOutput.status``).

Coordinates: x = column, y = row, pixel centres at integer coordinates, 0-based; flows have
channel 0 = u (along x), channel 1 = v (along y).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.formulations import Geometry, reference_subsets
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.offgrid import carry_params, carry_solution, snap_points
from torch_stsdic.core.shared_motion import known_window_motion
from torch_stsdic.core.solver import SubsetSolver, WindowSolution
from torch_stsdic.core.status import Status
from torch_stsdic.core.validation import check_pixels
from torch_stsdic.kernels.native.rows import in_own_threads

__all__ = [
    "STSDIC",
    "STSDICOutput",
    "points_to_dense",
    "dense_to_points",
]


# ------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------
@dataclass
class STSDICOutput:
    """Result of :meth:`STSDIC.forward_full` for a batch of B sequences and N POIs.

    Attributes:
        disp: (B, N, 2) displacement (u, v) at the window's centre frame, px. Differentiable
            (implicit gradient); NaN where ``status`` is DIVERGED, OUTSIDE, LOW_TEXTURE or
            NOT_COMPUTED.
        vel: (B, N, 2) velocity (ut, vt), px per time unit (NaN for m = 0). Differentiable.
        status: (B, N) int8 :class:`~torch_stsdic.core.status.Status` codes.
        zncc: (B, N) zero-normalised cross-correlation (mean over the window's frames).
        params: (B, N, P) all shape-function parameters (names in ``param_names``).
            Differentiable.
        param_names: e.g. ('u', 'ux', 'uy', 'ut', 'v', 'vx', 'vy', 'vt').
        iterations: (B, N) Gauss-Newton iterations used (all stages).
        solution: the solver's raw :class:`~torch_stsdic.core.solver.WindowSolution` for the
            B * N flattened POIs (row b * N + i is sequence b, POI i).
        report: filled by the backward pass: "zero_grad" (POIs given a zero gradient),
            "not_converged" (status not CONVERGED) and "not_stationary" (CONVERGED but the
            stationarity check failed). Empty until a backward pass has run.
    """

    disp: Tensor
    vel: Tensor
    status: Tensor
    zncc: Tensor
    params: Tensor
    param_names: tuple[str, ...]
    iterations: Tensor
    solution: WindowSolution | None = None
    report: dict = field(default_factory=dict)

    @property
    def converged(self) -> Tensor:
        """(B, N) bool: status CONVERGED, the POIs that carry a gradient."""
        return self.status == int(Status.CONVERGED)

    @property
    def ok(self) -> Tensor:
        """(B, N) bool: usable parameters (CONVERGED or MAX_ITER)."""
        return self.status <= int(Status.MAX_ITER)


# ------------------------------------------------------------------------------------------
# The problem description shared by forward and backward
# ------------------------------------------------------------------------------------------
@dataclass
class _Problem:
    solver: SubsetSolver
    dt: Tensor  # (N, T)
    fidx: Tensor  # (N, T)
    ridx: Tensor  # (N,)
    residual_tol: float
    grad_dtype: torch.dtype | None
    report: dict
    solution: WindowSolution | None = None
    motion: Tensor | None = None  # (N, T, 2) known motion of every frame (window offsets)


def _jacobian(f: Tensor, p: Tensor) -> Tensor:
    """(N, P, P) per-row Jacobian dF_n/dp_n (rows are independent), by reverse mode."""
    n, q = f.shape
    eye = torch.eye(q, dtype=f.dtype, device=f.device)
    cols = []
    for i in range(q):
        (gi,) = torch.autograd.grad(f, p, grad_outputs=eye[i].expand(n, q), retain_graph=True)
        cols.append(gi)
    return torch.stack(cols, 1)  # [n, i, j] = dF_i / dp_j


def _solve(a: Tensor, b: Tensor) -> Tensor:
    """Batched a x = b (a (N, Q, Q), b (N, Q)); NaN rows where a is singular."""
    x, info = torch.linalg.solve_ex(a, b.unsqueeze(-1))
    x = x.squeeze(-1)
    return torch.where((info > 0).unsqueeze(-1), torch.full_like(x, float("nan")), x)


def _implicit_vjp(
    prob: _Problem,
    stages: Sequence[str],
    ref_px: Tensor,
    frame_px: Tensor,
    pts: Tensor,
    params: Tensor,
    first: Tensor,
    status: Tensor,
    grad_out: Tensor,
    needs: tuple[bool, bool, bool],
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """Vector-Jacobian product of the converged parameters (N, P) with ``grad_out`` (N, P)
    with respect to ref pixels (R, H, W), frame pixels (F, H, W) and points (N, 2).

    Single stage: lambda = A^-T v with A = dF/dp; grad = -lambda^T dF/dtheta.
    Two stages ("joint+average": joint p1, then the spatial block s of p2 from the average condition
    at the joint velocity t): with A_J = dF_J/dp1, A_A = dF_A/dp2,
    mu = A_A[s, s]^-T v_s, w_t = v_t - A_A[s, t]^T mu, lambda = A_J^-T w (w zero on s),
    grad = -mu^T dF_A,s/dtheta - lambda^T dF_J/dtheta.
    """
    solver = prob.solver
    dtype = prob.grad_dtype or ref_px.dtype
    device = ref_px.device
    rows = torch.nonzero(status == int(Status.CONVERGED)).flatten()
    bad_report = int((status != int(Status.CONVERGED)).sum())
    ref_l = ref_px.detach().to(dtype).requires_grad_(needs[0])
    frm_l = frame_px.detach().to(dtype).requires_grad_(needs[1])
    pts_l = pts.detach().to(dtype).requires_grad_(needs[2])
    leaves = [x for x, nd in zip((ref_l, frm_l, pts_l), needs) if nd]
    zero = [None if not nd else torch.zeros_like(x)
            for x, nd in zip((ref_px, frame_px, pts), needs)]
    if rows.numel() == 0:
        prob.report.update(zero_grad=int(status.numel()), not_converged=bad_report,
                           not_stationary=0)
        return tuple(zero)  # type: ignore[return-value]
    dt = prob.dt[rows].to(dtype)
    fidx, ridx = prob.fidx[rows], prob.ridx[rows]
    shape = solver.shape_for(prob.dt)
    geo = Geometry.make(shape, solver.window, solver.config.criterion, dtype, device)
    order = solver.config.interpolation_order
    ref_img = BSplineImage(ref_l, order=order)
    frm_img = BSplineImage(frm_l, order=order)
    motion = None if prob.motion is None else prob.motion[rows].to(dtype)
    data = reference_subsets(geo, ref_img, pts_l[rows], ridx, dt, fidx, motion)
    forms = {f.name: f for f in solver.stages_for(shape)}
    v = torch.nan_to_num(grad_out[rows].to(dtype), nan=0.0, posinf=0.0, neginf=0.0)
    scale = shape.increment_scale(geo.spatial, dt)
    tol = prob.residual_tol

    def evaluate(kind: str, p_val: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        p = p_val[rows].detach().to(dtype).requires_grad_(True)
        f = forms[kind].stationarity(geo, frm_img, data, p)
        return f, _jacobian(f, p), p

    if len(stages) == 1:
        f, a, _ = evaluate(stages[0], params)
        step = _solve(a, f.detach())
        lam = _solve(a.transpose(1, 2), v)
        good = (step * scale).norm(dim=1) <= tol
        good &= torch.isfinite(lam).all(1)
        lam = torch.where(good.unsqueeze(1), lam, torch.zeros_like(lam))
        total = (f * lam).sum()
    else:
        if len(stages) != 2 or stages[1] != "average":
            raise NotImplementedError(f"implicit gradient for stages {stages}")
        temporal = shape.temporal_mask().to(device)
        s_idx = torch.nonzero(~temporal).flatten()
        t_idx = torch.nonzero(temporal).flatten()
        fj, aj, _ = evaluate(stages[0], first)
        fa, aa, _ = evaluate("average", params)
        fa_s = fa[:, s_idx]
        a_ss = aa[:, s_idx][:, :, s_idx]
        a_st = aa[:, s_idx][:, :, t_idx]
        step_j = _solve(aj, fj.detach())
        step_a = torch.zeros_like(step_j)
        step_a[:, s_idx] = _solve(a_ss, fa_s.detach())
        mu = _solve(a_ss.transpose(1, 2), v[:, s_idx])
        w_vec = torch.zeros_like(v)
        w_vec[:, t_idx] = v[:, t_idx] - (a_st.transpose(1, 2) @ mu.unsqueeze(-1)).squeeze(-1)
        lam = _solve(aj.transpose(1, 2), w_vec)
        good = ((step_j * scale).norm(dim=1) <= tol) & ((step_a * scale).norm(dim=1) <= tol)
        good &= torch.isfinite(lam).all(1) & torch.isfinite(mu).all(1)
        lam = torch.where(good.unsqueeze(1), lam, torch.zeros_like(lam))
        mu = torch.where(good.unsqueeze(1), mu, torch.zeros_like(mu))
        total = (fj * lam).sum() + (fa_s * mu).sum()
    n_bad = int((~good).sum())
    prob.report.update(
        zero_grad=bad_report + n_bad, not_converged=bad_report, not_stationary=n_bad,
    )
    if n_bad:
        warnings.warn(
            f"STSDIC backward: {n_bad} converged point(s) are not stationary to "
            f"residual_tol={tol:g} px (or have a singular Jacobian); their gradient is zero",
            RuntimeWarning, stacklevel=3,
        )
    grads = torch.autograd.grad(-total, leaves, allow_unused=True)
    out: list[Tensor | None] = []
    it = iter(grads)
    for x, nd in zip((ref_px, frame_px, pts), needs):
        if not nd:
            out.append(None)
            continue
        gx = next(it)
        out.append(torch.zeros_like(x) if gx is None else gx.to(x.dtype))
    return tuple(out)  # type: ignore[return-value]


class _ImplicitSTSDIC(torch.autograd.Function):
    """params = solve(ref_px, frame_px, points, init) with implicit-function backward."""

    @staticmethod
    def forward(ctx, ref_px, frame_px, pts, init, prob: _Problem):  # type: ignore[override]
        solver = prob.solver
        ref_img = solver.prepare(ref_px)
        frm_img = solver.prepare(frame_px)
        sol = solver.solve(
            ref_img, frm_img, pts, prob.dt, frame_index=prob.fidx, ref_index=prob.ridx,
            init=init, ref_pixels=ref_px, frame_pixels=frame_px, motion=prob.motion,
        )
        prob.solution = sol
        ctx.prob = prob
        ctx.stages = tuple(sol.info["stages"])
        ctx.init_meta = None if init is None else (tuple(init.shape), init.dtype, init.device)
        ctx.save_for_backward(ref_px, frame_px, pts, sol.params, sol.info["first_stage_params"],
                              sol.status)
        return sol.params.clone()

    @staticmethod
    def backward(ctx, grad_params):  # type: ignore[override]
        ref_px, frame_px, pts, params, first, status = ctx.saved_tensors
        needs = tuple(bool(x) for x in ctx.needs_input_grad[:3])
        g_init = None
        if ctx.init_meta is not None and ctx.needs_input_grad[3]:
            shape, dtype, device = ctx.init_meta
            # a converged solution does not depend on where the iteration started
            g_init = torch.zeros(shape, dtype=dtype, device=device)
        if not any(needs):
            return None, None, None, g_init, None
        with torch.enable_grad():
            g_ref, g_frm, g_pts = _implicit_vjp(
                ctx.prob, ctx.stages, ref_px, frame_px, pts, params, first, status,
                grad_params, needs,
            )
        return g_ref, g_frm, g_pts, g_init, None


def _window_motion(shared: Tensor | None, b: int, n: int, t_count: int, dt: Tensor,
                   dtype: torch.dtype, device: torch.device) -> Tensor | None:
    """(B*N, T, 2) window offsets from a shared motion (B, T, 2) or (B, N, T, 2), or None."""
    if shared is None:
        return None
    hint = f"(B={b}, 2m+1={t_count}, 2) or (B, N={n}, {t_count}, 2)"
    g = torch.as_tensor(shared).detach().to(device=device, dtype=dtype)
    if g.dim() == 3 and g.shape[0] == b:  # one motion per sequence: every point of it
        g = g.unsqueeze(1).expand(-1, n, -1, -1)
    if g.dim() != 4 or g.shape[:2] != (b, n):
        raise ValueError(f"shared_motion must be {hint}, got {tuple(g.shape)}")
    return known_window_motion(g.reshape(b * n, *g.shape[2:]), dt.to(dtype), hint)


# ------------------------------------------------------------------------------------------
# The module
# ------------------------------------------------------------------------------------------
class STSDIC(nn.Module):
    """Differentiable STS-DIC: displacement and velocity at POIs for a batch of sequences.

    Args:
        config: solver settings (:class:`~torch_stsdic.core.config.DICConfig`); ``config.m``
            fixes the window: ``frames`` must hold 2m+1 frames. All three formulations
            ("joint", "average", "joint+average"; "auto" is resolved by the solver, currently
            to "joint") have exact implicit gradients.
        times: optional (2m+1,) frame times (default 0, 1, ..., 2m). Results refer to the
            centre frame m; velocities are per time unit.
        residual_tol: a CONVERGED POI whose stationarity residual (the exact Newton step
            at the solution, px, measured like the solver's ``tol``) exceeds this gets a
            zero gradient (default ``max(100 * config.tol, 0.01)``: Gauss-Newton stops on
            its own step, which for slowly converging points is smaller than the distance
            to the stationary point; the check catches points that are not stationary at
            all, e.g. a first "joint+average" stage that hit ``max_iter``).
        grad_dtype: dtype of the backward computation (default torch.float64; gradients are
            returned in the inputs' dtype). None: the inputs' dtype.

    Shapes (B sequences, N POIs, T = 2m+1 frames, P shape parameters):
        ref (B, H, W) or (B, 1, H, W); frames (B, T, H, W) or (B, T, 1, H, W);
        points (N, 2) shared by all sequences or (B, N, 2), (x, y) px;
        init None (FFT cross-correlation) or (B, N, 2) (u, v), (B, N, 4) (u, v, ut, vt) or
        (B, N, P); it gets a zero gradient.
        forward -> (B, N, 2) displacement (u, v) at the centre frame;
        forward_full -> :class:`STSDICOutput`.

    The computation runs in the dtype of ``ref`` (float32 or float64; integer images are
    converted to float32) on its device; all B sequences are solved together.
    """

    def __init__(
        self,
        config: DICConfig | None = None,
        *,
        times: Tensor | Sequence[float] | None = None,
        residual_tol: float | None = None,
        grad_dtype: torch.dtype | None = torch.float64,
    ) -> None:
        super().__init__()
        self.config = config if config is not None else DICConfig()
        self.solver = SubsetSolver(self.config)
        self.times = None if times is None else torch.as_tensor(times, dtype=torch.float64)
        self.residual_tol = residual_tol
        self.grad_dtype = grad_dtype
        self.last_report: dict = {}

    def extra_repr(self) -> str:
        c = self.config
        return (f"subset_size={c.subset_size}, m={c.m}, shape={c.shape!r}, "
                f"formulation={c.formulation!r}, criterion={c.criterion!r}")

    # --------------------------------------------------------------------------------------
    def forward(
        self, ref: Tensor, frames: Tensor, points: Tensor, init: Tensor | None = None,
        shared_motion: Tensor | None = None,
    ) -> Tensor:
        """(B, N, 2) displacement (u, v) at the centre frame (see the class docstring)."""
        return self.forward_full(ref, frames, points, init, shared_motion).disp

    @in_own_threads(1, "ref")  # on the CPU: torch on one thread, the solve's work on the pool
    def forward_full(
        self, ref: Tensor, frames: Tensor, points: Tensor, init: Tensor | None = None,
        shared_motion: Tensor | None = None,
    ) -> STSDICOutput:
        """Displacement, velocity, all parameters, status and ZNCC for every POI.

        Args:
            ref: (B, H, W) or (B, 1, H, W) reference images.
            frames: (B, 2m+1, H, W) or (B, 2m+1, 1, H, W) windows of frames.
            points: (N, 2) or (B, N, 2) POIs (x, y) in px.
            init: None or (B, N, 2|4|P) initial guess (zero gradient).
            shared_motion: None, or the specimen's known displacement (u, v) px in every
                frame of the window, (B, 2m+1, 2) (the same at every point, e.g. a rigid
                shake measured by :func:`~torch_stsdic.core.shared_motion.fit_frame_motion`) or
                (B, N, 2m+1, 2): its jitter about a line in time is carried in every warp
                (:func:`~torch_stsdic.core.shared_motion.window_offsets`), so the outputs are the
                total displacement and the smooth velocity. No gradient flows to it.

        Returns:
            :class:`STSDICOutput` with (B, N, ...) tensors in ref's dtype and device.
        """
        ref, frames = self._check_images(ref, frames)
        b, t_count, h, w = frames.shape
        dtype, device = ref.dtype, ref.device
        pts = torch.as_tensor(points).to(device=device, dtype=dtype)
        if pts.dim() == 2:
            pts = pts.unsqueeze(0).expand(b, -1, -1)
        if pts.dim() != 3 or pts.shape[0] != b or pts.shape[-1] != 2:
            raise ValueError(f"points must be (N, 2) or (B={b}, N, 2), got {tuple(pts.shape)}")
        n = pts.shape[1]
        flat_pts = pts.reshape(b * n, 2)
        init_flat = None
        if init is not None:
            init_t = torch.as_tensor(init).to(device=device, dtype=dtype)
            if init_t.dim() != 3 or init_t.shape[:2] != (b, n):
                raise ValueError(f"init must be (B={b}, N={n}, 2|4|P), got "
                                 f"{tuple(init_t.shape)}")
            if not bool(torch.isfinite(init_t).all()):
                raise ValueError("init contains non-finite values")
            init_flat = init_t.reshape(b * n, -1)
        times = (torch.arange(t_count, dtype=dtype, device=device) if self.times is None
                 else self.times.to(device=device, dtype=dtype))
        if times.shape != (t_count,):
            raise ValueError(f"times must be ({t_count},), got {tuple(times.shape)}")
        dt = (times - times[t_count // 2]).expand(b * n, t_count)
        seq = torch.arange(b, device=device).repeat_interleave(n)  # (B*N,) sequence index
        fidx = seq.unsqueeze(1) * t_count + torch.arange(t_count, device=device)
        tol = self.residual_tol
        if tol is None:
            tol = max(100.0 * self.config.tol, 1e-2)
        report: dict = {}
        prob = _Problem(solver=self.solver, dt=dt, fidx=fidx, ridx=seq, residual_tol=tol,
                        grad_dtype=self.grad_dtype, report=report,
                        motion=_window_motion(shared_motion, b, n, t_count, dt, dtype, device))
        self.last_report = report
        grid, offset = snap_points(flat_pts)  # solved at pixel centres, carried to the POIs
        params = _ImplicitSTSDIC.apply(
            ref, frames.reshape(b * t_count, h, w), grid, init_flat, prob
        )
        sol = prob.solution
        assert sol is not None
        names = sol.param_names
        params = carry_params(params, names, offset)  # also at 0 offset: d/dpoints
        if bool((offset != 0).any()):
            sol = carry_solution(sol, flat_pts.detach(), offset.detach())
        p = params.reshape(b, n, -1)
        disp = torch.stack([p[..., names.index("u")], p[..., names.index("v")]], -1)
        if "ut" in names:
            vel = torch.stack([p[..., names.index("ut")], p[..., names.index("vt")]], -1)
        else:
            vel = torch.full_like(disp, float("nan"))
        return STSDICOutput(
            disp=disp, vel=vel, status=sol.status.reshape(b, n), zncc=sol.zncc.reshape(b, n),
            params=p, param_names=names, iterations=sol.iterations.reshape(b, n),
            solution=sol, report=report,
        )

    def _check_images(self, ref: Tensor, frames: Tensor) -> tuple[Tensor, Tensor]:
        if not isinstance(ref, Tensor) or not isinstance(frames, Tensor):
            raise TypeError("ref and frames must be torch tensors")
        check_pixels(ref, "ref")
        check_pixels(frames, "frames")
        if ref.dim() == 4 and ref.shape[1] == 1:
            ref = ref[:, 0]
        if frames.dim() == 5 and frames.shape[2] == 1:
            frames = frames[:, :, 0]
        if ref.dim() != 3:
            raise ValueError(f"ref must be (B, H, W) or (B, 1, H, W), got {tuple(ref.shape)}")
        if frames.dim() != 4:
            raise ValueError(f"frames must be (B, 2m+1, H, W), got {tuple(frames.shape)}")
        b, t_count, h, w = frames.shape
        if ref.shape != (b, h, w):
            raise ValueError(f"ref {tuple(ref.shape)} does not match frames "
                             f"{tuple(frames.shape)} (expected ({b}, {h}, {w}))")
        if t_count != self.config.n_frames:
            raise ValueError(f"frames: config.m = {self.config.m} needs 2m+1 = "
                             f"{self.config.n_frames} frames, got {t_count}")
        if min(h, w) < self.config.subset_size:
            raise ValueError(f"subset_size {self.config.subset_size} is larger than the "
                             f"image ({h}, {w})")
        dtype = ref.dtype if ref.dtype in (torch.float32, torch.float64) else torch.float32
        return ref.to(dtype), frames.to(device=ref.device, dtype=dtype)


# ------------------------------------------------------------------------------------------
# Dense fields <-> points
# ------------------------------------------------------------------------------------------
def _grid_axes(points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Origin (2,), spacing (2,), integer node indices ix, iy (N,) of POIs on a grid."""
    pts = points.detach().to(torch.float64)
    axes = []
    for c in range(2):
        vals = pts[:, c]
        uniq = torch.unique(torch.round(vals * 1e6) / 1e6)
        if uniq.numel() == 1:
            axes.append((uniq[0], torch.ones((), dtype=torch.float64, device=pts.device)))
            continue
        d = uniq.diff()
        step = d.min()
        idx = (uniq - uniq[0]) / step
        if not bool(torch.allclose(idx, idx.round(), atol=1e-4)) or step <= 0:
            raise ValueError("points are not on a regular grid (uneven spacing along "
                             f"{'xy'[c]})")
        axes.append((uniq[0], step))
    origin = torch.stack([axes[0][0], axes[1][0]])
    spacing = torch.stack([axes[0][1], axes[1][1]])
    ix = torch.round((pts[:, 0] - origin[0]) / spacing[0]).long()
    iy = torch.round((pts[:, 1] - origin[1]) / spacing[1]).long()
    return origin, spacing, ix, iy


def _fill_nan_nodes(grid: Tensor, valid: Tensor, max_iter: int) -> Tensor:
    """Fill invalid nodes of (B, C, gh, gw) by iterated 3x3 means of valid neighbours."""
    vals = torch.where(valid, grid, torch.zeros_like(grid))
    m = valid.to(grid.dtype)
    ker = torch.ones(1, 1, 3, 3, dtype=grid.dtype, device=grid.device)
    b, c, gh, gw = grid.shape
    for _ in range(max_iter):
        if bool(m.bool().all()):
            break
        num = torch.nn.functional.conv2d(
            (vals * m).reshape(b * c, 1, gh, gw), ker, padding=1).reshape(b, c, gh, gw)
        den = torch.nn.functional.conv2d(
            m.reshape(b * c, 1, gh, gw), ker, padding=1).reshape(b, c, gh, gw)
        new = (m == 0) & (den > 0)
        vals = torch.where(new, num / den.clamp(min=1e-12), vals)
        m = torch.where(new, torch.ones_like(m), m)
    return torch.where(m.bool(), vals, torch.full_like(vals, float("nan")))


def _interp_axis(coord: Tensor, n: int, mode: str):
    """Taps (L, K) indices into a node axis of length n padded by 1 ghost node at each end
    (index 0 = ghost) and their weights, for coordinates ``coord`` (L,) in node units."""
    if n == 1:
        idx = torch.ones_like(coord, dtype=torch.long).unsqueeze(-1)
        return idx, torch.ones_like(coord).unsqueeze(-1)
    i0 = torch.floor(coord).clamp(0, n - 2)
    t = coord - i0  # outside the grid: linear extrapolation from the edge cell
    i0 = i0.long() + 1  # shift for the ghost node
    if mode == "bilinear":
        return torch.stack([i0, i0 + 1], -1), torch.stack([1 - t, t], -1)
    inside = (t >= 0) & (t <= 1)
    tc = t.clamp(0, 1)
    t2, t3 = tc * tc, tc * tc * tc
    # Catmull-Rom (Keys a = -0.5): reproduces quadratics; ghost nodes make it linear-exact
    w = torch.stack([
        -0.5 * t3 + t2 - 0.5 * tc,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * tc,
        0.5 * t3 - 0.5 * t2,
    ], -1)
    lin = torch.stack([torch.zeros_like(t), 1 - t, t, torch.zeros_like(t)], -1)
    w = torch.where(inside.unsqueeze(-1), w, lin)
    return torch.stack([i0 - 1, i0, i0 + 1, i0 + 2], -1), w


def points_to_dense(
    points: Tensor,
    values: Tensor,
    shape: tuple[int, int],
    *,
    mode: str = "bilinear",
    nan: str = "keep",
) -> Tensor:
    """Interpolate values at POIs on a regular grid to a dense field.

    Args:
        points: (N, 2) POIs (x, y) px on a regular (possibly anisotropic) grid, any order
            (e.g. :func:`torch_stsdic.grid_points` without a mask); shared by the batch.
        values: (B, N, C) values at the POIs (e.g. ``STSDIC`` displacements, C = 2), or
            (N, C) for B = 1 (a (1, C, H, W) field is returned).
        shape: (H, W) of the dense field; pixel (row i, col j) is at (x, y) = (j, i).
        mode: "bilinear" or "bicubic" (Catmull-Rom, exact for linear and quadratic fields).
            Beyond the outermost POIs the field is extrapolated linearly from the edge cell.
        nan: NaN values (failed POIs). "keep": they are filled from valid neighbours for
            the interpolation, then every pixel whose nearest grid node was NaN is set to
            NaN (nothing is silently invented where DIC failed); "fill": the filled field
            is returned as is (NaN only if the whole grid is NaN).

    Returns:
        (B, C, H, W) field in ``values``' dtype and device; differentiable w.r.t. ``values``.
    """
    if mode not in ("bilinear", "bicubic"):
        raise ValueError(f"mode must be 'bilinear' or 'bicubic', got {mode!r}")
    if nan not in ("keep", "fill"):
        raise ValueError(f"nan must be 'keep' or 'fill', got {nan!r}")
    if values.dim() == 2:
        values = values.unsqueeze(0)
    if points.dim() != 2 or points.shape[-1] != 2 or values.dim() != 3 \
            or values.shape[1] != points.shape[0]:
        raise ValueError(f"points must be (N, 2) and values (B, N, C), got "
                         f"{tuple(points.shape)} and {tuple(values.shape)}")
    b, n, c = values.shape
    h, w = int(shape[0]), int(shape[1])
    dtype, device = values.dtype, values.device
    origin, spacing, ix, iy = _grid_axes(points.to(device))
    gw, gh = int(ix.max()) + 1, int(iy.max()) + 1
    if gw * gh != n or int(ix.min()) != 0 or int(iy.min()) != 0:
        raise ValueError(f"points do not fill a regular grid ({n} points for a "
                         f"{gh} x {gw} grid)")
    node = iy * gw + ix
    if torch.unique(node).numel() != n:
        raise ValueError("points contain duplicates")
    grid = torch.empty(b, c, gh * gw, dtype=dtype, device=device)
    grid = grid.index_copy(2, node, values.transpose(1, 2)).reshape(b, c, gh, gw)
    valid = torch.isfinite(grid)
    if not bool(valid.all()):
        grid = _fill_nan_nodes(grid, valid, max_iter=gh + gw)
    # ghost nodes: linear extrapolation (constant when an axis has a single node)
    if gw > 1:
        grid = torch.cat([2 * grid[..., :1] - grid[..., 1:2], grid,
                          2 * grid[..., -1:] - grid[..., -2:-1]], -1)
    else:
        grid = torch.cat([grid, grid, grid], -1)
    if gh > 1:
        grid = torch.cat([2 * grid[..., :1, :] - grid[..., 1:2, :], grid,
                          2 * grid[..., -1:, :] - grid[..., -2:-1, :]], -2)
    else:
        grid = torch.cat([grid, grid, grid], -2)
    cx = (torch.arange(w, dtype=torch.float64, device=device) - origin[0]) / spacing[0]
    cy = (torch.arange(h, dtype=torch.float64, device=device) - origin[1]) / spacing[1]
    jx, wx = _interp_axis(cx, gw, mode)  # (W, K)
    jy, wy = _interp_axis(cy, gh, mode)  # (H, K)
    wx, wy = wx.to(dtype), wy.to(dtype)
    # separable: along x then y
    tmp = (grid[..., jx] * wx).sum(-1)  # (B, C, gh+2, W)
    out = (tmp.transpose(-1, -2)[..., jy] * wy).sum(-1).transpose(-1, -2)  # (B, C, H, W)
    if nan == "keep" and not bool(valid.all()):
        nx = torch.round(cx).clamp(0, gw - 1).long()
        ny = torch.round(cy).clamp(0, gh - 1).long()
        near_bad = ~valid[:, :, ny][:, :, :, nx]
        out = torch.where(near_bad, torch.full_like(out, float("nan")), out)
    return out


def dense_to_points(flow: Tensor, points: Tensor, *, mode: str = "bilinear") -> Tensor:
    """Sample a dense field at POIs (e.g. a network's flow, as ``STSDIC`` init).

    Args:
        flow: (B, C, H, W) field (C = 2: u, v in px); pixel (row i, col j) at (x, y) = (j, i).
        points: (N, 2) shared or (B, N, 2) POIs (x, y) px.
        mode: "bilinear" (default) or "bicubic" (``grid_sample``, align_corners=True, so
            pixel centres are at integer coordinates; border values beyond the edges).

    Returns:
        (B, N, C), differentiable w.r.t. ``flow`` (and ``points``).
    """
    if flow.dim() != 4:
        raise ValueError(f"flow must be (B, C, H, W), got {tuple(flow.shape)}")
    b, _, h, w = flow.shape
    pts = points.to(device=flow.device, dtype=flow.dtype)
    if pts.dim() == 2:
        pts = pts.unsqueeze(0).expand(b, -1, -1)
    if pts.dim() != 3 or pts.shape[0] != b or pts.shape[-1] != 2:
        raise ValueError(f"points must be (N, 2) or (B={b}, N, 2), got {tuple(points.shape)}")
    sx = 2.0 / max(w - 1, 1)
    sy = 2.0 / max(h - 1, 1)
    grid = torch.stack([pts[..., 0] * sx - 1.0, pts[..., 1] * sy - 1.0], -1).unsqueeze(2)
    out = torch.nn.functional.grid_sample(flow, grid, mode=mode, padding_mode="border",
                                          align_corners=True)  # (B, C, N, 1)
    return out[..., 0].transpose(1, 2)
