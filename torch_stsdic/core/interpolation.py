"""B-spline image interpolation: prefilter once per image, then sample values and gradients.

Cubic (order 3, default) and quintic (order 5) B-splines. The prefilter turns pixel
intensities into B-spline coefficients so that the spline passes exactly through every
pixel (Unser, Aldroubi & Eden 1991); it is done exactly in the Fourier domain on the
mirror-symmetric extension of the image (the usual "mirror" boundary condition).
Sampling gathers the (order+1)^2 coefficients around each point and weights them with
the separable B-spline kernel and its derivative, so value and exact gradient come from the
same taps. All points of all subsets of all frames go through one call.

Not ``grid_sample(mode="bicubic")``: its cubic-convolution kernel (a = -0.75) is not a
B-spline and leaves a systematic error of order 1e-2 px in DIC.
"""

from __future__ import annotations

import math
import weakref
from collections import OrderedDict

import torch

from torch_stsdic.kernels import dispatch, native
from torch_stsdic.kernels.bspline import sample_kernel
from torch_stsdic.kernels.compile import maybe_compiled, set_compile

__all__ = ["BSplineImage", "bspline_prefilter", "set_compile", "window_view"]

#: subset offsets whose facts an image keeps (:meth:`BSplineImage._offset_facts`)
OFFSET_MEMO = 8


