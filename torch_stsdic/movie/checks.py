"""The trust checks of a block's rows (:class:`BlockChecks`, mixed into
:class:`torch_stsdic.movie.block.Block`): every window against the classical solution of its
target (shorter windows where the motion is not affine in time, the classical solution where
none fits; judged from the window's free classical step where it passes with room to spare),
rows still lost solved classically, poor fits and outliers among neighbours flagged. The
tests themselves are pure functions in :mod:`torch_stsdic.analysis.quality`."""

from __future__ import annotations

import numpy as np
import torch

from torch_stsdic.analysis.quality import (
    RESIDUAL_ZNCC,
    line_mismatch,
    median_test,
    model_mismatch,
    neighbour_tolerance,
    poor_fit,
    residual_mismatch,
)
from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.choices import every_candidate, masked_check, masked_groups, until_done
from torch_stsdic.core.initial import linear_fit_in_time
from torch_stsdic.core.solver import (
    SubsetSolver,
    WindowSolution,
    classical_step_info,
)
from torch_stsdic.core.status import Status
from torch_stsdic.movie.carry import Carry
from torch_stsdic.movie.frames import true_rows
from torch_stsdic.movie.row_set import RowSet, solution_rows, take, with_rows

#: Gauss-Newton steps of the model check's classical solutions (measured on a 2,500-point
#: movie: 26 % of rows had not converged after 3 steps, 0.8 % after 4; the rest are re-solved)
CHECK_ITER = 4

#: px: convergence threshold of the model check's classical solutions (the run's ``tol``,
#: 1e-4 px by default, where looser). The check compares the window with the classical
#: solution within 3 standard deviations of their difference (>= 0.015 px), so a classical
#: solution 1e-3 px from its minimum decides the same; the rows that keep the classical
#: solution (the check failed at every window) are converged to the run's ``tol`` first.
CHECK_TOL = 1e-3

#: The model check judges a row from its window's free classical step (``classical_step``:
#: the classical solution one Gauss-Newton step from the window, its ZNCC, noise and std
#: from the Gauss-Newton model; none where that step is large for the model,
#: ``gauss_newton.STEP_DROP``) where the row passes with room to spare: the displacement
#: test with SCREEN_SLACK times the step's size added to the difference (the classical
#: solution lies within that of the estimate where Gauss-Newton contracts at a rate <= 1/3)
#: and the residual test with the limit tightened by SCREEN_MARGIN. Other rows are solved
#: classically (CHECK_ITER steps from the step), as all were before; False: every row is.
#: Measured against solving every row (``scripts/real_time_model.py`` solves them all): the
#: 1024^2 pair 87 % of rows judged from the step, none that the solve fails; the muDIC
#: hourglass 86 %, one of 64,609 rows that the solve fails (z 3.11 against the limit 3);
#: sample 12 40 % / 12 % (its load step: most rows fail), none.
SCREEN = True
SCREEN_SLACK = 0.5
SCREEN_MARGIN = 0.98


