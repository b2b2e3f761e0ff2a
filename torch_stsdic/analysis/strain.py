"""Strain and strain rate from DIC displacement fields by local least-squares plane fits.

Wang & Ma (STS-DIC) compute strain "by fitting the displacement field as a plane": around every
point of interest the displacements ``u`` and ``v`` of the neighbouring points are fitted by
``u(x, y) ~ a + b (x - x0) + c (y - y0)`` in the weighted least-squares sense, and the slopes give
the displacement gradients ``du/dx = b``, ``du/dy = c`` (same for ``v``).

Conventions: ``x`` is the column (right), ``y`` the row (down), both in pixels; ``u`` is the
displacement along ``x`` and ``v`` along ``y`` (Lagrangian: the reference point ``X`` moves to
``X + U(X, t)``). Gradients are therefore dimensionless (pixel / pixel) and strain rates are in
1 / (time unit of ``ut``, ``vt``) -- with the velocities of the series tracker, per frame.

Two neighbourhood searches, same plane fit:

* **grid** (points on a regular grid, possibly with holes): the normal equations of every point
  are accumulated with ``conv2d`` over a ``window x window`` block of grid points (one batched
  convolution for all points and frames);
* **knn** (scattered points): the ``window**2`` nearest neighbours of each point
  (``torch.cdist`` + ``topk``), then the same weighted normal equations by gathering.

Invalid or missing neighbours get zero weight, so border points simply use the neighbours that
exist. A point gets NaN when it is itself invalid, has fewer than ``min_points`` valid neighbours
(itself included), or its valid neighbours are (nearly) collinear.
"""

from __future__ import annotations

import hashlib
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from torch_stsdic.analysis.points import nearest_points

__all__ = [
    "GridInfo",
    "compute_strain",
    "detect_grid",
    "plane_fit_gradients",
    "principal_strains",
]

_KINDS = ("green", "small")