def window_view(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Every ``height`` x ``width`` window of ``images`` (F, H, W), as a view (no copy):
    (F, H - height + 1, W - width + 1, height, width), ``[f, y, x]`` the window whose top-left
    pixel is (x, y). Indexing it with (N,) frames, rows and columns gathers N windows."""
    f, h, w = images.shape
    st = images.stride()
    return images.as_strided((f, h - height + 1, w - width + 1, height, width),
                             (st[0], st[1], st[2], st[1], st[2]))


def _transfer(order: int, n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Fourier transfer function of the sampled B-spline kernel on a period of n samples."""
    w = 2.0 * math.pi * torch.arange(n // 2 + 1, dtype=dtype, device=device) / n
    if order == 3:
        return (4.0 + 2.0 * torch.cos(w)) / 6.0
    if order == 5:
        return (66.0 + 52.0 * torch.cos(w) + 2.0 * torch.cos(2.0 * w)) / 120.0
    raise ValueError(f"interpolation order must be 3 (cubic) or 5 (quintic), got {order}")


def _prefilter_axis(x: torch.Tensor, order: int, dim: int) -> torch.Tensor:
    n = x.shape[dim]
    if n < 2:
        return x
    # whole-sample symmetric extension: x0 .. x_{n-1}, x_{n-2} .. x1  (period 2n - 2)
    mirrored = torch.flip(x.narrow(dim, 1, n - 2), dims=(dim,)) if n > 2 else x.narrow(dim, 0, 0)
    ext = torch.cat([x, mirrored], dim=dim)
    period = ext.shape[dim]
    spec = torch.fft.rfft(ext, dim=dim)
    shape = [1] * x.dim()
    shape[dim] = -1
    spec = spec / _transfer(order, period, x.dtype, x.device).view(shape)
    return torch.fft.irfft(spec, n=period, dim=dim).narrow(dim, 0, n)


def bspline_prefilter(images: torch.Tensor, order: int = 3) -> torch.Tensor:
    """B-spline coefficients of ``images`` (..., H, W) (same shape and dtype).

    The spline built on the returned coefficients interpolates the pixels exactly.
    """
    if not images.is_floating_point():
        raise TypeError("bspline_prefilter needs a floating-point tensor")
    if order not in (3, 5):
        raise ValueError(f"interpolation order must be 3 (cubic) or 5 (quintic), got {order}")
    if dispatch.prefilter(images) == "native":
        return native.prefilter(images, order)  # recursive filter, same result
    c = _prefilter_axis(images, order, images.dim() - 1)
    return _prefilter_axis(c, order, images.dim() - 2)


def _kernel(order: int, grad: bool, work: int, needs_autograd: bool, device=None):
    def eager(*args):
        return sample_kernel(*args, order, grad)

    def kernel(*args):
        return sample_kernel(*args, order, grad)

    run = maybe_compiled(kernel, ("sample", order, grad), work, needs_autograd, device)
    return eager if run is kernel else run


class BSplineImage:
    """A stack of images prepared for B-spline sampling (the per-image work, done once).

    Args:
        images: (T, H, W) or (H, W) float tensor (grey levels).
        order: 3 (cubic) or 5 (quintic).

    Sampling outside the image uses the mirror-extended spline (values stay finite); the
    solver flags points whose subsets leave the image, so such values are never used silently.
    """

    def __init__(self, images: torch.Tensor, order: int = 3) -> None:
        if images.dim() == 2:
            images = images.unsqueeze(0)
        if images.dim() != 3:
            raise ValueError(f"images must be (T, H, W) or (H, W), got shape {tuple(images.shape)}")
        if order not in (3, 5):
            raise ValueError(f"interpolation order must be 3 or 5, got {order}")
        self.order = order
        self.n_frames, self.height, self.width = images.shape
        self.taps = order + 1
        self.lo = (order - 1) // 2  # taps start at floor(x) - lo
        coeffs = bspline_prefilter(images, order)
        # margin so that every tap of a point up to `margin - taps` px outside the image exists
        self.margin = min(self.taps + 2, self.height - 1, self.width - 1)
        pad = self.margin
        coeffs = torch.nn.functional.pad(coeffs.unsqueeze(1), (pad, pad, pad, pad), mode="reflect")
        self.coeffs = coeffs.squeeze(1).contiguous()  # (T, Hp, Wp)
        self.padded_width = self.coeffs.shape[-1]
        self.padded_height = self.coeffs.shape[-2]
        self._flat = self.coeffs.reshape(-1)

    @property
    def device(self) -> torch.device:
        return self.coeffs.device

    @property
    def dtype(self) -> torch.dtype:
        return self.coeffs.dtype

    def sample(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        frame: torch.Tensor | int = 0,
        grad: bool = False,
        work: int | None = None,
    ):
        """Sample the spline at (x, y) (same shape, pixels) in frame ``frame``.

        ``frame`` is an int or an integer tensor broadcastable to ``x``. Returns the values
        (shape of x), and with ``grad=True`` also d/dx and d/dy (grey levels per px).
        Coordinates are clamped to the padded coefficient grid, so samples far outside the
        image are finite but meaningless (callers check bounds).
        """
        x = x.to(self.dtype)
        y = y.to(self.dtype)
        ka = self.kernel_args()
        flat, wp, x_lo, x_hi, y_lo, y_hi, shift, plane = ka
        if isinstance(frame, int):
            frame_t = torch.full((), frame * plane, dtype=torch.long, device=self.device)
        else:
            frame_t = torch.as_tensor(frame, device=self.device).long() * plane
        if dispatch.sample(ka, x, y) == "native":
            return native.sample(ka, self.order, x, y, frame_t, grad)
        args = (flat, x, y, frame_t, wp, x_lo, x_hi, y_lo, y_hi, shift)
        kernel = _kernel(self.order, grad, x.numel() if work is None else work,
                         x.requires_grad or self._flat.requires_grad, self.device)
        return kernel(*args)

    def sample_subsets(self, px: torch.Tensor, py: torch.Tensor, dx: torch.Tensor,
                       dy: torch.Tensor, frame: torch.Tensor | int = 0, inside: bool = False):
        """Values and gradients (each (N, S)) of whole subsets: the points
        (px[i] + dx[s], py[i] + dy[s]) of frame[i]; px, py (N,) or (N, 1), dx, dy (S,),
        frame an int or (N,) integer tensor. ``inside``: the caller knows every point is a
        whole pixel whose subset lies inside the image (its facts then not read)."""
        px, py = px.reshape(-1, 1).to(self.dtype), py.reshape(-1, 1).to(self.dtype)
        frame_t = (torch.full((1, 1), frame, dtype=torch.long, device=self.device)
                   if isinstance(frame, int)
                   else torch.as_tensor(frame, device=self.device).long().reshape(-1, 1))
        fast = self._subsets_on_grid(px, py, dx, dy, frame_t, inside)
        if fast is not None:
            return fast
        return self._subsets(px, py, dx, dy, frame_t)

    def _subsets(self, px, py, dx, dy, frame_t):
        """:meth:`sample_subsets` by the sampling kernels."""
        args = self.kernel_args()
        if dispatch.sample(args, px, py, dx, dy) == "native":
            return native.subsets(args, self.order, px, py, dx, dy, frame_t * args[-1], True)
        return self.sample(px + dx, py + dy, frame=frame_t, grad=True)

    #: the spline's values, d/dx and d/dy at every pixel, (T, H, W) each (None: not made;
    #: a class default, so stacks built without ``__init__`` have it too)
    _grid: tuple[torch.Tensor, ...] | None = None

    #: :meth:`sample_subsets` gathers whole-pixel subsets from the spline's values and
    #: gradients at every pixel (computed once) for stacks of at most this many frames,
    GRID_FRAMES = 4
    #: ... of at most this many MiB for the three per-pixel images, and once the subsets
    #: asked for hold at least half as many samples as the stack has pixels (sparse POIs on a
    #: large image are sampled: the per-pixel images would cost more than they save)
    GRID_MAX_MB = 512.0

    def _subsets_on_grid(self, px, py, dx, dy, frame_t, inside: bool = False):
        """Subsets whose points and offsets are all whole pixels (the reference subsets of
        POIs on the pixel grid), gathered from the spline's values and gradients at every
        pixel (computed once per image by the same kernel: the same numbers); None where
        that does not apply (off-grid, gradients required, a long stack, points whose
        subsets leave the image). ``inside``: :meth:`sample_subsets`'s (the points' facts
        known; the offsets' read once for the offsets the image last saw)."""
        if (self.n_frames > self.GRID_FRAMES or px.requires_grad or py.requires_grad
                or self._flat.requires_grad or px.numel() == 0):
            return None
        hx, hy, full, whole = self._offset_facts(dx, dy)  # (read once for the offsets)
        if not whole:
            return None
        x0, y0 = px.long().reshape(-1) - hx, py.long().reshape(-1) - hy
        if not inside:  # the points' tests in one host read: whole pixels, the bounds
            whole, pxmin, pxmax, pymin, pymax = torch.stack([
                t.to(dtype=torch.float64).reshape(()) for t in (
                    (px == px.round()).all() & (py == py.round()).all(), px.min(), px.max(),
                    py.min(), py.max())]).tolist()
            if (not whole or int(pxmin) - hx < 0 or int(pymin) - hy < 0
                    or int(pxmax) + hx >= self.width or int(pymax) + hy >= self.height):
                return None
        return self._gather_windows(x0, y0, dx, dy, frame_t, hx, hy, full)

    def _offset_facts(self, dx: torch.Tensor, dy: torch.Tensor) -> tuple[int, int, bool, bool]:
        """(reach x, reach y, the full square in raster order, all whole pixels) of the
        subset offsets ``dx``, ``dy`` (S,): one host read, kept for the last few offsets
        asked for (a solver's geometry keeps its tensors from solve to solve; a run's
        solver and its model check's take turns)."""
        memo = self.__dict__.setdefault("_offset_memo", OrderedDict())
        key = (id(dx), id(dy))
        hit = memo.get(key)
        if hit is not None and hit[0]() is dx and hit[1]() is dy:
            return hit[2]
        hx_t, hy_t = dx.abs().max(), dy.abs().max()
        wx_t = 2 * hx_t.round() + 1
        col_t = (dy.round() + hy_t.round()) * wx_t + dx.round() + hx_t.round()
        full_t = (col_t == torch.arange(dx.numel(), device=col_t.device,
                                        dtype=col_t.dtype)).all()
        full_t &= (wx_t * (2 * hy_t.round() + 1)) == dx.numel()
        whole_t = (dx == dx.round()).all() & (dy == dy.round()).all()
        hx, hy, full, whole = torch.stack([t.to(torch.float64).reshape(()) for t in (
            hx_t, hy_t, full_t, whole_t)]).tolist()
        facts = (int(hx), int(hy), bool(full), bool(whole))
        memo[key] = (weakref.ref(dx), weakref.ref(dy), facts)
        while len(memo) > OFFSET_MEMO:
            memo.popitem(last=False)
        return facts

    def _gather_windows(self, x0, y0, dx, dy, frame_t, hx: int, hy: int, full: bool):
        """:meth:`_subsets_on_grid`'s gather of the windows whose first pixels are ``x0``,
        ``y0`` (N,), or None where the per-pixel images would cost more than they save."""
        if self._grid is None:
            pixels = self.n_frames * self.height * self.width
            mb = 3 * pixels * self.coeffs.element_size() / 2**20
            if mb > self.GRID_MAX_MB or 2 * x0.numel() * dx.numel() < pixels:
                return None
        grid = self._pixel_grid()  # 3 x (T, H, W)
        wx, wy = 2 * hx + 1, 2 * hy + 1
        col = ((dy.round().long() + hy) * wx + dx.round().long() + hx).to(self.device)
        f = frame_t.reshape(-1).expand(x0.numel())
        if full and dispatch.windows(*grid) == dispatch.NATIVE:  # one copy a window row
            base = (f * self.height + y0) * self.width + x0
            return native.windows(grid, base, wy, wx)
        out = []
        for g in grid:
            sub = window_view(g, wy, wx)[f, y0, x0].reshape(x0.numel(), wx * wy)
            out.append(sub if full else sub[:, col])
        return tuple(out)

    def _pixel_grid(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The spline's values and d/dx, d/dy at every pixel of every frame, each (T, H, W),
        by the subset kernel itself (cached)."""
        if self._grid is None or self._grid[0].device != self.device:
            t, h, w = self.n_frames, self.height, self.width
            ys = torch.arange(h, device=self.device, dtype=self.dtype)
            py = ys.repeat(t).reshape(-1, 1)
            px = torch.zeros_like(py)
            dx = torch.arange(w, device=self.device, dtype=self.dtype)
            frame_t = torch.arange(t, device=self.device).repeat_interleave(h).reshape(-1, 1)
            v, gx, gy = self._subsets(px, py, dx, torch.zeros_like(dx), frame_t)
            self._grid = tuple(a.reshape(t, h, w).contiguous() for a in (v, gx, gy))
        return self._grid

    def kernel_args(self) -> tuple:
        """(flat coefficients, padded width, x_lo, x_hi, y_lo, y_hi, index shift, plane size):
        what :func:`sample_kernel` needs besides the coordinates and frame offsets."""
        pad = self.margin
        return (
            self._flat, self.padded_width,
            float(-pad + self.lo), float(self.width - 1 + pad - self.taps + self.lo),
            float(-pad + self.lo), float(self.height - 1 + pad - self.taps + self.lo),
            pad - self.lo, self.padded_height * self.padded_width,
        )

    def with_coeffs(self, coeffs: torch.Tensor) -> BSplineImage:
        """An image of this one's size and settings over the coefficients ``coeffs``
        (T, H', W') (no copy; no per-pixel grid: ``coeffs`` are other numbers)."""
        out = BSplineImage.__new__(BSplineImage)
        out.__dict__.update(self.__dict__)
        out.__dict__.pop("_grid", None)
        out.coeffs = coeffs
        out.n_frames = int(coeffs.shape[0])
        out._flat = coeffs.reshape(-1)
        return out

    @classmethod
    def stack(cls, images: list[BSplineImage]) -> BSplineImage:
        """Join prepared single- or multi-frame images (same size and order) into one stack,
        without prefiltering again (a sliding window reuses each frame's coefficients)."""
        return images[0].with_coeffs(torch.cat([im.coeffs for im in images], dim=0))

    def frame(self, i: int) -> BSplineImage:
        """Frame i as its own single-frame BSplineImage (shares memory)."""
        return self.with_coeffs(self.coeffs[i : i + 1])

    def to(self, device=None, dtype=None) -> BSplineImage:
        return self.with_coeffs(self.coeffs.to(device=device, dtype=dtype))
