"""The first block's initial guess from the measuring pass (:mod:`torch_stsdic.movie.shared_pass`).

A run with a shared motion measures a sample of its POIs classically (FFT cross-correlation
and Gauss-Newton) on every frame its windows use, before the first block. Those trusted
solutions are an initial guess for every other POI: the mean over its nearest trusted sample
points of their displacements carried by their own gradients, ``d_i = mean_s(d_s + G_s (x_i -
x_s))`` (and the mean of their gradients), per window frame, and a line
in time through them (:func:`~torch_stsdic.core.initial.linear_fit_in_time`) for the window's
velocity. The first block then starts where later blocks start, from a prediction, instead
of FFT cross-correlation at seed points (an STS(5) solve of 38,809 POIs: the FFT was a
quarter of it). The mean, not the nearest point alone: each sample point carries its
classical noise and its gradients' noise times the distance (1.5e-3 px/px over 16-30 px);
over the benchmark pair's 38,809 POIs the guess's 90th-percentile error in u fell from 0.049
to 0.033 px and the window solve from 2.63 to 2.44 Gauss-Newton steps a point.

A guess is only made where the sample agrees on it: the POI's nearest sample points (up to
:data:`NEAREST`, at least two) each carry their displacement to the POI, and the guesses
must agree within :data:`GUESS_TOL`. Where they do not (a crack or a neck between them, a
wrong sample point, a field that bends more than that at the sample's spacing) there is no
guess, and the row is solved as before (FFT cross-correlation); a POI that is a sample
point itself, where it agrees, starts from its own solution and gradients. A row that does not
converge from its guess is rescued as a carried row is (previous target, neighbours,
FFT)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_stsdic.analysis.points import nearest_among
from torch_stsdic.core.initial import linear_fit_in_time

__all__ = ["MeasuredSample", "GUESS_TOL", "NEAREST"]

#: px: the guesses of a POI's nearest sample points must agree within this (IC-GN converges
#: from a guess several px off on speckle; a field that bends by more between the sample
#: points is left to FFT cross-correlation)
GUESS_TOL = 0.5

#: sample points whose guesses a POI compares: its nearest ones, those of them trusted at
#: the frame (around a POI inside the sample's hull a straight crack cannot separate it
#: from all of them)
NEAREST = 4


@dataclass(eq=False)
class MeasuredSample:
    """The measuring pass's trusted classical solutions at a sample of a run's POIs.

    Attributes:
        points: (S, 2) the sample POIs (x, y), px.
        frames: (F,) int64 series frames measured (ascending).
        disp: (F, S, 2) displacement (u, v), px; NaN where not trusted.
        grad: (F, S, 2, 2) its gradients [[ux, uy], [vx, vy]], px/px; NaN where not trusted.
    """

    points: torch.Tensor
    frames: torch.Tensor
    disp: torch.Tensor
    grad: torch.Tensor

    def __post_init__(self) -> None:
        self.points = self.points.double()
        self.disp, self.grad = self.disp.double(), self.grad.double()

    @classmethod
    def from_fields(cls, points: torch.Tensor, frames: torch.Tensor, u: torch.Tensor,
                    v: torch.Tensor, grads: dict[str, torch.Tensor], valid: torch.Tensor
                    ) -> MeasuredSample:
        """The trusted solutions (``valid`` (F, n)) of a classical measurement of series
        ``frames`` (F,) at ``points`` (n, 2): its ``u``, ``v`` (F, n) and gradients ``grads``
        (``ux``, ``uy``, ``vx``, ``vy`` (F, n); zero where absent: a translation-only
        shape)."""
        nan = torch.tensor(float("nan"), dtype=torch.float64)
        disp = torch.stack([u, v], -1).double().cpu()
        if all(nm in grads for nm in ("ux", "uy", "vx", "vy")):
            g = torch.stack([torch.stack([grads["ux"], grads["uy"]], -1),
                             torch.stack([grads["vx"], grads["vy"]], -1)], -2).double().cpu()
        else:
            g = torch.zeros(*disp.shape, 2, dtype=torch.float64)
        ok = valid.cpu()
        return cls(points=points, frames=frames.cpu().long(),
                   disp=torch.where(ok.unsqueeze(-1), disp, nan),
                   grad=torch.where(ok.view(*ok.shape, 1, 1), g, nan))

    @classmethod
    def from_result(cls, res, points: torch.Tensor, valid: torch.Tensor) -> MeasuredSample:
        """:meth:`from_fields` of a classical result ``res``
        (:class:`~torch_stsdic.analysis.result.TrackResult`) at its points ``points``."""
        return cls.from_fields(points, res.frames, res.u, res.v, res.gradients, valid)

    @staticmethod
    def near_frames(frames: torch.Tensor, blocks: list[list[int]], m: int) -> torch.Tensor:
        """(F,) bool: which of the series frames ``frames`` (F,) the windows of targets
        ``blocks`` can use (within 2m frames of a block's targets: a window is shifted,
        never stretched, at the ends of the series or of a load segment): all that
        :meth:`guess` needs for those blocks, bounded by their number whatever the movie's
        length."""
        keep = torch.zeros(len(frames), dtype=torch.bool)
        for b in blocks:
            if len(b):
                keep |= (frames >= min(b) - 2 * m) & (frames <= max(b) + 2 * m)
        return keep

    def guess(self, points: torch.Tensor, windows: torch.Tensor, dt: torch.Tensor
              ) -> dict[str, torch.Tensor]:
        """Initial guesses of the rows (target j, POI i) of a block, row = j * N + i.

        Args:
            points: (N, 2) the run's POIs, px.
            windows: (B, T) series frames of every target's window.
            dt: (B, T) their times minus the target's.

        Returns u, ux, uy, v, vx, vy and (T > 1) ut, vt, each (B*N,) float64 (ut, vt in px
        per time unit); NaN in every entry of a row without a trusted guess at all of its
        window frames."""
        pts = points.detach().to("cpu", torch.float64)
        n, (b, t) = pts.shape[0], windows.shape
        nan = torch.full((b * n,), float("nan"), dtype=torch.float64)
        names = ("u", "ux", "uy", "v", "vx", "vy") + (("ut", "vt") if t > 1 else ())
        frames, where = torch.unique(windows.cpu(), return_inverse=True)  # (F,), (B, T)
        col = torch.searchsorted(self.frames, frames).clamp(max=max(len(self.frames) - 1, 0))
        if (self.points.shape[0] < 2 or len(self.frames) == 0
                or not bool((self.frames[col] == frames).all())):
            return {nm: nan.clone() for nm in names}  # a frame the pass did not measure
        # (N, k) each POI's nearest sample points, nearest first
        dist, near = nearest_among(pts, self.points, min(NEAREST, self.points.shape[0]))
        # per distinct frame: the mean of the valid sample points' guesses, whether they agree
        disp, grad, valid = self._valid(col)
        d, ok, ok_k = self._at(disp, grad, valid, near, pts)  # (F, N, 2), (F, N), (F, N, k)
        # a POI that is a sample point itself, trusted there and agreeing with the others:
        # its own solution (the mean with its neighbours' carried to it adds their field's
        # curvature: a round against the template started up to 0.18 px off on the
        # hourglass, ~1 step more a row)
        own = (dist[:, 0] < 1e-6).unsqueeze(0) & valid[:, near[:, 0]] & ok  # (F, N)
        d = torch.where(own.unsqueeze(-1), disp[:, near[:, 0]], d)
        ok = ok[where].all(1).reshape(b * n)  # every frame of the row's window
        disp = d[where].permute(0, 2, 1, 3).reshape(b * n, t, 2)  # (B*N, T, 2)
        dtr = dt.detach().cpu().double().repeat_interleave(n, 0)  # (B*N, T)
        d0, vel = linear_fit_in_time(disp, dtr)
        # the gradients at the target frame (dt = 0; the frame nearest the target if none)
        at = where[torch.arange(b), dt.detach().cpu().abs().argmin(1)]  # (B,) among col
        used, inv = torch.unique(at, return_inverse=True)
        mean_g = _mean_gradient(grad[used], near, ok_k[used])  # (U, N, 2, 2)
        mine = own[used].view(*own[used].shape, 1, 1)
        grad = torch.where(mine, grad[used][:, near[:, 0]], mean_g)[inv].reshape(b * n, 2, 2)
        out = {"u": d0[:, 0], "v": d0[:, 1], "ux": grad[:, 0, 0], "uy": grad[:, 0, 1],
               "vx": grad[:, 1, 0], "vy": grad[:, 1, 1]}
        if t > 1:
            out["ut"], out["vt"] = vel[:, 0], vel[:, 1]
        return {nm: torch.where(ok, v, nan) for nm, v in out.items()}

    def _valid(self, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """At measured frames ``col`` (F,): displacements (F, S, 2) and gradients (F, S, 2, 2)
        of the sample, 0 where not trusted, and (F, S) bool where trusted."""
        disp, grad = self.disp[col], self.grad[col]
        valid = torch.isfinite(disp).all(-1) & torch.isfinite(grad).flatten(2).all(-1)
        disp = torch.where(valid.unsqueeze(-1), disp, 0.0)
        grad = torch.where(valid.view(*valid.shape, 1, 1), grad, 0.0)
        return disp, grad, valid

    def _at(self, disp: torch.Tensor, grad: torch.Tensor, valid: torch.Tensor,
            near: torch.Tensor, pts: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """From the sample at F frames (:meth:`_valid`): (F, N, 2) the guess of every POI
        ``pts`` (N, 2), the mean of its valid candidates' (``near`` (N, k)) displacements
        carried to it by their gradients; (F, N) bool whether at least two candidates are
        valid and all agree with it within ``GUESS_TOL``; (F, N, k) bool which candidates
        are valid."""
        ok_k = valid[:, near]  # (F, N, k)
        w = ok_k.to(disp.dtype)
        cnt = w.sum(-1).clamp(min=1.0)
        ox = pts[:, 0:1] - self.points[near, 0]  # (N, k) px from each candidate
        oy = pts[:, 1:2] - self.points[near, 1]
        dn, gn = disp[:, near], grad[:, near]  # (F, N, k, 2), (F, N, k, 2, 2)
        cu = dn[..., 0] + gn[..., 0, 0] * ox + gn[..., 0, 1] * oy  # (F, N, k)
        cv = dn[..., 1] + gn[..., 1, 0] * ox + gn[..., 1, 1] * oy
        du, dv = (cu * w).sum(-1) / cnt, (cv * w).sum(-1) / cnt  # (F, N)
        spread = (torch.hypot(cu - du.unsqueeze(-1), cv - dv.unsqueeze(-1)) * w).amax(-1)
        ok = (ok_k.sum(-1) >= 2) & (spread <= GUESS_TOL)
        return torch.stack([du, dv], -1), ok, ok_k


def _mean_gradient(grad: torch.Tensor, near: torch.Tensor, ok_k: torch.Tensor) -> torch.Tensor:
    """(F, N, 2, 2) the mean gradients of every POI's valid candidates ``near`` (N, k)
    (``ok_k`` (F, N, k)) among the sample's gradients ``grad`` (F, S, 2, 2) at F frames."""
    w = ok_k.to(grad.dtype)
    return (grad[:, near] * w.view(*w.shape, 1, 1)).sum(2) / w.sum(-1).clamp(
        min=1.0).view(*w.shape[:2], 1, 1)
