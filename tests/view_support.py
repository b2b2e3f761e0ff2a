"""What the ``stsdic view`` tests share: a small result file, a server on it, Chromium."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from torch_stsdic.cli import main

#: fast settings of the small runs
FAST = ["--threads", "1", "--no-progress"]
RUN = ["--subset", "17", "--step", "10", "--m", "1", "--search-radius", "3",
       "--shared-motion", "none"]


def make_result(d: Path) -> tuple[Path, Path]:
    """(movie, result): a 7-frame 120 x 100 px strain movie and its 'stsdic run' result."""
    assert main(["synth", "--out", str(d), "--size", "120", "100", "--frames", "6",
                 "--motion", "strain", "--exx", "0.004", "--eyy", "-0.002", "--noise", "1",
                 "--seed", "3", "--threads", "1"]) == 0
    movie, out = d / "movie.tif", d / "r.h5"
    assert main(["run", str(movie), "--out", str(out), *RUN, *FAST]) == 0
    return movie, out


@contextlib.contextmanager
def serving(api_get, api_post=None) -> Iterator:
    """A view server on a free port, serving in a thread for the block."""
    from torch_stsdic.view.server import make_server

    server = make_server(0, api_get, api_post)
    server.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


@contextlib.contextmanager
def serving_result(path: Path, **kw) -> Iterator:
    """A view server on the result file ``path``."""
    from torch_stsdic.view.server import result_api
    from torch_stsdic.view.source import open_source

    with serving(result_api(open_source(path, **kw))) as server:
        yield server


def chromium() -> str | None:
    """Debian's Chromium (or $STSDIC_CHROMIUM), or None."""
    env = os.environ.get("STSDIC_CHROMIUM")
    if env and Path(env).exists():
        return env
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


#: a run writing a result file row by row in another process: it writes rows 0, 1, says
#: "ready", then two more rows for every line read from stdin, saying "wrote N" each time
WRITER = """
import sys
import numpy as np
from torch_stsdic.io.results import ResultWriter
pts = np.array([[x, y] for y in (10.0, 20.0, 30.0) for x in (10.0, 20.0, 30.0, 40.0)])
n = len(pts)
w = ResultWriter(sys.argv[1], points=pts, frames=np.arange(6), times=np.arange(6.0),
                 config={"m": 1}, inputs=[])
def rows(a, b):
    ks = np.arange(a, b)
    vals = {"u": ks[:, None] * (1.0 + pts[None, :, 0] / 100), "v": np.zeros((len(ks), n)),
            "ut": np.zeros((len(ks), n)), "vt": np.zeros((len(ks), n)),
            "zncc": np.ones((len(ks), n)), "status": np.zeros((len(ks), n))}
    w.write_rows(ks, vals)
    print(f"wrote {b}", flush=True)
rows(0, 2)
for line in sys.stdin:
    done = int(line)
    rows(done, done + 2)
    if done + 2 >= 6:
        break
w.close()
"""


@contextlib.contextmanager
def writing(path: Path) -> Iterator:
    """A process writing the result file ``path`` (see :data:`WRITER`); ``proc.more(k)``
    writes rows k, k + 1 and returns when they are flushed."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})

    def more(k: int) -> None:
        proc.stdin.write(f"{k}\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == f"wrote {k + 2}"

    assert proc.stdout.readline().strip() == "wrote 2"
    proc.more = more
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()
