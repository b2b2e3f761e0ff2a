"""Where the rows of a run go: memory, or an HDF5 file written as the run goes.

A sink receives the result rows of a :class:`~torch_stsdic.movie.plan.RunPlan` block by block
(:meth:`MemorySink.write_rows`), can give back rows finished by an earlier, interrupted run
(:meth:`completed_rows`, :meth:`read_rows`), completes the output when the run ends
(:meth:`finish`: a smoothed run's strains) and builds the
:class:`~torch_stsdic.analysis.result.TrackResult`. An HDF5 file gets every block's strain
fields with the block, and its sink holds nothing of size frames x points: a long movie's
run needs the memory of a short one. The HDF5 layout itself is
:mod:`torch_stsdic.io.results`'s business; :class:`HDF5Sink` is the only writer of it, so
``track(out=...)``, the distributed runner and ``stsdic run`` write the same file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.analysis.stored_result import StoredTrackResult, lazy_fields
from torch_stsdic.analysis.strain import compute_strain
from torch_stsdic.core.shared_motion import PARAM_NAMES, PARAM_UNITS
from torch_stsdic.core.status import Status
from torch_stsdic.io.results import STRAIN_FIELDS, ResultWriter, as_stored
from torch_stsdic.movie.plan import RunPlan

__all__ = ["MemorySink", "HDF5Sink", "open_sink", "SMOOTHED", "row_counts"]

#: rows whose strains a smoothed run computes at a time (:meth:`HDF5Sink.finish`)
STRAIN_ROWS = 64

#: fields that ``smoothing`` replaces (the file keeps the raw ones and adds ``<name>_smooth``)
SMOOTHED = ("u", "v", "ut", "vt")


class MemorySink:
    """Keeps the (F, N) rows of a run in memory (numpy, full precision).

    ``keep``: the fields to hold (default every field of the plan): a sub-run that needs
    only a few (the shared motion's measuring pass) holds those alone, at the plan's
    precision (float32 values of a float32 run are held exactly in float32); the others
    read NaN (status NOT_COMPUTED, iterations 0, m -1) in its :meth:`result`, taking no
    memory. ``at_rows`` (names, rows): fields held only at those rows (:attr:`sparse`).
    ``pair`` (two kept fields, e.g. ("u", "v")): held side by side in one (F, N, 2) array
    (:attr:`paired`; ``values`` holds its two views), which a fit over both reads without a
    copy (the shared-motion pass)."""

    path: str | None = None

    def __init__(self, plan: RunPlan, keep: Sequence[str] | None = None,
                 at_rows: tuple[Sequence[str], np.ndarray] | None = None,
                 pair: tuple[str, str] | None = None) -> None:
        self.plan = plan
        self.values: dict[str, np.ndarray] = {}
        #: (F, N, 2) the ``pair`` fields side by side (None: no pair)
        self.paired: np.ndarray | None = None
        #: ``at_rows`` (names, rows): fields held only at those rows (sorted), (R, N) each,
        #: in ``sparse`` (not in the result, which reads them NaN)
        self.sparse: dict[str, np.ndarray] = {}
        self.sparse_rows = np.zeros(0, dtype=np.int64)
        self._pos = np.full(plan.n_rows, -1, dtype=np.int64)
        if at_rows is not None:
            self.sparse_rows = np.asarray(at_rows[1], dtype=np.int64)
            self._pos[self.sparse_rows] = np.arange(len(self.sparse_rows))
            real = np.float32 if plan.dtype == torch.float32 else np.float64
            self.sparse = {nm: np.full((len(self.sparse_rows), plan.n_points), np.nan,
                                       dtype=real) for nm in at_rows[0]}
        self.reference_frames = np.full(plan.n_rows, plan.reference_frame, dtype=np.int64)
        self.raw: dict[str, np.ndarray] = {}
        #: per status code, the rows written or replayed; per window half-width, the
        #: usable rows (``row_counts``: a run's summary without its (F, N) fields)
        self.status_counts = np.zeros(256, dtype=np.int64)
        self.m_counts = np.zeros(256, dtype=np.int64)
        self._allocate(keep, pair)

    def _allocate(self, keep: Sequence[str] | None, pair: tuple[str, str] | None = None
                  ) -> None:
        """The (F, N) arrays of the fields held (``keep``; None: all), the ``pair`` as views
        of one (F, N, 2) array."""
        plan = self.plan
        f, n = plan.n_rows, plan.n_points
        names = (*plan.fields, "status", "iterations", "m") if keep is None else tuple(keep)
        real = np.float64 if keep is None or plan.dtype == torch.float64 else np.float32
        fills = {"status": (int(Status.NOT_COMPUTED), np.int8), "iterations": (0, np.int64),
                 "m": (-1, np.int8)}
        if pair is not None and set(pair) <= set(names) and not set(pair) & set(fills):
            self.paired = np.full((f, n, 2), np.nan, dtype=real)
            self.values[pair[0]], self.values[pair[1]] = self.paired[..., 0], self.paired[..., 1]
        for nm in dict.fromkeys(names):
            if nm not in self.values:
                fill, dt = fills.get(nm, (np.nan, real))
                self.values[nm] = np.full((f, n), fill, dtype=dt)

    def row_counts(self) -> dict[str, dict[str, int]]:
        """The rows held by status code and the usable rows by window half-width m
        (``info["row_counts"]``): what a summary needs, without the (F, N) fields."""
        return {"status": {str(i - 128): int(c) for i, c in enumerate(self.status_counts) if c},
                "m_usable": {str(i - 128): int(c) for i, c in enumerate(self.m_counts) if c}}

    def _count(self, stored: dict[str, np.ndarray]) -> None:
        """Add the rows ``stored`` (a block written or replayed) to :meth:`row_counts`."""
        st = np.asarray(stored["status"]).astype(np.int64).ravel()
        self.status_counts += np.bincount(st + 128, minlength=256)[:256]
        if "m" in stored:
            m = np.asarray(stored["m"]).astype(np.int64).ravel()[st <= int(Status.MAX_ITER)]
            self.m_counts += np.bincount(m + 128, minlength=256)[:256]

    def completed_rows(self) -> set[int]:
        """Rows finished by an earlier run (none in memory)."""
        return set()

    def read_rows(self, rows: Sequence[int]) -> dict[str, np.ndarray]:
        """The stored values of consecutive finished rows ``rows``."""
        out = {nm: a[rows[0] : rows[-1] + 1] for nm, a in self.values.items()}
        self._count(out)
        return out

    def write_rows(self, rows: Sequence[int], values: dict[str, np.ndarray],
                   reference_frame: int | None = None) -> None:
        """Store rows ``rows`` (k,) of every field, each (k, N)."""
        self._count(self._keep(rows, values))
        if reference_frame is not None:
            self.reference_frames[list(rows)] = reference_frame

    def _keep(self, rows: Sequence[int], values: dict[str, np.ndarray]
              ) -> dict[str, np.ndarray]:
        """Hold rows ``rows`` of the fields kept; returns the rows as held."""
        for nm, a in self.values.items():
            a[list(rows)] = values[nm]
        if self.sparse:
            pos = self._pos[np.asarray(rows, dtype=np.int64)]
            at = pos >= 0
            for nm, a in self.sparse.items():
                a[pos[at]] = np.asarray(values[nm])[at]
        return values

    def field_values(self, name: str) -> np.ndarray:
        """(F, N) every row of field ``name`` (for a step over the whole result: the
        smoothing in time)."""
        return self.values[name]

    def write_smoothed(self, values: dict[str, np.ndarray]) -> None:
        """The temporally smoothed u, v, ut, vt (F, N) replace the result's fields (the raw
        ones stay in ``raw``)."""
        self.raw = {nm: self.field_values(nm).copy() for nm in ("u", "v")}
        for nm in SMOOTHED:
            self.values[nm] = np.asarray(values[nm], dtype=np.float64)

    def finish(self, result: TrackResult) -> None:
        """Complete the output once every row is written (nothing to do in memory)."""

    def close(self, commit: bool = True) -> None:
        """Release the output (``commit`` False after an error or interruption)."""

    def write_shared_motion(self, shared: Any) -> None:
        """Record the run's shared motion (:class:`~torch_stsdic.core.shared_motion.SharedMotion`)
        as soon as it is measured (memory: kept in the result's info only)."""

    def write_series_reference(self, template: Any) -> None:
        """Record the template the run measured against
        (:class:`~torch_stsdic.movie.series_reference.SeriesReference`; memory: kept in the
        result's info only)."""

    def write_run_estimates(self, arrays: dict[str, np.ndarray], meta: str) -> None:
        """Record what a resumed run needs of the run-level estimates besides the shared
        motion and the template (:func:`~torch_stsdic.movie.estimates.record_estimates`):
        ``arrays`` by their paths, ``meta`` their description, JSON (memory: nothing)."""

    def read_run(self, name: str) -> tuple[Any, dict[str, Any]] | None:
        """A run-level array or group (``"run_estimates"``) an earlier run of the plan wrote,
        with its attributes (:meth:`torch_stsdic.io.ResultWriter.read_run`; memory: None)."""
        return None

    def result(self, info: dict[str, Any]) -> TrackResult:
        """The :class:`TrackResult` of the rows held, on the plan's device and dtype."""
        plan, v = self.plan, self.values
        f, n = plan.n_rows, plan.n_points

        def ft(name: str) -> torch.Tensor:
            if name not in v:  # not kept: NaN, without memory
                return torch.full((), float("nan"), dtype=plan.dtype,
                                  device=plan.device).expand(f, n)
            # the held values, converted only where the precision differs (a kept field)
            return torch.from_numpy(v[name]).to(device=plan.device, dtype=plan.dtype)

        def it(name: str, fill: int, dtype: np.dtype, tdt: torch.dtype) -> torch.Tensor:
            if name not in v:
                return torch.full((), fill, dtype=tdt).expand(f, n)
            return torch.from_numpy(np.nan_to_num(v[name], nan=fill).astype(dtype))

        info = {**info, "units": dict(plan.units), "row_counts": self.row_counts()}
        if self.raw:
            info["raw"] = {k: torch.from_numpy(np.asarray(a, dtype=np.float64)).to(
                device=plan.device, dtype=plan.dtype) for k, a in self.raw.items()}
        if self.path is not None:
            info["out"] = str(self.path)
        return TrackResult(
            points=plan.points.to(device=plan.device, dtype=plan.dtype),
            frames=torch.tensor(plan.targets, dtype=torch.long),
            times=torch.from_numpy(plan.row_times.copy()),
            u=ft("u"), v=ft("v"), ut=ft("ut"), vt=ft("vt"), zncc=ft("zncc"),
            status=it("status", int(Status.NOT_COMPUTED), np.int8, torch.int8),
            iterations=it("iterations", 0, np.int32, torch.int32),
            gradients={nm: ft(nm) for nm in plan.gradients},
            m=it("m", -1, np.int8, torch.int8),
            std={nm[:-4]: ft(nm) for nm in plan.fields if nm.endswith("_std")},
            reference_frames=torch.from_numpy(self.reference_frames.copy()),
            config=plan.config, info=info,
        )


class HDF5Sink(MemorySink):
    """Writes every block to an HDF5 result file as it comes (:class:`~torch_stsdic.io.
    ResultWriter`), with its strain fields (``strain_window`` grid points per side of the
    plane fit, ``strain_kind`` "green" or "small"; None: no strains), computed from the
    block's rows as stored (float32): a frame's plane fits need only that frame. Nothing of
    size frames x points stays in memory: the result (:meth:`result`) reads its fields from
    the file when asked (:class:`~torch_stsdic.analysis.stored_result.StoredTrackResult`), so
    a resumed run returns the same numbers as an uninterrupted one. A smoothed run
    (``smoothing``) gets its strains at :meth:`finish`, from the smoothed fields, a few
    frames at a time."""

    def __init__(self, plan: RunPlan, path: str | os.PathLike[str], *, resume: bool = False,
                 overwrite: bool = False, strain_window: int | None = 5,
                 strain_kind: str = "green", attrs: dict[str, Any] | None = None) -> None:
        super().__init__(plan, keep=())
        self.path = str(path)
        self.strain_window, self.strain_kind = strain_window, strain_kind
        extra = tuple(f"{nm}_smooth" for nm in SMOOTHED) if plan.options.get("smoothing") else ()
        attrs = dict(attrs or {})
        self.strain_fields: tuple[str, ...] = ()
        if strain_window is not None:  # allocated now: finishing changes no file metadata
            self.strain_fields = strain_fields(plan)
            extra += self.strain_fields
            attrs["strain"] = json.dumps({"window": strain_window, "kind": strain_kind})
        self.writer = ResultWriter(
            path, points=plan.points, frames=np.asarray(plan.targets, dtype=np.int64),
            times=plan.row_times, config=plan.record(), inputs=plan.series.sources,
            fields=plan.fields, extra_fields=extra, resume=resume, overwrite=overwrite,
            attrs=attrs,
        )
        # the calibration is recorded, not compared on resume (values stay in px)
        self.writer.add_fields({}, dict(plan.units))
        self.smoothed = False

    def completed_rows(self) -> set[int]:
        return set(self.writer.completed_rows().tolist())

    def read_rows(self, rows: Sequence[int]) -> dict[str, np.ndarray]:
        stored = self.writer.read_rows(rows[0], rows[-1])
        self._count(stored)
        self._write_strain(rows, stored)  # a file of an older run may have none yet
        return stored

    def _keep(self, rows: Sequence[int], values: dict[str, np.ndarray]
              ) -> dict[str, np.ndarray]:
        stored = as_stored({nm: values[nm] for nm in self.plan.fields})
        self.writer.write_rows(np.asarray(rows), stored)
        self._write_strain(rows, stored)
        return stored

    def field_values(self, name: str) -> np.ndarray:
        return self.writer.read_rows(0, self.plan.n_rows - 1, [name])[name]

    def _strain_of(self, stored: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The strain fields (k, N) of rows ``stored`` (u, v, ut, vt, status as stored),
        computed as :meth:`TrackResult.strain` computes them on the whole result: from the
        values at the plan's precision, rates wherever the file has rate fields. On the host,
        where the rows are (a run on a GPU copied them there already: no copy to the device
        and back, two waits a block, for a few thousand rows)."""
        plan = self.plan

        def ft(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.asarray(a, dtype=np.float64)).to(dtype=plan.dtype)

        rates = any(nm.endswith("_rate") for nm in self.strain_fields)
        valid = torch.from_numpy(np.asarray(stored["status"]).astype(np.int8)) <= int(
            Status.MAX_ITER)
        strain = compute_strain(
            plan.points.to(device="cpu", dtype=plan.dtype), ft(stored["u"]),
            ft(stored["v"]), window=self.strain_window, kind=self.strain_kind,
            valid=valid, ut=ft(stored["ut"]) if rates else None,
            vt=ft(stored["vt"]) if rates else None)
        return {k: np.asarray(a.detach().cpu()) for k, a in strain.items()
                if k in self.strain_fields}

    def _write_strain(self, rows: Sequence[int], stored: dict[str, np.ndarray]) -> None:
        """Write the strains of rows ``rows`` (their fields ``stored``), unless the run is
        smoothed (its strains come from the smoothed fields, at :meth:`finish`)."""
        if self.strain_window is None or self.plan.options.get("smoothing"):
            return
        self.writer.write_rows(np.asarray(rows), self._strain_of(stored),
                               mark_completed=False)

    def write_smoothed(self, values: dict[str, np.ndarray]) -> None:
        stored = as_stored({f"{nm}_smooth": values[nm] for nm in SMOOTHED})
        self.writer.write_rows(np.arange(self.plan.n_rows), stored, mark_completed=False)
        self.smoothed = True

    def finish(self, result: TrackResult) -> None:
        if self.strain_window is None:
            return
        if self.plan.options.get("smoothing"):  # from the smoothed fields, chunk by chunk
            src = {nm: f"{nm}_smooth" if self.smoothed else nm for nm in SMOOTHED}
            step = STRAIN_ROWS
            for r0 in range(0, self.plan.n_rows, step):
                r1 = min(r0 + step, self.plan.n_rows) - 1
                got = self.writer.read_rows(r0, r1, [*src.values(), "status"])
                stored = {nm: got[src[nm]] for nm in SMOOTHED}
                stored["status"] = got["status"]
                self.writer.write_rows(np.arange(r0, r1 + 1), self._strain_of(stored),
                                       mark_completed=False)
        settings = json.dumps({"window": self.strain_window, "kind": self.strain_kind})
        if self.writer.attrs().get("strain") != settings:
            # a resume with other strain options: every row's strains were computed with
            # these (replayed blocks included); the only case where finishing changes the
            # file's metadata
            self.writer.add_fields({}, {"strain": settings})

    def result(self, info: dict[str, Any]) -> TrackResult:
        """The run's :class:`TrackResult`, its (F, N) fields read from the file when first
        asked for (:class:`~torch_stsdic.analysis.stored_result.StoredTrackResult`)."""
        plan = self.plan
        info = {**info, "units": dict(plan.units), "row_counts": self.row_counts(),
                "out": str(self.path)}
        names = {nm: nm for nm in plan.fields}
        if self.smoothed:  # the smoothed fields stand for the raw ones
            names.update({nm: f"{nm}_smooth" for nm in SMOOTHED})
            info["raw"] = lazy_fields(self.path, {"u": "u", "v": "v"}, plan.dtype, plan.device)
        return StoredTrackResult.open(
            self.path, names, dtype=plan.dtype, device=plan.device,
            points=plan.points.to(device=plan.device, dtype=plan.dtype),
            frames=torch.tensor(plan.targets, dtype=torch.long),
            times=torch.from_numpy(plan.row_times.copy()),
            gradients=plan.gradients,
            std=tuple(nm[:-4] for nm in plan.fields if nm.endswith("_std")),
            reference_frames=torch.from_numpy(self.reference_frames.copy()),
            config=plan.config, info=info)

    def write_shared_motion(self, shared: Any) -> None:
        rec = shared.summary()
        attrs = {k: v for k, v in rec.items() if k != "params"}
        p = shared.params.shape[1]
        attrs["columns"] = list(PARAM_NAMES[:p])
        attrs["units"] = list(PARAM_UNITS[:p])
        self.writer.write_array("shared_motion", shared.params, attrs)

    def write_series_reference(self, template: Any) -> None:
        attrs = {**template.summary(), "units": "grey levels (the reference's)",
                 "what": "the template every frame was measured against, (H, W)"}
        # at the run's precision (float32 or float64): the image a resumed run reads back
        image = template.image.to(self.plan.dtype).cpu().numpy()
        self.writer.write_array("series_reference", image, attrs)

    def write_run_estimates(self, arrays: dict[str, np.ndarray], meta: str) -> None:
        self.writer.write_array("run_estimates", arrays, {
            "meta": meta, "what": "the run-level estimates a resumed run reads instead of "
            "measuring them again (docs/io.md)"})

    def read_run(self, name: str) -> tuple[Any, dict[str, Any]] | None:
        return self.writer.read_run(name)

    def close(self, commit: bool = True) -> None:
        self.writer.close(commit=commit)


def strain_fields(plan: RunPlan) -> tuple[str, ...]:
    """The strain fields a finished run of ``plan`` adds: exx, eyy, exy, and their rates when
    the run measures velocities (m > 0, or smoothing)."""
    rates = "ut" in plan.param_names or bool(plan.options.get("smoothing"))
    return STRAIN_FIELDS + (tuple(f"{nm}_rate" for nm in STRAIN_FIELDS) if rates else ())


def open_sink(plan: RunPlan, out: str | os.PathLike[str] | None, *, resume: bool = False,
              overwrite: bool = False, **kwargs: Any) -> MemorySink:
    """An :class:`HDF5Sink` on ``out``, or a :class:`MemorySink` when ``out`` is None."""
    if out is None:
        if resume:
            raise ValueError("resume: needs out (the result file to continue)")
        return MemorySink(plan)
    return HDF5Sink(plan, out, resume=resume, overwrite=overwrite, **kwargs)


def row_counts(status: np.ndarray, m: np.ndarray | None) -> dict[str, dict[str, int]]:
    """The (frame, point) results by status code and the usable ones by window half-width
    (the layout of ``TrackResult.info["row_counts"]``), from (F, N) fields."""
    s = np.asarray(status).astype(np.int64)
    codes, n = np.unique(s, return_counts=True)
    out = {"status": {str(c): int(k) for c, k in zip(codes.tolist(), n.tolist())},
           "m_usable": {}}
    if m is not None:
        mc, mn = np.unique(np.asarray(m).astype(np.int64)[s <= 1], return_counts=True)
        out["m_usable"] = {str(c): int(k) for c, k in zip(mc.tolist(), mn.tolist())}
    return out
