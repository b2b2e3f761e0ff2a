"""The specimen found by default (analysis.specimen, movie.plan): points on background, holes
and featureless areas are left out of the default grid; an implausible shared-motion fit is
refused (movie.shared_pass.implausible)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torch_stsdic as sts
from torch_stsdic import synth
from torch_stsdic.analysis.specimen import on_specimen, speckle_mask
from torch_stsdic.cli import main
from torch_stsdic.movie.plan import plan_run
from torch_stsdic.movie.shared_pass import implausible

H, W = 120, 200


def _specimen_image(radius: float = 2.0, seed: int = 0) -> torch.Tensor:
    """A speckled band x in [50, 170) with a dark hole (radius 16 at (110, 60)), saturated
    background left of it and a dark one right of it."""
    img = synth.synthetic_movie((H, W), 1, radius=radius, seed=seed).ref.double()
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                          torch.arange(W, dtype=torch.float64), indexing="ij")
    img = torch.where(x < 50, torch.full_like(img, 255.0), img)
    img = torch.where(x >= 170, torch.full_like(img, 12.0), img)
    hole = (x - 110) ** 2 + (y - 60) ** 2 < 16 ** 2
    return torch.where(hole, 14.0 + torch.randn_like(img), img), x, y, hole


def test_speckle_mask_finds_the_band_and_not_the_hole():
    img, x, y, hole = _specimen_image()
    m = speckle_mask(img, fill=5)
    band = (x >= 56) & (x < 164) & ~((x - 110) ** 2 + (y - 60) ** 2 < 22 ** 2)
    assert float(m[band].double().mean()) > 0.98
    assert float(m[x < 44].double().mean()) < 0.02
    assert float(m[x >= 176].double().mean()) < 0.02
    assert float(m[(x - 110) ** 2 + (y - 60) ** 2 < 10 ** 2].double().mean()) < 0.02


def test_large_speckles_count_as_speckle():
    """Speckles of radius 5 px have flat insides: closed, the whole image is speckle."""
    img = synth.synthetic_movie((120, 120), 1, radius=5.0, seed=3).ref.double()
    keep, rep = on_specimen(sts.grid_points((120, 120), 10, None, None, 21), img, 21)
    assert bool(keep.all()) and rep.left_out == 0


def test_default_grid_leaves_the_background_out():
    img, *_ = _specimen_image()
    series = torch.stack([img, img, img])
    cfg = sts.DICConfig(m=0, subset_size=21)
    plan = plan_run(series, 0, None, None, None, None, 10, cfg)
    full = plan_run(series, 0, None, None, None, None, 10, cfg, find_specimen=False)
    pts = plan.points
    assert plan.options["specimen"]["left_out"] == full.points.shape[0] - pts.shape[0] > 0
    assert bool(((pts[:, 0] >= 50 + 10) & (pts[:, 0] < 170 - 10)).all())
    r = ((pts[:, 0] - 110) ** 2 + (pts[:, 1] - 60) ** 2).sqrt()
    assert float(r.min()) > 16 + 8  # no subset mostly in the hole
    given = plan_run(series, 0, None, full.points, None, None, 10, cfg)
    assert given.points.shape == full.points.shape  # given points are the user's choice


def test_cli_says_what_it_left_out(tmp_path, capsys):
    img, *_ = _specimen_image()
    stack = torch.stack([img, img]).clamp(0, 255).numpy().astype(np.uint8)
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", stack)
    rc = main(["run", str(tmp_path / "s.tif"), "--m", "0", "--out", str(tmp_path / "r.h5"),
               "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0 and "grid points left out" in out
    rc = main(["run", str(tmp_path / "s.tif"), "--m", "0", "--out", str(tmp_path / "k.h5"),
               "--no-progress", "--keep-background"])
    assert rc == 0 and "left out" not in capsys.readouterr().out
    a, b = sts.read_results(tmp_path / "r.h5"), sts.read_results(tmp_path / "k.h5")
    assert a.n_points < b.n_points


def test_implausible_fit_is_refused():
    rng = np.random.default_rng(0)
    disp = torch.from_numpy(rng.normal(0, 0.05, (3, 200, 2))) + torch.tensor([1.5, -0.5])
    valid = torch.ones(3, 200, dtype=torch.bool)
    assert implausible(disp, disp + 0.01, valid, [1, 2, 3]) is None
    dragged = disp.clone()
    dragged[1] += torch.tensor([-75.0, 0.0])  # a "shake" far from every point
    reason = implausible(disp, dragged, valid, [1, 2, 3])
    assert reason is not None and "frame 2" in reason and "100%" in reason
    # each frame judged over its own trusted points: a frame with fewer than 10 is not
    # judged, the first frame that fails is named
    dragged[2] += torch.tensor([0.0, 40.0])
    valid[1, 9:] = False
    reason = implausible(disp, dragged, valid, [1, 2, 3])
    assert reason is not None and "frame 3" in reason
    # frame 2 moved at 60 of its 200 points: plausible; with only 100 trusted, 60 of them
    dragged[1, 60:] = disp[1, 60:]
    valid[1] = True
    assert "frame 3" in implausible(disp, dragged, valid, [1, 2, 3])
    valid[1, 100:] = False
    assert "frame 2" in implausible(disp, dragged, valid, [1, 2, 3])


@pytest.mark.parametrize("frames", [None])
def test_run_with_defaults_on_a_specimen_converges(frames):
    """The band moved by a known translation: every kept point is trusted and right."""
    img, *_ = _specimen_image()
    mv = synth.synthetic_movie((H, W), 3, synth.Translation(ut=0.2, vt=-0.1), seed=0)
    # the same masking of the moving frames: background does not move
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                          torch.arange(W, dtype=torch.float64), indexing="ij")
    frames_ = [mv.ref.double()] + [f.double() for f in mv.frames]
    series = torch.stack([torch.where(x < 50, 255.0, torch.where(x >= 170, 12.0, f))
                          for f in frames_])
    res = sts.track(series, config=sts.DICConfig(m=0, subset_size=21), progress=False)
    assert res.info["specimen"]["left_out"] > 0
    ok = res.status[1:] <= 1
    assert float(ok.double().mean()) > 0.99
    t = res.times[1:].double().view(-1, 1)
    assert float((res.u[1:].double() - 0.2 * t)[ok].abs().max()) < 0.05


def test_square_morphology_as_row_and_column_equals_the_full_square():
    """speckle_mask closes and erodes with a square as a row then a column
    (specimen._square): the same mask as kornia's morphology with the whole square, at the
    image's borders too (geodesic: pixels outside the image ignored)."""
    import kornia

    from torch_stsdic.analysis.specimen import _square

    g = torch.Generator().manual_seed(3)
    mask = (torch.rand(1, 1, 61, 47, generator=g) > 0.7).float()
    for size in (3, 7, 11):
        full = torch.ones(size, size)
        for op in (kornia.morphology.dilation, kornia.morphology.erosion):
            assert torch.equal(_square(op, mask, size), op(mask, full)), (op.__name__, size)
        closed = _square(kornia.morphology.erosion,
                         _square(kornia.morphology.dilation, mask, size), size)
        assert torch.equal(closed, kornia.morphology.closing(mask, full))
        assert not torch.equal(closed, mask)  # the closing did something


def test_box_mean_by_an_integral_image_equals_kornias_box_blur():
    """The local means of the specimen test come from an integral image (O(1) a pixel at any
    size: the subset's 31^2 box over a megapixel in ms, not a tenth of a second): equal to
    kornia's box blur with reflected borders, over the whole image and at given pixels."""
    import kornia

    from torch_stsdic.analysis.specimen import _box, _box_at

    g = torch.Generator().manual_seed(1)
    img = torch.rand(61, 97, generator=g, dtype=torch.float64) * 255.0
    iy, ix = torch.tensor([0, 5, 30, 60, 60]), torch.tensor([0, 96, 48, 0, 96])
    for size in (3, 7, 31):
        want = kornia.filters.box_blur(img[None, None], (size, size),
                                       border_type="reflect")[0, 0]
        torch.testing.assert_close(_box(img, size), want, rtol=0, atol=1e-9)
        torch.testing.assert_close(_box_at(img, size, iy, ix), want[iy, ix], rtol=0,
                                   atol=1e-9)
