"""Per-point result status codes shared by the solver, the series tracker and the result files."""

from __future__ import annotations

from enum import IntEnum


class Status(IntEnum):
    """Outcome of one point of interest (POI) in one window.

    Stored as ``int8`` in result tensors and files. Only ``CONVERGED`` and ``MAX_ITER``
    carry usable parameters; the other codes come with NaN parameters so that a NaN
    is never silent: its reason is always in the status array.
    """

    CONVERGED = 0  #: the Gauss-Newton increment fell below ``tol``
    MAX_ITER = 1  #: ``max_iter`` reached; parameters are the last iterate (use with care)
    DIVERGED = 2  #: the iteration blew up (non-finite or huge step, singular Hessian)
    OUTSIDE = 3  #: the subset (reference or warped) leaves the image
    LOW_TEXTURE = 4  #: subset intensity gradient too weak (flat or saturated texture)
    NOT_COMPUTED = 5  #: not solved (masked out, or not yet processed in a file being written)

    @classmethod
    def describe(cls) -> str:
        return ", ".join(f"{s.value}={s.name.lower()}" for s in cls)


__all__ = ["Status"]
