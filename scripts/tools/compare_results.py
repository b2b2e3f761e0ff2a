"""Run ``stsdic run`` from two source trees on the same inputs and compare the result files
field by field, bit for bit (a refactor must not change a number).

    python scripts/tools/compare_results.py --old /tmp/old [--new .] [--cases s12,hg,s3,hgd]

``--old``: a checkout of the earlier code (``git worktree add /tmp/old <commit>``). Each case
runs in a fresh process per tree with ``PYTHONPATH`` pointing at that tree. Every dataset of
the HDF5 file is compared (NaN equal to NaN); attributes that record when or how long a run
took are left out (also inside the JSON texts of a run's recorded estimates). Exit 0 when
every case is bit-identical, 1 otherwise. Needs
``../shared/data``."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
CASES = {
    "s12": ["dic-challenge-sample12", "--subset", "31", "--step", "10",
            "--roi", "58", "60", "334", "1020", "--m", "2"],
    "hg": ["mudic-hourglass", "--subset", "31", "--step", "20",
           "--roi", "150", "20", "1120", "734", "--m", "2"],
    "s3": ["dic-challenge-sample3", "--subset", "21", "--step", "16",
           "--roi", "40", "40", "471", "471", "--m", "2"],
    # the hourglass with its documented region and every default (template, windows chosen)
    "hgd": ["mudic-hourglass", "--subset", "31", "--step", "20",
            "--roi", "150", "20", "1120", "734"],
}
#: attributes that differ between any two runs (clock, host, software version)
VOLATILE = ("created", "finished", "elapsed", "software", "version", "time", "host", "seconds")


def run(tree: Path, case: list[str], out: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    src = str(DATA / case[0])
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "torch_stsdic", "run", src, *case[1:], "--out",
                    str(out), "--overwrite", "--no-progress"], env=env, check=True,
                   stdout=subprocess.DEVNULL, cwd=tree)
    return time.perf_counter() - t


def _volatile(key: str) -> bool:
    return any(s in key.lower() for s in VOLATILE)


def _steady(value: object) -> object:
    """An attribute's value without what differs between any two runs: a JSON text (a run's
    recorded estimates, :data:`VOLATILE` keys at any depth, e.g. a pass's ``seconds``)
    read and those keys dropped; any other value as it is."""
    text = value.decode() if isinstance(value, bytes) else value
    if not isinstance(text, str) or text[:1] not in "{[":
        return value

    def drop(x):
        if isinstance(x, dict):
            return {k: drop(v) for k, v in x.items() if not _volatile(k)}
        if isinstance(x, list):
            return [drop(v) for v in x]
        return x
    try:
        return json.dumps(drop(json.loads(text)), sort_keys=True)
    except ValueError:
        return value


def _items(f: h5py.File) -> dict[str, object]:
    out: dict[str, object] = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = obj[()]
        for k, v in obj.attrs.items():
            if not _volatile(k):
                out[f"{name}@{k}"] = _steady(v)

    f.visititems(visit)
    for k, v in f.attrs.items():
        if not _volatile(k):
            out[f"@{k}"] = _steady(v)
    return out


def _equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype.kind in "fc":
        return bool(np.array_equal(a, b, equal_nan=True))
    return bool(np.array_equal(a, b))


def compare(old: Path, new: Path) -> list[str]:
    with h5py.File(old, "r") as fa, h5py.File(new, "r") as fb:
        a, b = _items(fa), _items(fb)
    diff = [f"only in old: {k}" for k in sorted(set(a) - set(b))]
    diff += [f"only in new: {k}" for k in sorted(set(b) - set(a))]
    for k in sorted(set(a) & set(b)):
        if not _equal(a[k], b[k]):
            diff.append(f"differs: {k}")
    return diff


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, required=True)
    ap.add_argument("--new", type=Path, default=Path(__file__).resolve().parents[2])
    ap.add_argument("--cases", default="s12,hg,s3")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"skipped: {DATA} is absent")
        return 0
    failed = False
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases.split(","):
            fo, fn = Path(tmp, f"{name}-old.h5"), Path(tmp, f"{name}-new.h5")
            to = run(args.old.resolve(), CASES[name], fo)
            tn = run(args.new.resolve(), CASES[name], fn)
            diff = compare(fo, fn)
            with h5py.File(fn, "r") as f:
                n = sum(1 for _ in f)
            state = "bit-identical" if not diff else f"{len(diff)} differences"
            print(f"{name}: {state} ({n} top-level entries; old {to:.1f} s, new {tn:.1f} s)")
            for line in diff[:20]:
                print("   ", line)
            failed |= bool(diff)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
