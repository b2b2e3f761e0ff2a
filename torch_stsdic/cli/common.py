"""Small helpers shared by the sub-commands: numpy views, durations, devices, frame lists."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torch_stsdic.cli.errors import CommandError, UsageError


def to_numpy(a: Any) -> np.ndarray:
    """numpy view of a tensor or array-like (detached, on the CPU)."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def fmt_time(seconds: float) -> str:
    """A duration for people: '4.2 s', '3 min 20 s', '2 h 5 min'."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    m, s = divmod(seconds, 60)
    if m < 60:
        return f"{int(m)} min {s:.0f} s"
    h, m = divmod(m, 60)
    return f"{int(h)} h {int(m)} min"


def check_device(device: str) -> Any:
    """``--device`` as a ``torch.device``; UsageError if it does not exist on this machine."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError) as exc:
        raise UsageError(f"--device {device}: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {device}: CUDA is not available on this machine")
    if dev.type == "mps" and not (
        getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()
    ):
        raise UsageError(f"--device {device}: MPS is not available on this machine")
    return dev


def span(frames: Sequence[int]) -> str:
    """Frame numbers for an error message, shortened: '0, 1, 2, ..., 99 (100 frames)'."""
    f = list(frames)
    if len(f) > 6:
        return f"{f[0]}, {f[1]}, {f[2]}, ..., {f[-1]} ({len(f)} frames)"
    return ", ".join(str(x) for x in f)


def check_folder(folder: Path, shown: str) -> None:
    """``folder`` (or, if missing, the nearest existing folder above it, where it will be
    created) takes files: a CommandError beginning with ``shown`` (e.g. '--out plots/')
    before any work."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise CommandError(f"{shown}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CommandError(f"{shown}: the folder {existing} is not writable (read-only or no "
                           "permission); choose another --out")
