"""Carried guesses between blocks of a movie: the last stored row of every point moved on
by its velocity (:class:`Carry`), lost points filled from their grid neighbours'
(:func:`neighbour_guess`), and a block's rows turned into the next carry
(:func:`rows_numpy`, :func:`make_carry`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from torch_stsdic.analysis.quality import carried_neighbours, nanmedian_rows
from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.choices import until_done
from torch_stsdic.core.shared_motion import SharedMotion, window_slope
from torch_stsdic.core.status import Status
from torch_stsdic.movie.frames import true_rows, upload, window_frames

__all__ = ["Carry", "neighbour_guess", "rows_numpy", "make_carry", "FILL_ROUNDS"]

#: rings of lost points filled from their neighbours' carried motion (Carry.from_neighbours)
FILL_ROUNDS = 8

#: the displacement gradients a carry moves on by their rates (:func:`gradient_rates`)
GRADIENTS = ("ux", "uy", "vx", "vy")


@dataclass
class Carry:
    """Last stored row (total quantities, float32-rounded) and the velocity to extrapolate."""

    t: float
    vals: dict[str, torch.Tensor]  # name -> (N,)
    vel_u: torch.Tensor
    vel_v: torch.Tensor
    valid: torch.Tensor  # (N,) bool
    #: (N,) bool: the velocity was measured (ut, vt, or two rows); None: everywhere
    vel_known: torch.Tensor | None = None
    #: (N,) ZNCC of each point's last trusted row (NaN: none), the fit check's baseline
    fit_zncc: torch.Tensor | None = None
    #: where the velocity came from, for :meth:`shared_step`: the series frame of the last
    #: row and of the row a finite difference was taken from (None: unknown), and per point
    #: the half-width of the last row's window where the velocity is its ut, vt (else -1)
    frame: int | None = None
    prev_frame: int | None = None
    window_m: torch.Tensor | None = None
    #: name -> (N,) per time unit: the rate of each displacement gradient (ux, uy, vx, vy)
    #: over the last rows (0 where unknown); None: none carried
    rates: dict[str, torch.Tensor] | None = None
    #: (N,) bool: the point's last rows left the view (OUTSIDE, and no trusted row since);
    #: None: not known (none did)
    left: torch.Tensor | None = None

    def predict(self, tk: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted total parameters (B, N) at times ``tk`` (B,): u, v moved on by the
        velocity, the gradients by their :attr:`rates`, the rest as in the last row."""
        d = (tk - self.t).unsqueeze(1)
        out = {k: v.unsqueeze(0).expand(tk.shape[0], -1) for k, v in self.vals.items()}
        out["u"] = self.vals["u"] + self.vel_u * d
        out["v"] = self.vals["v"] + self.vel_v * d
        for nm, rate in (self.rates or {}).items():
            out[nm] = self.vals[nm] + rate * d
        return out

    def shared_step(self, shared: SharedMotion, points: torch.Tensor, ks: torch.Tensor,
                    ts: torch.Tensor, segments: torch.Tensor | None = None,
                    slope: torch.Tensor | None = None) -> torch.Tensor:
        """(B, N, 2) px: what the shared motion (:mod:`torch_stsdic.core.shared_motion`) adds
        to :meth:`predict` at series frames ``ks`` (B,) (times ``ts`` (T_series,)): its
        displacement there minus at the last row, minus the part of it the carried velocity
        already holds (the least-squares slope of the shared motion over the last row's
        window where the velocity is its ut, vt; its finite difference where the velocity is
        one). A specimen that shakes moves by the shake between frames, which no velocity
        predicts: on the muDIC hourglass (0.15 px median shake) the carry missed a frame's
        solution by 0.185 px median, 0.014 px with the shake added. Zero where unknown.
        ``slope``: :meth:`shared_slope`'s answer where the caller has it already."""
        n = points.shape[0]
        out = torch.zeros(ks.shape[0], n, 2, dtype=points.dtype, device=points.device)
        if self.frame is None:
            return out
        last = torch.full((1,), self.frame, dtype=torch.long, device=ks.device)  # (no copy)
        g_last = shared.displacement(points, last)[0]  # (N, 2)
        d = (ts[ks] - self.t).to(points.dtype).view(-1, 1, 1)
        if slope is None:
            slope = self.shared_slope(shared, points, ts, segments)
        return shared.displacement(points, ks) - g_last - slope * d

    def shared_slope(self, shared: SharedMotion, points: torch.Tensor, ts: torch.Tensor,
                     segments: torch.Tensor | None = None, m_max: int | None = None
                     ) -> torch.Tensor:
        """(N, 2) px per time unit: the part of the carried velocity that the shared motion
        made (:meth:`shared_step`): its least-squares slope over the last row's window where
        the velocity is that row's ut, vt, its finite difference where the velocity is one;
        0 where the velocity is unknown or no frame is known. Every half-width up to
        ``m_max`` (the run's longest: no host read; None: the rows' longest, one read)."""
        n = points.shape[0]
        slope = torch.zeros(n, 2, dtype=points.dtype, device=points.device)
        if self.frame is None:
            return slope
        dev = points.device
        last = torch.full((1,), self.frame, dtype=torch.long, device=dev)  # (no copy)
        g_last = shared.displacement(points, last)[0]  # (N, 2)
        wm = self.window_m
        if wm is not None:  # (the row's velocity in the reported terms: shared_velocity)
            top = (int(wm.max()) if wm.numel() else 0) if m_max is None else int(m_max)
            fits: dict[int, torch.Tensor] = {}  # by the slope's half-width
            for m in range(1, top + 1):
                h = shared.velocity_window(int(m))
                if h not in fits:
                    win = window_frames(last, h, len(ts), segments)[0]  # (T,)
                    g = shared.displacement(points, win).transpose(0, 1)  # (N, T, 2)
                    dt = (ts[win] - ts[self.frame]).to(points.dtype)
                    fits[h] = window_slope(g, dt.expand(n, -1))
                slope = torch.where((wm == m).unsqueeze(1), fits[h], slope)
        if self.prev_frame is not None and self.prev_frame != self.frame:
            span = (ts[self.frame] - ts[self.prev_frame]).to(points.dtype)  # (no read)
            g_prev = shared.displacement(points, torch.full(
                (1,), self.prev_frame, dtype=torch.long, device=dev))[0]
            fd = (g_last - g_prev) / span
            slope = fd if wm is None else torch.where((wm <= 0).unsqueeze(1), fd, slope)
        if self.vel_known is not None:
            slope = torch.where(self.vel_known.unsqueeze(1), slope, 0.0)
        return slope

    def from_neighbours(self, nb: torch.Tensor, points: torch.Tensor,
                        rounds: int = FILL_ROUNDS, missing: int | None = None
                        ) -> tuple[Carry, torch.Tensor]:
        """This carry with every point that has no valid carry (lost, or a poor fit) carried
        from its valid grid neighbours ``nb`` (N, k) instead (:func:`neighbour_guess`; points
        (N, 2) px in the first reference), ring by ring into a lost region (at most
        ``rounds``), so a lost point starts near the motion again rather than from FFT
        cross-correlation (or is seen to have left the image). ``missing``: how many points
        have no valid carry, where the caller read it (else read here); on a GPU
        (:data:`~torch_stsdic.core.choices.UNTIL_DONE` False) not read: every point's
        guess made in every ring, the valid ones left as they are. Returns the carry and
        the points filled (a 0-d tensor: not read here)."""
        names = list(self.vals)
        rated = list(self.rates or {})
        stack = torch.stack([self.vals[nm] for nm in names] + [self.vel_u, self.vel_v]
                            + [self.rates[nm] for nm in rated], 1)
        ok = self.valid.clone()
        # on the CPU until a ring fills none (then none after it would: nothing changed),
        # on a GPU every ring, no read (:data:`~torch_stsdic.core.choices.UNTIL_DONE`)
        stop = until_done(ok.device)
        if stop:  # only those (~0.2 of the work when 7 % are lost), chosen once: one host
            # read for all the rounds (a round fills those of them its guess reaches; a
            # guess of a point depends on its neighbours alone, so the rows filled before
            # take no part)
            if missing is None:
                missing = int((~ok).sum())
            need = true_rows(~ok, missing)
        else:  # every point (a valid one is not filled), no read
            need = torch.arange(ok.numel(), device=ok.device)
        for _ in range(rounds if missing or not stop else 0):
            guess = neighbour_guess(stack.unsqueeze(0), ok.unsqueeze(0),
                                    names + ["vel_u", "vel_v"] + [f"rate_{nm}" for nm in rated],
                                    nb, points, at=need, every_row=not stop)[0]
            fill = torch.isfinite(guess).all(1) & ~ok[need]
            if stop and not bool(fill.any()):
                break
            stack[need] = torch.where(fill.unsqueeze(1), guess.to(stack.dtype), stack[need])
            ok[need] |= fill
        filled = ok & ~self.valid
        vals = {nm: stack[:, i] for i, nm in enumerate(names)}
        nv = len(names)
        rates = {nm: stack[:, nv + 2 + i] for i, nm in enumerate(rated)} or self.rates
        known = None if self.vel_known is None else self.vel_known | filled
        return dataclasses.replace(self, vals=vals, vel_u=stack[:, nv], vel_v=stack[:, nv + 1],
                                   valid=ok, vel_known=known, rates=rates), filled.sum()


