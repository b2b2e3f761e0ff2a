"""The row-parallel runner: one kernel call over rows [0, n) on several threads, and the
library's thread scope.

ctypes releases the GIL, so a call's rows are split over :func:`threads` threads, the
calling thread and pool threads taking chunks in turn. No tensor whose pointer goes to C is
freed while C may still use it, and a call returns or raises (KeyboardInterrupt included)
only once no pool thread is inside the kernel (:class:`_Rows`); C code itself is never
interrupted. The pool's idle threads block (``queue.SimpleQueue.get``): they cost nothing
on a busy machine, whatever torch's OpenMP settings.

:func:`own_threads` (the scope a CPU solve runs in) keeps torch's intra-op (OpenMP) threads
out of the solve: inside it torch runs on one thread, and the library's parallel work (the
kernels here, :func:`run_tasks` for batches of torch work) on its own pool with the thread
count torch had. OpenMP threads that spin while waiting (libgomp's default unless
``OMP_WAIT_POLICY=PASSIVE`` was set before torch was imported) then never wake up in the
solve (issue 46).
"""

from __future__ import annotations

import _thread
import contextlib
import functools
import os
import queue
import threading
from collections.abc import Callable, Iterator

import torch

from torch_stsdic.kernels.native.declarations import Kernel

__all__ = ["run_rows", "run_shared", "run_tasks", "threads", "own_threads", "in_own_threads"]

# below this many samples a call runs on the calling thread (thread hand-off costs ~50 us)
_PARALLEL_MIN = 20_000


class _Scope:
    """The state of :func:`own_threads`: how many scopes are open (in any thread) and the
    library's threads inside them. Each thread's own torch count (OpenMP's is per thread)
    is saved and restored by that thread (``_Scope.local``)."""

    lock = threading.Lock()
    depth = 0
    threads: int | None = None
    local = threading.local()  # .depth, .torch_threads: this thread's scopes


def threads() -> int:
    """The kernels' threads: ``torch.get_num_threads()`` (``--threads``, ``OMP_NUM_THREADS``,
    else torch's default: the physical cores; inside :func:`own_threads`, the count torch had
    when the scope opened), at most the CPUs the scheduler lets this process run on
    (``os.sched_getaffinity``: a ``taskset``, a container's or a batch job's share; more
    threads than those only wait for each other)."""
    own = _Scope.threads
    n = max(1, own if own is not None else torch.get_num_threads())
    try:
        return max(1, min(n, len(os.sched_getaffinity(0))))
    except (AttributeError, OSError):  # not on Linux
        return n


class _Pool:
    """``size`` helper threads taking tasks from a queue.

    Made of the primitives a Ctrl-C cannot wedge: a ``queue.SimpleQueue`` (C) and threads
    started by ``_thread.start_new_thread``. (``threading.Event``, ``Condition``,
    ``queue.Queue`` and ``ThreadPoolExecutor`` take a lock in Python code; a KeyboardInterrupt
    raised in the calling thread just after that lock is taken leaves it taken for good, and
    the next call waits forever: seen once in CI and within ~2,000 interrupts in a stress
    loop.)"""

    def __init__(self, size: int) -> None:
        self.size, self.pid = size, os.getpid()
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        for _ in range(size):
            _thread.start_new_thread(self._work, (self.tasks,))

    @staticmethod
    def _work(tasks: queue.SimpleQueue) -> None:
        while True:
            task = tasks.get()
            if task is None:
                return
            task()  # _Rows.helper: catches everything itself
            # an idle thread holds no call (nor the tensors it points to) while it waits
            task = None

    def submit(self, task) -> None:
        self.tasks.put(task)

    def close(self) -> None:
        for _ in range(self.size):
            self.tasks.put(None)


_POOL: _Pool | None = None


def _pool(n: int) -> _Pool:
    """The helper threads (made again after a fork: a forked child has none of them)."""
    global _POOL
    if _POOL is None or _POOL.size != n or _POOL.pid != os.getpid():
        if _POOL is not None and _POOL.pid == os.getpid():
            _POOL.close()  # idle: every call waits for its helpers
        _POOL = _Pool(n)
    return _POOL


