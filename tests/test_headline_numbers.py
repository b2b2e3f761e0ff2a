"""The README's and docs' headline numbers on small versions of the same experiments
(issue 39): Table 1's ratio (STS-DIC m = 2 over classical DIC with a clean reference, README
0.45, theory 1/sqrt(5) = 0.447), the single-noisy-reference bound (README 0.77, theory
sqrt((1 + 1/5) / 2) = 0.775) and the noise floor (docs/validation.md: measured / predicted
0.94-1.09). The demo table's numbers are checked in tests/test_demo.py on the quick demo.

The small experiment: a 121 x 121 render of the paper's motion u = t/20, the window t = 3..7
centred on t = 5, 36 points, subset 21, sigma 5 on every noisy image, 4 noise realisations
(one solve_window each for classical and STS-DIC, clean and noisy reference; ~2 s).
"""

from __future__ import annotations

import pytest
import torch

import torch_stsdic as sts
from torch_stsdic.core.noise import predicted_std
from torch_stsdic.synth import Translation, add_noise, make_speckle, render_series

SIZE = (121, 121)
SIGMA = 5.0
U_CENTRE = 0.25  # u = t / 20 at t = 5


@pytest.fixture(scope="module")
def table1_small():
    pat = make_speckle(SIZE, seed=0)
    ref, frames = render_series(pat, SIZE, Translation(ut=0.05), torch.arange(3.0, 8.0),
                                seed=0)
    xs = torch.arange(25.0, 97.0, 12.0, dtype=torch.float64)
    pts = torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    g = torch.Generator().manual_seed(100)
    errs: dict[str, list[torch.Tensor]] = {}
    for _ in range(4):
        noisy_ref = add_noise(ref, SIGMA, generator=g)
        noisy = torch.stack([add_noise(f, SIGMA, generator=g) for f in frames])
        for kind, r in (("clean", ref), ("noisy", noisy_ref)):
            c = sts.solve_window(r, noisy[2:3], pts, sts.DICConfig(m=0))
            s = sts.solve_window(r, noisy, pts, sts.DICConfig(m=2))
            for name, sol in (("classical", c), ("sts", s)):
                assert sts.usable(sol.status).all()
                errs.setdefault(f"{name} {kind}", []).append(sol.u - U_CENTRE)
    rms = {k: float(torch.cat(v).pow(2).mean().sqrt()) for k, v in errs.items()}

    def floor(m: int, sigma_ref: float) -> float:
        p = predicted_std(ref, pts, sts.DICConfig(m=m), sigma_ref=sigma_ref, sigma_def=SIGMA,
                          n_frames=2 * m + 1, displacement=U_CENTRE)["u"]
        return float(p.pow(2).mean().sqrt())

    predicted = {"classical noisy": floor(0, SIGMA), "sts noisy": floor(2, SIGMA),
                 "classical clean": floor(0, 0.0), "sts clean": floor(2, 0.0)}
    return rms, predicted


def test_table1_ratio_clean_reference(table1_small):
    """README: 'With a clean reference, joint STS-DIC has 0.45x the classical error'. Here
    measured 0.452 (seeds 0-5 of this small experiment: 0.42-0.54); band 0.36..0.60."""
    rms, _ = table1_small
    ratio = rms["sts clean"] / rms["classical clean"]
    assert 0.36 < ratio < 0.60, rms


def test_single_noisy_reference_bound(table1_small):
    """README: with one noisy reference STS-DIC's u error is at least 0.77 of classical DIC's
    (0.75-0.80 measured on the demo). Here measured 0.748 (seeds 0-5: 0.70-0.78); band
    0.62..0.88: far from the clean-reference 0.45 and from no gain at all."""
    rms, _ = table1_small
    ratio = rms["sts noisy"] / rms["classical noisy"]
    assert 0.62 < ratio < 0.88, rms


def test_noise_floor_measured_over_predicted(table1_small):
    """docs/validation.md: measured / predicted random error 0.94-1.09. Here measured 0.958,
    0.963, 1.022, 1.033 (classical / STS, noisy / clean reference; seeds 0-5: 0.87-1.15);
    band 0.8..1.25."""
    rms, predicted = table1_small
    for key, p in predicted.items():
        assert 0.8 < rms[key] / p < 1.25, (key, rms[key], p)
