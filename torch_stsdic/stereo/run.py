"""Stereo STS-DIC of two image series: :func:`track_stereo`.

1. The left reference points (a grid, or given) are matched into the right reference
   (:func:`~torch_stsdic.stereo.matching.match_stereo`: epipolar search, subset solver).
2. The left series is tracked against the left reference and the right series against the
   right reference, both with :func:`torch_stsdic.track` and the same options (m, subset,
   reference, refinement ...); the right points are the matched ones, so the right track
   follows the left points through time.
3. Every frame's pixel pair is triangulated (distortion removed, least squares in the images):
   X, Y, Z and U, V, W mm in the left-camera frame; the STS velocities (ut, vt of both cameras)
   are carried through the same linearised triangulation to mm per time unit; the predicted
   pixel stds of both cameras give the predicted std of every 3D quantity.
"""

from __future__ import annotations

import os
import time as _time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.points import grid_points
from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.status import Status
from torch_stsdic.io import load_series
from torch_stsdic.movie.series import track

from .calibration import StereoCalibration, load_calibration
from .matching import calibration_mismatch, match_stereo
from .result import StereoFile, StereoResult, best_fit_plane
from .triangulation import propagate_cov, propagate_std, triangulate

__all__ = ["track_stereo", "write_stereo", "work_files"]

DTYPE = torch.float64