class _Rows:
    """One kernel call over rows [0, n) in chunks, taken in turn by the calling thread and
    helper threads of the pool.

    Nothing handed to C is freed while C may still use it: this object holds every tensor the
    arguments point to, and each helper holds this object. The call does not return, normally
    or by an exception (KeyboardInterrupt included), while a helper is inside the kernel: an
    exception in the calling thread stops the hand-out of chunks and waits for the chunks
    under way (at most one per helper; an interrupt during that wait is held back and the
    first exception propagates). The calling thread only ever takes ``lock`` in a ``with``
    (a C-level enter and exit) and waits on ``done``, a bare lock that the last helper to
    leave releases: an interrupt at any moment leaves nothing taken for good."""

    def __init__(self, kernel: Kernel, raw: list, keep: list, edges: list[int]):
        self.kernel, self.raw, self.keep, self.edges = kernel, raw, keep, edges
        self.lock = threading.Lock()
        self.done = _thread.allocate_lock()  # released by the last helper out
        self.next = 0
        self.busy = 0  # helpers inside the loop below
        self.stop = False
        self.failed: list = []  # (i0, i1, rc) or an exception of a helper

    def _take(self) -> int | None:
        with self.lock:
            j = self.next
            if self.stop or j >= len(self.edges) - 1:
                return None
            self.next = j + 1
        return j

    def _chunk(self, j: int) -> None:
        args = self.raw.copy()
        args[self.kernel.i0], args[self.kernel.i1] = self.edges[j], self.edges[j + 1]
        rc = self.kernel.fn(*args)
        if rc:
            self.failed.append((self.edges[j], self.edges[j + 1], rc))
            self.stop = True

    def helper(self) -> None:
        """A pool thread's part (signals are handled on the main thread only: no
        KeyboardInterrupt here)."""
        with self.lock:  # registered as busy before the calling thread can see it idle
            if self.stop or self.next >= len(self.edges) - 1:
                return
            self.busy += 1
        try:
            while (j := self._take()) is not None:
                self._chunk(j)
        except BaseException as exc:  # not expected (arguments are checked): report it
            self.failed.append(exc)
            self.stop = True
        finally:
            with self.lock:
                self.busy -= 1
                if not self.busy and self.done.locked():
                    self.done.release()

    def _wait(self, held: BaseException | None = None) -> BaseException | None:
        """Until no helper is inside the kernel; returns ``held``, else the first exception
        (e.g. a second Ctrl-C) that arrived meanwhile. (The waiting loop lies inside the
        ``try``: CPython checks for signals at its backward jump.)"""
        while True:
            try:
                while True:
                    with self.lock:  # a helper past its stop check is counted in busy now
                        if not self.busy:
                            return held
                    # the first pass takes ``done`` at once, the next waits for the last
                    # helper to release it (the timeout: a safety net, never needed)
                    self.done.acquire(True, 0.05)
            except BaseException as exc:
                held = held or exc
                self.stop = True

    def run(self, pool: _Pool, helpers: int) -> None:
        done = False
        held = None
        try:
            for _ in range(helpers):
                pool.submit(self.helper)
            while (j := self._take()) is not None:
                self._chunk(j)
            done = True
        finally:
            if not done:
                self.stop = True
            # a second interrupt can land at the entry of _wait, before its own try: wait
            # again (the call must not return while a helper is inside the kernel)
            while True:
                try:
                    held = self._wait(held)
                    break
                except BaseException as exc:
                    held = held or exc
                    self.stop = True
        if held is not None:
            raise held
        for f in self.failed:
            if isinstance(f, BaseException):
                raise f
            raise RuntimeError(f"{self.kernel.name} returned {f[2]} for rows [{f[0]}, {f[1]})")


@contextlib.contextmanager
def own_threads(device: torch.device | str | None = "cpu") -> Iterator[None]:
    """The scope of a CPU solve: torch's intra-op threads set to 1 inside, the library's
    parallel work (:func:`run_rows`, :func:`run_shared`, :func:`run_tasks`) on
    :func:`threads` threads of its own pool, as many as the threads that opened the open
    scopes had for torch (the most of them). Re-entrant and safe across threads: torch's
    count is per thread (OpenMP's), so each thread sets its own to 1 on its first scope and
    restores it on leaving its last, whatever other threads (a frame prefetcher) do in
    between. Does nothing for another device than the CPU."""
    if device is not None and torch.device(device).type != "cpu":
        yield
        return
    local = _Scope.local
    first = getattr(local, "depth", 0) == 0
    if first:
        local.torch_threads = torch.get_num_threads()
        if local.torch_threads != 1:
            torch.set_num_threads(1)
    local.depth = getattr(local, "depth", 0) + 1
    with _Scope.lock:
        n = max(1, local.torch_threads)
        _Scope.threads = n if _Scope.depth == 0 else max(n, _Scope.threads or 1)
        _Scope.depth += 1
    try:
        yield
    finally:
        with _Scope.lock:
            _Scope.depth -= 1
            if _Scope.depth == 0:
                _Scope.threads = None
        local.depth -= 1
        if local.depth == 0 and torch.get_num_threads() != local.torch_threads:
            torch.set_num_threads(local.torch_threads)


