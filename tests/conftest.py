"""Shared test settings."""

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
