"""Core solver: known motions from the analytic speckle renderer, formulations, edge cases."""

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core.status import Status
from torch_stsdic.kernels.compile import compile_failed

SIZE = (101, 101)


@pytest.fixture(scope="module")
def pattern():
    return synth.make_speckle(SIZE, seed=4)


def _grid(lo=30, hi=71, step=10):
    c = torch.arange(lo, hi, step, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)


def _series(pattern, motion, times, sigma=0.0, seed=0):
    return synth.render_series(
        pattern, SIZE, motion, torch.as_tensor(times, dtype=torch.float64),
        noise_sigma=sigma, seed=seed, reference_time=None,
    )


def test_translation_classical_and_sts(pattern):
    motion = synth.Translation(0.3, -0.2, ut=0.05, vt=0.02)
    ref, frames = _series(pattern, motion, [1, 2, 3, 4, 5])
    pts = _grid()
    # classical: one frame
    sol0 = sts.solve_window(ref, frames[2], pts, config=sts.DICConfig(m=0))
    assert (sol0.status == Status.CONVERGED).all()
    assert torch.allclose(sol0.u, torch.full_like(sol0.u, 0.45), atol=2e-3)
    assert torch.allclose(sol0.v, torch.full_like(sol0.v, -0.14), atol=2e-3)
    assert torch.isnan(sol0.ut).all()  # one frame has no velocity
    assert sol0.params.shape == (pts.shape[0], 6)
    # STS: five frames, results at the centre frame (t = 3)
    sol = sts.solve_window(ref, frames, pts, config=sts.DICConfig(m=2), times=[1, 2, 3, 4, 5])
    assert (sol.status == Status.CONVERGED).all()
    assert sol.params.shape == (pts.shape[0], 8)
    assert torch.allclose(sol.u, torch.full_like(sol.u, 0.45), atol=2e-3)
    assert torch.allclose(sol.v, torch.full_like(sol.v, -0.14), atol=2e-3)
    assert torch.allclose(sol.ut, torch.full_like(sol.ut, 0.05), atol=5e-4)
    assert torch.allclose(sol.vt, torch.full_like(sol.vt, 0.02), atol=5e-4)
    assert sol.time == 3.0
    assert (sol.zncc > 0.999).all()


@pytest.mark.parametrize("formulation", ["joint", "average", "joint+average", "auto"])
def test_formulations_find_displacement(pattern, formulation):
    motion = synth.Translation(0.2, 0.1, ut=0.05, vt=-0.03)
    ref, frames = _series(pattern, motion, [0, 1, 2])
    sol = sts.solve_window(ref, frames, _grid(), config=sts.DICConfig(m=1, formulation=formulation))
    assert torch.allclose(sol.u, torch.full_like(sol.u, 0.25), atol=3e-3)
    assert torch.allclose(sol.v, torch.full_like(sol.v, 0.07), atol=3e-3)
    if formulation != "average":  # the averaged image hardly sees the velocity (see README)
        assert torch.allclose(sol.ut, torch.full_like(sol.ut, 0.05), atol=1e-3)


def test_identical_frames_reduce_to_classical(pattern):
    # 2m+1 copies of one frame: zero velocity and the classical (m = 0) answer
    ref, frames = _series(pattern, synth.Translation(0.37, 0.21), [0])
    pts = _grid()
    classical = sts.solve_window(ref, frames[0], pts, config=sts.DICConfig(m=0, tol=1e-8))
    sts_sol = sts.solve_window(ref, frames.expand(5, -1, -1), pts,
                               config=sts.DICConfig(m=2, tol=1e-8))
    assert torch.allclose(sts_sol.u, classical.u, atol=1e-7)
    assert torch.allclose(sts_sol.v, classical.v, atol=1e-7)
    assert sts_sol.ut.abs().max() < 1e-7


def test_subpixel_sweep_systematic_error(pattern):
    # noise-free sub-pixel shifts 0..1 px: peak systematic error <= 2e-3 px with cubic B-splines
    shifts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    ref = synth.render(pattern, SIZE)
    frames = torch.stack([synth.render(pattern, SIZE, synth.Translation(float(s), 0.0))
                          for s in shifts])
    pts = _grid()
    worst = 0.0
    for i, s in enumerate(shifts):
        sol = sts.solve_window(ref, frames[i], pts, config=sts.DICConfig(m=0))
        worst = max(worst, abs(float((sol.u - s).mean())))
    assert worst <= 2e-3


