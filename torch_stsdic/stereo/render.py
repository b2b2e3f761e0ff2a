"""Synthetic stereo movies with exact truth: a speckled plane moving and deforming in 3D, seen
by two pinhole cameras with lens distortion, noise on every image.

The speckle pattern (:func:`torch_stsdic.synth.make_speckle`) is painted on the reference
plane in *texture pixels* of ``pitch`` mm. A material point with texture coordinates (s1, s2)
sits at ``X0 = O + pitch (s1 e1 + s2 e2)`` (plane origin O, in-plane axes e1, e2, normal n
towards the cameras) and moves to ``X(t) = X0 + D(a, b, t)`` (:class:`SurfaceMotion`, mm, with
a = pitch s1, b = pitch s2). Each camera's image is rendered by :func:`torch_stsdic.synth.
render` with the exact map texture -> image of that camera (projection with distortion) as the
motion: every spot centre is projected exactly and its shape mapped by the local Jacobian of
the projection (exact to first order over a spot, as the 2-D renderer is for non-uniform
fields); pixel values are exact pixel-area integrals. The truth at any left reference pixel
(its ray meets the plane at one material point) is exact: :meth:`StereoScene.truth`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

import torch_stsdic.synth as synth

from .calibration import Camera, StereoCalibration
from .triangulation import project, undistort

__all__ = ["SurfaceMotion", "StereoScene", "make_rig", "make_scene", "render_stereo"]

DTYPE = torch.float64


@dataclass
class SurfaceMotion:
    """Displacement of the plane's material points, linear in time (zero at t = 0), mm.

    ``D(a, b, t) = t * (translation + exx a e1 + eyy b e2 + bulge exp(-(a^2 + b^2) /
    (2 bulge_radius^2)) n)``, with (a, b) in-plane coordinates about the plane origin (mm),
    n the plane normal towards the cameras; rates per time unit.
    """

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    exx: float = 0.0
    eyy: float = 0.0
    bulge: float = 0.0
    bulge_radius: float = 10.0

    def rate(self, a: Tensor, b: Tensor, e1: Tensor, e2: Tensor, n: Tensor) -> Tensor:
        """(..., 3) velocity mm per time unit at in-plane coordinates (a, b)."""
        v = torch.as_tensor(self.translation, dtype=DTYPE).expand(*a.shape, 3).clone()
        v = v + (self.exx * a)[..., None] * e1 + (self.eyy * b)[..., None] * e2
        if self.bulge:
            g = torch.exp(-(a * a + b * b) / (2 * self.bulge_radius ** 2))
            v = v + (self.bulge * g)[..., None] * n
        return v


@dataclass
class StereoScene:
    """A rig, a speckled plane and its motion; renders images and gives the exact truth."""

    rig: StereoCalibration
    origin: Tensor
    e1: Tensor
    e2: Tensor
    normal: Tensor
    pitch: float
    pattern: synth.SpecklePattern
    motion: SurfaceMotion = field(default_factory=SurfaceMotion)

    # ---- geometry --------------------------------------------------------------------------
    def position(self, s: Tensor, t) -> Tensor:
        """World position (..., 3) mm at time t of the material point with texture coords s."""
        a, b = self.pitch * s[..., 0], self.pitch * s[..., 1]
        t = torch.as_tensor(t, dtype=DTYPE)
        x0 = self.origin + a[..., None] * self.e1 + b[..., None] * self.e2
        return x0 + t[..., None] * self.motion.rate(a, b, self.e1, self.e2, self.normal)

    def _pose(self, which: str):
        return (None, None) if which == "left" else (self.rig.R, self.rig.T)

    def _camera(self, which: str) -> Camera:
        return self.rig.left if which == "left" else self.rig.right

    def texture_of_pixel(self, px, which: str = "left") -> Tensor:
        """Texture coordinates (N, 2) of the reference plane point seen at pixels (N, 2)."""
        cam = self._camera(which)
        n = undistort(torch.as_tensor(np.asarray(px), dtype=DTYPE), cam)
        d = torch.cat([n, torch.ones_like(n[..., :1])], -1)
        if which == "left":
            c = torch.zeros(3, dtype=DTYPE)
        else:
            R = torch.as_tensor(self.rig.R, dtype=DTYPE)
            d = d @ R
            c = -(torch.as_tensor(self.rig.T, dtype=DTYPE) @ R)
        lam = ((self.origin - c) @ self.normal) / (d @ self.normal)
        X = c + lam[..., None] * d
        rel = X - self.origin
        return torch.stack([rel @ self.e1, rel @ self.e2], -1) / self.pitch

    def image_motion(self, which: str) -> synth.Custom:
        """The texture -> image map of one camera as a :class:`torch_stsdic.synth.Custom`
        motion (u, v = image position - texture position, px)."""
        cam = self._camera(which)
        R, T = self._pose(which)

        def fn(x, y, t):
            px = project(self.position(torch.stack([x, y], -1), t), cam, R, T)
            return px[..., 0] - x, px[..., 1] - y
        return synth.Custom(fn, h=1e-3)

    def render(self, t: float, which: str, quadrature: int = 4, cutoff: float = 6.0) -> Tensor:
        """Noise-free image (H, W) of camera ``which`` ("left"/"right") at time t
        (``quadrature``, ``cutoff``: of :func:`torch_stsdic.synth.render`)."""
        cam = self._camera(which)
        return synth.render(self.pattern, cam.image_size, self.image_motion(which), float(t),
                            quadrature=quadrature, cutoff=cutoff, check_coverage=False)

    def truth(self, left_px, times) -> dict[str, Tensor]:
        """Exact truth at left reference pixels (N, 2) and times (F,): "X" (F, N, 3) mm,
        "U" (F, N, 3) displacement mm, "velocity" (F, N, 3) mm per time unit, "X0" (N, 3),
        "left" / "right" (F, N, 2) px of the material points in each camera."""
        s = self.texture_of_pixel(left_px, "left")
        t = torch.as_tensor(np.asarray(times, dtype=np.float64))
        X = self.position(s[None].expand(t.numel(), -1, -1), t[:, None])
        X0 = self.position(s, 0.0)
        a, b = self.pitch * s[..., 0], self.pitch * s[..., 1]
        vel = self.motion.rate(a, b, self.e1, self.e2, self.normal)
        return {"X": X, "X0": X0, "U": X - X0, "velocity": vel.expand_as(X),
                "left": project(X, self.rig.left),
                "right": project(X, self.rig.right, self.rig.R, self.rig.T)}


def make_rig(shape=(200, 240), focal: float = 2400.0, distance: float = 300.0,
             angle: float = 20.0, distortion=(-0.3, 0.2, 1e-3, -5e-4, 0.0),
             right_distortion=None, skew: float = 0.0) -> StereoCalibration:
    """A symmetric converging rig whose optical axes meet ``distance`` mm in front of the left
    camera at ``angle`` degrees; the same intrinsics for both (principal point at the image
    centre, slightly off for the right camera)."""
    h, w = int(shape[0]), int(shape[1])
    Kl = np.array([[focal, skew, (w - 1) / 2 + 1.3], [0, focal * 1.001, (h - 1) / 2 - 0.7],
                   [0, 0, 1]])
    Kr = np.array([[focal * 0.995, skew, (w - 1) / 2 - 2.1], [0, focal * 0.996,
                                                              (h - 1) / 2 + 1.1], [0, 0, 1]])
    al = math.radians(angle)
    ry = np.array([[math.cos(al), 0, math.sin(al)], [0, 1, 0], [-math.sin(al), 0, math.cos(al)]])
    cr = np.array([distance * math.sin(al), 0.0, distance * (1 - math.cos(al))])
    dr = distortion if right_distortion is None else right_distortion
    return StereoCalibration(Camera(Kl, distortion, (h, w)), Camera(Kr, dr, (h, w)), ry,
                             -ry @ cr, source="synthetic rig")


def make_scene(rig: StereoCalibration | None = None, motion: SurfaceMotion | None = None, *,
               tilt: float = 5.0, shift: float = -15.0, radius: float = 2.0, seed: int = 0,
               max_time: float = 30.0) -> StereoScene:
    """A speckled plane facing the rig (normal on the bisector of the optical axes, tilted
    by ``tilt`` degrees about the horizontal axis), through the point where the axes meet
    moved by ``shift`` mm along the bisector (negative: nearer; the disparity then varies),
    with a speckle of ``radius`` px (in the left camera) covering both views for times up to
    ``max_time``."""
    rig = rig if rig is not None else make_rig()
    motion = motion if motion is not None else SurfaceMotion()
    R = torch.as_tensor(rig.R, dtype=DTYPE)
    zr = R[2]  # the right optical axis in the world frame
    zl = torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE)
    # where the axes meet (closest point of the two axes)
    c = -(torch.as_tensor(rig.T, dtype=DTYPE) @ R)
    A = torch.stack([zl, -zr], 1)
    ab = torch.linalg.lstsq(A, c[:, None]).solution[:, 0]
    P = 0.5 * (ab[0] * zl + c + ab[1] * zr)
    bis = (zl + zr) / torch.linalg.norm(zl + zr)
    P = P + shift * bis
    tl = math.radians(tilt)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(tl), -math.sin(tl)],
                       [0, math.sin(tl), math.cos(tl)]], dtype=DTYPE)
    n = -(rx @ bis)
    e1 = torch.tensor([1.0, 0.0, 0.0], dtype=DTYPE)
    e1 = e1 - (e1 @ n) * n
    e1 = e1 / torch.linalg.norm(e1)
    e2 = torch.linalg.cross(e1, n)
    pitch = float(P[2]) / rig.left.fx
    scene = StereoScene(rig, P, e1, e2, n, pitch, synth.make_speckle((1, 1), seed=seed), motion)
    # texture box covering both views (image borders back-projected) plus the motion
    pts = []
    for which, cam in (("left", rig.left), ("right", rig.right)):
        h, w = cam.image_size
        xs = torch.linspace(-0.5, w - 0.5, 33, dtype=DTYPE)
        ys = torch.linspace(-0.5, h - 0.5, 33, dtype=DTYPE)
        border = torch.cat([torch.stack([xs, torch.full_like(xs, -0.5)], 1),
                            torch.stack([xs, torch.full_like(xs, h - 0.5)], 1),
                            torch.stack([torch.full_like(ys, -0.5), ys], 1),
                            torch.stack([torch.full_like(ys, w - 0.5), ys], 1)])
        pts.append(scene.texture_of_pixel(border, which))
    pts = torch.cat(pts)
    lo, hi = pts.min(0).values, pts.max(0).values
    a, b = pitch * pts[:, 0], pitch * pts[:, 1]
    vmax = float(torch.linalg.norm(motion.rate(a, b, e1, e2, n), dim=-1).max()) * max_time
    margin = 8.0 * radius + 2.0 * vmax / pitch + 4.0
    W = int(math.ceil(float(hi[0] - lo[0]))) + 1
    H = int(math.ceil(float(hi[1] - lo[1]))) + 1
    pat = synth.make_speckle((H, W), radius=radius, seed=seed, margin=margin)
    scene.pattern = pat.shifted(float(lo[0]), float(lo[1]))
    return scene


def render_stereo(scene: StereoScene, times, noise_sigma: float = 0.0, seed: int = 1,
                  quadrature: int = 4, cutoff: float = 6.0) -> tuple[Tensor, Tensor]:
    """Left and right movies (F, H, W) float64 at ``times``, independent Gaussian noise of std
    ``noise_sigma`` grey levels on every image (``quadrature``, ``cutoff``: of
    :func:`torch_stsdic.synth.render`; 2 and 5 are about twice as fast)."""
    g = torch.Generator().manual_seed(int(seed))
    out = []
    for which in ("left", "right"):
        frames = []
        for t in np.asarray(times, dtype=np.float64).ravel():
            img = scene.render(float(t), which, quadrature, cutoff)
            if noise_sigma > 0:
                img = synth.add_noise(img, noise_sigma, generator=g)
            frames.append(img)
        out.append(torch.stack(frames))
    return out[0], out[1]
