"""The rescue of a block's lost rows (:class:`BlockRescue`, mixed into
:class:`torch_stsdic.movie.block.Block`): rows without a trustworthy solution after the
block's solve start again from the point's nearest earlier trusted target, from their grid
neighbours' solutions, or from FFT cross-correlation, all the block's targets at once in each
step."""

from __future__ import annotations

from typing import Any

import torch

from torch_stsdic.analysis.result import USABLE
from torch_stsdic.core.choices import guess_waves, until_done
from torch_stsdic.core.status import Status
from torch_stsdic.movie.block_guess import PLACEMENT, RESCUE
from torch_stsdic.movie.block_placement import Placement
from torch_stsdic.movie.carry import Carry, neighbour_guess
from torch_stsdic.movie.frames import true_rows
from torch_stsdic.movie.reference import to_relative

__all__ = ["BlockRescue", "MAX_UNREAD_WAVES"]

#: the most waves of a block's rescue taken unread (:meth:`BlockRescue._unread_waves`)
MAX_UNREAD_WAVES = 2
#: the guess "the waves end here" (:meth:`BlockRescue._waves_unread`), also the size
#: (:attr:`~torch_stsdic.movie.block_guess.ReadGuesses.sizes`) holding how many waves the
#: last reading rescue took (-1: it left rows to its neighbours or FFT), and the sites of
#: each wave's rows (``WAVE`` + its number)
WAVES, WAVE = "rescue waves", "rescue wave "
#: the guess "an unread wave's placement moves no subset" (where the last block's carried
#: start moved none: :meth:`BlockRescue._solve_own_masked`)
WAVE_PLACEMENT = "rescue wave placement"
#: the masked solves' sites of a rescue's rows (classical, windows)
RESCUE_SITES = ("rescue classical", "rescue windows")