def test_homogeneous_strain_and_linear_in_time(pattern):
    motion = synth.HomogeneousStrain(exx=0.004, eyy=-0.002, exy=0.001, center=(50.0, 50.0),
                                     rate=1.0)
    times = [1.0, 2.0, 3.0]
    ref, frames = _series(pattern, motion, times)
    pts = _grid()
    sol = sts.solve_window(ref, frames, pts, config=sts.DICConfig(m=1), times=times)
    truth = synth.ground_truth(motion, pts, torch.tensor([2.0], dtype=torch.float64))
    assert torch.allclose(sol.u, truth["u"][0], atol=3e-3)
    assert torch.allclose(sol.v, truth["v"][0], atol=3e-3)
    # the STS shape function has no dx*dt term (Eq. 9 drops it), so a strain *rate* of
    # 0.4 %/frame biases ut by a few 1e-3 px/frame on a random pattern
    assert torch.allclose(sol.ut, truth["ut"][0], atol=5e-3)
    ux = sol.params[:, sol.param_names.index("ux")]
    vy = sol.params[:, sol.param_names.index("vy")]
    assert torch.allclose(ux, truth["dudx"][0], atol=2e-4)
    assert torch.allclose(vy, truth["dvdy"][0], atol=2e-4)


def test_quadratic_shape(pattern):
    motion = synth.HomogeneousStrain(exx=0.003, eyy=0.0, exy=0.0, center=(50.0, 50.0))
    ref, frames = _series(pattern, motion, [0.0, 1.0, 2.0])
    sol = sts.solve_window(ref, frames, _grid(), config=sts.DICConfig(m=1, shape="quadratic"))
    truth = synth.ground_truth(motion, _grid(), torch.tensor([1.0], dtype=torch.float64))
    assert sol.params.shape[1] == 14
    assert torch.allclose(sol.u, truth["u"][0], atol=3e-3)
    uxx = sol.params[:, sol.param_names.index("uxx")]
    assert uxx.abs().max() < 1e-3


@pytest.mark.parametrize("window", ["circular", "gaussian"])
def test_other_windows(pattern, window):
    ref, frames = _series(pattern, synth.Translation(0.4, 0.1), [0])
    sol = sts.solve_window(ref, frames[0], _grid(), config=sts.DICConfig(m=0, window=window))
    assert torch.allclose(sol.u, torch.full_like(sol.u, 0.4), atol=3e-3)


def test_znssd_ignores_intensity_change_ssd_does_not(pattern):
    ref, frames = _series(pattern, synth.Translation(0.3, 0.0), [0])
    g = 1.3 * frames[0] + 12.0
    z = sts.solve_window(ref, g, _grid(), config=sts.DICConfig(m=0, criterion="znssd"))
    assert torch.allclose(z.u, torch.full_like(z.u, 0.3), atol=2e-3)
    s = sts.solve_window(ref, frames[0], _grid(), config=sts.DICConfig(m=0, criterion="ssd"))
    assert torch.allclose(s.u, torch.full_like(s.u, 0.3), atol=2e-3)


def test_fft_initial_guess_and_user_init(pattern):
    ref, frames = _series(pattern, synth.Translation(4.3, -3.6), [0])
    pts = _grid(35, 66, 10)
    sol = sts.solve_window(ref, frames[0], pts, config=sts.DICConfig(m=0, search_radius=8))
    assert torch.allclose(sol.u, torch.full_like(sol.u, 4.3), atol=3e-3)
    assert torch.allclose(sol.v, torch.full_like(sol.v, -3.6), atol=3e-3)
    init = torch.tensor([[4.0, -3.5]], dtype=torch.float64).expand(pts.shape[0], -1)
    sol2 = sts.solve_window(ref, frames[0], pts, config=sts.DICConfig(m=0, search_radius=0),
                            init=init)
    assert torch.allclose(sol2.u, sol.u, atol=1e-4)


