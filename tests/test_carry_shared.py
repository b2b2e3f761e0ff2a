"""The carried guess of a specimen that shakes (:meth:`torch_stsdic.movie.carry.Carry.shared_step`):
the shared motion's displacement between the last row and the next frames added to the
carry's linear prediction, less the part of it the carried velocity already holds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_stsdic.core.shared_motion import SharedMotion
from torch_stsdic.movie.carry import make_carry


def _shaking_linear_motion(seed: int):
    """Three points moving linearly in time plus an affine shake of the whole field (0.2 px
    translation, 1e-3 du/dx std per frame) over 30 frames: the times (30,), the shake
    (:class:`SharedMotion`), the points (3, 2) and ``total(frames)`` (K, 3, 2) px."""
    g = torch.Generator().manual_seed(seed)
    n_series = 30
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

    return ts, shared, pts, total


def test_carry_with_the_shared_motion_predicts_a_shaking_linear_motion_exactly():
    ts, shared, pts, total = _shaking_linear_motion(seed=0)
    n = pts.shape[0]

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


def _rows(t: np.ndarray, grads: dict[str, np.ndarray], status: np.ndarray | None = None
          ) -> dict[str, np.ndarray]:
    """A block's stored rows (B, N) with u = v = 0 and the given gradients."""
    b, n = grads["ux"].shape
    rows = {nm: np.zeros((b, n)) for nm in ("u", "v")}
    rows.update(grads)
    rows["status"] = np.zeros((b, n), dtype=np.int8) if status is None else status
    return rows


def test_the_carry_moves_the_displacement_gradients_on_by_their_rates():
    """A specimen that deforms steadily: each gradient's least-squares slope over the block's
    trusted rows carries it on exactly (a row that is not trusted does not enter it); a
    point with one trusted row takes the rate from the previous carry to that row; a point
    with none of either keeps its gradients."""
    names = ("u", "ux", "uy", "v", "vx", "vy")
    t = np.arange(4.0, 12.0)  # a block of 8 targets
    n = 3
    rate = np.array([[2e-3, -1e-3, 0.0], [5e-4, 0.0, 3e-3], [0.0, 4e-3, -2e-3],
                     [1e-3, 1e-3, 1e-3]])  # (4 gradients, N)
    base = np.array([0.01, -0.02, 0.03])
    grads = {nm: base + rate[g] * t[:, None] for g, nm in enumerate(("ux", "uy", "vx", "vy"))}
    status = np.zeros((8, n), dtype=np.int8)
    status[3, 0] = 5  # not trusted: its (wrong) value must not enter the slope
    grads["vy"][3, 0] = 1.0
    carry = make_carry(_rows(t, grads, status), t, names, None, torch.float64, "cpu")
    pred = carry.predict(torch.tensor([14.0, 19.0], dtype=torch.float64))
    for g, nm in enumerate(("ux", "uy", "vx", "vy")):
        truth = torch.from_numpy(base + rate[g] * np.array([[14.0], [19.0]]))
        torch.testing.assert_close(pred[nm], truth, rtol=0, atol=1e-12)
    # the next block of one target: its rate from the carry before
    t2 = np.array([12.0])
    one = {nm: base + rate[g] * t2[:, None] for g, nm in enumerate(("ux", "uy", "vx", "vy"))}
    st2 = np.zeros((1, n), dtype=np.int8)
    st2[0, 2] = 5  # the last row not trusted: no rate
    carry2 = make_carry(_rows(t2, one, st2), t2, names, carry, torch.float64, "cpu")
    pred2 = carry2.predict(torch.tensor([15.0], dtype=torch.float64))
    for g, nm in enumerate(("ux", "uy", "vx", "vy")):
        truth = base[:2] + rate[g, :2] * 15.0
        torch.testing.assert_close(pred2[nm][0, :2], torch.from_numpy(truth), rtol=0,
                                   atol=1e-12)
        assert float(carry2.rates[nm][2]) == 0.0


