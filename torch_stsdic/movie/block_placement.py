"""Subsets near the image border (:class:`BlockPlacement`, mixed into
:class:`torch_stsdic.movie.block.Block`): where a row's predicted motion takes its subset
out of view over its window, the subset is moved inside the image (an off-centre subset),
the row given the longest shorter window that stays in view, or the row left OUTSIDE."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch

from torch_stsdic.core.choices import masked_groups
from torch_stsdic.core.solver import subset_inside
from torch_stsdic.core.status import Status
from torch_stsdic.movie.block_guess import MISSED, PLACEMENT, SUBSETS_OFF
from torch_stsdic.movie.frames import true_rows

__all__ = ["BlockPlacement", "Placement", "OUTSIDE_MARGIN"]

#: px beyond the image border a carried prediction must put a subset before the row is
#: OUTSIDE without a solve
OUTSIDE_MARGIN = 2.0


class Placement(NamedTuple):
    """A placement of rows near the border (:meth:`BlockPlacement.place_outside`) before its
    facts are read: ``out`` (B*N,) bool the rows no window keeps in view, ``facts`` the 0-d
    facts stacked (None: read already) and ``placed`` (moved, centres, off)
    (:meth:`BlockPlacement._centre_facts`)."""

    out: torch.Tensor
    facts: torch.Tensor | None
    placed: tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class BlockPlacement:
    """The placement of a :class:`~torch_stsdic.movie.block.Block`'s subsets near the
    border (its run, reference, rows' points ``pts``, times ``dt``, statuses, ``centres``,
    ``window_m``, the reference subsets it keeps and its windows' motion)."""

    def keep_outside(self, inits: Sequence[torch.Tensor], carried: torch.Tensor,
                     mark: bool = True, guess: bool = False) -> torch.Tensor:
        """Carried rows near the image border. At every one of the predictions ``inits``
        ((B*N, P) relative parameters: the carry moved on by its velocity, and where it was
        last), over every frame of the row's window, the POI's predicted position is
        checked:

        * where, as predicted by the first (the carry moved on), the subset would come
          within ``OUTSIDE_MARGIN`` px of the border but the POI stays that far inside, the
          subset is moved inside the image by up to its half-size (an off-centre subset,
          :attr:`centres`; its solution is carried to the POI by its own gradients, the std
          with them): the point is measured while it is in view;
        * where that fails over the run's window but holds over a shorter one (the point
          leaves the image within the window), the row is solved with the longest such
          window (:attr:`window_m`);
        * where the POI is that close to the border, or beyond, by the first prediction even
          at the target frame alone, and the subset is by the others, the row is OUTSIDE,
          neither solved nor rescued: a specimen moving out of view (every rescue of such a
          point found some other peak inside the image, at low ZNCC, again in every block).

        Returns the (B*N,) bool mask of the OUTSIDE rows; without ``mark`` they are only
        returned, not marked (the caller decides which of them to give up on). ``guess``:
        where the last block's carried rows moved no subset, none is taken to move here,
        unread, nor a row left without a window in view
        (:meth:`~torch_stsdic.movie.block_guess.BlockGuesses.may_guess`)."""
        run = self.run
        if self.places_at_once:  # one read, of the facts of the placement made at once
            pending = self.place_outside(inits, carried)
            capacity = self._unread_capacity() if guess else None
            if capacity is not None:  # the last block's moved some: read later
                return self.settle_unread(pending, capacity, mark)
            # (guessed where the last block's moved none: the rows moved tell)
            facts = self.ask(PLACEMENT, pending.facts, 1, guess)
            if facts is not None:
                self._heard_facts(facts)
            return self.settle_outside(pending, [0, 1, 0] if facts is None else facts, mark)
        shift, left = self._run_window_fit(inits, carried)
        # one read: how many rows the run's window alone leaves (none where m = 0: no
        # shorter window), with the centres' facts as they stand (read again only where
        # shorter windows move some)
        n_left = left.sum() if run.m > 0 else left.new_zeros((), dtype=torch.int64)
        facts, placed = self._centre_facts(shift, left)
        capacity = self._unread_capacity() if guess and run.m == 0 else None
        if capacity is not None:  # (classical: no shorter window, none left to place)
            return self.settle_unread(Placement(left, torch.stack(facts), placed), capacity,
                                      mark)
        # (guessed where the last block's left none and moved none: those two tell)
        read = self.ask(PLACEMENT, torch.stack([n_left] + facts), 2, guess)
        if read is None:
            return self.settle_outside(Placement(left, None, placed), [0, 1, 0], mark)
        n_left, *facts = read
        self._heard_facts(facts)
        if n_left:  # every shorter window at once, the longest that stays in view
            self._shorter_windows_in_view(inits, left, shift, true_rows(left, n_left))
            facts, placed = self._centre_facts(shift, left)
            facts = self.read(torch.stack(facts))  # one read
        return self.settle_outside(Placement(left, None, placed), facts, mark)

    @property
    def places_at_once(self) -> bool:
        """Whether :meth:`keep_outside` places every row's shorter windows at once, masked,
        and reads once (a GPU's choice, :data:`~torch_stsdic.core.choices.MASKED_GROUPS`,
        where the block mixes window lengths): then :meth:`place_outside` makes a placement
        whose facts a caller may read with its own numbers."""
        run = self.run
        return run.m > 0 and self.mixes_windows and masked_groups(run.device)

    def place_outside(self, inits: Sequence[torch.Tensor], carried: torch.Tensor
                      ) -> Placement:
        """:meth:`keep_outside`'s placement with no host read (:attr:`places_at_once`):
        every carried row's shorter windows placed, those left taking theirs
        (:attr:`window_m` set at those rows), and the facts to read
        (:meth:`settle_outside` takes them)."""
        shift, left = self._run_window_fit(inits, carried)
        self._shorter_windows_in_view(inits, left, shift,
                                      torch.arange(carried.shape[0], device=carried.device))
        facts, placed = self._centre_facts(shift, left)
        return Placement(left, torch.stack(facts), placed)

    def _run_window_fit(self, inits: Sequence[torch.Tensor], carried: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``carried`` (B*N,) rows placed over the run's window (:meth:`_placement`):
        (B*N, 2) px the shift of each subset that fits (0 elsewhere) and (B*N,) bool the
        carried rows without a window of that length that stays in view."""
        fit, shift = self._placement(inits, self.dt, self.motion_of(self.run.m))
        fit &= carried
        return torch.where(fit.unsqueeze(1), shift, 0.0), carried & ~fit

    def settle_outside(self, placed: Placement, facts: list[int], mark: bool) -> torch.Tensor:
        """A placement's rows OUTSIDE marked (``mark``) and its moved subsets taken, given
        its ``facts`` read on the host (:meth:`_centre_facts`'s, in order). Returns the
        (B*N,) bool mask of the OUTSIDE rows."""
        run = self.run
        out = self._mark_outside(placed, mark)
        moved, centres, off = placed.placed
        n_moved, all_in, n_off, *n_miss = facts
        if n_moved:
            self.centres, self.centres_inside = centres, bool(all_in)
            self.off_count = int(n_off)
            if self.kept is not None:  # and the moved subsets' (no read: counted above)
                self.kept = run.solver.keep_reference_subsets(
                    self.ref.img, self.centres, missing=n_miss[0] if n_miss else None,
                    inside=bool(all_in) and run.point_facts(self.ref)[0])
            self._centres_moved(off, n_off, moved, n_moved)  # the shared motion there
            run.stats["off_centre_rows"] = run.stats.get("off_centre_rows", 0) + n_moved
        return out

    def _mark_outside(self, placed: Placement, mark: bool) -> torch.Tensor:
        """A placement's OUTSIDE rows (B*N,) bool, marked so (and gone) where ``mark``."""
        if mark:
            self.status.masked_fill_(placed.out, int(Status.OUTSIDE))
            self.gone |= placed.out
        return placed.out

    def _heard_facts(self, facts: list[int]) -> None:
        """A placement's facts read (:meth:`_centre_facts`'s), for the next block's guesses
        (:meth:`_unread_capacity`): whether every subset is inside the image and the
        reference subsets the cache missed."""
        self.heard(SUBSETS_OFF, facts[1] == 1)
        if len(facts) > 3:
            self._learn(MISSED, facts[3])

    def _unread_capacity(self, start: bool = True) -> int | None:
        """Whether this attempt places its rows without reading the facts
        (:meth:`settle_unread`): it guesses, the last placement read found every subset
        inside the image and, at the carried ``start``, the last block's placement moved
        subsets (else the guess "none moved" is taken, :meth:`keep_outside`); then the
        reference subsets the solver's cache may miss, at most (0: it keeps none), else
        None (the facts read)."""
        quiet = self.run.guesses.quiet
        if (not self.guessing or (start and quiet.get(PLACEMENT, True))
                or not quiet.get(SUBSETS_OFF, False)):
            return None
        if self.kept is None:
            return 0
        return self.learned_capacity(MISSED, self.pts.shape[0])

    def settle_unread(self, placed: Placement, capacity: int, mark: bool, start: bool = True
                      ) -> torch.Tensor:
        """:meth:`settle_outside` of a placement whose facts are not read
        (:meth:`_unread_capacity`'s guess): every subset taken inside the image (its centre
        clamped there: no change where that holds), the moved rows' motion over every row,
        masked (:meth:`~torch_stsdic.movie.block_motion.BlockMotion._centres_moved_masked`),
        at most ``capacity`` reference subsets added to the solver's cache; these guesses
        and the facts (the rows moved and off their POIs: the counters, :attr:`off_count`)
        read with the block's next read (the rows moved the next block's guess where this is
        the carried ``start``). Returns the (B*N,) bool mask of the OUTSIDE rows."""
        run = self.run
        out = self._mark_outside(placed, mark)
        moved, centres, off = placed.placed
        n_moved, all_in, n_off, *n_miss = placed.facts.unbind()
        half = float(run.solver.window.half)
        h, w = self.ref.img.height, self.ref.img.width
        self.centres = torch.stack([centres[:, 0].clamp(half, w - 1 - half),
                                    centres[:, 1].clamp(half, h - 1 - half)], 1)
        self.centres_inside = True
        self.defer(SUBSETS_OFF, 1 - all_in)
        if self.kept is not None:
            cache = run.solver.reference_cache
            self.kept = run.solver.keep_reference_subsets(
                self.ref.img, self.centres, inside=run.point_facts(self.ref)[0],
                capacity=capacity)
            self.defer_count(MISSED, n_miss[0], capacity,
                             then=lambda v: cache.drop_padding(v[0]))
        self._centres_moved_masked(off, moved)
        self.off_count = None  # (read with the facts)
        self.read_later(PLACEMENT, torch.stack([n_moved, n_off]),
                        lambda facts: self._placed_read(facts, start))
        return out

    def _placed_read(self, facts: list[int], start: bool) -> None:
        """:meth:`settle_unread`'s facts read (in order with the block's other placements:
        before those read with the same read): the rows moved (counted; the next block's
        guess where this was the carried ``start``) and those off their POIs
        (:attr:`off_count`)."""
        n_moved, n_off = facts
        if start:
            self.heard(PLACEMENT, n_moved == 0)
        self.run.stats["off_centre_rows"] = self.run.stats.get("off_centre_rows", 0) + n_moved
        self.off_count = n_off

    def _shorter_windows_in_view(self, inits: Sequence[torch.Tensor], left: torch.Tensor,
                                 shift: torch.Tensor, idx: torch.Tensor) -> None:
        """:meth:`keep_outside`'s rows ``left`` (B*N,) bool (no window of the run's length
        stays in view) among ``idx`` (R,) given the longest shorter window that does
        (:attr:`window_m`; no test: unused, it is the run's m) and its subset's shift
        (``shift`` (B*N, 2) px), every shorter window placed at once; ``left`` keeps those
        with none. In place."""
        run, rows = self.run, left.shape[0]
        halves = torch.arange(run.m - 1, -1, -1, device=run.device)  # (H,) descending
        f_h, d_h = self._placement([init[idx] for init in inits],
                                   *self.padded_windows(idx, run.m), idx)  # (H, R)
        j = f_h.to(torch.int8).argmax(0)  # the first that fits: the longest
        f_i = f_h.any(0) & left[idx]
        d_i = d_h[j, torch.arange(idx.numel(), device=run.device)]
        shift[idx] = torch.where(f_i.unsqueeze(1), d_i, shift[idx])
        if self.window_m is None:
            self.window_m = torch.full((rows,), run.m, dtype=torch.int8, device=run.device)
        half = halves[j].to(torch.int8)
        if self.window_cap is not None:  # (the point's motion's limit: a shorter one still)
            half = torch.minimum(half, self.window_cap[idx])
        self.window_m[idx] = torch.where(f_i, half, self.window_m[idx])
        left[idx] = left[idx] & ~f_i

    def _centre_facts(self, shift: torch.Tensor, out: torch.Tensor
                      ) -> tuple[list[torch.Tensor], tuple[torch.Tensor, ...]]:
        """The subsets moved by ``shift`` (B*N, 2) px but at the OUTSIDE rows ``out``: 0-d
        tensors to read (the rows moved, whether every subset is inside, the rows off their
        POIs, and the reference subsets the solver's cache misses at the centres, where it
        keeps them) and (B*N,) bool moved, (B*N, 2) centres, (B*N,) bool off their POIs."""
        run = self.run
        moved = (shift != 0).any(1) & ~out
        # whole px, away from the border, in the points' dtype (a guess in float64, a
        # neighbour rescue's, made float64 centres: the block's later solves then ran in
        # float64 and without the reference cache's subsets, a read a batch)
        whole = (torch.sign(shift) * shift.abs().ceil()).to(self.pts.dtype)
        # rows moved by an earlier call (the block's carry, then its rescue) keep theirs
        base = self.pts if self.centres is None else self.centres
        centres = torch.where(moved.unsqueeze(1), self.pts + whole, base)
        off = (centres != self.pts).any(1)
        inside = subset_inside(centres, float(run.solver.window.half), self.ref.img.height,
                               self.ref.img.width).all()
        miss = (None if self.kept is None
                else run.solver.missing_reference_subsets(self.ref.img, centres))
        facts = [moved.sum(), inside.long(), off.sum()] + ([] if miss is None else [miss])
        return facts, (moved, centres, off)

    def _placement(self, inits: Sequence[torch.Tensor], dt: torch.Tensor,
                   motion: torch.Tensor | None, rows: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., R) bool: the row's subset can be placed in view over its window (frame
        times ``dt`` (..., R, T), known motion ``motion`` (..., R, T, 2) or None; leading
        dimensions: windows of several lengths at once) by one of the predictions ``inits``
        ((R, P) each; :meth:`keep_outside`), and (..., R, 2) px the shift of its centre that
        this takes (the largest over the predictions that fit); the rows ``rows`` (R,) of
        the block (None: all of them, R = B*N)."""
        run = self.run
        names = run.names
        iu, iv = names.index("u"), names.index("v")
        half = float(run.solver.window.half)
        h, w = self.ref.img.height, self.ref.img.width
        pts = self.pts if rows is None else self.pts[rows]
        # every prediction and both components at once: (I, R, T, 2)
        lo_edge = half + OUTSIDE_MARGIN
        hi_edge = torch.full((2,), w - 1 - half - OUTSIDE_MARGIN, dtype=pts.dtype,
                             device=pts.device)  # (filled on the device: no copy to it)
        hi_edge[1] = h - 1 - half - OUTSIDE_MARGIN
        lead = dt.dim() - 2  # the window lengths' dimensions
        p = torch.stack(list(inits))  # (I, R, P)
        p = p.view(p.shape[0], *([1] * lead), *p.shape[1:])  # (I, ..., R, P)
        z = pts.unsqueeze(1) + p[..., [iu, iv]].unsqueeze(-2)  # (I, ..., R, 1, 2)
        if "ut" in names:
            vel = p[..., [names.index("ut"), names.index("vt")]].nan_to_num(0.0)
            z = z + vel.unsqueeze(-2) * dt.unsqueeze(-1)  # (I, R, T, 2)
        if motion is not None:
            z = z + motion
        # only the moved-on prediction (the first) moves a subset
        reach = torch.zeros(p.shape[0], *([1] * (lead + 2)), dtype=z.dtype, device=z.device)
        reach[0] = half
        lo = (lo_edge - z.amin(-2)).clamp(min=0)  # (I, R, 2) move the subset in
        hi = (z.amax(-2) - hi_edge).clamp(min=0)
        ok = ((lo == 0) | (hi == 0)) & (torch.maximum(lo, hi) <= reach)
        fit = ok.all(-1) & torch.isfinite(z).all(-2).all(-1)  # (I, R)
        d = lo - hi
        shift = torch.zeros_like(d[0])  # the largest shift over the predictions that fit
        for i in range(p.shape[0]):
            shift = torch.where(fit[i].unsqueeze(-1) & (d[i].abs() > shift.abs()), d[i], shift)
        feasible = fit.any(0)
        return feasible, shift