# --------------------------------------------------------------------------------------------
# grid detection
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GridInfo:
    """A regular grid found under a point set.

    Point ``n`` lies at ``x = x0 + ix[n] * sx``, ``y = y0 + iy[n] * sy`` (pixels); the grid has
    ``ny`` rows and ``nx`` columns, cells without a point are holes.
    """

    x0: float
    y0: float
    sx: float  #: grid step along x (pixels)
    sy: float  #: grid step along y (pixels)
    nx: int
    ny: int
    ix: np.ndarray  #: (N,) int64 column index of each point
    iy: np.ndarray  #: (N,) int64 row index of each point

    @property
    def flat_index(self) -> np.ndarray:
        """(N,) index of each point in the row-major ``(ny, nx)`` grid."""
        return self.iy * self.nx + self.ix

    def flat_on(self, device: torch.device) -> torch.Tensor:
        """:attr:`flat_index` as a tensor on ``device``, copied there once per device."""
        memo = self.__dict__.setdefault("_flat_on", {})
        if str(device) not in memo:
            memo[str(device)] = torch.as_tensor(self.flat_index, device=device)
        return memo[str(device)]

    def to_image(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Scatter per-point ``values`` (..., N) into a (..., ny, nx) array (holes: ``fill``)."""
        values = np.asarray(values)
        dtype = values.dtype if values.dtype.kind == "f" else np.float64
        out = np.full(values.shape[:-1] + (self.ny * self.nx,), fill, dtype=dtype)
        out[..., self.flat_index] = values
        return out.reshape(values.shape[:-1] + (self.ny, self.nx))


def _axis_grid(c: np.ndarray, rtol: float) -> tuple[float, float, np.ndarray] | None:
    """Origin, step and integer index of 1-D coordinates ``c``; None if not on a regular lattice."""
    c0 = float(c.min())
    span = float(c.max()) - c0
    if span == 0.0:
        return c0, 1.0, np.zeros(c.shape, dtype=np.int64)
    tol = rtol * max(span, 1.0)
    d = np.diff(np.sort(c))  # (np.unique's first call imports numpy.ma: 9 ms a run)
    d = d[d > tol]
    if d.size == 0:
        return c0, 1.0, np.zeros(c.shape, dtype=np.int64)
    step = float(d.min())
    idx = np.rint((c - c0) / step).astype(np.int64)
    # refine the step by least squares, then check that every coordinate sits on the lattice
    step = float(np.sum((c - c0) * idx) / np.sum(idx.astype(np.float64) ** 2))
    if not np.all(np.abs(c - (c0 + idx * step)) <= 1e-3 * step + tol):
        return None
    return c0, step, idx


def detect_grid(points: Any, *, max_fill: float = 4.0, rtol: float = 1e-6) -> GridInfo | None:
    """Detect whether ``points`` (N, 2) as ``(x, y)`` pixels lie on a regular grid.

    The grid is ``x0 + i * sx``, ``y0 + j * sy`` with steps taken from the unique coordinates.
    Holes (masked points) are allowed, but the bounding grid may hold at most ``max_fill * N``
    cells and no cell may hold two points. Returns a :class:`GridInfo` (its index arrays
    read-only), or None when the points are scattered. The last few answers are kept by the
    points' bytes: a run asks for the same points' grid three times (neighbour test, strains);
    and by the tensor itself (unchanged since): a block asks again without a copy to the host.
    """
    opts = (float(max_fill), float(rtol))
    if isinstance(points, torch.Tensor):
        hit = _GRID_TENSORS.get(id(points))
        if hit is not None and hit[0]() is points and hit[1:3] == (points._version, opts):
            return hit[3]
    p = np.ascontiguousarray(_as_numpy(points), dtype=np.float64).reshape(-1, 2)
    key = (hashlib.blake2b(p.tobytes(), digest_size=16).digest(), *opts)
    if key not in _GRIDS:
        grid = _detect_grid(p, max_fill, rtol)
        if grid is not None:
            grid.ix.flags.writeable = False
            grid.iy.flags.writeable = False
        _GRIDS[key] = grid
        while len(_GRIDS) > 4:
            _GRIDS.pop(next(iter(_GRIDS)))
    if isinstance(points, torch.Tensor):  # (tensors gone first: a writer's are short-lived)
        for k, hit in list(_GRID_TENSORS.items()):
            if hit[0]() is None:
                _GRID_TENSORS.pop(k, None)
        _GRID_TENSORS[id(points)] = (weakref.ref(points), points._version, opts, _GRIDS[key])
        while len(_GRID_TENSORS) > 4:
            _GRID_TENSORS.pop(next(iter(_GRID_TENSORS)), None)
    return _GRIDS[key]


_GRIDS: dict[tuple, GridInfo | None] = {}  # detect_grid's last answers, oldest first
#: detect_grid's last answers by tensor: id -> (weak reference, version, options, answer)
_GRID_TENSORS: dict[int, tuple[Any, int, tuple[float, float], GridInfo | None]] = {}


def _detect_grid(p: np.ndarray, max_fill: float, rtol: float) -> GridInfo | None:
    """:func:`detect_grid` of (N, 2) float64 points."""
    n = p.shape[0]
    if n == 0 or not np.all(np.isfinite(p)):
        return None
    gx = _axis_grid(p[:, 0], rtol)
    gy = _axis_grid(p[:, 1], rtol)
    if gx is None or gy is None:
        return None
    (x0, sx, ix), (y0, sy, iy) = gx, gy
    nx, ny = int(ix.max()) + 1, int(iy.max()) + 1
    if nx * ny > max(max_fill * n, 16):
        return None
    flat = iy * nx + ix
    if n > 1 and not np.all(np.diff(np.sort(flat))):  # two points in one grid cell
        return None
    return GridInfo(x0=x0, y0=y0, sx=sx, sy=sy, nx=nx, ny=ny, ix=ix, iy=iy)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def _as_numpy(a: Any) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().numpy()
    return np.asarray(a)


def _as_tensor(
    a: Any, *, device: torch.device | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    if isinstance(a, torch.Tensor):
        return a.to(device=device if device is not None else a.device, dtype=dtype)
    a = np.asarray(a)
    if not a.flags.writeable:
        a = a.copy()  # torch warns on read-only arrays (e.g. from np.broadcast_to)
    return torch.as_tensor(a, device=device, dtype=dtype)


def _work_dtype(device: torch.device) -> torch.dtype:
    # float64 avoids cancellation in the normal equations; MPS has no float64
    return torch.float32 if device.type == "mps" else torch.float64


def _solve_moments(
    s0: torch.Tensor,
    sx: torch.Tensor,
    sy: torch.Tensor,
    sxx: torch.Tensor,
    sxy: torch.Tensor,
    syy: torch.Tensor,
    su: torch.Tensor,
    sxu: torch.Tensor,
    syu: torch.Tensor,
    min_points: int,
    rcond: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slopes (b, c) of the weighted plane fit from raw moments; NaN where ill-posed.

    Weight moments have shape (B, M); value moments (B, C, M). Coordinates are offsets from the
    centre point in grid-step (or typical-spacing) units.
    """
    safe0 = torch.where(s0 > 0, s0, torch.ones_like(s0))
    cxx = sxx - sx * sx / safe0
    cxy = sxy - sx * sy / safe0
    cyy = syy - sy * sy / safe0
    det = cxx * cyy - cxy * cxy
    tr = cxx + cyy
    ok = (s0 >= min_points - 1e-9) & (det > rcond * tr * tr) & (tr > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    s0e, sxe, sye = safe0.unsqueeze(1), sx.unsqueeze(1), sy.unsqueeze(1)
    cxu = sxu - sxe * su / s0e
    cyu = syu - sye * su / s0e
    b = (cyy.unsqueeze(1) * cxu - cxy.unsqueeze(1) * cyu) / det_safe.unsqueeze(1)
    c = (cxx.unsqueeze(1) * cyu - cxy.unsqueeze(1) * cxu) / det_safe.unsqueeze(1)
    nan = torch.full_like(b, float("nan"))
    okc = ok.unsqueeze(1)
    return torch.where(okc, b, nan), torch.where(okc, c, nan)


def _box_moments(img: torch.Tensor, h: int, order: int) -> torch.Tensor:
    """Separable box sums ``sum_{|i|,|j|<=h} img[y+j, x+i] * i**p * j**q`` for p, q <= order.

    img (B, 1, ny, nx) with zero padding outside -> (B, order+1, order+1, ny, nx) indexed [p, q].
    Offsets ``i`` (along x) and ``j`` (along y) are in grid steps.
    """
    bsz, _, ny, nx = img.shape
    off = torch.arange(-h, h + 1, device=img.device, dtype=img.dtype)
    pw = torch.stack([off**p for p in range(order + 1)])  # (P, k)
    rows = F.conv2d(img, pw.view(-1, 1, 1, 2 * h + 1), padding=(0, h))  # (B, P, ny, nx)
    cols = F.conv2d(rows.reshape(-1, 1, ny, nx), pw.view(-1, 1, 2 * h + 1, 1), padding=(h, 0))
    return cols.view(bsz, order + 1, order + 1, ny, nx)


def _fit_planes(
    pts: torch.Tensor, grid: GridInfo | None, vals: torch.Tensor, w: torch.Tensor, window: int,
    min_points: int, rcond: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Plane-fit slopes: vals (B, C, N), w (B, N) -> (d/dx, d/dy) each (B, C, N), on the
    ``grid`` by box sums, else (grid None) over the ``window**2`` nearest neighbours."""
    if grid is not None:
        moments, sx, sy = _grid_moments(grid, vals, w, window), grid.sx, grid.sy
    else:
        moments, scale = _knn_moments(pts, vals, w, window)
        sx = sy = scale
    slopes = [_solve_moments(*mw, *mv, min_points=min_points, rcond=rcond) for mw, mv in moments]
    return torch.cat([b for b, _ in slopes], -1) / sx, torch.cat([c for _, c in slopes], -1) / sy


_Moments = Iterator[tuple[Sequence[torch.Tensor], Sequence[torch.Tensor]]]


def _grid_moments(grid: GridInfo, vals: torch.Tensor, w: torch.Tensor, window: int) -> _Moments:
    """The weighted position moments (6 of (B, N)) and value moments (3 of (B, C, N)) of every
    grid point's window, in grid steps: one chunk."""
    bsz, nch, n = vals.shape
    dev, dt = vals.device, vals.dtype
    cells = grid.ny * grid.nx
    flat = grid.flat_on(dev)
    wg = torch.zeros(bsz, cells, device=dev, dtype=dt)
    wg[:, flat] = w
    vg = torch.zeros(bsz, nch, cells, device=dev, dtype=dt)
    vg[:, :, flat] = vals * w.unsqueeze(1)
    h = window // 2
    mw = _box_moments(wg.view(bsz, 1, grid.ny, grid.nx), h, 2)  # (B, 3, 3, ny, nx)
    mv = _box_moments(vg.view(bsz * nch, 1, grid.ny, grid.nx), h, 1)  # (B*C, 2, 2, ny, nx)
    mw = torch.stack(
        [mw[:, 0, 0], mw[:, 1, 0], mw[:, 0, 1], mw[:, 2, 0], mw[:, 1, 1], mw[:, 0, 2]], 1
    )
    mv = torch.stack([mv[:, 0, 0], mv[:, 1, 0], mv[:, 0, 1]], 1)
    mw = mw.reshape(bsz, 6, cells)[:, :, flat]  # (B, 6, N)
    mv = mv.reshape(bsz, nch, 3, cells)[:, :, :, flat]  # (B, C, 3, N)
    yield mw.unbind(1), mv.unbind(2)


def _knn_moments(
    pts: torch.Tensor, vals: torch.Tensor, w: torch.Tensor, window: int
) -> tuple[_Moments, float]:
    """The moments of :func:`_grid_moments` over the ``window**2`` nearest neighbours, chunk by
    chunk of points (bounded memory), with offsets in units of the returned scale (px)."""
    bsz, nch, n = vals.shape
    k = min(window * window, n)
    idx = nearest_points(pts, k)[1]  # (N, k), itself first
    d = pts[idx] - pts.unsqueeze(1)  # (N, k, 2) offsets in pixels
    if n > 1:
        nn = torch.linalg.vector_norm(d[:, 1:2], dim=-1)
        scale = float(torch.median(nn[nn > 0])) if bool((nn > 0).any()) else 1.0
    else:
        scale = 1.0
    d = d / scale
    dx, dy = d[..., 0], d[..., 1]
    vals = torch.where(w.unsqueeze(1) > 0, vals, torch.zeros_like(vals))
    chunk = max(1, (1 << 24) // max(1, bsz * (nch + 6) * k))

    def chunks() -> _Moments:
        for i in range(0, n, chunk):
            sl = slice(i, i + chunk)
            wk = w[:, idx[sl]]  # (B, n_c, k)
            dxk, dyk = dx[sl], dy[sl]
            mw = [
                wk.sum(-1),
                (wk * dxk).sum(-1),
                (wk * dyk).sum(-1),
                (wk * dxk * dxk).sum(-1),
                (wk * dxk * dyk).sum(-1),
                (wk * dyk * dyk).sum(-1),
            ]
            vk = vals[:, :, idx[sl]] * wk.unsqueeze(1)  # (B, C, n_c, k)
            yield mw, [vk.sum(-1), (vk * dxk).sum(-1), (vk * dyk).sum(-1)]

    return chunks(), scale


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _PlaneFit:
    """Settings of the local plane fits (see :func:`plane_fit_gradients`), checked once."""

    window: int
    method: str
    min_points: int
    require_center: bool
    rcond: float | None

    def __post_init__(self) -> None:
        w = self.window
        if not isinstance(w, (int, np.integer)) or w < 3 or w % 2 == 0:
            raise ValueError(
                f"window must be an odd integer >= 3 (grid points per side), got {w!r}")
        if self.min_points < 3:
            raise ValueError(f"min_points must be >= 3 for a plane fit, got {self.min_points}")
        if self.method not in ("auto", "grid", "knn"):
            raise ValueError(f"method must be 'auto', 'grid' or 'knn', got {self.method!r}")


def _gradients(
    points: Any, values: Any, valid: Any, fit: _PlaneFit, stacked: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Core of :func:`plane_fit_gradients`.

    With ``stacked`` the values are (..., C, N) and share one validity (..., N) across C.
    """
    vt = _as_tensor(values)
    dev = vt.device
    wdt = _work_dtype(dev)
    out_dt = vt.dtype if vt.dtype.is_floating_point else torch.get_default_dtype()
    pts = _as_tensor(points, device=dev, dtype=wdt)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2) as (x, y), got {tuple(pts.shape)}")
    n = pts.shape[0]
    v = vt.to(wdt)
    if v.shape[-1] != n:
        raise ValueError(f"values must have shape (..., N) with N={n}, got {tuple(v.shape)}")
    if stacked:
        lead, nch = v.shape[:-2], v.shape[-2]
    else:
        lead, nch = v.shape[:-1], 1
        v = v.unsqueeze(-2)
    v = v.reshape(-1, nch, n)
    ok = torch.isfinite(v).all(dim=1)  # (B, N)
    if valid is not None:
        vm = _as_tensor(valid, device=dev).to(torch.bool)
        ok = ok & torch.broadcast_to(vm, tuple(lead) + (n,)).reshape(-1, n)
    w = ok.to(wdt)
    # subtract a per-field mean: removes the (often large) rigid translation before summing
    mean = (
        torch.where(ok.unsqueeze(1), v, torch.zeros_like(v)).sum(-1, keepdim=True)
        / w.sum(-1).clamp_min(1.0)[:, None, None]
    )
    v = torch.where(ok.unsqueeze(1), v - mean, torch.zeros_like(v))
    rcond = 1e3 * torch.finfo(wdt).eps if fit.rcond is None else fit.rcond
    grid = None
    if fit.method in ("auto", "grid") and n > 0:
        # the caller's tensor where it gave one: its grid is kept by identity (no copy)
        grid = detect_grid(points if isinstance(points, torch.Tensor) else pts)
        if grid is None and fit.method == "grid":
            raise ValueError("method='grid' but the points do not lie on a regular grid")
    if n == 0:
        gx = gy = v
    else:
        gx, gy = _fit_planes(pts, grid, v, w, fit.window, fit.min_points, rcond)
    if fit.require_center:
        bad = ~ok.unsqueeze(1)
        gx = gx.masked_fill(bad, float("nan"))
        gy = gy.masked_fill(bad, float("nan"))
    shape = tuple(lead) + ((nch,) if stacked else ()) + (n,)
    return gx.reshape(shape).to(out_dt), gy.reshape(shape).to(out_dt)


def plane_fit_gradients(
    points: Any,
    values: Any,
    *,
    window: int = 5,
    valid: Any = None,
    method: str = "auto",
    min_points: int = 3,
    require_center: bool = True,
    rcond: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Spatial gradients of a scalar field by local weighted least-squares plane fits.

    Args:
        points: (N, 2) point coordinates ``(x, y)`` in pixels.
        values: (..., N) field sampled at the points (any leading batch dims, e.g. frames).
        window: odd number of grid points per side of the square neighbourhood (``5`` -> 5 x 5).
            For scattered points, the ``window**2`` nearest neighbours (itself included).
        valid: optional (..., N) bool mask (broadcast against ``values``); non-finite values are
            always invalid.
        method: ``"auto"`` (grid if :func:`detect_grid` finds one, else knn), ``"grid"``, ``"knn"``.
        min_points: minimum number of valid points in the neighbourhood (>= 3).
        require_center: NaN at points whose own value is invalid (no hole filling).
        rcond: collinearity threshold on ``det / trace**2`` of the position covariance
            (default ``1e3 * eps`` of the working dtype).

    Returns:
        ``(d/dx, d/dy)`` torch tensors (..., N) in value units per pixel (on the device of
        ``values``), NaN where the fit is ill-posed.
    """
    fit = _PlaneFit(window, method, min_points, require_center, rcond)
    gx, gy = _gradients(points, values, valid, fit)
    if isinstance(values, torch.Tensor):
        return gx, gy
    return gx.numpy(), gy.numpy()


def compute_strain(
    points: Any,
    u: Any,
    v: Any,
    *,
    window: int = 5,
    kind: str = "green",
    valid: Any = None,
    ut: Any = None,
    vt: Any = None,
    method: str = "auto",
    min_points: int = 3,
    require_center: bool = True,
    return_gradients: bool = False,
) -> dict[str, Any]:
    """Strain (and strain rate) fields from displacement fields by local plane fits.

    Around each point, ``u`` and ``v`` of the valid neighbours are fitted by planes (weighted
    least squares, one 3 x 3 normal system per point and frame, all batched), giving the
    displacement gradient ``H = [[ux, uy], [vx, vy]]`` (``ux = du/dx`` ...). Then

    * ``kind="small"`` (infinitesimal): ``exx = ux``, ``eyy = vy``, ``exy = (uy + vx) / 2``;
    * ``kind="green"`` (Green-Lagrange, ``E = (F^T F - I) / 2`` with ``F = I + H``):
      ``exx = ux + (ux^2 + vx^2) / 2``, ``eyy = vy + (uy^2 + vy^2) / 2``,
      ``exy = (uy + vx + ux uy + vx vy) / 2``.

    ``exy`` is the **tensor** shear component; the engineering shear strain is
    ``gamma_xy = 2 * exy``. Strains are dimensionless (pixel / pixel).

    With the velocities ``ut``, ``vt`` (displacement per unit time, e.g. the STS-DIC ``dU/dt`` in
    pixel / frame), the strain rates are returned too: ``L = grad(Ut)`` from plane fits of
    ``ut``, ``vt``, then for ``"small"`` ``exx_rate = utx``, ``eyy_rate = vty``,
    ``exy_rate = (uty + vtx) / 2`` and for ``"green"`` ``dE/dt = sym(F^T L)``:
    ``exx_rate = utx + ux utx + vx vtx``, ``eyy_rate = vty + uy uty + vy vty``,
    ``exy_rate = (uty + vtx + utx uy + ux uty + vtx vy + vx vty) / 2`` (units 1 / time unit).

    Args:
        points: (N, 2) point coordinates ``(x, y)`` in pixels (a regular grid, possibly with
            holes, is detected automatically; otherwise scattered points).
        u, v: (..., N) displacements along x and y in pixels (leading dims: frames, ...).
        window: odd number of grid points per side of the fitting neighbourhood (5 -> 5 x 5
            points, i.e. a ``(window - 1) * step`` pixel wide square). For scattered points, the
            ``window**2`` nearest neighbours.
        kind: ``"green"`` (Green-Lagrange, default) or ``"small"``.
        valid: optional (..., N) bool mask of usable points, e.g. ``status <= 1``; non-finite
            ``u``/``v`` (``ut``/``vt`` for the rates) are always treated as invalid.
        ut, vt: optional (..., N) velocity fields (pixel / time unit); both or neither.
        method: ``"auto"``, ``"grid"`` or ``"knn"`` (neighbour search, see module docstring).
        min_points: minimum number of valid points in a neighbourhood (>= 3, non-collinear).
        require_center: NaN at points whose own displacement is invalid (no hole filling).
        return_gradients: also return ``ux, uy, vx, vy`` (and ``utx, uty, vtx, vty``).

    Returns:
        dict of (..., N) arrays: ``exx, eyy, exy`` (+ ``exx_rate, eyy_rate, exy_rate`` when
        ``ut``/``vt`` are given, + gradients if asked). numpy in -> numpy out; torch in -> torch
        out (same device, same floating dtype, differentiable). NaN where the fit is ill-posed.

    Example:
        >>> pts = np.stack(np.meshgrid(np.arange(0, 50, 10.0), np.arange(0, 50, 10.0)), -1)
        >>> pts = pts.reshape(-1, 2)
        >>> s = compute_strain(pts, 0.01 * pts[:, 0], np.zeros(25), kind="small", window=3)
        >>> round(float(s["exx"][12]), 9)
        0.01
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    if (ut is None) != (vt is None):
        raise ValueError("give both ut and vt (velocity fields) or neither")
    as_numpy = not isinstance(u, torch.Tensor)
    ut_, vt_ = _as_tensor(u), _as_tensor(v)
    dev = ut_.device
    vt_ = vt_.to(dev)
    # torch.broadcast_shapes imports sympy on its first call (0.25 s of a run)
    uv = torch.stack(torch.broadcast_tensors(ut_, vt_), dim=-2)  # (..., 2, N)
    fit = _PlaneFit(window, method, min_points, require_center, None)
    gx, gy = _gradients(points, uv, valid, fit, stacked=True)
    ux, vx = gx[..., 0, :], gx[..., 1, :]
    uy, vy = gy[..., 0, :], gy[..., 1, :]
    out: dict[str, torch.Tensor] = {}
    if kind == "small":
        out["exx"], out["eyy"], out["exy"] = ux, vy, 0.5 * (uy + vx)
    else:
        out["exx"] = ux + 0.5 * (ux * ux + vx * vx)
        out["eyy"] = vy + 0.5 * (uy * uy + vy * vy)
        out["exy"] = 0.5 * (uy + vx + ux * uy + vx * vy)
    if return_gradients:
        out.update(ux=ux, uy=uy, vx=vx, vy=vy)
    if ut is not None:
        a, b = _as_tensor(ut, device=dev), _as_tensor(vt, device=dev)
        uvt = torch.stack(torch.broadcast_tensors(a, b), dim=-2)
        tx, ty = _gradients(points, uvt, valid, fit, stacked=True)
        utx, vtx = tx[..., 0, :], tx[..., 1, :]
        uty, vty = ty[..., 0, :], ty[..., 1, :]
        if kind == "small":
            out["exx_rate"], out["eyy_rate"] = utx, vty
            out["exy_rate"] = 0.5 * (uty + vtx)
        else:
            out["exx_rate"] = utx + ux * utx + vx * vtx
            out["eyy_rate"] = vty + uy * uty + vy * vty
            out["exy_rate"] = 0.5 * (uty + vtx + utx * uy + ux * uty + vtx * vy + vx * vty)
        if return_gradients:
            out.update(utx=utx, uty=uty, vtx=vtx, vty=vty)
    if as_numpy:
        return {k: val.detach().cpu().numpy() for k, val in out.items()}
    return out


def principal_strains(exx: Any, eyy: Any, exy: Any) -> tuple[Any, Any, Any]:
    """Principal strains ``(e1 >= e2)`` and the angle (radians, from +x towards +y, i.e. down)
    of ``e1``, from the tensor components (``exy`` = tensor shear, not engineering ``2 exy``).

    Works elementwise on numpy arrays or torch tensors of any (matching) shape.
    """
    lib = torch if isinstance(exx, torch.Tensor) else np
    c = 0.5 * (exx + eyy)
    r = lib.sqrt((0.5 * (exx - eyy)) ** 2 + exy**2)
    theta = 0.5 * lib.arctan2(2 * exy, exx - eyy)
    return c + r, c - r, theta
