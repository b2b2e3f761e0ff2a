"""The fused Triton step (torch_stsdic.kernels) against the torch code, on CPU through
Triton's interpreter (TRITON_INTERPRET=1, small sizes), and on CUDA when there is a GPU."""

from __future__ import annotations

import os

import pytest
import torch

if not torch.cuda.is_available():  # no GPU: Triton's interpreter, before Triton is imported
    os.environ.setdefault("TRITON_INTERPRET", "1")

import torch_stsdic as sts
from torch_stsdic import kernels, synth
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.kernels import dispatch, fused_step, native
from torch_stsdic.kernels.ic_step import ic_rhs_kernel

pytestmark = pytest.mark.skipif(not kernels.available(),
                                reason="triton is not importable (pip install triton)")
INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"


@pytest.fixture(autouse=True)
def _modes():
    yield
    kernels.set_triton("auto")
    native.set_native("auto")


def _case(has_time, dtype, n=6, t=3, half=4, seed=0, device="cpu"):
    """A small random step problem: a 3-frame 40x52 image, affine shape, 9x9 subsets."""
    g = torch.Generator().manual_seed(seed)
    img = BSplineImage(torch.rand(t, 40, 52, generator=g, dtype=dtype) * 255, 3)
    shape = sts.AffineShape(temporal=has_time)
    d = torch.arange(-half, half + 1.0, dtype=dtype)
    dx, dy = d.repeat(d.numel()), d.repeat_interleave(d.numel())
    k = shape.n_basis
    p = torch.randn(n, 2 * k, generator=g, dtype=dtype) * 0.05
    p[:, 0] += 0.7
    c = dict(p=p, px=torch.rand(n, 1, generator=g, dtype=dtype) * 24 + 12,
             py=torch.rand(n, 1, generator=g, dtype=dtype) * 14 + 12, dx=dx, dy=dy,
             basis=shape.spatial_basis(dx, dy),
             dt=(torch.arange(t, dtype=dtype) - t // 2).expand(n, t).contiguous(),
             fidx=torch.randint(0, t, (n, t), generator=g) * img.kernel_args()[-1])
    ft = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    c["ft"] = ft - ft.mean(1, keepdim=True)
    c["fnorm"] = c["ft"].norm(dim=1)
    c["gx"] = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    c["gy"] = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    c["w"] = torch.rand(dx.numel(), generator=g, dtype=dtype) + 0.5
    c = {key: v.to(device) for key, v in c.items()}
    return img.to(device=device), k, c


def _rhs(img, k, c, has_time, znssd, rows=None, p=None, **extra):
    return kernels.ic_rhs(img.kernel_args(), 3, c["p"] if p is None else p, c["px"], c["py"],
                          c["dx"], c["dy"], c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"],
                          c["gx"], c["gy"], c["w"], img.width, img.height, k, has_time, znssd,
                          rows=rows, **extra)


def _motion(c, seed=5):
    """A known displacement (N, T, 2) per point and frame, up to +-1.5 px (subsets stay in)."""
    n, t = c["dt"].shape
    g = torch.Generator().manual_seed(seed)
    m = (torch.rand(n, t, 2, generator=g, dtype=torch.float64) - 0.5) * 3.0
    return m.to(device=c["p"].device, dtype=c["p"].dtype)


def _devices():
    devs = ["cpu"] if INTERPRET else []
    if torch.cuda.is_available() and not INTERPRET:
        devs.append("cuda")
    return devs or [pytest.param("cpu", marks=pytest.mark.skip(
        reason="no CUDA and TRITON_INTERPRET is not 1"))]


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("has_time,znssd", [(True, True), (False, True), (True, False)])
def test_fused_step_matches_torch_code(device, dtype, has_time, znssd):
    img, k, c = _case(has_time, dtype, device=device)
    kernels.set_triton("0")
    want = _rhs(img, k, c, has_time, znssd)  # the torch code (the op's fallback)
    kernels.set_triton("1")
    assert kernels.usable(img.kernel_args()[0], 3, c["dx"].numel(), c["p"])
    got = _rhs(img, k, c, has_time, znssd)
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    scale = float(want[0].abs().max())
    assert got[0].dtype == torch.float64 and got[0].shape == want[0].shape
    assert (got[0] - want[0]).abs().max() <= tol * scale
    assert torch.allclose(got[1], want[1], atol=10 * tol)
    assert torch.equal(got[2], want[2])
    # rows: the step of a few points picked by index (finished points skipped)
    rows = torch.tensor([4, 0, 2], device=device)
    got_r = _rhs(img, k, c, has_time, znssd, rows=rows, p=c["p"][rows])
    assert (got_r[0] - got[0][rows]).abs().max() <= tol * scale
    assert torch.allclose(got_r[1], got[1][rows], atol=10 * tol)


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("has_time,znssd", [(True, True), (False, True), (True, False)])
def test_fused_step_with_shared_motion_matches_torch_code(device, dtype, has_time, znssd):
    """The shared motion (a known displacement per point and frame added to every frame's
    warp): the Triton step equals the torch code (ic_rhs_kernel(..., motion=)) for STS
    (has_time) and classical windows, all rows and picked rows; and the motion is used."""
    img, k, c = _case(has_time, dtype, device=device)
    motion = _motion(c)
    kernels.set_triton("0")
    want = _rhs(img, k, c, has_time, znssd, motion=motion)  # the torch code
    flat, wp, x_lo, x_hi, y_lo, y_hi, shift, _ = img.kernel_args()
    direct = ic_rhs_kernel(flat, c["p"], c["px"], c["py"], c["dx"], c["dy"],
                           c["basis"].T.contiguous(), c["dt"], c["fidx"], c["ft"],
                           c["fnorm"].reshape(-1), c["gx"], c["gy"], c["w"], wp, x_lo, x_hi,
                           y_lo, y_hi, shift, img.width, img.height, c["basis"].shape[1], k,
                           has_time, znssd, 3, motion)
    assert torch.equal(want[0], direct[0].double())
    kernels.set_triton("1")
    got = _rhs(img, k, c, has_time, znssd, motion=motion)
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    scale = float(want[0].abs().max())
    assert (got[0] - want[0]).abs().max() <= tol * scale
    assert torch.allclose(got[1], want[1], atol=10 * tol)
    assert torch.equal(got[2], want[2])
    still = _rhs(img, k, c, has_time, znssd)
    assert float((still[0] - got[0]).abs().max()) > 100 * tol * scale  # the motion is used
    rows = torch.tensor([4, 0, 2], device=device)
    for mode in ("0", "1"):  # picked rows: the motion of each row's data row
        kernels.set_triton(mode)
        got_r = _rhs(img, k, c, has_time, znssd, rows=rows, p=c["p"][rows], motion=motion)
        assert (got_r[0] - got[0][rows]).abs().max() <= tol * scale
        assert torch.allclose(got_r[1], got[1][rows], atol=10 * tol)
    with pytest.raises(ValueError, match="motion must be"):
        _rhs(img, k, c, has_time, znssd, motion=motion[:, :1])


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("has_time", [True, False])
def test_fused_step_frame_rhs_with_shared_motion(device, has_time):
    """frame_rhs with the shared motion: each frame's own right-hand side and ZNCC as the
    native kernel writes them with the same motion, and summing to the joint b."""
    if not native.available():
        pytest.skip("the native kernel is the reference here")
    img, k, c = _case(has_time, torch.float64, device=device)
    motion = _motion(c)
    n, t = c["dt"].shape
    ks = c["basis"].shape[1]
    kernels.set_triton("1")
    rows = torch.tensor([4, 0, 2], device=device)
    cc = {key: v.cpu() for key, v in c.items()}
    for pick in (None, rows):
        p = c["p"] if pick is None else c["p"][pick]
        got = torch.full((p.shape[0], t, 2 * ks + 1), float("nan"), dtype=torch.float64,
                         device=device)
        b, zn, _ = _rhs(img, k, c, has_time, True, rows=pick, p=p, frame_rhs=got,
                        motion=motion)
        want = torch.full_like(got, float("nan")).cpu()
        b_nat, _, _ = native.ic_rhs(
            img.to(device="cpu").kernel_args(), 3, p.cpu(), cc["px"], cc["py"], cc["dx"],
            cc["dy"], cc["basis"], cc["dt"], cc["fidx"], cc["ft"], cc["fnorm"], cc["gx"],
            cc["gy"], cc["w"], img.width, img.height, k, has_time, True,
            rows=None if pick is None else pick.cpu(), frame_rhs=want, motion=motion.cpu())
        assert bool(torch.isfinite(got).all())
        assert torch.allclose(got.cpu(), want, rtol=1e-9, atol=1e-9)
        assert torch.allclose(b.cpu(), b_nat, rtol=1e-9, atol=1e-9)
        assert torch.allclose(got[..., :ks].sum(1), b[:, :ks], rtol=1e-9, atol=1e-9)
        assert torch.allclose(got[..., 2 * ks].mean(1), zn, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("znssd", [True, False])
def test_fused_step_frame_rhs_matches_the_native_kernel(device, znssd):
    """frame_rhs: each frame's own spatial right-hand side and ZNCC, as the native kernel
    writes them (the model check's free classical step on CUDA), also for picked rows; and
    refused where the Triton kernel does not serve the call."""
    if not native.available():
        pytest.skip("the native kernel is the reference here")
    img, k, c = _case(True, torch.float64, device=device)
    n, t = c["dt"].shape
    ks = c["basis"].shape[1]
    kernels.set_triton("1")
    rows = torch.tensor([4, 0, 2], device=device)
    for pick in (None, rows):
        p = c["p"] if pick is None else c["p"][pick]
        got = torch.full((p.shape[0], t, 2 * ks + 1), float("nan"), dtype=torch.float64,
                         device=device)
        b, zn, _ = kernels.ic_rhs(img.kernel_args(), 3, p, c["px"], c["py"], c["dx"], c["dy"],
                                  c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"],
                                  c["gy"], c["w"], img.width, img.height, k, True, znssd,
                                  rows=pick, frame_rhs=got)
        want = torch.full_like(got, float("nan")).cpu()
        cc = {key: v.cpu() for key, v in c.items()}
        native.ic_rhs(img.to(device="cpu").kernel_args(), 3, p.cpu(), cc["px"], cc["py"],
                      cc["dx"], cc["dy"], cc["basis"], cc["dt"], cc["fidx"], cc["ft"],
                      cc["fnorm"], cc["gx"], cc["gy"], cc["w"], img.width, img.height, k, True,
                      znssd, rows=None if pick is None else pick.cpu(), frame_rhs=want)
        assert bool(torch.isfinite(got).all())
        assert torch.allclose(got.cpu(), want, rtol=1e-9, atol=1e-9)
        assert torch.allclose(got[..., : ks].sum(1), b[:, :ks], rtol=1e-9, atol=1e-9)
        assert torch.allclose(got[..., 2 * ks].mean(1), zn, rtol=1e-9, atol=1e-9)
    kernels.set_triton("0")
    with pytest.raises(ValueError, match="frame_rhs needs the Triton kernel"):
        kernels.ic_rhs(img.kernel_args(), 3, c["p"], c["px"], c["py"], c["dx"], c["dy"],
                       c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"],
                       c["w"], img.width, img.height, k, True, znssd, frame_rhs=got)


@pytest.mark.skipif(not INTERPRET, reason="CPU check through Triton's interpreter")
def test_fused_step_flags_outside_and_uses_every_frame():
    img, k, c = _case(True, torch.float64)
    c["px"][2] = 3.0  # the 9x9 subset (half 4) leaves the image
    kernels.set_triton("1")
    b, zn, out = _rhs(img, k, c, True, True)
    assert out[2] and int(out.sum()) == 1
    # a frame's coefficients changed: the right-hand side changes (every frame is read)
    img2 = BSplineImage.__new__(BSplineImage)
    img2.__dict__.update(img.__dict__)
    img2.coeffs = img.coeffs.clone()
    img2.coeffs[1] += torch.rand_like(img2.coeffs[1])
    img2._flat = img2.coeffs.reshape(-1)
    b2, _, _ = _rhs(img2, k, c, True, True)
    uses_1 = (c["fidx"] == img.kernel_args()[-1]).any(1)
    assert ((b2 - b).abs().amax(1) > 1e-9).eq(uses_1).all()


def test_selection():
    img, k, c = _case(True, torch.float32)
    flat = img.kernel_args()[0]
    kernels.set_triton("auto")
    assert not kernels.usable(flat, 3, 81, c["p"])  # CPU tensors: the CPU paths serve
    kernels.set_triton("1")
    assert kernels.usable(flat, 3, 81, c["p"]) == INTERPRET
    assert not kernels.usable(flat, 5, 81, c["p"])  # quintic: torch code
    assert not kernels.usable(flat.half(), 3, 81)
    assert not kernels.usable(flat, 3, 10**6)  # subset too large for one program
    kernels.set_triton("0")
    assert not kernels.usable(flat, 3, 81, c["p"])
    with pytest.raises(ValueError, match="triton mode"):
        kernels.set_triton("sometimes")


def test_op_is_a_torch_operator():
    """Registered with torch.library: the op checks out under torch's own op tests (schema,
    fake implementation) and runs the torch code where the kernel is not selected."""
    img, k, c = _case(True, torch.float64, n=3)
    kernels.set_triton("0")
    a = img.kernel_args()
    args = (a[0], c["p"], c["px"].reshape(-1), c["py"].reshape(-1), c["dx"], c["dy"],
            c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"], c["w"],
            None, a[1], a[2], a[3], a[4], a[5], a[6], img.width, img.height, k, True, True, 3)
    torch.library.opcheck(torch.ops.torch_stsdic.ic_rhs.default, args,
                          test_utils=("test_schema", "test_faketensor"))


@pytest.mark.skipif(not INTERPRET, reason="CPU check through Triton's interpreter")
def test_solver_with_fused_step_matches_torch_code(monkeypatch):
    """A whole STS(3) solve with the Triton step (interpreted) equals the torch code's (the
    batched loop, one step of all points at a time: TORCH_STSDIC_PER_POINT=0; the whole-stage
    solver is tests/test_triton_solve.py's)."""
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "0")
    mv = synth.synthetic_movie((48, 48), 3, synth.Translation(ut=0.2, vt=-0.1), seed=2)
    mod = fused_step.triton_module()
    launches = []

    def counted(*args, _fn=mod.ic_rhs_triton, **kw):
        launches.append(args[1].shape[0])
        return _fn(*args, **kw)

    monkeypatch.setattr(mod, "ic_rhs_triton", counted)
    cfg = sts.DICConfig(subset_size=11, m=1, dtype="float64")
    pts = torch.tensor([[20.0, 20.0], [27.0, 24.0]], dtype=torch.float64)
    native.set_native("0")
    kernels.set_triton("0")
    want = sts.solve_window(mv.ref, mv.frames, pts, cfg, times=mv.times)
    kernels.set_triton("1")
    assert not launches
    got = sts.solve_window(mv.ref, mv.frames, pts, cfg, times=mv.times)
    assert launches and launches[0] == 2  # the solver's steps went through the kernel
    assert torch.equal(got.status, want.status)
    assert torch.allclose(got.params, want.params, atol=1e-8)
    assert (want.u - 0.4).abs().max() < 0.02  # and the solve is right (u at t = 2)


@pytest.mark.skipif(not INTERPRET, reason="CPU check through Triton's interpreter")
@pytest.mark.parametrize("m", [1, 0])
def test_solver_with_shared_motion_through_the_fused_step(monkeypatch, m):
    """A whole solve with the shared motion (STS(m) and classical) through the Triton step
    (interpreted) equals the torch code's; the dispatcher picks Triton with the motion (the
    batched loop's step: TORCH_STSDIC_PER_POINT=0)."""
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "0")
    mv = synth.synthetic_movie((48, 48), 2 * m + 1, synth.Translation(ut=0.2, vt=-0.1), seed=2)
    mod = fused_step.triton_module()
    launches = []

    def counted(*args, _fn=mod.ic_rhs_triton, **kw):
        launches.append(kw.get("motion") is not None)
        return _fn(*args, **kw)

    monkeypatch.setattr(mod, "ic_rhs_triton", counted)
    g = torch.tensor([[0.3, -0.2], [-0.25, 0.15], [0.1, 0.35]], dtype=torch.float64)
    g = g[: 2 * m + 1]
    frames, times = (mv.frames, mv.times) if m else (mv.frames[0], None)
    cfg = sts.DICConfig(subset_size=11, m=m, dtype="float64")
    pts = torch.tensor([[20.0, 20.0], [27.0, 24.0]], dtype=torch.float64)
    kw = dict(shared_motion=g, times=times)
    native.set_native("0")
    kernels.set_triton("0")
    want = sts.solve_window(mv.ref, frames, pts, cfg, **kw)
    kernels.set_triton("1")
    assert not launches
    img = BSplineImage(mv.frames.double(), 3)
    p = torch.zeros(2, 8, dtype=torch.float64)
    ft = torch.zeros(2, 121, dtype=torch.float64)
    assert dispatch.ic_step(img.kernel_args(), 3, p, ft, ft, ft) == "triton"
    got = sts.solve_window(mv.ref, frames, pts, cfg, **kw)
    assert launches and all(launches)  # every step went through the kernel, with the motion
    assert torch.equal(got.status, want.status)
    assert torch.allclose(got.params, want.params, atol=1e-8)
    assert torch.allclose(got.zncc, want.zncc, atol=1e-9)


