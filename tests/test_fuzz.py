"""Fuzzing (hypothesis) of the image readers and of the ``stsdic`` command line.

The oracle: the readers either give (H, W) finite float frames or raise ``InputError``
(nothing else); ``stsdic`` returns 0, 1 or 2 with every error on one ``stsdic: error:``
line, never a traceback and never an unexpected exception type (those are reported with
"run with --debug"). The default run tries a few dozen inputs per test; set
``STSDIC_FUZZ_EXAMPLES=2000`` for a long run, and ``STSDIC_FUZZ_RECORD=file.json`` to record
how many inputs each test tried.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis (test extra) not installed")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from torch_stsdic.cli import main  # noqa: E402
from torch_stsdic.io import InputError, load_series  # noqa: E402

EXAMPLES = int(os.environ.get("STSDIC_FUZZ_EXAMPLES", "25"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=EXAMPLES <= 25,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow, HealthCheck.data_too_large])
TRIED: Counter = Counter()


@pytest.fixture(scope="module", autouse=True)
def _record():
    yield
    path = os.environ.get("STSDIC_FUZZ_RECORD")
    if path:
        old = json.loads(Path(path).read_text()) if Path(path).exists() else {}
        old.update(TRIED)
        Path(path).write_text(json.dumps(old, indent=1) + "\n")


def _read_all(path: Path | list[Path]) -> None:
    """Open and decode every frame: success, or InputError (anything else fails the test)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            s = load_series(path)
            for i in range(len(s)):
                a = s.numpy(i)
                assert a.shape == s.shape and a.dtype == np.float32
            s.close()
        except InputError as exc:  # a message naming the file (or the folder) at fault
            names = [q.name for q in (path if isinstance(path, list) else [path])]
            assert any(n in str(exc) for n in names), (names, str(exc))


# ----------------------------------------------------------------------------------------
# image readers
# ----------------------------------------------------------------------------------------

EXTS = [".tif", ".tiff", ".png", ".bmp", ".jpg"]


@FUZZ
@given(data=st.binary(min_size=0, max_size=3000), ext=st.sampled_from(EXTS),
       magic=st.sampled_from([b"", b"II*\x00", b"MM\x00*", b"II+\x00", b"\x89PNG\r\n\x1a\n",
                              b"BM", b"\xff\xd8\xff"]))
def test_random_bytes(tmp_path, data, ext, magic):
    TRIED["random bytes"] += 1
    p = tmp_path / f"x{ext}"
    p.write_bytes(magic + data)
    _read_all(p)


DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float16", "float32",
          "float64", "bool", "complex64"]
SHAPES = [(9, 7), (3, 9, 7), (9, 7, 3), (2, 9, 7, 3), (9, 7, 4), (2, 9, 7), (4, 9, 7),
          (1, 9, 7), (9, 7, 2), (2, 3, 9, 7), (1, 1), (5, 1, 9), (2, 2, 9, 7, 3)]


def _array(dtype: str, shape: tuple[int, ...], seed: int, special: str) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(100, 50, shape)
    if dtype == "bool":
        return a > 100
    if dtype == "complex64":
        return (a + 1j).astype(np.complex64)
    a = a.astype(dtype) if dtype.startswith("float") else np.clip(
        a, np.iinfo(dtype).min, np.iinfo(dtype).max).astype(dtype)
    if special != "none" and dtype.startswith("float"):
        a.flat[seed % a.size] = {"nan": np.nan, "inf": np.inf, "big": 1e30}[special]
    return a


@FUZZ
@given(dtype=st.sampled_from(DTYPES), shape=st.sampled_from(SHAPES),
       photometric=st.sampled_from([None, "minisblack", "rgb"]),
       planar=st.sampled_from([None, "contig", "separate"]), seed=st.integers(0, 1000),
       special=st.sampled_from(["none", "nan", "inf", "big"]),
       cut=st.one_of(st.none(), st.floats(0.0, 1.0)))
