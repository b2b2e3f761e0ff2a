"""Projection, distortion removal and triangulation, vectorised over any number of points.

Conventions of :mod:`~torch_stsdic.stereo.calibration`: world = left camera frame (mm),
``X_R = R X_L + T``, OpenCV distortion (k1, k2, p1, p2, k3), pixel centres at integers.

:func:`triangulate` finds, for each pair of pixels, the 3D point whose projections into both
(distorted) images are closest to the two pixels in the least-squares sense (the maximum-
likelihood point for equal, independent pixel noise): a midpoint-of-rays start from the
undistorted rays, then Gauss-Newton on the four pixel residuals with the analytic Jacobian of
the distorted projection. It returns the reprojection error and the sensitivity
``A = dX / d(xL, yL, xR, yR)`` (3 x 4 per point), with which :func:`propagate_std` carries
pixel standard deviations to X, Y, Z (and displacements) in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .calibration import Camera, StereoCalibration

__all__ = ["project", "undistort", "triangulate", "Triangulated", "propagate_std",
           "propagate_cov",
           "distort"]

DTYPE = torch.float64


def _t(a, device=None) -> Tensor:
    if isinstance(a, Tensor):
        return a.to(dtype=DTYPE, device=device if device is not None else a.device)
    return torch.as_tensor(np.asarray(a, dtype=np.float64), device=device)


def _cam(cam: Camera, device) -> tuple[Tensor, Tensor]:
    return _t(cam.K, device), _t(cam.dist, device)


def distort(x: Tensor, y: Tensor, dist: Tensor, jacobian: bool = False):
    """Normalised (x, y) -> distorted normalised (xd, yd) (OpenCV model); with ``jacobian``
    also (dxd/dx, dxd/dy, dyd/dx, dyd/dy)."""
    k1, k2, p1, p2, k3 = dist.unbind(-1)
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if not jacobian:
        return xd, yd
    g = 2 * k1 + r2 * (4 * k2 + 6 * k3 * r2)  # d rad / d(x) = g x
    off = g * x * y + 2 * p1 * x + 2 * p2 * y
    return xd, yd, (rad + g * x * x + 2 * p1 * y + 6 * p2 * x, off, off,
                    rad + g * y * y + 6 * p1 * y + 2 * p2 * x)


def project(X: Tensor, cam: Camera, R=None, T=None, jacobian: bool = False):
    """Pixels (..., 2) of world points X (..., 3) mm seen by ``cam`` at pose (R, T)
    (world -> camera; None: the world frame). With ``jacobian`` also d(px)/dX (..., 2, 3)."""
    X = _t(X)
    dev = X.device
    K, d = _cam(cam, dev)
    if R is not None:
        Rt = _t(R, dev)
        Xc = X @ Rt.T + _t(T, dev)
    else:
        Rt = torch.eye(3, dtype=DTYPE, device=dev)
        Xc = X
    Z = Xc[..., 2]
    x, y = Xc[..., 0] / Z, Xc[..., 1] / Z
    out = distort(x, y, d, jacobian)
    xd, yd = out[0], out[1]
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    px = torch.stack([u, v], -1)
    if not jacobian:
        return px
    a, b, c, e = out[2]
    # d(xd, yd)/d(x, y), then d(u, v)/d(xd, yd)
    du_dx = K[0, 0] * a + K[0, 1] * c
    du_dy = K[0, 0] * b + K[0, 1] * e
    dv_dx = K[1, 1] * c
    dv_dy = K[1, 1] * e
    iz = 1.0 / Z
    # d(x, y)/d Xc: [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    zero = torch.zeros_like(Z)
    j_xy = torch.stack([torch.stack([iz, zero, -x * iz], -1),
                        torch.stack([zero, iz, -y * iz], -1)], -2)  # (..., 2, 3)
    j_uv = torch.stack([torch.stack([du_dx, du_dy], -1), torch.stack([dv_dx, dv_dy], -1)], -2)
    return px, j_uv @ j_xy @ Rt


def undistort(px: Tensor, cam: Camera, iterations: int = 20) -> Tensor:
    """Distorted pixels (..., 2) -> undistorted normalised coordinates (..., 2) (Newton)."""
    px = _t(px)
    K, d = _cam(cam, px.device)
    yd = (px[..., 1] - K[1, 2]) / K[1, 1]
    xd = (px[..., 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = xd.clone(), yd.clone()
    for _ in range(iterations):
        fx, fy, (a, b, c, e) = distort(x, y, d, True)
        rx, ry = fx - xd, fy - yd
        det = a * e - b * c
        dx = (e * rx - b * ry) / det
        dy = (-c * rx + a * ry) / det
        x, y = x - dx, y - dy
        if float(torch.nan_to_num(dx.abs() + dy.abs(), nan=0.0).max()) < 1e-15:
            break
    return torch.stack([x, y], -1)


@dataclass
class Triangulated:
    """Result of :func:`triangulate`.

    Attributes:
        X: (..., 3) points in the world (left camera) frame, mm.
        reprojection_error: (...,) RMS over the two cameras of the distance between each
            pixel and the projection of X, px.
        sensitivity: (..., 3, 4) dX / d(xL, yL, xR, yR), mm per px.
        in_front: (...,) bool: X is in front of both cameras.
    """

    X: Tensor
    reprojection_error: Tensor
    sensitivity: Tensor
    in_front: Tensor


def triangulate(rig: StereoCalibration, left_px, right_px, iterations: int = 6
                ) -> Triangulated:
    """Triangulate pixel pairs (..., 2) + (..., 2) (distorted image coordinates) -> 3D, mm.

    Non-finite pixels give NaN points. Vectorised: one set of tensor operations for all.
    """
    pl, pr = _t(left_px), _t(right_px)
    if pl.shape != pr.shape or pl.shape[-1] != 2:
        raise ValueError(f"left and right pixels must both be (..., 2), got {tuple(pl.shape)} "
                         f"and {tuple(pr.shape)}")
    dev = pl.device
    R, T = _t(rig.R, dev), _t(rig.T, dev)
    # start: midpoint of the undistorted rays
    nl = undistort(pl, rig.left)
    nr = undistort(pr, rig.right)
    dl = torch.cat([nl, torch.ones_like(nl[..., :1])], -1)
    dr = torch.cat([nr, torch.ones_like(nr[..., :1])], -1) @ R  # R^T d in world
    c = -(T @ R)  # right centre in the world: -R^T T
    # min |a dl - (c + b dr)|^2
    aa = (dl * dl).sum(-1)
    bb = (dr * dr).sum(-1)
    ab = (dl * dr).sum(-1)
    cl = (c * dl).sum(-1)
    cr = (c * dr).sum(-1)
    det = aa * bb - ab * ab
    a = (cl * bb - ab * cr) / det
    b = (ab * cl - aa * cr) / det
    X = 0.5 * (a[..., None] * dl + c + b[..., None] * dr)
    obs = torch.cat([pl, pr], -1)
    for _ in range(iterations):
        r, J = _residual(rig, X, obs, R, T)
        JtJ = J.transpose(-1, -2) @ J
        step = torch.linalg.solve(JtJ + 0.0 * torch.eye(3, dtype=DTYPE, device=dev),
                                  (J.transpose(-1, -2) @ r[..., None]))[..., 0]
        X = X - step
    r, J = _residual(rig, X, obs, R, T)
    JtJ = J.transpose(-1, -2) @ J
    A = torch.linalg.solve(JtJ, J.transpose(-1, -2))
    err = torch.sqrt((r * r).sum(-1) / 2)
    zr = (X @ R.T + T)[..., 2]
    front = (X[..., 2] > 0) & (zr > 0)
    return Triangulated(X, err, A, front)


def _residual(rig, X, obs, R, T):
    pl, jl = project(X, rig.left, jacobian=True)
    pr, jr = project(X, rig.right, R, T, jacobian=True)
    r = torch.cat([pl, pr], -1) - obs
    return r, torch.cat([jl, jr], -2)


def propagate_std(sensitivity: Tensor, std4: Tensor) -> Tensor:
    """Standard deviations (..., 3) mm of ``A @ p`` for independent pixel errors of std
    ``std4`` (..., 4) (xL, yL, xR, yR), with ``A = sensitivity`` (..., 3, 4): the square
    roots of :func:`propagate_cov`'s diagonal."""
    return torch.sqrt(((sensitivity ** 2) * (std4[..., None, :] ** 2)).sum(-1))


def propagate_cov(sensitivity: Tensor, std4: Tensor) -> Tensor:
    """Covariance (..., 3, 3) mm^2 of ``A @ p`` for independent pixel errors of std ``std4``
    (..., 4): ``A diag(std4^2) A^T``. Its off-diagonal terms matter: a point's depth error
    lies along the lines of sight, so its X, Y and Z errors are correlated."""
    a = sensitivity * std4[..., None, :]
    return a @ a.transpose(-1, -2)
