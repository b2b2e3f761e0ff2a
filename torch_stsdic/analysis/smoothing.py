"""Direct temporal smoothing of DIC results: the paper's Fig. 6 baseline (classical DIC,
then a moving local fit over ``span`` frames)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import TrackResult

__all__ = ["smooth_in_time", "temporal_smoothing"]


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
