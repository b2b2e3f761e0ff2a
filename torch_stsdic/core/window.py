"""Subset windows: which pixels around a point of interest take part, and with what weight."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["SubsetWindow", "SquareWindow", "CircularWindow", "GaussianWindow", "make_window",
           "effective_pixels", "weight_stats", "BUILT_IN_WINDOWS"]


def effective_pixels(weights: torch.Tensor) -> float:
    """``(sum w)^2 / sum w^2``: the number of equally weighted pixels that average noise as
    much as the weights ``weights`` (S,) do (S for a square window)."""
    w = weights.double()
    return float(w.sum() ** 2 / (w * w).sum())


def weight_stats(weights: torch.Tensor) -> tuple[float, bool, float]:
    """Host numbers of the weights ``weights`` (S,) that every solve asks for: their sum,
    whether they are all 0 or 1 (their squares are themselves), and
    :func:`effective_pixels`."""
    w = weights.detach().double().cpu()
    return float(w.sum()), bool(((w * w) == w).all()), effective_pixels(w)


class SubsetWindow(nn.Module):
    """Base class. ``offsets(dtype, device)`` -> (S, 2) pixel offsets (dx, dy) from the POI and
    ``weights`` -> (S,) non-negative weights. ``half`` is the half-size in px (the subset spans
    -half..half in x and y)."""

    def __init__(self, size: int) -> None:
        super().__init__()
        if not isinstance(size, int) or size < 3 or size % 2 == 0:
            raise ValueError(f"subset_size must be an odd integer >= 3, got {size!r}")
        self.size = size
        self.half = size // 2

    def _square(self, dtype: torch.dtype, device) -> torch.Tensor:
        r = torch.arange(-self.half, self.half + 1, dtype=dtype, device=device)
        dy, dx = torch.meshgrid(r, r, indexing="ij")
        return torch.stack([dx.reshape(-1), dy.reshape(-1)], dim=-1)

    def offsets_and_weights(self, dtype=torch.float64, device=None):
        """(S, 2) offsets (dx, dy) in px and (S,) weights."""
        raise NotImplementedError

    def effective_pixels(self) -> float:
        """:func:`effective_pixels` of this window's weights (worked out once: the checks ask
        for it in every block)."""
        return self.weight_stats()[2]

    def weight_stats(self) -> tuple[float, bool, float]:
        """:func:`weight_stats` of this window's weights, worked out once."""
        if getattr(self, "_weight_stats", None) is None:
            self._weight_stats = weight_stats(self.offsets_and_weights()[1])
        return self._weight_stats

    def extra_repr(self) -> str:
        return f"size={self.size}"


class SquareWindow(SubsetWindow):
    """All (2h+1)^2 pixels, equal weight: the classical square subset."""

    def offsets_and_weights(self, dtype=torch.float64, device=None):
        off = self._square(dtype, device)
        return off, torch.ones(off.shape[0], dtype=dtype, device=device)


class CircularWindow(SubsetWindow):
    """Pixels within radius ``half + 0.5`` of the POI, equal weight (rotation-invariant)."""

    def offsets_and_weights(self, dtype=torch.float64, device=None):
        off = self._square(dtype, device)
        keep = (off * off).sum(-1) <= (self.half + 0.5) ** 2
        off = off[keep]
        return off, torch.ones(off.shape[0], dtype=dtype, device=device)


class GaussianWindow(SubsetWindow):
    """Square subset with Gaussian weights exp(-r^2 / (2 sigma^2)); default sigma = half / 2.

    Down-weights the subset's rim: less sensitive to strain gradients across the subset."""

    def __init__(self, size: int, sigma: float | None = None) -> None:
        super().__init__(size)
        self.sigma = float(sigma) if sigma is not None else max(self.half / 2.0, 1.0)

    def offsets_and_weights(self, dtype=torch.float64, device=None):
        off = self._square(dtype, device)
        w = torch.exp(-(off * off).sum(-1) / (2.0 * self.sigma**2))
        return off, w

    def extra_repr(self) -> str:
        return f"size={self.size}, sigma={self.sigma}"


_WINDOWS = {"square": SquareWindow, "circular": CircularWindow, "gaussian": GaussianWindow}
#: the windows whose offsets and weights their settings (``extra_repr``) alone decide
BUILT_IN_WINDOWS = tuple(_WINDOWS.values())


def make_window(window: str | SubsetWindow, size: int) -> SubsetWindow:
    """A window module from a name ("square", "circular", "gaussian") or pass-through."""
    if isinstance(window, SubsetWindow):
        return window
    try:
        return _WINDOWS[str(window).lower()](size)
    except KeyError:
        raise ValueError(f"window must be one of {sorted(_WINDOWS)}, got {window!r}") from None
