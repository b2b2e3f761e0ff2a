"""The noise a template made from the series shares with the windows' frames: each sampled
frame's weight in the template at each POI, the registration's noise, and the factors they
put on the predicted variances of the results
(:func:`~torch_stsdic.core.uncertainty.shared_frame_factors`; docs/validation/window_length.md,
"Predicted error")."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_stsdic.core.uncertainty import shared_frame_factors
from torch_stsdic.movie.frames import window_frames

__all__ = ["TemplateShares", "REGISTRATION_GAIN"]

#: the variance of the template's registration error over what its local fits' variance
#: factor ``w^T R w`` predicts, measured: a rigid render's error against the template in its
#: centre frame (m = 5, 11 frames: the registration alone) regressed on the fitted mean of
#: its frames' classical errors (correlation 0.65-0.91) has slopes 0.51-0.84 (squared: mean
#: 0.51, 8 renders, steps 10 and 16); sample 3's centre frame reads 0.5 of the prediction.
#: Not derived: the overlap correlation alone is ~10 % high (docs/validation/window_length.md).
#: Six more renders (seeds 1-6 of tests/test_template_noise.py's, fits over 25 POIs and over
#: 25 .. 81) read 1.19-1.25x the variance 0.5 predicted in their centre frames: 0.6
REGISTRATION_GAIN = 0.6


@dataclass
class TemplateShares:
    """Each series frame's weight in the template at each POI.

    Attributes:
        rows: (T_series,) long, the row of ``share`` of each series frame (-1: not sampled).
        share: (F, N) float64, the sampled frames' weights (summing to 1 at every POI).
        share_sq: (N,) float64, the sum of their squares (the template's noise variance over
            one frame's, at the POI's low spatial frequencies).
        reference_frame: the series frame the frames were registered to (-1: none).
        registration: (N,) float64, the variance factor of that registration's local fits
            (None: not modelled here)."""

    rows: torch.Tensor
    share: torch.Tensor
    share_sq: torch.Tensor
    reference_frame: int = -1
    registration: torch.Tensor | None = None

    @classmethod
    def make(cls, frames: list[int], share: torch.Tensor, n_series: int,
             reference_frame: int = -1, registration: torch.Tensor | None = None,
             device: torch.device | str | None = None) -> TemplateShares:
        """From the sampled ``frames`` (F,) (series indices) and their weights (F, N), on
        ``device`` (default ``share``'s): a run's, where its blocks ask for them (every
        block: a copy from the host there would wait for a GPU each time)."""
        dev = share.device if device is None else torch.device(device)
        rows = torch.full((n_series,), -1, dtype=torch.long)
        rows[torch.as_tensor(frames, dtype=torch.long)] = torch.arange(len(frames))
        share = share.to(device=dev, dtype=torch.float64)
        return cls(rows=rows.to(dev), share=share, share_sq=(share * share).sum(0),
                   reference_frame=int(reference_frame),
                   registration=None if registration is None else registration.to(
                       device=dev, dtype=torch.float64))

    def of(self, win: torch.Tensor) -> torch.Tensor:
        """(B, N, T) the weights of the frames ``win`` (B, T) (series indices)."""
        r = self.rows.to(win.device)[win]  # (B, T)
        vals = self.share.to(win.device)[r.clamp(min=0)]  # (B, T, N)
        return torch.where((r >= 0)[..., None], vals, 0.0).permute(0, 2, 1)

    def variance_factors(self, ks: torch.Tensor, m_used: torch.Tensor, times: torch.Tensor,
                         rho: float, segments: torch.Tensor | None = None,
                         m_max: int | None = None) -> torch.Tensor:
        """(B, N, 2) the factors of the predicted variances of u, v and of ut, vt of the
        results at targets ``ks`` (B,) (series indices) solved with half-widths ``m_used``
        (B, N) (< 0: none, factor 1), ``times`` (T_series,) the series' frame times, ``rho``
        the noise ratio the solver was told. ``m_max``: the longest half-width there can be
        (the run's m): every half-width 0 .. m_max is worked out for all rows and each row
        takes its own, with no host synchronisation (None: only the half-widths present,
        read on the host)."""
        b, n = m_used.shape
        dev = m_used.device
        out = torch.ones(b, n, 2, dtype=torch.float64, device=dev)
        sq = self.share_sq.to(dev)
        reg = None if self.registration is None else REGISTRATION_GAIN * self.registration.to(dev)
        ks, times = ks.to(dev), times.to(dev)
        if m_max is not None:
            for m in range(int(m_max) + 1):
                win = window_frames(ks, m, int(self.rows.shape[0]),
                                    None if segments is None else segments.to(dev))
                dt = (times[win] - times[ks][:, None]).double()  # (B, T)
                f = shared_frame_factors(
                    dt.repeat_interleave(n, 0), self.of(win).reshape(b * n, -1), sq.repeat(b),
                    rho, reference=(win == self.reference_frame).repeat_interleave(n, 0),
                    registration=None if reg is None else reg.repeat(b))
                out = torch.where((m_used == m).unsqueeze(-1), f.reshape(b, n, 2), out)
            return out
        for m in torch.unique(m_used[m_used >= 0]).tolist():
            win = window_frames(ks, int(m), int(self.rows.shape[0]),
                                None if segments is None else segments.to(dev))
            dt = (times[win] - times[ks][:, None]).double()
            bi, ni = torch.nonzero(m_used == m, as_tuple=True)
            out[bi, ni] = shared_frame_factors(
                dt[bi], self.of(win)[bi, ni], sq[ni], rho,
                reference=(win == self.reference_frame)[bi],
                registration=None if reg is None else reg[ni])
        return out

