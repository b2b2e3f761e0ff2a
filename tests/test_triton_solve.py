"""The whole-stage Triton solver (``kernels.triton_solve``: every point iterated to its end in
one launch) against the C++ per-point solver (``native.ic_solve``) on the same inputs, and
through the solver's dispatch against the batched loop: the same statuses and iteration counts,
parameters and ZNCC equal to float rounding. On CPU tensors through Triton's interpreter
(TRITON_INTERPRET=1, small sizes); on CUDA where there is a GPU."""

from __future__ import annotations

import os

import pytest
import torch

if not torch.cuda.is_available():  # no GPU: Triton's interpreter, before Triton is imported
    os.environ.setdefault("TRITON_INTERPRET", "1")

from test_native_solve import _movie as native_movie  # tests/ on the path

import torch_stsdic as sts
from torch_stsdic import kernels
from torch_stsdic.core import point_solve
from torch_stsdic.kernels import dispatch, fused_step, native

pytestmark = pytest.mark.skipif(not kernels.available(),
                                reason="triton is not importable (pip install triton)")
INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
DEVICE = "cpu" if INTERPRET else "cuda"
needs_device = pytest.mark.skipif(not (INTERPRET or torch.cuda.is_available()),
                                  reason="no CUDA and TRITON_INTERPRET is not 1")


@pytest.fixture(autouse=True)
def _modes(monkeypatch):
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "1")
    yield
    kernels.set_triton("auto")
    native.set_native("auto")


def _movie(m: int, n: int = 44, every: int = 12):
    """:func:`test_native_solve._movie` at the interpreter's size: 44 px, a coarser grid."""
    return native_movie(m, n, 8.0, float(every), ((5.2, 20.0), (5.6, 24.0)))


def _native_calls(m, dtype, criterion, shared=False, **cfg):
    """The arguments of every ``native.ic_solve`` call of a solve_window on the CPU."""
    if not native.available():
        pytest.skip("the C++ kernel is the reference here")
    ref, frames, pts, times = _movie(m)
    config = sts.DICConfig(m=m, dtype=dtype, criterion=criterion, subset_size=11, **cfg)
    kw = {"shared_motion": torch.stack([0.1 * times, -0.05 * times], 1)} if shared else {}
    calls, real = [], native.ic_solve

    def spy(*a, **k):
        calls.append((a, k))
        return real(*a, **k)

    native.ic_solve = spy
    try:
        sts.solve_window(ref, frames, pts, config=config, **kw)
    finally:
        native.ic_solve = real
    assert calls
    return calls


def _to(x, device):
    if isinstance(x, torch.Tensor):
        return x.to(device)
    if isinstance(x, tuple):
        return tuple(_to(v, device) for v in x)
    return x


def _triton(a, k, **extra):
    """The captured native call's arguments through the Triton solver on DEVICE."""
    kernels.set_triton("1")
    a = _to(tuple(a), DEVICE)
    k = {key: _to(v, DEVICE) for key, v in {**k, **extra}.items()}
    return fused_step.ic_solve(*a, **k)


def _assert_same(want, got, atol, rhs_rtol=1e-9):
    """Same statuses and iterations; parameters and ZNCC within ``atol``; the last step's
    parameters within ``atol`` and its frame-by-frame right-hand sides within ``rhs_rtol`` of
    their largest (a residual at noise level: float32 rounding of the samples shows there)."""
    p1, z1, s1, i1, l1 = want
    p2, z2, s2, i2, l2 = (_to(v, "cpu") for v in got)
    assert torch.equal(s1, s2)
    assert torch.equal(i1, i2)
    ok = s1 <= int(sts.Status.MAX_ITER)
    assert ok.float().mean() > 0.8
    torch.testing.assert_close(p2[ok], p1[ok], rtol=0, atol=atol)
    torch.testing.assert_close(z2[ok], z1[ok], rtol=0, atol=atol)
    if l1 is not None:
        for a, b in zip(l1, l2):
            assert torch.equal(torch.isnan(a), torch.isnan(b))
        (pa, ba), (pb, bb) = ((x.nan_to_num() for x in last) for last in (l1, l2))
        torch.testing.assert_close(pb, pa, rtol=0, atol=atol)
        rhs_tol = rhs_rtol * float(ba[..., :6].abs().max())
        torch.testing.assert_close(bb[..., :6], ba[..., :6], rtol=0, atol=rhs_tol)
        torch.testing.assert_close(bb[..., 6], ba[..., 6], rtol=0, atol=atol)  # ZNCC


