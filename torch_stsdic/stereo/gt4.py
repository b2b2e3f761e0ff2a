"""Compare stereo STS-DIC with DICe's results on the Stereo-DIC Challenge GT4 pairs.

``python -m torch_stsdic.stereo.gt4 [DATA_DIR]`` (default ``../shared/data/stereo-gt4-dspecimen``
next to the repository) prints the point-by-point comparison that ``docs/stereo.md`` reports:

* the cross-camera match (right - left px) against DICe's ``CROSS_CORR_Q, R``;
* the left 2-D displacements against DICe's ``DISPLACEMENT_X, Y``;
* the reference shape against DICe's ``MODEL_COORDINATES`` (its best-fit-plane frame), after
  the rigid transform that best aligns the two point sets, and the same for DICe's own pixel
  pairs triangulated here (so matching and triangulation differences are told apart);
* the 3D displacements against DICe's ``MODEL_DISPLACEMENT`` rotated into the same frame.

Everything is at DICe's 123 points (subset 25, frames 0-5), with classical DIC (m = 0, as
DICe) and STS (m = 2).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torch_stsdic.core.config import DICConfig

from .calibration import load_calibration
from .run import track_stereo
from .triangulation import triangulate

__all__ = ["read_dice_text", "read_dice_exodus", "rigid_align", "compare_with_dice",
           "default_data_dir"]


def default_data_dir() -> Path:
    return Path(__file__).resolve().parents[3] / "shared" / "data" / "stereo-gt4-dspecimen"


def read_dice_text(data: Path, frames=range(6)) -> dict[str, np.ndarray]:
    """DICe's ``gold/DICe_solution_k.txt``: "x", "y" (N,), "q", "r" (N,), "u", "v" (F, N),
    "match" (F, N)."""
    rows = []
    for k in frames:
        a = np.genfromtxt(data / "gold" / f"DICe_solution_{k}.txt", delimiter=",",
                          names=True)
        rows.append(a)
    first = rows[0]
    return {"x": first["COORDINATE_X"], "y": first["COORDINATE_Y"],
            "q": first["CROSS_CORR_Q"], "r": first["CROSS_CORR_R"],
            "u": np.stack([a["DISPLACEMENT_X"] for a in rows]),
            "v": np.stack([a["DISPLACEMENT_Y"] for a in rows]),
            "match": np.stack([a["MATCH"] for a in rows])}


def read_dice_exodus(path: Path) -> dict[str, np.ndarray]:
    """Nodal variables (T, N) of DICe's Exodus II file by name (needs scipy)."""
    from scipy.io import netcdf_file
    with netcdf_file(str(path), "r", mmap=False) as f:
        raw = f.variables["name_nod_var"][:]
        names = [bytes(r).decode("latin-1").strip("\x00 ").strip() for r in raw]
        return {n: np.array(f.variables[f"vals_nod_var{i + 1}"][:], dtype=np.float64)
                for i, n in enumerate(names)}


