"""A block's rows being worked on, narrowed step by step (:class:`RowSet`): on the CPU by
taking the rows a step keeps (a host read: free there, and later steps compute those rows
only), on a GPU by a mask over a fixed set of rows (no read: every row computed, those not
kept masked; :data:`~torch_stsdic.core.choices.MASKED_CHECK`). Both give the same numbers
at the rows that count; the model check (:meth:`~torch_stsdic.movie.checks.BlockChecks.
check_model`) is written once over a :class:`RowSet`. Also the row selection of a
:class:`~torch_stsdic.core.solver.WindowSolution` (:func:`solution_rows`,
:func:`with_rows`, :func:`blend`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from torch_stsdic.core.solver import WindowSolution

__all__ = ["RowSet", "take", "solution_rows", "with_rows", "blend"]


def take(x: torch.Tensor, pos: torch.Tensor | None) -> torch.Tensor:
    """``x`` (R, ...) at the positions ``pos`` (a :meth:`RowSet.narrow`'s; None: every
    row, ``x`` itself)."""
    return x if pos is None else x[pos]


def solution_rows(sol: WindowSolution, pick: torch.Tensor | None) -> WindowSolution:
    """The rows ``pick`` (bool mask or indices; None: every row, ``sol`` itself) of a
    solution."""
    if pick is None:
        return sol
    if pick.dtype == torch.bool:  # one index for all the fields (a mask syncs per tensor)
        pick = torch.nonzero(pick).flatten()
    return WindowSolution(
        points=sol.points[pick], params=sol.params[pick], param_names=sol.param_names,
        zncc=sol.zncc[pick], status=sol.status[pick], iterations=sol.iterations[pick],
        time=sol.time, std=None if sol.std is None else sol.std[pick],
        sigma=None if sol.sigma is None else sol.sigma[pick],
    )


def with_rows(sol: WindowSolution, pick: torch.Tensor, new: WindowSolution) -> WindowSolution:
    """``sol`` with its rows ``pick`` (bool mask or indices) replaced by the rows of ``new``
    (their iterations added to those ``sol`` took)."""
    if pick.dtype == torch.bool:  # one index for all the fields
        pick = torch.nonzero(pick).flatten()

    def put(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
        if a is None or b is None:
            return a
        out = a.clone()
        out[pick] = b.to(a.dtype)
        return out

    return WindowSolution(
        points=sol.points, params=put(sol.params, new.params), param_names=sol.param_names,
        zncc=put(sol.zncc, new.zncc), status=put(sol.status, new.status),
        iterations=put(sol.iterations, sol.iterations[pick] + new.iterations), time=sol.time,
        std=put(sol.std, new.std), sigma=put(sol.sigma, new.sigma),
    )


def blend(sol: WindowSolution, where: torch.Tensor, new: WindowSolution) -> WindowSolution:
    """:func:`with_rows` by a mask of the same rows, with no read: ``sol``'s rows where
    ``where`` (R,) bool are ``new``'s (R rows too), their iterations added."""
    def pick(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
        if a is None or b is None:
            return a
        w = where.view(-1, *([1] * (a.dim() - 1)))
        return torch.where(w, b.to(a.dtype), a)

    return WindowSolution(
        points=sol.points, params=pick(sol.params, new.params), param_names=sol.param_names,
        zncc=pick(sol.zncc, new.zncc), status=pick(sol.status, new.status),
        iterations=torch.where(where, sol.iterations + new.iterations, sol.iterations),
        time=sol.time, std=pick(sol.std, new.std), sigma=pick(sol.sigma, new.sigma),
    )


@dataclass(frozen=True)
class RowSet:
    """Rows of a block: ``idx`` (R,) long, and where ``masked``, ``act`` (R,) bool, the rows
    that still count (the others carried along, computed and ignored)."""

    idx: torch.Tensor
    masked: bool
    act: torch.Tensor | None = None

    @classmethod
    def every(cls, rows: int, device: torch.device, masked: bool) -> RowSet:
        """All ``rows`` rows of a block, narrowed later by mask (``masked``) or by taking."""
        idx = torch.arange(rows, device=device)
        return cls(idx, masked, torch.ones(rows, dtype=torch.bool, device=device)
                   if masked else None)

    def narrow(self, keep: torch.Tensor) -> tuple[RowSet, torch.Tensor | None]:
        """The rows where ``keep`` (R,) bool holds, and the positions taken to narrow
        what is aligned with these rows (:func:`take`; None: none taken, the mask in
        :attr:`act`). The CPU takes them (one host read); masked, no read."""
        if self.masked:
            return RowSet(self.idx, True, self.act & keep), None
        pos = torch.nonzero(keep).flatten()
        return RowSet(self.idx[pos], False), pos

    def on(self, mask: torch.Tensor) -> torch.Tensor:
        """``mask`` (R,) bool at the rows that count (False at the others)."""
        return mask if self.act is None else mask & self.act

    def none(self) -> bool:
        """Whether no row is left: read on the CPU (the rows taken), never on a GPU (False:
        the masked steps go on and change nothing)."""
        return not self.masked and self.idx.numel() == 0

    def count(self) -> int | torch.Tensor:
        """How many rows count (an int taken, a 0-d tensor masked: not read here)."""
        return self.idx.numel() if self.act is None else self.act.sum()

    def put(self, dst: torch.Tensor, value: torch.Tensor) -> None:
        """``dst[idx] = value`` (R, ...) at the rows that count, in place (no read)."""
        if self.act is None:
            dst[self.idx] = value
        else:
            w = self.act.view(-1, *([1] * (value.dim() - 1)))
            dst[self.idx] = torch.where(w, value, dst[self.idx])

    def redo(self, sol: WindowSolution, mask: torch.Tensor,
             solve: Callable[[torch.Tensor | None, torch.Tensor | None], WindowSolution]
             ) -> WindowSolution:
        """``sol`` (R rows) with its rows where ``mask`` (R,) bool holds (and that count)
        replaced by ``solve(pos, active)``'s: the CPU takes those rows (``pos``: their
        positions, one host read; ``active`` None), masked every row is solved (``pos``
        None) with the others masked (``active``)."""
        if self.masked:
            active = self.on(mask)
            return blend(sol, active, solve(None, active))
        pos = torch.nonzero(mask).flatten()
        return sol if not pos.numel() else with_rows(sol, pos, solve(pos, None))
