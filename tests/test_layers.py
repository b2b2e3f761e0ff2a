"""The package's layers: every import (top level or inside a function) goes down the layer
order, no module imports another module's private name, and there is no circle of modules or
of top-level folders. The order is docs/architecture.md's:

    kernels < core < io, synth < analysis < movie < stereo < faces (cli, nn, plot, demo, root)

Also the size rules: no module over 700 lines, no function over 120 lines, at most 8 modules
in the package root besides ``__init__``/``__main__``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "torch_stsdic"

#: rank of each top-level unit (a sub-package, or a root module: the faces)
RANKS = {"kernels": 0, "core": 1, "io": 2, "synth": 2, "analysis": 3, "movie": 4, "stereo": 5}
FACES = 6  # cli/, nn, plot, demo, allocator, the package's __init__ and __main__


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = ("torch_stsdic",) + p.relative_to(PKG).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _unit(mod: str) -> str:
    """The top-level unit of a module: its sub-package, or "faces" for root modules."""
    parts = mod.split(".")
    if len(parts) == 1:
        return "faces"
    if parts[1] in RANKS:
        return parts[1]
    return "faces"


def _rank(mod: str) -> int:
    return RANKS.get(_unit(mod), FACES)


def _imports(mod: str) -> list[tuple[str, list[str], int]]:
    """(imported module, imported names, line) for every package import in ``mod``."""
    if mod not in _IMPORTS:
        _IMPORTS[mod] = _parse_imports(mod)
    return _IMPORTS[mod]


def _parse_imports(mod: str) -> list[tuple[str, list[str], int]]:
    path = MODULES[mod]
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "torch_stsdic":
                    out.append((_longest(a.name), [], node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.split(".")[0] != "torch_stsdic":
                continue
            for a in node.names:
                full = f"{name}.{a.name}"
                if full in MODULES:
                    out.append((full, [], node.lineno))
                else:
                    out.append((_longest(name), [a.name], node.lineno))
    return out


def _longest(name: str) -> str:
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        if ".".join(parts[:i]) in MODULES:
            return ".".join(parts[:i])
    return name


_IMPORTS: dict[str, list] = {}


def _graph() -> dict[str, set[str]]:
    g = {m: set() for m in MODULES}
    for m in MODULES:
        for target, _, _ in _imports(m):
            # a package's __init__ is imported with any of its modules: only edges that name
            # the package module itself count as importing it
            if target != m:
                g[m].add(target)
    return g


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of ``graph`` (as a list of nodes), or None."""
    colour: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        colour[n] = 1
        stack.append(n)
        for t in sorted(graph.get(n, ())):
            if colour.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if colour.get(t) is None:
                found = visit(t)
                if found:
                    return found
        stack.pop()
        colour[n] = 2
        return None

    for n in sorted(graph):
        if colour.get(n) is None:
            found = visit(n)
            if found:
                return found
    return None


def _package_parent(a: str, b: str) -> bool:
    """Whether ``b`` is a package that contains ``a`` (a module importing its own package's
    ``__init__`` for a sibling, as ``from torch_stsdic.core.formulations import base``)."""
    return a.startswith(b + ".")


def test_imports_go_down_the_layers():
    bad = []
    for m in MODULES:
        for target, _, line in _imports(m):
            if target == "torch_stsdic" and _unit(m) == "faces":
                continue
            if _rank(target) > _rank(m):
                bad.append(f"{MODULES[m].relative_to(PKG.parent)}:{line} imports {target} "
                           f"({_unit(m)} -> {_unit(target)})")
            elif _rank(target) == _rank(m) and _unit(target) != _unit(m):
                bad.append(f"{MODULES[m].relative_to(PKG.parent)}:{line} imports {target} "
                           f"(across {_unit(m)} and {_unit(target)} of one rank)")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_circle_of_modules():
    g = _graph()
    # edges into a containing package's __init__ (a sub-module importing its package) are
    # the same circle as the package importing the sub-module: keep them, they count
    cyc = _cycle(g)
    assert cyc is None, "import circle: " + " -> ".join(cyc)


def test_no_circle_of_folders():
    units: dict[str, set[str]] = {}
    for m, targets in _graph().items():
        for t in targets:
            if _unit(t) != _unit(m):
                units.setdefault(_unit(m), set()).add(_unit(t))
    cyc = _cycle(units)
    assert cyc is None, "circle of top-level folders: " + " -> ".join(cyc)


def test_no_private_name_across_modules():
    bad = []
    for m in MODULES:
        for target, names, line in _imports(m):
            for n in names:
                if n.startswith("_") and not n.startswith("__") and target != m:
                    bad.append(f"{MODULES[m].relative_to(PKG.parent)}:{line}: {target}.{n}")
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_sizes():
    root = [p for p in PKG.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
    names = sorted(p.name for p in root)
    assert len(root) <= 8, f"{len(root)} modules in the package root: {names}"
    long_modules = []
    long_functions = []
    for p in MODULES.values():
        text = p.read_text()
        n = len(text.splitlines())
        if n > 700:
            long_modules.append(f"{p.relative_to(PKG.parent)}: {n} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 120:
                    long_functions.append(f"{p.relative_to(PKG.parent)}:{node.lineno} "
                                          f"{node.name}: {length} lines")
    assert not long_modules, "\n".join(long_modules)
    assert not long_functions, "\n".join(long_functions)


@pytest.mark.parametrize("bad_edge", [("torch_stsdic.core.solver", "torch_stsdic.movie.series")])
def test_the_check_can_fail(bad_edge):
    """The circle finder and the rank rule see an injected upward edge."""
    g = _graph()
    a, b = bad_edge
    g[b].add(a)
    g[a].add(b)
    assert _cycle(g) is not None
    assert _rank(b) > _rank(a)


def test_architecture_page_shows_the_tree_of_the_code():
    """docs/architecture.md's tree is the one the code gives (architecture_tree.py)."""
    import subprocess
    import sys

    root = PKG.parent
    r = subprocess.run([sys.executable, str(root / "scripts/tools/architecture_tree.py"),
                        "--check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
