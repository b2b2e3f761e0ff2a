"""Physical units of result fields: the calibration a result file records, and what it does to
each field.

A run computes and stores everything in pixels and in its time unit (frames unless
timestamps are given). The file records the calibration as root attributes (:data:`ATTRS`):
``scale`` (length units per pixel, e.g. 0.02 mm/px; absent: pixels), ``unit`` (e.g. "mm")
and ``time_unit`` (e.g. "frame", "s"). Exports and figures convert with :class:`Units`:

- a field's dimension comes from its name (:meth:`Units.dims`): ``u, v, x, y`` are lengths;
  each trailing ``x``/``y`` of ``u``/``v`` divides by a length (``ux`` is dimensionless,
  ``uxx`` per length), a trailing ``t`` divides by time (``ut``: length per time);
  ``exx, eyy, exy`` and ``zncc`` are dimensionless, ``*_rate`` per time; suffixes such as
  ``_std`` or ``_smooth`` keep the dimension of the field they qualify (``u_std``: length);
  ``status``, ``iterations``, ``m`` are integers without unit. A name not known here is
  exported unchanged, without unit.
- values are multiplied by ``scale ** length_power`` (time is never rescaled).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ATTRS", "Units", "check_calibration", "units_of"]

#: root attributes of a result file that hold the calibration
ATTRS = ("scale", "unit", "time_unit")

#: integer fields: no unit, never converted
_COUNTS = {"status", "iterations", "m"}
#: dimensionless float fields
_PURE = {"zncc", "exx", "eyy", "exy", "e1", "e2", "theta"}
#: name suffixes that keep the dimension of the field they qualify
_QUALIFIERS = ("_std", "_smooth", "_raw", "_mean", "_true", "_error")
_DISPLACEMENT = re.compile(r"^([uv])([xy]*)(t?)$")


def check_calibration(scale: Any, unit: Any, time_unit: Any = None) -> dict[str, Any]:
    """The calibration as file attributes (``scale`` only when given); ValueError naming the
    argument for a scale that is not a finite number > 0, a unit without a scale (or a
    scale without a unit), or an empty unit."""
    out: dict[str, Any] = {}
    if scale is not None:
        try:
            s = float(scale)
        except (TypeError, ValueError):
            raise ValueError(f"scale: expected a number (length units per px), got "
                             f"{scale!r}") from None
        if not math.isfinite(s) or s <= 0:
            raise ValueError(f"scale: must be a finite number > 0 (length units per px), "
                             f"got {scale!r}")
        if not isinstance(unit, str) or not unit.strip():
            raise ValueError("unit: a scale needs its length unit, e.g. unit='mm' "
                             "(scale is length units per px)")
        out["scale"], out["unit"] = s, unit.strip()
    elif unit is not None and str(unit).strip() not in ("", "px"):
        raise ValueError(f"unit: {unit!r} needs a scale (its length per px)")
    else:
        out["unit"] = "px"
    if time_unit is not None:
        if not isinstance(time_unit, str) or not time_unit.strip():
            raise ValueError(f"time_unit: expected a non-empty name, e.g. 's', got {time_unit!r}")
        out["time_unit"] = time_unit.strip()
    return out


@dataclass(frozen=True)
class Units:
    """The calibration of a result: ``scale`` length units per px (None: pixels), the length
    ``unit`` ("px" without scale) and the ``time_unit`` of times and rates."""

    scale: float | None = None
    unit: str = "px"
    time_unit: str = "frame"

    @property
    def length_factor(self) -> float:
        """Length units per px (1 without calibration)."""
        return 1.0 if self.scale is None else float(self.scale)

    def dims(self, name: str) -> tuple[int, int] | None:
        """(length power, time power) of field ``name``; None for integer fields and
        unknown names (no unit)."""
        if name in _COUNTS:
            return None
        if name in ("x", "y"):
            return (1, 0)
        if name in _PURE:
            return (0, 0)
        if name.endswith("_rate"):
            base = self.dims(name[: -len("_rate")])
            return None if base is None else (base[0], base[1] - 1)
        for q in _QUALIFIERS:
            if name.endswith(q) and len(name) > len(q):
                return self.dims(name[: -len(q)])
        hit = _DISPLACEMENT.match(name)
        if hit:
            return (1 - len(hit.group(2)), -len(hit.group(3)))
        return None

    def factor(self, name: str) -> float:
        """What the stored (px) values of ``name`` are multiplied by to be in :meth:`unit_of`."""
        d = self.dims(name)
        return 1.0 if d is None else self.length_factor ** d[0]

    def convert(self, name: str, values: Any) -> np.ndarray:
        """``values`` of field ``name`` in the physical unit (integer fields unchanged)."""
        a = np.asarray(values)
        f = self.factor(name)
        return a if f == 1.0 or a.dtype.kind in "iub" else a * f

    def unit_of(self, name: str) -> str:
        """The unit of field ``name`` as text: "mm", "mm/s", "1/frame", "-" (dimensionless),
        "" (integer or unknown field)."""
        d = self.dims(name)
        if d is None:
            return ""
        lp, tp = d
        num = self.unit if lp == 1 else (f"{self.unit}^{lp}" if lp > 1 else "")
        den = []
        if lp < 0:
            den.append(self.unit if lp == -1 else f"{self.unit}^{-lp}")
        if tp < 0:
            den.append(self.time_unit if tp == -1 else f"{self.time_unit}^{-tp}")
        if not num and not den:
            return "-"
        if not den:
            return num
        return f"{num or '1'}/{den[0]}" if len(den) == 1 else f"{num or '1'}/({' '.join(den)})"

    def label(self, name: str, quantity: str | None = None) -> str:
        """Axis or colour-bar label: ``"u (mm)"``, ``"ut (mm/s)"``, ``"exx (-)"``, ``"status"``."""
        u = self.unit_of(name)
        q = quantity or name
        return f"{q} ({u})" if u else q

    @property
    def time_label(self) -> str:
        """Label of a time axis, e.g. ``"time (frame)"``."""
        return f"time ({self.time_unit})"

    def to_attrs(self) -> dict[str, Any]:
        """The file attributes of this calibration."""
        out: dict[str, Any] = {"unit": self.unit, "time_unit": self.time_unit}
        if self.scale is not None:
            out["scale"] = self.scale
        return out


def units_of(attrs: Mapping[str, Any]) -> Units:
    """The :class:`Units` recorded in result-file attributes (pixels and frames when none)."""
    scale = attrs.get("scale")
    scale = None if scale is None or not np.isfinite(float(scale)) else float(scale)
    unit = str(attrs.get("unit", "px" if scale is None else "unit"))
    return Units(scale=scale, unit=unit, time_unit=str(attrs.get("time_unit", "frame")))
