"""How a result file stores a field's values: its dtype and fill (float32 and NaN; status,
iterations and window half-width as small integers), and values rounded exactly as stored
(what a resumed run reads back), of numpy arrays on the host or of tensors where they are."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from torch_stsdic.core.status import Status
from torch_stsdic.io.run_record import as_numpy

__all__ = ["INT_FIELDS", "field_dtype", "as_stored", "as_stored_tensors"]

_INT_FIELDS: dict[str, tuple[type, int]] = {"status": (np.int8, int(Status.NOT_COMPUTED)),
                                             "iterations": (np.int16, -1), "m": (np.int8, -1)}
#: the fields stored as integers (no unit, no conversion)
INT_FIELDS = tuple(_INT_FIELDS)
#: the torch dtype of each dtype a result file stores
_TORCH_DTYPES = {np.float32: torch.float32, np.int8: torch.int8, np.int16: torch.int16}


def field_dtype(name: str) -> tuple[type, float | int]:
    """The numpy dtype field ``name`` is stored in, and its fill (a row not written yet)."""
    return _INT_FIELDS.get(name, (np.float32, np.nan))


def as_stored(values: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Values rounded exactly as a result file stores them (float32; status int8;
    iterations int16, clipped): what a resumed run reads back."""
    out = {}
    for name, val in values.items():
        a = np.asarray(as_numpy(val))
        dt = field_dtype(name)[0]
        if np.issubdtype(dt, np.integer):
            info = np.iinfo(dt)
            a = np.clip(a, info.min, info.max)
        out[name] = a.astype(dt)
    return out


def as_stored_tensors(values: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """:func:`as_stored` of tensors, where they are (a run's device: no copy to the host):
    the same numbers (float32 rounding, integer fields clipped) as torch tensors."""
    out = {}
    for name, val in values.items():
        dt = np.dtype(field_dtype(name)[0])
        if np.issubdtype(dt, np.integer):
            info = np.iinfo(dt)
            val = val.clamp(info.min, info.max)
        out[name] = val.to(_TORCH_DTYPES[dt.type])
    return out