@pytest.mark.parametrize("device", _devices())
def test_classical_step_through_the_fused_step(device):
    """The model check's free classical step and its estimates (classical_step*) from the
    Triton step (interpreted on the CPU, or on CUDA) equal the native kernel's: the check
    judges rows on CUDA as on the CPU."""
    if not native.available():
        pytest.skip("the native kernel is the reference here")
    mv = synth.synthetic_movie((64, 64), 5, synth.Translation(ut=0.2, vt=-0.1), seed=3,
                               noise_sigma=2.0)
    solver = sts.SubsetSolver(sts.DICConfig(subset_size=11, m=2, dtype="float64"))
    ref, frames = mv.ref.double(), mv.frames.double()
    pts = torch.tensor([[24.0, 24.0], [30.0, 28.0], [36.0, 33.0]], dtype=torch.float64)
    dt = torch.arange(-2.0, 3.0, dtype=torch.float64)

    def solve(dev):
        r, f = ref.to(dev), frames.to(dev)
        return solver.solve(solver.prepare(r), solver.prepare(f), pts.to(dev), dt.to(dev),
                            ref_pixels=r.unsqueeze(0), frame_pixels=f, classical_step=True)
    want = solve("cpu")  # the native kernel
    native.set_native("0")
    kernels.set_triton("1")
    got = solve(device)
    got.info = {key: v.cpu() if isinstance(v, torch.Tensor) else v
                for key, v in got.info.items()}
    keys = ("classical_step", "classical_step_size", "classical_step_zncc",
            "classical_step_sigma", "classical_step_std")
    for key in keys:
        assert bool(torch.isfinite(want.info[key]).all()), key
        assert torch.allclose(got.info[key], want.info[key], rtol=1e-7, atol=1e-9), key