@pytest.mark.parametrize("masked", [False, True], ids=["half-widths-read", "every-masked"])
def test_a_carried_window_velocity_holds_the_shake_of_the_rows_own_window(monkeypatch,
                                                                          masked):
    """A window's ut, vt hold the shared motion's slope over its own frames: the carried
    velocity minus the slope over the carry's window (:meth:`Carry.shared_slope`), plus the
    slope over each row's window (``block_start.window_shake``), is the window velocity of a
    shaking linear motion exactly, for windows of any half-width; with the half-widths the
    rows take read first (the CPU's choice) or every half-width's slope masked (a GPU's,
    ``core.choices.MASKED_GROUPS``)."""
    from types import SimpleNamespace

    from torch_stsdic.core import choices
    from torch_stsdic.movie.block_start import window_shake

    monkeypatch.setattr(choices, "MASKED_GROUPS", masked)

    ts, shared, pts, total = _shaking_linear_motion(seed=1)
    n = pts.shape[0]

    def window_velocity(k: int, m: int) -> torch.Tensor:  # (N, 2) by numpy's line fit
        frames = list(range(k - m, k + m + 1))
        tot = total(frames).numpy()
        return torch.from_numpy(np.stack([np.polyfit(frames, tot[:, i], 1)[0]
                                          for i in range(n)]))

    last, m = 10, 2
    slope = window_velocity(last, m)
    rows = {"u": total([9, 10])[..., 0].numpy(), "v": total([9, 10])[..., 1].numpy(),
            "ut": np.stack([np.full(n, np.nan), slope[:, 0].numpy()]),
            "vt": np.stack([np.full(n, np.nan), slope[:, 1].numpy()]),
            "status": np.zeros((2, n), dtype=np.int8), "m": np.full((2, n), m, dtype=np.int8)}
    rows["ut"][1, 2] = rows["vt"][1, 2] = np.nan  # point 2: classical, a finite difference
    rows["m"][1, 2] = 0
    names = ("u", "v", "ut", "vt")
    carry = make_carry(rows, np.array([9.0, 10.0]), names, None, torch.float64, "cpu",
                       frames=[9, 10])
    ks = [12, 16]
    pred = carry.predict(ts[ks])
    init = torch.stack([pred[nm].reshape(-1) for nm in names], 1)  # (B*N, P)
    held = carry.shared_slope(shared, pts, ts).repeat(len(ks), 1)
    window_m = torch.tensor([1, 3, 3, 3, 1, 1], dtype=torch.int8)  # each row's own

    asked = []

    def shake_slope(mm: int) -> torch.Tensor:  # (B*N, 2) by numpy's line fit
        asked.append(mm)
        out = []
        for k in ks:
            frames = list(range(k - mm, k + mm + 1))
            gd = shared.displacement(pts, torch.tensor(frames)).numpy()
            out.append(np.stack([np.polyfit(frames, gd[:, i], 1)[0] for i in range(n)]))
        return torch.from_numpy(np.concatenate(out))

    blk = SimpleNamespace(run=SimpleNamespace(names=list(names), m=3), window_m=window_m,
                          shared_slope=shake_slope)
    before = init.clone()
    window_shake(blk, init, torch.ones(len(ks) * n, dtype=torch.bool), held)
    truth = torch.cat([torch.stack([window_velocity(k, int(window_m[j * n + i]))[i]
                                    for i in range(n)]) for j, k in enumerate(ks)])
    torch.testing.assert_close(init[:, 2:4], truth, rtol=0, atol=1e-10)
    assert float((before[:, 2:4] - truth).abs().max()) > 0.01  # the carry's own: off
    assert asked == ([1, 2, 3] if masked else [1, 3])  # every one, or those the rows take


def test_a_classical_block_of_a_shaking_specimen_starts_from_its_pilots_shift(monkeypatch):
    """A plain classical run of a specimen that shakes (0.3 px a frame at random, a drift of
    0.2 px a frame): each block solves a few pilot points per target first and starts its
    other carried rows moved by their median shift (``block_start.pilot_shift``): fewer
    Gauss-Newton iterations, the same solutions within the solver's tolerance, and the
    motion measured to its noise."""
    from torch_stsdic import DICConfig
    from torch_stsdic.movie import block as block_mod
    from torch_stsdic.movie import block_start
    from torch_stsdic.movie.series import track
    from torch_stsdic.synth import RigidJitter, Translation, make_speckle, render_series

    size, times = 192, torch.arange(0.0, 25)
    jitter = RigidJitter.random(times, 0.3, seed=3)
    motion = Translation(ut=0.2, vt=-0.1) + jitter
    ref, frames = render_series(make_speckle((size, size), seed=6), (size, size), motion,
                                times[1:], noise_sigma=2.0, seed=7)
    movie = torch.cat([ref[None], frames]).numpy()
    kw = dict(config=DICConfig(m=0, subset_size=21), step=7, batch_frames=8, progress=False,
              series_reference=False, checks=False)
    with_pilot = track(movie, **kw)
    assert with_pilot.points.shape[0] >= 8 * block_start.PILOT_POINTS
    monkeypatch.setattr(block_mod, "pilot_shift", lambda *a: None)
    without = track(movie, **kw)
    ok = (with_pilot.status <= 1) & (without.status <= 1)
    assert float(ok.double().mean()) > 0.99
    its = with_pilot.iterations[1:].double().mean(), without.iterations[1:].double().mean()
    assert its[0] < its[1] - 1.0, its  # measured 3.5 against 5.3
    truth_u = (0.2 * times + jitter.tx)[:, None]  # the shake moves every point alike
    err = with_pilot.u.double() - truth_u
    good = with_pilot.status <= 1
    # no wrong peak (started 0.3 px off, 4 rows of the run without pilots converged 1.7 px
    # away at ZNCC 0.81-0.84), the motion to its noise
    assert float(err[good].abs().max()) < 0.1
    assert float(err[good][1:].pow(2).mean().sqrt()) < 0.02
    truth_v = (-0.1 * times + jitter.ty)[:, None]
    both = ok & ((without.u.double() - truth_u).abs() < 0.1) & (
        (without.v.double() - truth_v).abs() < 0.1)
    for nm in ("u", "v"):  # the same minimum where both found it (a row that took the
        # run without pilots 21-25 iterations ends 0.02 px off: within 0.05)
        x, y = getattr(with_pilot, nm)[both].double(), getattr(without, nm)[both].double()
        assert float((x - y).pow(2).mean().sqrt()) < 1e-3, nm
        assert float((x - y).abs().max()) < 0.05, nm


