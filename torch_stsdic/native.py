"""Fused CPU kernels (C++), built on first use and loaded with ctypes.

On a CPU the Gauss-Newton iteration is bound by B-spline sampling: every subset pixel of
every frame is 16 (cubic) or 36 (quintic) gathered coefficients, and a chain of torch
operations writes each intermediate (N, T, S) tensor to memory. The kernels in
``_native/dic_kernels.cpp`` do warp + sample + criterion + reduction of one IC-GN step in
one pass per point (double accumulators across frames), about 7-9 ns per sample and thread
(``scripts/bench_kernels.py``); also the reference subsets with gradients, the IC Hessian's
moments and the recursive B-spline prefilter.

* Built with the system C++ compiler (``$CXX``, else ``c++``/``g++``/``clang++``; the same
  one torch.compile needs on a CPU) into ``$TORCH_STSDIC_CACHE`` (default
  ``~/.cache/torch_stsdic``; a temp directory if that is not writable), keyed by source,
  compiler and CPU; about 3 s, once. The build targets the CPU it runs on
  (``-march=native``: AVX2 where present); ``TORCH_STSDIC_NATIVE_MARCH`` names another
  target (e.g. ``x86-64-v2``) or, empty, the compiler's portable default.
* Plain C ABI, no torch headers; tensors are passed as pointers. ctypes releases the GIL, so
  the rows are split over ``torch.get_num_threads()`` Python threads.
* Used for CPU tensors of float32/float64 outside autograd (nothing requiring gradients
  while grad mode is on). Everything else (CUDA, autograd through the sampler) uses the
  torch code, which the tests compare with these kernels. Without a compiler the torch code
  is used, with one warning.

Control: the environment variable ``TORCH_STSDIC_NATIVE`` ("auto" default, "0" off) or
:func:`set_native`.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

__all__ = ["available", "set_native", "native_enabled", "sample", "ic_rhs", "gram", "prefilter",
           "build"]

_SOURCE = Path(__file__).with_name("_native") / "dic_kernels.cpp"
_MODE = os.environ.get("TORCH_STSDIC_NATIVE", "auto").lower()
_LIB: ctypes.CDLL | None = None
_FAILED: str | None = None
_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_PID = 0
# below this many samples a call runs on the calling thread (thread hand-off costs ~50 us)
_PARALLEL_MIN = 20_000

_i64 = ctypes.c_int64
_dbl = ctypes.c_double
_int = ctypes.c_int
_ptr = ctypes.c_void_p


def set_native(mode: str | bool) -> None:
    """Use the fused C++ CPU kernels: "auto"/True (when they build) or False/"0" (never)."""
    global _MODE
    m = {True: "auto", False: "0"}.get(mode, str(mode).lower())  # type: ignore[arg-type]
    if m not in ("auto", "1", "0"):
        raise ValueError(f"native mode must be 'auto', True or False, got {mode!r}")
    _MODE = m


def native_enabled() -> bool:
    """Whether the native kernels are switched on (they may still fail to build)."""
    return _MODE != "0"


def _cache_dir() -> Path:
    root = os.environ.get("TORCH_STSDIC_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "torch_stsdic"


def _user() -> str:
    try:
        return str(os.getuid())
    except AttributeError:  # Windows
        return os.environ.get("USERNAME", "user")


def _compiler() -> str | None:
    """$CXX if set (and only it), else the first of c++, g++, clang++ on the PATH."""
    if os.environ.get("CXX"):
        return shutil.which(os.environ["CXX"])
    for name in ("c++", "g++", "clang++"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _cpu_key() -> str:
    flags = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features", "model name")):
                flags += line
    except OSError:
        pass
    return platform.machine() + flags


def build(verbose: bool = False) -> Path:
    """Compile the kernels (or find them in the cache); returns the shared library's path.

    Raises RuntimeError with the compiler's message when no compiler works."""
    cxx = _compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found (set $CXX)")
    src = _SOURCE.read_bytes()
    try:
        ver = subprocess.run([cxx, "--version"], capture_output=True, text=True,
                             timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise RuntimeError(f"{cxx} --version failed: {exc}") from exc
    march = os.environ.get("TORCH_STSDIC_NATIVE_MARCH", "native")
    key = hashlib.sha256(src + ver.encode() + _cpu_key().encode() + march.encode()
                         ).hexdigest()[:16]
    suffix = ".dll" if os.name == "nt" else ".so"
    name = f"dic_kernels-{key}{suffix}"
    out = _cache_dir() / name
    if out.exists():
        return out
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        if not os.access(out.parent, os.W_OK):
            raise PermissionError(str(out.parent))
    except OSError:  # read-only home (clusters, containers): a per-user temp directory
        out = Path(tempfile.gettempdir()) / f"torch_stsdic-{_user()}" / name
        if out.exists():
            return out
        out.parent.mkdir(parents=True, exist_ok=True)
    errors = []
    base = [cxx, "-O3", "-std=c++17", "-shared", "-fPIC", "-fno-math-errno",
            "-ffp-contract=fast", "-fopenmp-simd"]
    for extra in ([f"-march={march}"] if march else [], []):
        fd, tmp = tempfile.mkstemp(suffix=suffix, dir=out.parent)
        os.close(fd)
        cmd = base + extra + ["-o", tmp, str(_SOURCE)]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        except (OSError, subprocess.SubprocessError) as exc:
            errors.append(str(exc))
            os.unlink(tmp)
            continue
        if res.returncode == 0:
            if verbose:
                print(" ".join(cmd))
            os.replace(tmp, out)  # atomic: concurrent builders do not see half a file
            return out
        os.unlink(tmp)
        errors.append(res.stderr.strip().splitlines()[-1] if res.stderr.strip() else "failed")
    raise RuntimeError(f"compiling {_SOURCE.name} failed: {'; '.join(errors)}")


_ABI = 4  # sts_abi_version() of the matching dic_kernels.cpp
_GEO = [_ptr, _i64, _dbl, _dbl, _dbl, _dbl, _i64, _int]  # coefficients, geometry, order
_SIGNATURES = {  # kernel -> argument types (each exists as <kernel>_f32 and <kernel>_f64)
    "sts_sample": _GEO + [_ptr, _ptr, _ptr, _i64, _i64, _i64, _ptr, _ptr, _ptr],
    "sts_subsets": _GEO + [_i64] * 3 + [_ptr] * 8,
    "sts_ic_rhs": _GEO + [_i64] * 6 + [_int, _int] + [_ptr] * 14 + [_dbl, _dbl] + [_ptr] * 3,
    "sts_prefilter": [_ptr, _i64, _i64, _i64, _int, _int, _i64, _i64],
    "sts_gram": [_i64] * 4 + [_ptr] * 6,
}


def _declare(lib: ctypes.CDLL) -> None:
    for base, argtypes in _SIGNATURES.items():
        for suffix in ("_f32", "_f64"):
            fn = getattr(lib, base + suffix)
            fn.restype = _int
            fn.argtypes = argtypes
    lib.sts_abi_version.restype = _int


def _kernel(base: str, dtype: torch.dtype):
    """The float32 or float64 variant of a kernel."""
    return getattr(_load(), base + ("_f32" if dtype == torch.float32 else "_f64"))


def _geo(img_args: tuple, order: int, flat: torch.Tensor) -> tuple:
    """The leading arguments shared by the sampling kernels: coefficients pointer (``flat``,
    contiguous, kept alive by the caller), padded width, clamp range, tap shift, order."""
    _, wp, x_lo, x_hi, y_lo, y_hi, shift, _plane = img_args
    return (flat.data_ptr(), wp, x_lo, x_hi, y_lo, y_hi, shift, order)


def _load() -> ctypes.CDLL | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is not None or _FAILED is not None:
            return _LIB
        try:
            lib = ctypes.CDLL(str(build()))
            _declare(lib)
            if lib.sts_abi_version() != _ABI:
                raise RuntimeError("stale kernel library")
            _LIB = lib
        except (RuntimeError, OSError, AttributeError) as exc:
            _FAILED = str(exc)
            warnings.warn(f"torch_stsdic: fused CPU kernels unavailable ({_FAILED}); using "
                          "the torch code (slower)", RuntimeWarning, stacklevel=3)
    return _LIB


def available() -> bool:
    """Whether the fused CPU kernels are switched on and built (builds them on first call)."""
    return native_enabled() and _load() is not None


def usable(*tensors: torch.Tensor) -> bool:
    """Whether a call with these tensors can take the native path: switched on, built, CPU,
    float32/float64, and no autograd graph wanted through them (nothing requiring gradients
    while grad mode is on)."""
    if _MODE == "0":
        return False
    grad_on = torch.is_grad_enabled()
    for t in tensors:
        if t.device.type != "cpu" or (grad_on and t.requires_grad):
            return False
        if t.is_floating_point() and t.dtype not in (torch.float32, torch.float64):
            return False
    return _load() is not None


def usable_image(img_args: tuple, *tensors: torch.Tensor) -> bool:
    """:func:`usable`, and the image's planes small enough for 32-bit tap indices."""
    return img_args[-1] < 2**31 - 1 and usable(img_args[0], *tensors)


def _pool(n: int) -> ThreadPoolExecutor:
    """The worker threads (made again after a fork: a forked child has none of them)."""
    global _POOL, _POOL_SIZE, _POOL_PID
    if _POOL is None or _POOL_SIZE != n or _POOL_PID != os.getpid():
        if _POOL is not None and _POOL_PID == os.getpid():
            _POOL.shutdown(wait=False)
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="stsdic")
        _POOL_SIZE, _POOL_PID = n, os.getpid()
    return _POOL