def rigid_align(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation Q and translation t minimising |a Q^T + t - b| (Kabsch); returns (Q, t,
    residual vectors (N, 3))."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    Q = vt.T @ np.diag([1, 1, d]) @ u.T
    t = cb - ca @ Q.T
    return Q, t, a @ Q.T + t - b


def _rms(x) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def compare_with_dice(data: Path | None = None, m_values=(0, 2), vic_kappa: str = "opencv",
                      progress: bool = False) -> dict[str, Any]:
    """Run stereo DIC at DICe's points and compare (see the module docstring)."""
    data = Path(data) if data is not None else default_data_dir()
    rig = load_calibration(data / "cal.xml", vic_kappa=vic_kappa)
    dice = read_dice_text(data)
    exo = read_dice_exodus(data / "gold" / "DICe_solution.e")
    pts = np.stack([dice["x"], dice["y"]], 1)
    # Exodus nodes in the text files' order (by their left coordinates)
    ex_xy = np.stack([exo["COORDINATE_X"][0], exo["COORDINATE_Y"][0]], 1)
    order = np.array([int(np.argmin(np.abs(ex_xy - p).sum(1))) for p in pts])
    model = np.stack([exo[f"MODEL_COORDINATES_{c}"][0][order] for c in "XYZ"], 1)
    model_disp = np.stack([exo[f"MODEL_DISPLACEMENT_{c}"][:, order] for c in "XYZ"], -1)
    left = [str(data / "images" / f"GT4-{k:04d}_0.tif") for k in range(6)]
    right = [str(data / "images" / f"GT4-{k:04d}_1.tif") for k in range(6)]
    out: dict[str, Any] = {"calibration": rig.describe(), "points": len(pts)}
    # DICe's own pixel pairs, triangulated here: the triangulation/calibration difference
    dice_right = pts + np.stack([dice["q"], dice["r"]], 1)
    tri_d = triangulate(rig, torch.as_tensor(pts), torch.as_tensor(dice_right))
    Xd = tri_d.X.numpy()
    _, _, res_d = rigid_align(Xd, model)
    out["dice_pairs_triangulated_here_vs_dice_shape_rms_mm"] = _rms(np.linalg.norm(res_d, axis=1))
    out["dice_pairs_reprojection_px_median"] = float(tri_d.reprojection_error.median())
    for m in m_values:
        # like for like: DICe measures every frame against the reference image
        res = track_stereo(left, right, rig, points=pts, config=DICConfig(subset_size=25, m=m),
                           progress=progress, max_reprojection=2.0, series_reference=False)
        ok = res.ok.numpy()
        okc = (res.cross.status <= 1).numpy() & (dice["match"][0] == 0)
        key = f"m{m}"
        r: dict[str, Any] = {"usable": float(ok.mean()), "cross_matched": int(okc.sum()),
                             "time_s": res.info["total_s"]}
        dq = (res.right_points.numpy() - pts) - np.stack([dice["q"], dice["r"]], 1)
        r["cross_diff_rms_px"] = [_rms(dq[okc, 0]), _rms(dq[okc, 1])]
        r["cross_diff_median_px"] = [float(np.median(dq[okc, 0])), float(np.median(dq[okc, 1]))]
        r["cross_pred_std_px"] = [_rms(res.cross.std.numpy()[okc, 0]),
                                  _rms(res.cross.std.numpy()[okc, 1])]
        du = res.left.u.numpy() - dice["u"]
        dv = res.left.v.numpy() - dice["v"]
        both = ok & (dice["match"] == 0)
        both[0] = False
        r["left_disp_diff_rms_px"] = [_rms(du[both]), _rms(dv[both])]
        r["left_disp_pred_std_px"] = [_rms(res.left.std["u"].numpy()[both]),
                                      _rms(res.left.std["v"].numpy()[both])]
        r["dice_left_disp_rms_px"] = [_rms(dice["u"][both]), _rms(dice["v"][both])]
        # shape: rigid alignment of our reference points onto DICe's model coordinates
        X0 = res.X0.numpy()
        Q, t, resid = rigid_align(X0[okc], model[okc])
        r["shape_diff_rms_mm"] = _rms(np.linalg.norm(resid, axis=1))
        r["shape_diff_rms_xyz_mm"] = [_rms(resid[:, i]) for i in range(3)]
        r["shape_pred_std_xyz_mm"] = [_rms((res.X0_std.numpy()[okc] @ np.abs(Q.T))[:, i])
                                      for i in range(3)]
        # against DICe's pairs triangulated here: matching difference only
        _, _, rm = rigid_align(X0[okc], Xd[okc])
        r["shape_vs_dice_pairs_here_rms_mm"] = _rms(np.linalg.norm(rm, axis=1))
        # 3D displacement in DICe's frame
        U = res.displacement.numpy() @ Q.T
        dU = U - model_disp
        r["disp3d_diff_rms_xyz_mm"] = [_rms(dU[..., i][both]) for i in range(3)]
        sd = np.stack([res.std[k].numpy() for k in "UVW"], -1) @ np.abs(Q.T)
        r["disp3d_pred_std_xyz_mm"] = [_rms(sd[..., i][both]) for i in range(3)]
        r["dice_disp3d_rms_xyz_mm"] = [_rms(model_disp[..., i][both]) for i in range(3)]
        r["disp3d_diff_rms_per_frame_mm"] = [
            [_rms(dU[f, both[f], i]) for i in range(3)] for f in range(1, dU.shape[0])]
        out[key] = r
    return out


def main(argv=None) -> int:  # pragma: no cover - a report, exercised by the slow test
    argv = sys.argv[1:] if argv is None else argv
    data = Path(argv[0]) if argv else default_data_dir()
    rep = compare_with_dice(data, progress=True)
    for k, v in rep.items():
        if isinstance(v, dict):
            print(k)
            for kk, vv in v.items():
                print(f"  {kk}: {vv}")
        else:
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