@needs_device
@pytest.mark.parametrize("m,dtype,criterion,atol", [
    (0, "float32", "znssd", 1e-5),   # classical
    (2, "float32", "znssd", 1e-5),   # STS(2)
    (2, "float64", "znssd", 1e-11),
    (1, "float32", "ssd", 1e-5),
])
def test_triton_solve_equals_the_native_solve(m, dtype, criterion, atol):
    """The last stage of a solve_window (classical, STS), the C++ kernel's inputs replayed
    through the Triton solver: the same statuses and iterations, parameters, ZNCC, the last
    step's parameters and frame-by-frame right-hand sides equal to float rounding."""
    a, k = _native_calls(m, dtype, criterion)[-1]
    k = {**k, "frame_rhs": True}
    want = native.ic_solve(*a, **k)
    _assert_same(want, _triton(a, k), atol, 1e-9 if dtype == "float64" else 2e-2)
    assert (want[2] == int(sts.Status.OUTSIDE)).any()  # the moved edge points


@needs_device
def test_triton_solve_shared_motion_max_iter_and_ref_rows():
    """The shared motion carried in every warp; max_iter (the last iterate, NaN last step);
    reference subsets read through ``ref_rows`` (shuffled rows: the same numbers as without);
    the previous increments of the convergence rate."""
    calls = _native_calls(2, "float64", "znssd", shared=True)
    a, k = calls[-1]
    assert k.get("motion") is not None
    a2 = list(a)
    a2[24] = 3  # max_iter
    k2 = {**k, "frame_rhs": True}
    want = native.ic_solve(*a2, **k2)
    assert (want[2] == int(sts.Status.MAX_ITER)).any()
    assert (want[2] == int(sts.Status.CONVERGED)).any()
    got = _triton(a2, k2)
    _assert_same(want, got, 1e-11)
    # the same problem with the reference subsets stored in another order
    n = a[10].shape[0]
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    a3 = list(a2)
    for j in (10, 12, 13):  # ft, gx, gy
        a3[j] = torch.empty_like(a2[j])
        a3[j][perm] = a2[j]
    got3 = _triton(a3, k2, ref_rows=perm)
    for x, y in zip(got[:4], got3[:4]):
        assert torch.equal(x.nan_to_num(), y.nan_to_num())
    # a start 1e-3 px from the solution with a previous increment given (a step before it):
    # the convergence rate's first ratio uses it (converged one step earlier than without)
    a4 = list(a)
    a4[2] = native.ic_solve(*a, **k)[0].clone()
    a4[2][:, [0, a[17]]] += 1e-3  # u, v
    a4[22] = torch.zeros_like(a[22])
    without = native.ic_solve(*a4, **k)
    a4[22] = torch.full_like(a[22], 0.5)
    want4 = native.ic_solve(*a4, **k)
    assert (want4[3] < without[3]).any()  # the previous increment is used
    _assert_same(want4, _triton(a4, k), 1e-11)


@pytest.mark.skipif(not INTERPRET, reason="CPU check through Triton's interpreter")
def test_solver_dispatch_takes_the_triton_solve(monkeypatch):
    """A whole STS(1) solve_window with the C++ kernels off and Triton on: the stage runs
    through the Triton solver (one call per stage) and equals the batched loop with the
    torch step (TORCH_STSDIC_PER_POINT=0, Triton off): statuses, iterations, parameters."""
    ref, frames, pts, times = _movie(1)
    config = sts.DICConfig(m=1, dtype="float64", subset_size=11)
    calls, real = [], fused_step.ic_solve
    monkeypatch.setattr(fused_step, "ic_solve",
                        lambda *a, **k: calls.append(a[2].shape[0]) or real(*a, **k))
    native.set_native("0")
    kernels.set_triton("0")
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "0")
    want = sts.solve_window(ref, frames, pts, config=config)
    assert not calls
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "1")
    kernels.set_triton("1")
    got = sts.solve_window(ref, frames, pts, config=config)
    assert calls  # the stages went through the Triton solver
    assert torch.equal(got.status, want.status)
    assert torch.equal(got.iterations, want.iterations)
    ok = want.status <= int(sts.Status.MAX_ITER)
    assert ok.float().mean() > 0.8
    torch.testing.assert_close(got.params[ok], want.params[ok], rtol=0, atol=1e-9)
    torch.testing.assert_close(got.zncc[ok], want.zncc[ok], rtol=0, atol=1e-9)


def test_dispatch_rules(monkeypatch):
    img = sts.BSplineImage(torch.rand(1, 32, 32))
    ka = img.kernel_args()
    p = torch.zeros(4, 6)
    native.set_native("0")
    kernels.set_triton("1")
    want = "triton" if INTERPRET else "torch"  # CPU tensors: only under the interpreter
    assert dispatch.ic_solve(ka, p, p, 3, True, 3) == want
    assert point_solve.CODES == (0, 1, 2, 3)
    assert dispatch.ic_solve(ka, p, p, 3, True, 5) == "torch"  # quintic: batched loop
    assert dispatch.ic_solve(ka, p, p, 6, True, 3) == "torch"  # quadratic
    assert dispatch.ic_solve(ka, p.double(), p, 3, True, 3) == "torch"  # not the image's dtype
    assert dispatch.ic_solve(ka, p.requires_grad_(), p, 3, True, 3) == "torch"  # autograd
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "0")  # the switch back to the batched loop
    assert dispatch.ic_solve(ka, p.detach(), p, 3, True, 3) == "torch"
    monkeypatch.setenv("TORCH_STSDIC_PER_POINT", "1")
    kernels.set_triton("0")
    assert dispatch.ic_solve(ka, p.detach(), p, 3, True, 3) == "torch"
    with pytest.raises(ValueError, match="Triton solver does not serve"):
        fused_step.ic_solve(ka, 3, p, *([torch.zeros(4, 3)] * 12), 32, 32, 3, False, True,
                            None, None, None, 1e-4, 10, 10.0, 0.05, point_solve.CODES)


