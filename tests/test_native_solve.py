"""The per-point C++ solve (``sts_ic_solve``: every point iterated to its end in one call, no
barrier per iteration) against the batched loop (one step of all points at a time): the same
statuses and iteration counts, parameters and ZNCC equal to float rounding, on renders."""

import os

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.core import point_solve
from torch_stsdic.kernels import dispatch, native

pytestmark = pytest.mark.skipif(not native.available(), reason="no native kernels")


@pytest.fixture(autouse=True)
def _restore_mode():
    old = os.environ.get("TORCH_STSDIC_PER_POINT")
    yield
    if old is None:
        os.environ.pop("TORCH_STSDIC_PER_POINT", None)
    else:
        os.environ["TORCH_STSDIC_PER_POINT"] = old


def _movie(m: int, n: int = 96, margin: float = 12.0, every: float = 3.0,
           edge: tuple = ((10.2, 40.0), (10.6, 50.0))):
    """A rendered speckle movie (homogeneous strain and a translation moving in time), its
    2m + 1 frames, points on a grid ``every`` px apart ``margin`` px inside, and two (``edge``:
    (x, y) from the left and (x from the right, y)) whose subsets leave the image once moved
    (OUTSIDE statuses)."""
    pattern = synth.make_speckle((n, n), seed=5)
    motion = synth.HomogeneousStrain(exx=0.01, eyy=-0.004, exy=0.003, center=(n / 2, n / 2)) \
        + synth.Translation(0.4, -0.3, ut=0.05, vt=0.02)
    times = torch.arange(0.0, 2 * m + 1, dtype=torch.float64)
    ref, frames = synth.render_series(pattern, (n, n), motion, times, noise_sigma=1.0, seed=3,
                                      reference_time=None)
    c = torch.arange(margin, n - margin, every, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    (x0, y0), (x1, y1) = edge
    pts = torch.cat([torch.stack([xx.reshape(-1), yy.reshape(-1)], 1),
                     torch.tensor([[x0, y0], [n - x1, y1]], dtype=torch.float64)])
    return ref, (frames if m else frames[0]), pts, times


def _both(m, criterion, dtype="float32", shape="affine", shared=False, calls=None, **cfg):
    ref, frames, pts, times = _movie(m)
    config = sts.DICConfig(m=m, dtype=dtype, criterion=criterion, shape=shape, **cfg)
    kw = {}
    if shared:  # the specimen's known motion, carried in every warp
        kw["shared_motion"] = torch.stack([0.1 * times, -0.05 * times], 1)
    out = []
    for mode in ("1", "0"):
        os.environ["TORCH_STSDIC_PER_POINT"] = mode
        out.append(sts.solve_window(ref, frames, pts, config=config, **kw))
    return out


def _assert_same(a, b, atol):
    assert torch.equal(a.status, b.status)
    assert torch.equal(a.iterations, b.iterations)
    ok = a.status <= int(sts.Status.MAX_ITER)
    assert ok.float().mean() > 0.9
    torch.testing.assert_close(a.params[ok], b.params[ok], rtol=0, atol=atol)
    torch.testing.assert_close(a.zncc[ok], b.zncc[ok], rtol=0, atol=atol)
    assert torch.equal(torch.isnan(a.params), torch.isnan(b.params))


@pytest.mark.parametrize("m", [0, 2])
@pytest.mark.parametrize("criterion", ["znssd", "ssd"])
def test_per_point_equals_batched(m, criterion):
    a, b = _both(m, criterion)
    _assert_same(a, b, atol=2e-5)


def test_per_point_equals_batched_float64_and_shared_motion():
    a, b = _both(2, "znssd", dtype="float64", shared=True)
    _assert_same(a, b, atol=1e-10)
    a, b = _both(2, "znssd", shared=True)
    _assert_same(a, b, atol=2e-5)


def test_per_point_statuses_max_iter_and_outside():
    a, b = _both(2, "znssd", max_iter=2)  # most points run out of iterations
    assert (a.status == int(sts.Status.MAX_ITER)).any()
    _assert_same(a, b, atol=2e-5)
    assert (a.status == int(sts.Status.OUTSIDE)).any() or \
        (a.status == int(sts.Status.DIVERGED)).any()


def test_quadratic_shape_falls_back_to_the_batched_loop(monkeypatch):
    calls = []
    real = native.ic_solve
    monkeypatch.setattr(native, "ic_solve", lambda *a, **k: calls.append(1) or real(*a, **k))
    a, b = _both(1, "znssd", shape="quadratic")
    assert not calls  # not closed under composition: no per-point kernel
    _assert_same(a, b, atol=0)
    _both(1, "znssd")
    assert calls  # the affine shape takes it


def test_dispatch_rules():
    ref, frames, _, _ = _movie(0, n=32)
    img = sts.BSplineImage(ref.float().unsqueeze(0))
    ka = img.kernel_args()
    p = torch.zeros(4, 6)
    assert dispatch.ic_solve(ka, p, p, 3, True) == "native"
    assert dispatch.ic_solve(ka, p, p, 6, True) == "torch"  # quadratic
    assert dispatch.ic_solve(ka, p, p, 3, False) == "torch"
    assert dispatch.ic_solve(ka, p.double(), p, 3, True) == "torch"  # not the image's dtype
    assert dispatch.ic_solve(ka, p.requires_grad_(), p, 3, True) == "torch"  # autograd
    os.environ["TORCH_STSDIC_PER_POINT"] = "0"
    assert dispatch.ic_solve(ka, p.detach(), p, 3, True) == "torch"


def test_classical_step_from_the_last_frame_rhs():
    """The model check's classical step (the last step's frame-by-frame right-hand sides)
    from the per-point solve equals the batched loop's."""
    ref, frames, pts, _ = _movie(2)
    solver = sts.SubsetSolver(sts.DICConfig(m=2, dtype="float32"))
    r, f = solver.prepare(ref), solver.prepare(frames)
    dt = (torch.arange(5.0) - 2).expand(len(pts), -1)
    fidx = torch.arange(5).expand(len(pts), -1)
    out = []
    for mode in ("1", "0"):
        os.environ["TORCH_STSDIC_PER_POINT"] = mode
        out.append(solver.solve(r, f, pts.float(), dt, frame_index=fidx, classical_step=True,
                                ref_pixels=ref.float().unsqueeze(0), frame_pixels=frames.float()))
    a, b = out
    assert torch.equal(a.status, b.status)
    ca, cb = a.info.get("classical_step"), b.info.get("classical_step")
    if ca is None:
        pytest.skip("this solver does not report the classical step in info")
    assert torch.equal(torch.isnan(ca), torch.isnan(cb))
    ok = ~torch.isnan(ca)
    torch.testing.assert_close(ca[ok], cb[ok], rtol=1e-4, atol=1e-4)


def test_applies_only_to_the_joint_ic_affine_stage():
    assert point_solve.CODES == (0, 1, 2, 3)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_guesses_of_nan_inf_or_far_away_are_a_status_not_a_crash(dtype):
    """Rows started from NaN, an infinite or a far-away guess (a caller's bad init): the C++
    kernels clamp every sample inside the image (a NaN coordinate once read past its plane:
    a segmentation fault in float64), the rows end DIVERGED or OUTSIDE with NaN numbers, and
    the other rows get what they get without them."""
    ref, frames, pts, _ = _movie(1, n=64, every=6.0)
    solver = sts.SubsetSolver(sts.DICConfig(m=1, subset_size=15, dtype=dtype))
    r, f = solver.prepare(ref), solver.prepare(frames)
    p = pts.to(getattr(torch, dtype))
    init = torch.zeros(p.shape[0], 8, dtype=p.dtype)
    init[:, 0], init[:, 4] = 0.4, -0.3
    good = solver.solve(r, f, p, torch.tensor([-1.0, 0.0, 1.0]), init=init)
    bad = init.clone()
    bad[3] = float("nan")
    bad[5, 0] = float("inf")
    bad[6, 4] = float("-inf")
    bad[7, 0] = 1e30
    bad[9, 3] = float("nan")  # the velocity alone
    sol = solver.solve(r, f, p, torch.tensor([-1.0, 0.0, 1.0]), init=bad)
    hit = torch.tensor([3, 5, 6, 7, 9])
    assert set(sol.status[hit].tolist()) <= {int(sts.Status.DIVERGED), int(sts.Status.OUTSIDE)}
    assert bool(torch.isnan(sol.params[hit]).all())
    rest = torch.ones(p.shape[0], dtype=torch.bool)
    rest[hit] = False
    assert torch.equal(sol.status[rest], good.status[rest])
    assert torch.equal(sol.params[rest].nan_to_num(0), good.params[rest].nan_to_num(0))
