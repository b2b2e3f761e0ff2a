"""Per-point result status codes shared by the solver, the series tracker and the result files."""

from __future__ import annotations

from enum import IntEnum
from typing import Any

__all__ = ["Status", "usable"]


class Status(IntEnum):
    """Outcome of one point of interest (POI) in one window.

    Stored as ``int8`` in result tensors and files. Only ``CONVERGED`` and ``MAX_ITER`` are
    *usable* (``status <= MAX_ITER``; :func:`usable`): plots, means and strains use only
    those. ``DIVERGED``, ``OUTSIDE``, ``LOW_TEXTURE`` and ``NOT_COMPUTED`` come with NaN
    parameters, so a NaN is never silent: its reason is in the status array.
    ``POOR_FIT`` and ``INCONSISTENT`` mark points that were solved but whose answer the
    checks do not trust; their values are kept for inspection, never used.
    """

    CONVERGED = 0  #: the Gauss-Newton increment fell below ``tol`` and the checks passed
    MAX_ITER = 1  #: ``max_iter`` reached; parameters are the last iterate (use with care)
    DIVERGED = 2  #: the iteration blew up (non-finite or huge step, singular Hessian)
    OUTSIDE = 3  #: the subset (reference or warped) leaves the image
    LOW_TEXTURE = 4  #: subset intensity gradient too weak (flat or saturated texture)
    NOT_COMPUTED = 5  #: not solved (masked out, or not yet processed in a file being written)
    POOR_FIT = 6  #: solved, but the subset does not match: residual far above the image noise
    INCONSISTENT = 7  #: solved, but an outlier against its neighbours

    @classmethod
    def describe(cls) -> str:
        return ", ".join(f"{s.value}={s.name.lower()}" for s in cls)


def usable(status: Any) -> Any:
    """Boolean mask (numpy array or tensor, like ``status``) of usable results: CONVERGED or
    MAX_ITER."""
    return status <= int(Status.MAX_ITER)