_COMPILE = r'''
import inspect
import re
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from torch_stsdic.kernels import triton_solve as ts

fn = ts._ic_solve_kernel
names = list(inspect.signature(fn.fn).parameters)
for dt, has_time, on in (("fp32", True, True), ("fp64", False, False)):
    kinds = {"foff_ptr": "*i64", "ref_ptr": "*i64", "hinv_ptr": "*fp64", "st_ptr": "*i8",
             "used_ptr": "*i32", "bf_ptr": "*fp64", "NT": "i32", "S": "i32", "wp": "i32",
             "shift": "i32", "max_iter": "i32", "w_img": "fp32", "h": "fp32"}
    sig = {n: kinds.get(n, "*" + dt if n.endswith("_ptr") else "constexpr") for n in names}
    c = dict(C_CONV=0, C_MAXIT=1, C_DIV=2, C_OUT=3, K=4 if has_time else 3, HAS_TIME=has_time,
             ZNSSD=on, HAS_REF=on, HAS_MOTION=on, FRAME_RHS=on, BLOCK_S=512)
    src = ASTSource(fn=fn, signature=sig,
                    constexprs={(names.index(k),): v for k, v in c.items()})
    k = triton.compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": 4})
    assert len(k.asm["cubin"]) > 1000
    # the values the Gauss-Newton loop carries (scf.while's results)
    carried = re.search(r":(\d+) = scf.while", k.asm["ttir"])
    print("compiled", dt, carried.group(1) if carried else "none")
'''


def test_kernel_compiles_for_a_gpu(tmp_path):
    """The solver compiles (Triton's frontend, LLVM, ptxas) for an sm_90 GPU, without one:
    the interpreter runs Python, so a construct only the compiler rejects (a loop-carried
    variable that changes type, say) shows here, not only on the next GPU run."""
    import importlib.util
    import subprocess
    import sys

    if importlib.util.find_spec("triton.backends.nvidia") is None:
        pytest.skip("this Triton has no NVIDIA backend")
    env = {key: v for key, v in os.environ.items() if key != "TRITON_INTERPRET"}
    env.update(TRITON_CACHE_DIR=str(tmp_path), TRITON_DEFAULT_FP_FUSION="1")
    r = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout.split()
    assert out[0::3] == ["compiled", "compiled"] and out[1::3] == ["fp32", "fp64"], out
    # the loop carries the parameters (P), the last step's (P, kept with FRAME_RHS alone), the
    # previous increment, the ZNCC, the status and the iteration count: fp32 has time (P = 8)
    # and FRAME_RHS, fp64 neither (P = 6, last step dropped as unused). Fails where the last
    # step's parameters are set from the parameters before the loop (``ou0 = pu0``): the
    # compiler then does not carry them and returns the starting parameters as the last step's
    # on a GPU (what the first H200 run of this solver showed), while the interpreter is right.
    assert [int(n) for n in out[2::3]] == [2 * 8 + 4, 6 + 4], out


@needs_device
def test_rows_with_a_zero_inverse_hessian_stop_where_they_start():
    """``point_solve`` gives the rows it does not iterate (no texture, a singular Hessian) a
    zero inverse Hessian rather than leaving them out (no index of the rows, no host read):
    such a row takes one zero step and stops where it started, in the C++ solver and in the
    Triton solver alike, and the other rows are unchanged by it."""
    a, k = _native_calls(2, "float32", "znssd")[-1]
    a = list(a)
    base = native.ic_solve(*a, **k)
    dead = torch.zeros(a[2].shape[0], dtype=torch.bool)
    dead[::3] = True
    a[20] = torch.where(dead.view(-1, 1, 1), 0.0, a[20])
    want = native.ic_solve(*a, **k)
    inside = want[2] != int(sts.Status.OUTSIDE)
    assert bool((dead & inside).any())
    assert torch.equal(want[0][dead], a[2][dead].to(want[0].dtype))
    assert bool((want[3][dead & inside] == 1).all())
    assert bool((want[2][dead & inside] == int(sts.Status.CONVERGED)).all())
    for got, ref in zip(want[:4], base[:4]):
        assert torch.equal(got[~dead], ref[~dead])
    _assert_same(want, _triton(a, k), 1e-5)
