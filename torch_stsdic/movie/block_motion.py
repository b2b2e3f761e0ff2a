"""The shared motion in a block's windows (:class:`BlockMotion`, mixed into
:class:`torch_stsdic.movie.block.Block`): every row's known motion over its window's frames,
at its subset's centre, computed once a block for each half-width and updated only at the
rows whose subsets :meth:`~torch_stsdic.movie.block_placement.BlockPlacement.keep_outside` moves."""

from __future__ import annotations

import torch

from torch_stsdic.core.shared_motion import window_offsets
from torch_stsdic.movie.frames import true_rows

__all__ = ["BlockMotion"]


class BlockMotion:
    """The shared motion of a :class:`~torch_stsdic.movie.block.Block`'s windows (its run,
    targets ``k``, frames ``needed``, points ``pts`` and ``centres``, and its
    ``window_columns``). State: the motion at
    the POIs in every needed frame, that at the off-centre subsets' centres, and each
    half-width's window offsets and slopes."""

    def _init_motion(self) -> None:
        self._motion: dict[int, torch.Tensor] = {}  # m -> (B*N, 2m+1, 2)
        self._slope: dict[int, torch.Tensor] = {}  # m -> (B*N, 2)
        self._shared_g: torch.Tensor | None = None  # (N, F, 2) at the POIs, needed frames
        #: (M,) rows whose subsets are off their POIs and (M, F, 2) the motion at their
        #: centres in the needed frames (None: every subset at its POI)
        self._off: tuple[torch.Tensor, torch.Tensor] | None = None

    def motion_of(self, m: int) -> torch.Tensor | None:
        """(B*N, 2m+1, 2) the shared motion's known part of every row's window frames
        (:func:`~torch_stsdic.core.shared_motion.window_offsets`) at the row's subset centre,
        or None (no shared motion, or m = 0)."""
        run = self.run
        if run.shared is None or m == 0:
            return None
        if m not in self._motion:
            o, slope = self._window_motion(m, None)
            self._motion[m], self._slope[m] = o, slope
        return self._motion[m]

    def mixed_motion(self, idx: torch.Tensor, m: torch.Tensor) -> torch.Tensor | None:
        """(R, 2M+1, 2) :meth:`motion_of` the rows ``idx`` (R,) with windows of half-widths
        ``m`` (R,) (1 .. the run's M), each row's in its first 2m + 1 columns (the rest 0,
        padding: :meth:`~torch_stsdic.movie.block_windows.BlockWindows.mixed_rows`), or
        None (no shared motion)."""
        run = self.run
        if run.shared is None:
            return None
        out = None
        for h in range(1, run.m + 1):  # each half-width's rows take theirs (no host read)
            o = self.motion_of(h)[idx]  # (R, 2h+1, 2)
            if out is None:
                out = o.new_zeros(idx.numel(), 2 * run.m + 1, 2)
            part = out[:, :2 * h + 1]
            part.copy_(torch.where((m == h).view(-1, 1, 1), o, part))
        return out

    def shared_slope(self, m: int) -> torch.Tensor | None:
        """(B*N, 2) px per time unit: the shared motion's least-squares slope over every
        row's window of half-width ``m`` (the part of the window's ut, vt it makes), or None
        (no shared motion, or m = 0)."""
        if self.motion_of(m) is None:
            return None
        return self._slope[m]

    def _window_motion(self, m: int, rows: torch.Tensor | None,
                       at_rows: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Window offsets (R, 2m+1, 2) and slopes (R, 2) of half-width ``m`` at the rows
        ``rows`` (R,) (None: all B*N), each at its subset's centre (``at_rows`` (R, F, 2):
        the shared motion there in the needed frames, where the caller has it). A row's
        numbers do not depend on which other rows are computed with it."""
        n = self.n
        cols, dt = self.window_columns(m)  # (B, T) the needed frames' columns, times
        b, t = cols.shape
        if rows is not None:  # only these rows, at their subsets' centres
            g = self._motion_at(rows) if at_rows is None else at_rows  # (R, F, 2)
            g = g[torch.arange(rows.numel(), device=g.device).unsqueeze(1), cols[rows // n]]
            return window_offsets(g, dt[rows // n], return_slope=True)
        g = self._pois_motion()[:, cols].permute(1, 0, 2, 3)  # (B, N, T, 2)
        if self._off is not None:  # off-centre subsets: the motion at their centres
            at, off_g = self._off
            g = g.reshape(-1, t, 2)  # (a copy: g is a permuted gather)
            g[at] = off_g[torch.arange(at.numel(), device=at.device).unsqueeze(1),
                          cols[at // n]]
            g = g.view(b, n, t, 2)
        # dt (B, 1, T): the same for all the target's points
        o, slope = window_offsets(g, dt.unsqueeze(1), return_slope=True)
        return o.reshape(-1, t, 2).contiguous(), slope.reshape(-1, 2)

    def _pois_motion(self) -> torch.Tensor:
        """(N, F, 2) the shared motion at the POIs in the block's needed frames (once)."""
        if self._shared_g is None:
            run = self.run
            self._shared_g = run.shared.displacement(self.ref.points, self.needed).to(
                run.dtype).transpose(0, 1)
        return self._shared_g

    def _motion_at(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, F, 2) the shared motion at the subset centres of ``rows`` (R,) in the block's
        needed frames."""
        run = self.run
        return run.shared.displacement(self.centres[rows], self.needed).to(
            run.dtype).transpose(0, 1)

    def _centres_moved(self, off: torch.Tensor, n_off: int, moved: torch.Tensor,
                       n_moved: int) -> None:
        """The subsets' :attr:`centres` changed at the rows ``moved`` (B*N,) bool
        (``n_moved`` of them, read by the caller); ``off`` (B*N,) bool the rows now off
        their POIs (``n_off``): the motion at those centres kept, the cached windows'
        offsets and slopes computed again at the moved rows only. No host read."""
        run = self.run
        if run.shared is None:
            return
        # the rows ascending without an index read (the counts known)
        at = true_rows(off, n_off)
        self._off = (at, run.shared.displacement(self.centres[at], self.needed).to(
            run.dtype).transpose(0, 1))
        if not self._motion:
            return
        rows = true_rows(moved, n_moved)
        at_rows = self._motion_at(rows)  # once for every half-width
        for m in list(self._motion):  # new tensors: a caller may hold the old ones
            o, slope = self._window_motion(m, rows, at_rows)
            self._motion[m] = self._motion[m].index_put((rows,), o)
            self._slope[m] = self._slope[m].index_put((rows,), slope)

    def _centres_moved_masked(self, off: torch.Tensor, moved: torch.Tensor) -> None:
        """:meth:`_centres_moved` without the counts (not read yet): the motion at every
        row's subset centre, taken at the rows ``off`` (B*N,) bool, the windows' offsets and
        slopes computed again at every row and taken at the rows ``moved`` (B*N,) bool. The
        same numbers (a row's do not depend on the rows computed with it); no host read."""
        run = self.run
        if run.shared is None:
            return
        every = torch.arange(off.numel(), device=off.device)
        at_all = self._motion_at(every)  # (B*N, F, 2)
        pois = self._pois_motion().repeat(off.numel() // self.n, 1, 1)
        self._off = (every, torch.where(off.view(-1, 1, 1), at_all, pois))
        for m in list(self._motion):  # new tensors: a caller may hold the old ones
            o, slope = self._window_motion(m, every, at_all)
            self._motion[m] = torch.where(moved.view(-1, 1, 1), o, self._motion[m])
            self._slope[m] = torch.where(moved.view(-1, 1), slope, self._slope[m])