def test_eager_launch_does_not_import_the_compiler_stack():
    """Outside torch.compile the step is called directly, not through the torch.library op:
    launching a Triton kernel inside the op makes torch import torch._dynamo (with sympy and
    FSDP: seconds of every fresh process's first GPU run). A fresh interpreter: the kernel
    (Triton's interpreter without a GPU) runs, and torch._dynamo is not imported."""
    import subprocess
    import sys
    from pathlib import Path

    if not (INTERPRET or torch.cuda.is_available()):
        pytest.skip("no CUDA and TRITON_INTERPRET is not 1")
    dev = "cuda" if torch.cuda.is_available() and not INTERPRET else "cpu"
    code = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
import torch
from torch_stsdic import kernels
from test_triton import _case, _rhs
kernels.set_triton("1")
img, k, c = _case(True, torch.float32, device={dev!r})
b, zn, out = _rhs(img, k, c, True, True)
assert b.shape == (6, 2 * k) and bool(torch.isfinite(b).all()), b
print("dynamo" if "torch._dynamo" in sys.modules else "no dynamo")
"""
    env = dict(os.environ, TRITON_INTERPRET="1" if dev == "cpu" else "0")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().endswith("no dynamo"), r.stdout


def test_auto_compile_policy_is_for_cpu_jobs_only(monkeypatch):
    """"auto" compiles large CPU jobs (unchanged: with the device, a CPU tensor or none
    given); a CUDA job never ("1" still forces it). The policy alone: no GPU needed, and
    nothing is compiled (maybe_compiled hands back the function itself)."""
    from torch_stsdic.kernels import compile as kc

    big, small = kc._COMPILE_MIN, kc._COMPILE_MIN - 1
    cpu_t = torch.zeros(1)
    cuda = torch.device("cuda")
    try:
        kc.set_compile("auto")
        for dev in (None, "cpu", torch.device("cpu"), cpu_t):
            assert kc.compile_wanted(big, dev) and not kc.compile_wanted(small, dev)
        for dev in ("cuda", "cuda:0", cuda):
            assert not kc.compile_wanted(big, dev) and not kc.compile_wanted(10**12, dev)

        def fn(x):
            return x

        # a CUDA job in auto mode: the function itself, also where a compiled one exists
        monkeypatch.setitem(kc._COMPILED, ("policy-test",), "compiled")
        assert kc.maybe_compiled(fn, ("policy-test",), 10**12, device=cuda) is fn
        assert kc.maybe_compiled(fn, ("policy-test",), kc._COMPILED_MIN, device="cuda") is fn
        # a CPU job: the compiled one once it exists (for >= _COMPILED_MIN), as before
        assert kc.maybe_compiled(fn, ("policy-test",), kc._COMPILED_MIN, device="cpu") \
            == "compiled"
        assert kc.maybe_compiled(fn, ("policy-test",), kc._COMPILED_MIN) == "compiled"
        assert kc.maybe_compiled(fn, ("policy-test",), kc._COMPILED_MIN - 1) is fn
        kc.set_compile("1")
        assert kc.compile_wanted(1, cuda) and kc.compile_wanted(1, "cpu")
        assert kc.maybe_compiled(fn, ("policy-test",), 1, device=cuda) == "compiled"
        kc.set_compile("0")
        assert not kc.compile_wanted(big, "cpu")
        assert kc.maybe_compiled(fn, ("policy-test",), 10**12, device="cpu") is fn
    finally:
        kc.set_compile("auto")
