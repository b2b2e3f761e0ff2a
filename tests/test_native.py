"""Fused C++ CPU kernels (torch_stsdic.native) against the torch code they replace."""

import os
import subprocess
import sys
import textwrap

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import native, synth
from torch_stsdic.formulations import ic_rhs_kernel
from torch_stsdic.interpolation import BSplineImage, sample_kernel

pytestmark = pytest.mark.skipif(not native.available(),
                                reason="fused CPU kernels did not build (no C++ compiler?)")


@pytest.fixture(autouse=True)
def _restore_mode():
    yield
    native.set_native("auto")


def _image(dtype, order, frames=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return BSplineImage(torch.rand(frames, 48, 64, generator=g, dtype=dtype) * 255, order)


@pytest.mark.parametrize("order", [3, 5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_matches_torch(order, dtype):
    img = _image(dtype, order)
    a = img.kernel_args()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(40, 25, generator=g, dtype=dtype) * 74 - 5  # also outside: clamped alike
    y = torch.rand(40, 25, generator=g, dtype=dtype) * 58 - 5
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    for off in (torch.randint(0, 3, (40, 1), generator=g) * a[-1],  # per row
                torch.tensor(2 * a[-1]),  # one plane
                torch.randint(0, 3, (40, 25), generator=g) * a[-1]):  # per sample
        ref = sample_kernel(a[0], x, y, off, *a[1:7], order, True)
        got = native.sample(a, order, x, y, off, True)
        for r, n_ in zip(ref, got):
            assert n_.shape == r.shape
            assert (n_ - r).abs().max() <= tol * max(1.0, float(r.abs().max()) / 255)
        val = native.sample(a, order, x, y, off, False)
        assert torch.allclose(val, got[0], rtol=1e-5, atol=tol)


@pytest.mark.parametrize("order", [3, 5])
def test_subsets_match_points(order):
    img = _image(torch.float64, order)
    px = torch.tensor([12.0, 30.5, 40.25])
    py = torch.tensor([14.0, 20.0, 33.75])
    d = torch.arange(-3.0, 4.0, dtype=torch.float64)
    dx, dy = d.repeat(7), d.repeat_interleave(7)
    frame = torch.tensor([0, 2, 1])
    v, gx, gy = img.sample_subsets(px, py, dx, dy, frame=frame)
    a = img.kernel_args()
    r = sample_kernel(a[0], px.double().view(-1, 1) + dx, py.double().view(-1, 1) + dy,
                       frame.view(-1, 1) * a[-1], *a[1:7], order, True)
    for got, want in zip((v, gx, gy), r):
        assert torch.allclose(got, want, atol=1e-9)


def _rhs_case(has_time, dtype=torch.float64, n=7, t=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    img = _image(dtype, 3, frames=t, seed=seed)
    shape = sts.shape.AffineShape(temporal=has_time)
    d = torch.arange(-4.0, 5.0, dtype=dtype)
    dx, dy = d.repeat(9), d.repeat_interleave(9)
    basis = shape.spatial_basis(dx, dy)
    k = shape.n_basis
    p = torch.randn(n, 2 * k, generator=g, dtype=dtype) * 0.05
    p[:, 0] += 0.7
    px = torch.rand(n, 1, generator=g, dtype=dtype) * 30 + 15
    py = torch.rand(n, 1, generator=g, dtype=dtype) * 20 + 14
    dt = (torch.arange(t, dtype=dtype) - t // 2).expand(n, t).contiguous()
    fidx = torch.randint(0, t, (n, t), generator=g) * img.kernel_args()[-1]
    ft = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    ft = ft - ft.mean(1, keepdim=True)
    fnorm = ft.norm(dim=1)
    gx = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    gy = torch.randn(n, dx.numel(), generator=g, dtype=dtype)
    w = torch.rand(dx.numel(), generator=g, dtype=dtype) + 0.5
    return img, shape, dict(p=p, px=px, py=py, dx=dx, dy=dy, basis=basis, dt=dt, fidx=fidx,
                            ft=ft, fnorm=fnorm, gx=gx, gy=gy, w=w, k=k)


@pytest.mark.parametrize("has_time", [False, True])
@pytest.mark.parametrize("znssd", [True, False])
def test_ic_rhs_matches_torch(has_time, znssd):
    img, shape, c = _rhs_case(has_time)
    a = img.kernel_args()
    ks = c["basis"].shape[1]
    want_b, want_zn, want_out = ic_rhs_kernel(
        a[0], c["p"], c["px"], c["py"], c["dx"], c["dy"], c["basis"].T.contiguous(), c["dt"],
        c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"], c["w"], *a[1:7], 64, 48, ks,
        c["k"], has_time, znssd, 3)
    b, zn, out = native.ic_rhs(a, 3, c["p"], c["px"], c["py"], c["dx"], c["dy"], c["basis"],
                               c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"],
                               c["w"], 64, 48, c["k"], has_time, znssd)
    assert torch.allclose(b, want_b.double(), rtol=1e-9, atol=1e-7)
    assert torch.allclose(zn, want_zn, atol=1e-12)
    assert torch.equal(out, want_out)
    # a subset of the rows through `rows`: the same numbers for those rows
    rows = torch.tensor([5, 1, 3])
    b2, zn2, _ = native.ic_rhs(a, 3, c["p"][rows], c["px"], c["py"], c["dx"], c["dy"],
                               c["basis"], c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"],
                               c["gy"], c["w"], 64, 48, c["k"], has_time, znssd, rows=rows)
    assert torch.allclose(b2, b[rows], rtol=1e-12, atol=1e-12)
    assert torch.allclose(zn2, zn[rows])


def test_ic_rhs_flags_outside():
    img, shape, c = _rhs_case(False)
    c["px"][2] = 3.0  # subset half-width 4: leaves the image
    a = img.kernel_args()
    _, _, out = native.ic_rhs(a, 3, c["p"], c["px"], c["py"], c["dx"], c["dy"], c["basis"],
                              c["dt"], c["fidx"], c["ft"], c["fnorm"], c["gx"], c["gy"],
                              c["w"], 64, 48, c["k"], False, True)
    assert out[2] and out.sum() == 1


def test_gram_matches_torch():
    from torch_stsdic.formulations import gram

    img, shape, c = _rhs_case(True, n=5)
    g_nat, m_nat = gram(c["gx"], c["gy"], c["basis"], c["w"])
    native.set_native(False)
    g_t, m_t = gram(c["gx"], c["gy"], c["basis"], c["w"])
    assert torch.allclose(g_nat, g_t, rtol=1e-12, atol=1e-9)
    assert torch.allclose(m_nat, m_t, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("m", [0, 1])
def test_solver_same_with_and_without_native(m):
    pattern = synth.make_speckle((96, 96), seed=5)
    motion = synth.HomogeneousStrain(exx=0.01, eyy=-0.004, exy=0.003, center=(48, 48)) + \
        synth.Translation(0.4, -0.3, ut=0.05, vt=0.02)
    times = torch.arange(0.0, 2 * m + 1, dtype=torch.float64)
    ref, frames = synth.render_series(pattern, (96, 96), motion, times, noise_sigma=1.0,
                                      seed=3, reference_time=None)
    c = torch.arange(30.0, 67.0, 6.0, dtype=torch.float64)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    pts = torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)
    cfg = sts.DICConfig(m=m, dtype="float64", initial_guess="fft")
    fr = frames if m else frames[0]
    a = sts.solve_window(ref, fr, pts, config=cfg)
    native.set_native(False)
    b = sts.solve_window(ref, fr, pts, config=cfg)
    assert torch.equal(a.status, b.status)
    assert torch.allclose(a.params, b.params, atol=1e-7)
    assert torch.allclose(a.zncc, b.zncc, atol=1e-9)


def test_set_native_rejects_unknown_mode():
    with pytest.raises(ValueError, match="native mode"):
        native.set_native("sometimes")


def test_no_compiler_falls_back_with_one_warning(tmp_path):
    code = textwrap.dedent("""
        import warnings, torch
        import torch_stsdic as sts
        warnings.simplefilter("always")
        with warnings.catch_warnings(record=True) as w:
            img = torch.rand(40, 40) * 255
            sol = sts.solve_window(img, img, [[20.0, 20.0]], config=sts.DICConfig(m=0))
            sol = sts.solve_window(img, img, [[20.0, 21.0]], config=sts.DICConfig(m=0))
        msgs = [str(x.message) for x in w if "fused CPU kernels" in str(x.message)]
        print(len(msgs), bool(sol.ok.all()), float(sol.u.abs().max()) < 1e-3)
    """)
    env = {**os.environ, "CXX": "/nonexistent/c++", "TORCH_STSDIC_CACHE": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "True", "True"]


def test_kernels_work_in_a_forked_child():
    """A child forked after the worker threads exist (e.g. a DataLoader worker) must not
    wait for threads that did not survive the fork."""
    import multiprocessing as mp

    torch.set_num_threads(2)
    try:
        img = _image(torch.float32, 3)
        a = img.kernel_args()
        x = torch.rand(200, 441) * 40 + 5
        y = torch.rand(200, 441) * 30 + 5
        off = torch.zeros(200, 1, dtype=torch.long)
        want = native.sample(a, 3, x, y, off, False)  # starts the worker threads
        ctx = mp.get_context("fork")
        with ctx.Pool(1) as pool:
            got = pool.apply_async(_sample_in_child, (img.coeffs, a, x, y, off)).get(timeout=30)
        assert torch.allclose(torch.from_numpy(got), want)
    finally:
        torch.set_num_threads(1)


def _sample_in_child(coeffs, a, x, y, off):
    # no torch op with intra-op threads here: GNU OpenMP itself is not fork-safe
    assert torch.get_num_threads() == 2  # inherited: the kernels split over 2 threads
    val = native.sample((coeffs.reshape(-1), *a[1:]), 3, x, y, off, False)
    return val.numpy()  # numpy: torch's shared-memory tensor transfer is not needed here


def test_portable_build_matches_torch(tmp_path):
    """The scalar code path (no AVX2: what other CPUs run) built and checked in float32."""
    code = textwrap.dedent("""
        import torch
        from torch_stsdic import native
        from torch_stsdic.interpolation import BSplineImage, sample_kernel
        from torch_stsdic.formulations import ic_rhs_kernel
        from torch_stsdic.shape import AffineShape
        g = torch.Generator().manual_seed(0)
        img = BSplineImage(torch.rand(2, 40, 50, generator=g) * 255, 3)
        a = img.kernel_args()
        x = torch.rand(30, 49, generator=g) * 40 + 3
        y = torch.rand(30, 49, generator=g) * 30 + 3
        off = torch.randint(0, 2, (30, 1), generator=g) * a[-1]
        e1 = max(float((p - q).abs().max()) for p, q in zip(
            native.sample(a, 3, x, y, off, True), sample_kernel(a[0], x, y, off, *a[1:7], 3,
                                                                 True)))
        d = torch.arange(-3.0, 4.0)
        dx, dy = d.repeat(7), d.repeat_interleave(7)
        basis = AffineShape(temporal=False).spatial_basis(dx, dy)
        p = torch.randn(30, 6, generator=g) * 0.02
        px, py = x[:, :1] + 2, y[:, :1] + 2
        dt = torch.zeros(30, 1)
        ft = torch.randn(30, 49, generator=g)
        ft = ft - ft.mean(1, keepdim=True)
        args = (p, px, py, dx, dy)
        b, zn, _ = native.ic_rhs(a, 3, *args, basis, dt, off, ft, ft.norm(dim=1), ft, -ft,
                                 torch.ones(49), 50, 40, 3, False, True)
        bt, znt, _ = ic_rhs_kernel(a[0], *args, basis.T.contiguous(), dt, off, ft,
                                    ft.norm(dim=1), ft, -ft, torch.ones(49), *a[1:7], 50, 40,
                                    3, 3, False, True, 3)
        e2 = float(((b - bt.double()).abs() / (1 + bt.double().abs())).max())
        print(e1, e2, float((zn - znt).abs().max()))
    """)
    env = {**os.environ, "TORCH_STSDIC_NATIVE_MARCH": "", "TORCH_STSDIC_CACHE": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    e_sample, e_rhs, e_zn = map(float, out.stdout.split())
    assert e_sample < 1e-3 and e_rhs < 1e-3 and e_zn < 1e-5
    assert len(list(tmp_path.glob("dic_kernels-*"))) == 1  # built into the given cache


@pytest.mark.parametrize("order", [3, 5])
@pytest.mark.parametrize("shape", [(3, 40, 50), (2, 7), (5, 3), (1, 9), (9, 1), (1, 1), (30, 200)])
def test_prefilter_matches_fft(order, shape):
    from torch_stsdic.interpolation import _prefilter_axis

    g = torch.Generator().manual_seed(2)
    x = torch.rand(*shape, generator=g, dtype=torch.float64) * 255
    want = _prefilter_axis(_prefilter_axis(x, order, x.dim() - 1), order, x.dim() - 2)
    got = native.prefilter(x, order)
    assert got.shape == x.shape and got.dtype == x.dtype
    assert (got - want).abs().max() < 1e-8
    assert torch.equal(x, x.clone())  # input untouched
    got32 = native.prefilter(x.float(), order)
    assert (got32.double() - want).abs().max() < 1e-5 * (1 + float(want.abs().max()))
    # the spline through the coefficients interpolates the pixels
    if min(shape[-2:]) >= 8:  # (smaller images have too few pixels for the tap margin)
        img = BSplineImage(x.reshape(-1, *shape[-2:]), order)
        yy, xx = torch.meshgrid(torch.arange(shape[-2]).double(),
                                torch.arange(shape[-1]).double(), indexing="ij")
        vals = img.sample(xx, yy, frame=0)
        assert torch.allclose(vals, x.reshape(-1, *shape[-2:])[0], atol=1e-8)


def test_read_only_cache_falls_back_to_temp(tmp_path, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    monkeypatch.setenv("TORCH_STSDIC_CACHE", str(ro / "cache"))
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    try:
        if os.access(ro, os.W_OK):  # root ignores the mode bits
            monkeypatch.setattr(os, "access", lambda p, m: not str(p).startswith(str(ro)))
        path = native.build()
        assert str(path).startswith(str(tmp_path / "tmp")) and path.exists()
    finally:
        ro.chmod(0o700)