class BlockChecks:
    """The checks of a :class:`~torch_stsdic.movie.block.Block` (its rows, solves and
    ``keep`` come from the block)."""

    def _own(self, idx: torch.Tensor) -> torch.Tensor:
        """(R,) bool: rows ``idx`` whose target is the current reference frame itself (their
        classical solution is the identity)."""
        return self.k.repeat_interleave(self.n)[idx] == self.ref.frame

    def _no_residual(self, idx: torch.Tensor, zncc: torch.Tensor) -> torch.Tensor:
        """(R,) bool: rows ``idx`` whose classical residual (classical ZNCC ``zncc`` (R,)) is
        round-off, no measure of the noise: the target is the reference frame itself
        (:meth:`_own`), or, against a template made from the series (the reference no frame,
        ``ref.frame`` -1, the plan's reference a frame: ``run.reference_desc`` its index),
        that frame where the template kept its pixels (no other frame entered it there, e.g.
        too few POIs for the planes that register it): its classical solution matches at
        ZNCC >= ``RESIDUAL_ZNCC``."""
        own = self._own(idx)
        desc = self.run.reference_desc
        if self.ref.frame >= 0 or isinstance(desc, bool) or not isinstance(
                desc, (int, np.integer)):
            return own
        at = self.k.repeat_interleave(self.n)[idx] == int(desc)
        return own | (at & (zncc.to(self.run.dtype) >= RESIDUAL_ZNCC))

    def _classical(self, idx: torch.Tensor, solver: SubsetSolver,
                   active: torch.Tensor | None = None) -> WindowSolution:
        """The classical solutions of rows ``idx`` from their window's solution (with
        ``solver``; ``active`` (R,) bool: only those, the others masked); where the target
        is the reference frame itself it is the :meth:`identity_solution`, not solved."""
        own = self._own(idx)
        # one classical step from the window's solution is known where its solve gave it:
        # the solve goes on from there, that step its previous increment
        start, step = self.params[idx], None
        if self.check_start is not None:
            known = classical_step_info(self.check_start[idx])
            spatial = [self.run.names.index(nm)
                       for nm in self.run.solver.shape.spatial().param_names]
            p0, size = known["classical_step"], known["classical_step_size"]
            have = (torch.isfinite(p0).all(1) & torch.isfinite(size)).unsqueeze(1)
            start = torch.where(have, p0, start[:, spatial])
            step = torch.where(have.squeeze(1), size, 0.0)
        if active is not None:  # (the masked rows' start: any finite one)
            start = start.nan_to_num(0.0)
        # (one read for both tests, only in the block whose targets hold the reference frame)
        n_own = int(own.sum()) if self.ref.frame in self.ks else 0
        if not n_own:
            return self.solve(idx, start, m=0, solver=solver, init_step=step, active=active,
                              site="check")
        ident = self.identity_solution(idx)
        if n_own == idx.numel():
            return ident
        other = torch.nonzero(~own).flatten()
        return with_rows(ident, other, self.solve(
            idx[other], start[other], m=0, solver=solver,
            init_step=None if step is None else step[other],
            active=None if active is None else active[other], site="check"))

    def _screen(self, idx: torch.Tensor) -> tuple[torch.Tensor | None, WindowSolution | None]:
        """(R,) bool: rows ``idx`` that pass the model check from their window's free
        classical step (:data:`SCREEN`), and the classical solutions estimated there (a
        :class:`WindowSolution` of R rows, CONVERGED, NaN where unknown); (None, None)
        where no solve gave one."""
        run = self.run
        if not SCREEN or self.check_start is None:
            return None, None
        names = run.solver.shape.spatial().param_names
        known = self.check_start[idx]
        step = classical_step_info(known)
        p_est, sd = step["classical_step"], step["classical_step_std"]
        size, zn = step["classical_step_size"], step["classical_step_zncc"]
        sig = step["classical_step_sigma"]
        cu, cv = names.index("u"), names.index("v")
        iu, iv = run.names.index("u"), run.names.index("v")
        ok = torch.isfinite(known).all(1) & ~self._own(idx)
        ok &= ~model_mismatch(self.params[idx][:, [iu, iv]], p_est[:, [cu, cv]],
                              self.std[idx][:, [iu, iv]], sd[:, [cu, cv]],
                              slack=SCREEN_SLACK * size)
        ok &= ~residual_mismatch(self.sigma[idx], sig, run.solver.window.effective_pixels(),
                                 self.zncc[idx], margin=SCREEN_MARGIN)
        r = idx.numel()
        est = WindowSolution(
            points=self.pts[idx], params=p_est.to(run.dtype), param_names=names,
            zncc=zn.to(run.dtype), status=torch.full((r,), int(Status.CONVERGED),
                                                     dtype=torch.int8, device=run.device),
            iterations=torch.zeros(r, dtype=torch.int32, device=run.device),
            std=sd.to(run.dtype), sigma=sig.to(run.dtype))
        return ok, est

    def _off_a_line(self, rows: torch.Tensor, m: int, disp: torch.Tensor, std: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(R,) bool: rows whose window of half-width ``m`` cannot pass the model check,
        judged from the classical solutions ``disp`` (B*N, 2) (std ``std``) of the block's
        rows at the window's frames (:func:`~torch_stsdic.analysis.quality.line_mismatch`; False
        where a frame of the window is not a target of the block); and (R, 2) the velocity
        of the line through them, px per time unit (NaN where a frame has none)."""
        run, n = self.run, self.n
        win = self.windows(m)  # (B, T)
        pos = torch.full((run.n_series,), -1, dtype=torch.long, device=run.device)
        pos[self.k] = torch.arange(self.b, device=run.device)
        j, i = rows // n, rows % n
        at = pos[win[j]]  # (R, T) the block target of each window frame, -1: none
        d = disp[(at * n + i.unsqueeze(1)).clamp(min=0)]  # (R, T, 2)
        d = torch.where((at >= 0).unsqueeze(-1), d, float("nan"))
        off = self.motion_of(m)
        if off is not None:
            d = d - off[rows]
        _, dt = self.window_rows(m)
        _, vel = linear_fit_in_time(d, dt[rows], spread=True)  # m > 0: distinct times
        return line_mismatch(d, dt[rows], disp[rows], std[rows]), vel

    def check_model(self) -> tuple[int | torch.Tensor, int | torch.Tensor]:
        """Model check (:func:`~torch_stsdic.analysis.quality.model_mismatch`) of every usable row
        against its classical solution at the target frame (started from the row's own
        solution: ``CHECK_ITER`` steps to ``CHECK_TOL``, in full where those do not converge
        or disagree; the identity where the target is the reference frame). Rows that fail
        are solved again with shorter windows (m - 1 .. 1) started from the classical
        solution and the velocity of the line through the block's classical solutions,
        except where those already miss a line
        (:func:`~torch_stsdic.analysis.quality.line_mismatch`);
        where no window fits they keep the classical solution, converged to the run's
        ``tol`` (ut, vt NaN, ``m_used`` 0). A usable row whose classical solution fails is
        POOR_FIT. The rows of each step are taken from the last's on the CPU, masked over
        all the block's rows on a GPU (:class:`~torch_stsdic.movie.row_set.RowSet`: no
        host read; :data:`~torch_stsdic.core.choices.MASKED_CHECK`). Returns (rows
        shortened, rows left classical: ints, or 0-d tensors not read here)."""
        run = self.run
        if run.m == 0:
            return 0, 0
        use = (self.status <= USABLE) & torch.isfinite(self.params).all(1)
        iu, iv = run.names.index("u"), run.names.index("v")
        rows, _ = RowSet.every(use.numel(), run.device, masked_check(run.device)).narrow(use)
        if rows.none():
            return 0, 0
        idx = rows.idx
        # rows whose free classical step passes with room to spare are judged from it; the
        # others take a few classical steps from there; rows that do not converge in them,
        # or disagree, are solved classically in full before they are judged
        screened, quick = self._screen(idx)
        solver = run.check_solver()

        def classical(pos: torch.Tensor | None, active: torch.Tensor | None) -> WindowSolution:
            return self._classical(take(idx, pos), solver, active)
        quick = classical(None, rows.act) if screened is None else rows.redo(
            quick, ~screened, classical)
        cu, cv = quick.param_names.index("u"), quick.param_names.index("v")
        # every row's classical (u, v) and std (NaN: none), for the shorter windows below
        d_all = torch.full((self.b * self.n, 2), float("nan"), dtype=run.dtype,
                           device=run.device)
        s_all = d_all.clone()
        conv = rows.on(quick.status == int(Status.CONVERGED)).unsqueeze(1)  # (no read)
        d_all[idx] = torch.where(conv, quick.params[:, [cu, cv]].to(run.dtype), float("nan"))
        s_all[idx] = torch.where(conv, quick.std[:, [cu, cv]].to(run.dtype), float("nan"))
        # the reference frame as target: its classical residual is round-off, no measure
        not_ref = ~self._no_residual(idx, quick.zncc)
        pixels = run.solver.window.effective_pixels()
        suspect = (quick.status != int(Status.CONVERGED)) | model_mismatch(
            self.params[idx][:, [iu, iv]], quick.params[:, [cu, cv]].to(run.dtype),
            self.std[idx][:, [iu, iv]], quick.std[:, [cu, cv]].to(run.dtype))
        suspect |= not_ref & residual_mismatch(self.sigma[idx], quick.sigma, pixels,
                                               self.zncc[idx])
        rows, pos = rows.narrow(suspect)
        if rows.none():
            return 0, 0
        idx, not_ref, cls = rows.idx, take(not_ref, pos), solution_rows(quick, pos)
        # where the few steps converged they are the classical solution (the full solver
        # takes the same steps); only the others go on
        redo = cls.status != int(Status.CONVERGED)

        def in_full(pos: torch.Tensor | None, active: torch.Tensor | None,
                    start: torch.Tensor = cls.params) -> WindowSolution:
            return self.solve(take(idx, pos), take(start, pos).nan_to_num(0.0), m=0,
                              active=active, site="check in full")
        cls = rows.redo(cls, redo, in_full)
        not_ref = ~self._no_residual(idx, cls.zncc)
        ok_c = cls.status <= USABLE
        rows.put(d_all, torch.where(ok_c.unsqueeze(1), cls.params[:, [cu, cv]].to(run.dtype),
                                    float("nan")))
        rows.put(s_all, torch.where(ok_c.unsqueeze(1), cls.std[:, [cu, cv]].to(run.dtype),
                                    float("nan")))
        rows.put(self.status, self.status[idx].masked_fill(~ok_c, int(Status.POOR_FIT)))
        # the usable classical rows whose window fails
        fail = model_mismatch(self.params[idx][:, [iu, iv]], cls.params[:, [cu, cv]].to(
            run.dtype), self.std[idx][:, [iu, iv]], cls.std[:, [cu, cv]].to(run.dtype))
        fail |= not_ref & residual_mismatch(self.sigma[idx], cls.sigma, pixels, self.zncc[idx])
        fail &= ok_c
        rows, pos = rows.narrow(ok_c)
        idx, not_ref, redo = rows.idx, take(not_ref, pos), take(redo, pos)
        fail = rows.on(take(fail, pos))
        cls = solution_rows(cls, pos)
        d_cls = cls.params[:, [cu, cv]].to(run.dtype)
        s_cls = cls.std[:, [cu, cv]].to(run.dtype)
        init = self.params[idx].clone()  # shorter windows start from the classical solution
        for j, nm in enumerate(cls.param_names):
            init[:, run.names.index(nm)] = cls.params[:, j].to(run.dtype)
        shortened: int | torch.Tensor = 0
        if run.m > 1 and (rows.masked or bool(fail.any())):
            shortened = self._shorter_windows(idx, fail, init, (d_all, s_all),
                                              (d_cls, s_cls, cls.sigma), not_ref)
        # the rows no window fits keep their classical solution; those converged to
        # CHECK_TOL only go on to the run's tol (the usable ones kept over them)
        rows, pos = rows.narrow(fail)
        kept, redo = solution_rows(cls, pos), take(redo, pos)
        self.keep(rows.idx, kept, only_better=False, m=0, where=rows.act)
        loose, lpos = rows.narrow(~redo)
        if not loose.none():
            pol = self.solve(loose.idx, take(kept.params, lpos).nan_to_num(0.0), m=0,
                             active=loose.act, site="check to tol")
            self.keep(loose.idx, pol, only_better=False, m=0,
                      where=loose.on(pol.status <= USABLE))
        return shortened, rows.count()

    def _shorter_windows(self, idx: torch.Tensor, fail: torch.Tensor, init: torch.Tensor,
                         block_cls: tuple[torch.Tensor, torch.Tensor],
                         cls: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                         not_ref: torch.Tensor) -> torch.Tensor:
        """The rows ``idx`` (R,) that fail the model check (``fail`` (R,) bool, cleared where
        a window passes) solved again with shorter windows from ``init`` (R, P): each row's
        candidates are the half-widths below its window's, longest first, but those whose
        frames' classical solutions miss a line (:meth:`_off_a_line`, from the block's
        classical (u, v) and std ``block_cls``: (B*N, 2) each); the first that passes the
        check against the row's classical solution ``cls`` ((R, 2) (u, v), (R, 2) std,
        (R,) residual sigma; ``not_ref``: where its residual measures the noise) is kept.
        Where the solver mixes window lengths, every failing row's next candidate in one
        solve (one read and one solve a round, as many rounds as the deepest row's tries,
        not one a half-width), or on a GPU every candidate at once
        (:data:`~torch_stsdic.core.choices.EVERY_CANDIDATE`,
        :meth:`_every_window`); else one solve a half-width. Returns the rows shortened
        (0-d tensor, not read)."""
        run = self.run
        ms = list(range(run.m - 1, 0, -1))  # the candidates' half-widths, longest first
        first_m = self.m_used[idx].long()
        offs, vels = zip(*(self._off_a_line(idx, m, *block_cls) for m in ms))
        cand = torch.stack([(first_m > m) & ~off for m, off in zip(ms, offs)], 1)  # (R, M)
        vel = torch.stack(vels, 1)  # (R, M, 2) the velocity of each candidate's line
        shortened = torch.zeros((), dtype=torch.int64, device=run.device)
        if not self.mixes_windows:
            for c, m in enumerate(ms):
                sel = torch.nonzero(fail & cand[:, c]).flatten()  # one read a half-width
                if sel.numel():
                    shortened += self._try_window(idx, sel, m, vel[sel, c], init, fail, cls,
                                                  not_ref)
            return shortened
        col = torch.arange(len(ms), device=run.device)
        m_col = torch.arange(run.m - 1, 0, -1, dtype=torch.int8, device=run.device)
        if every_candidate(run.device):
            return self._every_window(idx, fail, cand, m_col, vel, init, cls, not_ref)
        last = torch.full_like(first_m, -1)  # each row's candidate tried last (-1: none)
        left = cand & fail.unsqueeze(1)  # each row's candidates not tried yet
        # one read: the rows of the first round and the rounds at most (the most candidates
        # a row has): no read after the last
        n_sel, rounds = torch.stack([left.any(1).sum(), left.sum(1).max()]).tolist()
        for r in range(rounds):
            if r:  # the rows that failed their try and have candidates left (one read)
                left = cand & (col > last.unsqueeze(1)) & fail.unsqueeze(1)
                n_sel = int(left.any(1).sum())
            if n_sel == 0:
                break
            sel = true_rows(left.any(1), n_sel)
            c = left[sel].to(torch.int8).argmax(1)  # each row's next: its first one left
            last[sel] = c
            shortened += self._try_window(idx, sel, m_col[c], vel[sel, c], init, fail, cls,
                                          not_ref)
        return shortened

    def _try_window(self, idx: torch.Tensor, sel: torch.Tensor, m: int | torch.Tensor,
                    vel: torch.Tensor, init: torch.Tensor, fail: torch.Tensor,
                    cls: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                    not_ref: torch.Tensor) -> torch.Tensor:
        """One try of :meth:`_shorter_windows`: rows ``idx[sel]`` with windows of
        half-width ``m`` (an int, or (S,) each row's), started from ``init[sel]`` with the
        velocity ``vel`` (S, 2) of their classical solutions' line where known; kept where
        they pass (``fail`` cleared there). Returns how many passed (0-d tensor)."""
        sol, good = self._judge_window(idx, sel, m, vel, init, cls, not_ref)
        self.keep(idx[sel], sol, only_better=False, m=m, where=good)  # (no read)
        fail[sel] &= ~good
        return good.sum()

    def _every_window(self, idx: torch.Tensor, fail: torch.Tensor, cand: torch.Tensor,
                      m_col: torch.Tensor, vel: torch.Tensor, init: torch.Tensor,
                      cls: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                      not_ref: torch.Tensor) -> torch.Tensor:
        """:meth:`_shorter_windows` at once
        (:data:`~torch_stsdic.core.choices.EVERY_CANDIDATE`): every candidate
        ``cand`` (R, M) (half-widths ``m_col`` (M,), longest first; line velocities ``vel``
        (R, M, 2)) of every failing row in one solve (rows of mixed window lengths), each
        row's first that passes kept, as the rounds keep it. One host read (how many
        candidates), or on a GPU none: every (row, candidate) pair in the solve, those not
        to try masked (:data:`~torch_stsdic.core.choices.MASKED_GROUPS`). Returns the rows
        shortened (0-d tensor, not read)."""
        run = self.run
        n_rows, n_cand = cand.shape
        pairs = cand & fail.unsqueeze(1)  # (R, M) the windows to try
        active = None
        if masked_groups(run.device):  # every (row, candidate) pair, those not to try
            n_pairs = n_rows * n_cand   # masked (no read)
            q = torch.arange(n_pairs, device=run.device)
            active = pairs.reshape(-1)
        else:
            n_pairs = int(pairs.sum())  # the one read
            if n_pairs == 0:
                return torch.zeros((), dtype=torch.int64, device=run.device)
            q = true_rows(pairs.reshape(-1), n_pairs)
        # row-major: a row's candidates together, longest first
        sel, c = torch.div(q, n_cand, rounding_mode="floor"), q % n_cand
        sol, good = self._judge_window(idx, sel, m_col[c], vel[sel, c], init, cls, not_ref,
                                       active)
        # each row's first candidate that passes: the least position among its good ones
        # (n_pairs: none), one gathered solution a row (no row twice in a store)
        first = torch.full((n_rows,), n_pairs, dtype=torch.long, device=run.device)
        pos = torch.arange(n_pairs, device=run.device)
        first = first.scatter_reduce(0, sel, torch.where(good, pos, n_pairs), "amin")
        passed = first < n_pairs
        pick = first.clamp(max=n_pairs - 1)
        self.keep(idx, solution_rows(sol, pick), only_better=False, m=m_col[c[pick]],
                  where=passed)
        fail &= ~passed
        return passed.sum()

    def _judge_window(self, idx: torch.Tensor, sel: torch.Tensor, m: int | torch.Tensor,
                      vel: torch.Tensor, init: torch.Tensor,
                      cls: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                      not_ref: torch.Tensor, active: torch.Tensor | None = None
                      ) -> tuple[WindowSolution, torch.Tensor]:
        """Rows ``idx[sel]`` solved with windows of half-width ``m`` (an int, or (S,) each
        row's) from ``init[sel]`` with the velocity ``vel`` (S, 2) of their classical
        solutions' line where known, and judged against their classical solutions ``cls``:
        the solution and (S,) bool where it passes (nothing kept here; ``active`` (S,) bool:
        only those solved, the others masked and not passing)."""
        run = self.run
        iu, iv = run.names.index("u"), run.names.index("v")
        cls_uv, cls_std, cls_sig = cls
        start = init[sel]
        for c, nm in ((0, "ut"), (1, "vt")):
            if nm in run.names:
                j = run.names.index(nm)
                start[:, j] = torch.where(torch.isfinite(vel[:, c]), vel[:, c].to(start),
                                          start[:, j])
        sol = self.solve(idx[sel], start, m=m, for_check=False,  # judged here, now
                         active=active, site="shorter windows")
        good = sol.status <= USABLE
        d = sol.params[:, [iu, iv]].to(run.dtype)
        good &= ~model_mismatch(d, cls_uv[sel], sol.std[:, [iu, iv]], cls_std[sel])
        good &= ~(not_ref[sel] & residual_mismatch(
            sol.sigma, cls_sig[sel], run.solver.window.effective_pixels(), sol.zncc))
        return sol, good

    def rescue_classical(self, guess: torch.Tensor | None, carry: Carry | None
                         ) -> int | torch.Tensor:
        """Rows a window could not solve (still lost after :meth:`rescue`) are solved
        classically (m = 0): from their carried ``guess`` (R, P) (NaN rows: none), then as
        in :meth:`rescue`. On a GPU the guessed rows in one masked solve of every row, and
        no read of whether any row is lost
        (:data:`~torch_stsdic.core.choices.MASKED_GROUPS`). Returns the rows that became
        usable (a 0-d tensor: read with the block's counts; 0 where none was lost)."""
        lost = self.lost()
        masked = masked_groups(self.run.device)
        if not masked and not bool(lost.any()):
            return 0
        if guess is not None:
            go = lost & torch.isfinite(guess).all(1)
            if masked:
                every = torch.arange(go.numel(), device=go.device)
                sol = self.solve_masked(every, guess, go, m=0, site="classical rescue")
                self.keep(every, sol, only_better=True, m=0, where=go)
            else:
                r = torch.nonzero(go).flatten()
                if r.numel():
                    self.keep(r, self.solve(r, guess[r], m=0), only_better=True, m=0)
        self.rescue(carry, torch.zeros_like(lost), m=0)
        return (lost & ~self.lost()).sum()

    def check_fit(self, carry: Carry | None = None) -> torch.Tensor:
        """Usable rows whose residual is not the image noise, or whose ZNCC is below the
        floor, become POOR_FIT (:func:`~torch_stsdic.analysis.quality.poor_fit`), each compared with
        the rows of its own target and with its point's last trusted row (``carry``, then
        the block's targets in time order). Returns their number (a 0-d tensor: read with
        the block's other counts)."""
        n, count = self.n, 0
        run = self.run
        base = torch.full((n,), float("nan"), dtype=run.dtype, device=run.device)
        if carry is not None and carry.fit_zncc is not None:
            base = carry.fit_zncc.to(base)
        for j in range(self.b):
            sl = slice(j * n, (j + 1) * n)
            bad = poor_fit(self.sigma[sl], self.zncc[sl], self.status[sl] <= USABLE,
                           run.lost_zncc, baseline_zncc=base)
            self.status[sl].masked_fill_(bad, int(Status.POOR_FIT))  # a view: no host sync
            count = count + bad.sum()
            base = torch.where(self.status[sl] <= USABLE, self.zncc[sl], base)
        return torch.as_tensor(count)

    def check_neighbours(self) -> torch.Tensor | int:
        """Usable rows that are outliers among their grid neighbours become INCONSISTENT
        (:func:`~torch_stsdic.analysis.quality.median_test` on u and v per target). Returns their
        number (a 0-d tensor: read with the block's other counts)."""
        run = self.run
        nb = run.grid_neighbours(self.ref)
        b, n = self.b, self.n
        rows = torch.arange(b * n, device=run.device)
        if self.identity is not None and self.has_identity:
            # the reference frame as its own target (zero motion everywhere) has no outlier
            rows = rows[~self.identity]
            b = rows.numel() // n
            if b == 0:
                return 0
        iu, iv = run.names.index("u"), run.names.index("v")
        params, std = self.params[rows], self.std[rows]
        uv = params[:, [iu, iv]].reshape(b, n, 2)
        ok = (self.status[rows] <= USABLE).reshape(b, n)
        sd = std[:, [iu, iv]].reshape(b, n, 2)
        grads = sg = None
        reach = 0.0
        if all(nm in run.names for nm in ("ux", "uy", "vx", "vy")):
            gi = [run.names.index(nm) for nm in ("ux", "uy", "vx", "vy")]
            grads = params[:, gi].reshape(b, n, 2, 2)
            # the gradients' own noise, carried over the neighbours' distance
            sg = std[:, gi].reshape(b, n, 4).amax(-1)
            reach = run.neighbour_reach
        eps = neighbour_tolerance(sd, sg, ok, nb, reach)
        out = median_test(uv, ok, nb, eps, points=self.ref.points, gradients=grads,
                          until_done=until_done(run.device))  # (a GPU: no read a round)
        self.status[rows] = self.status[rows].masked_fill(out.reshape(-1),
                                                          int(Status.INCONSISTENT))
        return out.sum()