def neighbour_guess(params: torch.Tensor, ok: torch.Tensor, names, nb: torch.Tensor,
                    points: torch.Tensor, min_count: int = 2,
                    at: torch.Tensor | None = None, every_row: bool = False) -> torch.Tensor:
    """(B, N, P) every point's parameters from its ``ok`` (B, N) grid neighbours ``nb``
    (N, k) in ``params`` (B, N, P) (names ``names``): the median over them, u and v first
    carried to the point by each neighbour's own gradients (positions ``points`` (N, 2) px,
    :func:`~torch_stsdic.analysis.quality.carried_neighbours`); NaN where fewer than ``min_count``
    neighbours are ``ok``. Parameters NaN at every neighbour (a classical row's ut) stay
    NaN. ``at`` (M,) long: only those points' guesses, (B, M, P). ``every_row``: no host
    read (:func:`~torch_stsdic.analysis.quality.carried_neighbours`'s)."""
    vn = carried_neighbours(params, ok, nb, at=at)  # (B, N, k, P)
    iu, iv = names.index("u"), names.index("v")
    if all(nm in names for nm in ("ux", "uy", "vx", "vy")):
        b, n = params.shape[:2]
        gi = [names.index(nm) for nm in ("ux", "uy", "vx", "vy")]
        uv = carried_neighbours(params[..., [iu, iv]], ok, nb, points,
                                params[..., gi].reshape(b, n, 2, 2), at=at, every_row=every_row)
        vn[..., iu], vn[..., iv] = uv[..., 0], uv[..., 1]
    out = nanmedian_rows(vn.transpose(-1, -2))  # (B, N, P)
    few = (~torch.isnan(vn[..., iu])).sum(-1) < min_count
    return torch.where(few.unsqueeze(-1), torch.nan, out)




