"""The (F, N) fields of a result file, each read when first asked for and then kept: what a
figure, an export or a run's returned result reads of a long movie's file is the fields it
uses, not all of them."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py

__all__ = ["FileFields"]


class FileFields(Mapping[str, Any]):
    """name -> (F, N) field of result file ``path`` (its dataset ``names[name]``; a list of
    names: the datasets of those names), read on first access and kept. ``convert(name,
    array)`` turns the stored array into what the caller holds (default: the numpy array)."""

    def __init__(self, path: str | Path, names: Mapping[str, str] | Sequence[str],
                 convert: Callable[[str, Any], Any] | None = None) -> None:
        self.path = Path(path)
        self.names = dict(names) if isinstance(names, Mapping) else {n: n for n in names}
        self._convert = convert
        self._held: dict[str, Any] = {}

    def __getitem__(self, name: str) -> Any:
        if name not in self._held:
            if name not in self.names:
                raise KeyError(name)
            # the file was checked when its fields were listed (read_results, a run's sink)
            with h5py.File(self.path, "r", locking=False) as f:
                a = f[self.names[name]][()]
            self._held[name] = a if self._convert is None else self._convert(name, a)
        return self._held[name]

    def read_rows(self, name: str, rows: Sequence[int]) -> Any:
        """Rows ``rows`` (in that order) of field ``name``, as ``convert`` gives them: read
        from the file without keeping the field (the held field's rows where it was read)."""
        if name not in self.names:
            raise KeyError(name)
        rows = [int(r) for r in rows]
        if name in self._held:
            return self._held[name][rows]
        uniq = sorted(set(rows))
        with h5py.File(self.path, "r", locking=False) as f:
            ds = f[self.names[name]]
            if uniq and uniq == list(range(uniq[0], uniq[-1] + 1)):
                a = ds[uniq[0]:uniq[-1] + 1]
            else:
                a = ds[uniq] if uniq else ds[0:0]
        if uniq != rows:
            at = {r: i for i, r in enumerate(uniq)}
            a = a[[at[r] for r in rows]]
        return a if self._convert is None else self._convert(name, a)

    def __contains__(self, name: object) -> bool:
        # by name, reading nothing (Mapping's own test would read the field)
        return name in self.names

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        return f"<FileFields {sorted(self.names)} of {self.path} ({len(self._held)} read)>"