class BlockRescue:
    """The rescue steps of a :class:`~torch_stsdic.movie.block.Block` (its rows, statuses,
    ``lost``, ``keep`` and ``solve``)."""

    #: the waves the block's rescue took reading, where at most :data:`MAX_UNREAD_WAVES`
    #: (None: more, or not read)
    waves_read: int | None = None

    def rescue(self, carry: Carry | None, carried: torch.Tensor, m: int | None = None
               ) -> tuple[int, int, int]:
        """Lost rows solved again, all the block's targets at once in each step (a few solves
        a block, not up to three a target: on a GPU each solve costs its launches and host
        reads): (1) from the point's nearest earlier trusted target of the block, moved on by
        its velocity (any earlier target where the velocity is known, as the block's carried
        rows are predicted over the whole block; the target just before where it is not), in
        waves while rows are found; (2) from their trusted grid neighbours' solutions at the
        same target; (3) from FFT cross-correlation at each point's first lost target with no
        trusted one before, then (1) again; (4) from FFT cross-correlation where still lost,
        then (1) again. The better result is kept (windows of half-width ``m``, default the
        run's). ``carried``: rows that started from the carried guess. Returns the rows
        restarted from an earlier target, by FFT, and by FFT after a carried start (ints, or
        0-d tensors read with the block's counts)."""
        run, b, n = self.run, self.b, self.n
        tried = torch.full((b * n,), -1, dtype=torch.long, device=run.device)
        fft_tried = torch.zeros(b * n, dtype=torch.bool, device=run.device)
        # each step's facts read with the waves' last read (:meth:`_facts`), read again only
        # after a step that changed the rows: a block with no lost row reads once
        from_prev, facts = self._from_earlier(carry, m, tried, fft_tried)
        if m is None and self.waves_read is not None:  # the pattern for the next block
            self.run.guesses.sizes[WAVES] = -1 if facts[0] else self.waves_read
        from_nb = 0
        by_fft: Any = 0
        redone: Any = 0
        if facts[0]:  # lost rows
            from_nb = self._rescue_from_neighbours(m, facts[2:])
            if from_nb:
                facts = self.read(self._facts(fft_tried))  # one read
            for first in (True, False):
                n_try = facts[1] if first else facts[0]  # (read with the rows as they stand)
                if not n_try:
                    continue
                r = true_rows(self._fft_rows(fft_tried, first), n_try)
                fft_tried[r] = True
                self._solve_own(r, None, m)
                by_fft, redone = by_fft + n_try, redone + carried[r].sum()
                found, facts = self._from_earlier(carry, m, tried, fft_tried)
                from_prev += found
        run.stats["neighbour_rescued_rows"] = run.stats.get("neighbour_rescued_rows", 0) + from_nb
        return from_prev, by_fft, redone

    def _fft_rows(self, fft_tried: torch.Tensor, first: bool,
                  now: torch.Tensor | None = None) -> torch.Tensor:
        """(B*N,) bool the lost rows not tried by FFT yet (``fft_tried``); ``first``: only
        each point's first lost target without a trusted one before it (``now``: the lost
        rows, :meth:`lost`, where the caller has them)."""
        b, n = self.b, self.n
        now = self.lost() if now is None else now
        lost = now & ~fft_tried
        if first:
            alone = lost.view(b, n) & ~self._trusted(now).view(b, n).cummax(0).values
            lost = (alone & (alone.cumsum(0) == 1)).reshape(-1)
        return lost

    def _facts(self, fft_tried: torch.Tensor) -> torch.Tensor:
        """(2 + B,) int64 of the rows as they stand, for :meth:`rescue` to read with other
        numbers: the lost rows not tried by FFT (:meth:`_fft_rows`), those FFT tries first,
        and per target whether its neighbours can help (a lost row and at least two trusted
        ones: :meth:`_rescue_from_neighbours`)."""
        b, n = self.b, self.n
        lost = self.lost()
        ok = self._trusted(lost)
        has = lost.view(b, n).any(1) & (ok.view(b, n).sum(1) >= 2)
        return torch.cat([torch.stack([self._fft_rows(fft_tried, False, lost).sum(),
                                       self._fft_rows(fft_tried, True, lost).sum()]),
                          has.long()])

    def _solve_own(self, rows: torch.Tensor, init: torch.Tensor | None, m: int | None,
                   near: torch.Tensor | None = None,
                   placed: tuple[Placement, list[int]] | None = None) -> None:
        """Rows ``rows`` solved again from ``init`` (None: FFT) with their own windows and
        subsets: from ``init``, placed as the block's carried rows are
        (:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.keep_outside`: a subset
        near the border moved inside, a shorter window where the point leaves the image
        within the run's, not solved where it has left: OUTSIDE where ``init`` predicts from
        the target before or the same one, ``near`` (R,) bool, default all, and along the
        run of rows predicted out after one, :func:`_outside_runs`); then at most half-width
        ``m`` (default the run's) and no longer than the row's :attr:`window_m` (also the
        point's measured motion, a point classical there): all of them in one solve and the
        classical rows in another
        (:meth:`~torch_stsdic.movie.block_windows.BlockWindows.solve_windows`; from FFT, one
        per half-width). The better result is kept. Without it a rescued row took the run's
        window and a centred subset wherever it started, and a point leaving the image
        failed again where a block's carry had placed it (32-target blocks lost rows that
        1-target blocks solve). ``placed``: the rows' placement made already, with its
        facts read (:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.
        place_outside`; None: placed here)."""
        if init is not None:
            full = torch.full((self.pts.shape[0], init.shape[1]), float("nan"),
                              dtype=init.dtype, device=init.device)
            full[rows] = init
            ask = torch.zeros(self.pts.shape[0], dtype=torch.bool, device=rows.device)
            ask[rows] = True
            close = ask.clone()  # the rows whose guess is as near as a carry's
            if near is not None:
                close[rows] = near
            out = (self.keep_outside((full,), ask, mark=False) if placed is None
                   else self.settle_outside(*placed, mark=False))
            self._outside_for_good(out, close)
            solved = ~out[rows]  # the rows still in view (grouped below: one read for both)
        else:
            solved = torch.ones_like(rows, dtype=torch.bool)
        self._solve_in_own_windows(rows, init, m, solved)

    def _solve_own_masked(self, go: torch.Tensor, init: torch.Tensor, near: torch.Tensor,
                          placed: Placement) -> None:
        """:meth:`_solve_own` of the rows ``go`` (B*N,) bool, every row at once, the others
        masked (no read of which): from ``init`` (B*N, P) (NaN off ``go``), ``near`` (B*N,)
        bool as there, their placement ``placed`` taken unread
        (:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.settle_unread`, its
        facts read with the block's next read; where the last block's carried start moved
        no subset, the guess "none moved" instead, no masked work); the run's window, no
        longer than the row's :attr:`window_m`."""
        if self.may_guess(PLACEMENT):  # the last block's carried rows moved no subset:
            # nor do the same points' rescued rows (guessed; the rows moved tell)
            self.defer(WAVE_PLACEMENT, placed.facts[:1])
            out = self.settle_outside(placed, [0, 1, 0], mark=False)
        else:
            out = self.settle_unread(placed, self._unread_capacity(start=False), mark=False,
                                     start=False)
        self._outside_for_good(out, go & near)
        self._solve_in_own_windows(torch.arange(go.numel(), device=go.device),
                                   init.nan_to_num(0.0), None, go & ~out)

    def _outside_for_good(self, out: torch.Tensor, close: torch.Tensor) -> None:
        """The rows of a rescue's placement predicted out of view, ``out`` (B*N,) bool, made
        OUTSIDE for good where :func:`_outside_runs` says so (``close`` (B*N,) bool: the
        rows whose guess is as near as a carry's)."""
        b, n = self.b, self.n
        left = (self.gone & (self.status == int(Status.OUTSIDE))).view(b, n)
        final = _outside_runs(out.view(b, n), close.view(b, n), left).reshape(-1)
        self.status.masked_fill_(final, int(Status.OUTSIDE))
        self.gone |= final

    def _solve_in_own_windows(self, rows: torch.Tensor, init: torch.Tensor | None,
                              m: int | None, pick: torch.Tensor) -> None:
        """Rows ``rows`` (R,) where ``pick`` (R,) bool solved from ``init`` (R, P) (None:
        FFT), each with at most half-width ``m`` (default the run's) and no longer than its
        :attr:`window_m` (:meth:`~torch_stsdic.movie.block_windows.BlockWindows.
        solve_windows` at the rescue's sites); the better result kept."""
        m_req = self.run.m if m is None else m
        own = torch.full((rows.numel(),), m_req, dtype=torch.int8, device=rows.device)
        if self.window_m is not None and m_req > 0:
            own = torch.minimum(own, self.window_m[rows])
        for r, mk, sol, where in self.solve_windows(rows, own, init, pick=pick,
                                                    sites=RESCUE_SITES):
            self.keep(r, sol, only_better=True, m=mk, where=where)

    def _trusted(self, lost: torch.Tensor) -> torch.Tensor:
        """(B*N,) bool: usable rows that are not ``lost`` (:meth:`lost`, read by the caller)."""
        return (self.status <= USABLE) & ~lost

    def _from_earlier(self, carry: Carry | None, m: int | None, tried: torch.Tensor,
                      fft_tried: torch.Tensor) -> tuple[int, list[int]]:
        """Step (1) of :meth:`rescue`: lost rows (target j, point i) started from the point's
        nearest earlier trusted target p of the block, its parameters with u, v moved on by
        its velocity over t_j - t_p (any j - p where that velocity is known, j - p = 1 where
        not), in waves while a wave finds rows to try; a row whose guess puts it out of view
        is OUTSIDE only from p = j - 1 (else it waits for a nearer p). ``tried``
        (B*N,) long: the target each row was last started from (-1: none), updated: a row
        is tried again only from a nearer target. Returns the rows tried and the facts of
        the rows as the waves leave them (:meth:`_facts` with ``fft_tried``, read with the
        last wave's numbers: one read a wave)."""
        b = self.b
        self.waves_read = None
        # the block's rescue (m None) may be guessed: no lost row, as in the last block (the
        # classical rescue's first read, after the model check, is then the block's one
        # read, the guesses' numbers with it)
        if b < 2:
            facts = self.ask(RESCUE, self._facts(fft_tried), 1, m is None)  # one read
            return 0, [0] * (b + 2) if facts is None else facts
        caps = self._unread_waves() if m is None else None
        if caps is not None:  # as many waves as the last block's, read later
            return self._waves_unread(carry, tried, fft_tried, caps), [0] * (b + 2)
        total, waves = 0, 0
        for wave in range(b):
            cand, fin, go, init, p = self._wave(carry, m, tried)
            numbers = [torch.stack([go.sum(), (cand & ~fin).sum()]), self._facts(fft_tried)]
            placed = None
            if self.places_at_once:  # the wave's rows placed near the border now, the
                # placement's facts read with the wave's (its solve reads none of its own)
                placed = self.place_outside(
                    (torch.where(go.unsqueeze(1), init, float("nan")),), go)
                numbers.append(placed.facts)
            # one read for the wave: the candidates with a guess, those without, and the
            # rows' facts (the caller's, where this wave is the last); the first wave's
            # answer (no candidate, no lost row) guessed where the rescue may be
            read = self.ask(RESCUE, torch.cat(numbers), 3, wave == 0 and m is None)
            if read is None:
                return 0, [0] * (b + 2)
            n_go, n_wait, *facts = read
            facts, placed_facts = facts[:b + 2], facts[b + 2:]
            if placed is not None:
                self._heard_facts(placed_facts)
            if not n_go + n_wait:
                break
            if m is None:  # (the block's rescue: the next block's capacities)
                self._learn(WAVE + str(wave), n_go)
            waves += 1
            tried.copy_(torch.where(cand, p, tried))
            if n_go:  # (a point predicted out of view from further back: tried later)
                go = true_rows(go, n_go)
                self._solve_own(go, init[go], m, near=self._near(p)[go],
                                placed=None if placed is None else (placed, placed_facts))
                total += n_go
                facts = None  # rows changed: the next wave's read tells
        if m is None and waves <= MAX_UNREAD_WAVES:
            self.waves_read = waves
        return total, (self.read(self._facts(fft_tried)) if facts is None else facts)

    def _wave(self, carry: Carry | None, m: int | None, tried: torch.Tensor
              ) -> tuple[torch.Tensor, ...]:
        """One wave of :meth:`_from_earlier` on the rows as they stand: (B*N,) bool the
        candidates (lost, a trusted target p before them not tried yet, within reach), those
        with a finite guess, the rows to solve (both), (B*N, P) every row's guess moved on
        from its p, and (B*N,) long that p (-1: none). No host read."""
        run, n, b = self.run, self.n, self.b
        names, dev = run.names, run.device
        iu, iv = names.index("u"), names.index("v")
        j_of = torch.arange(b, device=dev).repeat_interleave(n)  # (B*N,) each row's target
        i_of = torch.arange(n, device=dev).repeat(b)  # (B*N,) each row's point
        lost = self.lost()
        good = self._trusted(lost)
        # (B, N) the nearest trusted target strictly before each row's (-1: none)
        at = torch.where(good, j_of, -1).view(b, n).cummax(0).values
        p = torch.cat([at.new_full((1, n), -1), at[:-1]]).reshape(-1)
        pr = p.clamp(min=0) * n + i_of
        vel_u, vel_v, known = self._velocity_at(pr, carry)
        reach = torch.where(known, b, 1)
        cand = lost & (p >= 0) & (p > tried) & (j_of - p <= reach)
        # every row's guess (the candidates' taken below): moved on from target p
        init = self.params[pr]  # a copy
        d = (run.ts[self.k[j_of]] - run.ts[self.k[p.clamp(min=0)]]).to(run.dtype)
        init[:, iu] += vel_u * d
        init[:, iv] += vel_v * d
        if m == 0:
            init = init.nan_to_num(0.0)  # a classical row has no ut, vt
        else:
            for nm, vel in (("ut", vel_u), ("vt", vel_v)):  # a classical row: its
                if nm in names:                              # velocity
                    i = names.index(nm)
                    init[:, i] = torch.where(torch.isfinite(init[:, i]), init[:, i], vel)
        fin = torch.isfinite(init).all(1)
        return cand, fin, cand & fin, init, p

    def _near(self, p: torch.Tensor) -> torch.Tensor:
        """(B*N,) bool: the rows whose wave starts them from the target just before theirs
        (or their own; ``p`` (B*N,) :meth:`_wave`'s): their guess as near as a carry's."""
        j_of = torch.arange(self.b, device=p.device).repeat_interleave(self.n)
        return j_of - p <= 1

    def _wave_answer(self, cand: torch.Tensor, fin: torch.Tensor, go: torch.Tensor,
                     fft_tried: torch.Tensor) -> torch.Tensor:
        """(3,) int64 a wave's answer, all 0 where it has nothing to do: its rows to solve,
        its candidates without a guess, and the lost rows not tried by FFT (:meth:`_facts`'
        first)."""
        return torch.stack([go.sum(), (cand & ~fin).sum(),
                            self._fft_rows(fft_tried, False).sum()])

    def _unread_waves(self) -> list[int] | None:
        """The capacities of the rows of each wave of a block's rescue taken unread
        (:meth:`_waves_unread`): where this attempt guesses, the last block's rescue was not
        quiet but ended after as many waves as its last reading one (at most
        :data:`MAX_UNREAD_WAVES`, no row left for its neighbours or FFT), each wave's rows
        known, and the waves' placements may be taken unread; else None (read). A GPU's
        choice (:data:`~torch_stsdic.core.choices.GUESS_WAVES`)."""
        run = self.run
        waves = run.guesses.sizes.get(WAVES, -1)
        if (not guess_waves(run.device) or not self.guessing
                or run.guesses.quiet.get(RESCUE, True) or waves < 1
                or not self.places_at_once or self._unread_capacity(start=False) is None):
            return None
        caps = [self.learned_capacity(WAVE + str(w), self.pts.shape[0])
                for w in range(waves)]
        return None if None in caps else caps

    def _waves_unread(self, carry: Carry | None, tried: torch.Tensor,
                      fft_tried: torch.Tensor, caps: list[int]) -> torch.Tensor:
        """:meth:`_from_earlier`'s waves of the block's rescue without a read: ``caps``
        (:meth:`_unread_waves`) waves, each wave's rows (at most its capacity: the guess
        deferred) placed (:meth:`~torch_stsdic.movie.block_placement.BlockPlacement.
        settle_unread`) and solved masked over every row; then the guess that the next wave
        finds no row and no lost row is left untried by FFT (the numbers deferred: a wave
        that finds none changes nothing, so fewer waves than guessed give the reading way's
        rows; the first wave's answer heard for the next block's guess, as a reading
        rescue's). Returns the rows tried (a 0-d tensor)."""
        total = None
        for w, cap in enumerate(caps):
            cand, fin, go, init, p = self._wave(carry, None, tried)
            answer = self._wave_answer(cand, fin, go, fft_tried)
            self.defer_count(WAVE + str(w), answer[0], cap)
            if w == 0:  # the first wave's answer heard, as a reading rescue's (nothing to
                # do: the next block guesses so, not these waves)
                self.read_later(RESCUE, answer,
                                lambda values: self.heard(RESCUE, not any(values)))
            tried.copy_(torch.where(cand, p, tried))
            init = torch.where(go.unsqueeze(1), init, float("nan"))
            placed = self.place_outside((init,), go)
            self._solve_own_masked(go, init, self._near(p), placed)
            total = answer[0] if total is None else total + answer[0]
        cand, fin, go, _, _ = self._wave(carry, None, tried)
        self.defer(WAVES, self._wave_answer(cand, fin, go, fft_tried))
        return total

    def _velocity_at(self, rows: torch.Tensor, carry: Carry | None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(R,) velocity (u, v) of the block's rows ``rows`` and whether it is known: the
        measured ut, vt where there is one, else the finite difference to the row of the
        target before (at the block's first target the carried velocity, else the finite
        difference to the carry's last row; 0 and not known without a carry)."""
        run, n = self.run, self.n
        names = run.names
        iu, iv = names.index("u"), names.index("v")
        j = rows // n
        first = j == 0
        before = torch.where(first, rows, rows - n)
        span = (run.ts[self.k[j]] - run.ts[self.k[(j - 1).clamp(min=0)]]).to(run.dtype)
        span = torch.where(first, torch.ones_like(span), span)
        du = (self.params[rows, iu] - self.params[before, iu]) / span
        dv = (self.params[rows, iv] - self.params[before, iv]) / span
        if carry is not None:
            i = rows % n
            vk = carry.vel_known[i] if carry.vel_known is not None else torch.ones_like(first)
            # without a carried velocity: the finite difference to the carry's last row
            last = to_relative(dict(carry.vals), self.ref.acc)
            gap = (run.ts[self.ks[0]] - carry.t).to(run.dtype)
            fu = (self.params[rows, iu] - last["u"][i].to(du)) / gap
            fv = (self.params[rows, iv] - last["v"][i].to(dv)) / gap
            fd = carry.valid[i] & (gap > 0)
            du = torch.where(first, torch.where(vk, carry.vel_u[i].to(du), fu), du)
            dv = torch.where(first, torch.where(vk, carry.vel_v[i].to(dv), fv), dv)
            known = ~first | vk | fd
        else:
            du = torch.where(first, torch.zeros_like(du), du)
            dv = torch.where(first, torch.zeros_like(dv), dv)
            known = ~first
        known = known & torch.isfinite(du) & torch.isfinite(dv)
        if "ut" in names:
            mu, mv = self.params[rows, names.index("ut")], self.params[rows, names.index("vt")]
            window = torch.isfinite(mu) & torch.isfinite(mv)
            du = torch.where(window, mu, du)
            dv = torch.where(window, mv, dv)
            known = known | window
        return torch.nan_to_num(du), torch.nan_to_num(dv), known

    def _rescue_from_neighbours(self, m: int | None, has: list[int]) -> int:
        """Lost rows of every target solved again from their trusted grid neighbours'
        solutions at the same target (:func:`neighbour_guess`); the better result is kept.
        ``has`` (B,): the targets with a lost row and at least two trusted ones (read by the
        caller: :meth:`_facts`). Returns the rows tried."""
        b, n = self.b, self.n
        js = [j for j in range(b) if has[j]]
        if not js:
            return 0
        lost = self.lost()
        ok = self._trusted(lost)
        sel = torch.tensor(js, device=self.run.device)
        guess = neighbour_guess(self.params.view(b, n, -1)[sel], ok.view(b, n)[sel],
                                self.run.names, self.run.grid_neighbours(self.ref),
                                self.ref.points,  # (J, N, P); on a GPU no read of its own
                                every_row=not until_done(self.run.device))
        for nm in ("ut", "vt"):  # a classical neighbour has no velocity: none
            if nm in self.run.names:
                i = self.run.names.index(nm)
                guess[..., i] = guess[..., i].nan_to_num(0.0)
        rows = (sel[:, None] * n + torch.arange(n, device=sel.device)).reshape(-1)
        guess = guess.reshape(rows.numel(), -1)
        try_ = torch.nonzero(lost[rows] & torch.isfinite(guess).all(1)).flatten()
        r = rows[try_]
        if r.numel():
            self._solve_own(r, guess[try_], m)
        return r.numel()


def _outside_runs(out: torch.Tensor, near: torch.Tensor, left: torch.Tensor) -> torch.Tensor:
    """(B, N) bool: the rows predicted out of view (``out`` (B, N), targets along dim 0) that
    are OUTSIDE for good: from a guess of the target before or the same one (``near``), or
    where the point's row at the target before is OUTSIDE already (``left``) or becomes so
    here, along each run of consecutive ``out`` rows (no loop over the targets)."""
    b = out.shape[0]
    j = torch.arange(b, device=out.device).view(-1, 1).expand_as(out)
    before = torch.cat([torch.zeros_like(left[:1]), left[:-1]])  # OUTSIDE at j - 1
    start = out & (near | before)  # a run of OUTSIDE rows starts or goes on here
    last_start = torch.where(start, j, -1).cummax(0).values
    last_gap = torch.where(out, -1, j).cummax(0).values  # the last row not predicted out
    return out & (last_start > last_gap)
