"""Track a whole movie with STS-DIC: sliding 2m+1 windows, carried-forward guesses, batching.

For every target frame ``k`` the window ``k-m .. k+m`` (2m+1 frames) is solved against the
reference; the result refers to the time of frame ``k`` (``dt = t_j - t_k``, the paper's
Eqs. 1-10 with the expansion time at the target frame). At the ends of the series the
window is **shifted, not shrunk**: frames ``0 .. 2m`` for the first ``m`` targets (and the
last ``2m+1`` frames at the end), so every result averages the same number of frames.

Target frames are processed in time order, in fixed *blocks* of consecutive targets
(``batch_frames``). The first block is the first target alone, initialised by FFT
cross-correlation; every later block is initialised from the last row of the block before,
moved on by its velocity: ``u + ut (t_k - t_last)``, ``v + vt (t_k - t_last)``, gradients
carried (classical DIC, m = 0, uses the finite-difference velocity of the last two rows).
All POIs of all targets of a block go through **one** call of
:meth:`~torch_stsdic.solver.SubsetSolver.solve` (each row has its own frames and ``dt``).
Lost points (not converged, or ZNCC below ``lost_zncc``) are solved again with an FFT
initial guess, and the better of the two results is kept.

Frames are read lazily from the :class:`~torch_stsdic.io.ImageSeries`: only the frames of
the current block's windows are held (raw pixels and B-spline coefficients, each frame
prefiltered once while it is in use), so memory is bounded by ``batch_frames + 2m`` frames,
not by the movie length.

Determinism and resume: the carried state is always taken from the rows *as stored*
(float32, like the HDF5 file), and blocks are fixed by the target list and
``batch_frames``. A run resumed from a result file replays the finished blocks from the
file (carry, reference updates) and recomputes exactly the same pending blocks, so it ends
with the same numbers as an uninterrupted run.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from .config import DICConfig
from .interpolation import BSplineImage
from .io import (
    DEFAULT_FIELDS,
    ImageSeries,
    InputError,
    ResultWriter,
    load_series,
    parse_frame_spec,
)
from .solver import SubsetSolver, WindowSolution
from .status import Status
from .strain import compute_strain

__all__ = [
    "TrackResult",
    "track",
    "grid_points",
    "smooth_in_time",
    "temporal_smoothing",
    "classical_smoothed",
]

_OK = int(Status.MAX_ITER)  # status <= _OK: usable parameters
_BASE = ("u", "v", "ut", "vt")
_GRAD = ("ux", "uy", "vx", "vy")
_MAX_DEFAULT_BATCH = 8


# ---------------------------------------------------------------------------------------
# result
# ---------------------------------------------------------------------------------------
@dataclass
class TrackResult:
    """Displacement and velocity fields of a tracked movie.

    All displacements refer to the POIs ``points`` in the *first* reference image
    (Lagrangian), also after incremental reference updates.

    Attributes:
        points: (N, 2) POIs (x, y) in the reference image, px.
        frames: (F,) int64 target-frame indices into the series (ascending).
        times: (F,) float64 times of the target frames (series time unit).
        u, v: (F, N) displacement along x / y at the target frame's time, px.
        ut, vt: (F, N) velocity, px per time unit (NaN for classical DIC, m = 0).
        zncc: (F, N) zero-normalised cross-correlation (mean over the window's frames).
        status: (F, N) int8 :class:`~torch_stsdic.status.Status` codes.
        iterations: (F, N) int32 Gauss-Newton iterations (all stages, including a redo).
        gradients: name -> (F, N) displacement gradients ("ux", "uy", "vx", "vy"; with
            the quadratic shape also "uxx", ... relative to the current reference).
        reference_frames: (F,) int64 series index of the reference each row was measured
            against (-1: the initial reference was not a single frame).
        config: the :class:`DICConfig` used.
        info: run details: "batch_frames", "blocks", "frames_read", "prefiltered",
            "max_cached_frames", "fft_rows", "redone_rows", "reference_updates", ...
    """

    points: torch.Tensor
    frames: torch.Tensor
    times: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    ut: torch.Tensor
    vt: torch.Tensor
    zncc: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    gradients: dict[str, torch.Tensor]
    reference_frames: torch.Tensor
    config: DICConfig
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """F, the number of target frames."""
        return int(self.frames.shape[0])

    @property
    def n_points(self) -> int:
        """N, the number of POIs."""
        return int(self.points.shape[0])

    @property
    def ok(self) -> torch.Tensor:
        """(F, N) bool: usable results (CONVERGED or MAX_ITER)."""
        return self.status <= _OK

    def row_of(self, frame: int) -> int:
        """Row holding series frame ``frame``."""
        hit = torch.nonzero(self.frames == int(frame)).flatten()
        if hit.numel() == 0:
            raise KeyError(f"frame {frame} is not a target frame of this result")
        return int(hit[0])

    def strain(self, window: int = 5, kind: str = "green", **kwargs: Any) -> dict[str, Any]:
        """Strain fields (F, N) by local plane fits (:func:`~torch_stsdic.strain.
        compute_strain`): ``exx, eyy, exy`` (+ ``*_rate`` per time unit when velocities
        exist). ``window``: grid points per side of the fit; ``kind``: "green" or "small"."""
        has_rate = bool(torch.isfinite(self.ut).any())
        return compute_strain(
            self.points, self.u, self.v, window=window, kind=kind, valid=self.ok,
            ut=self.ut if has_rate else None, vt=self.vt if has_rate else None, **kwargs,
        )

    def __repr__(self) -> str:
        return (
            f"<TrackResult {self.n_frames} frames x {self.n_points} points, "
            f"m={self.config.m}, ok={float(self.ok.float().mean()):.1%}>"
        )


# ---------------------------------------------------------------------------------------
# points of interest
# ---------------------------------------------------------------------------------------
def _check_roi(roi: Any, shape: tuple[int, int]) -> tuple[float, float, float, float]:
    h, w = shape
    try:
        x0, y0, x1, y1 = (float(c) for c in roi)
    except (TypeError, ValueError):
        raise ValueError(f"roi: expected (x0, y0, x1, y1) in px, got {roi!r}") from None
    if not all(math.isfinite(c) for c in (x0, y0, x1, y1)) or x1 < x0 or y1 < y0:
        raise ValueError(f"roi: expected finite (x0, y0, x1, y1) with x0 <= x1, y0 <= y1, "
                         f"got {roi!r}")
    if x1 < 0 or y1 < 0 or x0 > w - 1 or y0 > h - 1:
        raise ValueError(
            f"roi {tuple(roi)} is off the image (x 0..{w - 1}, y 0..{h - 1} for {h}x{w} HxW)"
        )
    return x0, y0, x1, y1


def _load_mask(mask: Any, shape: tuple[int, int]) -> torch.Tensor:
    if isinstance(mask, (str, os.PathLike)):
        try:
            m = load_series(mask).numpy(0, np.float64)
        except (InputError, OSError) as exc:
            raise ValueError(f"mask: cannot read {mask}: {exc}") from exc
        arr = torch.from_numpy(m != 0)
    else:
        arr = torch.as_tensor(np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor)
                                         else mask))
        if arr.dim() == 3 and arr.shape[0] == 1:
            arr = arr[0]
        arr = arr != 0
    if tuple(arr.shape) != tuple(shape):
        raise ValueError(
            f"mask: shape {tuple(arr.shape)} does not match the images {tuple(shape)} (H, W)"
        )
    return arr


def grid_points(
    shape: tuple[int, int],
    step: int = 10,
    roi: Sequence[float] | None = None,
    mask: Any = None,
    subset_size: int = 21,
) -> torch.Tensor:
    """A regular grid of POIs (N, 2) float64 as (x, y) px.

    The grid has spacing ``step`` px, lies inside ``roi = (x0, y0, x1, y1)`` (inclusive,
    default the whole image) and keeps a margin of ``subset_size // 2`` px from the image
    border so that every subset fits; it is centred in the available range. ``mask``: (H, W)
    bool/number array or an image path; points where the mask is zero are dropped (only the
    POI itself is tested). Raises ValueError naming ``roi``, ``mask`` or ``step``.
    """
    h, w = int(shape[0]), int(shape[1])
    if not isinstance(step, (int, np.integer)) or step < 1:
        raise ValueError(f"step: must be an integer >= 1 (px), got {step!r}")
    half = subset_size // 2
    x0, y0, x1, y1 = (0.0, 0.0, w - 1.0, h - 1.0) if roi is None else _check_roi(roi, (h, w))
    lo_x, hi_x = math.ceil(max(x0, half)), math.floor(min(x1, w - 1 - half))
    lo_y, hi_y = math.ceil(max(y0, half)), math.floor(min(y1, h - 1 - half))
    if lo_x > hi_x or lo_y > hi_y:
        where = "the image" if roi is None else f"roi {tuple(roi)}"
        raise ValueError(
            f"no points inside {where}: a subset of {subset_size} px needs a margin of {half} "
            f"px from the {h}x{w} image border"
        )
    xs = torch.arange(lo_x + ((hi_x - lo_x) % step) // 2, hi_x + 1, step, dtype=torch.float64)
    ys = torch.arange(lo_y + ((hi_y - lo_y) % step) // 2, hi_y + 1, step, dtype=torch.float64)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1)], 1)
    if mask is not None:
        m = _load_mask(mask, (h, w))
        pts = pts[m[pts[:, 1].long(), pts[:, 0].long()]]
        if pts.shape[0] == 0:
            raise ValueError(f"no points inside roi/mask: the mask is zero at every grid point "
                             f"(step {step} px)")
    return pts


def _filter_points(points: Any, shape, roi, mask) -> torch.Tensor:
    """User POIs (N, 2), kept where inside ``roi`` and ``mask``."""
    pts = torch.as_tensor(np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor)
                                     else points, dtype=np.float64))
    if pts.dim() == 1 and pts.shape[0] == 2:
        pts = pts.unsqueeze(0)
    if pts.dim() != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
        raise ValueError(f"points: expected a non-empty (N, 2) array of (x, y), got shape "
                         f"{tuple(pts.shape)}")
    if not bool(torch.isfinite(pts).all()):
        raise ValueError("points: contains non-finite coordinates")
    h, w = shape
    keep = torch.ones(pts.shape[0], dtype=torch.bool)
    if roi is not None:
        x0, y0, x1, y1 = _check_roi(roi, shape)
        keep &= (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    if mask is not None:
        m = _load_mask(mask, shape)
        ix = pts[:, 0].round().long().clamp(0, w - 1)
        iy = pts[:, 1].round().long().clamp(0, h - 1)
        keep &= m[iy, ix]
    if not bool(keep.any()):
        raise ValueError("points: no point inside roi/mask")
    return pts[keep]


# ---------------------------------------------------------------------------------------
# frames
# ---------------------------------------------------------------------------------------
class _FrameCache:
    """Frames of the current block: raw pixels and prefiltered coefficients, by index.

    ``load`` keeps exactly the frames asked for (older ones are dropped), so a frame is read
    and prefiltered once while consecutive blocks overlap."""

    def __init__(self, series: ImageSeries, solver: SubsetSolver, dtype, device) -> None:
        self.series, self.solver = series, solver
        self.dtype, self.device = dtype, device
        self.raw: OrderedDict[int, torch.Tensor] = OrderedDict()
        self.prep: dict[int, BSplineImage] = {}
        self.reads = 0
        self.prefiltered = 0
        self.max_cached = 0

    def read(self, i: int) -> torch.Tensor:
        """(H, W) frame ``i`` from the cache or the series (counted)."""
        if i in self.raw:
            return self.raw[i]
        self.reads += 1
        return self.series.get(i, dtype=self.dtype).to(self.device)

    def load(self, idx: list[int]) -> tuple[torch.Tensor, BSplineImage]:
        """Frames ``idx``: raw (L, H, W) and a prepared L-frame stack."""
        keep = set(idx)
        for k in [k for k in self.raw if k not in keep]:
            del self.raw[k]
            del self.prep[k]
        for i in idx:
            if i not in self.raw:
                raw = self.read(i)
                self.raw[i] = raw
                self.prep[i] = self.solver.prepare(raw)
                self.prefiltered += 1
        self.max_cached = max(self.max_cached, len(self.raw))
        raw = torch.stack([self.raw[i] for i in idx])
        return raw, BSplineImage.stack([self.prep[i] for i in idx])


@dataclass
class _Reference:
    """Current reference: image, POI positions in it, and the displacement (total, to the
    first reference) of those positions (None before any update)."""

    frame: int  # series index, -1 for a mean/array reference
    raw: torch.Tensor | None  # (H, W), loaded lazily after a replayed update
    img: BSplineImage | None
    points: torch.Tensor  # (N, 2)
    acc: dict[str, torch.Tensor] | None = None  # u, v (+ ux, uy, vx, vy) (N,)

    def ensure(self, cache: _FrameCache) -> None:
        if self.raw is None:
            self.raw = cache.read(self.frame)
            self.img = cache.solver.prepare(self.raw)


@dataclass
class _Carry:
    """Last stored row (total quantities, float32-rounded) and the velocity to extrapolate."""

    t: float
    vals: dict[str, torch.Tensor]  # name -> (N,)
    vel_u: torch.Tensor
    vel_v: torch.Tensor
    valid: torch.Tensor  # (N,) bool

    def predict(self, tk: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted total parameters (B, N) at times ``tk`` (B,)."""
        d = (tk - self.t).unsqueeze(1)
        out = {k: v.unsqueeze(0).expand(tk.shape[0], -1) for k, v in self.vals.items()}
        out["u"] = self.vals["u"] + self.vel_u * d
        out["v"] = self.vals["v"] + self.vel_v * d
        return out


def _compose(g: dict[str, torch.Tensor], a: dict[str, torch.Tensor], inverse: bool):
    """Gradients: (I + G)(I + A) - I, or with ``inverse`` (I + G)(I + A)^-1 - I."""
    a11, a12, a21, a22 = 1.0 + a["ux"], a["uy"], a["vx"], 1.0 + a["vy"]
    if inverse:
        det = a11 * a22 - a12 * a21
        a11, a12, a21, a22 = a22 / det, -a12 / det, -a21 / det, a11 / det
    g11, g12, g21, g22 = 1.0 + g["ux"], g["uy"], g["vx"], 1.0 + g["vy"]
    return {
        "ux": g11 * a11 + g12 * a21 - 1.0, "uy": g11 * a12 + g12 * a22,
        "vx": g21 * a11 + g22 * a21, "vy": g21 * a12 + g22 * a22 - 1.0,
    }


def _to_relative(total: dict[str, torch.Tensor], acc) -> dict[str, torch.Tensor]:
    if acc is None:
        return total
    rel = dict(total)
    rel["u"] = total["u"] - acc["u"]
    rel["v"] = total["v"] - acc["v"]
    if all(k in total for k in _GRAD):
        rel.update(_compose(total, acc, inverse=True))
    return rel


def _to_total(rel: dict[str, torch.Tensor], acc) -> dict[str, torch.Tensor]:
    if acc is None:
        return rel
    tot = dict(rel)
    tot["u"] = rel["u"] + acc["u"]
    tot["v"] = rel["v"] + acc["v"]
    if all(k in rel for k in _GRAD):
        tot.update(_compose(rel, acc, inverse=False))
    return tot


def _idw_fill(vals: dict[str, torch.Tensor], valid: torch.Tensor, pts: torch.Tensor, k: int = 4):
    """Fill invalid entries of every (N,) field by inverse-distance weighting of the k
    nearest valid points (distances in the first reference)."""
    bad = ~valid
    if not bool(bad.any()):
        return vals
    src = torch.nonzero(valid).flatten()
    kk = min(k, src.numel())
    d = torch.cdist(pts[bad], pts[src])
    dist, nn = torch.topk(d, kk, dim=1, largest=False)
    wgt = 1.0 / dist.clamp(min=1e-9)
    wgt = wgt / wgt.sum(1, keepdim=True)
    out = {}
    for name, v in vals.items():
        filled = v.clone()
        filled[bad] = (v[src][nn] * wgt).sum(1)
        out[name] = filled
    return out


# ---------------------------------------------------------------------------------------
# the block solve
# ---------------------------------------------------------------------------------------
@dataclass
class _Run:
    solver: SubsetSolver
    cache: _FrameCache
    ts: torch.Tensor  # (T_s,) series times, float64
    n_series: int
    m: int
    dtype: torch.dtype
    device: torch.device
    lost_zncc: float
    names: tuple[str, ...]  # parameter names of the run's shape
    stats: dict[str, int]


def _solve_block(run: _Run, ks: list[int], ref: _Reference, carry: _Carry | None):
    """Solve all POIs of target frames ``ks`` (B,) in one batched solve.

    Returns a dict of (B, N) tensors: total parameters by name, "zncc", "status",
    "iterations"."""
    solver, dev = run.solver, run.device
    n_win = 2 * run.m + 1
    k = torch.tensor(ks, dtype=torch.long, device=dev)
    start = (k - run.m).clamp(0, run.n_series - n_win)  # shifted (not shrunk) at the ends
    win = start.unsqueeze(1) + torch.arange(n_win, device=dev)  # (B, T)
    needed = torch.unique(win)  # sorted; only the windows' frames (sparse targets: gaps)
    raw, img = run.cache.load(needed.tolist())
    ref.ensure(run.cache)
    b, n = len(ks), ref.points.shape[0]
    pts = ref.points.repeat(b, 1)  # (B*N, 2), row = target * N + point
    fidx = torch.searchsorted(needed, win).repeat_interleave(n, 0)
    dt = (run.ts[win] - run.ts[k].unsqueeze(1)).to(run.dtype).repeat_interleave(n, 0)
    names = run.names
    p_count = len(names)
    rows = b * n
    params = torch.full((rows, p_count), float("nan"), dtype=run.dtype, device=dev)
    zncc = torch.full((rows,), float("nan"), dtype=run.dtype, device=dev)
    status = torch.full((rows,), int(Status.NOT_COMPUTED), dtype=torch.int8, device=dev)
    iters = torch.zeros(rows, dtype=torch.int32, device=dev)
    ref_pix = ref.raw.unsqueeze(0)

    def solve(idx: torch.Tensor, init: torch.Tensor | None) -> WindowSolution:
        return solver.solve(
            ref.img, img, pts[idx], dt[idx], frame_index=fidx[idx], init=init,
            ref_pixels=ref_pix, frame_pixels=raw,
        )

    def put(idx: torch.Tensor, sol: WindowSolution) -> None:
        params[idx] = sol.params.to(run.dtype)
        zncc[idx] = sol.zncc.to(run.dtype)
        status[idx] = sol.status
        iters[idx] += sol.iterations

    if carry is None:
        carried = torch.zeros(rows, dtype=torch.bool, device=dev)
    else:
        pred = _to_relative(carry.predict(run.ts[k].to(run.dtype)), ref.acc)
        init = torch.stack(
            [pred[nm].reshape(-1) if nm in pred else torch.zeros(rows, dtype=run.dtype,
                                                                 device=dev) for nm in names],
            1,
        )
        carried = carry.valid.repeat(b) & torch.isfinite(init).all(1)
    idx_c = torch.nonzero(carried).flatten()
    redo = idx_c[:0]
    if idx_c.numel():
        sol = solve(idx_c, init[idx_c])
        put(idx_c, sol)
        st = sol.status
        lost = (
            (st == int(Status.MAX_ITER)) | (st == int(Status.DIVERGED))
            | (st == int(Status.OUTSIDE))
            | ((st <= _OK) & ~(sol.zncc >= run.lost_zncc))
        )
        redo = idx_c[lost]
    idx_f = torch.cat([torch.nonzero(~carried).flatten(), redo])
    if idx_f.numel():
        sol = solve(idx_f, None)
        nf = int((~carried).sum())
        first = idx_f[:nf]
        params[first] = sol.params[:nf].to(run.dtype)
        zncc[first] = sol.zncc[:nf].to(run.dtype)
        status[first] = sol.status[:nf]
        iters[first] += sol.iterations[:nf]
        if redo.numel():
            new_ok = sol.status[nf:] <= _OK
            old_ok = status[redo] <= _OK
            better = new_ok & (~old_ok | (sol.zncc[nf:].to(run.dtype) > zncc[redo]))
            iters[redo] += sol.iterations[nf:]
            r = redo[better]
            params[r] = sol.params[nf:][better].to(run.dtype)
            zncc[r] = sol.zncc[nf:][better].to(run.dtype)
            status[r] = sol.status[nf:][better]
    run.stats["fft_rows"] += int(idx_f.numel())
    run.stats["redone_rows"] += int(redo.numel())
    rel = {nm: params[:, j].reshape(b, n) for j, nm in enumerate(names)}
    out = _to_total(rel, ref.acc)
    out["zncc"] = zncc.reshape(b, n)
    out["status"] = status.reshape(b, n)
    out["iterations"] = iters.reshape(b, n)
    return out


def _rows_numpy(block: dict[str, torch.Tensor], fields: Sequence[str]) -> dict[str, np.ndarray]:
    """(B, N) numpy rows per field (float64; ut/vt NaN when absent)."""
    b, n = block["status"].shape
    out = {}
    for nm in fields:
        if nm in block:
            out[nm] = block[nm].detach().cpu().numpy()
        else:
            out[nm] = np.full((b, n), np.nan)
    out["status"] = out["status"].astype(np.int8)
    out["iterations"] = out["iterations"].astype(np.int64)
    return out


def _stored(rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows rounded as the result file stores them (float32, int8, int16)."""
    out = {}
    for nm, a in rows.items():
        if nm == "status":
            out[nm] = a.astype(np.int8)
        elif nm == "iterations":
            out[nm] = np.clip(a, -1, np.iinfo(np.int16).max).astype(np.int16)
        else:
            out[nm] = a.astype(np.float32)
    return out


def _make_carry(rows: dict[str, np.ndarray], times: np.ndarray, names, prev: _Carry | None,
                dtype, device) -> _Carry:
    """Carry from the last stored row (velocity from ut/vt, else from the last two rows)."""

    def col(nm: str, i: int = -1) -> torch.Tensor:
        return torch.from_numpy(rows[nm][i].astype(np.float64)).to(device=device, dtype=dtype)

    vals = {nm: col(nm) for nm in names}
    ok = torch.from_numpy(rows["status"][-1] <= _OK).to(device)
    ok &= torch.isfinite(vals["u"]) & torch.isfinite(vals["v"])
    t_last = float(times[-1])
    if "ut" in names:
        vel_u, vel_v = vals["ut"], vals["vt"]
        ok &= torch.isfinite(vel_u) & torch.isfinite(vel_v)
    else:
        if len(times) >= 2:
            t_prev, u_prev, v_prev = float(times[-2]), col("u", -2), col("v", -2)
        elif prev is not None:
            t_prev, u_prev, v_prev = prev.t, prev.vals["u"], prev.vals["v"]
        else:
            t_prev, u_prev, v_prev = t_last, vals["u"], vals["v"]
        span = t_last - t_prev
        if span > 0:
            vel_u, vel_v = (vals["u"] - u_prev) / span, (vals["v"] - v_prev) / span
            fin = torch.isfinite(vel_u) & torch.isfinite(vel_v)
            vel_u = torch.where(fin, vel_u, torch.zeros_like(vel_u))
            vel_v = torch.where(fin, vel_v, torch.zeros_like(vel_v))
        else:
            vel_u, vel_v = torch.zeros_like(vals["u"]), torch.zeros_like(vals["v"])
    return _Carry(t=t_last, vals=vals, vel_u=vel_u, vel_v=vel_v, valid=ok)


# ---------------------------------------------------------------------------------------
# argument handling
# ---------------------------------------------------------------------------------------
def _resolve_reference(reference: Any, series: ImageSeries, dtype, device):
    """(raw (H, W), frame index or -1, description for the config)."""
    n = len(series)
    if isinstance(reference, (np.ndarray, torch.Tensor)) and np.ndim(reference) >= 2:
        arr = torch.as_tensor(np.asarray(reference.detach().cpu() if isinstance(
            reference, torch.Tensor) else reference)).to(dtype)
        if arr.dim() == 3 and arr.shape[0] == 1:
            arr = arr[0]
        if tuple(arr.shape) != tuple(series.shape):
            raise ValueError(f"reference: image shape {tuple(arr.shape)} differs from the "
                             f"series {tuple(series.shape)} (H, W)")
        if not bool(torch.isfinite(arr).all()):
            raise ValueError("reference: contains non-finite pixels")
        digest = hashlib.sha1(arr.to(torch.float64).numpy().tobytes()).hexdigest()[:16]
        return arr.to(device), -1, f"array:{digest}"
    if isinstance(reference, (int, np.integer)) and not isinstance(reference, bool):
        i = int(reference)
        if not -n <= i < n:
            raise ValueError(f"reference: frame index {i} out of range for {n} frames")
        return None, i % n, i % n
    try:
        if isinstance(reference, str):
            idx = parse_frame_spec(reference, n)
        else:
            idx = series.resolve(list(reference))
    except (InputError, IndexError, TypeError, ValueError) as exc:
        raise ValueError(f"reference: {exc}") from None
    if len(idx) == 1:
        return None, idx[0], idx[0]
    raw = series.mean_of(idx, dtype=torch.float64).to(device=device, dtype=dtype)
    return raw, -1, f"mean:{','.join(map(str, idx))}"


def _resolve_frames(frames: Any, n: int) -> list[int]:
    if frames is None:
        return list(range(n))
    try:
        if isinstance(frames, (str, int, np.integer)):
            idx = parse_frame_spec(frames, n)
        else:
            vals = np.asarray(frames.detach().cpu() if isinstance(frames, torch.Tensor)
                              else list(frames))
            if vals.ndim != 1 or vals.size == 0 or vals.dtype.kind not in "iu":
                raise ValueError(f"expected a non-empty list of frame indices, got {frames!r}")
            bad = [int(i) for i in vals if not -n <= int(i) < n]
            if bad:
                raise ValueError(f"indices {bad} out of range for {n} frames")
            idx = [int(i) % n for i in vals]
    except (InputError, ValueError, TypeError) as exc:
        raise ValueError(f"frames: {exc}") from None
    return sorted(set(idx))


def _resolve_times(times: Any, series: ImageSeries) -> np.ndarray:
    n = len(series)
    if times is None:
        return series.times.astype(np.float64)
    t = np.asarray(times.detach().cpu() if isinstance(times, torch.Tensor) else times,
                   dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"times: expected {n} values (one per series frame), got {t.shape[0]}")
    if not np.isfinite(t).all() or (n > 1 and not (np.diff(t) > 0).all()):
        raise ValueError("times: must be finite and strictly increasing")
    return t


def _default_batch(cfg: DICConfig, shape: tuple[int, int], elem: int) -> int:
    """Target frames per block: the frames of a block (raw + padded coefficients, ~3 copies)
    within half of ``memory_mb`` (the other half bounds the solver's batches), at most 8
    (the carried guess is extrapolated over the block, so very long blocks start further
    from the solution)."""
    frame_bytes = 3.0 * shape[0] * shape[1] * elem
    fit = int(cfg.memory_mb * 2**20 / (2.0 * frame_bytes)) - 2 * cfg.m
    return max(1, min(_MAX_DEFAULT_BATCH, fit))


# ---------------------------------------------------------------------------------------
# track
# ---------------------------------------------------------------------------------------
def track(
    series: Any,
    reference: Any = 0,
    frames: Any = None,
    points: Any = None,
    roi: Sequence[float] | None = None,
    mask: Any = None,
    step: int = 10,
    config: DICConfig | None = None,
    device: str | torch.device = "cpu",
    times: Any = None,
    progress: bool = True,
    out: str | os.PathLike[str] | None = None,
    resume: bool = False,
    batch_frames: int | None = None,
    reference_update: float | None = None,
    smoothing: int | None = None,
    *,
    lost_zncc: float = 0.8,
    overwrite: bool = False,
    callback: Callable[[int, int], None] | None = None,
) -> TrackResult:
    """Track POIs through a movie with STS-DIC (sliding windows of 2m+1 frames).

    Args:
        series: anything :func:`~torch_stsdic.io.load_series` accepts (TIFF stack, directory,
            glob, list of files, (T, H, W) array/tensor) or an ImageSeries; read lazily.
        reference: frame index (int), a frame spec / list ("0:5", [0, 1, 2]) whose pixel-wise
            MEAN is the reference (less reference noise), or an (H, W) image.
        frames: target frames (spec string, int or list; default all frames of the series,
            the reference frame included). Sorted ascending; one result row each.
        points: (N, 2) POIs (x, y) px; default a grid of spacing ``step`` px inside ``roi``
            and ``mask`` (see :func:`grid_points`). Given points are filtered by roi/mask.
        roi: (x0, y0, x1, y1) px, inclusive. mask: (H, W) array or image path, 0 = drop.
        step: grid spacing, px.
        config: :class:`DICConfig` (default DICConfig()); ``config.m`` sets the window.
        device: torch device of the computation.
        times: (T,) time of every series frame (uneven frame rates); default the series'
            timestamps, else frame indices. Velocities are px per this time unit.
        progress: tqdm progress bar on stderr (frames/s, ETA).
        out: HDF5 result path, written block by block (:class:`~torch_stsdic.io.
            ResultWriter`; fields u, v, ut, vt, zncc, status, iterations, ux, uy, vx, vy).
        resume: continue the run recorded in ``out`` (same settings); the result equals
            an uninterrupted run. overwrite: replace an existing ``out``.
        batch_frames: target frames solved together per block (default from
            ``config.memory_mb``, at most 8).
        reference_update: ZNCC threshold in (0, 1): when the mean ZNCC of a block's last
            frame drops below it, that frame becomes the new reference (see docs).
        smoothing: odd span (frames): run classical DIC (config.m = 0) and smooth u, v in
            time with :func:`smooth_in_time` (the paper's "direct smoothing" baseline).
        lost_zncc: points whose ZNCC falls below this are re-solved with an FFT guess.
        callback: called as ``callback(rows_done, n_rows)`` after each block.

    Returns:
        :class:`TrackResult` with (F, N) fields. With ``out`` the values are those stored in
        the file (float32 precision), so a resumed run returns the same numbers.

    Raises:
        ValueError naming the argument: ROI off the image, subset larger than the image,
        fewer frames than 2m+1, mask of the wrong shape, no points inside ROI/mask,
        reference index out of range, bad times/frames/batch_frames/reference_update.
    """
    cfg = config if config is not None else DICConfig()
    if not isinstance(cfg, DICConfig):
        raise TypeError(f"config: expected a DICConfig, got {type(cfg).__name__}")
    if smoothing is not None:
        if not isinstance(smoothing, (int, np.integer)) or smoothing < 1 or smoothing % 2 == 0:
            raise ValueError(f"smoothing: span must be an odd integer >= 1, got {smoothing!r}")
        cfg = cfg.replace(m=0)
    if reference_update is not None and not 0.0 < float(reference_update) < 1.0:
        raise ValueError(f"reference_update: ZNCC threshold must be in (0, 1), got "
                         f"{reference_update!r}")
    if batch_frames is not None and (not isinstance(batch_frames, (int, np.integer))
                                     or batch_frames < 1):
        raise ValueError(f"batch_frames: must be an integer >= 1, got {batch_frames!r}")
    if resume and out is None:
        raise ValueError("resume: needs out (the result file to continue)")
    if isinstance(series, ImageSeries):
        ser = series
    else:
        try:
            ser = load_series(series)
        except InputError as exc:
            raise InputError(f"series: {exc}") from exc
    h, w = ser.shape
    n_series = len(ser)
    if cfg.subset_size > min(h, w):
        raise ValueError(f"config.subset_size: {cfg.subset_size} px is larger than the image "
                         f"({h}x{w} HxW)")
    n_win = cfg.n_frames
    if n_series < n_win:
        raise ValueError(f"series: {n_series} frames, fewer than the 2m+1 = {n_win} frames of "
                         f"one window (config.m = {cfg.m})")
    ts_np = _resolve_times(times, ser)
    targets = _resolve_frames(frames, n_series)
    if smoothing is not None and smoothing > len(targets):
        raise ValueError(f"smoothing: span {smoothing} is longer than the {len(targets)} "
                         "target frames")
    dev = torch.device(device)
    if cfg.dtype is not None:
        dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    else:
        dtype = torch.float64 if ser.dtype_name == "float64" else torch.float32
    ref_raw, ref_frame, ref_desc = _resolve_reference(reference, ser, dtype, dev)
    if points is None:
        pts0 = grid_points((h, w), step, roi, mask, cfg.subset_size)
    else:
        pts0 = _filter_points(points, (h, w), roi, mask)
    pts0 = pts0.to(device=dev, dtype=dtype)
    n_pts = pts0.shape[0]
    elem = torch.finfo(dtype).bits // 8
    n_batch = int(batch_frames) if batch_frames is not None else _default_batch(cfg, (h, w),
                                                                                elem)
    blocks = [targets[:1]] + [targets[i : i + n_batch] for i in range(1, len(targets), n_batch)]
    blocks = [b for b in blocks if b]

    solver = SubsetSolver(cfg)
    ts = torch.from_numpy(ts_np).to(device=dev, dtype=torch.float64)
    names = solver.shape_for(torch.ones(1, n_win) if n_win > 1 else torch.zeros(1, 1)
                             ).param_names
    grads = tuple(nm for nm in names if nm not in _BASE)
    fields = (*DEFAULT_FIELDS, "iterations", *grads)
    cache = _FrameCache(ser, solver, dtype, dev)
    run = _Run(solver=solver, cache=cache, ts=ts, n_series=n_series, m=cfg.m, dtype=dtype,
               device=dev, lost_zncc=float(lost_zncc), names=names,
               stats={"fft_rows": 0, "redone_rows": 0})
    if ref_raw is None:
        ref_raw = cache.read(ref_frame)
    ref = _Reference(frame=ref_frame, raw=ref_raw, img=solver.prepare(ref_raw), points=pts0)
    row_of = {k: r for r, k in enumerate(targets)}
    n_rows = len(targets)
    res_np = {nm: np.full((n_rows, n_pts), np.nan) for nm in fields}
    res_np["status"] = np.full((n_rows, n_pts), int(Status.NOT_COMPUTED), dtype=np.int8)
    res_np["iterations"] = np.zeros((n_rows, n_pts), dtype=np.int64)
    ref_rows = np.full(n_rows, ref_frame, dtype=np.int64)
    updates: list[dict[str, Any]] = []

    writer = None
    if out is not None:
        track_cfg = {
            "reference": ref_desc, "step": int(step), "roi": None if roi is None else list(roi),
            "batch_frames": n_batch, "reference_update": reference_update,
            "lost_zncc": float(lost_zncc), "smoothing": smoothing, "points": n_pts,
        }
        writer = ResultWriter(
            out, points=pts0.cpu().double(), frames=np.asarray(targets, dtype=np.int64),
            times=ts_np[targets], config={**cfg.to_dict(), "track": track_cfg},
            inputs=ser.sources, fields=fields,
            extra_fields=tuple(f"{nm}_smooth" for nm in _BASE) if smoothing else (),
            resume=resume, overwrite=overwrite,
        )
    done = set(writer.completed_rows().tolist()) if writer is not None else set()
    bar = tqdm(total=n_rows, unit="frame", file=sys.stderr, disable=not progress,
               desc="STS-DIC" if cfg.m else "DIC", dynamic_ncols=True)
    carry: _Carry | None = None
    rows_done = 0
    try:
        for block in blocks:
            rs = [row_of[k] for k in block]
            if writer is not None and all(r in done for r in rs):
                f = writer._h5()  # replay a finished block from the file
                stored = {nm: f[nm][rs[0] : rs[-1] + 1] for nm in fields}
                full = None
            else:
                res = _solve_block(run, block, ref, carry)
                full = _rows_numpy(res, fields)
                stored = _stored(full)
                if writer is not None:
                    writer.write_rows(np.asarray(rs), stored)
            keep = stored if (writer is not None or full is None) else full
            for nm in fields:
                res_np[nm][rs] = keep[nm]
            ref_rows[rs] = ref.frame
            carry = _make_carry(stored, ts_np[block], names, carry, dtype, dev)
            if reference_update is not None:
                ref = _maybe_update(ref, stored, block[-1], float(reference_update), pts0,
                                    names, cache, dtype, dev, updates, rs[-1])
            rows_done += len(block)
            bar.update(len(block))
            if callback is not None:
                callback(rows_done, n_rows)
        if smoothing is not None:
            t_rows = ts_np[targets]
            su, sut = smooth_in_time(res_np["u"], smoothing, t_rows, return_rate=True)
            sv, svt = smooth_in_time(res_np["v"], smoothing, t_rows, return_rate=True)
            raw_uv = {"u": res_np["u"].copy(), "v": res_np["v"].copy()}
            res_np["u"], res_np["v"], res_np["ut"], res_np["vt"] = su, sv, sut, svt
            if writer is not None:
                writer.write_rows(
                    np.arange(n_rows),
                    {f"{nm}_smooth": res_np[nm].astype(np.float32) for nm in _BASE},
                    mark_completed=False,
                )
                for nm in _BASE:
                    res_np[nm] = res_np[nm].astype(np.float32).astype(np.float64)
    except BaseException:
        bar.close()
        if writer is not None:
            writer.close(commit=False)
        raise
    bar.close()
    if writer is not None:
        writer.close()

    def ft(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.asarray(a, dtype=np.float64)).to(device=dev, dtype=dtype)

    info: dict[str, Any] = {
        "batch_frames": n_batch, "blocks": len(blocks), "frames_read": cache.reads,
        "prefiltered": cache.prefiltered, "max_cached_frames": cache.max_cached,
        "reference": ref_desc, "reference_updates": updates, **run.stats,
    }
    if smoothing is not None:
        info["smoothing"] = smoothing
        info["raw"] = {k: ft(v) for k, v in raw_uv.items()}
    if out is not None:
        info["out"] = str(out)
    return TrackResult(
        points=pts0, frames=torch.tensor(targets, dtype=torch.long),
        times=torch.from_numpy(ts_np[targets].copy()),
        u=ft(res_np["u"]), v=ft(res_np["v"]), ut=ft(res_np["ut"]), vt=ft(res_np["vt"]),
        zncc=ft(res_np["zncc"]), status=torch.from_numpy(res_np["status"].astype(np.int8)),
        iterations=torch.from_numpy(res_np["iterations"].astype(np.int32)),
        gradients={nm: ft(res_np[nm]) for nm in grads},
        reference_frames=torch.from_numpy(ref_rows), config=cfg, info=info,
    )


def _maybe_update(ref: _Reference, stored: dict[str, np.ndarray], frame: int, thr: float,
                  pts0: torch.Tensor, names, cache: _FrameCache, dtype, dev,
                  updates: list, row: int) -> _Reference:
    """Incremental reference update after a block (decided from the stored rows only)."""
    ok = stored["status"][-1] <= _OK
    z = stored["zncc"][-1][ok]
    if frame == ref.frame or z.size == 0 or not float(z.mean()) < thr:
        return ref
    acc_names = [nm for nm in ("u", "v", *_GRAD) if nm in names]
    acc = {nm: torch.from_numpy(stored[nm][-1].astype(np.float64)).to(device=dev, dtype=dtype)
           for nm in acc_names}
    valid = torch.from_numpy(ok).to(dev)
    for a in acc.values():
        valid &= torch.isfinite(a)
    if not bool(valid.any()):
        return ref
    acc = _idw_fill(acc, valid, pts0)
    updates.append({"frame": int(frame), "row": int(row), "mean_zncc": float(z.mean()),
                    "interpolated_points": int((~valid).sum())})
    raw = cache.raw.get(frame)
    return _Reference(
        frame=int(frame), raw=raw, img=cache.prep.get(frame) if raw is not None else None,
        points=pts0 + torch.stack([acc["u"], acc["v"]], 1), acc=acc,
    )


# ---------------------------------------------------------------------------------------
# the "direct smoothing" baseline
# ---------------------------------------------------------------------------------------
def smooth_in_time(
    values: Any,
    span: int,
    times: Any = None,
    *,
    fit: str = "linear",
    return_rate: bool = False,
):
    """Smooth every column of ``values`` (F, N) over a centred moving window of ``span`` rows.

    Each output row ``f`` is the value at ``t_f`` of a least-squares fit to the rows of its
    window (``fit="linear"``: a straight line, which leaves linear motion unbiased, as the
    STS-DIC window does; ``"mean"``: the moving average). The window is shifted, not shrunk,
    at the ends (rows 0..span-1 for the first ones), like the STS-DIC window. NaN values are
    left out of the fits (one valid value: that value; none: NaN).

    Args:
        values: (F, N) array or tensor (e.g. u of classical DIC), px.
        span: odd window length in rows (the paper's Fig. 6 uses 5).
        times: (F,) row times (default 0..F-1).
        return_rate: also return the fitted slope (F, N) (px per time unit; NaN for "mean").

    Returns:
        (F, N) smoothed values (numpy in -> numpy out, torch in -> torch out), and the slope
        if ``return_rate``.
    """
    as_np = not isinstance(values, torch.Tensor)
    y = torch.as_tensor(np.asarray(values, dtype=np.float64)) if as_np else values
    work = y.to(torch.float64)
    squeeze = work.dim() == 1
    if squeeze:
        work = work.unsqueeze(1)
    if work.dim() != 2:
        raise ValueError(f"values: expected shape (F, N), got {tuple(y.shape)}")
    n_f = work.shape[0]
    if not isinstance(span, (int, np.integer)) or span < 1 or span % 2 == 0 or span > n_f:
        raise ValueError(f"span: must be an odd integer in 1..{n_f} (rows), got {span!r}")
    if fit not in ("linear", "mean"):
        raise ValueError(f"fit: must be 'linear' or 'mean', got {fit!r}")
    dev = work.device
    if times is None:
        t = torch.arange(n_f, dtype=torch.float64, device=dev)
    else:
        t = torch.as_tensor(np.asarray(times.detach().cpu() if isinstance(times, torch.Tensor)
                                       else times, dtype=np.float64)).to(dev).reshape(-1)
        if t.shape[0] != n_f:
            raise ValueError(f"times: expected {n_f} values, got {t.shape[0]}")
    start = (torch.arange(n_f, device=dev) - span // 2).clamp(0, n_f - span)
    idx = start.unsqueeze(1) + torch.arange(span, device=dev)  # (F, span)
    yy = work[idx]  # (F, span, N)
    tc = (t[idx] - t.unsqueeze(1)).unsqueeze(-1)  # (F, span, 1)
    wgt = torch.isfinite(yy).to(torch.float64)
    y0 = torch.where(wgt > 0, yy, torch.zeros_like(yy))
    s0 = wgt.sum(1)
    sy = y0.sum(1)
    mean = sy / s0.clamp(min=1.0)
    if fit == "linear":
        s1, s2 = (wgt * tc).sum(1), (wgt * tc * tc).sum(1)
        sty = (tc * y0).sum(1)
        det = s0 * s2 - s1 * s1
        lin = det > 1e-12 * (s0 * s2).clamp(min=1e-300)
        dsafe = torch.where(lin, det, torch.ones_like(det))
        val = torch.where(lin, (s2 * sy - s1 * sty) / dsafe, mean)
        rate = torch.where(lin, (s0 * sty - s1 * sy) / dsafe, torch.full_like(det, math.nan))
    else:
        val, rate = mean, torch.full_like(mean, math.nan)
    nan = torch.full_like(val, math.nan)
    val = torch.where(s0 > 0, val, nan)
    if squeeze:
        val, rate = val[:, 0], rate[:, 0]
    if as_np:
        val_o, rate_o = val.numpy(), rate.numpy()
    else:
        val_o, rate_o = val.to(y.dtype if y.is_floating_point() else torch.float64), rate
    return (val_o, rate_o) if return_rate else val_o


def temporal_smoothing(res: TrackResult, span: int = 5, *, fit: str = "linear") -> TrackResult:
    """The paper's "direct smoothing" (Fig. 6): smooth each POI's u, v of a (classical, m = 0)
    result over ``span`` frames (:func:`smooth_in_time`, local linear fit by default, in the
    result's time). ut, vt become the fitted slopes when the input has no velocities,
    otherwise they are smoothed the same way. Returns a new :class:`TrackResult`."""
    t = res.times
    u, ut = smooth_in_time(res.u, span, t, fit=fit, return_rate=True)
    v, vt = smooth_in_time(res.v, span, t, fit=fit, return_rate=True)
    if bool(torch.isfinite(res.ut).any()):
        ut = smooth_in_time(res.ut, span, t, fit=fit)
        vt = smooth_in_time(res.vt, span, t, fit=fit)
    return replace(res, u=u, v=v, ut=ut.to(res.u.dtype), vt=vt.to(res.u.dtype),
                   info={**res.info, "smoothing": span, "raw": {"u": res.u, "v": res.v}})


def classical_smoothed(series: Any, span: int = 5, **kwargs: Any) -> TrackResult:
    """Classical DIC (m = 0) of ``series`` smoothed in time over ``span`` frames: shorthand
    for ``track(series, smoothing=span, **kwargs)``."""
    return track(series, smoothing=span, **kwargs)
