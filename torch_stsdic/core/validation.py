"""Input checks at the API edge: tensors or arrays in, clear errors naming the argument."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["as_image", "as_series", "as_points", "as_times", "check_init", "check_pixel_dtype",
           "check_pixels", "resolve_dtype"]

_DTYPES = {None: None, "float32": torch.float32, "float64": torch.float64}


def resolve_dtype(x: torch.Tensor, dtype: str | torch.dtype | None) -> torch.dtype:
    """The compute dtype: the requested one, else the input's float dtype (float32 for ints)."""
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype is not None:
        return _DTYPES[dtype]
    if x.dtype in (torch.float64, torch.float32):
        return x.dtype
    return torch.float32


def _to_tensor(x, name: str) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    if isinstance(x, np.ndarray) or isinstance(x, (list, tuple)):
        try:
            arr = np.asarray(x)
        except Exception as exc:  # ragged lists etc.
            raise TypeError(f"{name}: cannot be converted to an array ({exc})") from None
        if arr.dtype == np.uint16:
            arr = arr.astype(np.int32)
        elif arr.dtype == np.uint32:
            arr = arr.astype(np.int64)
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            raise TypeError(f"{name}: must be numeric, got dtype {arr.dtype}")
        return torch.from_numpy(np.ascontiguousarray(arr))
    raise TypeError(f"{name}: expected a torch.Tensor or numpy array, got {type(x).__name__}")


def check_pixel_dtype(x: torch.Tensor | np.ndarray, name: str) -> None:
    """Images hold real numbers, integer or float: TypeError for bool, complex and others."""
    kind = x.dtype.kind if isinstance(x, np.ndarray) else (
        "c" if x.is_complex() else "b" if x.dtype == torch.bool else "f")
    if kind not in "iuf":
        raise TypeError(f"{name}: pixels must be real numbers (integer or float), got dtype "
                        f"{str(x.dtype).replace('torch.', '')}")


def check_pixels(x: torch.Tensor | np.ndarray, name: str) -> None:
    """The one rule for images at every entry point (``solve_window``, ``nn.STSDIC``,
    reference images of ``track`` / ``plan_run``; arrays given to ``load_series`` are checked
    frame by frame as they are read): :func:`check_pixel_dtype`, and every pixel finite
    (ValueError with the count of NaN / inf pixels)."""
    check_pixel_dtype(x, name)
    if isinstance(x, np.ndarray):
        bad = int((~np.isfinite(x)).sum()) if x.dtype.kind == "f" else 0
    else:
        bad = int((~torch.isfinite(x)).sum()) if x.is_floating_point() else 0
    if bad:
        raise ValueError(f"{name}: contains {bad} non-finite pixel(s) (NaN or inf)")


def _check_finite(x: torch.Tensor, name: str) -> None:
    check_pixels(x, name)


def as_image(x, name: str, dtype=None, device=None) -> torch.Tensor:
    """A single grey image (H, W) as a float tensor; colour and stacks are rejected."""
    t = _to_tensor(x, name)
    check_pixels(t, name)
    if t.dim() == 3 and t.shape[-1] in (3, 4) and t.shape[0] > 4:
        raise ValueError(
            f"{name}: shape {tuple(t.shape)} looks like a colour image (H, W, {t.shape[-1]}); "
            "convert it to grey first (torch_stsdic.io.load_series does this)"
        )
    if t.dim() == 3 and t.shape[0] == 1:
        t = t[0]
    if t.dim() != 2:
        raise ValueError(f"{name}: expected a grey image of shape (H, W), got {tuple(t.shape)}")
    out_dtype = resolve_dtype(t, dtype)
    t = t.to(device=device if device is not None else t.device, dtype=out_dtype)
    _check_finite(t, name)
    return t


def as_series(x, name: str, dtype, device, like: torch.Tensor, m: int = 0) -> torch.Tensor:
    """A (T, H, W) float stack matching ``like`` (H, W); (H, W) is accepted as one frame."""
    t = _to_tensor(x, name)
    check_pixels(t, name)
    if t.dim() == 4 and t.shape[-1] in (3, 4):
        raise ValueError(
            f"{name}: shape {tuple(t.shape)} looks like colour frames (T, H, W, {t.shape[-1]}); "
            "convert them to grey first"
        )
    if t.dim() == 4 and t.shape[1] == 1:
        t = t[:, 0]
    if t.dim() == 2:
        t = t.unsqueeze(0)
    if t.dim() != 3:
        raise ValueError(f"{name}: expected frames of shape (2m+1, H, W), got {tuple(t.shape)}")
    if tuple(t.shape[-2:]) != tuple(like.shape[-2:]):
        raise ValueError(
            f"{name}: frame size {tuple(t.shape[-2:])} differs from the reference "
            f"{tuple(like.shape[-2:])}"
        )
    t = t.to(device=device, dtype=dtype)
    _check_finite(t, name)
    return t


def as_points(x, name: str, dtype, device) -> torch.Tensor:
    """POIs (N, 2) as (x, y) floats."""
    t = _to_tensor(x, name)
    if t.dim() == 1 and t.shape[0] == 2:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[1] != 2:
        raise ValueError(f"{name}: expected shape (N, 2) as (x, y), got {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError(f"{name}: no points given")
    t = t.to(device=device, dtype=dtype)
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains non-finite coordinates")
    return t


def as_times(x, n: int, dtype, device) -> torch.Tensor:
    """Frame times (n,), strictly increasing; default 0..n-1 (frame units)."""
    if x is None:
        return torch.arange(n, dtype=dtype, device=device)
    t = _to_tensor(x, "times").to(device=device, dtype=dtype).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"times: expected {n} values (one per frame), got {t.shape[0]}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError("times: contains non-finite values")
    if n > 1 and not bool((t[1:] > t[:-1]).all()):
        raise ValueError("times: must be strictly increasing")
    return t


def check_init(x, n: int, dtype, device) -> torch.Tensor | None:
    """Initial guess (N, k) or None."""
    if x is None:
        return None
    t = _to_tensor(x, "init")
    if t.dim() != 2 or t.shape[0] != n:
        raise ValueError(
            f"init: expected shape ({n}, 2), ({n}, 4) or ({n}, P), got {tuple(t.shape)}"
        )
    t = t.to(device=device, dtype=dtype)
    if not bool(torch.isfinite(t).all()):
        raise ValueError("init: contains non-finite values")
    return t