def test_tiff_dtypes_shapes_pages_truncations(tmp_path, dtype, shape, photometric, planar, seed,
                                              special, cut):
    TRIED["tiff variants"] += 1
    p = tmp_path / "x.tif"
    a = _array(dtype, shape, seed, special)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tifffile.imwrite(p, a, photometric=photometric, planarconfig=planar)
    except Exception:  # noqa: BLE001 - tifffile refuses the combination: nothing to read
        return
    if cut is not None:  # a truncated file
        raw = p.read_bytes()
        p.write_bytes(raw[: int(len(raw) * cut)])
    _read_all(p)


@FUZZ
@given(mode=st.sampled_from(["L", "RGB", "RGBA", "LA", "P", "1", "I;16", "I", "F", "CMYK",
                             "YCbCr", "HSV"]),
       fmt=st.sampled_from(["png", "tif", "bmp", "jpg"]), size=st.tuples(
           st.integers(1, 12), st.integers(1, 12)), seed=st.integers(0, 1000),
       n_files=st.integers(1, 3))
def test_pil_modes_and_file_lists(tmp_path, mode, fmt, size, seed, n_files):
    TRIED["pil modes"] += 1
    rng = np.random.default_rng(seed)
    paths = []
    for k in range(n_files):
        im = Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
        try:
            im = im.convert(mode)
            p = tmp_path / f"f{k}.{fmt}"
            im.save(p)
        except (OSError, ValueError, KeyError):  # PIL cannot save this mode in this format
            return
        paths.append(p)
    _read_all(paths)
    _read_all(tmp_path)


