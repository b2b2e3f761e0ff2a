"""The torch code of B-spline sampling: tap weights of the cubic and quintic B-splines and
their derivatives, and the sampling kernel over flat padded coefficients (the fused C++
kernel, ``native.sample``, computes the same; the tests compare the two).
:class:`torch_stsdic.core.interpolation.BSplineImage` is the entry point for everything else."""

from __future__ import annotations

import torch

__all__ = ["sample_kernel", "tap_weights", "quintic_kernel"]


def quintic_kernel(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Centred quintic B-spline B5(d) and its derivative."""
    a = d.abs()
    s = torch.sign(d)
    a2, a3, a4, a5 = a * a, a * a * a, a**4, a**5
    b0 = (66.0 - 60.0 * a2 + 30.0 * a4 - 10.0 * a5) / 120.0
    db0 = (-120.0 * a + 120.0 * a3 - 50.0 * a4) / 120.0
    b1 = (51.0 + 75.0 * a - 210.0 * a2 + 150.0 * a3 - 45.0 * a4 + 5.0 * a5) / 120.0
    db1 = (75.0 - 420.0 * a + 450.0 * a2 - 180.0 * a3 + 25.0 * a4) / 120.0
    r = (3.0 - a).clamp(min=0.0)
    b2 = r**5 / 120.0
    db2 = -5.0 * r**4 / 120.0
    b = torch.where(a < 1.0, b0, torch.where(a < 2.0, b1, b2))
    db = torch.where(a < 1.0, db0, torch.where(a < 2.0, db1, db2)) * s
    return b, db


def tap_weights(f: torch.Tensor, order: int, grad: bool):
    """B-spline tap weights (and derivatives) as lists of tensors shaped like f."""
    if order == 3:
        f2 = f * f
        f3 = f2 * f
        g = 1.0 - f
        w = [g * g * g / 6.0, (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0,
             (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0, f3 / 6.0]
        dw = [-0.5 * g * g, 1.5 * f2 - 2.0 * f, -1.5 * f2 + f + 0.5, 0.5 * f2] if grad else None
        return w, dw
    w, dw = [], []
    for k in range(-2, 4):
        b, db = quintic_kernel(f - k)
        w.append(b)
        dw.append(db)
    return w, (dw if grad else None)


def sample_kernel(flat, x, y, frame_off, wp: int, x_lo: float, x_hi: float, y_lo: float,
                   y_hi: float, shift: int, order: int, grad: bool):
    """Value (and gradient) of the B-spline at (x, y): (order+1)^2 gathers from the flat
    padded coefficients. Written as plain element-wise code so torch.compile can fuse it
    into one loop (no per-tap temporaries in memory)."""
    xc = x.clamp(x_lo, x_hi)
    yc = y.clamp(y_lo, y_hi)
    x0 = torch.floor(xc)
    y0 = torch.floor(yc)
    fx = xc - x0
    fy = yc - y0
    base = (y0.long() + shift) * wp + (x0.long() + shift) + frame_off
    wx, dwx = tap_weights(fx, order, grad)
    wy, dwy = tap_weights(fy, order, grad)
    taps = order + 1
    val = gx = gy = None
    for j in range(taps):
        row = rowd = None
        for i in range(taps):
            c = flat[base + (j * wp + i)]
            row = c * wx[i] if row is None else row + c * wx[i]
            if grad:
                rowd = c * dwx[i] if rowd is None else rowd + c * dwx[i]
        val = row * wy[j] if val is None else val + row * wy[j]
        if grad:
            gx = rowd * wy[j] if gx is None else gx + rowd * wy[j]
            gy = row * dwy[j] if gy is None else gy + row * dwy[j]
    if not grad:
        return val
    return val, gx, gy
