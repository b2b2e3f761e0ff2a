"""Nothing lost on faults, and input that cannot be misread (issue 13).

Faults: SIGINT / SIGTERM / SIGKILL at random moments of a real ``stsdic`` process (another
process loading the CPU), a full disk (simulated mid-run; a real small tmpfs where this
test may mount one), a read-only output folder, corrupt or foreign files given to
``--resume``, a frame that vanishes or changes size mid-run. Every case: one clear line,
the finished frames kept, and ``--resume`` ending with the numbers of an uninterrupted run.
The long campaign on real images is ``scripts/tools/interrupt_resume.py``.
"""

from __future__ import annotations

import contextlib
import errno
import os
import random
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
import torch

from torch_stsdic import DICConfig, track
from torch_stsdic.analysis.points import grid_points
from torch_stsdic.cli import main
from torch_stsdic.core.status import Status
from torch_stsdic.io import ImageSeries, load_series
from torch_stsdic.io.results import ResultWriter
from torch_stsdic.synth import Translation, make_speckle, render_series

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--threads", "1", "--no-progress"]
#: 12 frames of 81 x 81 px, one block per target frame (--memory-mb 0.2): many moments to
#: interrupt, each run ~1 s
RUN = ["--subset", "17", "--step", "7", "--m", "1", "--search-radius", "3", "--memory-mb", "0.2",
       "--shared-motion", "none"]  # its pass comes before the first frame: see the test below


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err: str, start: str = "stsdic: error: ") -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()
             and not ln.startswith("stsdic: warning:")]
    assert len(lines) == 1, err
    assert lines[0].startswith(start), lines[0]
    return lines[0]


def _fields(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in ("u", "v", "status", "completed")}


def _assert_same(a: Path, b: Path) -> None:
    fa, fb = _fields(a), _fields(b)
    assert fa["completed"].all() and fb["completed"].all()
    for k in ("u", "v", "status"):
        np.testing.assert_array_equal(fa[k], fb[k], err_msg=k)


