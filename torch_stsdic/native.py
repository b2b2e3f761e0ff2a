"""Fused CPU kernels (C++), built on first use and loaded with ctypes.

On a CPU the Gauss-Newton iteration is bound by B-spline sampling: every subset pixel of
every frame is 16 (cubic) or 36 (quintic) gathered coefficients, and a chain of torch
operations writes each intermediate (N, T, S) tensor to memory. The kernels in
``_native/dic_kernels.cpp`` do warp + sample + criterion + reduction of one IC-GN step in
one pass per point (double accumulators across frames), a few ns per sample and thread
(measured by ``scripts/bench_kernels.py``, recorded in ``docs/bench/kernels-cpu.json``);
also the reference subsets with gradients, the IC Hessian's moments and the recursive
B-spline prefilter.

* Built with the system C++ compiler (``$CXX``, else ``c++``/``g++``/``clang++``; the same
  one torch.compile needs on a CPU) into ``$TORCH_STSDIC_CACHE`` (default
  ``~/.cache/torch_stsdic``; a temp directory if that is not writable), keyed by source,
  compiler and CPU; about 3 s, once. The build targets the CPU it runs on
  (``-march=native``: AVX2 where present); ``TORCH_STSDIC_NATIVE_MARCH`` names another
  target (e.g. ``x86-64-v2``) or, empty, the compiler's portable default.
* Plain C ABI, no torch headers; tensors are passed as pointers.
* One declaration per kernel, in C++: each kernel's parameter list is written once, in its
  ``STS_KERNEL`` definition. The library reports, for every kernel and its float/double
  instance, the parameter list as written (names; ``nullable<...>`` marks pointers that may
  be null), the parameters' kinds as compiled (``i32``, ``i64``, ``f32``, ``f64``, ``*`` +
  element kind for pointers) and the address (``sts_kernel_*``, read only after
  ``sts_abi_version()`` matched :data:`_ABI`). The loader checks that the written list reads
  as the compiled kinds and builds each ctypes prototype from the kinds; this module holds
  no signature. Every call goes through a :class:`Kernel`, with each parameter by name, and
  is checked before any C code runs: no name missing or unknown, pointers get contiguous CPU
  tensors of the declared element dtype (None only where nullable), integers get ints in
  the C type's range, floating-point parameters real numbers. A mismatch raises TypeError
  (ValueError for a range) naming the kernel, the parameter's index, name and declaration.
  Not checked: that the tensors are as large as the kernel assumes.
* Threads: ctypes releases the GIL, so a call's rows are split over
  ``torch.get_num_threads()`` threads, the calling thread and pool threads taking chunks in
  turn. No tensor whose pointer goes to C is freed while C may still use it, and a call
  returns or raises (KeyboardInterrupt included) only once no pool thread is inside the
  kernel (:class:`_Rows`); C code itself is never interrupted.
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
import numbers
import operator
import os
import platform
import re
import shutil
import subprocess
import tempfile
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import torch

__all__ = ["available", "set_native", "native_enabled", "sample", "subsets", "ic_rhs", "gram",
           "prefilter", "build", "kernels", "Kernel"]

_SOURCE = Path(__file__).with_name("_native") / "dic_kernels.cpp"
_MODE = os.environ.get("TORCH_STSDIC_NATIVE", "auto").lower()
_LIB: _Library | None = None
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


_ABI = 5  # sts_abi_version() of the matching dic_kernels.cpp
# the kernels the wrappers below call (each as <name>_f32 and <name>_f64); their signatures
# come from the library (see the module docstring)
_KERNELS = ("sts_sample", "sts_subsets", "sts_ic_rhs", "sts_prefilter", "sts_gram")
_VARIANTS = {torch.float32: "_f32", torch.float64: "_f64"}

# parameter kinds of the library's declarations (dic_kernels.cpp, kind_of): scalars, and
# "*" + the element kind for pointers
_SCALAR_CTYPES = {"i32": ctypes.c_int32, "i64": ctypes.c_int64, "f32": ctypes.c_float,
                  "f64": ctypes.c_double}
_ELEMENT_DTYPES = {"i32": torch.int32, "i64": torch.int64, "u8": torch.uint8,
                   "f32": torch.float32, "f64": torch.float64}
_TYPE_KINDS = {"int": "i32", "int32_t": "i32", "int64_t": "i64", "uint8_t": "u8",
               "float": "f32", "double": "f64"}  # C type names of the parameter lists
_PARAM_RE = re.compile(
    r"(?:nullable\s*<\s*(?P<nconst>const\s+)?(?P<ntype>\w+)\s*>"  # nullable<const T>
    r"|(?P<const>const\s+)?(?P<type>\w+)\s*(?P<ptr>\*)?)"  # const T*, int64_t
    r"\s*(?P<name>[A-Za-z_]\w*)")


class Param(NamedTuple):
    """One declared kernel parameter: position, name, kind ("i32", "i64", "f32", "f64", or
    "*<element kind>"), whether a pointer may be null, and its C declaration."""

    index: int
    name: str
    kind: str
    nullable: bool
    decl: str


def _parse_params(text: str, t_kind: str) -> list[tuple[str, str, bool, str]]:
    """(name, kind, nullable, declaration) of each parameter of a parameter list as written
    in dic_kernels.cpp, e.g. "(const T* x, int64_t n, nullable<T> gx)", with the template
    type T of kind ``t_kind``. Raises ValueError for what it cannot read."""
    body = text.strip()
    if not (body.startswith("(") and body.endswith(")")):
        raise ValueError(f"not a parameter list: {text!r}")
    body = body[1:-1].strip()
    out = []
    for item in body.split(",") if body else []:
        item = " ".join(item.split())
        m = _PARAM_RE.fullmatch(item)
        tname = m and (m["ntype"] or m["type"])
        kind = t_kind if tname == "T" else _TYPE_KINDS.get(tname or "")
        if m is None or kind is None:
            raise ValueError(f"cannot read parameter {len(out)} {item!r} of {text!r}")
        nullable = m["ntype"] is not None
        decl = re.sub(r"\bT\b", {"f32": "float", "f64": "double"}.get(t_kind, "T"), item)
        out.append((m["name"], "*" + kind if nullable or m["ptr"] else kind, nullable, decl))
    return out


def _declared_params(name: str, text: str, t_kind: str, kinds: list[str]) -> list[Param]:
    """The parameters of kernel ``name`` from its declaration as written (``text``) and the
    compiler's kinds of its parameters (``kinds``); RuntimeError where the two disagree (a
    parameter list this parser misreads, a type it does not know)."""
    try:
        parsed = _parse_params(text, t_kind)
    except ValueError as exc:
        raise RuntimeError(f"declaration of {name}: {exc}") from None
    if len(parsed) != len(kinds):
        raise RuntimeError(f"declaration of {name}: {len(parsed)} parameters written, "
                           f"{len(kinds)} compiled")
    params = []
    for i, ((pname, kind, nullable, decl), ckind) in enumerate(zip(parsed, kinds)):
        if kind != ckind:
            raise RuntimeError(f"declaration of {name}: parameter {i} {decl!r} reads as "
                               f"{kind}, compiled as {ckind}")
        if ckind.lstrip("*") not in (_ELEMENT_DTYPES if ckind[0] == "*" else _SCALAR_CTYPES):
            raise RuntimeError(f"declaration of {name}: parameter {i} {decl!r} has a kind "
                               f"({ckind}) with no ctypes type here")
        params.append(Param(i, pname, ckind, nullable, decl))
    if len({p.name for p in params}) != len(params):
        raise RuntimeError(f"declaration of {name}: repeated parameter names")
    return params


class Kernel:
    """A native kernel, built from the library's declaration of it; called with every
    parameter by name. Before any C code runs, :meth:`bind` checks the names (none missing,
    none unknown) and each value's kind: pointers take contiguous CPU tensors of the declared
    element dtype (None only where the declaration says ``nullable``), integers take ints in
    the C type's range, floating-point parameters take real numbers. A mismatch raises
    TypeError or ValueError naming the kernel and the parameter (index, name, declaration)."""

    def __init__(self, name: str, params: list[Param], address: int, owner):
        self.name = name
        self.params = tuple(params)
        self.names = frozenset(p.name for p in params)
        argtypes = [ctypes.c_void_p if p.kind[0] == "*" else _SCALAR_CTYPES[p.kind]
                    for p in params]
        self.fn = ctypes.CFUNCTYPE(ctypes.c_int, *argtypes)(address)
        self._owner = owner  # the library stays loaded while a kernel is referenced
        # per parameter: (name, parameter, 0 pointer / 1 integer / 2 real, element dtype or
        # integer bound)
        self._checks = [(p.name, p, 0, _ELEMENT_DTYPES[p.kind[1:]]) if p.kind[0] == "*" else
                        (p.name, p, 1, 1 << (31 if p.kind == "i32" else 63)) if p.kind[0] == "i"
                        else (p.name, p, 2, None) for p in params]
        pos = {p.name: p.index for p in params}
        self.i0, self.i1 = pos.get("i0"), pos.get("i1")

    @property
    def signature(self) -> str:
        return f"{self.name}({', '.join(p.decl for p in self.params)})"

    def __repr__(self) -> str:
        return f"<native kernel {self.signature}>"

    def bind(self, args: dict) -> tuple[list, list]:
        """The C arguments (in declared order) of a call with ``args`` (name -> value), and
        the tensors whose memory they point to (keep them alive until the kernel returns)."""
        if args.keys() != self.names:
            missing = [f"{p.index} {p.name!r}" for p in self.params if p.name not in args]
            unknown = sorted(set(args) - self.names)
            what = ([f"missing {', '.join(missing)}"] if missing else []) + \
                ([f"unknown {', '.join(map(repr, unknown))}"] if unknown else [])
            raise TypeError(f"{self.name}: {'; '.join(what)} (declared: {self.signature})")
        raw, keep = [], []
        for name, p, code, spec in self._checks:
            v = args[name]
            tv = type(v)
            if code == 0:  # pointer: spec is the element dtype
                if v is None and p.nullable:
                    raw.append(None)
                    continue
                if not ((tv is torch.Tensor or isinstance(v, torch.Tensor)) and v.dtype == spec
                        and v.is_cpu and v.is_contiguous()):
                    raise self._reject(p, v, f"a contiguous CPU {str(spec)[6:]} tensor"
                                       + (" or None" if p.nullable else ""))
                keep.append(v)
                raw.append(v.data_ptr())
            elif code == 1:  # integer: spec is 2**(bits - 1)
                if tv is not int:
                    if isinstance(v, torch.Tensor):  # (a one-element int tensor has __index__)
                        raise self._reject(p, v, "an int")
                    try:
                        v = operator.index(v)
                    except TypeError:
                        raise self._reject(p, v, "an int") from None
                if not -spec <= v < spec:
                    raise ValueError(f"{self.name}: argument {p.index} {p.name!r} ({p.decl}) "
                                     f"out of range: {v}")
                raw.append(v)
            else:
                if tv is not float:
                    if isinstance(v, (torch.Tensor, bool)) or not isinstance(v, numbers.Real):
                        raise self._reject(p, v, "a real number")
                    v = float(v)
                raw.append(v)
        return raw, keep

    def _reject(self, p: Param, v, want: str) -> TypeError:
        if isinstance(v, torch.Tensor):
            got = (f"a {'' if v.is_contiguous() else 'non-contiguous '}{v.device.type} "
                   f"{str(v.dtype)[6:]} tensor")
        else:
            got = f"{type(v).__name__} {v!r}"[:80]
        return TypeError(f"{self.name}: argument {p.index} {p.name!r} ({p.decl}) takes {want}, "
                         f"got {got}")

    def __call__(self, **args) -> None:
        """Run the kernel once on the calling thread (all of i0..i1 as given)."""
        raw, keep = self.bind(args)
        rc = self.fn(*raw)
        del keep  # (held across the call above)
        if rc:
            raise RuntimeError(f"{self.name} returned {rc}")


class _Library:
    """The loaded kernels library: its kernels, from its own declarations."""

    def __init__(self, path: Path):
        lib = ctypes.CDLL(str(path))
        abi = lib.sts_abi_version()
        if abi != _ABI:  # checked first: the sts_kernel_* functions below are those of _ABI
            raise RuntimeError(f"{path.name} is ABI version {abi}, this torch_stsdic needs "
                               f"{_ABI} (a stale library)")
        lib.sts_kernel_count.restype = ctypes.c_int
        lib.sts_kernel_count.argtypes = []
        for f in ("name", "params"):
            getattr(lib, f"sts_kernel_{f}").restype = ctypes.c_char_p
            getattr(lib, f"sts_kernel_{f}").argtypes = [ctypes.c_int]
        lib.sts_kernel_kinds.restype = ctypes.c_char_p
        lib.sts_kernel_kinds.argtypes = [ctypes.c_int, ctypes.c_int]
        lib.sts_kernel_address.restype = ctypes.c_void_p
        lib.sts_kernel_address.argtypes = [ctypes.c_int, ctypes.c_int]
        self.path = path
        self.kernels: dict[str, Kernel] = {}
        for i in range(lib.sts_kernel_count()):
            base = lib.sts_kernel_name(i).decode()
            text = lib.sts_kernel_params(i).decode()
            for f64, (suffix, t_kind) in enumerate((("_f32", "f32"), ("_f64", "f64"))):
                kinds = lib.sts_kernel_kinds(i, f64).decode()
                params = _declared_params(base + suffix, text, t_kind,
                                         kinds.split(",") if kinds else [])
                self.kernels[base + suffix] = Kernel(base + suffix, params,
                                                     lib.sts_kernel_address(i, f64), lib)
        missing = [k for k in _KERNELS for s in _VARIANTS.values() if k + s not in self.kernels]
        if missing:
            raise RuntimeError(f"{path.name} does not declare {', '.join(missing)}")


def kernels() -> dict[str, Kernel]:
    """The native kernels by name ("sts_sample_f32", ...), as the library declares them (empty
    when the kernels are unavailable)."""
    lib = _load()
    return dict(lib.kernels) if lib is not None else {}


def _kernel(base: str, dtype: torch.dtype) -> Kernel:
    """The float32 or float64 variant of a kernel."""
    lib = _load()
    if lib is None:
        raise RuntimeError(f"native kernels unavailable ({_FAILED})")
    return lib.kernels[base + _VARIANTS[dtype]]


def _geo(img_args: tuple, order: int) -> dict:
    """The geometry arguments shared by the sampling kernels: padded width, clamp range, tap
    shift, spline order (the coefficients go as ``flat``)."""
    _, wp, x_lo, x_hi, y_lo, y_hi, shift, _plane = img_args
    return dict(wp=wp, x_lo=x_lo, x_hi=x_hi, y_lo=y_lo, y_hi=y_hi, shift=shift, order=order)


def _load() -> _Library | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is not None or _FAILED is not None:
            return _LIB
        try:
            _LIB = _Library(build())
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
    """The helper threads (made again after a fork: a forked child has none of them)."""
    global _POOL, _POOL_SIZE, _POOL_PID
    if _POOL is None or _POOL_SIZE != n or _POOL_PID != os.getpid():
        if _POOL is not None and _POOL_PID == os.getpid():
            _POOL.shutdown(wait=False)  # idle: every call waits for its helpers
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="stsdic")
        _POOL_SIZE, _POOL_PID = n, os.getpid()
    return _POOL


class _Rows:
    """One kernel call over rows [0, n) in chunks, taken in turn by the calling thread and
    helper threads of the pool.

    Nothing handed to C is freed while C may still use it: this object holds every tensor the
    arguments point to, and each helper holds this object. The call does not return, normally
    or by an exception (KeyboardInterrupt included), while a helper is inside the kernel: an
    exception in the calling thread stops the hand-out of chunks and waits for the chunks
    under way (at most one per helper; an interrupt during that wait is held back and the
    first exception propagates)."""

    def __init__(self, kernel: Kernel, raw: list, keep: list, edges: list[int]):
        self.kernel, self.raw, self.keep, self.edges = kernel, raw, keep, edges
        self.lock = threading.Lock()
        self.idle = threading.Event()
        self.idle.set()
        self.next = 0
        self.busy = 0  # helpers inside the loop below
        self.stop = False
        self.failed: list = []  # (i0, i1, rc) or an exception of a helper

    def _take(self) -> int | None:
        with self.lock:
            j = self.next
            if self.stop or j >= len(self.edges) - 1:
                return None
            self.next = j + 1
        return j

    def _chunk(self, j: int) -> None:
        args = self.raw.copy()
        args[self.kernel.i0], args[self.kernel.i1] = self.edges[j], self.edges[j + 1]
        rc = self.kernel.fn(*args)
        if rc:
            self.failed.append((self.edges[j], self.edges[j + 1], rc))
            self.stop = True

    def helper(self) -> None:
        """A pool thread's part (signals are handled on the main thread only: no
        KeyboardInterrupt here)."""
        with self.lock:  # registered as busy before the calling thread can see idle
            if self.stop or self.next >= len(self.edges) - 1:
                return
            self.busy += 1
            self.idle.clear()
        try:
            while (j := self._take()) is not None:
                self._chunk(j)
        except BaseException as exc:  # not expected (arguments are checked): report it
            self.failed.append(exc)
            self.stop = True
        finally:
            with self.lock:
                self.busy -= 1
                if not self.busy:
                    self.idle.set()

    def _wait(self) -> BaseException | None:
        """Until no helper is inside the kernel; returns an exception (e.g. a second Ctrl-C)
        that arrived meanwhile."""
        held = None
        while True:
            try:
                with self.lock:  # a helper past its stop check is counted in busy now
                    pass
                self.idle.wait()
                return held
            except BaseException as exc:
                held = held or exc
                self.stop = True

    def run(self, pool: ThreadPoolExecutor, helpers: int) -> None:
        done = False
        try:
            for _ in range(helpers):
                try:
                    pool.submit(self.helper)
                except RuntimeError:  # interpreter shutting down: no new threads
                    break
            while (j := self._take()) is not None:
                self._chunk(j)
            done = True
        finally:
            if not done:
                self.stop = True
            held = self._wait()
        if held is not None:
            raise held
        for f in self.failed:
            if isinstance(f, BaseException):
                raise f
            raise RuntimeError(f"{self.kernel.name} returned {f[2]} for rows [{f[0]}, {f[1]})")


def _run_rows(kernel: Kernel, n_rows: int, work_per_row: int, args: dict) -> None:
    """Call ``kernel`` with ``args`` (every parameter but i0, i1, by name) over the rows
    [0, n_rows), split over ``torch.get_num_threads()`` threads when that pays."""
    if "i0" in args or "i1" in args or kernel.i0 is None or kernel.i1 is None:
        raise TypeError(f"{kernel.name}: the rows i0, i1 are set by _run_rows")
    raw, keep = kernel.bind({**args, "i0": 0, "i1": n_rows})
    if n_rows <= 0:
        return
    threads = max(1, torch.get_num_threads())
    if threads == 1 or n_rows * work_per_row < _PARALLEL_MIN or n_rows < 2:
        # on this thread alone: a Ctrl-C is raised only once C returned, and keep holds the
        # tensors until then
        rc = kernel.fn(*raw)
        del keep
        if rc:
            raise RuntimeError(f"{kernel.name} returned {rc}")
        return
    parts = min(threads * 4, n_rows)  # a few chunks per thread evens out uneven rows
    edges = [n_rows * j // parts for j in range(parts + 1)]
    _Rows(kernel, raw, keep, edges).run(_pool(threads - 1), min(threads, parts) - 1)


def _require(fn: str, ok: bool, what: str) -> None:
    """The wrappers' size checks: the kernels index their arrays by these sizes (the
    declarations check kinds and dtypes, not sizes)."""
    if not ok:
        raise ValueError(f"native.{fn}: {what}")


def _check_planes(fn: str, img_args: tuple, off: torch.Tensor) -> None:
    """Plane offsets (int64) within the coefficient array."""
    if off.numel():
        lo, hi = (int(v) for v in torch.aminmax(off))
        last = img_args[0].numel() - img_args[-1]
        _require(fn, 0 <= lo and hi <= last,
                 f"plane offsets [{lo}, {hi}] outside the image's [0, {last}]")


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
    _check_planes("sample", img_args, off_c)
    n = xc.numel()
    val = torch.empty(shape, dtype=dtype)
    gx = torch.empty(shape, dtype=dtype) if grad else None
    gy = torch.empty(shape, dtype=dtype) if grad else None
    _run_rows(_kernel("sts_sample", dtype), n, 1,
              dict(flat=flat, **_geo(img_args, order), x=xc, y=yc, off=off_c,
                   off_period=period, val=val, gx=gx, gy=gy))
    return (val, gx, gy) if grad else val


def subsets(img_args: tuple, order: int, px, py, dx, dy, frame_off, grad: bool):
    """Samples of whole subsets: (px[i] + dx[s], py[i] + dy[s]) in the plane at frame_off[i];
    px, py, frame_off (N,) (or (N, 1)), dx, dy (S,). Returns values (N, S) (and d/dx, d/dy)."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    n, ns = px.numel(), dx.numel()
    tens = {k: t.to(dtype).reshape(-1).contiguous()
            for k, t in dict(px=px, py=py, dx=dx, dy=dy).items()}
    _require("subsets", tens["py"].numel() == n and tens["dy"].numel() == ns
             and frame_off.numel() in (1, n), "px, py, frame_off (N,) and dx, dy (S,)")
    off = frame_off.to(torch.int64).reshape(-1).expand(n).contiguous()
    _check_planes("subsets", img_args, off)
    val = torch.empty(n, ns, dtype=dtype)
    gx = torch.empty(n, ns, dtype=dtype) if grad else None
    gy = torch.empty(n, ns, dtype=dtype) if grad else None
    _run_rows(_kernel("sts_subsets", dtype), n, ns,
              dict(flat=flat, **_geo(img_args, order), ns=ns, **tens, off=off, val=val, gx=gx,
                   gy=gy))
    return (val, gx, gy) if grad else val


