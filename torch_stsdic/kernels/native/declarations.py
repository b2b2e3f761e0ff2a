"""The kernels' signatures, as the library declares them, and the checked call.

Each kernel's parameter list is written once, in its ``STS_KERNEL`` definition in
``_native/dic_kernels.cpp``. The library reports, for every kernel and its float/double
instance, the parameter list as written (names; ``nullable<...>`` marks pointers that may be
null), the parameters' kinds as compiled (``i32``, ``i64``, ``f32``, ``f64``, ``*`` + element
kind for pointers) and the address (``sts_kernel_*``, read only after ``sts_abi_version()``
matched :data:`ABI`). :class:`Library` checks that the written list reads as the compiled
kinds and builds each ctypes prototype from the kinds; this module holds no signature.
Every call goes through a :class:`Kernel`, with each parameter by name, checked before any
C code runs (see :class:`Kernel`). Not checked: that the tensors are as large as the kernel
assumes (the wrappers in :mod:`.ops` check sizes).
"""

from __future__ import annotations

import ctypes
import numbers
import operator
import re
from pathlib import Path
from typing import NamedTuple

import torch

__all__ = ["ABI", "KERNELS", "VARIANTS", "Param", "Kernel", "Library"]

ABI = 18  # sts_abi_version() of the matching dic_kernels.cpp
# the kernels the wrappers (ops.py) call (each as <name>_f32 and <name>_f64); their signatures
# come from the library (see the module docstring)
KERNELS = ("sts_sample", "sts_subsets", "sts_ic_rhs", "sts_ic_solve", "sts_prefilter",
           "sts_gram", "sts_spd_inverse", "sts_param_std", "sts_nanmedian", "sts_nb_own",
           "sts_nb_test", "sts_splat", "sts_splat_add", "sts_splat_fused",
           "sts_splat_finish",
           "sts_windows", "sts_sobel_counts", "sts_flat_sums")
VARIANTS = {torch.float32: "_f32", torch.float64: "_f64"}

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


class Library:
    """The loaded kernels library: its kernels, from its own declarations."""

    def __init__(self, path: Path):
        lib = ctypes.CDLL(str(path))
        abi = lib.sts_abi_version()
        if abi != ABI:  # checked first: the sts_kernel_* functions below are those of ABI
            raise RuntimeError(f"{path.name} is ABI version {abi}, this torch_stsdic needs "
                               f"{ABI} (a stale library)")
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
        missing = [k for k in KERNELS for s in VARIANTS.values() if k + s not in self.kernels]
        if missing:
            raise RuntimeError(f"{path.name} does not declare {', '.join(missing)}")