def _run_rows(fn, n_rows: int, work_per_row: int, args_before, args_after) -> None:
    """Call fn(*args_before, i0, i1, *args_after) over [0, n_rows), split over threads."""
    threads = max(1, torch.get_num_threads())
    if threads == 1 or n_rows * work_per_row < _PARALLEL_MIN or n_rows < 2:
        rc = fn(*args_before, 0, n_rows, *args_after)
        if rc:
            raise RuntimeError(f"{fn.__name__} returned {rc}")
        return
    parts = min(threads * 4, n_rows)  # a few chunks per thread evens out uneven rows
    edges = [n_rows * j // parts for j in range(parts + 1)]
    futs = [_pool(threads).submit(fn, *args_before, a, b, *args_after)
            for a, b in zip(edges[:-1], edges[1:]) if b > a]
    for f in futs:
        if f.result():
            raise RuntimeError(f"{fn.__name__} failed")


def _p(t: torch.Tensor | None):
    return None if t is None else t.data_ptr()


def sample(img_args: tuple, order: int, x: torch.Tensor, y: torch.Tensor,
           frame_off: torch.Tensor, grad: bool):
    """Native twin of interpolation.sample_kernel: values (shape of x) and, with grad, d/dx
    and d/dy. ``frame_off`` (int64 plane offsets) broadcasts against x (e.g. (N, 1) for
    (N, S) points)."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    shape = torch.broadcast_shapes(x.shape, y.shape, frame_off.shape)
    xc = x.to(dtype).expand(shape).contiguous()
    yc = y.to(dtype).expand(shape).contiguous()
    off = frame_off.to(torch.int64)
    # the offset array is indexed as off[i // period]: possible when off's shape is shape's
    # leading dims followed by ones; otherwise materialise it
    lead = off.dim() - len(shape)
    oshape = (1,) * max(0, -lead) + tuple(off.shape)
    k = len(shape)
    while k > 0 and oshape[k - 1] == 1:
        k -= 1
    if off.numel() == 1:
        off_c, period = off.reshape(1).contiguous(), 0
    elif tuple(oshape[:k]) == tuple(shape[:k]):
        off_c = off.reshape(-1).contiguous()
        period = int(torch.Size(shape[k:]).numel())
    else:
        off_c, period = off.expand(shape).contiguous().reshape(-1), 1
    n = xc.numel()
    val = torch.empty(shape, dtype=dtype)
    gx = torch.empty(shape, dtype=dtype) if grad else None
    gy = torch.empty(shape, dtype=dtype) if grad else None
    _run_rows(_kernel("sts_sample", dtype), n, 1,
              (*_geo(img_args, order, flat), xc.data_ptr(), yc.data_ptr(), off_c.data_ptr(),
               period),
              (val.data_ptr(), _p(gx), _p(gy)))
    return (val, gx, gy) if grad else val


def subsets(img_args: tuple, order: int, px, py, dx, dy, frame_off, grad: bool):
    """Samples of whole subsets: (px[i] + dx[s], py[i] + dy[s]) in the plane at frame_off[i];
    px, py, frame_off (N,) (or (N, 1)), dx, dy (S,). Returns values (N, S) (and d/dx, d/dy)."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    n, ns = px.numel(), dx.numel()
    tens = [t.to(dtype).reshape(-1).contiguous() for t in (px, py, dx, dy)]
    off = frame_off.to(torch.int64).reshape(-1).expand(n).contiguous()
    val = torch.empty(n, ns, dtype=dtype)
    gx = torch.empty(n, ns, dtype=dtype) if grad else None
    gy = torch.empty(n, ns, dtype=dtype) if grad else None
    _run_rows(_kernel("sts_subsets", dtype), n, ns, _geo(img_args, order, flat),
              (ns, *[t.data_ptr() for t in tens], off.data_ptr(), val.data_ptr(), _p(gx),
               _p(gy)))
    return (val, gx, gy) if grad else val


def ic_rhs(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
           gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool,
           rows: torch.Tensor | None = None):
    """Native twin of solver._ic_rhs_kernel. Shapes: p (M, 2k), px/py (N, 1) or (N,),
    dx/dy/w (S,), basis (S, Ks), dt and frame_off (N, T), ft/gx/gy (N, S), fnorm (N,);
    ``rows`` (M,) picks the per-point data rows of p's rows (default: M = N, row j = j).
    Returns b (M, 2k) float64, per-POI mean ZNCC (M,) and the outside flag (M,) bool."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    nt = dt.shape[1]
    n = p.shape[0]
    ns, ks = basis.shape

    def c(t):
        return t.to(dtype).contiguous()

    tens = [c(p), c(px.reshape(-1)), c(py.reshape(-1)), c(dx), c(dy), c(basis), c(dt),
            frame_off.to(torch.int64).contiguous(), c(ft), c(fnorm.reshape(-1)), c(gx), c(gy),
            c(w), None if rows is None else rows.to(torch.int64).contiguous()]
    b = torch.empty(n, 2 * k, dtype=torch.float64)
    zn = torch.empty(n, dtype=dtype)
    out = torch.empty(n, dtype=torch.uint8)
    _run_rows(_kernel("sts_ic_rhs", dtype), n, nt * ns, _geo(img_args, order, flat),
              (nt, ns, ks, k, int(has_time), int(znssd), *[_p(t) for t in tens],
               float(w_img), float(h), b.data_ptr(), zn.data_ptr(), out.data_ptr()))
    return b, zn, out.bool()


def gram(gx: torch.Tensor, gy: torch.Tensor, basis: torch.Tensor, w: torch.Tensor):
    """Native twin of solver._gram: G (N, P', P') and m (N, P') in float64 for the augmented
    steepest-descent images [gx B, gx, gy B, gy] (P' = 2 (Ks + 1)) weighted by w (S,)."""
    dtype = gx.dtype
    n, ns = gx.shape
    ks = basis.shape[1]
    npa = 2 * (ks + 1)
    tens = [t.to(dtype).contiguous() for t in (gx, gy, basis, w)]
    g = torch.empty(n, npa, npa, dtype=torch.float64)
    m = torch.empty(n, npa, dtype=torch.float64)
    _run_rows(_kernel("sts_gram", dtype), n, ns * npa, (),
              (ns, ks, *[t.data_ptr() for t in tens], g.data_ptr(), m.data_ptr()))
    return g, m


def prefilter(images: torch.Tensor, order: int) -> torch.Tensor:
    """Native twin of interpolation.bspline_prefilter for (..., H, W) float32/float64 CPU
    tensors: the recursive filter (two passes per pole and axis), mirror boundary. Returns a
    new tensor."""
    h, w = images.shape[-2:]
    out = images.clone(memory_format=torch.contiguous_format)  # filtered in place
    planes = out.numel() // max(1, h * w)
    fn = _kernel("sts_prefilter", out.dtype)
    if w >= 2:
        _run_rows(fn, planes * h, w * 4, (out.data_ptr(), planes, h, w, order, 1), ())
    if h >= 2:
        blocks = planes * ((w + 63) // 64)
        _run_rows(fn, blocks, h * 64 * 4, (out.data_ptr(), planes, h, w, order, 0), ())
    return out