def ic_rhs(img_args: tuple, order: int, p, px, py, dx, dy, basis, dt, frame_off, ft, fnorm,
           gx, gy, w, w_img: int, h: int, k: int, has_time: bool, znssd: bool,
           rows: torch.Tensor | None = None):
    """Native twin of formulations.joint_ic.ic_rhs_kernel. Shapes: p (M, 2k), px/py (N, 1) or (N,),
    dx/dy/w (S,), basis (S, Ks), dt and frame_off (N, T), ft/gx/gy (N, S), fnorm (N,);
    ``rows`` (M,) picks the per-point data rows of p's rows (default: M = N, row j = j).
    Returns b (M, 2k) float64, per-POI mean ZNCC (M,) and the outside flag (M,) bool."""
    flat = img_args[0].contiguous()
    dtype = flat.dtype
    n, (big_n, nt), (ns, ks) = p.shape[0], dt.shape, basis.shape
    _require("ic_rhs", tuple(p.shape) == (n, 2 * k) and k == ks + int(has_time),
             f"p must be (M, 2k) with k = Ks (+ 1 with time), got {tuple(p.shape)}, k={k}, "
             f"Ks={ks}")
    _require("ic_rhs", all(tuple(t.shape) == (big_n, ns) for t in (ft, gx, gy))
             and all(t.numel() == big_n for t in (px, py, fnorm))
             and all(t.numel() == ns for t in (dx, dy, w)) and frame_off.shape == dt.shape
             and ns > 0,
             "shapes: px/py/fnorm (N,), dx/dy/w (S,), basis (S, Ks), dt and frame_off "
             "(N, T), ft/gx/gy (N, S)")
    if rows is None:
        _require("ic_rhs", n == big_n, f"p has {n} rows for {big_n} points (pass rows)")
    else:
        _require("ic_rhs", rows.shape == (n,) and (n == 0 or 0 <= int(rows.min())
                                                  and int(rows.max()) < big_n),
                 f"rows must be (M,) = ({n},) indices into the {big_n} points")
    frame_off = frame_off.to(torch.int64).contiguous()
    _check_planes("ic_rhs", img_args, frame_off)

    def c(t):
        return t.to(dtype).contiguous()

    b = torch.empty(n, 2 * k, dtype=torch.float64)
    zn = torch.empty(n, dtype=dtype)
    out = torch.empty(n, dtype=torch.uint8)
    _run_rows(_kernel("sts_ic_rhs", dtype), n, nt * ns,
              dict(flat=flat, **_geo(img_args, order), nt=nt, ns=ns, ks=ks, k=k,
                   has_time=int(has_time), znssd=int(znssd), p=c(p), px=c(px.reshape(-1)),
                   py=c(py.reshape(-1)), dx=c(dx), dy=c(dy), basis=c(basis), dt=c(dt),
                   frame_off=frame_off, ft=c(ft),
                   fnorm=c(fnorm.reshape(-1)), gx=c(gx), gy=c(gy), w=c(w),
                   rows=None if rows is None else rows.to(torch.int64).contiguous(),
                   w_img=float(w_img), h=float(h), b=b, zn=zn, outside=out))
    return b, zn, out.bool()


