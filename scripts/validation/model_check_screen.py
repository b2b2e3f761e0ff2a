#!/usr/bin/env python
"""How the model check's screen (``checks.SCREEN``) decides against solving every row.

The model check (``checks.BlockChecks.check_model``) judges a row from its window's free classical
step where the row passes with room to spare, and solves the others classically. This script
runs ``stsdic run ARGS`` and, at every check, also solves *every* usable row classically (as
the check did before the screen: CHECK_ITER steps from the step, in full where those do not
converge) and judges it with the same tests. Printed per block and in total:

- the rows judged, the share the screen passed, the share the full check passes;
- false passes: rows the screen passed that the full check fails, with their z (the
  difference over its predicted std; the limit is ``quality.MODEL_Z``), their residual over
  the limit and their window - classical difference, px;
- how near the step's estimates are to the solved classical solutions (u, v px; ZNCC;
  noise and std ratios) and the estimate's error over the step's size (the contraction the
  slack ``checks.SCREEN_SLACK`` allows for).

    python scripts/validation/model_check_screen.py run ../shared/data/mudic-hourglass/ \\
        --subset 31 --step 20 --roi 150 20 1120 734 --m 2

The run's own results are not changed (the extra solves only inform the printout), but for
the run-level decision of points to solve classically: the study switches it off (the
template's or the run's own time-model test, ``RunEstimates.model_holds``), so that every
point's windows reach the check (with it, sample 12's points are all classical before any
check).
"""

from __future__ import annotations

import sys

import torch

import torch_stsdic.movie.checks as checks
from torch_stsdic.analysis.quality import (
    RESIDUAL_Z,
    difference_std,
    model_mismatch,
    residual_mismatch,
)
from torch_stsdic.analysis.result import USABLE
from torch_stsdic.cli import main as cli_main
from torch_stsdic.core.gauss_newton import classical_step_columns
from torch_stsdic.core.status import Status
from torch_stsdic.movie.estimates import RunEstimates

TOTAL = {"rows": 0, "screened": 0, "pass": 0, "false": 0}


def _judged(self, idx, screened, est) -> None:
    """Solve every row of ``idx`` as the full check does, compare, print one line."""
    run = self.run
    act = self._classical(idx, run.check_solver())
    nc = act.status != int(Status.CONVERGED)
    if bool(nc.any()):  # the full check solves these to the run's tol before judging
        act = checks.with_rows(act, nc, self.solve(idx[nc], act.params[nc].nan_to_num(0.0),
                                                   m=0))
    names = est.param_names
    cu, cv = names.index("u"), names.index("v")
    iu, iv = run.names.index("u"), run.names.index("v")
    own = self.k.repeat_interleave(self.n)[idx] == self.ref.frame
    d_win = self.params[idx][:, [iu, iv]].double()
    d_cls = act.params[:, [cu, cv]].double()
    pixels = run.solver.window.effective_pixels()
    fail = (act.status > int(Status.MAX_ITER)) | model_mismatch(
        d_win, d_cls, self.std[idx][:, [iu, iv]], act.std[:, [cu, cv]])
    fail |= ~own & residual_mismatch(self.sigma[idx], act.sigma, pixels, self.zncc[idx])
    false = screened & fail
    n = idx.numel()
    TOTAL["rows"] += n
    TOTAL["screened"] += int(screened.sum())
    TOTAL["pass"] += int((~fail).sum())
    TOTAL["false"] += int(false.sum())
    line = (f"block: {n} rows, screened {screened.float().mean():.1%}, full check passes "
            f"{(~fail).float().mean():.1%}, false passes {int(false.sum())}")
    ok = torch.isfinite(est.params).all(1) & ~own & (act.status == int(Status.CONVERGED))
    if bool(ok.any()):
        err = (est.params[ok][:, [cu, cv]].double() - d_cls[ok]).abs().amax(1)
        size = self.check_start[idx][ok, classical_step_columns(len(names) // 2)["size"]]
        ratio = err / size.squeeze(-1).double().clamp(min=1e-12)
        have = torch.isfinite(est.sigma[ok]) & (act.sigma[ok] > 0)
        line += (f" | estimate - solved: u,v p99 {err.quantile(0.99):.1e} px; error/step "
                 f"p99 {ratio.quantile(0.99):.2f} max {ratio.max():.2f}")
        if bool(have.any()):
            rs = (est.sigma[ok][have] / act.sigma[ok][have]).double()
            line += f"; sigma ratio {rs.min():.3f}-{rs.max():.3f}"
    print(line, flush=True)
    if bool(false.any()):
        sd = difference_std(self.std[idx][:, [iu, iv]], act.std[:, [cu, cv]])
        z = ((d_win - d_cls).abs() / sd).amax(1)
        limit = 1.0 + RESIDUAL_Z / max(float(pixels), 1.0) ** 0.5
        res = self.sigma[idx].double() / act.sigma.double() / limit
        for r in torch.nonzero(false).flatten().tolist():
            print(f"  false pass: z {float(z[r]):.2f}, residual / limit {float(res[r]):.3f}, "
                  f"|window - classical| {float((d_win[r] - d_cls[r]).abs().max()):.4f} px")


def main(argv: list[str]) -> int:
    screen = checks.BlockChecks._screen

    def recording(self, idx):  # the screen sees every row: the usable ones are judged
        screened, est = screen(self, idx)
        if screened is not None:
            use = (self.status[idx] <= USABLE) & torch.isfinite(self.params[idx]).all(1)
            sel = torch.nonzero(use).flatten()
            _judged(self, idx[sel], screened[sel], checks.solution_rows(est, sel))
        return screened, est

    checks.BlockChecks._screen = recording
    # every point's windows judged by the check: no points decided classical up front
    RunEstimates.model_holds = property(lambda self: None)
    code = cli_main(argv)
    t = TOTAL
    if t["rows"]:
        print(f"total: {t['rows']} rows, screened {t['screened'] / t['rows']:.1%}, full check "
              f"passes {t['pass'] / t['rows']:.1%}, false passes {t['false']}")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
