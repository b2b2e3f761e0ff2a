"""Learned initial guess + STS-DIC refinement, and training a network through STS-DIC.

Part 1: a tiny CNN is trained for a few hundred steps on synthetic speckle pairs (Fourier-
shifted speckle, random sub-pixel translations of up to +-5 px) to predict a coarse flow from
(reference, centre frame). Its flow, sampled at the POIs with ``dense_to_points``, is the
initial guess of :class:`torch_stsdic.nn.STSDIC` (whose FFT search is switched off:
``search_radius=0``). Errors before and after the refinement are printed, on held-out
sequences rendered exactly by :mod:`torch_stsdic.synth` (translation + velocity + strain).

Part 2: a small residual denoiser is applied to noisy frames before STS-DIC, and trained for
a few steps with a loss on STS-DIC's displacement and velocity: gradients flow through the
solver by implicit differentiation into the denoiser's weights.

Runs on 2 CPU cores in about a minute:  python scripts/tools/learned_init_example.py
"""

from __future__ import annotations

import math
import time
import warnings

import torch
from torch import nn

from torch_stsdic import DICConfig, grid_points
from torch_stsdic.nn import STSDIC, dense_to_points, points_to_dense
from torch_stsdic.synth import HomogeneousStrain, Translation, make_speckle, render, render_series

torch.manual_seed(0)
torch.set_num_threads(1)  # tiny ops: one thread is fastest on a shared CPU
SIZE = 64  # training / evaluation images are SIZE x SIZE
MAX_SHIFT = 5.0


