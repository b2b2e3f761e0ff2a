"""Shared motion: the per-frame affine motion of the whole specimen, carried as a known term in
every window.

Real movies are not smooth in time the way a render is: the specimen (or the camera) shakes
as a whole by a fraction of a pixel from frame to frame, and machines move in load steps. A
window of 2m+1 frames with a displacement affine in time cannot describe such a jitter, so the
model check rejects it and the point falls back to classical DIC. But the jitter is the *same*
motion for every point: a rigid (or affine) motion of the whole field of view per frame. It is
measured once, from all points together, and carried as a known term:

    U(x, t) = G_t(x) + D(x, t),     G_t(x) = a_t + B_t (x - x0)

``G_t`` (6 numbers per frame: translation ``a_t`` and the 2x2 gradient ``B_t``) is fitted
robustly (Huber IRLS) to the classical displacements of a sample of points at every frame
(:func:`~torch_stsdic.movie.shared_pass.estimate_shared_motion`: one classical pass over the
frames at up to ``max_points`` POIs), so outliers, lost points and background move it by
at most a bounded share. ``D``, the deformation, is what the STS window has to describe;
it is smooth in time even where ``G`` jitters. In a window of target frame ``k``, the known
part of frame ``t`` is the jitter of ``G`` about its own line through the window
(:func:`window_offsets`):

    o_t(x_i) = G_t(x_i) - G_k(x_i) - beta_i (t - t_k)      (beta_i: the window's LS slope of G)

added to the warp of frame ``t`` (``SubsetSolver.solve(..., motion=)``), so the window's
parameters keep their meaning (u, v: the total displacement at the target frame; ut, vt: the
smooth velocity) and a window where ``G`` moves affinely in time is solved exactly as without
it (o = 0). Within a subset only the translation of ``o`` at the POI is carried: the jitter's
own rotation moves a subset's edge by ``|B_t - line| * half`` (1e-3 rad: 0.01 px at 10 px),
a zero-mean misfit that the window's gradients cannot absorb but that does not bias u, v.

The estimate's own error is the classical noise over the sample, ``sigma_c * sqrt(3 / n)`` for
n points (0.05 sigma_c at 1,000 independent points), far below the window's error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torch_stsdic.core.shared_fit import SHARED_MOTION_KINDS, fit_frame_motion, frame_chunks

__all__ = ["SharedMotion", "SHARED_MOTION_KINDS", "PARAM_NAMES", "PARAM_UNITS",
           "fit_frame_motion", "window_offsets", "window_slope", "known_window_motion",
           "overlap_factor",
           "sample_points", "frame_chunks",
           "detect_steps", "step_increments", "steps_from_increments",
           "carried_note", "DEFAULT_MAX_POINTS", "SIGNIFICANT", "DEPARTURE", "VELOCITY_M",
           "SMOOTH_H",
           "SMOOTH_LIMIT", "STEP_Z", "STEP_RATIO", "SE_FLOOR"]

#: the columns of ``SharedMotion.params`` (px, px/px, px/px^2): u = a_x + du/dx dx + du/dy dy
#: + d2u/dx2 dx^2 / 2 + d2u/dxdy dx dy + d2u/dy2 dy^2 / 2 (dx, dy from the origin), v alike
PARAM_NAMES = ("a_x", "a_y", "du/dx", "du/dy", "dv/dx", "dv/dy", "d2u/dx2", "d2u/dxdy",
               "d2u/dy2", "d2v/dx2", "d2v/dxdy", "d2v/dy2")
PARAM_UNITS = ("px", "px", "px/px", "px/px", "px/px", "px/px", "px/px^2", "px/px^2",
               "px/px^2", "px/px^2", "px/px^2", "px/px^2")
#: POIs of the classical pass that measures the shared motion
DEFAULT_MAX_POINTS = 1000
#: "auto" applies the shared motion where its significance (jitter variance over estimation
#: variance) exceeds this: a jitter of 5 times the estimate's standard error. (A motion
#: affine in time gives ~1, and up to ~6 where the sub-pixel interpolation bias, the same at
#: every point of a uniform translation, moves the estimate; a real shake gives 10^3-10^5.)
SIGNIFICANT = 25.0
#: "auto" also applies it where its departure from a line over the run's windows
#: (:meth:`SharedMotion.departure`: the offsets the windows would carry, over the noise that
#: carrying them adds) exceeds this: a motion that is smooth but not affine in time (a
#: relaxing stretch, a decelerating drift, load steps of a uniform strain) that the windows'
#: lines would miss. Renders affine in time read 0.2-0.3, DIC Challenge sample 3 0.24
#: (carried, its estimate's sub-pixel bias would go into every window: 0.237x -> 0.34x);
#: a relaxing stretch 2.35, uniform load steps 12, a vibration of 0.03 px 29
#: (docs/validation/window_length.md)
DEPARTURE = 1.5
#: the half-width of the frames whose slope of the shared motion a reported velocity holds
#: where it is carried for its departure alone (SharedMotion.velocity_m; a relaxing
#: stretch's velocity error 2.31e-3 px per frame with the windows' own slopes, 0.87e-3 with
#: five frames', 1.23e-3 with three, 1.14e-3 with seven)
VELOCITY_M = 2
#: a shared motion carried for its departure alone is smoothed in time
#: (:meth:`SharedMotion.smooth`): at each frame the value of a quadratic in time over the
#: 2 SMOOTH_H + 1 frames about it, where that quadratic fits its displacement at the sample
#: points within SMOOTH_LIMIT times the noise (not across a jump: a load step of a uniform
#: strain keeps its frames as measured). Each window carries the motion's estimate at its
#: target, whose noise is common to every point of the frame: the relaxing stretch 0.368x ->
#: 0.356x classical DIC, six draws' mean 0.332x -> 0.318x (docs/validation/window_length.md)
SMOOTH_H = 3
SMOOTH_LIMIT = 2.0
#: load-step detection (:func:`detect_steps`): an increment above STEP_Z times its noise and
#: STEP_RATIO times the median increment of the frames around it starts a new load state
STEP_Z = 2.0
#: px added in quadrature to the shared motion's standard error in its significance: what
#: the noise model leaves out (the sub-pixel interpolation bias, the same at every point of a
#: uniform motion, ~1e-3 px); so noise-free images, whose noise is ~0, need a shake of
#: 5 x 0.002 = 0.01 px before it is carried
SE_FLOOR = 0.002
STEP_RATIO = 2.0
#: sample points :meth:`SharedMotion.find_jumps` reads the motion at (a low-order polynomial
#: of the position: a few hundred points see it)
JUMP_POINTS = 256


@dataclass
class SharedMotion:
    """The shared (whole-specimen) motion of every series frame relative to the reference.

    Attributes:
        kind: "translation", "affine" or "quadratic".
        params: (T_series, 6) float64 per frame, (T_series, 12) for "quadratic" (columns
            ``PARAM_NAMES``): a_x, a_y (px, the displacement at ``origin``), du/dx, du/dy,
            dv/dx, dv/dy there (px/px; zeros for "translation") and the second derivatives
            (px/px^2). Frames not measured: interpolated in time.
        origin: (2,) x0, y0 px, the point the translation refers to (centre of the POIs).
        scatter: (T_series,) robust std (px) of the points about the fitted motion (NaN where
            not measured): the deformation plus the noise.
        points: (T_series,) points that carried the fit per frame.
        measured: (T_series,) bool, frames with their own estimate.
        se: (T_series,) standard error of the translation per component, px (NaN where not
            measured; 0 at the reference).
        times: (T_series,) the series frames' times (None: frame indices).
        steps: series frames that begin a new load state (:func:`detect_steps`); windows stay
            inside a load state where it holds 2m+1 frames.
        applied: whether the windows carry it (``"auto"`` applies it only where the jitter is
            significant, :meth:`significance`, or its departure from a line over the run's
            windows, :meth:`departure`).
        seconds: wall time of the measurement.
        sample: the pass's solutions at its sample points (the first block's initial guess).
    """

    kind: str
    params: np.ndarray
    origin: np.ndarray
    scatter: np.ndarray
    points: np.ndarray
    measured: np.ndarray
    se: np.ndarray | None = None
    times: np.ndarray | None = None
    steps: list[int] = field(default_factory=list)
    applied: bool = True
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    #: a reported velocity holds the shared motion's slope over this half-width about the
    #: target (None: over the row's whole window; :meth:`velocity_window`)
    velocity_m: int | None = None
    #: series frames where the motion itself jumps among smooth frames (:meth:`find_jumps`:
    #: load steps of a uniform strain, which the fit takes out of the deformation's
    #: residual): a reported velocity's slope of the motion stays on its target's side
    jumps: list[int] = field(default_factory=list)
    #: the measuring pass's trusted solutions at its sample of POIs
    #: (:class:`~torch_stsdic.movie.sample_guess.MeasuredSample`: the first block's initial guess);
    #: None where not measured by a pass (not written to results)
    sample: Any = field(default=None, repr=False)

    def significance(self) -> float:
        """How far the translation departs from a line in time, in units of its own
        estimation noise: the median over frames of ``|a_t+1 - 2 a_t + a_t-1|^2 / (6 se^2)``
        divided by its median without any jitter (ln 4), ``se`` including ``SE_FLOOR``. About
        1 for a motion that is affine in time (the estimate's noise alone); a jitter of std j
        gives about (j / se)^2. NaN when fewer than 3 measured frames."""
        if self.se is None or len(self.params) < 3:
            return float("nan")
        a = self.params[:, :2]
        d2 = np.linalg.norm(a[2:] - 2 * a[1:-1] + a[:-2], axis=1) ** 2
        se = np.sqrt(self.se ** 2 + SE_FLOOR ** 2)
        var = se[2:] ** 2 + 4 * se[1:-1] ** 2 + se[:-2] ** 2  # per component
        ok = (self.measured[2:] & self.measured[1:-1] & self.measured[:-2]
              & np.isfinite(var) & (var > 0))
        if not ok.any():
            return float("nan")
        return float(np.median(d2[ok] / var[ok]) / np.log(4.0))

    def velocity_window(self, m: int) -> int:
        """The half-width of the frames whose slope of this motion a reported velocity of a
        window of half-width ``m`` holds (:mod:`torch_stsdic.movie.shared_velocity`): the
        window's own, or at most :attr:`velocity_m` where set (a motion carried for its
        departure from a line: its slope over a long window misses its velocity at the
        target)."""
        return int(m) if self.velocity_m is None else min(int(m), int(self.velocity_m))

    @property
    def terms(self) -> int:
        """The kind's parameters a component (translation 1, affine 3, quadratic 6): the
        fitted displacement's mean variance over the sample points is ``terms * se^2``."""
        return {"translation": 1, "affine": 3}.get(self.kind, 6)

    def _time_axis(self) -> np.ndarray:
        """(T_series,) float64 the frames' times (frame indices where none were given)."""
        n = len(self.params)
        return (np.arange(n, dtype=np.float64) if self.times is None
                else np.asarray(self.times, dtype=np.float64))

    def _noise2(self) -> np.ndarray:
        """(T_series,) px^2 the estimate's variance a component with ``SE_FLOOR`` added
        (0 + floor where not measured)."""
        return np.nan_to_num(np.asarray(self.se, dtype=np.float64)) ** 2 + SE_FLOOR ** 2

    def _segment_of(self) -> np.ndarray:
        """(T_series,) int64 each frame's load segment (:attr:`steps` and :attr:`jumps`
        start new ones)."""
        seg = np.zeros(len(self.params), dtype=np.int64)
        for k in sorted(set(self.steps) | set(self.jumps)):
            if 0 < k < len(seg):
                seg[k:] += 1
        return seg

    def smooth(self, points: Tensor, h: int = SMOOTH_H, limit: float = SMOOTH_LIMIT) -> int:
        """Smooth the motion in time, in place: at every measured frame, its parameters
        replaced by the value of a least-squares quadratic in time over the ``2h + 1``
        measured frames about it (shifted at the ends and at load steps), where that
        quadratic fits the motion's displacement at ``points`` (N, 2) (the fit's sample)
        within ``limit`` times the noise (the mean square residual over
        ``p (se^2 + SE_FLOOR^2) (T - 3) / T``, as :meth:`departure`); elsewhere (a jump) the
        frame keeps its estimate, as does the reference frame (0 by definition). For a
        motion carried for its departure alone (smooth, not affine in time): a window
        carries the estimate at its target, whose noise is common to the frame's points.
        Returns the frames smoothed."""
        n, t_count = len(self.params), 2 * int(h) + 1
        if h < 1 or n < t_count or self.se is None:
            return 0
        times, se2, seg = self._time_axis(), self._noise2(), self._segment_of()
        fixed = self.measured & ~((self.se == 0) & (np.abs(self.params).sum(1) == 0))
        pts = points.double()
        new, done = self.params.copy(), 0
        for k in np.nonzero(fixed)[0]:
            own = np.nonzero(self.measured & (seg == seg[k]))[0]  # its segment's frames
            if own.size < t_count:
                continue
            i = int(np.searchsorted(own, k))
            win = own[min(max(i - h, 0), own.size - t_count):][:t_count]
            dt = times[win] - times[k]
            a = np.stack([np.ones_like(dt), dt, dt * dt], 1)  # (T, 3)
            hat = np.linalg.pinv(a)  # (3, T)
            g = self.displacement(pts, torch.as_tensor(win)).numpy().reshape(t_count, -1)
            resid = g - a @ (hat @ g)  # (a window's frames at a time: no (F, N) array)
            ratio = (resid ** 2).mean() / (self.terms * se2[win].mean() * (t_count - 3)
                                           / t_count)
            if ratio <= limit:
                new[k] = hat[0] @ self.params[win]
                done += 1
        self.params = new
        return done

    def departure(self, points: Tensor, m: int, max_windows: int = 256) -> float:
        """How far the motion departs from a line in time over windows of ``2m + 1`` frames,
        in units of the noise that carrying it adds: over windows of adjacent measured
        frames (none across a load step; at most ``max_windows``, spread evenly), the mean
        square of the offsets a window would carry (:func:`window_offsets`) at ``points``
        (N, 2) (the fit's sample) over ``p (se^2 + SE_FLOOR^2) (T - 2) / T`` (``p`` the
        kind's terms a component: the fitted displacement's mean variance over the sample
        points is ``p se^2``; ``(T - 2) / T`` what a line through T noisy frames leaves),
        the mean over the windows. About 0.2-0.5 for a motion affine in time; NaN where no
        window fits (``m`` < 1, too few frames)."""
        n, t_count = len(self.params), 2 * int(m) + 1
        if m < 1 or n < t_count or self.se is None:
            return float("nan")
        seg = self._segment_of()  # a window within one load segment
        ok = [s for s in range(n - t_count + 1) if self.measured[s:s + t_count].all()
              and seg[s] == seg[s + t_count - 1]]
        if not ok:
            return float("nan")
        starts = np.asarray(ok)[np.unique(np.round(np.linspace(0, len(ok) - 1, min(
            len(ok), int(max_windows)))).astype(int))]
        idx = torch.as_tensor(starts)[:, None] + torch.arange(t_count)  # (W, T)
        times, se2 = torch.as_tensor(self._time_axis()), torch.as_tensor(self._noise2())
        ratios = []
        for w0 in range(0, idx.shape[0], 32):  # (32, N, T, 2) at a time
            win = idx[w0:w0 + 32]
            g = self.displacement(points.double(), win.reshape(-1)).double()  # (W*T, N, 2)
            g = g.view(win.shape[0], t_count, -1, 2).transpose(1, 2)  # (W, N, T, 2)
            dt = (times[win] - times[win[:, int(m)]].unsqueeze(1)).unsqueeze(1)  # (W, 1, T)
            ms = window_offsets(g, dt).pow(2).mean((1, 2, 3))  # (W,)
            ratios.append(ms / (self.terms * se2[win].mean(1) * (t_count - 2) / t_count))
        return float(torch.cat(ratios).mean())

    def find_jumps(self, points: Tensor, z: float = STEP_Z, ratio: float = STEP_RATIO,
                   reach: int = 5, max_points: int = JUMP_POINTS) -> list[int]:
        """Series frames where the motion itself jumps among smooth frames (a load step of a
        uniform strain: the fit takes it, so :func:`detect_steps` never sees it in the
        deformation's residual). Each adjacent pair of measured frames' increment of the
        displacement at ``points`` (N, 2) (the fit's sample; at most ``max_points`` of
        them, spread), per time unit, is compared at each point with what the pairs about it
        predict: the median of the two on either side (robust to one jump among them, and
        to a vibration: its increments' signs alternate), at the series' ends the line
        through the three on the one side (an accelerating start). The median distance
        over the points, ``j``, starts a jump where it exceeds ``z`` times its noise (1.18
        times ``sqrt(2 p se^2)`` a component, ``se^2`` the frames' mean variance with
        ``SE_FLOOR``, ``p`` the kind's terms) and ``ratio`` times the median ``j`` of the
        pairs within ``reach``: a jump, not a vibration or a shake (every increment alike).
        Uniform 0.1 % strain steps every 6 frames over a 0.02 px drift: each step found
        (docs/validation/window_length.md)."""
        meas = np.nonzero(self.measured)[0]
        if meas.size < 6 or self.se is None:
            return []
        pts = points.double()
        if pts.shape[0] > max_points:
            pts = pts[torch.linspace(0, pts.shape[0] - 1, max_points).round().long()]
        fr = torch.as_tensor(meas)
        g = self.displacement(pts, fr).double()  # (F, N, 2)
        span = torch.as_tensor(self._time_axis())[fr].diff().clamp(min=1e-12)  # (F-1,)
        inc = g.diff(dim=0) / span.view(-1, 1, 1)  # (F-1, N, 2) per time unit
        jump = (inc - _predicted_increments(inc)).norm(dim=-1).median(1).values  # (F-1,)
        se2 = torch.as_tensor(self._noise2())[fr]
        noise = 1.1774 * (2 * self.terms * se2.mean()).sqrt() / span  # (F-1,)
        return _above_neighbours(jump, noise, fr, z, ratio, reach)

    def _at(self, points: Tensor, frames: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        dev = points.device
        params, origin = self._on(dev)
        p = params[frames.to(device=dev, dtype=torch.long)]  # (K, P)
        d = points.double() - origin
        return p, d[:, 0], d[:, 1]

    def _on(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """(T_series, P) :attr:`params` and (2,) :attr:`origin`, float64, on ``device``, kept
        while they are the same arrays (a block asks for them many times: no copy to the
        device, and no host read of the frames asked for, each time)."""
        held = self.__dict__.get("_held")
        if (held is None or held[0] is not self.params or held[1] is not self.origin
                or held[2] != device):
            held = (self.params, self.origin, device,
                    torch.as_tensor(self.params, dtype=torch.float64, device=device),
                    torch.as_tensor(self.origin, dtype=torch.float64, device=device))
            self.__dict__["_held"] = held
        return held[3], held[4]

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_held", None)  # (a device copy: not sent to other processes)
        return state

    def displacement(self, points: Tensor, frames: Tensor) -> Tensor:
        """(K, N, 2) the shared motion's displacement (u, v) px at ``points`` (N, 2) px in
        series frames ``frames`` (K,), in the points' dtype and device."""
        p, dx, dy = self._at(points, frames)
        p = p.unsqueeze(1)  # (K, 1, P): u's and v's coefficients side by side, (..., 2)
        dx, dy = dx.unsqueeze(1), dy.unsqueeze(1)  # (N, 1)
        uv = p[..., 0:2] + p[..., [2, 4]] * dx + p[..., [3, 5]] * dy
        if p.shape[-1] == 12:
            uv = (uv + 0.5 * p[..., [6, 9]] * dx * dx + p[..., [7, 10]] * dx * dy
                  + 0.5 * p[..., [8, 11]] * dy * dy)
        return uv.to(points.dtype)

    def gradient(self, points: Tensor, frames: Tensor) -> Tensor:
        """(K, N, 4) du/dx, du/dy, dv/dx, dv/dy of the shared motion at ``points`` (N, 2) in
        series frames ``frames`` (K,)."""
        p, dx, dy = self._at(points, frames)
        g = [p[:, 2:3] + 0 * dx, p[:, 3:4] + 0 * dx, p[:, 4:5] + 0 * dx, p[:, 5:6] + 0 * dx]
        if p.shape[1] == 12:
            g[0] = g[0] + p[:, 6:7] * dx + p[:, 7:8] * dy
            g[1] = g[1] + p[:, 7:8] * dx + p[:, 8:9] * dy
            g[2] = g[2] + p[:, 9:10] * dx + p[:, 10:11] * dy
            g[3] = g[3] + p[:, 10:11] * dx + p[:, 11:12] * dy
        return torch.stack(g, -1).to(points.dtype)

    @property
    def rotation(self) -> np.ndarray:
        """(T_series,) small-angle rotation per frame, rad ((dv/dx - du/dy) / 2)."""
        return 0.5 * (self.params[:, 4] - self.params[:, 3])

    def jitter(self) -> np.ndarray:
        """(T_series,) px, the frame-to-frame jitter of the translation: |second difference|
        / sqrt(6) (a smooth motion gives ~0; independent jitter of std s gives ~s)."""
        a = self.params[:, :2]
        out = np.full(len(a), np.nan)
        if len(a) >= 3:
            d2 = a[2:] - 2 * a[1:-1] + a[:-2]
            out[1:-1] = np.linalg.norm(d2, axis=1) / np.sqrt(6.0)
        return out

    def summary(self) -> dict[str, Any]:
        """JSON-friendly record for ``TrackResult.info["shared_motion"]`` (per-frame arrays
        as lists, so the result file and ``TrackResult.shared_motion`` carry them)."""
        jit = self.jitter()
        fin = jit[np.isfinite(jit)]
        return {
            "kind": self.kind,
            "origin": [float(x) for x in self.origin],
            "params": np.round(self.params, 9).tolist(),
            "scatter": [None if not np.isfinite(s) else round(float(s), 6)
                        for s in self.scatter],
            "points": [int(n) for n in self.points],
            "measured": [bool(b) for b in self.measured],
            "jitter_px_median": round(float(np.median(fin)), 6) if fin.size else None,
            "jitter_px_max": round(float(np.max(fin)), 6) if fin.size else None,
            "se": [None if not np.isfinite(s) else round(float(s), 7)
                   for s in (self.se if self.se is not None else self.scatter * np.nan)],
            "significance": (round(self.significance(), 3)
                             if np.isfinite(self.significance()) else None),
            "applied": bool(self.applied),
            "steps": [int(k) for k in self.steps],
            "velocity_m": self.velocity_m,
            "jumps": [int(k) for k in self.jumps],
            "times": (None if self.times is None
                      else [float(t) for t in np.asarray(self.times, dtype=np.float64)]),
            "seconds": round(self.seconds, 3),
            **self.extra,
        }

    @classmethod
    def from_summary(cls, rec: dict[str, Any]) -> SharedMotion:
        """The inverse of :meth:`summary`."""
        known = {"kind", "origin", "params", "scatter", "points", "measured", "seconds",
                 "jitter_px_median", "jitter_px_max", "se", "significance", "applied",
                 "times", "steps", "velocity_m", "jumps"}
        se = rec.get("se")
        return cls(kind=rec["kind"], params=np.asarray(rec["params"], dtype=np.float64),
                   origin=np.asarray(rec["origin"], dtype=np.float64),
                   scatter=np.array([np.nan if s is None else s for s in rec["scatter"]],
                                    dtype=np.float64),
                   points=np.asarray(rec["points"], dtype=np.int64),
                   measured=np.asarray(rec["measured"], dtype=bool),
                   se=None if se is None else np.array([np.nan if s is None else s
                                                        for s in se], dtype=np.float64),
                   applied=bool(rec.get("applied", True)),
                   steps=[int(k) for k in rec.get("steps", [])],
                   jumps=[int(k) for k in rec.get("jumps", [])],
                   velocity_m=(None if rec.get("velocity_m") is None
                               else int(rec["velocity_m"])),
                   times=(None if rec.get("times") is None
                          else np.asarray(rec["times"], dtype=np.float64)),
                   seconds=float(rec.get("seconds", 0.0)),
                   extra={k: v for k, v in rec.items() if k not in known})


def carried_note(applied: bool, velocity_m: int | None = None, smoothed: int | None = None,
                 jumps: Sequence[int] | None = None) -> str:
    """How a run used its shared motion, for its summary and figure: ``applied``,
    :attr:`SharedMotion.velocity_m` (None where the windows carry the motion as measured),
    the frames :meth:`SharedMotion.smooth` smoothed (``extra["smoothed_frames"]``) and the
    frames where the motion jumps (:attr:`SharedMotion.jumps`)."""
    if not applied:
        return "measured, not carried (no significant shake, affine in time over the windows)"
    if velocity_m is None:
        return "carried in every window"
    where = ""
    if jumps:
        where = (f"; jumps before frame{'s' if len(jumps) > 1 else ''} "
                 f"{', '.join(str(int(k)) for k in jumps)}: velocities not across them")
    return ("carried in every window (not affine in time over the windows"
            + (f"; smoothed in time at {int(smoothed)} frames" if smoothed else "") + where
            + ")")


def _window_sums(g: Tensor, dt: Tensor) -> Tensor:
    """(..., 2, 3): per component of ``g`` (..., T, 2) over a window's times ``dt`` (..., T;
    its leading dimensions may be 1 where they repeat, e.g. one row of times per target
    for all its points): the least-squares slope, the value at dt = 0 (the mean over the
    frames there; the line's value where none is) and the mean. One batched matrix product
    with the (..., T, 3) weights (the times' centred values over their spread, ...)."""
    dt = dt.to(g.dtype)
    t_count = dt.shape[-1]
    dc = dt - dt.mean(-1, keepdim=True)
    slope_w = dc / (dc * dc).sum(-1, keepdim=True).clamp(min=1e-30)
    at0 = (dt == 0).to(g.dtype)
    cnt = at0.sum(-1, keepdim=True)
    w = torch.stack([slope_w, at0 / cnt.clamp(min=1), torch.full_like(dt, 1.0 / t_count)], -1)
    sums = g.transpose(-1, -2) @ w  # (..., 2, 3)
    beta, g_k, mean = sums.unbind(-1)
    line0 = mean - beta * dt.mean(-1, keepdim=True)  # the line's value at dt = 0
    g_k = torch.where(cnt > 0, g_k, line0)
    return torch.stack([beta, g_k, mean], -1)


def window_slope(g: Tensor, dt: Tensor) -> Tensor:
    """(..., 2) px per time unit: the least-squares slope of the shared motion's displacement
    ``g`` (..., T, 2) over a window's frame times ``dt`` (..., T; broadcast against g's
    leading dimensions): the part of it a window's velocity (ut, vt) holds (0 where the
    window has one frame)."""
    if dt.shape[-1] < 2:
        return torch.zeros_like(g[..., 0, :])
    return _window_sums(g, dt)[..., 0]


def window_offsets(g: Tensor, dt: Tensor, return_slope: bool = False
                   ) -> Tensor | tuple[Tensor, Tensor]:
    """The known motion of every frame of a window: the shared motion's jitter about its own
    line through the window (module docstring).

    Args:
        g: (..., T, 2) the shared motion's displacement at a point in the window's T frames.
        dt: (..., T) frame times minus the target's (0 at the target frame); its leading
            dimensions broadcast against g's.

    Returns:
        (..., T, 2) ``o_t = g_t - g_k - beta dt_t`` (``beta`` the least-squares slope of g over
        the window; ``g_k`` its value at dt = 0), 0 where the window has one frame; with
        ``return_slope`` also beta (..., 2) (:func:`window_slope`)."""
    if dt.shape[-1] < 2:
        o = torch.zeros_like(g)
        return (o, o[..., 0, :]) if return_slope else o
    sums = _window_sums(g, dt)
    beta, g_k = sums[..., 0], sums[..., 1]
    o = g - g_k.unsqueeze(-2) - beta.unsqueeze(-2) * dt.to(g.dtype).unsqueeze(-1)
    return (o, beta) if return_slope else o


def detect_steps(residual: Tensor, valid: Tensor, sigma: Tensor, frames: Sequence[int],
                 z: float = STEP_Z, ratio: float = STEP_RATIO, reach: int = 5) -> list[int]:
    """Load steps: frames where the deformation jumps while it holds still around them.

    Args:
        residual: (F, N, 2) each point's displacement minus the shared motion (the
            deformation's own part), px, at series frames ``frames`` (F,) ascending.
        valid: (F, N) bool measurements to use.
        sigma: (F,) typical classical noise std of one displacement component, px.
        frames: the series index of each row.

    A frame ``t`` (following frame ``t - 1`` in the series) starts a new load state when the
    median increment ``s_t = med_i |r_i(t) - r_i(t-1)|`` exceeds both ``z`` times its noise
    level (1.18 sigma, the median length of the increment of two frames' noise: the
    reference's noise, half of sigma^2, cancels) and ``ratio`` times the median increment of
    the frames within ``reach`` of it: a jump among still frames (measured on renders: holds
    at 1.0 sigma, a 0.3 px sinusoidal step at 3 sigma). A steady motion (every increment
    alike) or one load state per image has no step.

    Returns:
        series frames that begin a new segment (ascending)."""
    if residual.shape[0] < 3:
        return []
    return steps_from_increments(step_increments(residual, valid), sigma, frames, z, ratio,
                                 reach)


def step_increments(residual: Tensor, valid: Tensor) -> Tensor:
    """(F - 1,) px the median over the points valid in both frames of each point's increment
    ``|r_i(t+1) - r_i(t)|`` into frames 1.. of ``residual`` (F, N, 2) (``valid`` (F, N));
    frame chunk by frame chunk (each increment's median is its own: a caller may give the
    rows of a long series a chunk at a time, each with one frame more)."""
    f = residual.shape[0]
    s = torch.empty(max(f - 1, 0), dtype=residual.dtype, device=residual.device)
    for sl in frame_chunks(f - 1, residual.shape[1]):  # bounded memory, the same numbers
        a, b = sl.start, sl.stop
        both = valid[a + 1:b + 1] & valid[a:b]
        inc = (residual[a + 1:b + 1] - residual[a:b]).norm(dim=-1)
        inc = torch.where(both & torch.isfinite(inc), inc, torch.nan)
        s[sl] = torch.nanmedian(inc, dim=1).values  # increment into frames[1:]
    return s


def steps_from_increments(s: Tensor, sigma: Tensor, frames: Sequence[int],
                          z: float = STEP_Z, ratio: float = STEP_RATIO, reach: int = 5
                          ) -> list[int]:
    """The load steps of :func:`detect_steps` from the median increments ``s`` (F - 1,)
    (:func:`step_increments`), the noise ``sigma`` (F,) and the series frames (F,)."""
    if len(frames) < 3:
        return []
    noise = 1.1774 * torch.maximum(sigma[1:], sigma[:-1])
    return _above_neighbours(s, noise, torch.as_tensor(list(frames)), z, ratio, reach)


def _predicted_increments(inc: Tensor) -> Tensor:
    """(F1, ...) each increment of ``inc`` (F1 >= 5, ...) as the ones about it predict it
    (:meth:`SharedMotion.find_jumps`): the median of the two on either side, at the two at
    either end the line through the three beyond them; the middle ones all at once."""
    f1 = inc.shape[0]
    line = torch.tensor([4.0, 1.0, -2.0], dtype=inc.dtype, device=inc.device)
    line = line.view(3, *([1] * (inc.dim() - 1))) / 3.0
    pred = torch.empty_like(inc)
    pred[2:f1 - 2] = torch.stack([inc[:f1 - 4], inc[1:f1 - 3], inc[3:f1 - 1],
                                  inc[4:]]).median(0).values
    for j in (0, 1):  # the line through increments j+1 .. j+3, at j
        pred[j] = (line * inc[j + 1:j + 4]).sum(0)
    for j in (f1 - 2, f1 - 1):
        pred[j] = (line * inc[[j - 1, j - 2, j - 3]]).sum(0)
    return pred


def _above_neighbours(s: Tensor, noise: Tensor, frames: Tensor, z: float, ratio: float,
                      reach: int) -> list[int]:
    """The frames ``frames[j + 1]`` (``frames`` (F,) series frames) whose pair ``j`` of
    adjacent frames has ``s[j]`` ((F - 1,)) above both ``z`` times its ``noise[j]`` and
    ``ratio`` times the median ``s`` of the pairs within ``reach``: a jump among still
    pairs (:func:`steps_from_increments`, :meth:`SharedMotion.find_jumps`)."""
    s, noise = s.double(), noise.double().to(s.device)
    n = s.shape[0]
    if n == 0:
        return []
    adjacent = (frames[1:] - frames[:-1]) == 1  # (host frame numbers)
    # (n, 2 reach) the pairs within reach of each, NaN beyond the series' ends: their median
    # is that of the pairs there (the same entries, NaN skipped), every pair at once
    dev = s.device
    off = torch.cat([torch.arange(-reach, 0, device=dev), torch.arange(1, reach + 1, device=dev)])
    at = torch.arange(n, device=dev)[:, None] + off
    near = torch.where((at >= 0) & (at < n), s[at.clamp(0, n - 1)], torch.nan)
    base = torch.nanmedian(near, dim=1).values if reach > 0 else torch.full_like(s, torch.nan)
    jump = torch.isfinite(s) & torch.isfinite(base) & (s > z * noise) & (s > ratio * base)
    return frames[1:][jump.cpu() & adjacent.cpu()].tolist()  # one read


def overlap_factor(points: Tensor, subset_size: int) -> float:
    """Standard-error factor for the errors of overlapping subsets: points closer than a
    subset share pixels, so their errors correlate and n points carry about
    ``n (spacing / subset)^2`` independent measurements: ``max(1, subset / spacing)``, the
    spacing being the median nearest-neighbour distance (measured: 2.0 at subset 21, step
    10; this gives 2.1)."""
    if points.shape[0] < 2:
        return 1.0
    d = torch.cdist(points.double(), points.double())
    d.fill_diagonal_(float("inf"))
    spacing = float(d.min(1).values.median())
    return max(1.0, float(subset_size) / max(spacing, 1e-9))


def known_window_motion(shared: Tensor, dt: Tensor, shape_hint: str = "") -> Tensor:
    """(N, T, 2) what a window carries of a known shared motion given by the user: ``shared``
    (T, 2) (the same at every point) or (N, T, 2) px per frame, ``dt`` (N, T) frame times
    minus the target's; checked (shape, finite values: ValueError naming
    ``shared_motion``), then :func:`window_offsets`, in ``dt``'s dtype and device.
    ``shape_hint``: the accepted shapes as the caller names them, for the error."""
    n, t_count = dt.shape
    g = torch.as_tensor(shared).detach().to(device=dt.device, dtype=dt.dtype)
    if g.dim() == 2:
        g = g.unsqueeze(0).expand(n, -1, -1)
    if tuple(g.shape) != (n, t_count, 2):
        hint = shape_hint or f"({t_count}, 2) or (N={n}, {t_count}, 2)"
        raise ValueError(f"shared_motion must be {hint}, got "
                         f"{tuple(torch.as_tensor(shared).shape)}")
    if not bool(torch.isfinite(g).all()):
        raise ValueError("shared_motion contains NaN or infinite values")
    return window_offsets(g, dt).contiguous()


def sample_points(points: Tensor, max_points: int) -> Tensor:
    """(n,) indices of at most ``max_points`` of the POIs, spread evenly over them."""
    n = points.shape[0]
    if n <= max_points:
        return torch.arange(n)
    return torch.linspace(0, n - 1, int(max_points)).round().long().unique()