def test_init_and_init_step_must_have_a_row_per_point(pattern):
    """SubsetSolver.solve: an init or init_step of another length than the points is a clear
    error (an init with extra rows was used silently, its first rows taken)."""
    ref, frames = _series(pattern, synth.Translation(0.3, 0.1), [0])
    solver = sts.SubsetSolver(sts.DICConfig(m=0))
    args = (solver.prepare(ref), solver.prepare(frames), _grid(35, 45, 10), torch.zeros(1))
    n = args[2].shape[0]
    with pytest.raises(ValueError, match=rf"init must be \(N, P\) with a row for each of "
                                         rf"the {n} points, got \({n + 1}, 6\)"):
        solver.solve(*args, init=torch.zeros(n + 1, 6))
    with pytest.raises(ValueError, match=rf"init_step must be \(N,\) with a value for each "
                                         rf"of the {n} points"):
        solver.solve(*args, init=torch.zeros(n, 6), init_step=torch.zeros(n + 1))
    ok = solver.solve(*args, init=torch.zeros(n, 6), init_step=torch.zeros(n))
    assert bool(ok.ok.all())


def test_float32_matches_float64(pattern):
    ref, frames = _series(pattern, synth.Translation(0.3, 0.2, ut=0.05), [0, 1, 2])
    pts = _grid()
    s64 = sts.solve_window(ref, frames, pts, config=sts.DICConfig(m=1))
    s32 = sts.solve_window(ref.float(), frames.float(), pts.float(), config=sts.DICConfig(m=1))
    assert s32.u.dtype == torch.float32 and s64.u.dtype == torch.float64
    assert torch.allclose(s32.u.double(), s64.u, atol=5e-4)
    assert torch.allclose(s32.ut.double(), s64.ut, atol=5e-4)


def test_numpy_and_uint8_inputs(pattern):
    ref, frames = _series(pattern, synth.Translation(0.5, 0.0), [0])
    ref8 = synth.quantize(ref, 8).numpy().astype(np.uint8)
    g8 = synth.quantize(frames[0], 8).numpy().astype(np.uint8)
    sol = sts.solve_window(ref8, g8, _grid().numpy(), config=sts.DICConfig(m=0))
    assert sol.u.dtype == torch.float32
    assert torch.allclose(sol.u, torch.full_like(sol.u, 0.5), atol=1e-2)


def test_ic_hessian_matches_brute_force(pattern):
    # the factored IC Hessian equals sum_t J_t^T J_t built explicitly (ZNSSD: centred J)
    from torch_stsdic.core.formulations import Geometry, ic_hessian, ic_jacobian

    solver = sts.SubsetSolver(sts.DICConfig(m=1, subset_size=11))
    ref = synth.render(pattern, SIZE)
    img = solver.prepare(ref)
    off, w = solver.window.offsets_and_weights(torch.float64, None)
    dt = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 0.5]], dtype=torch.float64)
    pts = torch.tensor([[40.0, 50.0], [60.3, 44.7]], dtype=torch.float64)
    f, gx, gy = img.sample(pts[:, :1] + off[:, 0], pts[:, 1:] + off[:, 1], grad=True)
    shape = solver.shape
    geo = Geometry.make(shape, solver.window, "znssd", torch.float64, None)
    h = ic_hessian(geo, gx, gy, dt)
    basis = torch.stack([shape.basis(off[:, 0], off[:, 1], dt[i]) for i in range(2)])  # N,T,S,K
    jac = torch.cat([gx[:, None, :, None] * basis, gy[:, None, :, None] * basis], -1)
    jac = jac - (jac * w[None, None, :, None]).sum(2, keepdim=True) / w.sum()
    brute = torch.einsum("ntsp,ntsq->npq", jac * w[None, None, :, None], jac)
    assert torch.allclose(h, brute, rtol=1e-10, atol=1e-8)
    # the Jacobian the noise model and the Hessian come from is that same J
    assert torch.allclose(ic_jacobian(geo, gx, gy, dt), jac, rtol=1e-12, atol=1e-9)


# ---- bad input ------------------------------------------------------------------------
def test_points_near_edges_are_flagged_not_crashing(pattern):
    ref, frames = _series(pattern, synth.Translation(0.2, 0.0), [0])
    pts = torch.tensor([[50.0, 50.0], [5.0, 50.0], [50.0, 98.0], [-3.0, 200.0]],
                       dtype=torch.float64)
    sol = sts.solve_window(ref, frames[0], pts, config=sts.DICConfig(m=0))
    assert sol.status.tolist() == [Status.CONVERGED, Status.OUTSIDE, Status.OUTSIDE,
                                   Status.OUTSIDE]
    assert torch.isnan(sol.u[1:]).all() and torch.isfinite(sol.u[0])


