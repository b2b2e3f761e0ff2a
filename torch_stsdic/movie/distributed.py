"""Beyond one machine: a movie split into frame chunks, each tracked by a Dask worker.

:func:`track_distributed` splits the target frames of a movie into consecutive *chunks* of
``chunk_frames`` targets. Each chunk is one task: :func:`~torch_stsdic.movie.series.track` with
``frames=<the chunk's targets>`` and the same points, reference and settings, on a Dask
worker. Target frames never overlap between chunks; the frames *read* do: the windows of a
chunk's first and last targets reach ``m`` frames beyond its edges (``2m`` extra reads and
prefilters per chunk, shifted windows at the ends of the movie exactly as in ``track``). The
driver (the calling process) writes every finished chunk's rows into one HDF5 result file,
the same layout as ``track(out=...)`` (:class:`~torch_stsdic.io.ResultWriter`), so
``read_results``/``export_csv``/``stsdic plot`` work unchanged; ``resume=True`` skips the
chunks whose rows are all completed in the file.

Guesses are not carried across chunks: each chunk starts, like a single run, with FFT cross-
correlation on its first target and carries its own guesses from there. A point that
converges lands on the same minimum from either guess, so the results equal the single-process
run to within the Gauss-Newton stopping tolerance (``config.tol``, the last increment in px):
measured differences are ~1e-6 px or less with ``tol = 1e-8`` (noise-free or noisy), and a
fraction of ``tol`` with the default ``tol = 1e-4`` (see docs/benchmarks.md, "Beyond one
machine"). Points that do not converge (MAX_ITER, lost, DIVERGED) can differ, as between any
two initialisations. Not supported, because they chain state along the whole movie:
``reference_update`` (incremental reference) and ``smoothing`` (run ``m = 0`` here, then
:func:`~torch_stsdic.movie.series.temporal_smoothing` on the result).

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
from torch_stsdic.movie.plan import RunPlan, plan_run
from torch_stsdic.movie.series import track
from torch_stsdic.movie.sinks import MemorySink, open_sink

__all__ = ["track_distributed", "track_distributed_many", "chunk_plan", "DASK_HINT"]

DASK_HINT = "pip install torch_stsdic[dist]  (or: pip install \"dask[distributed]\")"
_BASE = ("u", "v", "ut", "vt")
_UNSUPPORTED = {
    "reference_update": "the incremental reference chains every frame to the previous ones",
    "smoothing": "smoothing spans chunk edges: run with config.m = 0, then "
                 "temporal_smoothing(result)",
}


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            f"track_distributed needs Dask distributed, which is not installed: {DASK_HINT}"
        ) from exc
    return distributed


def chunk_plan(targets: Sequence[int], chunk_frames: int, n_series: int, m: int
               ) -> list[dict[str, Any]]:
    """Chunks of consecutive targets: ``targets`` (the chunk's result rows, disjoint) and
    ``reads`` (first, last) series frames its windows need (overlapping with neighbours).

    >>> [c["reads"] for c in chunk_plan(range(10), 4, 10, 1)]
    [(0, 4), (3, 8), (7, 9)]
    """
    if not isinstance(chunk_frames, (int, np.integer)) or chunk_frames < 1:
        raise ValueError(f"chunk_frames: must be an integer >= 1, got {chunk_frames!r}")
    tg = [int(t) for t in targets]
    n_win = 2 * m + 1
    out = []
    for i in range(0, len(tg), int(chunk_frames)):
        part = tg[i : i + int(chunk_frames)]
        lo = min(max(part[0] - m, 0), n_series - n_win)
        hi = max(min(part[-1] + m, n_series - 1), n_win - 1)
        out.append({"index": len(out), "targets": part, "reads": (lo, hi)})
    return out


def _run_chunk(series: Any, targets: list[int], kwargs: dict[str, Any], torch_threads: int | None,
               fields: tuple[str, ...]) -> dict[str, Any]:
    """Worker side: ``track`` one chunk; (F_chunk, N) numpy rows per field + counters."""
    if torch_threads is None:
        torch_threads = _threads_per_task()
    if torch_threads > 0:
        torch.set_num_threads(int(torch_threads))
    res = track(series, frames=targets, progress=False, **kwargs)
    rows: dict[str, np.ndarray] = {}
    for nm in fields:
        rows[nm] = res.field(nm).detach().cpu().numpy()
    info = {k: v for k, v in res.info.items() if isinstance(v, (int, float))}
    return {"targets": list(targets), "rows": rows, "info": info, "pid": os.getpid()}


@dataclass
class _Job:
    """One movie: its plan, its sink (memory or HDF5) and the chunks still to run."""

    plan: RunPlan
    sink: MemorySink
    chunks: list[dict[str, Any]]
    n_chunks: int
    kwargs: dict[str, Any]
    info: dict[str, Any] = field(default_factory=dict)
    rows_done: int = 0


def _plan_job(series: Any, plan_args: dict[str, Any], *, chunk_frames: int, out: Any,
              resume: bool, overwrite: bool, extra: dict[str, Any]) -> _Job:
    if resume and out is None:
        raise ValueError("resume: needs out (the result file to continue)")
    # the shared motion recorded as track records it; every chunk measures that of its frames
    plan = plan_run(series, **plan_args, lost_zncc=float(extra.get("lost_zncc", 0.8)),
                    shared_motion=extra.get("shared_motion", "auto"))
    chunks = chunk_plan(plan.targets, chunk_frames, len(plan.series), plan.config.m)
    ref = plan.reference_image
    kwargs = dict(
        reference=plan.reference_frame if ref is None else ref.numpy(),
        points=plan.points.numpy(), config=plan.config, times=plan.times,
        batch_frames=plan.batch_frames, **extra,
    )
    dist = {"chunk_frames": int(chunk_frames), "chunks": len(chunks)}
    sink = open_sink(plan, out, resume=resume, overwrite=overwrite,
                     attrs={"distributed": json.dumps(dist)})
    job = _Job(plan=plan, sink=sink, chunks=chunks, n_chunks=len(chunks), kwargs=kwargs)
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


def _accept(job: _Job, result: dict[str, Any]) -> int:
    """Merge one chunk's rows into the job's sink. Returns the rows added."""
    row0 = job.plan.row_of()[result["targets"][0]]
    rows = list(range(row0, row0 + len(result["targets"])))
    job.sink.write_rows(rows, result["rows"])
    for k, v in result["info"].items():
        if k in ("frames_read", "prefiltered", "fft_rows", "redone_rows", "blocks",
                 "off_centre_rows", "first_guess_rows"):
            job.info[k] = job.info.get(k, 0) + v
        elif k == "max_cached_frames":
            job.info[k] = max(job.info.get(k, 0), v)
    job.info.setdefault("worker_pids", set()).add(result["pid"])
    job.rows_done += len(rows)
    return len(rows)


def _finish(job: _Job, chunk_frames: int, workers: int) -> TrackResult:
    info = {
        "batch_frames": job.plan.batch_frames, "reference": job.plan.reference_desc,
        "reference_updates": [], "chunk_frames": chunk_frames, "chunks": job.n_chunks,
        "chunks_run": len(job.chunks), "workers": workers,
        **{k: v for k, v in job.info.items() if k != "worker_pids"},
        "worker_processes": len(job.info.get("worker_pids", ())),
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
    if k_bad := {"series", "out", "progress"} & set(track_kwargs):
        raise TypeError(f"unexpected argument(s) {sorted(k_bad)}")
    movies = list(movies)
    if outs is not None and len(list(outs)) != len(movies):
        raise ValueError(f"outs: {len(list(outs))} paths for {len(movies)} movies")
    outs_l = list(outs) if outs is not None else [None] * len(movies)
    if client is None and torch_threads is None:
        # threads share this process' torch thread pool: leave it alone (0)
        torch_threads = max(1, _cores() // (n_workers * threads_per_worker)) if processes else 0
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
    total = sum(j.plan.n_rows for j in jobs)
    done = sum(j.rows_done for j in jobs)
    bar = tqdm(total=total, initial=done, unit="frame", file=sys.stderr, disable=not progress,
               desc="STS-DIC (dask)", dynamic_ncols=True)
    cl, cluster, owns = (None, None, False)
    futures: list[Any] = []
    try:
        if any(j.chunks for j in jobs):
            cl, cluster, owns = _open_client(client, n_workers, threads_per_worker, processes)
            futures, where = _submit(cl, jobs, torch_threads)
            distributed = _import_distributed()
            for fut in distributed.as_completed(futures):
                added = _accept(where[fut.key], fut.result())
                done += added
                bar.update(added)
                if callback is not None:
                    callback(done, total)
    except BaseException:
        for fut in futures:
            fut.cancel()
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
    return [_finish(j, int(chunk_frames), workers) for j in jobs]


def _submit(cl: Any, jobs: list[_Job], torch_threads: int | None
            ) -> tuple[list[Any], dict[str, _Job]]:
    """One task per pending chunk of every job (the series scattered once per job): the
    futures, and the job of every future's key."""
    run_id = uuid.uuid4().hex[:8]
    futures, where = [], {}
    for ji, job in enumerate(jobs):
        src = cl.scatter(job.plan.series, broadcast=True, hash=False)
        for ch in job.chunks:
            fut = cl.submit(_run_chunk, src, ch["targets"], job.kwargs, torch_threads,
                            job.plan.fields, key=f"stsdic-{run_id}-{ji}-{ch['index']}",
                            pure=False)
            where[fut.key] = job
            futures.append(fut)
    return futures, where


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
        chunk_frames: target frames per task. Each chunk costs ``2m`` extra frame reads and
            one FFT-initialised block, so keep it well above ``m`` (default 50).
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
        **track_kwargs: passed to ``track`` (reference, frames, points, roi, mask, step,
            config, times, device, batch_frames, lost_zncc). ``reference_update`` and
            ``smoothing`` are not supported (ValueError).

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
