"""Where samples are solved: local worker processes (default) or a Dask distributed cluster.

An executor takes a :class:`~.worker.Recipe` once and then solves work items (a
:class:`~.worker.Task` or a :class:`~.batch.Batch` of them), yielding each item's list of
:class:`~.worker.SampleResult`\\ s in completion order. Workers only compute; the
parent process alone writes the store, so no two processes ever write the same chunk.

Determinism: every worker runs its BLAS single-threaded, so a sample's bits do not depend on
where it ran: local workers are spawned with ``OMP/OPENBLAS/MKL_NUM_THREADS=1``, and every
worker (Dask's too, whatever its environment says) also limits the BLAS libraries it has
loaded to one thread at run time (threadpoolctl) before its first solve.
A local worker also exits by itself when its parent process dies (``kill -9``).

Stopping: local workers ignore SIGINT (Ctrl+C reaches the whole process group, but only the
parent decides); when the parent leaves the executor by an exception (Ctrl+C, SIGTERM turned
into one by the CLI, an error), it stops the workers at once and waits for them, so that the
pool's queues and locks are released before the process exits (no leaked semaphores) and the
samples the parent has written stay in the store for the next run to continue from. A result a
stopped worker had half sent does not hold the shutdown up (:meth:`LocalExecutor._stop_workers`).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import time
from typing import Iterable, Iterator

from ..errors import DatasetError, require
from .batch import Batch, solve_item
from .worker import Recipe, SampleResult, Task, context_for

__all__ = ["LocalExecutor", "DaskExecutor", "make_executor", "default_workers", "single_threaded_blas",
           "sigterm_as_interrupt"]

log = logging.getLogger(__name__)

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
                "NUMEXPR_NUM_THREADS")
_RECIPE: Recipe | None = None
_BARRIER = None  # this local worker's pool-wide barrier (LocalExecutor start-up and update)
#: Seconds a local worker waits for the others while the pool takes a new recipe.
UPDATE_TIMEOUT = 600.0
#: Seconds the parent waits for each terminated worker process to end when stopping.
STOP_TIMEOUT = 10.0
#: The parent waits on its workers this long at a time (a stop signal acts in between).
POLL_SECONDS = 0.2


def default_workers(memory_gib: float = 0.0) -> int:
    """Automatic number of local workers: one per CPU this process may run on (its affinity
    mask where the platform has one, e.g. a container's or a batch job's share; else the CPU
    count), and with ``memory_gib`` > 0 (GiB a worker's batch may hold, ``dataset.batch_memory``)
    no more than the memory now available holds (Linux' ``MemAvailable``); at least 1. Each
    worker runs its BLAS on one thread."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity masks on this platform (macOS, Windows)
        cpus = os.cpu_count() or 1
    available = _available_memory_gib()
    if memory_gib > 0.0 and available is not None:
        cpus = min(cpus, int(available // memory_gib))
    return max(1, cpus)


def _available_memory_gib() -> float | None:
    """``MemAvailable`` of ``/proc/meminfo`` in GiB, or None where there is none."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2.0**20  # kB
    except (OSError, ValueError, IndexError):
        pass
    return None


class _Terminated(KeyboardInterrupt):
    """SIGTERM received while a data set is being made (see :func:`sigterm_as_interrupt`)."""


class _StopSignals:
    """SIGTERM and SIGINT handlers that stop a run at a safe point (see :func:`sigterm_as_interrupt`).

    Outside :meth:`deferred` a signal acts at once, as the previous handler would (SIGTERM with
    its default action raises :class:`_Terminated` instead of ending the process). Inside it
    (the parent waiting on its workers, holding the pool's locks in between) the signal is
    only recorded and acts when the block is left, so that no lock of the pool stays taken by
    an exception raised in the middle of acquiring it."""

    def __init__(self) -> None:
        self.previous: dict = {}
        self.depth = 0
        self.pending: list = []

    def handle(self, signum, frame) -> None:
        if self.depth:
            self.pending.append((signum, frame))
            return
        self.act(signum, frame)

    def act(self, signum, frame) -> None:
        previous = self.previous.get(signum, signal.SIG_DFL)
        if callable(previous):
            previous(signum, frame)  # e.g. the CLI's SIGTERM handler, Python's KeyboardInterrupt
        elif previous == signal.SIG_DFL:
            raise _Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    @contextlib.contextmanager
    def deferred(self):
        """A block in which the signals wait (see the class notes)."""
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1
            if not self.depth and self.pending:
                signum, frame = self.pending.pop(0)
                self.pending.clear()
                self.act(signum, frame)


_SIGNALS = _StopSignals()


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block, SIGTERM (``kill``, ``timeout``) raises a KeyboardInterrupt in the main
    thread, so that a run stops as after Ctrl+C: the executor stops its workers and releases
    its locks, the finished samples are saved (module notes); both signals wait for a safe
    point while the parent waits on its workers (:class:`_StopSignals`). Only in the main
    thread, for signals not ignored; the previous handlers are restored after."""
    if threading.current_thread() is not threading.main_thread() or _SIGNALS.previous:
        yield
        return
    for signum in (signal.SIGTERM, signal.SIGINT):
        previous = signal.getsignal(signum)
        if previous not in (signal.SIG_IGN, None):
            _SIGNALS.previous[signum] = previous
            signal.signal(signum, _SIGNALS.handle)
    try:
        yield
    finally:
        for signum, previous in _SIGNALS.previous.items():
            signal.signal(signum, previous)
        _SIGNALS.previous.clear()


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            os._exit(0)  # the parent is gone (e.g. kill -9): stop solving for nobody


_BLAS_LIMIT = None  # this process's threadpoolctl limiter, kept alive


def single_threaded_blas() -> None:
    """Limit every BLAS/OpenMP library loaded in this process to one thread (once per process).

    A multi-threaded BLAS sums in another order, so CHOLMOD factors and the solutions built
    on them would differ in their last bits with the thread count; a Dask worker started with
    ``OPENBLAS_NUM_THREADS=2`` gave a different store than local workers without this.
    """
    global _BLAS_LIMIT
    if _BLAS_LIMIT is None:
        require("threadpoolctl", "data", "single-threaded BLAS in data-set workers")
        from ..fem.linear import one_blas_thread

        _BLAS_LIMIT = one_blas_thread()


def _init_worker(parent: int, barrier) -> None:
    global _BARRIER
    _BARRIER = barrier
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C is the parent's to handle (module notes)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    single_threaded_blas()


def _run(item: Task | Batch) -> list[SampleResult]:
    return solve_item(_RECIPE, item)


def _take_recipe(recipe: Recipe) -> None:
    """Make ``recipe`` this worker's (its context built or upgraded now: mesh, problem and
    solver once per process), then wait until every worker of the pool holds one of these
    calls, so that each takes exactly one."""
    global _RECIPE
    _RECIPE = recipe
    try:
        context_for(recipe)
    except BaseException:
        _BARRIER.abort()  # the others stop waiting for this one (their calls end BrokenBarrierError)
        raise
    _BARRIER.wait(UPDATE_TIMEOUT)


_NO_MAIN_GUARD = ("Worker processes are spawned: they import the script that started them, so a script that runs "
                  "simulations at its top level must put them under `if __name__ == \"__main__\":`")


def refuse_in_starting_worker() -> None:
    """Raise DatasetError in a spawned worker that is still importing the script that started it
    (a script without a main guard runs its simulations again there): the worker prints why and
    exits. :func:`~.generate.simulate` calls it first, before the store is opened.

    Raises:
        DatasetError: naming the fix.
    """
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise DatasetError(_NO_MAIN_GUARD)


class LocalExecutor:
    """A pool of ``workers`` spawned processes, each holding one reusable solver."""

    def __init__(self, recipe: Recipe, workers: int):
        self.recipe, self.workers = recipe, int(workers)
        self._pool: cf.ProcessPoolExecutor | None = None

    def __enter__(self) -> "LocalExecutor":
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})  # inherited by the spawned workers only
        try:
            mp = multiprocessing.get_context("spawn")
            # The recipe (megabytes: mesh, basis, scenario) goes through the task queue, not
            # the spawn pipe: the parent writes a new process's start-up data whole and
            # holds the pipe's other end until it is written, so a worker that dies before
            # reading it (a script without a main guard) would leave that write waiting forever.
            self._pool = cf.ProcessPoolExecutor(
                self.workers, mp_context=mp, initializer=_init_worker, initargs=(os.getpid(), mp.Barrier(self.workers)))
            self._take_all(self.recipe, "the worker processes could not start (their errors are printed above). "
                           + _NO_MAIN_GUARD)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._close(stop=exc_type is not None)  # stopped or failed: the solves in flight are not waited for

    def _close(self, stop: bool) -> None:
        """Shut the pool down (``stop``: terminating the workers first) and drop it."""
        if self._pool is not None:
            with _SIGNALS.deferred():  # a second Ctrl+C does not break the clean-up
                if stop:
                    self._stop_workers()
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None

    def _take_all(self, recipe: Recipe, broken: str) -> None:
        """Give every worker ``recipe`` (:func:`_take_recipe`, one call each) and wait for all.
        A worker's own error (it could not build its solver) is raised as it is; a broken pool,
        or a worker that waited past ``UPDATE_TIMEOUT`` for the others, raises DatasetError
        ``broken`` (or says that building took too long). On any error the pool is stopped."""
        futures = [self._pool.submit(_take_recipe, recipe) for _ in range(self.workers)]
        try:
            cf.wait(futures)
        except BaseException:
            self._close(stop=True)
            raise
        errors = [e for e in (f.exception() for f in futures) if e is not None]
        if not errors:
            return
        self._close(stop=True)
        pool_errors = (cf.process.BrokenProcessPool, threading.BrokenBarrierError)
        own = [e for e in errors if not isinstance(e, pool_errors)]
        if own:
            raise own[0]
        if not any(isinstance(e, cf.process.BrokenProcessPool) for e in errors):
            raise DatasetError(f"a worker took more than {UPDATE_TIMEOUT:.0f} s to build its solver from the "
                               "recipe while the others waited; run the same command again (the samples "
                               "finished so far are saved), with fewer workers if memory is short") from errors[0]
        raise DatasetError(broken) from errors[0]

    def _stop_workers(self) -> None:
        """Terminate the worker processes (they only compute; the parent alone writes) and
        wait until they are gone."""
        processes = list((self._pool._processes or {}).values())  # no public handle before Python 3.14
        for p in processes:
            if p.is_alive():
                p.terminate()
        for p in processes:
            p.join(STOP_TIMEOUT)
            if p.is_alive():  # deaf to SIGTERM (e.g. a wedged native library): SIGKILL
                p.kill()
                p.join(STOP_TIMEOUT)
        # A worker terminated while it sent its result leaves part of a message in the result
        # pipe, and the pool's manager thread would wait for the rest forever (shutdown then
        # hangs). The parent never writes to that pipe: with its own write end closed as well,
        # that read ends (EOF) once the workers are gone, and the pool reports itself broken.
        results = getattr(self._pool, "_result_queue", None)  # no public handle (Python 3.11-3.13)
        writer = getattr(results, "_writer", None)
        if writer is not None and all(not p.is_alive() for p in processes):
            writer.close()

    def update(self, recipe: Recipe) -> None:
        """Give every worker ``recipe`` instead of the current one (call with no work in flight).

        The workers keep their processes, and their solvers when only the reduced-order
        predictor changed (:func:`~.worker.context_for`): no new processes, imports or
        factorisations, as a new pool would need.
        """
        self._take_all(recipe, "a worker process stopped or stalled while taking the reduced model; the samples "
                               "finished so far are saved: run the same command again to continue")
        self.recipe = recipe

    def imap_unordered(self, tasks: Iterable[Task | Batch]) -> Iterator[list[SampleResult]]:
        """Solve work items; yield each one's results as it completes. Items are taken from
        the iterable only as workers become free (at most ``WINDOW_PER_WORKER`` per worker in
        flight)."""
        source = iter(tasks)
        futures: set = set()
        try:
            while True:
                with _SIGNALS.deferred():  # a stop acts between waits, not inside the pool's locks
                    _fill(futures, source, lambda t: self._pool.submit(_run, t), WINDOW_PER_WORKER * self.workers)
                    if not futures:
                        return
                    finished, _ = cf.wait(futures, timeout=POLL_SECONDS, return_when=cf.FIRST_COMPLETED)
                if not finished:
                    yield []  # still solving: the caller may say so
                for f in sorted(finished, key=id):
                    futures.discard(f)
                    try:
                        result = f.result()
                    except cf.process.BrokenProcessPool as exc:
                        raise DatasetError(
                            "a worker process stopped abruptly (killed, or out of memory: try fewer --workers); the "
                            "samples finished so far are saved: run the same command again to continue") from exc
                    yield result
        except GeneratorExit:  # the caller stopped early without an error: drop the queued items
            for f in futures:
                f.cancel()
            raise
        # on an exception (Ctrl+C, SIGTERM) nothing is cancelled here: __exit__ stops the
        # workers and the pool fails the outstanding futures itself (cancelling them first
        # races with that in Python 3.11 and can leave the pool's manager thread dead)

    def describe(self) -> str:
        return f"{self.workers} local worker process{'es' if self.workers != 1 else ''}"


def _dask_run(recipe: Recipe, item: Task | Batch) -> list[SampleResult]:
    single_threaded_blas()
    return solve_item(recipe, item)


class DaskExecutor:
    """Tasks on a Dask distributed cluster at ``address`` (``tcp://HOST:PORT``).

    The recipe is scattered to every worker once; each Dask worker process builds its
    solver on its first task and reuses it.
    """

    def __init__(self, recipe: Recipe, address: str):
        self.recipe, self.address = recipe, address
        self._client = None
        self._recipe_future = None  # the recipe scattered to the workers (on __enter__)

    @property
    def workers(self) -> int:
        """Tasks the cluster solves at once (its workers' threads, summed; 1 before connecting)."""
        if self._client is None:
            return 1
        return max(sum(self._client.nthreads().values()), 1)

    def __enter__(self) -> "DaskExecutor":
        distributed = require("distributed", "data", "running simulations on a Dask cluster")
        self._client = distributed.Client(self.address, timeout="30s", set_as_default=False)
        self._recipe_future = self._client.scatter(self.recipe, broadcast=True, hash=False)
        return self

    def __exit__(self, *exc) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def update(self, recipe: Recipe) -> None:
        """Scatter ``recipe`` to every worker in place of the current one; each worker upgrades
        its context on its next task (keeping its solvers when only the predictor changed)."""
        self._recipe_future = self._client.scatter(recipe, broadcast=True, hash=False)
        self.recipe = recipe

    def imap_unordered(self, tasks: Iterable[Task | Batch]) -> Iterator[list[SampleResult]]:
        """Solve work items on the cluster; yield each one's results as it completes. Items
        are taken from the iterable only as results come back (``WINDOW_PER_WORKER`` per
        worker thread in flight)."""
        distributed = require("distributed", "data", "running simulations on a Dask cluster")
        source = iter(tasks)
        window = WINDOW_PER_WORKER * max(1, sum(self._client.nthreads().values()))
        futures: set = set()

        def submit(t):
            return self._client.submit(_dask_run, self._recipe_future, t, pure=False)

        _fill(futures, source, submit, window)
        queue = distributed.as_completed(list(futures), loop=self._client.loop)
        try:
            while not queue.is_empty():
                if not queue.has_ready():
                    time.sleep(POLL_SECONDS)
                    yield []  # still solving: the caller may say so
                    continue
                f = next(queue)
                futures.discard(f)
                result = f.result()
                for new in _fill(futures, source, submit, window):
                    queue.add(new)
                yield result
        finally:
            self._client.cancel(list(futures))

    def describe(self) -> str:
        n = len(self._client.nthreads()) if self._client else 0
        return f"Dask cluster {self.address} ({n} workers)"


#: Tasks in flight per worker: enough to keep it busy, few enough that the tasks handed out
#: later carry up-to-date budgets (:mod:`.supervise`).
WINDOW_PER_WORKER = 2


def _fill(futures: set, source, submit, window: int) -> list:
    """Submit tasks from ``source`` until ``window`` are in flight; returns the new futures."""
    new = []
    while len(futures) < window:
        task = next(source, None)
        if task is None:
            break
        f = submit(task)
        futures.add(f)
        new.append(f)
    return new


def make_executor(recipe: Recipe, *, scheduler: str = "", workers: int = 0, memory_gib: float = 0.0):
    """A Dask executor when ``scheduler`` names one, else local processes (``workers`` 0 = auto:
    :func:`default_workers` with ``memory_gib`` GiB a worker)."""
    if scheduler:
        return DaskExecutor(recipe, scheduler)
    return LocalExecutor(recipe, workers or default_workers(memory_gib))