def test_flat_texture_is_flagged(pattern):
    ref, frames = _series(pattern, synth.Translation(0.2, 0.0), [0])
    ref = ref.clone()
    frames = frames.clone()
    ref[:, :45] = 100.0
    frames[:, :, :45] = 100.0
    pts = torch.tensor([[20.0, 50.0], [70.0, 50.0]], dtype=torch.float64)
    sol = sts.solve_window(ref, frames[0], pts, config=sts.DICConfig(m=0))
    assert sol.status.tolist() == [Status.LOW_TEXTURE, Status.CONVERGED]


def test_subset_leaving_image_during_iterations():
    # a motion that carries the subset out of the image ends as OUTSIDE, not NaN noise
    pat = synth.make_speckle(SIZE, seed=1)
    ref = synth.render(pat, SIZE)
    g = synth.render(pat, SIZE, synth.Translation(6.0, 0.0))
    pts = torch.tensor([[88.0, 50.0]], dtype=torch.float64)
    sol = sts.solve_window(ref, g, pts, config=sts.DICConfig(m=0, subset_size=21),
                           init=torch.tensor([[6.0, 0.0]], dtype=torch.float64))
    assert sol.status.tolist() == [Status.OUTSIDE]


@pytest.mark.parametrize(
    "kwargs,exc,match",
    [
        (dict(ref=np.zeros((50, 50, 3))), ValueError, "colour"),
        (dict(ref=np.zeros((4, 50, 50))), ValueError, "ref"),
        (dict(frames=np.zeros((3, 40, 50))), ValueError, "differs from the reference"),
        (dict(frames=np.zeros((2, 50, 50))), ValueError, "m is larger than the frames"),
        (dict(points=np.zeros((5, 3))), ValueError, "points"),
        (dict(points=np.full((2, 2), np.nan)), ValueError, "points"),
        (dict(times=[0, 2, 1]), ValueError, "times"),
        (dict(times=[0, 1]), ValueError, "times"),
        (dict(init=np.zeros((7, 2))), ValueError, "init"),
        (dict(ref="image.tif"), TypeError, "ref"),
        (dict(config={"m": 1}), TypeError, "config"),
    ],
)
def test_bad_input_messages(kwargs, exc, match):
    rng = np.random.default_rng(0)
    args = dict(ref=rng.random((50, 50)) * 200, frames=rng.random((3, 50, 50)) * 200,
                points=np.array([[25.0, 25.0]]), config=sts.DICConfig(m=1, subset_size=11))
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        sts.solve_window(**args)


def test_non_finite_pixels_and_tiny_images():
    rng = np.random.default_rng(0)
    ref = rng.random((50, 50)) * 200
    frames = rng.random((1, 50, 50)) * 200
    bad = ref.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        sts.solve_window(bad, frames, [[25.0, 25.0]], config=sts.DICConfig(m=0))
    frames_bad = frames.copy()
    frames_bad[0, 1, 1] = np.inf
    with pytest.raises(ValueError, match="frames: contains 1 non-finite"):
        sts.solve_window(ref, frames_bad, [[25.0, 25.0]], config=sts.DICConfig(m=0))
    with pytest.raises(ValueError, match="larger than the image"):
        sts.solve_window(ref[:15, :15], frames[:, :15, :15], [[7.0, 7.0]],
                         config=sts.DICConfig(m=0, subset_size=21))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(subset_size=20), "subset_size"),
        (dict(m=-1), "m"),
        (dict(criterion="ncc"), "criterion"),
        (dict(formulation="best"), "formulation"),
        (dict(interpolation="linear"), "interpolation"),
        (dict(tol=0), "tol"),
        (dict(shape="cubic"), "shape"),
    ],
)
def test_bad_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sts.DICConfig(**kwargs)


@pytest.mark.slow  # compiles three kernels: 1-3 min on 2 cores
def test_compiled_ic_step_matches_eager(pattern):
    # large jobs run the fused (torch.compile) IC step: same answer as the eager code
    from torch_stsdic.core import interpolation

    ref, frames = _series(pattern, synth.Translation(0.3, -0.2, ut=0.05), [0, 1, 2])
    cfg = sts.DICConfig(m=1)
    interpolation.set_compile(False)
    try:
        eager = sts.solve_window(ref.float(), frames.float(), _grid().float(), config=cfg)
        interpolation.set_compile(True)
        fused = sts.solve_window(ref.float(), frames.float(), _grid().float(), config=cfg)
    finally:
        interpolation.set_compile("auto")
    if compile_failed():
        pytest.skip("torch.compile is not available on this machine (eager fallback used)")
    assert torch.allclose(fused.u, eager.u, atol=1e-4)
    assert torch.allclose(fused.ut, eager.ut, atol=1e-4)
    assert (fused.status == eager.status).all()