# ----------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fuzzcli")
    rng = np.random.default_rng(0)
    movie = d / "movie.tif"
    tifffile.imwrite(movie, rng.integers(0, 255, (5, 48, 48), dtype=np.uint8),
                     photometric="minisblack")
    (d / "poi.csv").write_text("x,y\n20,20\n30,25\n")
    (d / "bad.csv").write_text("x;y\nfoo,bar\n1e999,-3\n")
    (d / "t.txt").write_text("0\n0.5\n1\n2\n3\n")
    np.save(d / "mask.npy", np.ones((48, 48), bool))
    (d / "junk.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + rng.bytes(200))
    out = d / "r.h5"
    assert main(["run", str(movie), "--subset", "11", "--step", "8", "--m", "1", "--out",
                 str(out), "--no-progress", "--threads", "1"]) == 0
    return {"movie": movie, "poi": d / "poi.csv", "bad": d / "bad.csv", "t": d / "t.txt",
            "mask": d / "mask.npy", "junk": d / "junk.h5", "result": out, "dir": d}


VALUES = st.one_of(
    st.sampled_from(["0", "1", "-1", "2", "3", "5", "7", "21", "1e9", "nan", "inf", "-inf",
                     "0.5", "1.5", "", " ", "x", "0:3", "::2", "-2:", "1,2", "all", "0:0",
                     "1::0", "99", "-99", ":", ",", "0,,1", "1e-9", "9" * 30, "\x00",
                     "é", "--", "-"]),
    st.text(max_size=8),
    st.integers(-10**12, 10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)

RUN_OPTS = ["--subset", "--m", "--step", "--roi", "--mask", "--points", "--reference",
            "--frames", "--timestamps", "--reference-update", "--formulation", "--criterion",
            "--shape", "--window", "--interpolation", "--search-radius", "--initial-guess",
            "--seed-spacing", "--tol", "--max-iter", "--batch-points", "--memory-mb",
            "--dtype", "--strain-window", "--strain-kind", "--device", "--threads"]
FLAGS = ["--resume", "--overwrite", "--no-progress"]  # not --debug: it shows tracebacks


class _Stop(BaseException):
    """Raised instead of running the solver: the fuzz run is about the checks before it."""


@pytest.fixture
def no_solve(monkeypatch):
    import torch_stsdic.movie.series as series

    def stop(*args, **kwargs):
        raise _Stop

    monkeypatch.setattr(series, "run_plan", stop)


def _call(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except _Stop:
            return 0, ""
    return code, err.getvalue()


def _check(code: int, err: str, argv: list[str]) -> None:
    assert code in (0, 1, 2), (code, argv, err)
    assert "Traceback" not in err, (argv, err)
    errors = [ln for ln in err.splitlines() if ln.startswith("stsdic: error:")]
    assert "--debug for the traceback" not in err, (argv, err)  # an unexpected exception
    if code:
        assert len(errors) == 1, (argv, err)


def _file_or_value(files: dict[str, Path]):
    return st.one_of(VALUES, st.sampled_from([str(p) for p in files.values()]))


@FUZZ
@given(data=st.data())
def test_run_arguments(files, no_solve, tmp_path, data):
    TRIED["cli run"] += 1
    opts = data.draw(st.lists(st.sampled_from(RUN_OPTS), max_size=4))
    argv = ["run", data.draw(st.sampled_from([str(files["movie"]), str(files["dir"]),
                                              str(files["junk"]), "nope.tif", "*.tif"]))]
    for o in opts:
        n = 4 if o == "--roi" else 1
        argv += [o, *[data.draw(_file_or_value(files)) for _ in range(n)]]
    argv += data.draw(st.lists(st.sampled_from(FLAGS), max_size=2, unique=True))
    argv += ["--out", data.draw(st.sampled_from([str(tmp_path / "o.h5"), str(files["junk"]),
                                                 str(files["dir"]), str(files["result"])])),
             "--threads", "1"]
    code, err = _call(argv)
    _check(code, err, argv)


@FUZZ
@given(data=st.data())
def test_export_and_parsing_of_every_command(files, tmp_path, data):
    TRIED["cli export/parse"] += 1
    cmd = data.draw(st.sampled_from(["export", "plot", "synth", "demo", "bogus", ""]))
    words = data.draw(st.lists(st.one_of(
        st.sampled_from(["--frames", "--fields", "--frame", "--size", "--frames", "--noise",
                         "--motion", "--layout", "--out", "--format", "--quick", "--dpi",
                         "--seed", "--bits", "--m", "--subset"]),
        _file_or_value(files)), max_size=6))
    argv = [cmd, *words] if cmd else words
    if cmd == "export":
        argv = ["export", str(files["result"]), "--out", str(tmp_path / "csv"), *words]
        code, err = _call(argv)
        _check(code, err, argv)
        return
    # the other commands compute for seconds: only their argument parsing is fuzzed
    from torch_stsdic.cli.app import build_parser
    from torch_stsdic.cli.errors import UsageError

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            build_parser().parse_args(argv)
        except (UsageError, SystemExit):
            pass
    assert "Traceback" not in err.getvalue()


@FUZZ
@given(which=st.sampled_from(["--points", "--timestamps", "--mask"]),
       text=st.one_of(st.text(max_size=300), st.lists(
           st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-99, 999)),
           max_size=12).map(lambda v: "\n".join(map(str, v)))),
       raw=st.binary(max_size=300), shape=st.sampled_from([(48, 48), (48,), (2, 48, 48),
                                                          (47, 48), (0,), ()]),
       kind=st.sampled_from(["text", "npy", "bytes"]))
def test_side_file_contents(files, no_solve, tmp_path, which, text, raw, shape, kind):
    """--points, --timestamps and --mask files with random contents."""
    TRIED["cli side files"] += 1
    p = tmp_path / ("side.npy" if kind == "npy" else "side.csv")
    if kind == "text":
        p.write_text(text, encoding="utf-8", errors="surrogatepass")
    elif kind == "npy":
        np.save(p, np.random.default_rng(0).normal(size=shape))
    else:
        p.write_bytes(raw)
    argv = ["run", str(files["movie"]), "--subset", "11", which, str(p), "--out",
            str(tmp_path / "o.h5"), "--overwrite", "--threads", "1"]
    code, err = _call(argv)
    _check(code, err, argv)
    if code:  # the error names the option or the file at fault
        assert which in err or p.name in err, (argv, err)
