"""Beyond one machine: a movie split into frame chunks, each tracked by a Dask worker.

:func:`track_distributed` splits the target frames of a movie into consecutive *chunks* of
``chunk_frames`` targets, rounded up to whole blocks of the one-process run
(``batch_frames``). Each chunk is one task on a Dask worker:
:func:`~torch_stsdic.movie.series.run_plan` of the whole run's plan over the chunk's targets
and blocks. Target frames never overlap between chunks; the frames *read* do (the windows
reach ``m`` frames beyond a chunk's edges, and a chunk also solves the ``WARM_UP`` targets
before it). The driver (the calling process) writes every finished chunk's rows into one
HDF5 result file, the same layout as ``track(out=...)`` (:class:`~torch_stsdic.io.
ResultWriter`), so ``read_results``/``export_csv``/``stsdic plot`` work unchanged;
``resume=True`` skips the chunks whose rows are all completed in the file.

Every run-level estimate is measured once, by the driver, on the whole movie
(:func:`~torch_stsdic.movie.estimates.measure_run`: the shared motion and its load steps,
the measuring pass's solutions that are the first block's guess, the reference made from the
series, the refined reference's offsets, the reference's noise ratio), recorded in the result
file as a one-process run records them (its group ``run_estimates`` included, so that a
one-process ``resume`` of the file reads them), and handed to every chunk
(``run_plan(estimates=...)``): a chunk's windows, segments, reference and blocks are those of
the one-process run. A resumed run reads them back from its file
(:func:`~torch_stsdic.movie.estimates.stored_or_measured`), but measures them again where
chunks are left to run with a shared motion (they start from its first guess, not stored).
Guesses are not carried across chunks; instead a chunk other than the first solves the
``WARM_UP`` targets before it (from the measuring pass's guess, as a first block starts) and
carries its guesses on from those rows, which are then dropped: its first
block starts, like the one-process run's, from a carried prediction, with the fit check's
baselines of the rows just before it (a warm-up row that the fit check made POOR_FIT for
its residual alone, without the point's history, is carried on as trusted). A point that
converges lands on the same minimum from either guess, so the results equal the one-process
run's to within the Gauss-Newton stopping tolerance (``config.tol``), and so do the statuses
and windows but for the rare point whose decision turns on that (docs/benchmarks.md,
"Beyond one machine"). Not supported, because they chain state along the whole movie:
``reference_update`` (incremental reference) and ``smoothing`` (run ``m = 0`` here, then
:func:`~torch_stsdic.analysis.smoothing.smooth_in_time` on the result).

Why Dask distributed rather than Ray: it is pure pip (``pip install torch_stsdic[dist]``),
``LocalCluster`` runs the workers as ordinary local processes (or threads) started and
stopped by the call itself - no daemon, no object store, no ``ray start`` - and the same code
runs on a cluster by passing a scheduler address (``dask scheduler`` / ``dask worker``,
dask-jobqueue on SLURM/PBS, dask-kubernetes, dask-mpi). Tasks here are coarse (seconds to
minutes each) and exchange only small numpy arrays, which is Dask's sweet spot; Ray's
shared-memory object store, actors and GPU scheduling bring a heavier install and runtime
that this workload does not need.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sys
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from torch_stsdic.analysis.result import TrackResult
from torch_stsdic.core.signatures import POSITIONAL, param, signature_like
from torch_stsdic.movie.estimates import RunEstimates, record_estimates, stored_or_measured
from torch_stsdic.movie.plan import RunPlan, plan_run
from torch_stsdic.movie.series import run_plan, set_reference_mode
from torch_stsdic.movie.sinks import MemorySink, open_sink

__all__ = ["track_distributed", "track_distributed_many", "run_plan_distributed", "chunk_plan",
           "DASK_HINT", "WARM_UP"]

DASK_HINT = "pip install torch_stsdic[dist]  (or: pip install \"dask[distributed]\")"
_UNSUPPORTED = {
    "reference_update": "the incremental reference chains every frame to the previous ones",
    "smoothing": "smoothing spans chunk edges: run with config.m = 0, then "
                 "smooth_in_time(result)",
}
#: targets before a chunk (but the first) solved first and dropped: the chunk's guesses are
#: carried on from their rows, as the one-process run carries them from the rows before
#: (two rows: the velocity of a classical row is their difference)
WARM_UP = 2
#: keyword arguments of track that the plan, the reference mode and the result file take
_PLAN_KW = ("device", "lost_zncc", "checks", "scale", "unit", "time_unit", "shared_motion",
            "find_specimen")
_MODE_KW = ("refine_reference", "refine_frames", "series_reference", "series_frames")
_SINK_KW = ("strain_window", "strain_kind")


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            f"track_distributed needs Dask distributed, which is not installed: {DASK_HINT}"
        ) from exc
    return distributed


def chunk_plan(targets: Sequence[int], chunk_frames: int, n_series: int, m: int,
               warm: int = 0, blocks: Sequence[Sequence[int]] | None = None
               ) -> list[dict[str, Any]]:
    """Chunks of consecutive targets: ``targets`` (the chunk's result rows, disjoint),
    ``warm`` (up to ``warm`` targets before them, solved first and dropped: every chunk but
    the first) and ``reads`` (first, last) series frames its windows need (overlapping with
    neighbours). With ``blocks`` (the run's blocks of targets), a chunk is whole blocks, as
    few as make ``chunk_frames`` targets, so that its blocks are the run's.

    >>> [c["reads"] for c in chunk_plan(range(10), 4, 10, 1)]
    [(0, 4), (3, 8), (7, 9)]
    """
    if not isinstance(chunk_frames, (int, np.integer)) or chunk_frames < 1:
        raise ValueError(f"chunk_frames: must be an integer >= 1, got {chunk_frames!r}")
    tg = [int(t) for t in targets]
    if blocks is None:
        blocks = [[t] for t in tg]
    parts: list[list[int]] = []
    for blk in blocks:
        if not parts or len(parts[-1]) >= int(chunk_frames):
            parts.append([])
        parts[-1].extend(int(t) for t in blk)
    n_win = 2 * m + 1
    out, i = [], 0
    for part in parts:
        before = tg[max(0, i - int(warm)) : i]
        lo = min(max((before or part)[0] - m, 0), n_series - n_win)
        hi = max(min(part[-1] + m, n_series - 1), n_win - 1)
        out.append({"index": len(out), "targets": part, "warm": before, "reads": (lo, hi)})
        i += len(part)
    return out


@dataclass
class _ChunkPlan(RunPlan):
    """A chunk's plan: the whole run's plan over the chunk's targets, with the whole run's
    blocks (and the warm-up block first) instead of its own."""

    chunk_blocks: list[list[int]] = field(default_factory=list)

    @property
    def blocks(self) -> list[list[int]]:
        return self.chunk_blocks


def _run_chunk(plan: RunPlan, chunk: dict[str, Any], estimates: RunEstimates,
               torch_threads: int | None) -> dict[str, Any]:
    """Worker side: run one chunk of ``plan`` with the whole run's ``estimates``; (F_chunk, N)
    numpy rows per field (the warm-up rows dropped) + counters."""
    if torch_threads is None:
        torch_threads = _threads_per_task()
    if torch_threads > 0:
        torch.set_num_threads(int(torch_threads))
    warm = list(chunk["warm"])
    args = {f.name: getattr(plan, f.name) for f in dataclasses.fields(RunPlan) if f.init}
    args["targets"] = warm + list(chunk["targets"])
    sub = _ChunkPlan(**args, chunk_blocks=([warm] if warm else []) + chunk["blocks"])
    res = run_plan(sub, MemorySink(sub), progress=False, estimates=estimates,
                   warm_up=bool(warm))
    rows = {nm: res.field(nm)[len(warm):].detach().cpu().numpy() for nm in plan.fields}
    info = {k: v for k, v in res.info.items() if isinstance(v, (int, float))}
    return {"targets": list(chunk["targets"]), "rows": rows, "info": info, "pid": os.getpid()}


@dataclass
class _Job:
    """One movie: its plan, its sink (memory or HDF5), the chunks still to run and the
    run-level estimates handed to them."""

    plan: RunPlan
    sink: MemorySink
    chunks: list[dict[str, Any]]
    n_chunks: int
    estimates: RunEstimates | None = None
    info: dict[str, Any] = field(default_factory=dict)
    rows_done: int = 0


def _job(plan: RunPlan, sink: MemorySink, chunk_frames: int) -> _Job:
    """The chunks of ``plan`` (those ``sink`` holds already read back, not run again)."""
    for k, why in _UNSUPPORTED.items():
        if plan.options.get(k) is not None:
            raise ValueError(f"{k}: not supported by track_distributed ({why})")
    chunks = chunk_plan(plan.targets, chunk_frames, len(plan.series), plan.config.m,
                        warm=WARM_UP, blocks=plan.blocks)
    for ch in chunks:  # the one-process run's blocks
        mine = set(ch["targets"])
        ch["blocks"] = [c for c in ([k for k in b if k in mine] for b in plan.blocks) if c]
    job = _Job(plan=plan, sink=sink, chunks=chunks, n_chunks=len(chunks))
    done = sink.completed_rows()
    if done:
        row_of = plan.row_of()
        pending = []
        for ch in chunks:
            rows = [row_of[t] for t in ch["targets"]]
            if all(r in done for r in rows):
                sink.read_rows(rows)
                job.rows_done += len(rows)
            else:
                pending.append(ch)
        job.info["chunks_resumed"] = len(chunks) - len(pending)
        job.chunks = pending
    return job


def _plan_job(series: Any, plan_args: dict[str, Any], *, chunk_frames: int, out: Any,
              resume: bool, overwrite: bool, extra: dict[str, Any]) -> _Job:
    """Plan one movie as ``track`` plans it, and open its result file."""
    if resume and out is None:
        raise ValueError("resume: needs out (the result file to continue)")
    plan = plan_run(series, **plan_args, **{k: extra[k] for k in _PLAN_KW if k in extra})
    mode = {k: extra.get(k) for k in _MODE_KW}
    set_reference_mode(plan, bool(mode["refine_reference"]), mode["refine_frames"],
                       "auto" if mode["series_reference"] is None else mode["series_reference"],
                       mode["series_frames"])
    dist = {"chunk_frames": int(chunk_frames)}
    sink = open_sink(plan, out, resume=resume, overwrite=overwrite,
                     attrs={"distributed": json.dumps(dist)},
                     **{k: extra[k] for k in _SINK_KW if k in extra})
    try:
        return _job(plan, sink, chunk_frames)
    except BaseException:
        sink.close(commit=False)
        raise


def _measure(job: _Job) -> None:
    """The run-level estimates of the whole movie, measured here once (with the reference's
    noise ratio), recorded in the result file as the one-process run records them
    (:func:`~torch_stsdic.movie.estimates.record_estimates`: its run-level arrays and the
    group ``run_estimates``), so that a later resume, distributed or one-process, reads them
    back. A resumed job reads them from its file
    (:func:`~torch_stsdic.movie.estimates.stored_or_measured`) but where it has chunks to
    run with a shared motion: each starts from the shared motion's first guess, which the
    file does not hold, so they are measured again."""
    job.estimates = stored_or_measured(
        job.plan, job.sink, run=run_plan, first_noise=True, guess_needed=bool(job.chunks),
        # each chunk starts from the first guess: the pass's solutions kept at their frames
        guess_blocks=[ch["warm"] or ch["blocks"][0] for ch in job.chunks])
    record_estimates(job.estimates, job.sink)


def _accept(job: _Job, result: dict[str, Any]) -> int:
    """Merge one chunk's rows into the job's sink. Returns the rows added."""
    row0 = job.plan.row_of()[result["targets"][0]]
    rows = list(range(row0, row0 + len(result["targets"])))
    job.sink.write_rows(rows, result["rows"])
    for k, v in result["info"].items():
        if k in ("frames_read", "prefiltered", "fft_rows", "redone_rows", "blocks",
                 "off_centre_rows", "first_guess_rows", "rescued_rows", "neighbour_rows",
                 "shortened_rows", "classical_rows", "poor_fit_rows", "inconsistent_rows",
                 "neighbour_rescued_rows", "blocks_guessed_wrong"):
            job.info[k] = job.info.get(k, 0) + v
        elif k == "max_cached_frames":
            job.info[k] = max(job.info.get(k, 0), v)
    job.info.setdefault("worker_pids", set()).add(result["pid"])
    job.rows_done += len(rows)
    return len(rows)


def _finish(job: _Job, chunk_frames: int, workers: int) -> TrackResult:
    est = job.estimates or RunEstimates()
    info = {
        "batch_frames": job.plan.batch_frames, "reference": job.plan.reference_desc,
        "reference_updates": [], "reference_noise_ratio": est.noise_ratio,
        "chunk_frames": chunk_frames, "chunks": job.n_chunks,
        "chunks_run": len(job.chunks), "workers": workers, "warm_up": WARM_UP,
        **{k: v for k, v in job.info.items() if k != "worker_pids"},
        "worker_processes": len(job.info.get("worker_pids", ())),
        **est.summary(), **job.plan.info(),
    }
    result = job.sink.result(info)
    job.sink.finish(result)
    job.sink.close()
    return result


def _open_client(client: Any, n_workers: int, threads_per_worker: int, processes: bool):
    """(client, cluster-or-None, owns_client) from a Client, an address, a scheduler file
    or None (a LocalCluster started here)."""
    distributed = _import_distributed()
    if isinstance(client, distributed.Client):
        return client, None, False
    if client is None:
        cluster = distributed.LocalCluster(
            n_workers=int(n_workers), threads_per_worker=int(threads_per_worker),
            processes=bool(processes), dashboard_address=None, silence_logs=logging.ERROR,
        )
        return distributed.Client(cluster), cluster, True
    if isinstance(client, (str, os.PathLike)):
        s = os.fspath(client)
        if s.endswith(".json") and os.path.exists(s):
            return distributed.Client(scheduler_file=s), None, True
        return distributed.Client(s), None, True
    raise TypeError(f"client: expected a dask.distributed Client, a scheduler address, a "
                    f"scheduler file or None, got {type(client).__name__}")


_PLAN_ARGS = ("reference", "frames", "points", "roi", "mask", "step", "config", "times",
              "batch_frames")


def _threads_per_task() -> int:
    """Torch (and kernel) threads of one task on this worker of a cluster not made here: the
    cores this process may use over the task threads of every worker on this host (the
    scheduler's list of workers), so that workers side by side do not oversubscribe the node;
    1 where that is not known."""
    try:
        from distributed import get_worker

        worker = get_worker()
        per = int(worker.state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return 1

    def host(addr: str) -> str:
        return addr.split("://")[-1].rsplit(":", 1)[0]

    try:  # every worker on this host, with its task threads
        infos = worker.client.scheduler_info().get("workers", {})
        here = sum(int(w.get("nthreads", 1)) for a, w in infos.items()
                   if host(a) == host(worker.address))
    except Exception:  # (a scheduler that does not answer: this worker alone)
        here = 0
    return max(1, _cores() // max(1, per, here))


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def track_distributed_many(
    movies: Sequence[Any],
    outs: Sequence[Any] | None = None,
    *,
    chunk_frames: int = 50,
    client: Any = None,
    n_workers: int = 2,
    threads_per_worker: int = 1,
    processes: bool = True,
    torch_threads: int | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    callback: Callable[[int, int], None] | None = None,
    **track_kwargs: Any,
) -> list[TrackResult]:
    """:func:`track_distributed` for several movies at once (one result and one ``outs``
    file each); the chunks of all movies share the workers. Settings apply to every movie."""
    for k in track_kwargs:
        if k in _UNSUPPORTED:
            raise ValueError(f"{k}: not supported by track_distributed ({_UNSUPPORTED[k]})")
    known = set(_PLAN_ARGS + _PLAN_KW + _MODE_KW + _SINK_KW)
    if k_bad := set(track_kwargs) - known:
        raise TypeError(f"unexpected argument(s) {sorted(k_bad)}")
    movies = list(movies)
    if outs is not None and len(list(outs)) != len(movies):
        raise ValueError(f"outs: {len(list(outs))} paths for {len(movies)} movies")
    outs_l = list(outs) if outs is not None else [None] * len(movies)
    plan_args = {k: track_kwargs.pop(k) for k in _PLAN_ARGS if k in track_kwargs}
    jobs: list[_Job] = []
    try:
        for mv, o in zip(movies, outs_l):
            jobs.append(_plan_job(mv, plan_args, chunk_frames=chunk_frames, out=o,
                                  resume=resume, overwrite=overwrite, extra=track_kwargs))
    except BaseException:
        for j in jobs:
            j.sink.close(commit=False)
        raise
    return _run_jobs(jobs, int(chunk_frames), _Cluster(client, n_workers, threads_per_worker,
                                                       processes, torch_threads),
                     progress, callback)


def run_plan_distributed(
    plan: RunPlan,
    sink: MemorySink | None = None,
    *,
    chunk_frames: int = 50,
    client: Any = None,
    n_workers: int = 2,
    threads_per_worker: int = 1,
    processes: bool = True,
    torch_threads: int | None = None,
    progress: bool = True,
    callback: Callable[[int, int], None] | None = None,
) -> TrackResult:
    """:func:`~torch_stsdic.movie.series.run_plan` on Dask workers: ``plan`` in chunks of
    ``chunk_frames`` targets into ``sink`` (memory, or an HDF5 file opened by the caller,
    resumed where it holds finished chunks); the cluster settings as for
    :func:`track_distributed`. The result equals ``run_plan(plan, sink)``'s to within the
    stopping tolerance (``stsdic run --workers``)."""
    sink = sink if sink is not None else MemorySink(plan)
    try:
        job = _job(plan, sink, chunk_frames)
    except BaseException:
        sink.close(commit=False)
        raise
    cluster = _Cluster(client, n_workers, threads_per_worker, processes, torch_threads)
    return _run_jobs([job], int(chunk_frames), cluster, progress, callback)[0]


@dataclass
class _Cluster:
    """Where the chunks run: a client (or address, scheduler file, None for a LocalCluster
    of ``n_workers`` x ``threads_per_worker``) and the torch threads of a task."""

    client: Any
    n_workers: int
    threads_per_worker: int
    processes: bool
    torch_threads: int | None

    def task_threads(self) -> int | None:
        if self.client is None and self.torch_threads is None:
            # threads share this process' torch thread pool: leave it alone (0)
            per = self.n_workers * self.threads_per_worker
            return max(1, _cores() // per) if self.processes else 0
        return self.torch_threads


def _run_jobs(jobs: list[_Job], chunk_frames: int, where: _Cluster, progress: bool,
              callback: Callable[[int, int], None] | None) -> list[TrackResult]:
    """Measure every job's run-level estimates, run their pending chunks on the cluster,
    merge the rows as the chunks finish; on any error or interruption every sink is closed
    without committing (a file keeps its finished chunks and can be resumed)."""
    cl, cluster, owns = (None, None, False)
    futures: list[Any] = []
    bar = None
    try:
        for j in jobs:
            _measure(j)
        total = sum(j.plan.n_rows for j in jobs)
        done = sum(j.rows_done for j in jobs)
        n_chunks = sum(len(j.chunks) for j in jobs)
        bar = tqdm(total=total, initial=done, unit="frame", file=sys.stderr,
                   disable=not progress, desc="STS-DIC (dask)", dynamic_ncols=True)
        if n_chunks:
            cl, cluster, owns = _open_client(where.client, where.n_workers,
                                             where.threads_per_worker, where.processes)
            futures, job_of = _submit(cl, jobs, where.task_threads())
            distributed = _import_distributed()
            for i, fut in enumerate(distributed.as_completed(futures)):
                added = _accept(job_of[fut.key], fut.result())
                done += added
                bar.set_postfix_str(f"chunk {i + 1}/{n_chunks}", refresh=False)
                bar.update(added)
                if callback is not None:
                    callback(done, total)
    except BaseException:
        for fut in futures:
            fut.cancel()
        if bar is not None:
            bar.close()
        for j in jobs:
            j.sink.close(commit=False)
        _close_client(cl, cluster, owns)
        raise
    bar.close()
    workers = 0
    if cl is not None:
        try:
            workers = len(cl.scheduler_info().get("workers", {}))
        except Exception:
            workers = 0
    _close_client(cl, cluster, owns)
    return [_finish(j, chunk_frames, workers) for j in jobs]


def _submit(cl: Any, jobs: list[_Job], torch_threads: int | None
            ) -> tuple[list[Any], dict[str, _Job]]:
    """One task per pending chunk of every job (the plan, with its series, and the estimates
    scattered once per job): the futures, and the job of every future's key."""
    run_id = uuid.uuid4().hex[:8]
    futures, job_of = [], {}
    for ji, job in enumerate(jobs):
        if not job.chunks:
            continue
        plan = cl.scatter(job.plan, broadcast=True, hash=False)
        est = cl.scatter(job.estimates, broadcast=True, hash=False)
        for ch in job.chunks:
            fut = cl.submit(_run_chunk, plan, ch, est, torch_threads,
                            key=f"stsdic-{run_id}-{ji}-{ch['index']}", pure=False)
            job_of[fut.key] = job
            futures.append(fut)
    return futures, job_of


def _close_client(cl: Any, cluster: Any, owns: bool) -> None:
    if owns and cl is not None:
        cl.close()
    if cluster is not None:
        cluster.close()


def track_distributed(series: Any, *, out: Any = None, **kwargs: Any) -> TrackResult:
    """Track a movie on several processes or machines: frame chunks on Dask workers.

    Args:
        series: as for :func:`~torch_stsdic.movie.series.track` (TIFF stack, directory, glob, list
            of files, array, ImageSeries). Workers read the frames themselves: on a cluster
            the paths must be visible to every worker (shared filesystem); an in-memory
            array is sent to each worker once (``Client.scatter``).
        chunk_frames: target frames per task, rounded up to whole blocks of ``batch_frames``
            targets (the first block is the first target alone). Each chunk but the first
            also solves the
            ``WARM_UP`` (2) targets before it, and reads their and its windows' frames
            (``2m + 2`` extra reads and prefilters), so keep it well above ``m`` and
            ``WARM_UP`` (default 50; docs/benchmarks.md sizes it).
        client: None (a ``LocalCluster`` of ``n_workers`` is started and stopped here), a
            ``dask.distributed.Client``, a scheduler address (``"tcp://host:8786"``) or a
            scheduler file (``scheduler.json``, e.g. from dask-mpi / dask-jobqueue).
        n_workers, threads_per_worker, processes: the LocalCluster (``processes=False``:
            threads in this process, for small jobs and tests).
        torch_threads: torch intra-op threads per task; default: cores / (workers x threads)
            locally, cores / (the worker's threads) on a cluster; 0 leaves torch alone.
        out: HDF5 result file (same layout as ``track``), written by this process as
            chunks finish. resume: skip the chunks already completed in ``out``.
            overwrite: replace an existing ``out``.
        progress: progress bar (rows). callback: ``callback(rows_done, n_rows)``.
        **track_kwargs: as for ``track`` (reference, frames, points, roi, mask, step,
            config, times, device, batch_frames, lost_zncc, checks, shared_motion, find_specimen,
            refine_reference, refine_frames, series_reference, series_frames,
            strain_window, strain_kind, scale, unit, time_unit). ``reference_update`` and
            ``smoothing`` are not supported (ValueError). The run-level estimates (shared
            motion, load steps, first guess, the reference made from the series, the
            refined reference's offsets) are measured once, here, on the whole movie,
            recorded in ``out`` (read back on ``resume`` where no chunk left to run needs
            the shared motion's first guess) and handed to every chunk.

    Returns:
        :class:`~torch_stsdic.movie.series.TrackResult` over all targets; ``info["chunks"]``,
        ``info["chunks_run"]``, ``info["workers"]`` describe the run. With ``out`` the
        values are those stored in the file (float32).

    Raises:
        ImportError (with the pip command) when Dask distributed is not installed.
    """
    return track_distributed_many([series], None if out is None else [out], **kwargs)[0]


# the settings are those of track_distributed_many, written once there
track_distributed.__signature__ = signature_like(  # type: ignore[attr-defined]
    track_distributed_many, replace={"movies": param("series", kind=POSITIONAL)}, drop=["outs"],
    insert={"resume": [param("out", None)]}, returns="TrackResult")
