"""The carried guess of a specimen that shakes (:meth:`torch_stsdic.movie.carry.Carry.shared_step`):
the shared motion's displacement between the last row and the next frames added to the
carry's linear prediction, less the part of it the carried velocity already holds."""

from __future__ import annotations

import numpy as np
import torch

from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.carry import make_carry


def test_carry_with_the_shared_motion_predicts_a_shaking_linear_motion_exactly():
    g = torch.Generator().manual_seed(0)
    n_series, n = 30, 3
    ts = torch.arange(n_series, dtype=torch.float64)
    params = np.zeros((n_series, 6))
    params[:, :2] = 0.2 * torch.randn(n_series, 2, generator=g, dtype=torch.float64).numpy()
    params[:, 2] = 1e-3 * torch.randn(n_series, generator=g, dtype=torch.float64).numpy()
    shared = SharedMotion(kind="affine", params=params, origin=np.array([50.0, 50.0]),
                          scatter=np.zeros(n_series), points=np.ones(n_series, dtype=int),
                          measured=np.ones(n_series, dtype=bool))
    pts = torch.tensor([[10.0, 20.0], [60.0, 45.0], [90.0, 80.0]], dtype=torch.float64)
    a = torch.tensor([[0.3, -0.1], [1.0, 0.2], [-0.5, 0.4]], dtype=torch.float64)
    b = torch.tensor([[0.05, 0.02], [-0.03, 0.01], [0.0, -0.04]], dtype=torch.float64)

    def total(frames: list[int]) -> torch.Tensor:  # (K, N, 2) deformation + shake
        f = torch.tensor(frames)
        return a + b * ts[f].view(-1, 1, 1) + shared.displacement(pts, f)

    last, m = 10, 2
    win = list(range(last - m, last + m + 1))
    tot = total(win)  # (T, N, 2): the window's ut, vt are the slope of its LS line
    dt = ts[win] - ts[win].mean()
    slope = (dt.view(-1, 1, 1) * (tot - tot.mean(0))).sum(0) / dt.square().sum()
    rows = {"u": total([9, 10])[..., 0].numpy(), "v": total([9, 10])[..., 1].numpy(),
            "ut": np.stack([np.full(n, np.nan), slope[:, 0].numpy()]),
            "vt": np.stack([np.full(n, np.nan), slope[:, 1].numpy()]),
            "status": np.zeros((2, n), dtype=np.int8), "m": np.full((2, n), m, dtype=np.int8)}
    rows["ut"][1, 2] = rows["vt"][1, 2] = np.nan  # point 2: a classical row, its velocity a
    rows["m"][1, 2] = 0  # finite difference of frames 9 and 10
    carry = make_carry(rows, np.array([9.0, 10.0]), ("u", "v", "ut", "vt"), None,
                       torch.float64, "cpu", frames=[9, 10])
    ks = torch.tensor([11, 13])
    pred = carry.predict(ts[ks])
    plain = torch.stack([pred["u"], pred["v"]], -1)
    step = carry.shared_step(shared, pts, ks, ts)
    truth = total([11, 13])
    torch.testing.assert_close(plain + step, truth, rtol=0, atol=1e-12)
    assert float((plain - truth).abs().max()) > 0.1  # without it: the shake's error
