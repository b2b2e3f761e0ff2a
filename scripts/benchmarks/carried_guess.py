#!/usr/bin/env python
"""How far a run's carried guesses start from their solutions: every carried row of the
main run's blocks (not the checks' or the rescue's solves), its first Gauss-Newton increment
per parameter (scaled as the convergence test scales it: px over the subset's half-width
and the window), and the solution minus the guess by the row's target within its block.

    python scripts/benchmarks/carried_guess.py -- ../shared/data/mudic-hourglass \\
        --roi 150 20 1120 734 --subset 31 --step 20

Runs ``stsdic run`` with those arguments in this process on the Python Gauss-Newton loop
(``TORCH_STSDIC_PER_POINT=0``: it sees every increment; the solutions are the C++ solver's
within its tolerance) and prints the medians and 90th percentiles of the first increments,
then per target of a block the rows, their mean iterations and the median |solution -
guess| of each parameter. Slower than a plain run (the increments are recorded)."""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
import traceback
from pathlib import Path

#: the main run's carried solves only (not these callers')
_OTHER = ("check_model", "rescue", "estimate_shared_motion", "build_series_reference",
          "_solve_own", "measure_window_lengths")


def _main_solve() -> bool:
    names = [f.name for f in traceback.extract_stack()]
    return "solve_block" in names and not any(x in names for x in _OTHER)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_args", nargs="+", help="stsdic run's arguments (after --)")
    a = ap.parse_args()
    os.environ["TORCH_STSDIC_PER_POINT"] = "0"
    import torch

    import torch_stsdic.core.gauss_newton as gn
    import torch_stsdic.movie.block as block_mod
    from torch_stsdic.cli.app import main as cli_main
    from torch_stsdic.core.formulations import joint_ic

    first: list[torch.Tensor] = []
    state = {"main": False, "step": 0, "t": 0}
    run_stage, update = gn._run_stage, joint_ic.JointIC.update

    def recording_stage(ctx, form, params, data, live, *args, **kwargs):
        state.update(main=_main_solve(), step=0,
                     t=0 if data is None or data.dt is None else data.dt.shape[1])
        return run_stage(ctx, form, params, data, live, *args, **kwargs)

    def recording_update(self, geo, p, dp):
        if state["main"] and state["t"] > 1 and state["step"] == 0:
            half = torch.full((1, state["t"]), float(state["t"] // 2), dtype=dp.dtype)
            scale = geo.shape.increment_scale(geo.spatial, half)
            first.append((dp.detach().double() * scale.double()).abs().cpu())
        state["step"] += 1
        return update(self, geo, p, dp)

    by_target: dict[int, list] = collections.defaultdict(list)
    solve = block_mod.Block.solve
    names: list[str] = []

    def recording_solve(self, idx, init, m=None, solver=None, init_step=None):
        sol = solve(self, idx, init, m=m, solver=solver, init_step=init_step)
        if (init is not None and self.run.m > 0 and sol.params.shape[1] == init.shape[1]
                and _main_solve()):
            names[:] = list(self.run.names)
            ok = sol.status == 0
            j = (idx // self.n)[ok]
            miss = (sol.params - init)[ok].abs().double().cpu()
            for jj in torch.unique(j).tolist():
                sel = (j == jj).cpu()
                by_target[jj].append((miss[sel], sol.iterations[ok][sel].double().cpu()))
        return sol

    gn._run_stage = recording_stage
    joint_ic.JointIC.update = recording_update
    block_mod.Block.solve = recording_solve
    with tempfile.TemporaryDirectory() as tmp:
        args = list(a.run_args)
        if "--out" not in args:
            args += ["--out", str(Path(tmp) / "run.h5")]
        rc = cli_main(["run", *args, "--overwrite", "--no-progress"])
    if not first:
        print("no carried rows with a window were solved")
        return rc or 1
    inc = torch.cat(first)
    inc = inc[torch.isfinite(inc).all(1)]
    print(f"first increments of {inc.shape[0]} carried rows (scaled; {', '.join(names)}):")
    print("  median " + "  ".join(f"{v:.1e}" for v in inc.median(0).values.tolist()))
    print("  p90    " + "  ".join(f"{v:.1e}" for v in inc.quantile(0.9, dim=0).tolist()))
    print("solution - guess by the row's target in its block (median |.|):")
    for jj in sorted(by_target):
        miss = torch.cat([m for m, _ in by_target[jj]])
        its = torch.cat([i for _, i in by_target[jj]])
        med = miss.median(0).values
        print(f"  target {jj}: {miss.shape[0]} rows, {float(its.mean()):.2f} iterations, "
              + " ".join(f"{nm}={v:.1e}" for nm, v in zip(names, med.tolist())))
    return rc


if __name__ == "__main__":
    sys.exit(main())
