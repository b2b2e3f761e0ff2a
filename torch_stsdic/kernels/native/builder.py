"""Building the kernels library: the C++ compiler, the cache directory, the build.

:func:`build` compiles ``kernels/native/dic_kernels.cpp`` (beside this module) with the system C++
compiler (``$CXX``,
else ``c++``/``g++``/``clang++``) into ``$TORCH_STSDIC_CACHE`` (default
``~/.cache/torch_stsdic``; a per-user temp directory if that is not writable), keyed by the
source, the compiler's version, the CPU and the target (``TORCH_STSDIC_NATIVE_MARCH``,
default ``native``; empty: the compiler's portable default). About 3 s, once per key.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["SOURCE", "build"]

SOURCE = Path(__file__).parent / "dic_kernels.cpp"


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
    src = SOURCE.read_bytes()
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
        cmd = base + extra + ["-o", tmp, str(SOURCE)]
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
    raise RuntimeError(f"compiling {SOURCE.name} failed: {'; '.join(errors)}")
