"""GT4 (Stereo-DIC Challenge sample 3, VIC-3D calibration): point-by-point comparison with
DICe's results in gold/ (a peer's result, not truth)."""

import pytest

from torch_stsdic.stereo.gt4 import compare_with_dice, default_data_dir

DATA = default_data_dir()
pytestmark = pytest.mark.skipif(
    not (DATA / "cal.xml").is_file() or not (DATA / "gold" / "DICe_solution.e").is_file(),
    reason="GT4 stereo data (../shared/data/stereo-gt4-dspecimen) not present")


pytest.importorskip("scipy", reason="reading DICe's Exodus file needs scipy")


def _check(r):
    assert r["cross_matched"] >= 115 and r["usable"] > 0.9
    # the left -> right match: within ~2x the predicted std of DICe's, no bias
    assert max(r["cross_diff_rms_px"]) < 0.06
    assert max(abs(v) for v in r["cross_diff_median_px"]) < 0.01
    # the reference shape (rigidly aligned): within 1.5x the predicted std per axis
    for d, p in zip(r["shape_diff_rms_xyz_mm"], r["shape_pred_std_xyz_mm"]):
        assert d < 1.5 * p + 5e-4, (d, p)
    # 3D displacements: differences below the predicted std of one method's noise
    for d, p in zip(r["disp3d_diff_rms_xyz_mm"], r["disp3d_pred_std_xyz_mm"]):
        assert d < 1.5 * p, (d, p)


def test_gt4_classical_against_dice():
    rep = compare_with_dice(DATA, m_values=(0,))
    assert rep["dice_pairs_triangulated_here_vs_dice_shape_rms_mm"] < 0.01
    _check(rep["m0"])
    assert max(rep["m0"]["left_disp_diff_rms_px"]) < 0.01


@pytest.mark.slow
def test_gt4_sts_against_dice():
    _check(compare_with_dice(DATA, m_values=(2,))["m2"])