def test_stopping_rule_predicts_the_next_increment():
    from torch_stsdic.core.gauss_newton import RATE_FLOOR, _next_increment

    norm = torch.tensor([1e-3, 1e-3, 1e-3, 2e-3, 1e-3])
    prev = torch.tensor([0.0, 0.1, 1.5e-3, 1e-3, float("nan")])
    got = _next_increment(norm, prev)
    # no previous increment: the increment itself; a fast rate: no faster than the floor;
    # a slow rate: the rate; a growing increment (or none known): the increment itself
    want = torch.tensor([1e-3, 1e-3 * RATE_FLOOR, 1e-3 * (1e-3 / 1.5e-3), 2e-3, 1e-3])
    assert torch.allclose(got, want, rtol=1e-6)


@pytest.mark.parametrize("m", [0, 2])
def test_stopping_rule_stays_within_tol_of_the_minimum(pattern, m, monkeypatch):
    """Stopping once the predicted next increment is below tol: the solution is within a few
    tol of the one converged to 1e-10 px, with fewer iterations than waiting for the
    increment itself to be below tol (a rate floor of 1: no prediction)."""
    motion = synth.Translation(0.6, -0.3, ut=0.04, vt=0.02) + synth.HomogeneousStrain(
        exx=0.004, eyy=-0.003, center=(50.0, 50.0), rate=0.3)
    ref, frames = _series(pattern, motion, [1, 2, 3, 4, 5], sigma=2.0, seed=3)
    pts = _grid(step=5)
    win = frames if m else frames[2]
    sol = sts.solve_window(ref, win, pts, config=sts.DICConfig(m=m))
    tight = sts.solve_window(ref, win, pts, config=sts.DICConfig(m=m, tol=1e-10, max_iter=60))
    assert sol.ok.all() and tight.ok.all()
    tol = sts.DICConfig().tol
    assert (sol.u - tight.u).abs().max() < 3 * tol
    assert (sol.v - tight.v).abs().max() < 3 * tol
    monkeypatch.setattr("torch_stsdic.core.gauss_newton.RATE_FLOOR", 1.0)
    plain = sts.solve_window(ref, win, pts, config=sts.DICConfig(m=m))
    assert (plain.u - tight.u).abs().max() < tol
    assert sol.iterations.float().mean() < plain.iterations.float().mean() - 0.5


def test_texture_is_read_off_the_gram():
    from torch_stsdic.core.formulations import Geometry, centred_gram, gram_and_texture

    g = torch.Generator().manual_seed(2)
    shape = sts.AffineShape(temporal=False)
    for window in (sts.SquareWindow(11), sts.GaussianWindow(11)):
        geo = Geometry.make(shape, window, "znssd", torch.float64, torch.device("cpu"))
        gx = torch.randn(6, geo.w.numel(), generator=g, dtype=torch.float64)
        gy = torch.randn(6, geo.w.numel(), generator=g, dtype=torch.float64)
        cg, texture = gram_and_texture(geo, gx, gy)
        want = ((gx * gx + gy * gy) * geo.w).sum(-1) / geo.w.sum()
        assert torch.allclose(texture, want, rtol=1e-12)
        assert torch.equal(cg, centred_gram(geo, gx, gy))