def in_own_threads(index: int, name: str) -> Callable:
    """Decorator: the function runs in :func:`own_threads` for the device of its argument at
    position ``index`` or keyword ``name`` (a tensor; CPU where absent)."""

    def decorate(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def scoped(*args, **kwargs):
            t = args[index] if len(args) > index else kwargs.get(name)
            with own_threads(getattr(t, "device", "cpu")):
                return fn(*args, **kwargs)

        return scoped

    return decorate


class _Tasks(_Rows):
    """Python callables (torch work on disjoint outputs, which releases the GIL) taken in turn
    by the calling thread and pool threads, with :class:`_Rows`' guarantees: the call returns
    or raises only once no helper runs a task; the first exception propagates."""

    def __init__(self, tasks: list[Callable[[], None]]):
        super().__init__(None, [], [], list(range(len(tasks) + 1)))  # type: ignore[arg-type]
        self.tasks = tasks

    def _chunk(self, j: int) -> None:
        self.tasks[j]()


def run_tasks(tasks: list[Callable[[], None]]) -> None:
    """Run ``tasks`` (each writes its own part of the outputs) on :func:`threads` threads of
    the library's pool inside :func:`own_threads` (torch on one thread per task); outside
    it, one after the other on the calling thread (torch's own threads split each)."""
    n = min(threads(), len(tasks))
    if n <= 1 or _Scope.depth == 0:
        for task in tasks:
            task()
        return
    _Tasks(tasks).run(_pool(threads() - 1), n - 1)


def run_rows(kernel: Kernel, n_rows: int, work_per_row: int, args: dict,
             parts: int | None = None) -> None:
    """Call ``kernel`` with ``args`` (every parameter but i0, i1, by name) over the rows
    [0, n_rows), split over :func:`threads` threads when that pays (in ``parts`` ranges;
    default 4 a thread, which evens out uneven rows)."""
    if "i0" in args or "i1" in args or kernel.i0 is None or kernel.i1 is None:
        raise TypeError(f"{kernel.name}: the rows i0, i1 are set by run_rows")
    raw, keep = kernel.bind({**args, "i0": 0, "i1": n_rows})
    if n_rows <= 0:
        return
    threads = _threads()
    if threads == 1 or n_rows * work_per_row < _PARALLEL_MIN or n_rows < 2:
        # on this thread alone: a Ctrl-C is raised only once C returned, and keep holds the
        # tensors until then
        rc = kernel.fn(*raw)
        del keep
        if rc:
            raise RuntimeError(f"{kernel.name} returned {rc}")
        return
    parts = min(threads * 4 if parts is None else max(1, parts), n_rows)
    edges = [n_rows * j // parts for j in range(parts + 1)]
    _Rows(kernel, raw, keep, edges).run(_pool(threads - 1), min(threads, parts) - 1)


class _Shared(_Rows):
    """One kernel call per thread, every one over all rows: the kernel hands its rows out
    itself (a shared counter), so a thread that is descheduled holds back only the rows it
    took, and no thread waits for another until the end of the call."""

    def _chunk(self, j: int) -> None:
        rc = self.kernel.fn(*self.raw)
        if rc:
            self.failed.append((self.edges[0], self.edges[-1], rc))
            self.stop = True


def run_shared(kernel: Kernel, n_rows: int, work_per_row: int, args: dict,
               threads: int | None = None) -> None:
    """Call ``kernel`` with ``args`` (every parameter but i0, i1) once on each of ``threads``
    threads (default :func:`threads`), each call over all rows [0, n_rows): the
    kernel takes its rows from a shared counter in ``args`` (zeroed by the caller). Small
    calls run on the calling thread alone."""
    if "i0" in args or "i1" in args or kernel.i0 is None or kernel.i1 is None:
        raise TypeError(f"{kernel.name}: the rows i0, i1 are set by run_shared")
    raw, keep = kernel.bind({**args, "i0": 0, "i1": n_rows})
    if n_rows <= 0:
        return
    threads = min(max(1, _threads() if threads is None else int(threads)), n_rows)
    if threads == 1 or n_rows * work_per_row < _PARALLEL_MIN:
        rc = kernel.fn(*raw)
        del keep
        if rc:
            raise RuntimeError(f"{kernel.name} returned {rc}")
        return
    edges = list(range(threads + 1))  # one call per thread (its "chunk")
    _Shared(kernel, raw, keep, edges).run(_pool(threads - 1), threads - 1)


_threads = threads  # (the runners' name for it: run_shared's parameter shadows the function)
