"""One window of 2m+1 frames measured at many POIs from plain images: the entry point for a
pipeline of its own (:func:`solve_window`), over :class:`~torch_stsdic.core.solver.SubsetSolver`."""

from __future__ import annotations

from torch_stsdic.core.config import DICConfig
from torch_stsdic.core.shared_motion import known_window_motion
from torch_stsdic.core.solution import WindowSolution
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.core.validation import as_image, as_points, as_series, as_times, check_init
from torch_stsdic.kernels.native.rows import in_own_threads

__all__ = ["solve_window"]


# on the CPU the inputs' conversion runs in the scope too: outside it, torch's spinning OpenMP
# threads (torch imported first) under load made it cost ~0.09 s a call (issue 46)
@in_own_threads(0, "ref")
def solve_window(
    ref,
    frames,
    points,
    config: DICConfig | None = None,
    times=None,
    init=None,
    center: int | None = None,
    shared_motion=None,
    centres=None,
) -> WindowSolution:
    """Measure displacement and velocity at many POIs from one window of 2m+1 frames.

    Args:
        ref: reference image f, (H, W) tensor or array (grey; any real dtype).
        frames: the window's deformed frames g_t in time order, (2m+1, H, W); (H, W) is
            accepted when m = 0.
        points: (N, 2) POIs as (x, y) in px (x = column, y = row, 0-based).
        config: a :class:`DICConfig` (default DICConfig()).
        times: (2m+1,) frame times (default 0, 1, ..., 2m: frame units).
        init: optional initial guess per POI: (N, 2) (u, v), (N, 4) (u, v, ut, vt) or
            (N, P) full parameters; default: FFT cross-correlation within
            ``config.search_radius`` on every frame of the window, then a line fit in time.
        center: index of the frame the results refer to (default m, the window centre; a
            shifted window at the ends of a movie uses another index).
        shared_motion: the specimen's known displacement (u, v) px in every frame, (2m+1, 2)
            (the same at every POI: a rigid shake) or (N, 2m+1, 2); its jitter about a line in
            time is carried in every warp (:mod:`torch_stsdic.core.shared_motion`), so u, v stay
            the total displacement and ut, vt the smooth velocity. None: none.
        centres: (N, 2) px where each POI's subset is centred (default: the POI itself): an
            off-centre subset, e.g. kept inside the image where its point nears the border;
            the solution is carried to the POI by the subset's gradients (u += ux dx + uy dy),
            its predicted std with them.

    Returns:
        :class:`WindowSolution` on the input's device: u, v, ut, vt (N,), params (N, P),
        zncc (N,), status (N,), iterations (N,).
    """
    cfg = config if config is not None else DICConfig()
    if not isinstance(cfg, DICConfig):
        raise TypeError(f"config must be a DICConfig, got {type(cfg).__name__}")
    ref_t = as_image(ref, "ref", dtype=cfg.dtype)
    frames_t = as_series(frames, "frames", dtype=ref_t.dtype, device=ref_t.device,
                         like=ref_t, m=cfg.m)
    n_frames = frames_t.shape[0]
    if n_frames != cfg.n_frames:
        raise ValueError(
            f"frames: config.m = {cfg.m} needs 2m+1 = {cfg.n_frames} frames, got {n_frames}"
            + (" (m is larger than the frames given)" if n_frames < cfg.n_frames else "")
        )
    if min(ref_t.shape) < cfg.subset_size:
        raise ValueError(
            f"subset_size {cfg.subset_size} is larger than the image {tuple(ref_t.shape)}"
        )
    pts = as_points(points, "points", dtype=ref_t.dtype, device=ref_t.device)
    t = as_times(times, n_frames, dtype=ref_t.dtype, device=ref_t.device)
    c = cfg.m if center is None else int(center)
    if not 0 <= c < n_frames:
        raise ValueError(f"center must be in 0..{n_frames - 1}, got {center}")
    init_t = check_init(init, pts.shape[0], dtype=ref_t.dtype, device=ref_t.device)
    solver = SubsetSolver(cfg)
    ref_img = solver.prepare(ref_t)
    frames_img = solver.prepare(frames_t)
    motion = None
    if shared_motion is not None:
        motion = known_window_motion(shared_motion, (t - t[c]).expand(pts.shape[0], -1))
    centres_t = None  # one per point: SubsetSolver.solve checks that
    if centres is not None:
        centres_t = as_points(centres, "centres", dtype=ref_t.dtype, device=ref_t.device)
    return solver.solve(
        ref_img, frames_img, pts, t - t[c], init=init_t, ref_pixels=ref_t.unsqueeze(0),
        frame_pixels=frames_t, time=float(t[c]), motion=motion, centres=centres_t,
    )