def work_files(work: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The two cameras' result files of a stereo run whose work stem is ``work``
    (``3d.h5`` -> ``3d.left.h5``, ``3d.right.h5``)."""
    p = Path(work)
    stem = p.with_suffix("") if p.suffix == ".h5" else p
    return stem.with_name(stem.name + ".left.h5"), stem.with_name(stem.name + ".right.h5")


def _reference_image(series, reference, which: str) -> torch.Tensor:
    if isinstance(reference, (tuple, list)) and len(reference) == 2 and not isinstance(
            reference[0], (int, np.integer)):
        img = reference[0 if which == "left" else 1]
        return torch.as_tensor(np.asarray(img, dtype=np.float64))
    if isinstance(reference, (int, np.integer)):
        return series.get(int(reference), dtype=DTYPE)
    return series.mean_of(reference, dtype=DTYPE)


def track_stereo(left: Any, right: Any, calibration: StereoCalibration | str, *,
                 points: Any = None, roi=None, mask=None, step: int = 10,
                 config: DICConfig | None = None, reference: Any = 0, frames: Any = None,
                 times: Any = None, device: str | torch.device = "cpu", progress: bool = False,
                 cross_shape: str = "affine", depth_range=None,
                 max_reprojection: float = 1.0, work: str | os.PathLike[str] | None = None,
                 resume: bool = False, **track_kwargs: Any) -> StereoResult:
    """Stereo STS-DIC: 3D shape, displacement and velocity of points over a stereo movie.

    Args:
        left, right: the two series, anything :func:`torch_stsdic.load_series` accepts
            ((T, H, W) arrays or tensors, TIFF stacks, lists of files, globs), frame k of one
            taken at the same time as frame k of the other.
        calibration: a :class:`StereoCalibration` or a calibration file
            (:func:`~torch_stsdic.stereo.calibration.load_calibration`).
        points: (N, 2) left reference points px; default a grid of spacing ``step`` inside
            ``roi`` (x0, y0, x1, y1) and ``mask``.
        config: :class:`torch_stsdic.DICConfig` of both tracks (m, subset size, ...).
        reference: frame index or frame spec ("0:5": the mean of frames 0-4) of both series,
            or a pair of (H, W) images (left, right).
        frames, times, device, progress: as for :func:`torch_stsdic.track`.
        cross_shape: subset warp of the cross-camera match, "affine" or "quadratic".
        depth_range: (min, max) depth mm of the epipolar search (default: any).
        max_reprojection: px; rows whose reprojection error exceeds it are INCONSISTENT.
        work: the stem of the two cameras' result files, written as the tracks go
            (``<work>.left.h5``, ``<work>.right.h5``: 2-D result files; a killed run keeps
            every finished frame of them). None: in memory only.
        resume: continue the tracks in the ``work`` files (frames finished there are kept,
            as ``stsdic run --resume`` keeps them); else they are replaced.
        **track_kwargs: passed to both :func:`torch_stsdic.track` calls
            (``refine_reference``, ``shared_motion``, ``checks`` ...).

    Returns:
        :class:`~torch_stsdic.stereo.result.StereoResult` (tensors on the CPU, float64).

    Raises:
        ValueError (one line) for a calibration that does not fit the images, series of
        different lengths, and the input errors of :func:`torch_stsdic.track`.
    """
    run = _stereo_tracks(left, right, calibration, points=points, roi=roi, mask=mask,
                         step=step, config=config, reference=reference, frames=frames,
                         times=times, device=device, progress=progress,
                         cross_shape=cross_shape, depth_range=depth_range, work=work,
                         resume=resume, **track_kwargs)
    res = _result(run, run["lres"], run["rres"], max_reprojection)
    res.info["total_s"] = _time.perf_counter() - run["t_start"]
    res.strain = res.surface_strain()
    return res


#: (frame, point) entries of the 3-D stage a file-writing stereo run takes at a time
#: (:func:`write_stereo`: triangulation, covariances, surface strain, ~1 kB an entry)
STEREO_ROWS = 1 << 15


def write_stereo(path: str | os.PathLike[str], left: Any, right: Any,
                 calibration: StereoCalibration | str, *, coordinates: str = "camera",
                 overwrite: bool = False, max_reprojection: float = 1.0,
                 **kwargs: Any) -> dict[str, Any]:
    """:func:`track_stereo` into the stereo result file ``path``, its 3-D stage a few
    frames at a time (:data:`STEREO_ROWS` entries: the two cameras' tracks read from their
    ``work`` files by rows), so that a long movie's run never holds its (F, N) fields whole:
    the file :meth:`StereoResult.to_hdf5` writes of :func:`track_stereo`'s result (with
    ``coordinates`` "plane": of its :meth:`~StereoResult.in_plane_frame`, the plane fitted
    to the points usable in any frame, found by a first pass over the frames).

    Returns:
        the run's ``info`` and ``usable``: the share of usable (frame, point) results.
    """
    if coordinates not in ("camera", "plane"):
        raise ValueError(f"coordinates: 'camera' or 'plane', got {coordinates!r}")
    run = _stereo_tracks(left, right, calibration, **kwargs)
    lres, rres = run["lres"], run["rres"]
    frames = lres.frames.cpu()
    n_f, n = int(frames.numel()), int(run["pts"].shape[0])
    step = max(1, STEREO_ROWS // max(n, 1))
    chunks = [frames[i:i + step].tolist() for i in range(0, n_f, step)] or [[]]

    def part(ks: list[int]) -> StereoResult:
        return _result(run, lres.select(ks), rres.select(ks), max_reprojection)

    plane = None
    if coordinates == "plane":  # the plane of the points usable in any frame
        usable = torch.zeros(n, dtype=torch.bool)
        for ks in chunks:
            usable |= part(ks).ok.any(0)
        x0 = part(chunks[0][:1]).X0.double()
        ok0 = torch.isfinite(x0).all(1) & usable
        if int(ok0.sum()) < 3:
            raise ValueError(f"best-fit plane: {int(ok0.sum())} usable reference points, 3 "
                             "or more needed")
        plane = best_fit_plane(x0, ok0)
    out = None
    ok = 0
    tmp = Path(str(path) + ".partial")  # renamed when complete: no half-written result
    try:
        for i, ks in enumerate(chunks):
            res = part(ks)
            if plane is not None:
                res = res.in_plane_frame(plane)
            res.strain = res.surface_strain()
            info = res.info
            if out is None:
                if not overwrite and Path(path).exists():
                    raise ValueError(f"{path} exists (overwrite=True replaces it)")
                out = StereoFile(tmp, res, frames=frames, times=lres.times.cpu(),
                                 overwrite=True)
            out.write_rows(res, i * step)
            ok += int(res.ok.sum())
    except BaseException:
        if out is not None:
            out.close()
        tmp.unlink(missing_ok=True)
        raise
    info["total_s"] = _time.perf_counter() - run["t_start"]
    out.close(info)
    os.replace(tmp, path)
    return {**info, "usable": ok / max(n_f * n, 1), "frames": n_f}


def _stereo_tracks(left: Any, right: Any, calibration: StereoCalibration | str, *,
                   points: Any = None, roi=None, mask=None, step: int = 10,
                   config: DICConfig | None = None, reference: Any = 0, frames: Any = None,
                   times: Any = None, device: str | torch.device = "cpu",
                   progress: bool = False, cross_shape: str = "affine", depth_range=None,
                   work: str | os.PathLike[str] | None = None, resume: bool = False,
                   **track_kwargs: Any) -> dict[str, Any]:
    """Steps 1 and 2 of :func:`track_stereo` (module docstring): the cross-camera match and
    the two cameras' tracks, with what the 3-D stage needs (``rig``, ``pts``, ``cross``,
    ``okc``, ``lres``, ``rres``, ``cfg``, ``info``, ``t_start``)."""
    t_start = _time.perf_counter()
    rig = calibration if isinstance(calibration, StereoCalibration) else \
        load_calibration(calibration)
    cfg = config if config is not None else DICConfig()
    ls = load_series(left, timestamps=times)
    rs = load_series(right, timestamps=times)
    rig.check_images(ls.shape, rs.shape)
    if len(ls) != len(rs):
        raise ValueError(f"left and right series differ in length: {len(ls)} and {len(rs)} "
                         "frames")
    for k in ("out", "resume", "overwrite", "roi", "mask", "step", "points"):
        if k in track_kwargs:
            raise ValueError(f"track_stereo: {k} is not passed to the 2-D tracks")
    if points is None:
        pts = grid_points(ls.shape, step, roi, mask, cfg.subset_size).to(DTYPE)
    else:
        pts = torch.as_tensor(np.asarray(points, dtype=np.float64))
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
            raise ValueError(f"points: expected (N, 2), got {tuple(pts.shape)}")
    n = pts.shape[0]
    lref = _reference_image(ls, reference, "left")
    rref = _reference_image(rs, reference, "right")
    t0 = _time.perf_counter()
    cross = match_stereo(rig, lref, rref, pts, cfg, shape=cross_shape, depth_range=depth_range)
    t_cross = _time.perf_counter() - t0
    okc = cross.status <= int(Status.MAX_ITER)
    if float(okc.double().mean()) < 0.5:  # most points unmatched: does the calibration fit?
        mismatch = calibration_mismatch(rig, lref, rref, pts, cfg.subset_size)
        if mismatch is not None:
            raise ValueError(f"cross-camera match: {mismatch}")
    if not bool(okc.any()):
        raise ValueError("cross-camera match: no point of the left reference was found in the "
                         "right reference (check the calibration and the image order)")
    ref_l = lref if isinstance(reference, (tuple, list)) and len(reference) == 2 and not \
        isinstance(reference[0], (int, np.integer)) else reference
    ref_r = rref if ref_l is lref else reference
    common = dict(frames=frames, config=cfg, device=device, times=times, progress=progress,
                  **track_kwargs)
    t0 = _time.perf_counter()
    files = work_files(work) if work is not None else (None, None)

    def camera(series, ref, p, f: Path | None):  # the track of one camera, into its file
        return track(series, reference=ref, points=p, out=f,
                     resume=bool(resume and f is not None and f.exists()),
                     overwrite=f is not None and not resume, **common)

    lres = camera(ls, ref_l, pts, files[0])
    rres = camera(rs, ref_r, cross.right[okc], files[1])
    t_track = _time.perf_counter() - t0
    info = {"cross_s": t_cross, "track_s": t_track, "m": cfg.m,
            "subset_size": cfg.subset_size, "cross_ok": int(okc.sum()), "points": n,
            "cross_repaired": int(cross.repaired.sum())}
    return {"rig": rig, "pts": pts, "cross": cross, "okc": okc, "lres": lres, "rres": rres,
            "cfg": cfg, "info": info, "t_start": t_start}


def _result(run: dict[str, Any], lres, rres, max_reprojection: float) -> StereoResult:
    """The stereo result of the rows of the left and right tracks ``lres``, ``rres`` (the
    run's, or some of their frames: every quantity of a frame is the frame's own)."""
    rig, pts, cross, okc, cfg = (run[k] for k in ("rig", "pts", "cross", "okc", "cfg"))
    d = _three_d(rig, pts, cross, okc, lres, rres, cfg, max_reprojection)
    X, U, vel, std, X0, x0_std = d["X"], d["U"], d["vel"], d["std"], d["X0"], d["x0_std"]
    tri, tri0, right0, status = d["tri"], d["tri0"], d["right0"], d["status"]
    info = {**run["info"],
            "reference_reprojection_px": float(tri0.reprojection_error[okc].median()),
            "max_reprojection": max_reprojection}
    return StereoResult(
        points=pts, right_points=right0, frames=lres.frames.cpu(), times=lres.times.cpu(),
        X=X[..., 0], Y=X[..., 1], Z=X[..., 2], U=U[..., 0], V=U[..., 1], W=U[..., 2],
        Ut=vel[..., 0], Vt=vel[..., 1], Wt=vel[..., 2], X0=X0, X0_std=x0_std, std=std,
        reprojection_error=tri.reprojection_error, status=status, left=lres, right=rres,
        cross=cross, calibration=rig.summary(), info=info, U_cov=d["U_cov"])


def _three_d(rig: StereoCalibration, pts: torch.Tensor, cross, okc: torch.Tensor, lres, rres,
             cfg: DICConfig, max_reprojection: float) -> dict[str, Any]:
    """The left and right tracks triangulated: X, U, velocity (F, N, 3), their predicted std,
    the reference shape and its std, and each row's status (cross match, then the left and
    right tracks, then the geometry: reprojection error, points behind a camera)."""
    n = pts.shape[0]
    F = lres.frames.numel()

    def full(a):  # right (F, n_ok) -> (F, N), NaN where not matched
        out = torch.full((F, n), float("nan"), dtype=DTYPE)
        out[:, okc] = a.to(DTYPE).cpu()
        return out

    def col(res, name):
        return res.field(name).to(DTYPE).cpu()

    uL, vL = col(lres, "u"), col(lres, "v")
    uR, vR = full(rres.u), full(rres.v)
    pl = pts[None] + torch.stack([uL, vL], -1)
    right0 = cross.right.to(DTYPE)
    pr = right0[None] + torch.stack([uR, vR], -1)
    tri = triangulate(rig, pl, pr)
    tri0 = triangulate(rig, pts, right0)
    X, X0 = tri.X, tri0.X
    U = X - X0[None]
    s_l = [lres.std.get(k) for k in ("u", "v")]
    s_r = [rres.std.get(k) for k in ("u", "v")]
    std: dict[str, torch.Tensor] = {}
    u_cov = None
    if all(s is not None for s in s_l + s_r):
        std4 = torch.stack([s_l[0].to(DTYPE).cpu(), s_l[1].to(DTYPE).cpu(), full(s_r[0]),
                            full(s_r[1])], -1)
        u_cov = propagate_cov(tri.sensitivity, std4)
        sd = torch.diagonal(u_cov, dim1=-2, dim2=-1).sqrt()
        for i, k in enumerate("XYZ"):
            std[k] = sd[..., i]
        for i, k in enumerate("UVW"):
            std[k] = sd[..., i]  # the reference's triangulation error is common: cancels
    vel = torch.full_like(X, float("nan"))
    if cfg.m > 0:
        rate = torch.stack([col(lres, "ut"), col(lres, "vt"), full(rres.ut), full(rres.vt)], -1)
        vel = (tri.sensitivity @ rate[..., None])[..., 0]
        st_l = [lres.std.get(k) for k in ("ut", "vt")]
        st_r = [rres.std.get(k) for k in ("ut", "vt")]
        if all(s is not None for s in st_l + st_r):
            s4 = torch.stack([st_l[0].to(DTYPE).cpu(), st_l[1].to(DTYPE).cpu(), full(st_r[0]),
                              full(st_r[1])], -1)
            sv = propagate_std(tri.sensitivity, s4)
            for i, k in enumerate(("Ut", "Vt", "Wt")):
                std[k] = sv[..., i]
    x0_std = propagate_std(tri0.sensitivity, torch.cat(
        [torch.zeros_like(cross.std), cross.std], -1))
    # status: the cross match, then the left and right tracks, then the geometry
    st_l = lres.status.cpu().to(torch.int16)
    st_r = torch.full((F, n), int(Status.NOT_COMPUTED), dtype=torch.int16)
    st_r[:, okc] = rres.status.cpu().to(torch.int16)
    st_c = cross.status.cpu().to(torch.int16)[None].expand(F, n)
    bad = int(Status.MAX_ITER)
    status = torch.where(st_c > bad, st_c, torch.where(st_l > bad, st_l, torch.where(
        st_r > bad, st_r, torch.maximum(st_l, st_r))))
    geo_bad = ~(tri.reprojection_error <= max_reprojection) | ~tri.in_front
    status = torch.where((status <= bad) & geo_bad, torch.full_like(status,
                         int(Status.INCONSISTENT)), status).to(torch.int8)
    nan = status > bad
    for a in (X, U, vel):
        a[nan] = float("nan")
    for k in std:
        std[k][nan] = float("nan")
    if u_cov is not None:
        u_cov[nan] = float("nan")
    return {"X": X, "U": U, "vel": vel, "std": std, "X0": X0, "x0_std": x0_std, "tri": tri,
            "tri0": tri0, "right0": right0, "status": status, "U_cov": u_cov}
