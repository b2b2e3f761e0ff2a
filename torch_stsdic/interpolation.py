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
import os
import warnings

import torch

from . import native

__all__ = ["BSplineImage", "bspline_prefilter", "set_compile", "window_view"]


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
    if images.dim() >= 2 and native.usable(images):
        return native.prefilter(images, order)  # recursive filter, same result
    c = _prefilter_axis(images, order, images.dim() - 1)
    return _prefilter_axis(c, order, images.dim() - 2)


def _quintic_kernel(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
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


def _weights_list(f: torch.Tensor, order: int, grad: bool):
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
        b, db = _quintic_kernel(f - k)
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
    wx, dwx = _weights_list(fx, order, grad)
    wy, dwy = _weights_list(fy, order, grad)
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


# ---- optional torch.compile of the sampling kernel -------------------------------------
# "auto": compile for large jobs: >= _COMPILE_MIN samples per call, or per Gauss-Newton
# iteration over all batches of a solve (>= ~4 s per iteration in eager mode on one core);
# once compiled, the kernel serves every job of >= _COMPILED_MIN samples in the process.
# There the one-off compile time (~10-30 s; cached on disk by torch, ~7 s in a new process)
# pays back. "1"/"0": always / never. The environment variable TORCH_STSDIC_COMPILE sets the
# initial mode; see set_compile(). Fused, the sampler runs ~25x faster on a CPU.
_COMPILE_MODE = os.environ.get("TORCH_STSDIC_COMPILE", "auto").lower()
_COMPILE_MIN = 8_000_000
_COMPILED_MIN = 200_000
_COMPILED: dict = {}
_COMPILE_FAILED = False


def set_compile(mode: str | bool) -> None:
    """Use torch.compile for B-spline sampling: "auto" (large calls), True/"1", False/"0"."""
    global _COMPILE_MODE
    _COMPILE_MODE = {True: "1", False: "0"}.get(mode, str(mode).lower())  # type: ignore[arg-type]
    if _COMPILE_MODE not in ("auto", "1", "0"):
        raise ValueError(f"compile mode must be 'auto', True or False, got {mode!r}")


def compile_wanted(work: int) -> bool:
    """Whether "auto" mode compiles for a job of ``work`` samples in all (e.g. all POIs x
    frames x subset pixels of one Gauss-Newton iteration, over all batches)."""
    return _COMPILE_MODE == "1" or (_COMPILE_MODE == "auto" and work >= _COMPILE_MIN)


def maybe_compiled(fn, key, work: int, needs_autograd: bool = False):
    """``fn`` itself, or its torch.compile'd version (made once per ``key`` and process) when
    the compile policy wants it for a job of ``work`` samples. A compile failure (no C++
    compiler, unsupported platform) warns once and falls back to ``fn`` for good."""
    use = compile_wanted(work) or (
        _COMPILE_MODE == "auto" and key in _COMPILED and work >= _COMPILED_MIN
    )
    if not use or _COMPILE_FAILED or needs_autograd:
        return fn
    if key not in _COMPILED:
        compiled = torch.compile(fn, dynamic=True)

        def run(*args, _fn=compiled):
            global _COMPILE_FAILED
            try:
                return _fn(*args)
            except Exception as exc:  # no compiler, unsupported platform ...
                _COMPILE_FAILED = True
                first = str(exc).splitlines()[0] if str(exc) else ""
                warnings.warn(
                    f"torch.compile failed ({type(exc).__name__}: {first}); using eager mode",
                    RuntimeWarning, stacklevel=3,
                )
                return fn(*args)

        _COMPILED[key] = run
    return _COMPILED[key]


def _kernel(order: int, grad: bool, work: int, needs_autograd: bool):
    def eager(*args):
        return sample_kernel(*args, order, grad)

    def kernel(*args):
        return sample_kernel(*args, order, grad)

    run = maybe_compiled(kernel, ("sample", order, grad), work, needs_autograd)
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
            frame_t = torch.tensor(frame * plane, device=self.device)
        else:
            frame_t = torch.as_tensor(frame, device=self.device).long() * plane
        if native.usable_image(ka, x, y):
            return native.sample(ka, self.order, x, y, frame_t, grad)
        args = (flat, x, y, frame_t, wp, x_lo, x_hi, y_lo, y_hi, shift)
        kernel = _kernel(self.order, grad, x.numel() if work is None else work,
                         x.requires_grad or self._flat.requires_grad)
        return kernel(*args)

    def sample_subsets(self, px: torch.Tensor, py: torch.Tensor, dx: torch.Tensor,
                       dy: torch.Tensor, frame: torch.Tensor | int = 0):
        """Values and gradients (each (N, S)) of whole subsets: the points
        (px[i] + dx[s], py[i] + dy[s]) of frame[i]; px, py (N,) or (N, 1), dx, dy (S,),
        frame an int or (N,) integer tensor."""
        px, py = px.reshape(-1, 1).to(self.dtype), py.reshape(-1, 1).to(self.dtype)
        frame_t = torch.as_tensor(frame, device=self.device).long().reshape(-1, 1)
        fast = self._subsets_on_grid(px, py, dx, dy, frame_t)
        if fast is not None:
            return fast
        return self._subsets(px, py, dx, dy, frame_t)

    def _subsets(self, px, py, dx, dy, frame_t):
        """:meth:`sample_subsets` by the sampling kernels."""
        args = self.kernel_args()
        if native.usable_image(args, px, py, dx, dy):
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

    def _subsets_on_grid(self, px, py, dx, dy, frame_t):
        """Subsets whose points and offsets are all whole pixels (the reference subsets of
        POIs on the pixel grid), gathered from the spline's values and gradients at every
        pixel (computed once per image by the same kernel: the same numbers); None where
        that does not apply (off-grid, gradients required, a long stack, points whose
        subsets leave the image)."""
        if (self.n_frames > self.GRID_FRAMES or px.requires_grad or py.requires_grad
                or self._flat.requires_grad or px.numel() == 0):
            return None
        if not (bool((px == px.round()).all()) and bool((py == py.round()).all())
                and bool((dx == dx.round()).all()) and bool((dy == dy.round()).all())):
            return None
        hx, hy = int(dx.abs().max()), int(dy.abs().max())
        x0, y0 = px.long().reshape(-1) - hx, py.long().reshape(-1) - hy
        if (int(x0.min()) < 0 or int(y0.min()) < 0 or int(x0.max()) + 2 * hx >= self.width
                or int(y0.max()) + 2 * hy >= self.height):
            return None
        if self._grid is None:
            pixels = self.n_frames * self.height * self.width
            mb = 3 * pixels * self.coeffs.element_size() / 2**20
            if mb > self.GRID_MAX_MB or 2 * x0.numel() * dx.numel() < pixels:
                return None
        grid = self._pixel_grid()  # 3 x (T, H, W)
        wx, wy = 2 * hx + 1, 2 * hy + 1
        col = ((dy.round().long() + hy) * wx + dx.round().long() + hx).to(self.device)
        full = col.numel() == wx * wy and bool((col == torch.arange(wx * wy,
                                                                   device=col.device)).all())
        f = frame_t.reshape(-1).expand(x0.numel())
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

    @classmethod
    def stack(cls, images: list[BSplineImage]) -> BSplineImage:
        """Join prepared single- or multi-frame images (same size and order) into one stack,
        without prefiltering again (a sliding window reuses each frame's coefficients)."""
        first = images[0]
        out = cls.__new__(cls)
        out.__dict__.update(first.__dict__)
        out.coeffs = torch.cat([im.coeffs for im in images], dim=0)
        out.n_frames = out.coeffs.shape[0]
        out._flat = out.coeffs.reshape(-1)
        return out

    def frame(self, i: int) -> BSplineImage:
        """Frame i as its own single-frame BSplineImage (shares memory)."""
        out = BSplineImage.__new__(BSplineImage)
        out.__dict__.update(self.__dict__)
        out.coeffs = self.coeffs[i : i + 1]
        out.n_frames = 1
        out._flat = out.coeffs.reshape(-1)
        return out

    def to(self, device=None, dtype=None) -> BSplineImage:
        out = BSplineImage.__new__(BSplineImage)
        out.__dict__.update(self.__dict__)
        out.coeffs = self.coeffs.to(device=device, dtype=dtype)
        out._flat = out.coeffs.reshape(-1)
        return out