def gram(gx: torch.Tensor, gy: torch.Tensor, basis: torch.Tensor, w: torch.Tensor):
    """Native twin of solver._gram: G (N, P', P') and m (N, P') in float64 for the augmented
    steepest-descent images [gx B, gx, gy B, gy] (P' = 2 (Ks + 1)) weighted by w (S,)."""
    dtype = gx.dtype
    n, ns = gx.shape
    ks = basis.shape[1]
    _require("gram", gy.shape == gx.shape and tuple(basis.shape) == (ns, ks)
             and w.numel() == ns, "gx, gy (N, S), basis (S, Ks), w (S,)")
    npa = 2 * (ks + 1)
    tens = {k: t.to(dtype).contiguous()
            for k, t in dict(gx=gx, gy=gy, basis=basis, w=w).items()}
    g = torch.empty(n, npa, npa, dtype=torch.float64)
    m = torch.empty(n, npa, dtype=torch.float64)
    _run_rows(_kernel("sts_gram", dtype), n, ns * npa, dict(ns=ns, ks=ks, **tens, G=g, m=m))
    return g, m


def prefilter(images: torch.Tensor, order: int) -> torch.Tensor:
    """Native twin of interpolation.bspline_prefilter for (..., H, W) float32/float64 CPU
    tensors: the recursive filter (two passes per pole and axis), mirror boundary. Returns a
    new tensor."""
    h, w = images.shape[-2:]
    out = images.clone(memory_format=torch.contiguous_format)  # filtered in place
    planes = out.numel() // max(1, h * w)
    fn = _kernel("sts_prefilter", out.dtype)
    args = dict(data=out, planes=planes, h=h, w=w, order=order)
    if w >= 2:
        _run_rows(fn, planes * h, w * 4, dict(args, axis=1))
    if h >= 2:
        blocks = planes * ((w + 63) // 64)
        _run_rows(fn, blocks, h * 64 * 4, dict(args, axis=0))
    return out
