"""A block's windows (:class:`BlockWindows`, mixed into
:class:`torch_stsdic.movie.block.Block`): every target's window of each half-width, its
frames' planes and times per row, and the solves of rows whose windows differ in length,
in one call where the solver takes windows of mixed length
(:meth:`~torch_stsdic.core.solver.SubsetSolver.mixed_windows`)."""

from __future__ import annotations

import torch

from torch_stsdic.core.choices import masked_groups
from torch_stsdic.core.solver import WindowSolution
from torch_stsdic.movie.frames import grouped_rows, rows_by_half_width, window_frames

__all__ = ["BlockWindows"]


class BlockWindows:
    """The windows of a :class:`~torch_stsdic.movie.block.Block` (its run, targets ``k``,
    frames ``needed`` and their ``planes``, ``n`` points, ``solve``). State: per half-width
    the targets' windows, their columns and times, and those per row; the padded table of
    every half-width's columns and times (:meth:`mixed_rows`)."""

    def _init_windows(self) -> None:
        self._win: dict[int, torch.Tensor] = {}  # :meth:`windows`
        self._cols: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # :meth:`window_columns`
        self._rows: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # :meth:`window_rows`
        self._table: tuple[torch.Tensor, torch.Tensor] | None = None  # :meth:`_window_table`
        self._mixes: bool | None = None  # :attr:`mixes_windows`

    def windows(self, m: int) -> torch.Tensor:
        """(B, 2m+1) series frames of every target's window, shifted (not shrunk) at the
        ends of the series (made once a block and half-width: read, not written)."""
        if m not in self._win:
            seg = self.run.segments
            self._win[m] = window_frames(self.k, m, self.run.n_series,
                                         None if seg is None else seg.to(self.k.device))
        return self._win[m]

    def window_columns(self, m: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Per target, the windows of half-width ``m``: (B, T) their frames' columns among
        :attr:`needed` and (B, T) their times minus the target's (made once a block and
        half-width: read, not written)."""
        if m not in self._cols:
            run, win = self.run, self.windows(m)
            self._cols[m] = (torch.searchsorted(self.needed, win),
                             (run.ts[win] - run.ts[self.k].unsqueeze(1)).to(run.dtype))
        return self._cols[m]

    def window_rows(self, m: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Per row, the windows of half-width ``m``: (B*N, T) the planes of the block's
        frame stack and (B*N, T) dt (:meth:`window_columns` for every point; made once a
        block and half-width: read, not written)."""
        if m not in self._rows:
            cols, dt = self.window_columns(m)
            self._rows[m] = (self.planes[cols].repeat_interleave(self.n, 0),
                             dt.repeat_interleave(self.n, 0))
        return self._rows[m]

    def _window_table(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, B, T) every half-width h = 1 .. M's windows (:meth:`window_columns`) as
        columns of :attr:`needed` and times, padded to T = 2M + 1 columns (the first column,
        time 0: the solver reads only a row's first 2h + 1). Made once a block."""
        if self._table is None:
            run = self.run
            t = 2 * run.m + 1
            cols, dts = [], []
            for h in range(1, run.m + 1):
                c, d = self.window_columns(h)
                pad = t - c.shape[1]
                cols.append(torch.cat([c, c[:, :1].expand(-1, pad)], 1))
                dts.append(torch.cat([d, d.new_zeros(d.shape[0], pad)], 1))
            self._table = (torch.stack(cols), torch.stack(dts))
        return self._table

    def padded_windows(self, idx: torch.Tensor, top: int
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The rows ``idx`` (R,)'s windows of every half-width ``top - 1`` down to 0 at once,
        padded to T = 2 top - 1 frames by repeating their last (so a window's extremes over
        its frames are its own): times (H, R, T) and the shared motion's known part
        (H, R, T, 2) (:meth:`motion_of`; None without shared motion)."""
        t = 2 * top - 1
        b = torch.div(idx, self.n, rounding_mode="floor")
        times, motion = [], []
        for h in range(top - 1, -1, -1):
            _, d = self.window_columns(h)
            d = d[b]  # (R, 2h+1)
            times.append(torch.cat([d, d[:, -1:].expand(-1, t - d.shape[1])], 1))
            o = self.motion_of(h)
            if o is not None or h == 0:
                o = d.new_zeros(idx.numel(), 1, 2) if o is None else o[idx]
                motion.append(torch.cat([o, o[:, -1:].expand(-1, t - o.shape[1], -1)], 1))
        return torch.stack(times), (torch.stack(motion) if len(motion) == len(times)
                                    else None)

    def mixed_rows(self, idx: torch.Tensor, m: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rows ``idx`` (R,) with windows of half-widths ``m`` (R,) (1 .. the run's m): their
        planes of the block's frame stack (R, T) and times (R, T), T = 2M + 1, each row's
        first 2m + 1 columns its window (the rest padding), and that count (R,) int64."""
        cols, dts = self._window_table()
        h = m.long() - 1
        b = torch.div(idx, self.n, rounding_mode="floor")
        return self.planes[cols[h, b]], dts[h, b], 2 * m.long() + 1

    def solve_windows(self, rows: torch.Tensor, m_of: torch.Tensor,
                      init: torch.Tensor | None, pick: torch.Tensor | None = None,
                      sites: tuple[str, str] = ("classical", "windows")
                      ) -> list[tuple[torch.Tensor, int | torch.Tensor | None, WindowSolution,
                                      torch.Tensor | None]]:
        """Solve the rows ``rows`` (R,) (where ``pick`` (R,) bool, default all) from ``init``
        (R, P) (None: FFT), each with its window of half-width ``m_of`` (R,) (clamped to
        0 .. the run's m). Returns ``(rows solved, their half-width, solution, where)`` per
        solve, for the caller to keep (the half-width an int, None for the run's, or (R_s,)
        per row; ``where`` (R_s,) bool the rows of the solve that count, None: all). Where
        the solver takes windows of mixed length and there is a guess, the classical rows
        (m = 0) in one solve and all others in one more: each group's rows alone, their
        counts read first (one host read), or on a GPU each solve over all the ``rows``,
        the others masked (:data:`~torch_stsdic.core.choices.MASKED_GROUPS`: no read);
        otherwise one solve per half-width (:func:`rows_by_half_width`, one read), but a
        classical run's rows from a guess on a GPU: one solve of every row, the others
        masked (no read). ``sites``: the masked solves' (classical, windows) names
        (:meth:`~torch_stsdic.movie.block_guess.BlockGuesses.compact`)."""
        run = self.run
        pick = torch.ones_like(rows, dtype=torch.bool) if pick is None else pick
        out = []
        if init is not None and run.m == 0 and masked_groups(run.device):
            # one half-width (a classical run's rows from their guesses): every row in one
            # solve, those not picked masked (no read)
            return [(rows, None, self.solve_masked(rows, init, pick, site="classical rows"),
                     pick)]
        if init is None or run.m == 0 or not self.mixes_windows:
            for mm, sel in rows_by_half_width(m_of, pick, run.m):
                mk = None if mm == run.m else mm
                sol = self.solve(rows[sel], None if init is None else init[sel], m=mk)
                out.append((rows[sel], mk, sol, None))
            return out
        m_of = m_of.clamp(0, run.m)
        key = torch.where(pick, (m_of > 0).long(), 2)  # classical, a window, not solved
        if masked_groups(run.device):  # every row in both solves, the others masked
            windows = torch.where(key == 1, m_of, run.m).to(torch.int8)
            for window, mm in enumerate((0, windows)):
                where = key == window
                out.append((rows, mm, self.solve(rows, init, m=mm, active=where,
                                                 site=sites[window]),
                            where))
            return out
        counts = torch.bincount(key, minlength=3)[:2].tolist()
        for window, sel in enumerate(grouped_rows(key, counts)):
            if sel.numel():
                mm = m_of[sel].to(torch.int8) if window else 0
                out.append((rows[sel], mm, self.solve(rows[sel], init[sel], m=mm), None))
        return out

    @property
    def mixes_windows(self) -> bool:
        """The run's solver takes windows of mixed length in one call (the run's shape)."""
        if self._mixes is None:
            self._mixes = self.run.solver.mixed_windows(self.run.solver.shape)
        return self._mixes
