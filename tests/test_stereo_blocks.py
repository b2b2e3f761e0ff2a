"""A stereo run written to its file a few frames at a time (issue 50: ``stsdic stereo``'s 3-D
stage in bounded chunks): the file is the one ``to_hdf5`` writes of the whole result, in the
camera's frame and in the plane's; the cameras' tracks are read by rows, not whole."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from test_stereo_export import write_stereo_movies  # tests/ on the path

from torch_stsdic import DICConfig
from torch_stsdic.stereo import run as stereo_run
from torch_stsdic.stereo.render import SurfaceMotion

MOTION = SurfaceMotion(translation=(0.004, -0.003, 0.01), exx=2e-4, eyy=-1e-4, bulge=0.004,
                       bulge_radius=25.0)

KW = dict(roi=(20, 20, 160, 120), step=20, config=DICConfig(subset_size=21, m=1))


@pytest.fixture(scope="module")
def movies(tmp_path_factory):
    d = tmp_path_factory.mktemp("stereo_blocks")
    write_stereo_movies(d, MOTION)  # test_stereo_export's render, a wider bulge
    return d


def _datasets(path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f}


@pytest.mark.parametrize("coordinates", ["camera", "plane"])
def test_file_written_in_chunks_is_the_whole_results(movies, tmp_path, monkeypatch,
                                                     coordinates):
    d = movies
    args = (d / "left.tif", d / "right.tif", d / "cal.yml")
    whole = stereo_run.track_stereo(*args, work=tmp_path / "w.h5", **KW)
    if coordinates == "plane":
        whole = whole.in_plane_frame()
    whole.to_hdf5(tmp_path / "whole.h5")
    # chunks of 2 frames (the 6 frames in 3 parts); the cameras' files read by rows only
    monkeypatch.setattr(stereo_run, "STEREO_ROWS", 2 * len(whole.points))
    from torch_stsdic.analysis import stored_result

    monkeypatch.setattr(stored_result.StoredTrackResult, "u", property(
        lambda self: pytest.fail("the 3-D stage read a whole field")), raising=True)
    info = stereo_run.write_stereo(tmp_path / "parts.h5", *args, coordinates=coordinates,
                                   work=tmp_path / "w.h5", resume=True, **KW)
    monkeypatch.undo()
    a, b = _datasets(tmp_path / "whole.h5"), _datasets(tmp_path / "parts.h5")
    assert sorted(a) == sorted(b) and {"exx", "U_cov", "W_std", "status"} <= set(a)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        np.testing.assert_array_equal(b[k], a[k], err_msg=k)
    assert info["frames"] == 6 and info["usable"] == pytest.approx(float(whole.ok.double().mean()))
    assert not (tmp_path / "parts.h5.partial").exists()
    with h5py.File(tmp_path / "parts.h5", "r") as f:
        assert f.attrs["frame"] == whole.frame
