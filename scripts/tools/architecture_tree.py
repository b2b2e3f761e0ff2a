"""Write the package tree of docs/architecture.md from the code: every folder in layer order
and every module with the first line of its docstring, between the page's
``<!-- tree -->`` markers.

    python scripts/tools/architecture_tree.py          # rewrite the block
    python scripts/tools/architecture_tree.py --check  # exit 1 when the page is stale
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "torch_stsdic"
PAGE = ROOT / "docs" / "architecture.md"
BEGIN, END = "<!-- tree: scripts/tools/architecture_tree.py -->", "<!-- /tree -->"
#: top-level units from the bottom layer up (the faces last)
ORDER = ["kernels", "core", "io", "synth", "analysis", "movie", "stereo", "cli", "view"]


def _summary(path: Path) -> str:
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = doc.strip().split("\n\n")[0].replace("\n", " ")
    first = first.split(". ")[0].rstrip(".")
    return first if len(first) <= 90 else first[:87] + "..."


def _lines(folder: Path, depth: int) -> list[str]:
    out = []
    pad = "    " * depth
    for p in sorted(folder.iterdir()):
        if p.name.startswith("__pycache__"):
            continue
        if p.is_dir() and (p / "__init__.py").exists():
            out.append(f"{pad}{p.name}/  {_summary(p / '__init__.py')}")
            out += _lines(p, depth + 1)
        elif p.suffix in (".py", ".cpp") and p.name not in ("__init__.py", "__main__.py"):
            text = _summary(p) if p.suffix == ".py" else "the C++ source of the native kernels"
            out.append(f"{pad}{p.name}  {text}")
    return out


def tree() -> str:
    lines = ["torch_stsdic/"]
    for i, unit in enumerate(ORDER):
        d = PKG / unit
        if not d.is_dir():
            continue
        layer = "faces" if unit == "cli" else f"layer {min(i, 6) if unit != 'synth' else 2}"
        layer = {"kernels": "layer 0", "core": "layer 1", "io": "layer 2", "synth": "layer 2",
                 "analysis": "layer 3", "movie": "layer 4", "stereo": "layer 5",
                 "cli": "faces", "view": "faces"}[unit]
        lines.append(f"    {unit}/  [{layer}] {_summary(d / '__init__.py')}")
        lines += _lines(d, 2)
    faces = sorted(p for p in PKG.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    for p in faces:
        lines.append(f"    {p.name}  [faces] {_summary(p)}")
    return "```\n" + "\n".join(lines) + "\n```"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    page = PAGE.read_text()
    a, b = page.index(BEGIN) + len(BEGIN), page.index(END)
    new = page[:a] + "\n" + tree() + "\n" + page[b:]
    if args.check:
        if new != page:
            print(f"{PAGE} is stale: run python {Path(__file__).relative_to(ROOT)}")
            return 1
        return 0
    PAGE.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
