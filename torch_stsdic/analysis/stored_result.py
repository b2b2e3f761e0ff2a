"""A run's :class:`~torch_stsdic.analysis.result.TrackResult` backed by its result file: the
(F, N) fields are read from the file when first asked for, so a run that writes a file keeps
none of them in memory (a long movie: frames x points)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.io.file_fields import FileFields

__all__ = ["lazy_fields", "StoredTrackResult"]

#: the (F, N) attributes of a TrackResult read from the file (besides ``gradients``, ``std``)
LAZY = ("u", "v", "ut", "vt", "zncc", "status", "iterations", "m")
#: integer fields as a TrackResult holds them (on the CPU, as an in-memory run gives them)
_INT = {"status": torch.int8, "iterations": torch.int32, "m": torch.int8}


def _as_held(dtype: torch.dtype, device: torch.device | str):
    """``convert`` of :class:`~torch_stsdic.io.file_fields.FileFields` that gives a stored
    field as the TrackResult attribute of its name holds it: floats at ``dtype`` on
    ``device`` (the stored float32 values exactly), integers on the CPU."""

    def convert(name: str, a: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(a))
        return t.to(_INT[name]) if name in _INT else t.to(device=device, dtype=dtype)
    return convert


def lazy_fields(path: str | Path, names: Mapping[str, str], dtype: torch.dtype,
               device: torch.device | str) -> FileFields:
    """name -> (F, N) tensor, read from result file ``path`` (dataset ``names[name]``) on
    first access and kept (what the caller asks for)."""
    return FileFields(path, names, _as_held(dtype, device))


class StoredTrackResult(TrackResult):
    """A :class:`TrackResult` whose (F, N) fields (u, v, ut, vt, zncc, status, iterations,
    m, the gradients and the std) are read from its result file when first used (then
    kept); everything else (points, frames, times, reference frames, config, info) is held.
    The numbers are those of an in-memory result of the same rows as stored."""

    @classmethod
    def open(cls, path: str | Path, names: Mapping[str, str], *, dtype: torch.dtype,
             device: torch.device | str, gradients: tuple[str, ...], std: tuple[str, ...],
             **held: Any) -> StoredTrackResult:
        """The result of file ``path``: attribute or field name -> its dataset
        (``names``), the gradient and std names, and the held attributes ``held``."""
        obj = cls.__new__(cls)
        for k, v in held.items():
            object.__setattr__(obj, k, v)
        obj.gradients = lazy_fields(path, {g: names[g] for g in gradients}, dtype, device)
        obj.std = lazy_fields(path, {s: names[f"{s}_std"] for s in std}, dtype, device)
        obj._fields = lazy_fields(path, {nm: names[nm] for nm in LAZY if nm in names}, dtype,
                                 device)
        return obj



    def select(self, frames: list[int] | None = None, points: torch.Tensor | None = None
               ) -> TrackResult:
        """The rows of series ``frames`` (in that order; None: all) at ``points`` (POI
        indices; None: all), as an in-memory :class:`TrackResult` of their own: only those
        rows are read from the file (a long movie's result a few frames at a time), the
        numbers those of :meth:`TrackResult.select` of the whole result."""
        rows = (list(range(int(self.frames.numel()))) if frames is None
                else [self.row_of(k) for k in frames])

        def get(name: str) -> Any:
            held = self.__dict__
            if name in held:  # set on the result: its rows
                return None if held[name] is None else held[name][rows]
            lazy = held.get("_fields")
            return lazy.read_rows(name, rows) if lazy is not None and name in lazy else None

        at = torch.as_tensor(rows, dtype=torch.long)
        part = TrackResult(
            points=self.points, frames=self.frames[at], times=self.times[at], u=get("u"),
            v=get("v"), ut=get("ut"), vt=get("vt"), zncc=get("zncc"), status=get("status"),
            iterations=get("iterations"), m=get("m"),
            gradients=_rows_of(self.gradients, rows), std=_rows_of(self.std, rows),
            reference_frames=self.reference_frames[at], config=self.config,
            info=dict(self.info))
        return part if points is None else part.select(None, points)


def _rows_of(fields: Mapping[str, Any], rows: list[int]) -> dict[str, Any]:
    """Rows ``rows`` of every field of ``fields`` (file-backed: only those rows read)."""
    if isinstance(fields, FileFields):
        return {k: fields.read_rows(k, rows) for k in fields}
    return {k: a[rows] for k, a in fields.items()}


def _lazy(name: str) -> property:
    """The attribute ``name`` of a :class:`StoredTrackResult`: a value set on it (e.g. by
    ``dataclasses.replace``), else its field read from the file (None where the file has
    none)."""

    def get(self: StoredTrackResult) -> Any:
        held = self.__dict__
        if name in held:
            return held[name]
        lazy = held.get("_fields")
        return lazy[name] if lazy is not None and name in lazy else None

    def put(self: StoredTrackResult, value: Any) -> None:
        self.__dict__[name] = value

    return property(get, put, doc=f"(F, N) {name}, read from the result file when first used")


for _name in LAZY:
    setattr(StoredTrackResult, _name, _lazy(_name))