def rows_numpy(block: dict[str, torch.Tensor], fields: Sequence[str]) -> dict[str, np.ndarray]:
    """(B, N) numpy rows per field (float64; ut/vt NaN when absent)."""
    b, n = block["status"].shape
    # one device-to-host copy per dtype (a stack of the fields), not one per field: each
    # copy of a CUDA tensor waits for the device
    groups: dict[tuple, list[str]] = {}
    for nm in fields:
        if nm in block:
            groups.setdefault((block[nm].dtype, tuple(block[nm].shape)), []).append(nm)
    host = {}
    for names in groups.values():
        stacked = torch.stack([block[nm].detach() for nm in names]).cpu().numpy()
        host.update(zip(names, stacked))
    out = {}
    for nm in fields:
        out[nm] = host[nm] if nm in host else np.full((b, n), np.nan)
    out["status"] = out["status"].astype(np.int8)
    if "m" in out:
        out["m"] = np.nan_to_num(out["m"], nan=-1).astype(np.int8)
    out["iterations"] = out["iterations"].astype(np.int64)
    return out



def make_carry(rows: Mapping[str, np.ndarray | torch.Tensor], times: np.ndarray, names,
               prev: Carry | None, dtype, device, frames: list[int] | None = None) -> Carry:
    """Carry from the last stored row (velocity from ut/vt, else from the last two rows).
    ``rows``: name -> (B, N) the block's rows as stored (numpy, or tensors: on the run's
    device, made there from the solved rows, no copy to the host and back);
    ``frames``: the rows' series frames (for :meth:`Carry.shared_step`). No host read.

    Valid are the usable rows and the INCONSISTENT ones: a point the neighbour test
    doubts fitted its own subset (it passed the fit check), so it goes on from its own
    solution; restarting it would lose the many good points a bad neighbour condemns."""
    rows = {nm: (a if isinstance(a, torch.Tensor) else torch.from_numpy(np.asarray(a))).to(
        device) for nm, a in rows.items()}

    def col(nm: str, i: int = -1) -> torch.Tensor:
        return rows[nm][i].to(torch.float64).to(dtype)

    vals = {nm: col(nm) for nm in names}
    status = rows["status"]
    st = status[-1]
    ok = (st <= USABLE) | (st == int(Status.INCONSISTENT))
    ok &= torch.isfinite(vals["u"]) & torch.isfinite(vals["v"])
    t_last = float(times[-1])
    if len(times) >= 2:
        t_prev, u_prev, v_prev = float(times[-2]), col("u", -2), col("v", -2)
    elif prev is not None:
        t_prev, u_prev, v_prev = prev.t, prev.vals["u"], prev.vals["v"]
    else:
        t_prev, u_prev, v_prev = t_last, vals["u"], vals["v"]
    span = t_last - t_prev
    if span > 0:
        vel_u, vel_v = (vals["u"] - u_prev) / span, (vals["v"] - v_prev) / span
    else:
        vel_u, vel_v = torch.zeros_like(vals["u"]), torch.zeros_like(vals["v"])
    # two rows: a finite difference at every point (None: known everywhere, no read)
    known = None if span > 0 else torch.zeros_like(ok)
    if "ut" in names:  # the measured velocity where the window had one (m > 0)
        vel_u = torch.where(torch.isfinite(vals["ut"]), vals["ut"], vel_u)
        vel_v = torch.where(torch.isfinite(vals["vt"]), vals["vt"], vel_v)
        if known is not None:
            known = known | (torch.isfinite(vals["ut"]) & torch.isfinite(vals["vt"]))
    fin = torch.isfinite(vel_u) & torch.isfinite(vel_v)
    vel_u = torch.where(fin, vel_u, torch.zeros_like(vel_u))
    vel_v = torch.where(fin, vel_v, torch.zeros_like(vel_v))
    # where the row had no window velocity (classical, m = 0), the next window starts from
    # the finite difference, as its displacement does (not from zero velocity: sample 12's
    # rows left classical before a load step took 3.5 instead of 3.2 steps in the next block)
    for nm, vel in (("ut", vel_u), ("vt", vel_v)):
        if nm in vals:
            vals[nm] = torch.where(torch.isfinite(vals[nm]), vals[nm], vel)
    rates = gradient_rates(rows, times, names, prev, ok, col)
    fit = None
    if "zncc" in rows:  # the last trusted row of every point, in time order
        fit = torch.full_like(vals["u"], float("nan")) if prev is None or \
            prev.fit_zncc is None else prev.fit_zncc.clone()
        for i in range(len(times)):
            fit = torch.where(status[i] <= USABLE, col("zncc", i), fit)
    frame = prev_frame = window_m = None
    if frames is not None:
        frame = int(frames[-1])
        prev_frame = int(frames[-2]) if len(frames) >= 2 else (
            prev.frame if prev is not None else None)
        m_row = (rows["m"][-1].to(torch.int64) if "m" in rows
                 else torch.zeros(ok.shape, dtype=torch.long, device=device))
        if "ut" in names:
            window_m = torch.where(torch.isfinite(col("ut")) & torch.isfinite(col("vt")),
                                   m_row.clamp(min=1), -1)
        else:
            window_m = torch.full_like(m_row, -1)
    # a point that left the view stays out until a trusted row (or its neighbours') brings
    # it back: without a carry of its own it was searched by FFT in every block (a specimen
    # moving out of view: wrong peaks, POOR_FIT, most of the run's time); kept as a mask
    # (all False where none left: no read of whether any did)
    left = st == int(Status.OUTSIDE)
    if prev is not None and prev.left is not None:
        left |= prev.left & ~ok & ~(status <= USABLE).any(0)
    return Carry(t=t_last, vals=vals, vel_u=vel_u, vel_v=vel_v, valid=ok, vel_known=known,
                 fit_zncc=fit, frame=frame, prev_frame=prev_frame, window_m=window_m,
                 rates=rates, left=left)


