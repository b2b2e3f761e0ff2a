"""kernels.scatter.scatter_add_: bin sums equal to a plain loop's, the same on every call,
and a clear error for bad input."""

from __future__ import annotations

import pytest
import torch

from torch_stsdic.kernels.scatter import scatter_add_


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_scatter_add_is_the_sum_per_bin(dtype):
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(0, 17, (500,), generator=g)
    vals = torch.randn(500, generator=g).to(dtype)
    start = torch.arange(20, dtype=dtype)
    out = scatter_add_(start.clone(), idx, vals)
    assert out.dtype == dtype and out.shape == (20,)
    want = start.double().clone()
    for i, v in zip(idx.tolist(), vals.double().tolist()):
        want[i] += v
    tol = dict(rtol=1e-6, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-14, atol=1e-12)
    torch.testing.assert_close(out.double(), want, **tol)
    assert torch.equal(out[17:], start[17:])  # bins no index reaches: untouched
    assert torch.equal(scatter_add_(start.clone(), idx, vals), out)  # the same every call
    # the same as index_put_ with accumulate (the CUDA path's operation)
    ref = start.clone().index_put_((idx,), vals, accumulate=True)
    torch.testing.assert_close(out, ref)


def test_scatter_add_rejects_bad_input():
    with pytest.raises(ValueError, match="3 indices for 4 values"):
        scatter_add_(torch.zeros(5), torch.tensor([0, 1, 2]), torch.ones(4))
    with pytest.raises(ValueError, match="must be 1-D"):
        scatter_add_(torch.zeros(2, 5), torch.tensor([0]), torch.ones(1))