@pytest.fixture(scope="module")
def movie(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("movie")
    assert main(["synth", "--out", str(d), "--size", "81", "--frames", "11", "--noise", "1",
                 "--seed", "5", "--threads", "1"]) == 0
    return d / "movie.tif"


@pytest.fixture(scope="module")
def reference(movie, tmp_path_factory) -> Path:
    """The uninterrupted run every interrupted one must reproduce."""
    out = tmp_path_factory.mktemp("ref") / "ref.h5"
    assert main(["run", str(movie), *RUN, "--out", str(out), *FAST]) == 0
    return out


@pytest.fixture
def cpu_load():
    """Another process spinning on a CPU while the test runs."""
    p = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    yield
    p.kill()
    p.wait()


def _finished_frames(out: Path) -> int:
    """Frames a running ``stsdic run`` has flushed to ``out`` (0 while it cannot be read:
    the writer flushes after every row, and reading takes no lock: a read that meets the
    file mid-write may fail in any of h5py's ways, RuntimeError "free block size is zero?"
    included, seen once in CI)."""
    try:
        with h5py.File(out, "r", locking=False) as f:
            return int(f["completed"][()].sum()) if "completed" in f else 0
    except (OSError, KeyError, ValueError, RuntimeError):
        return 0


def _wait_for_first_frame(proc: subprocess.Popen, out: Path, timeout: float = 120.0) -> None:
    """Wait until the run has finished its first frame; fail if it ends or hangs first."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if out.exists() and _finished_frames(out) > 0:
            return
        if proc.poll() is not None:
            pytest.fail(f"the run ended (exit {proc.returncode}) before a finished frame was "
                        "seen: nothing to interrupt")
        time.sleep(0.005)
    proc.kill()
    pytest.fail(f"no finished frame after {timeout} s")


def _launch(argv: list[str]) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "stsdic_launcher", *map(str, argv)],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


# ----------------------------------------------------------------------------------------
# signals
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL],
                         ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_signal_at_a_random_moment_then_resume(capsys, movie, reference, tmp_path, cpu_load,
                                               sig):
    out = tmp_path / "r.h5"
    proc = _launch(["run", movie, *RUN, "--out", out, *FAST])
    # the signal always lands in the run: after its first finished frame (so there is
    # something to resume), early enough that most of the 11 frames left remain (< 20 ms
    # each on an idle 2-core VM since the solves run on both threads: 0.2 s let a run end)
    _wait_for_first_frame(proc, out)
    delay = random.uniform(0.0, 0.05)
    time.sleep(delay)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    note = f"signal {sig.name} {delay:.3f} s after the first frame: exit {proc.returncode}"
    assert "Traceback" not in err, note + "\n" + err
    assert proc.returncode != 0, "the run finished before the signal: " + note
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL, note
    else:
        assert proc.returncode == 128 + sig, note + "\n" + err
        line = _one_line(err, f"stsdic: interrupted by {sig.name}")
        # "N frames finished", or "all N frames are finished" (stopped in the strains)
        assert "--resume" in line and ("frames finished" in line
                                       or "frames are finished" in line), line
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    _assert_same(out, reference)


def test_signal_during_the_shared_motion_pass(capsys, movie, tmp_path):
    """An interrupt while the shared motion is measured (before any frame is solved): one
    line, exit 130, and the same command then runs to the end."""
    out = tmp_path / "r.h5"
    run = [a for a in RUN if a not in ("--shared-motion", "none")]
    proc = _launch(["run", movie, *run, "--shared-motion", "affine", "--out", out, *FAST])
    t0 = time.monotonic()
    while not out.exists() and proc.poll() is None and time.monotonic() - t0 < 120:
        time.sleep(0.002)
    proc.send_signal(signal.SIGINT)  # within ms of the file: 12 frames are still to solve
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err, err
    assert proc.returncode == 130, f"exit {proc.returncode} (0: finished before the signal)\n{err}"
    line = _one_line(err, "stsdic: interrupted by SIGINT")
    assert "nothing was written yet" in line or "--resume" in line, line
    if "nothing was written yet" in line:  # and nothing is left: no file of 0 frames
        assert not out.exists(), line
    again = ["--resume"] if out.exists() else []
    code, _, err = _run(capsys, "run", movie, *run, "--shared-motion", "affine", "--out", out,
                        *again, *FAST)
    assert code == 0, err


def test_sigint_while_importing(tmp_path):
    """Ctrl-C during the seconds torch takes to import: one line, exit 130, no file. The
    signal is sent from inside the import, so that it lands there on any machine."""
    script = (
        "import builtins, os, signal, sys, stsdic_launcher\n"
        "real = builtins.__import__\n"
        "def hook(name, *args, **kwargs):\n"
        "    if name == 'torch_stsdic.cli':\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = hook\n"
        "sys.exit(stsdic_launcher.main())\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", script, "run", str(tmp_path / "no.tif"), "--out",
                        str(tmp_path / "r.h5")], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 130, r.stderr
    line = _one_line(r.stderr, "stsdic: interrupted by SIGINT")
    assert "nothing was written" in line
    assert not (tmp_path / "r.h5").exists()


def test_sigkill_never_leaves_a_broken_file(tmp_path):
    """A writer killed at random moments (creation included): the file is absent or opens,
    and every row flagged completed holds its data."""
    script = tmp_path / "w.py"
    script.write_text(
        "import sys, numpy as np\n"
        "from torch_stsdic.io.results import ResultWriter\n"
        "F, N = 40, 2000\n"
        "w = ResultWriter(sys.argv[1], points=np.zeros((N, 2)) + np.arange(N)[:, None],\n"
        "                 frames=np.arange(F), times=np.arange(F, dtype=float), config={},\n"
        "                 inputs=[], fields=('u', 'v', 'status'), extra_fields=('exx',))\n"
        "for r in range(F):\n"
        "    w.write_rows([r], {'u': np.full(N, r + 1.0), 'v': np.full(N, -r - 1.0),\n"
        "                       'status': np.zeros(N, np.int8)})\n"
        "w.write_rows(np.arange(F), {'exx': np.ones((F, N))}, mark_completed=False)\n"
        "w.close()\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for k in range(3):
        out = tmp_path / f"k{k}.h5"
        proc = subprocess.Popen([sys.executable, str(script), str(out)], env=env)
        while not (out.exists() or out.with_name(out.name + ".creating").exists()) \
                and proc.poll() is None:
            time.sleep(0.001)
        time.sleep(0.0 if k == 0 else random.uniform(0.0, 0.05))  # try 0: while it is made
        proc.kill()
        proc.wait()
        if not out.exists():
            continue
        with h5py.File(out, "r") as f:
            done = np.flatnonzero(f["completed"][()])
            u = f["u"][()]
        for r in done:
            assert (u[r] == r + 1).all()


# ----------------------------------------------------------------------------------------
# disk and output folder
# ----------------------------------------------------------------------------------------


def test_full_disk_mid_run(capsys, monkeypatch, movie, reference, tmp_path):
    out = tmp_path / "r.h5"
    calls = {"n": 0}
    real = ResultWriter.write_rows

    def failing(self, rows, values, *, mark_completed=True):
        if mark_completed:
            calls["n"] += 1
            if calls["n"] == 4:
                raise self._write_error(OSError(errno.ENOSPC, "No space left on device"))
        return real(self, rows, values, mark_completed=mark_completed)

    monkeypatch.setattr(ResultWriter, "write_rows", failing)
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, *FAST)
    assert code == 1
    line = _one_line(err)
    for part in ("disk is full", str(out), "3 of 12 frames finished", "--resume"):
        assert part in line, (part, line)
    assert _fields(out)["completed"].sum() == 3
    monkeypatch.setattr(ResultWriter, "write_rows", real)
    code, _, err = _run(capsys, "run", movie, *RUN, "--out", out, "--resume", *FAST)
    assert code == 0, err
    _assert_same(out, reference)


def test_real_full_disk_is_found_before_computing(capsys, movie, tmp_path, tmpfs):
    """The result file takes its full size when it is made, so a disk too small fails at
    once (nothing computed, nothing left behind)."""
    with tmpfs(tmp_path / "small", "size=64k") as d:
        code, _, err = _run(capsys, "run", movie, *RUN, "--step", "2", "--out", d / "r.h5",
                            *FAST)
        assert code == 1
        line = _one_line(err)
        assert "disk is full" in line and "r.h5" in line, line
        assert not list(d.iterdir())


def test_read_only_output_folder(capsys, movie, tmp_path, tmpfs):
    ro = tmp_path / "ro"
    if os.geteuid() != 0:
        ro.mkdir()
        ro.chmod(0o500)
        ctx: contextlib.AbstractContextManager = contextlib.nullcontext(ro)
    else:  # root ignores permissions: a read-only file system
        ctx = tmpfs(ro, "ro,size=64k")
    with ctx as d:
        code, _, err = _run(capsys, "run", movie, *RUN, "--out", d / "r.h5", *FAST)
        assert code == 1
        line = _one_line(err)
        assert "not writable" in line and str(d) in line, line


# ----------------------------------------------------------------------------------------
# --resume on files it cannot continue
# ----------------------------------------------------------------------------------------


def _foreign(p: Path) -> None:
    with h5py.File(p, "w") as f:
        f["data"] = np.arange(5)


@pytest.mark.parametrize("kind", ["random", "truncated", "foreign", "options"])
def test_resume_refuses_what_it_cannot_continue(capsys, movie, reference, tmp_path, kind):
    out = tmp_path / "r.h5"
    extra: list[str] = []
    if kind == "random":
        out.write_bytes(np.random.default_rng(0).bytes(5000))
        want = ["cannot be read as HDF5"]
    elif kind == "truncated":
        out.write_bytes(reference.read_bytes()[:20000])
        want = ["cannot be read as HDF5"]
    elif kind == "foreign":
        _foreign(out)
        want = ["not a result file"]
    else:
        out.write_bytes(reference.read_bytes())
        extra = ["--step", "4", "--subset", "19"]
        want = ["--step", "--subset", "other options"]
    before = out.read_bytes()
    code, _, err = _run(capsys, "run", movie, *RUN, *extra, "--out", out, "--resume", *FAST)
    assert code == 1
    line = _one_line(err)
    for w in [*want, str(out), "--overwrite"]:
        assert w in line, (w, line)
    assert "overwrite=True" not in line
    assert out.read_bytes() == before


# ----------------------------------------------------------------------------------------
# frames that vanish or change mid-run
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("change", ["vanishes", "resized"])
def test_frame_changes_mid_run(capsys, monkeypatch, movie, tmp_path, change):
    d = tmp_path / "frames"
    d.mkdir()
    stack = tifffile.imread(movie)
    for i, img in enumerate(stack):
        tifffile.imwrite(d / f"f{i:02d}.tif", img)
    victim = d / "f09.tif"
    real = ImageSeries._raw
    state = {"changed": False}

    def raw(self, i):
        if i == 9 and not state["changed"]:  # the first time frame 9 is needed
            state["changed"] = True
            if change == "vanishes":
                victim.unlink()
            else:
                tifffile.imwrite(victim, stack[9][:-3])
        return real(self, i)

    monkeypatch.setattr(ImageSeries, "_raw", raw)
    out = tmp_path / "r.h5"
    # classical DIC against the single reference: the template's pre-pass (and an STS
    # run's time-model pre-pass) would read the frame before any block
    code, _, err = _run(capsys, "run", d, *RUN, "--m", "0", "--out", out, "--single-reference",
                        *FAST)
    assert code == 1
    line = _one_line(err)
    assert "f09.tif" in line and "frames finished, kept in" in line, line
    done = _fields(out)["completed"]
    assert 0 < done.sum() < len(done)


# ----------------------------------------------------------------------------------------
# input that cannot be misread
# ----------------------------------------------------------------------------------------


def test_fewer_than_two_frames_refused(capsys, tmp_path):
    one = tmp_path / "one.tif"
    tifffile.imwrite(one, np.zeros((40, 40), np.uint8))
    code, _, err = _run(capsys, "run", one, "--m", "0", "--out", tmp_path / "r.h5", *FAST)
    assert code == 2
    assert "1 frame" in _one_line(err)
    assert not (tmp_path / "r.h5").exists()
    with pytest.raises(ValueError, match="1 frame"):
        track(torch.rand(1, 40, 40), config=DICConfig(m=0, subset_size=11), progress=False)


def test_planar_tiff_is_a_stack_not_a_colour_frame(tmp_path):
    planes = np.random.default_rng(1).integers(0, 255, (3, 30, 40), dtype=np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # tifffile: "stored as RGB"
        tifffile.imwrite(tmp_path / "p.tif", planes)  # no photometric: one planar RGB page
        tifffile.imwrite(tmp_path / "pp.tif", np.zeros((2, 3, 30, 40), np.uint8),
                         photometric="rgb", planarconfig="separate")
    with pytest.warns(UserWarning, match="3 grey frames"):
        s = load_series(tmp_path / "p.tif")
    assert len(s) == 3 and not s.is_colour
    for i in range(3):
        np.testing.assert_array_equal(s[i].numpy(), planes[i])
    with pytest.raises(ValueError, match="2 colour frames or 6 grey frames"):
        load_series(tmp_path / "pp.tif")
    # interleaved colour stays one colour frame, converted to grey
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((30, 40, 3), np.uint8), photometric="rgb")
    with pytest.warns(UserWarning, match="converted to grey"):
        assert len(load_series(tmp_path / "rgb.tif")) == 1


def test_file_named_reference_comes_first(capsys, movie, tmp_path):
    d = tmp_path / "dic"
    d.mkdir()
    stack = tifffile.imread(movie)
    names = ["Sample_Reference.tif"] + [f"Sample_{k:03d}.tif" for k in range(1, 4)]
    for name, img in zip(names, stack[:4]):
        tifffile.imwrite(d / name, img)
    with pytest.warns(UserWarning, match="Sample_Reference.tif is named as a reference"):
        s = load_series(d)
    assert Path(s.frame_name(0)).name == "Sample_Reference.tif"
    assert [Path(s.frame_name(i)).name for i in range(1, 4)] == names[1:]
    with pytest.warns(UserWarning, match="kept in the given order"):
        s = load_series(sorted(d.iterdir()))
    assert Path(s.frame_name(3)).name == "Sample_Reference.tif"
    code, out, err = _run(capsys, "run", d, *RUN, "--out", tmp_path / "r.h5", *FAST)
    assert code == 0, err
    assert "reference: 0 (Sample_Reference.tif)" in out
    assert "named as a reference" in err


def test_default_grid_leaves_room_for_motion():
    """Motion 1.5 px/frame upwards, m = 2: the first window of the reference frame moves 6 px;
    the default grid's first row stays inside (a subset/2 margin alone does not)."""
    shape, motion = (72, 72), Translation(vt=-1.5)
    pattern = make_speckle(shape, seed=2, margin=16.0)
    ref, frames = render_series(pattern, shape, motion, torch.arange(1.0, 7.0), seed=3)
    movie = torch.cat([ref[None], frames]).float()
    cfg = DICConfig(subset_size=15, m=2)
    res = track(movie, config=cfg, step=6, frames=[0], progress=False)
    first = res.points[:, 1] == res.points[:, 1].min()
    assert not (res.status[0][first] == int(Status.OUTSIDE)).any()
    plain = grid_points(shape, 6, subset_size=15)  # subset/2 only: the old default
    res0 = track(movie, config=cfg, points=plain, frames=[0], progress=False)
    first0 = res0.points[:, 1] == res0.points[:, 1].min()
    # the old default's first row: its 5-frame window leaves the image; it is OUTSIDE, or
    # measured with a shorter window (m < 2) or with its subsets moved inside the image
    # (off-centre, from the measuring pass's first guess), and then right
    st, m0 = res0.status[0][first0], res0.m[0][first0]
    out = st == int(Status.OUTSIDE)
    assert (out | (m0 < 2)).all() or res0.info.get("off_centre_rows", 0) > 0
    vel = ~out & (m0 > 0)
    # measured: all 10 points of the row solved (30 off-centre rows), 2 with a velocity
    assert vel.any(), (st, m0)
    assert float((res0.vt[0][first0][vel] + 1.5).abs().max()) < 0.05
    assert float(res0.v[0][first0][~out].abs().max()) < 0.01  # frame 0: no motion yet


def test_a_signal_inside_a_finalizer_is_not_lost():
    """Python drops an exception raised in a finalizer (``__del__``, a weakref callback): the
    handler then keeps the signal, and the run stops at the next block instead."""
    import weakref

    from torch_stsdic.cli import signals

    class Thing:
        pass

    with pytest.raises(signals.Interrupted):
        with signals.stop_on_signals():
            t = Thing()

            def callback(_):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # the handler runs here, inside the weakref callback

            ref = weakref.ref(t, callback)
            del t  # the callback runs now; its exception would be printed and dropped
            assert ref() is None
            signals.checkpoint()  # ... the next block: raises
