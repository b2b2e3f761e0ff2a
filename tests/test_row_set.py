"""The rows of a block's steps narrowed by taking them (the CPU) or by a mask over fixed rows
(a GPU's choice, no host read): the same numbers at the rows that count."""

from __future__ import annotations

import torch

from torch_stsdic.core.solver import WindowSolution
from torch_stsdic.movie.row_set import RowSet, blend, solution_rows, take, with_rows


def _solution(values: torch.Tensor) -> WindowSolution:
    r = values.numel()
    return WindowSolution(points=torch.zeros(r, 2), params=values.view(-1, 1).repeat(1, 2),
                          param_names=["u", "v"], zncc=values.clone(),
                          status=torch.zeros(r, dtype=torch.int8),
                          iterations=torch.full((r,), 2, dtype=torch.int32),
                          std=values.view(-1, 1).repeat(1, 2) / 10, sigma=values / 100)


def test_narrowing_by_mask_and_by_taking_agree_at_the_rows_that_count():
    """Two steps of narrowing, a re-solve of some rows and a store: every field at the rows
    that count equals the taken rows', the rows that do not count untouched by the store,
    the counts equal; the masked steps compute every row and read nothing."""
    gen = torch.Generator().manual_seed(3)
    n = 40
    first, second = torch.rand(n, generator=gen) > 0.3, torch.rand(n, generator=gen) > 0.5
    values = torch.arange(n, dtype=torch.float64)
    calls = {True: [], False: []}
    stores = {}
    for masked in (False, True):
        rows, _ = RowSet.every(n, torch.device("cpu"), masked).narrow(first)
        sol = solution_rows(_solution(values), None if masked else rows.idx)
        redo = take(second, None if masked else rows.idx)

        def solve(pos, active, masked=masked, idx=rows.idx):
            calls[masked].append((None if pos is None else pos.numel(), active is not None))
            picked = take(idx, pos)
            return _solution(-picked.double())  # a "solution": minus the row number

        sol = rows.redo(sol, redo, solve)
        dst = torch.full((n,), 99.0, dtype=torch.float64)
        rows.put(dst, sol.params[:, 0])
        stores[masked] = (dst, sol, rows)
    (dst_t, sol_t, rows_t), (dst_m, sol_m, rows_m) = stores[False], stores[True]
    assert torch.equal(dst_t, dst_m)  # the store: the same at every row
    at = rows_m.act.nonzero().flatten()
    assert torch.equal(rows_t.idx, at)
    for f in ("params", "zncc", "status", "iterations", "std", "sigma"):
        assert torch.equal(getattr(sol_t, f), getattr(sol_m, f)[at]), f
    assert rows_t.count() == int(rows_m.count()) == int(first.sum())
    expect = torch.where(first & second, -values, values)
    assert torch.equal(dst_t, torch.where(first, expect, 99.0))
    assert torch.equal(sol_t.iterations, torch.where((first & second)[at], 4, 2).int())
    assert calls[True] == [(None, True)]  # every row, masked: one solve, no read
    assert calls[False] == [(int((first & second).sum()), False)]  # the rows taken
    assert not rows_m.none() and RowSet.every(0, torch.device("cpu"), False).none()


def test_blend_is_with_rows_by_a_mask():
    a, b = _solution(torch.arange(6.0)), _solution(-torch.arange(6.0))
    where = torch.tensor([True, False, True, False, False, True])
    got, want = blend(a, where, b), with_rows(a, where, solution_rows(b, where))
    for f in ("params", "zncc", "status", "iterations", "std", "sigma"):
        assert torch.equal(getattr(got, f), getattr(want, f)), f
