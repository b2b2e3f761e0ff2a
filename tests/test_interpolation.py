"""B-spline prefilter and sampling: exact interpolation, analytic gradients, polynomials."""

import pytest
import torch

from torch_stsdic.core.interpolation import BSplineImage, bspline_prefilter
from torch_stsdic.kernels import native
from torch_stsdic.kernels.compile import compile_failed


def _smooth(h=40, w=50, dtype=torch.float64):
    yy, xx = torch.meshgrid(
        torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij"
    )
    return torch.sin(0.3 * xx) * torch.cos(0.2 * yy) * 50 + 100, xx, yy


@pytest.mark.parametrize("order", [3, 5])
def test_interpolates_pixels_exactly(order):
    img, xx, yy = _smooth()
    b = BSplineImage(img, order)
    assert torch.allclose(b.sample(xx, yy), img, atol=1e-10)


@pytest.mark.parametrize("order", [3, 5])
def test_gradient_matches_finite_differences(order):
    img, _, _ = _smooth()
    b = BSplineImage(img, order)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(500, generator=g, dtype=torch.float64) * 40 + 3
    y = torch.rand(500, generator=g, dtype=torch.float64) * 30 + 3
    _, gx, gy = b.sample(x, y, grad=True)
    e = 1e-6
    fdx = (b.sample(x + e, y) - b.sample(x - e, y)) / (2 * e)
    fdy = (b.sample(x, y + e) - b.sample(x, y - e)) / (2 * e)
    assert torch.allclose(gx, fdx, atol=1e-6)
    assert torch.allclose(gy, fdy, atol=1e-6)


@pytest.mark.parametrize("order", [3, 5])
def test_reproduces_linear_ramps_inside(order):
    # B-splines reproduce polynomials up to their order away from the boundary
    h, w = 80, 80  # the mirror boundary bends the ramp; its effect decays inside
    yy, xx = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    img = 2.0 * xx - 0.5 * yy + 7.0
    b = BSplineImage(img, order)
    x = torch.tensor([40.25, 42.5, 35.75], dtype=torch.float64)
    y = torch.tensor([41.1, 33.9, 44.5], dtype=torch.float64)
    v, gx, gy = b.sample(x, y, grad=True)
    assert torch.allclose(v, 2.0 * x - 0.5 * y + 7.0, atol=1e-6)
    assert torch.allclose(gx, torch.full_like(gx, 2.0), atol=1e-6)
    assert torch.allclose(gy, torch.full_like(gy, -0.5), atol=1e-6)


def test_frames_are_independent_and_stackable():
    img, xx, yy = _smooth()
    b = BSplineImage(torch.stack([img, 2 * img, 3 * img]))
    f = torch.arange(3).view(3, 1, 1)
    v = b.sample(xx.expand(3, -1, -1), yy.expand(3, -1, -1), frame=f)
    assert torch.allclose(v, torch.stack([img, 2 * img, 3 * img]), atol=1e-9)
    s = BSplineImage.stack([b.frame(2), b.frame(0)])
    assert torch.allclose(s.sample(xx, yy, frame=1), img, atol=1e-9)


def test_float32_close_to_float64():
    img, _, _ = _smooth()
    b64 = BSplineImage(img)
    b32 = BSplineImage(img.float())
    x = torch.linspace(5, 40, 100, dtype=torch.float64)
    y = torch.linspace(5, 30, 100, dtype=torch.float64)
    assert torch.allclose(b32.sample(x.float(), y.float()).double(), b64.sample(x, y), atol=1e-3)


def test_prefilter_rejects_integers_and_bad_order():
    with pytest.raises(TypeError):
        bspline_prefilter(torch.zeros(5, 5, dtype=torch.int32))
    with pytest.raises(ValueError):
        BSplineImage(torch.zeros(5, 5), order=4)


def test_compiled_sampler_matches_eager():
    # the fused (torch.compile) kernel used for large calls gives the eager kernel's numbers
    from torch_stsdic.core import interpolation

    img, _, _ = _smooth()
    b = BSplineImage(torch.stack([img, img.flip(0)]).float())
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(7, 2, 30, generator=g) * 40 + 3).float()
    y = (torch.rand(7, 2, 30, generator=g) * 30 + 3).float()
    frame = torch.arange(2).view(1, 2, 1)
    interpolation.set_compile(False)
    try:
        ref = b.sample(x, y, frame=frame, grad=True)
        interpolation.set_compile(True)
        out = b.sample(x, y, frame=frame, grad=True)
    finally:
        interpolation.set_compile("auto")
    if compile_failed():
        pytest.skip("torch.compile is not available on this machine (eager fallback used)")
    for a, e in zip(out, ref):
        assert torch.allclose(a, e, atol=1e-3)


@pytest.mark.parametrize("order", [3, 5])
def test_whole_pixel_subsets_are_gathered_bit_identically(order):
    """Subsets of POIs on the pixel grid (the reference subsets) are gathered from the
    spline's values and gradients at every pixel, computed by the same kernel: the very
    same numbers as sampling them, for square and circular windows and several frames;
    off-grid points and subsets past the border are sampled as before."""
    from torch_stsdic.core.interpolation import BSplineImage

    g = torch.Generator().manual_seed(3)
    img = torch.rand(2, 90, 70, generator=g) * 255
    b = BSplineImage(img, order)
    r = 6
    a = torch.arange(-r, r + 1, dtype=torch.float32)
    yy, xx = torch.meshgrid(a, a, indexing="ij")
    dx, dy = xx.flatten(), yy.flatten()
    n = 400
    px = torch.randint(r, 70 - r, (n,), generator=g).float()
    py = torch.randint(r, 90 - r, (n,), generator=g).float()
    fr = torch.randint(0, 2, (n,), generator=g)
    for keep in (torch.ones_like(dx, dtype=torch.bool), dx * dx + dy * dy <= (r + 0.5) ** 2):
        fast = b.sample_subsets(px, py, dx[keep], dy[keep], fr)
        slow = b._subsets(px.view(-1, 1), py.view(-1, 1), dx[keep], dy[keep], fr.view(-1, 1))
        assert all(torch.equal(f, s) for f, s in zip(fast, slow))
        # the C++ copy of whole windows (where it runs) and torch's gather agree
        native.set_native("0")
        try:
            plain = b.sample_subsets(px, py, dx[keep], dy[keep], fr)
        finally:
            native.set_native("auto")
        assert all(torch.equal(f, s) for f, s in zip(plain, slow))
    assert b._grid is not None  # the gathered path was taken
    assert b._subsets_on_grid(px.view(-1, 1) + 0.5, py.view(-1, 1), dx, dy,
                              fr.view(-1, 1)) is None
    edge = torch.tensor([[2.0]])
    assert b._subsets_on_grid(edge, edge, dx, dy, torch.zeros(1, 1, dtype=torch.long)) is None
    # a few POIs on a large image: sampled (the per-pixel images would cost more)
    big = BSplineImage(torch.rand(400, 400, generator=g) * 255, order)
    few = torch.tensor([100.0, 250.0])
    got = big.sample_subsets(few, few, dx, dy)
    assert big._grid is None
    assert all(torch.equal(a, b_) for a, b_ in zip(got, big._subsets(
        few.view(-1, 1), few.view(-1, 1), dx, dy, torch.zeros(2, 1, dtype=torch.long))))