def gradient_rates(rows: Mapping[str, torch.Tensor], times: np.ndarray, names, prev: Carry | None,
                   ok: torch.Tensor, col) -> dict[str, torch.Tensor] | None:
    """name -> (N,) the rate of each displacement gradient (ux, uy, vx, vy) per time unit:
    the least-squares slope over a block's trusted rows (``rows`` (B, N) per field, times
    ``times`` (B,)) where a point has two or more of them, else the difference from the
    previous carry's value (``prev``) to the last row (``ok`` (N,): that row trusted;
    ``col(name, i)`` its values); 0 where neither is known. A specimen that deforms
    changes its gradients steadily: carried unchanged, the hourglass's dv/dy missed the next
    block's solutions by 8e-3 px/px (median; 0.12 px over the subset's half-width), the
    largest part of the carried guess's miss (by its rate: 1e-3)."""
    grads = [nm for nm in GRADIENTS if nm in names]
    if not grads:
        return None
    # the block's times to the device without waiting for it (pinned, not blocking)
    t = upload(torch.tensor(np.asarray(times, dtype=np.float64)), ok.device)
    trusted = rows["status"] <= USABLE  # (B, N)
    dtype = col(grads[0]).dtype  # (the carry's)
    vals = torch.stack([rows[nm].to(torch.float64).to(dtype) for nm in grads])
    trusted = trusted & torch.isfinite(vals).all(0)  # (B, N)
    w = trusted.to(vals.dtype)
    cnt = w.sum(0)
    tb = t.to(vals.dtype).unsqueeze(1)  # (B, 1)
    tm = (w * tb).sum(0) / cnt.clamp(min=1)
    tc = (tb - tm) * w  # (B, N) centred times of the trusted rows, 0 elsewhere
    den = (tc * tc).sum(0)
    x = torch.where(trusted, vals, 0.0)
    slope = (tc * x).sum(1) / den.clamp(min=1e-30)  # (G, N)
    fit = (cnt >= 2) & (den > 0)
    out = {}
    for g, nm in enumerate(grads):
        rate = torch.where(fit, slope[g], 0.0)
        if prev is not None and float(times[-1]) > prev.t:  # one row: from the previous carry
            fd = (col(nm) - prev.vals[nm].to(vals.dtype)) / (float(times[-1]) - prev.t)
            use = ~fit & ok & prev.valid & torch.isfinite(fd)
            rate = torch.where(use, fd, rate)
        out[nm] = torch.nan_to_num(rate, nan=0.0, posinf=0.0, neginf=0.0)
    return out
