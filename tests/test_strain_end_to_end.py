"""Strain and strain rate end to end against known non-zero fields (issue 39): a uniaxial
stretch with lateral contraction and a pure shear, rendered exactly (torch_stsdic.synth),
measured through ``track`` and through ``stsdic synth`` + ``stsdic run``, compared with the
Green-Lagrange strains and rates of the exact motion. A swap of u and v, of x and y, a
wrong strain kind or a rate off by a time factor anywhere in the chain fails here (only zero
strain was checked end to end before).

Bands: measured RMS errors over 4 seeds (speckle and noise), each band about 2x the largest.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic.cli import main
from torch_stsdic.synth import HomogeneousStrain, make_speckle, render_series

SIZE = (81, 81)
CENTRE = (40.0, 40.0)
FIELDS = ("exx", "eyy", "exy")
MOTIONS = {
    "stretch": HomogeneousStrain(exx=0.01, eyy=-0.003, center=CENTRE, rate=1.0),
    "shear": HomogeneousStrain(exy=0.008, center=CENTRE, rate=1.0),
}


def green(ux, uy, vx, vy):
    return (ux + 0.5 * (ux**2 + vx**2), vy + 0.5 * (uy**2 + vy**2),
            0.5 * (uy + vx + ux * uy + vx * vy))


def exact(motion, t: float, h: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Green-Lagrange (exx, eyy, exy) of the motion at time t, and their time rates."""

    def at(tt):
        g = motion.gradient(torch.zeros(1), torch.zeros(1), torch.tensor([tt]))
        return np.array(green(*(float(a) for a in g)))

    return at(t), (at(t + h) - at(t - h)) / (2 * h)


def _errors(strain: dict, times, motion) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """RMS error of every field over points and frames, and its per-frame median."""
    rms, med = {}, {}
    truth = [exact(motion, float(t)) for t in times]
    for k, name in enumerate(FIELDS):
        for field, col in ((name, 0), (name + "_rate", 1)):
            want = np.array([tr[col][k] for tr in truth])[:, None]
            e = np.asarray(strain[field], dtype=np.float64) - want
            # rates: NaN where a window was cut to classical (points near the border at the
            # ends of the series: measured 8 % of the rows of the CLI run)
            assert np.isfinite(e).mean() > (0.95 if col == 0 else 0.85), field
            rms[field] = float(np.sqrt(np.nanmean(e**2)))
            med[field] = np.nanmedian(e, axis=1)
    return rms, med


@pytest.mark.parametrize("name", list(MOTIONS))
def test_track_strain_and_rate_of_a_known_field(name):
    """track (m = 1, noise 1 grey level, 64 points, 7 frames up to 6 % strain): RMS errors
    measured 2.0e-4..4.8e-4 (strains) and 2.3e-4..6.8e-4 (rates) over 4 seeds; band 1.4e-3
    RMS and 6e-4 for the per-frame median (Green vs small strain differ by 1.8e-3 at the
    last frame of the stretch)."""
    motion = MOTIONS[name]
    pat = make_speckle(SIZE, seed=4, margin=8.0)
    ref, frames = render_series(pat, SIZE, motion, torch.arange(1.0, 7.0), noise_sigma=1.0,
                                seed=50)
    res = sts.track(torch.cat([ref[None], frames]), config=sts.DICConfig(subset_size=15, m=1),
                    step=6, progress=False, strain_window=None)
    assert float(res.ok.float().mean()) > 0.95
    rms, med = _errors(res.strain(), res.times.numpy(), motion)
    for field, e in rms.items():
        assert e < 1.4e-3, (field, rms)
        assert np.abs(med[field]).max() < 6e-4, (field, med[field])


@pytest.fixture(scope="module")
def cli_stretch(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("cli_stretch")
    assert main(["synth", "--out", str(d), "--size", "81", "--frames", "6", "--motion",
                 "strain", "--exx", "0.01", "--eyy", "-0.003", "--exy", "0.004", "--noise",
                 "1", "--seed", "2", "--threads", "1"]) == 0  # fmt: skip
    out = d / "r.h5"
    assert main(["run", str(d / "movie.tif"), "--subset", "15", "--step", "6", "--m", "1",
                 "--search-radius", "4", "--out", str(out), "--threads", "1",
                 "--no-progress"]) == 0  # fmt: skip
    return d, out


def test_stsdic_run_strain_and_rate_of_a_known_field(cli_stretch):
    """stsdic synth --motion strain (8-bit, noise 1) then stsdic run (m = 1): the file's
    strains and rates against the exact motion. RMS errors measured 2.6e-4..8.1e-4 over 4
    seeds, per-frame medians 3.5e-4 at most; bands 1.5e-3 (RMS) and 7e-4 (median)."""
    d, out = cli_stretch
    meta = json.loads((d / "motion.json").read_text())
    p = meta["motion"]["params"]
    motion = HomogeneousStrain(exx=p["exx"], eyy=p["eyy"], exy=p["exy"],
                               center=tuple(p["center"]), rate=1.0, omega=p.get("omega", 0.0))
    with h5py.File(out, "r") as f:
        strain = {k: f[k][()] for k in f if k.startswith("e")}
        times = f["times"][()]
        assert json.loads(f.attrs["strain"]) == {"window": 5, "kind": "green"}
        # u and v of the file against the motion too: the strains are of these
        pts, u, v = f["points"][()], f["u"][()], f["v"][()]
    du, dv = motion.displacement(torch.from_numpy(pts[:, 0]), torch.from_numpy(pts[:, 1]),
                                 torch.from_numpy(times)[:, None])
    # measured 0.031..0.051 px at most over 4 seeds (8-bit images, up to 3.4 px of motion)
    assert np.nanmax(np.abs(u - du.numpy())) < 0.1 and np.nanmax(np.abs(v - dv.numpy())) < 0.1
    rms, med = _errors(strain, times, motion)
    for field, e in rms.items():
        assert e < 1.5e-3, (field, rms)
        assert np.abs(med[field]).max() < 7e-4, (field, med[field])
