"""The reference a movie is measured against, and its incremental update.

All results stay Lagrangian: displacements refer to the POIs in the *first* reference. After
an update the current reference is a later frame, the POIs sit at their displaced positions
in it, and ``acc`` holds the displacement (and gradients) accumulated to it; solutions against
it are turned into totals by composition (:func:`to_total`) and back (:func:`to_relative`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.gauss_newton import KeptToken
from torch_stsdic.core.interpolation import BSplineImage
from torch_stsdic.core.noise import estimate_noise_sigma
from torch_stsdic.core.pyramid import ImagePyramid, PyramidStack
from torch_stsdic.core.solver import SubsetSolver
from torch_stsdic.movie.frames import FrameCache

__all__ = ["Reference", "GRADIENTS", "compose_gradients", "to_relative", "to_total",
           "idw_fill", "maybe_update"]

GRADIENTS = ("ux", "uy", "vx", "vy")


@dataclass
class Reference:
    """Current reference: image, POI positions in it, and the displacement (total, to the
    first reference) of those positions (None before any update)."""

    frame: int  # series index, -1 for a mean/array reference
    raw: torch.Tensor | None  # (H, W), loaded lazily after a replayed update
    img: BSplineImage | None
    points: torch.Tensor  # (N, 2)
    acc: dict[str, torch.Tensor] | None = None  # u, v (+ ux, uy, vx, vy) (N,)
    pyramid: ImagePyramid | None = None  # its Gaussian pyramid, built on first use
    #: (N, 2, 4) where a window's velocity refers to at each POI (movie/velocity_point.py),
    #: worked out on first use
    velocity_maps: torch.Tensor | None = None
    #: their subset columns on the device (``velocity_point.map_offsets``), made with them
    map_offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    #: the token of a solver's reference cache holding the POIs' subsets (:meth:`kept_by`)
    kept: KeptToken | None = None

    def kept_by(self, solver: SubsetSolver, inside: bool = False) -> KeptToken | None:
        """``solver.keep_reference_subsets`` of the POIs (one host read), or, with no read,
        the token an earlier block got while the solver's cache still holds them: every
        block's solves then read the POIs' reference subsets with no host read
        (:meth:`~torch_stsdic.core.solver.SubsetSolver.keep_reference_subsets`).
        ``inside``: the POIs are whole pixels whose subsets lie inside the image (known to
        the caller: not read)."""
        cache = solver.reference_cache
        if cache is None or self.kept is None or self.kept != cache.token():
            self.kept = solver.keep_reference_subsets(self.img, self.points, inside=inside)
        return self.kept

    def ensure(self, cache: FrameCache) -> None:
        if self.raw is None:
            got = cache.frame(self.frame)
            self.raw, self.img, self.pyramid = got.raw, got.prep, got.pyramid()

    def pyramids(self) -> PyramidStack:
        """The reference's pyramid as a one-image stack (the coarse-to-fine search's)."""
        if self.pyramid is None:
            self.pyramid = ImagePyramid(self.raw)
        return PyramidStack([self.pyramid])


def noise_ratio(desc, raw: torch.Tensor, frames: torch.Tensor) -> float:
    """The reference's noise variance over one frame's (for the predicted uncertainty and the
    model check): 1 for a frame of the series, 1/K for the mean of K frames, and for an image
    given as an array the ratio of its Immerkaer noise estimate to the median of the
    frames' (a clean, e.g. synthetic, reference reads near 0; the median ignores the
    reference itself when it is also one of the frames), clamped to [0, 4].

    Args:
        desc: the plan's reference description (an int, "mean:0,1,2" or "array:...").
        raw: (H, W) the reference image; frames: (k, H, W) frames of the series.
    """
    if isinstance(desc, (int, np.integer)):
        return 1.0
    text = str(desc)
    if text.startswith("mean:"):
        return 1.0 / max(1, len(text[5:].split(",")))
    s_ref = estimate_noise_sigma(raw.detach().double().cpu())
    ests = [estimate_noise_sigma(f.detach().double().cpu()) for f in frames.reshape(
        -1, *frames.shape[-2:])]
    s_frame = float(np.median(ests))
    return float(min(4.0, (s_ref / max(s_frame, 1e-12)) ** 2))


def compose_gradients(g: dict[str, torch.Tensor], a: dict[str, torch.Tensor], inverse: bool):
    """Gradients: (I + G)(I + A) - I, or with ``inverse`` (I + G)(I + A)^-1 - I."""
    a11, a12, a21, a22 = 1.0 + a["ux"], a["uy"], a["vx"], 1.0 + a["vy"]
    if inverse:
        det = a11 * a22 - a12 * a21
        a11, a12, a21, a22 = a22 / det, -a12 / det, -a21 / det, a11 / det
    g11, g12, g21, g22 = 1.0 + g["ux"], g["uy"], g["vx"], 1.0 + g["vy"]
    return {
        "ux": g11 * a11 + g12 * a21 - 1.0, "uy": g11 * a12 + g12 * a22,
        "vx": g21 * a11 + g22 * a21, "vy": g21 * a12 + g22 * a22 - 1.0,
    }


def to_relative(total: dict[str, torch.Tensor], acc) -> dict[str, torch.Tensor]:
    """Parameters relative to the current reference from totals (to the first reference)."""
    if acc is None:
        return total
    rel = dict(total)
    rel["u"] = total["u"] - acc["u"]
    rel["v"] = total["v"] - acc["v"]
    if all(k in total for k in GRADIENTS):
        rel.update(compose_gradients(total, acc, inverse=True))
    return rel


def to_total(rel: dict[str, torch.Tensor], acc) -> dict[str, torch.Tensor]:
    """Totals (to the first reference) from parameters relative to the current reference."""
    if acc is None:
        return rel
    tot = dict(rel)
    tot["u"] = rel["u"] + acc["u"]
    tot["v"] = rel["v"] + acc["v"]
    if all(k in rel for k in GRADIENTS):
        tot.update(compose_gradients(rel, acc, inverse=False))
    return tot


def idw_fill(vals: dict[str, torch.Tensor], valid: torch.Tensor, pts: torch.Tensor, k: int = 4):
    """Fill invalid entries of every (N,) field by inverse-distance weighting of the k
    nearest valid points (distances in the first reference)."""
    bad = ~valid
    if not bool(bad.any()):
        return vals
    src = torch.nonzero(valid).flatten()
    kk = min(k, src.numel())
    d = torch.cdist(pts[bad], pts[src])
    dist, nn = torch.topk(d, kk, dim=1, largest=False)
    wgt = 1.0 / dist.clamp(min=1e-9)
    wgt = wgt / wgt.sum(1, keepdim=True)
    out = {}
    for name, v in vals.items():
        filled = v.clone()
        filled[bad] = (v[src][nn] * wgt).sum(1)
        out[name] = filled
    return out


def maybe_update(ref: Reference, stored: dict[str, np.ndarray], frame: int, thr: float,
                  pts0: torch.Tensor, names, cache: FrameCache, dtype, dev,
                  updates: list, row: int) -> Reference:
    """Incremental reference update after a block (decided from the stored rows only)."""
    ok = stored["status"][-1] <= USABLE
    z = stored["zncc"][-1][ok]
    if frame == ref.frame or z.size == 0 or not float(z.mean()) < thr:
        return ref
    acc_names = [nm for nm in ("u", "v", *GRADIENTS) if nm in names]
    acc = {nm: torch.from_numpy(stored[nm][-1].astype(np.float64)).to(device=dev, dtype=dtype)
           for nm in acc_names}
    valid = torch.from_numpy(ok).to(dev)
    for a in acc.values():
        valid &= torch.isfinite(a)
    if not bool(valid.any()):
        return ref
    acc = idw_fill(acc, valid, pts0)
    updates.append({"frame": int(frame), "row": int(row), "mean_zncc": float(z.mean()),
                    "interpolated_points": int((~valid).sum())})
    held = cache.entries.get(frame)
    return Reference(
        frame=int(frame), raw=None if held is None else held.raw,
        img=None if held is None else held.prep,
        points=pts0 + torch.stack([acc["u"], acc["v"]], 1), acc=acc,
        pyramid=None if held is None else held.pyramid(),
    )
