"""What a result file records beside its fields, and how it is laid out in HDF5: the
software version and time stamps, the run's settings as JSON and their differences (resume
checks them), the chunk shape and creation properties of the datasets, and one-line reasons
for the OS errors a write can meet."""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import json
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from torch_stsdic.core.config import DEFAULT_MEMORY_MB

__all__ = ["software_version", "now_stamp", "json_default", "config_json", "as_numpy", "chunks",
           "OS_REASONS", "os_reason", "WriteError", "write_error", "written_atomically",
           "creation_properties", "flat_config", "diff_config"]


def software_version() -> str:
    try:
        from importlib.metadata import version

        return version("torch_stsdic")
    except Exception:
        return "unknown"


def now_stamp() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, torch.Tensor):
        return o.detach().cpu().tolist()
    if isinstance(o, (Path, torch.dtype, torch.device)):
        return str(o)
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    raise TypeError(f"config value of type {type(o).__name__} is not JSON serialisable")


def config_json(config: Mapping[str, Any]) -> str:
    return json.dumps(dict(config), sort_keys=True, default=json_default, allow_nan=True)


def as_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def chunks(n_rows: int, n_cols: int, itemsize: int) -> tuple[int, int] | None:
    if n_rows == 0 or n_cols == 0:
        return None
    cols = min(n_cols, max(1, (4 << 20) // itemsize))  # <= 4 MiB per row chunk
    rows = max(1, min(n_rows, (64 << 10) // (cols * itemsize)))  # >= ~64 KiB when N small
    return rows, cols


#: short reasons for the errors a result file meets (HDF5's own messages run to a paragraph)
OS_REASONS = {errno.ENOSPC: "no space left on the device (the disk is full)",
            errno.EDQUOT: "disk quota exceeded", errno.EROFS: "read-only file system",
            errno.EACCES: "permission denied", errno.EPERM: "permission denied",
            errno.EFBIG: "file too large (file-size limit of the system or file system)",
            errno.EIO: "input/output error (device lost?)"}


def os_reason(exc: BaseException) -> str:
    """A short reason for an OSError, e.g. 'no space left on the device (the disk is full)';
    HDF5's own text when the error number is unknown."""
    text = " ".join(str(exc).split())
    code = getattr(exc, "errno", None)
    if code is None:  # HDF5 puts the number in the text: "errno = 28"
        m = re.search(r"errno = (\d+)", text)
        code = int(m.group(1)) if m else None
    if code in OS_REASONS:
        return OS_REASONS[code]
    strerror = getattr(exc, "strerror", None)  # the OS's words, without '[Errno N]' and paths
    if isinstance(exc, OSError) and strerror and "errno =" not in strerror:
        return strerror[:1].lower() + strerror[1:]
    return text


class WriteError(OSError):
    """A file that could not be written, its message one line naming it: 'cannot write
    PATH: no space left on the device (the disk is full)'."""


def is_io_error(exc: BaseException) -> bool:
    """An OSError, or an HDF5 error that carries the OS's error number ("errno = 28")."""
    return isinstance(exc, OSError) or (isinstance(exc, Exception) and "errno =" in str(exc))


def write_error(path: Any, exc: BaseException, what: str = "write") -> WriteError:
    """``exc`` met while writing ``path`` as a :class:`WriteError` ('cannot write PATH:
    reason'; ``what``: the verb, e.g. "create the result file")."""
    if isinstance(exc, WriteError):
        return exc
    code = getattr(exc, "errno", None)
    if code is None:
        m = re.search(r"errno = (\d+)", str(exc))
        code = int(m.group(1)) if m else None
    return WriteError(code, f"cannot {what} {path}: {os_reason(exc)}")


@contextlib.contextmanager
def written_atomically(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Write ``path`` whole or not at all: yields a temporary name beside it (same folder
    and suffix) to write to, renamed over ``path`` when the block ends; on any error the
    temporary file is deleted (a full disk leaves no truncated or empty file, an existing
    ``path`` stays as it was) and I/O errors are raised as :class:`WriteError` naming
    ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if is_io_error(exc):
            raise write_error(path, exc) from exc
        raise


def creation_properties() -> Any:
    """Dataset creation properties: storage allocated (and filled) when the dataset is
    created, so writing rows later only overwrites data in place and never changes the
    file's metadata (nothing for a killed process to leave half-written)."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    return dcpl


def flat_config(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested settings as one level with dotted keys ({"track": {"step": 5}} -> track.step)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping) and v:
            out.update(flat_config(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


#: settings whose value "not given" (None) stands for a value files wrote before None was
#: possible: the two compare equal (``memory_mb``: 256 MiB, written until 2026-11-30)
_NOT_GIVEN = {"memory_mb": DEFAULT_MEMORY_MB}


def diff_config(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(dotted key, "key: old -> new") for every setting that differs (a setting not given,
    None, equal to the value it stands for: :data:`_NOT_GIVEN`)."""
    old, new = flat_config(old), flat_config(new)
    for d in (old, new):
        for k, v in _NOT_GIVEN.items():
            if k in d and d[k] is None:
                d[k] = v
    out = []
    for k in sorted(set(old) | set(new)):
        if k not in old:
            text = f"{k}: (absent) -> {new[k]!r}"
        elif k not in new:
            text = f"{k}: {old[k]!r} -> (absent)"
        elif old[k] != new[k]:
            text = f"{k}: {old[k]!r} -> {new[k]!r}"
        else:
            continue
        out.append((k, text if len(text) < 200 else text[:197] + "..."))
    return out
