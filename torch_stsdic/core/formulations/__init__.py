"""STS-DIC formulations: one linearised model per module (residual, Jacobian, Hessian,
stationarity), iterated by :mod:`torch_stsdic.core.solver`, differentiated by
:mod:`torch_stsdic.nn`, propagated to a covariance by :mod:`torch_stsdic.core.noise`.

=================  =============================================================
``joint_ic``       :class:`JointIC`: sum over frames, inverse compositional (default)
``joint_fa``       :class:`JointFA`: the same criterion, forward additive (quadratic shape)
``average``        :class:`AverageFA`: the paper's averaged image (Eqs. 2, 11), forward additive
=================  =============================================================

:func:`stages` turns a configured formulation name into the stages the solver runs. A new
formulation is a new module with a :class:`Formulation` subclass, and a line in
:func:`stages`.
"""

from __future__ import annotations

from torch_stsdic.core.formulations.base import (
    Formulation,
    Geometry,
    SubsetData,
    reference_subsets,
    wsum,
)
from torch_stsdic.core.formulations.forward_additive import AverageFA, JointFA
from torch_stsdic.core.formulations.joint_ic import (
    JointIC,
    centred_gram,
    gram,
    gram_and_texture,
    ic_hessian,
    ic_jacobian,
    ic_rhs_kernel,
)
from torch_stsdic.core.shape import ShapeFunction

__all__ = [
    "Formulation",
    "Geometry",
    "SubsetData",
    "JointIC",
    "JointFA",
    "AverageFA",
    "stages",
    "joint",
    "reference_subsets",
    "wsum",
    "gram",
    "centred_gram",
    "gram_and_texture",
    "ic_hessian",
    "ic_jacobian",
    "ic_rhs_kernel",
]


def joint(shape: ShapeFunction) -> Formulation:
    """The joint formulation for ``shape``: inverse compositional where the shape family is
    closed under composition, else forward additive."""
    return JointIC() if shape.inverse_compositional else JointFA()


def stages(name: str, shape: ShapeFunction) -> list[Formulation]:
    """The Gauss-Newton stages for formulation ``name`` ("auto", "joint", "average",
    "joint+average") and shape function ``shape`` (already without temporal terms for a
    single frame, where every formulation is classical DIC)."""
    if not shape.has_time or name in ("joint", "auto"):
        return [joint(shape)]
    if name == "average":
        return [AverageFA()]
    if name == "joint+average":
        return [joint(shape), AverageFA(free=~shape.temporal_mask())]
    raise ValueError(f"unknown formulation {name!r}")