def test_the_carried_shake_slope_of_every_half_width_reads_nothing_and_is_the_same():
    """Given the run's longest half-width, :meth:`Carry.shared_slope` takes every half-width
    up to it without a host read of those its rows have (on a GPU a read waits for the
    device), and gives the numbers of the read path: rows of mixed half-widths, a classical
    row (its finite difference) and a point without a velocity."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Reads(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.seen: list[str] = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket.__name__ in ("_local_scalar_dense", "nonzero", "equal"):
                self.seen.append(func.overloadpacket.__name__)
            return func(*args, **(kwargs or {}))

    ts, shared, pts, total = _shaking_linear_motion(seed=2)
    n = pts.shape[0]
    rows = {"u": total([9, 10])[..., 0].numpy(), "v": total([9, 10])[..., 1].numpy(),
            "ut": np.stack([np.full(n, np.nan), np.array([0.1, np.nan, 0.3])]),
            "vt": np.stack([np.full(n, np.nan), np.array([0.2, np.nan, -0.1])]),
            "status": np.zeros((2, n), dtype=np.int8),
            "m": np.stack([np.zeros(n, dtype=np.int8), np.array([3, 0, 1], dtype=np.int8)])}
    carry = make_carry(rows, np.array([9.0, 10.0]), ("u", "v", "ut", "vt"), None,
                       torch.float64, "cpu", frames=[9, 10])
    read = carry.shared_slope(shared, pts, ts)
    reads = Reads()
    with reads:
        free = carry.shared_slope(shared, pts, ts, m_max=4)
    assert not reads.seen, reads.seen
    assert torch.equal(free, read)
    assert bool((read.abs() > 0).all(1)[[0, 2]].all())  # the windows' slopes, not zero


def test_the_neighbour_fill_stops_at_the_first_ring_that_fills_none_with_the_same_carry(
        monkeypatch):
    """A lost region three rings deep (a square of 6 x 6 points in a 14 x 14 grid) and a
    lost point with no valid neighbour within reach of any ring: until done (the CPU's
    choice, ``core.choices.UNTIL_DONE``) the fill takes the three rings that fill
    points and one that fills none, then stops; every ring (a GPU's) takes all eight. The
    carry is the same to the bit."""
    from torch_stsdic.analysis.quality import neighbours
    from torch_stsdic.core import choices
    from torch_stsdic.movie import carry as carry_mod
    from torch_stsdic.movie.carry import Carry

    ys, xs = torch.meshgrid(torch.arange(14.0) * 10, torch.arange(14.0) * 10, indexing="ij")
    pts = torch.stack([xs.flatten(), ys.flatten()], 1)
    n = pts.shape[0]
    far = torch.tensor([[500.0, 500.0]])  # a point alone, far from the grid
    pts = torch.cat([pts, far])
    nb = neighbours(pts)
    g = torch.Generator().manual_seed(5)
    vals = {nm: torch.randn(n + 1, generator=g, dtype=torch.float64) * 0.01
            for nm in ("u", "v", "ux", "uy", "vx", "vy")}
    vals["u"] = vals["u"] + 2e-3 * pts[:, 0]
    lost = ((xs >= 40) & (xs < 100) & (ys >= 40) & (ys < 100)).flatten()
    valid = torch.cat([~lost, torch.tensor([False])])
    carry = Carry(t=0.0, vals=vals, vel_u=0.1 * vals["u"], vel_v=0.1 * vals["v"],
                  valid=valid)
    calls = []
    guess = carry_mod.neighbour_guess

    def spy(*args, **kwargs):
        calls.append(1)
        return guess(*args, **kwargs)

    monkeypatch.setattr(carry_mod, "neighbour_guess", spy)
    out = {}
    for until_done in (True, False):
        monkeypatch.setattr(choices, "UNTIL_DONE", until_done)
        calls.clear()
        filled_carry, filled = carry.from_neighbours(nb, pts)
        out[until_done] = (filled_carry, int(filled), len(calls))
    (a, fa, ca), (b, fb, cb) = out[True], out[False]
    assert (ca, cb) == (4, carry_mod.FILL_ROUNDS)
    assert fa == fb == int(lost.sum())  # the lone point stays without a carry
    assert not bool(a.valid[-1]) and bool(a.valid[:-1].all())
    assert torch.equal(a.valid, b.valid)
    for nm in vals:
        assert torch.equal(a.vals[nm], b.vals[nm])
    assert torch.equal(a.vel_u, b.vel_u) and torch.equal(a.vel_v, b.vel_v)
