"""Frame specifications ("0:5", "-1", "3,7,9") and natural file order (img2 before img10)."""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np

__all__ = ["InputError", "natural_sort_key", "parse_frame_spec"]


class InputError(ValueError):
    """Bad input images, arrays, timestamps or frame specifications (message names the culprit)."""




def natural_sort_key(s: str | os.PathLike[str]) -> tuple[Any, ...]:
    """Sort key putting ``frame_2`` before ``frame_10`` (digit runs compare as integers)."""
    parts = re.split(r"(\d+)", os.fspath(s))
    return tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts))


def parse_frame_spec(spec: str | int, n: int) -> list[int]:
    """Parse a CLI frame specification into frame indices in ``0..n-1``.

    Accepts a single index (``"0"``, ``"-1"``), Python-style slices (``"0:5"``, ``"10:100:2"``,
    ``"-5:"``, ``":"``), ``"all"``, and comma-separated combinations (``"3,7,9"``,
    ``"0:5,10"``). Negative indices count from the end. Slices follow Python semantics
    (bounds are clipped to the series); single indices out of range are an error. The result
    keeps the given order with duplicates dropped; an empty result is an error.
    """
    if isinstance(spec, (int, np.integer)):
        spec = str(int(spec))
    if not isinstance(spec, str):
        raise InputError(f"frame spec must be a string, got {type(spec).__name__}")
    n = int(n)
    if n < 0:
        raise InputError(f"number of frames must be >= 0, got {n}")
    text = spec.strip()
    if not text:
        raise InputError("empty frame spec")
    out: list[int] = []
    seen: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise InputError(f"frame spec {spec!r}: empty item")
        if part.lower() == "all":
            idx = list(range(n))
        elif ":" in part:
            bits = [b.strip() for b in part.split(":")]
            if len(bits) > 3:
                raise InputError(f"frame spec {spec!r}: bad slice {part!r}")
            try:
                vals = [int(b) if b else None for b in bits]
            except ValueError:
                raise InputError(f"frame spec {spec!r}: bad slice {part!r}") from None
            if len(vals) == 3 and vals[2] == 0:
                raise InputError(f"frame spec {spec!r}: slice step cannot be 0")
            idx = list(range(n))[slice(*vals)]
        else:
            try:
                i = int(part)
            except ValueError:
                raise InputError(f"frame spec {spec!r}: {part!r} is not an integer") from None
            if not -n <= i < n:
                raise InputError(f"frame spec {spec!r}: index {i} out of range for {n} frames")
            idx = [i % n]
        for i in idx:
            if i not in seen:
                seen.add(i)
                out.append(i)
    if not out:
        raise InputError(f"frame spec {spec!r} selects no frame out of {n}")
    return out