# ------------------------------------------------------------------------------------------
# Training data: sub-pixel Fourier shifts of a large rendered speckle image, random crops
# ------------------------------------------------------------------------------------------
def fourier_shift(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """g(x) = f(x - (u, v)) for (B, H, W) images (periodic, band-limited interpolation)."""
    h, w = img.shape[-2:]
    ky = torch.fft.fftfreq(h, dtype=img.dtype).view(1, h, 1)
    kx = torch.fft.rfftfreq(w, dtype=img.dtype).view(1, 1, -1)
    phase = torch.exp(-2j * math.pi * (kx * u.view(-1, 1, 1) + ky * v.view(-1, 1, 1)))
    return torch.fft.irfft2(torch.fft.rfft2(img) * phase, s=(h, w))


BIG = render(make_speckle((256, 256), seed=11), (256, 256)).float()
CROP = SIZE + 32  # Fourier-shift a larger crop, keep its centre (away from the wrap-around)


def training_batch(n: int, gen: torch.Generator):
    """(n, 2, SIZE, SIZE) (ref, moved) pairs and their (n, 2) displacements."""
    d = (torch.rand(n, 2, generator=gen) * 2 - 1) * MAX_SHIFT
    i, j = torch.randint(0, 256 - CROP, (2, n), generator=gen)
    rows = (i.view(n, 1) + torch.arange(CROP)).view(n, CROP, 1)
    cols = (j.view(n, 1) + torch.arange(CROP)).view(n, 1, CROP)
    crops = BIG[rows, cols]
    moved = fourier_shift(crops, d[:, 0], d[:, 1])
    inner = slice(16, 16 + SIZE)
    pair = torch.stack([crops[:, inner, inner], moved[:, inner, inner]], 1)
    return pair + 2.0 * torch.randn(pair.shape, generator=gen), d


class CoarseFlow(nn.Module):
    """(B, 2, H, W) image pair -> (B, 2, H/2, W/2) coarse flow, px.

    A shared 3-layer encoder (half resolution), a local correlation volume over +-R feature
    pixels (+-2R px), box-filtered, a soft-argmax, and a small convolutional correction."""

    def __init__(self, ch: int = 16, radius: int = 3) -> None:
        super().__init__()
        self.r = radius
        self.enc = nn.Sequential(
            nn.Conv2d(1, ch, 3, padding=1), nn.ReLU(),
            nn.Conv2d(ch, ch, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(ch, ch, 3, padding=1),
        )
        k = (2 * radius + 1) ** 2
        self.head = nn.Sequential(nn.Conv2d(k, 32, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(32, 2, 3, padding=1))
        self.beta = nn.Parameter(torch.tensor(10.0))
        r = torch.arange(-radius, radius + 1, dtype=torch.float32)
        dy, dx = torch.meshgrid(r, r, indexing="ij")
        self.register_buffer("disp", torch.stack([dx.reshape(-1), dy.reshape(-1)]) * 2.0)

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        x = (pair - pair.mean((2, 3), keepdim=True)) / pair.std((2, 3), keepdim=True)
        b, _, h, w = x.shape
        f = self.enc(x.reshape(b * 2, 1, h, w))
        f = nn.functional.normalize(f, dim=1).reshape(b, 2, -1, h // 2, w // 2)
        f1, f2 = f[:, 0], f[:, 1]
        r = self.r
        f2p = nn.functional.pad(f2, (r, r, r, r))
        hh, ww = f1.shape[-2:]
        corr = torch.stack([
            (f1 * f2p[..., r + dy : r + dy + hh, r + dx : r + dx + ww]).sum(1)
            for dy in range(-r, r + 1) for dx in range(-r, r + 1)
        ], 1)  # (B, K, h/2, w/2): <f1(x), f2(x + d)>
        corr = nn.functional.avg_pool2d(corr, 5, 1, 2, count_include_pad=False)
        prob = torch.softmax(self.beta * corr, 1)
        flow = torch.einsum("bkhw,ck->bchw", prob, self.disp)
        return flow + self.head(corr)

    def dense(self, pair: torch.Tensor) -> torch.Tensor:
        """(B, 2, H, W) flow, bilinear upsampling of the coarse flow."""
        return nn.functional.interpolate(self(pair), size=pair.shape[-2:], mode="bilinear",
                                         align_corners=False)


def train_coarse_flow(steps: int = 200) -> CoarseFlow:
    gen = torch.Generator().manual_seed(1)
    net = CoarseFlow()
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for step in range(steps):
        pair, d = training_batch(12, gen)
        pred = net(pair)
        loss = (pred - d.view(-1, 2, 1, 1)).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 100 == 0 or step == steps - 1:
            print(f"  CNN step {step:3d}  L1 loss {loss.item():.3f} px")
    return net


# ------------------------------------------------------------------------------------------
# Evaluation sequences: exact renders with known motion
# ------------------------------------------------------------------------------------------
def sequences(n: int, seed: int, noise: float, size: int = SIZE, m: int = 1):
    """n sequences: refs (n, H, W), frames (n, 2m+1, H, W) at t = 1..2m+1 (centre m+1),
    truth(points) -> (disp (n, N, 2), vel (n, N, 2)) at the centre frame."""
    gen = torch.Generator().manual_seed(seed)
    times = torch.arange(1.0, 2 * m + 2)
    tc = float(times[m])
    refs, frames, motions = [], [], []
    for k in range(n):
        u0, v0 = ((torch.rand(2, generator=gen) * 2 - 1) * (MAX_SHIFT - 1.0)).tolist()
        ut, vt = ((torch.rand(2, generator=gen) * 2 - 1) * 0.3).tolist()
        exx, eyy = ((torch.rand(2, generator=gen) * 2 - 1) * 0.005).tolist()
        c = (size / 2, size / 2)
        motion = Translation(u0, v0, ut, vt) + HomogeneousStrain(exx, eyy, center=c)
        pat = make_speckle((size, size), seed=seed * 1000 + k)
        r, f = render_series(pat, (size, size), motion, times, noise_sigma=noise,
                             seed=seed * 1000 + k, reference_time=None)
        refs.append(r)
        frames.append(f)
        motions.append(motion)

    def truth(points: torch.Tensor):
        x, y = points[:, 0].double(), points[:, 1].double()
        disp, vel = [], []
        for mo in motions:
            u, v = mo.displacement(x, y, torch.full_like(x, tc))
            ut, vt = mo.velocity(x, y, torch.full_like(x, tc))
            disp.append(torch.stack([u, v], -1))
            vel.append(torch.stack([ut, vt], -1))
        return torch.stack(disp), torch.stack(vel)

    return torch.stack(refs), torch.stack(frames), truth


def rms(e: torch.Tensor) -> float:
    e = e[torch.isfinite(e).all(-1)]
    return float(e.pow(2).sum(-1).mean().sqrt()) if e.numel() else float("nan")


def part1(net: CoarseFlow) -> None:
    refs, frames, truth = sequences(8, seed=5, noise=2.0)
    # margin 13 px: subset half-width 7 + the largest shift; x, y = 13, 19, ..., 49
    pts = grid_points((SIZE, SIZE), 6, roi=(13, 13, SIZE - 14, SIZE - 14)).float()
    disp_true, _ = truth(pts)
    with torch.no_grad():
        pair = torch.stack([refs, frames[:, 1]], 1).float()
        flow = net.dense(pair)  # (B, 2, H, W) coarse flow at the centre frame
    init = dense_to_points(flow, pts)  # (B, N, 2)
    print(f"  CNN flow at {pts.shape[0]} POIs x {refs.shape[0]} sequences: "
          f"RMS error {rms(init.double() - disp_true):.3f} px")
    cfg = DICConfig(subset_size=15, m=1, search_radius=0)  # no FFT search: the CNN's guess
    dic = STSDIC(cfg)
    t0 = time.perf_counter()
    out = dic.forward_full(refs.float(), frames.float(), pts, init=init)
    t1 = time.perf_counter() - t0
    ok = out.ok
    print(f"  STS-DIC from the CNN init: RMS error {rms(out.disp.double() - disp_true):.4f} px, "
          f"{int(ok.sum())}/{ok.numel()} POIs ok, {t1:.2f} s")
    zero = dic.forward_full(refs.float(), frames.float(), pts, init=torch.zeros_like(init))
    print(f"  STS-DIC from a zero init (same settings): RMS error "
          f"{rms(zero.disp.double() - disp_true):.4f} px on "
          f"{int(zero.ok.sum())}/{zero.ok.numel()} POIs ok")
    dense = points_to_dense(pts, out.disp, (SIZE, SIZE))
    print(f"  dense field from the POIs: {tuple(dense.shape)}, "
          f"{int(torch.isfinite(dense).all(1).sum())} finite pixels")


# ------------------------------------------------------------------------------------------
# Part 2: train a denoiser through STS-DIC
# ------------------------------------------------------------------------------------------
class Denoiser(nn.Module):
    """Residual 3-layer CNN applied to every image (B, 1, H, W); starts as the identity."""

    def __init__(self, ch: int = 8) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(1, ch, 3, padding=1), nn.ReLU(),
            nn.Conv2d(ch, ch, 3, padding=1), nn.ReLU(),
            nn.Conv2d(ch, 1, 3, padding=1),
        )
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + 10.0 * self.body(x / 100.0)


def dic_loss(den: Denoiser, dic: STSDIC, refs, frames, pts, disp_true, vel_true):
    """Mean squared (disp, vel) error of the CONVERGED POIs (the others carry no gradient)."""
    b, t, h, w = frames.shape
    imgs = torch.cat([refs.unsqueeze(1), frames], 1).reshape(-1, 1, h, w)
    clean = den(imgs).reshape(b, t + 1, h, w)
    out = dic.forward_full(clean[:, 0], clean[:, 1:], pts)
    ok = out.converged
    err = torch.cat([out.disp - disp_true, out.vel - vel_true], -1)[ok]
    return err.pow(2).sum(-1).mean(), out


def evaluate(den: Denoiser, dic: STSDIC, data, pts) -> str:
    with torch.no_grad():
        loss, out = dic_loss(den, dic, *data[:2], pts, *data[2:])
    e = (out.disp - data[2]).norm(dim=-1)[out.converged]
    return (f"disp+vel RMS {loss.sqrt().item():.4f} px, disp RMS "
            f"{e.pow(2).mean().sqrt().item():.4f} px, median {e.median().item():.4f} px, "
            f"{int(out.converged.sum())}/{out.converged.numel()} converged")


def part2(steps: int = 20) -> None:
    size = 48
    pts = grid_points((size, size), 6, roi=(11, 11, size - 12, size - 12)).float()
    dic = STSDIC(DICConfig(subset_size=13, m=1))  # formulation "auto"
    train = sequences(6, seed=7, noise=8.0, size=size)
    test = sequences(6, seed=8, noise=8.0, size=size)
    tr = [x.float() for x in train[:2]] + [y.float() for y in train[2](pts)]
    te = [x.float() for x in test[:2]] + [y.float() for y in test[2](pts)]
    den = Denoiser()
    opt = torch.optim.Adam(den.parameters(), lr=5e-3)
    print(f"  held-out, identity denoiser: {evaluate(den, dic, te, pts)}")
    for step in range(steps):
        loss, out = dic_loss(den, dic, *tr[:2], pts, *tr[2:])
        opt.zero_grad()
        with warnings.catch_warnings():  # counted in out.report instead
            warnings.simplefilter("ignore", RuntimeWarning)
            loss.backward()
        gnorm = sum(float(p.grad.norm() ** 2) for p in den.parameters()) ** 0.5
        opt.step()
        if step % 4 == 0 or step == steps - 1:
            rep = out.report
            print(f"  step {step:2d}  train loss (disp+vel MSE) {loss.item():.5f} px^2  "
                  f"|grad| {gnorm:.3g}  zero-grad POIs {rep['zero_grad']}/"
                  f"{out.status.numel()}")
    print(f"  held-out, trained denoiser:  {evaluate(den, dic, te, pts)}")


def main() -> None:
    t0 = time.perf_counter()
    print("Part 1: learned coarse flow, refined by STS-DIC")
    net = train_coarse_flow()
    part1(net)
    print(f"  ({time.perf_counter() - t0:.1f} s so far)")
    print("Part 2: training a denoiser through STS-DIC (implicit gradients)")
    part2()
    print(f"total {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
