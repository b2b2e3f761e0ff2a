"""How an interrupted ``stsdic`` process ends: exit code 130 even when a daemon thread is
inside a torch op at that moment (the interpreter's shutdown would abort the process)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

import torch_stsdic as sts
from torch_stsdic.cli import signals

ROOT = Path(sts.__file__).resolve().parents[1]

# a command that leaves a daemon thread inside torch ops (as a frame reader that did not stop
# within its wait), then reports an interruption, run through the ``stsdic`` launcher
_CHILD = """
import sys, threading, time
import torch
import torch_stsdic.cli
import stsdic_launcher

a = torch.randn(400, 400)
inside = threading.Event()

def reader():
    while True:
        inside.set()
        a @ a  # torch releases the GIL here and takes it back on the way out

def command(argv=None):
    threading.Thread(target=reader, daemon=True).start()
    inside.wait()
    time.sleep(0.05)
    print("stsdic: interrupted by SIGINT: 3 of 12 frames kept in out.h5", file=sys.stderr)
    print("summary line", end="")  # unflushed output is kept
    return 130

torch_stsdic.cli.main = command
sys.exit(stsdic_launcher.main())
"""


def test_an_interrupted_command_exits_130_with_a_thread_inside_torch(tmp_path):
    """The shutdown stops a daemon thread that takes the GIL with pthread_exit; inside a
    torch op that unwinds through a noexcept destructor: "terminate called without an active
    exception", exit 134 (5 of 5 runs before). The launcher ends the process at once."""
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT),
                                                        os.environ.get("PYTHONPATH", "")])}
    for _ in range(3):
        r = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
        assert "terminate called" not in r.stderr
        assert r.stdout == "summary line"
        assert r.stderr.startswith("stsdic: interrupted by SIGINT")


@pytest.mark.parametrize("code", [0, 1, 2, 3, 134])
def test_other_exit_codes_take_the_normal_way_out(code):
    assert signals.leave_if_interrupted(code) == code
