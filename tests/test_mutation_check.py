"""The mutation check (scripts/tools/mutation_check.py): every deliberate breakage of the
list fails the default suite. Several minutes: slow-marked (the default run is what it
checks, not a part of it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from repo_scripts import load_script  # tests/ on the path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "tools" / "mutation_check.py"


def _module():
    return load_script(SCRIPT, "mutation_check")


def test_every_mutation_still_applies():
    """Each substitution matches its file exactly once (else the list is stale), and the
    list covers what issue 39 names."""
    mod = _module()
    assert len(mod.MUTATIONS) >= 15
    assert len({m.name for m in mod.MUTATIONS}) == len(mod.MUTATIONS)
    for m in mod.MUTATIONS:
        src = (mod.REPO / m.path).read_text(encoding="utf-8")
        assert src.count(m.old) == 1, m.name
        for t in m.tests:
            assert (mod.REPO / "tests" / t).is_file(), (m.name, t)
    areas = {m.area for m in mod.MUTATIONS}
    assert {"solver", "criteria", "interpolation", "shape", "window", "strain", "reference",
            "CLI", "exports", "resume"} <= areas


@pytest.mark.slow
def test_mutation_check_catches_every_mutation():
    proc = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True,
                          timeout=3600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
