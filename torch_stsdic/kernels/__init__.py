"""The kernels layer: the compute kernels and, per operation, the one place that chooses the
backend that runs it.

- :mod:`.native`: the fused C++ CPU kernels (source ``native/dic_kernels.cpp``, built on
  first use), with their loader and :func:`~.native.usable` rule.
- :mod:`.triton_ic`: the fused Triton step on CUDA; :mod:`.triton_solve`: a whole
  Gauss-Newton stage in one Triton launch (every point iterated to its end).
- :mod:`.bspline`, :mod:`.ic_step`: the torch code of the same operations (any device,
  autograd), :mod:`.compile` its torch.compile policy.
- :mod:`.fused_step`: the joint IC right-hand side op (Triton, else torch; the C++ kernel is
  chosen by :mod:`.dispatch`).
- :mod:`.dispatch`: which backend serves each operation.
- :mod:`.linalg`: batched inverses of small SPD matrices.

Nothing here imports from the layers above (core, io, analysis, movie, the faces).
"""

from torch_stsdic.kernels.fused_step import available, ic_rhs, set_triton, triton_mode, usable

__all__ = ["available", "set_triton", "triton_mode", "usable", "ic_rhs"]
