"""Shared test settings and helpers."""

import contextlib
import os
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
