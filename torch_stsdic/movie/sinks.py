"""Where the rows of a run go: memory, or an HDF5 file written as the run goes.

A sink receives the result rows of a :class:`~torch_stsdic.movie.plan.RunPlan` block by block
(:meth:`MemorySink.write_rows`), can give back rows finished by an earlier, interrupted run
(:meth:`completed_rows`, :meth:`read_rows`), completes the output when the run ends
(:meth:`finish`: an HDF5 file gets its strain fields) and builds the
:class:`~torch_stsdic.analysis.result.TrackResult`. The HDF5 layout itself is
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
from torch_stsdic.core.shared_motion import PARAM_NAMES, PARAM_UNITS
from torch_stsdic.core.status import Status
from torch_stsdic.io.results import STRAIN_FIELDS, ResultWriter, as_stored
from torch_stsdic.movie.plan import RunPlan

__all__ = ["MemorySink", "HDF5Sink", "open_sink", "SMOOTHED"]

#: fields that ``smoothing`` replaces (the file keeps the raw ones and adds ``<name>_smooth``)
SMOOTHED = ("u", "v", "ut", "vt")


class MemorySink:
    """Keeps the (F, N) rows of a run in memory (numpy, full precision)."""

    path: str | None = None

    def __init__(self, plan: RunPlan) -> None:
        self.plan = plan
        f, n = plan.n_rows, plan.n_points
        self.values: dict[str, np.ndarray] = {nm: np.full((f, n), np.nan) for nm in plan.fields}
        self.values["status"] = np.full((f, n), int(Status.NOT_COMPUTED), dtype=np.int8)
        self.values["iterations"] = np.zeros((f, n), dtype=np.int64)
        self.values["m"] = np.full((f, n), -1, dtype=np.int8)
        self.reference_frames = np.full(f, plan.reference_frame, dtype=np.int64)
        self.raw: dict[str, np.ndarray] = {}

    def completed_rows(self) -> set[int]:
        """Rows finished by an earlier run (none in memory)."""
        return set()

    def read_rows(self, rows: Sequence[int]) -> dict[str, np.ndarray]:
        """The stored values of consecutive finished rows ``rows``."""
        return {nm: a[rows[0] : rows[-1] + 1] for nm, a in self.values.items()}

    def write_rows(self, rows: Sequence[int], values: dict[str, np.ndarray],
                   reference_frame: int | None = None) -> None:
        """Store rows ``rows`` (k,) of every field, each (k, N)."""
        self._keep(rows, values)
        if reference_frame is not None:
            self.reference_frames[list(rows)] = reference_frame

    def _keep(self, rows: Sequence[int], values: dict[str, np.ndarray]) -> None:
        for nm in self.plan.fields:
            self.values[nm][list(rows)] = values[nm]

    def write_smoothed(self, values: dict[str, np.ndarray]) -> None:
        """The temporally smoothed u, v, ut, vt (F, N) replace the result's fields (the raw
        ones stay in ``raw``)."""
        self.raw = {nm: self.values[nm].copy() for nm in ("u", "v")}
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

        def ft(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.asarray(a, dtype=np.float64)).to(device=plan.device,
                                                                          dtype=plan.dtype)

        info = {**info, "units": dict(plan.units)}
        if self.raw:
            info["raw"] = {k: ft(a) for k, a in self.raw.items()}
        if self.path is not None:
            info["out"] = str(self.path)
        return TrackResult(
            points=plan.points.to(device=plan.device, dtype=plan.dtype),
            frames=torch.tensor(plan.targets, dtype=torch.long),
            times=torch.from_numpy(plan.row_times.copy()),
            u=ft(v["u"]), v=ft(v["v"]), ut=ft(v["ut"]), vt=ft(v["vt"]), zncc=ft(v["zncc"]),
            status=torch.from_numpy(v["status"].astype(np.int8)),
            iterations=torch.from_numpy(v["iterations"].astype(np.int32)),
            gradients={nm: ft(v[nm]) for nm in plan.gradients},
            m=torch.from_numpy(np.nan_to_num(v["m"], nan=-1).astype(np.int8)),
            std={nm[:-4]: ft(v[nm]) for nm in plan.fields if nm.endswith("_std")},
            reference_frames=torch.from_numpy(self.reference_frames.copy()),
            config=plan.config, info=info,
        )


class HDF5Sink(MemorySink):
    """Writes every block to an HDF5 result file as it comes (:class:`~torch_stsdic.io.
    ResultWriter`), keeping in memory the values as stored (float32), so that a resumed run
    returns the same numbers as an uninterrupted one. :meth:`finish` adds the strain fields
    (``strain_window`` grid points per side, ``strain_kind`` "green" or "small"; None: no
    strains)."""

    def __init__(self, plan: RunPlan, path: str | os.PathLike[str], *, resume: bool = False,
                 overwrite: bool = False, strain_window: int | None = 5,
                 strain_kind: str = "green", attrs: dict[str, Any] | None = None) -> None:
        super().__init__(plan)
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

    def completed_rows(self) -> set[int]:
        return set(self.writer.completed_rows().tolist())

    def read_rows(self, rows: Sequence[int]) -> dict[str, np.ndarray]:
        stored = self.writer.read_rows(rows[0], rows[-1])
        super()._keep(rows, stored)
        return stored

    def _keep(self, rows: Sequence[int], values: dict[str, np.ndarray]) -> None:
        stored = as_stored({nm: values[nm] for nm in self.plan.fields})
        self.writer.write_rows(np.asarray(rows), stored)
        super()._keep(rows, stored)

    def write_smoothed(self, values: dict[str, np.ndarray]) -> None:
        stored = as_stored({f"{nm}_smooth": values[nm] for nm in SMOOTHED})
        self.writer.write_rows(np.arange(self.plan.n_rows), stored, mark_completed=False)
        super().write_smoothed({nm: stored[f"{nm}_smooth"] for nm in SMOOTHED})

    def finish(self, result: TrackResult) -> None:
        if self.strain_window is None:
            return
        strain = result.strain(window=self.strain_window, kind=self.strain_kind)
        shape = tuple(result.u.shape)
        fields = {k: np.asarray(v.detach().cpu() if isinstance(v, torch.Tensor) else v)
                  for k, v in strain.items()}
        fields = {k: a for k, a in fields.items() if a.shape == shape}
        known = {k: a for k, a in fields.items() if k in self.strain_fields}
        self.writer.write_rows(np.arange(self.plan.n_rows), known, mark_completed=False)
        new = {k: a for k, a in fields.items() if k not in self.strain_fields}
        settings = json.dumps({"window": self.strain_window, "kind": self.strain_kind})
        if new or self.writer.attrs().get("strain") != settings:
            # not foreseen when the file was made (a resume with other strain options):
            # the only case where finishing changes the file's metadata
            self.writer.add_fields(new, {"strain": settings})

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
