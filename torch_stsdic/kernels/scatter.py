"""Sums of values into bins (a splat, a histogram with weights) that give the same numbers on
every run: each bin's values added in the order they come.

On the CPU ``index_add_`` adds sequentially in input order (twice as fast as
``index_put_(..., accumulate=True)`` there); on CUDA ``index_add_`` adds with atomics, in any
order, so there ``index_put_`` with ``accumulate=True`` (sorted by bin, then summed in order)
is used.
"""

from __future__ import annotations

import torch

__all__ = ["scatter_add_"]


def scatter_add_(out: torch.Tensor, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Add ``values`` (M,) to the bins ``index`` (M,) (integers in ``[0, len(out))``) of the
    1-D ``out``, in place, deterministic on every device; returns ``out``."""
    index, values = index.reshape(-1), values.reshape(-1)
    if index.numel() != values.numel():
        raise ValueError(f"scatter_add_: {index.numel()} indices for {values.numel()} values")
    if out.dim() != 1:
        raise ValueError(f"scatter_add_: out must be 1-D, got shape {tuple(out.shape)}")
    values = values.to(out.dtype)
    if out.device.type == "cuda":
        return out.index_put_((index,), values, accumulate=True)
    return out.index_add_(0, index, values)
