"""Shared test settings and helpers."""

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    # The tests use small tensors: intra-op threading only costs time there, and on a loaded
    # 2-core machine oversubscription slowed some tests down 10-50x.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


_SIGINT_AT_START = signal.getsignal(signal.SIGINT)


def _signal_leak(where: str) -> None:
    """SIGINT's handler found changed (``where``): put the session's first one back, and name
    the test in the file the environment variable STSDIC_SIGNAL_LOG names, where set."""
    signal.signal(signal.SIGINT, _SIGINT_AT_START)
    log = os.environ.get("STSDIC_SIGNAL_LOG")
    if log:
        with open(log, "a") as f:
            f.write(where + "\n")


@pytest.fixture(autouse=True)
def _sigint_handler_restored(request):
    """Every test starts and ends with the session's SIGINT handler: a handler left ignored
    (SIG_IGN), by a test or a fixture's or a finalizer's clean-up between tests, passes on
    through exec to every child process a later test starts, which then never sees a
    Ctrl-C (test_native's interrupted children "hung" so)."""
    if signal.getsignal(signal.SIGINT) is not _SIGINT_AT_START:
        _signal_leak(f"before {request.node.nodeid}")
    yield
    if signal.getsignal(signal.SIGINT) is not _SIGINT_AT_START:
        _signal_leak(f"in {request.node.nodeid}")


@contextlib.contextmanager
def _mounted_tmpfs(where: Path, options: str):
    """A small tmpfs (mount ``options``, e.g. "size=64k" or "ro,size=64k") at ``where``
    (root on Linux only), else the test is skipped."""
    where.mkdir()
    if sys.platform != "linux" or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root on Linux")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


@pytest.fixture
def tmpfs():
    """``with tmpfs(folder, "size=64k") as d:`` a real small file system for fault tests."""
    return _mounted_tmpfs