def test_classical_step_is_one_classical_step_from_the_window(pattern):
    """info["classical_step"]: the classical solution one Gauss-Newton step from the window's
    solution at its centre frame, read off the window solve's last step: what the classical
    solver's own first step from there gives (to the size of the window's last increment),
    and much nearer the classical minimum than the window's solution."""
    from torch_stsdic.kernels import native

    if not native.available():
        pytest.skip("the classical step comes from the native kernel (not built here)")
    motion = synth.Translation(0.6, -0.3, ut=0.04, vt=0.02) + synth.HomogeneousStrain(
        exx=0.004, eyy=-0.003, center=(50.0, 50.0), rate=0.3)
    ref, frames = _series(pattern, motion, [1, 2, 3, 4, 5], sigma=2.0, seed=3)
    pts = _grid(step=5)
    solver = sts.SubsetSolver(sts.DICConfig(m=2))
    ref_img, frames_img = solver.prepare(ref), solver.prepare(frames)
    dt = torch.arange(-2.0, 3.0, dtype=torch.float64)
    sol = solver.solve(ref_img, frames_img, pts, dt, ref_pixels=ref.unsqueeze(0),
                       frame_pixels=frames, classical_step=True)
    step = sol.info["classical_step"]
    assert step.shape == (pts.shape[0], 6) and torch.isfinite(step).all()
    at_centre = torch.cat([sol.params[:, 0:3], sol.params[:, 4:7]], 1)  # u.. v.. at dt = 0
    centre = sts.SubsetSolver(sts.DICConfig(m=0)).prepare(frames[2:3])
    zero = torch.zeros(1, dtype=torch.float64)
    one = sts.SubsetSolver(sts.DICConfig(m=0, max_iter=1, tol=1e-12)).solve(
        ref_img, centre, pts, zero, init=at_centre)
    full = sts.SubsetSolver(sts.DICConfig(m=0, tol=1e-10, max_iter=50)).solve(
        ref_img, centre, pts, zero, init=at_centre)
    assert (step - one.params).abs().max() < 2e-4
    far = (at_centre - full.params)[:, [0, 3]].abs().max()
    assert (step - full.params)[:, [0, 3]].abs().max() < 0.1 * far
    # what the classical solve reports at its minimum, from the Gauss-Newton model
    z, sg = sol.info["classical_step_zncc"], sol.info["classical_step_sigma"]
    sd, size = sol.info["classical_step_std"], sol.info["classical_step_size"]
    assert bool(torch.isfinite(z).all() & torch.isfinite(sg).all() & torch.isfinite(sd).all())
    assert float(((z - full.zncc) / (1 - full.zncc)).abs().max()) < 0.01  # of the misfit
    assert float((sg / full.sigma - 1).abs().max()) < 0.01
    assert float((sd / full.std - 1).abs().max()) < 0.01
    step = (at_centre - one.params)[:, [0, 3]].abs().amax(1)  # the step moved u or v by ...
    assert bool((size >= step - 1e-9).all())  # ... no more than its size
    plain = solver.solve(ref_img, frames_img, pts, dt, ref_pixels=ref.unsqueeze(0),
                         frame_pixels=frames)
    assert "classical_step" not in plain.info and torch.equal(plain.params, sol.params)


def test_classical_step_is_nan_where_the_native_kernel_is_not_used(pattern):
    """Without the native kernel (CUDA, autograd, no compiler) the window solve cannot give
    the classical step: NaN, and the model check starts from the window's solution."""
    from torch_stsdic.kernels import native

    ref, frames = _series(pattern, synth.Translation(0.3, -0.2, ut=0.05), [1, 2, 3])
    pts = _grid()
    solver = sts.SubsetSolver(sts.DICConfig(m=1))
    native.set_native(False)
    try:
        sol = solver.solve(solver.prepare(ref), solver.prepare(frames), pts,
                           torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64),
                           ref_pixels=ref.unsqueeze(0), frame_pixels=frames, classical_step=True)
    finally:
        native.set_native("auto")
    assert sol.ok.all() and torch.isnan(sol.info["classical_step"]).all()


def test_a_solver_keeps_its_geometries_between_solves():
    """``SubsetSolver._geometry``: the same geometry for the same shape, dtype and device
    (its tensors and the bare basis's moments made once), another for another shape or a
    window set anew; a pickled solver makes them again."""
    import pickle

    from torch_stsdic.core.window import make_window

    solver = sts.SubsetSolver(sts.DICConfig(m=1, subset_size=15))
    spatial = solver.shape.spatial()
    g1 = solver._geometry(solver.shape, torch.float32, "cpu")
    assert solver._geometry(solver.shape, torch.float32, "cpu") is g1
    assert solver._geometry(solver.shape, torch.float64, "cpu") is not g1
    g2 = solver._geometry(spatial, torch.float32, "cpu")
    assert g2 is not g1 and g2.spatial.shape == g1.spatial.shape and not g2.shape.has_time
    solver.window = make_window("circular", 15)
    g3 = solver._geometry(solver.shape, torch.float32, "cpu")
    assert g3 is not g1 and g3.w.sum() < g1.w.sum()
    assert pickle.loads(pickle.dumps(solver))._geometries == {}
