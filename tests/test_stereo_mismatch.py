"""A calibration that does not fit the images: when the epipolar cross-camera match finds
(almost) nothing, a search free of the epipolar constraint measures how far off the lines
the matches lie, and the error names that offset (torch_stsdic.stereo.matching)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from torch_stsdic import DICConfig
from torch_stsdic.stereo import track_stereo
from torch_stsdic.stereo.calibration import StereoCalibration
from torch_stsdic.stereo.matching import calibration_mismatch, epipolar_candidates
from torch_stsdic.stereo.render import make_rig, make_scene, render_stereo

SHAPE = (140, 180)


@pytest.fixture(scope="module")
def pair():
    """A static rendered stereo pair (2 frames), its true rig and a wrong one: the right
    camera turned 0.5 degree about its horizontal axis (its epipolar lines move ~20 px)."""
    rig = make_rig(SHAPE)
    scene = make_scene(rig, seed=3, max_time=2)
    left, right = render_stereo(scene, np.arange(2.0), noise_sigma=2.0, seed=4, quadrature=2,
                                cutoff=5)
    a = math.radians(0.5)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    wrong = StereoCalibration(rig.left, rig.right, rx @ rig.R, rig.T, source="wrong rig")
    return rig, wrong, scene, left, right


def _true_offsets(wrong, scene, pts):
    """The true right matches' distances (px) from the wrong rig's epipolar curves."""
    right = scene.truth(pts, [0.0])["right"][0]
    cand, valid = epipolar_candidates(wrong, pts, SHAPE, 0.0, 0.25)
    d = (cand - right[:, None, :]).norm(dim=-1).where(valid, torch.tensor(math.inf))
    return d.min(1).values


def test_the_wrong_calibration_is_named_with_its_offset(pair):
    rig, wrong, scene, left, right = pair
    cfg = DICConfig(subset_size=21, m=0)
    with pytest.raises(ValueError) as err:
        track_stereo(left, right, wrong, step=12, config=cfg)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("cross-camera match: the calibration does not fit these images: "
                          "matches lie ")
    got = re.search(r"median (\d+) px", msg)
    assert got, msg
    ys, xs = np.meshgrid(np.arange(20, 121, 12), np.arange(20, 161, 12), indexing="ij")
    pts = torch.tensor(np.stack([xs.ravel(), ys.ravel()], 1), dtype=torch.float64)
    truth = _true_offsets(wrong, scene, pts)
    truth = truth[torch.isfinite(truth)]
    assert 10 < float(truth.median()) < 40  # the wrong rig is far off indeed
    assert abs(int(got.group(1)) - float(truth.median())) <= 3


def test_the_right_calibration_is_not_blamed(pair):
    rig, _, _, left, right = pair
    ys, xs = np.meshgrid(np.arange(20, 121, 12), np.arange(20, 161, 12), indexing="ij")
    pts = torch.tensor(np.stack([xs.ravel(), ys.ravel()], 1), dtype=torch.float64)
    assert calibration_mismatch(rig, left[0], right[0], pts, 21) is None
    res = track_stereo(left, right, rig, step=12, config=DICConfig(subset_size=21, m=0))
    assert res.info["cross_ok"] > 0.5 * res.info["points"]
