"""Watching the solves of a data set: per-sample time budgets and progress that says what is slow.

Every phase of :func:`~.generate.simulate` (each calibration round, the predictor's basis
samples, the pending samples) runs its tasks through a :class:`Supervisor`:

* **Budget**: each task pulled by the executor carries ``budget`` = ``dataset.time_budget``
  times the running median of the worker seconds of the phase's finished samples (at least
  ``dataset.time_budget_min`` seconds; until ``MEDIAN_MIN_SAMPLES`` have finished, the previous
  phase's median stands in, so the first tasks of a calibration round are limited too).
  A solver attempt that runs past it is stopped; the sample goes on with its cautious retries
  and, if those stall or fail too, is recorded failed with the reason (:mod:`.worker`).
  Samples within their budget are not affected, so stores stay bit-identical; a sample that
  was stopped depends on the machine's speed (its reason says so).
* **Progress**: a tqdm bar per phase on a terminal, else a log line at the phase's first
  result and then every ``LOG_SECONDS``: what the phase is (``calibration round 2 (at most
  10)``), samples done, samples/s, the ETA, and how many were slow; every finished sample
  slower than ``SLOW_FACTOR`` x the running median is one warning at once, saying what it
  means, and the phase's last line names the slowest. Until a few results have come in, the
  ETA is the running median of the worker seconds times the waves of tasks left on the
  workers (a rate needs more results) and the line calls it rough. A phase may add
  an outlook to each line (the calibration's ETA as a whole, :mod:`.calibrate`).
* **Heartbeat**: while nothing finishes (a slow sample, a batch of hard ones) a line every
  ``LOG_SECONDS`` says the phase is still solving, how long since the last result, the median
  and the budget that will stop a stalled attempt: a run never goes quiet.
* **Counts**: each phase's results are summed into a :class:`~.phase_stats.PhaseStats`
  (:attr:`Supervisor.phases`): where the run's time went.

The executor pulls tasks lazily (a bounded window per worker), so a budget reflects the
median at the time the task is handed out.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import sys
import time
from typing import Iterable, Iterator

from .batch import Batch
from .codes import SampleStatus
from .phase_stats import PhaseStats, eta_text, work_seconds
from .worker import SampleResult, Task

__all__ = ["Supervisor", "SampleClock", "SLOW_FACTOR", "SLOW_MIN_SECONDS", "MEDIAN_MIN_SAMPLES", "LOG_SECONDS"]

log = logging.getLogger(__name__)

#: A finished sample this many times slower than the running median is reported.
SLOW_FACTOR = 10.0
#: Samples faster than this (s) are never reported slow, whatever the median.
SLOW_MIN_SECONDS = 1.0
#: Finished samples needed before the median sets budgets and flags slow samples.
MEDIAN_MIN_SAMPLES = 3
#: Without a terminal, a progress line at most this often, s.
LOG_SECONDS = 30.0


class SampleClock:
    """Running median of the worker seconds of finished samples, and the budget it sets.

    Args:
        factor: budget = ``factor`` x median (0: no budget).
        floor: the budget is at least this many seconds.
        fallback: median seconds to use until ``MEDIAN_MIN_SAMPLES`` have finished (the
            previous phase's; None: no budget until then).
    """

    def __init__(self, factor: float, floor: float, fallback: float | None = None) -> None:
        self.factor, self.floor, self.fallback = float(factor), float(floor), fallback
        self._seconds: list[float] = []
        self.slow: list[tuple[int, float, float]] = []  # (sample, seconds, x median)

    @property
    def median(self) -> float | None:
        """Median seconds of the samples so far (None before ``MEDIAN_MIN_SAMPLES``)."""
        return self.median_so_far if len(self._seconds) >= MEDIAN_MIN_SAMPLES else None

    @property
    def median_so_far(self) -> float | None:
        """Median seconds of every sample so far, however few (None before the first)."""
        s = self._seconds
        if not s:
            return None
        m = len(s) // 2
        return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])

    def budget(self) -> float:
        """Seconds a solver attempt of the next task may run (0 = no limit)."""
        median = self.median if self.median is not None else self.fallback
        if not self.factor or median is None:
            return 0.0
        return max(self.factor * median, self.floor)

    def add(self, index: int, seconds: float) -> float | None:
        """Record a finished sample; returns its ratio to the median before it when that is
        above ``SLOW_FACTOR`` and the sample took more than ``SLOW_MIN_SECONDS`` (it is then
        kept in :attr:`slow`), else None."""
        median = self.median
        bisect.insort(self._seconds, float(seconds))
        if median is not None and median > 0 and seconds > max(SLOW_FACTOR * median, SLOW_MIN_SECONDS):
            self.slow.append((int(index), float(seconds), float(seconds / median)))
            return seconds / median
        return None


class Supervisor:
    """Runs tasks on an executor with budgets and progress (see the module notes).

    Args:
        executor: has ``imap_unordered(items) -> lists of results`` pulling work items lazily
            (an empty list where a wait ended with nothing finished).
        factor, floor: ``dataset.time_budget`` and ``dataset.time_budget_min``.
        progress: show a bar on a terminal / log progress lines.
    """

    def __init__(self, executor, factor: float, floor: float, progress: bool = True) -> None:
        self.executor, self.factor, self.floor, self.progress = executor, factor, floor, progress
        self.slow: list[tuple[str, int, float, float]] = []  # (phase, sample, seconds, x median)
        self.stopped: list[tuple[str, int]] = []  # (phase, sample) of samples stopped by a budget
        self.last_median: float | None = None  # of the last phase: the next one's budget until it has its own
        self.phases: list[PhaseStats] = []  # the counts of every phase run so far

    @property
    def workers(self) -> int:
        """Tasks the executor solves at once (its worker processes or cluster threads)."""
        return max(int(self.executor.workers), 1)

    def run(self, tasks: Iterable[Task | Batch], phase: str, total: int | None = None, done: int = 0,
            unit: str = "sample", outlook=None) -> Iterator[SampleResult]:
        """Solve ``tasks`` (each given the budget of the moment it is handed out); yield the
        results as they complete.

        Args:
            tasks: the phase's tasks, or :class:`~.batch.Batch`\\ es of them (their results
                come one by one all the same).  phase: what the phase is, for the messages.
            total, done: the bar's total and starting count (default: the tasks, 0).
            unit: what a task is, for the messages ("sample", "pilot").
            outlook: optional ``f(eta_seconds, median_seconds) -> str`` whose text ends each
                progress line (e.g. the whole calibration's ETA).
        """
        tasks = list(tasks)
        clock = SampleClock(self.factor, self.floor, self.last_median)
        n = sum(len(t.tasks) if isinstance(t, Batch) else 1 for t in tasks)
        stats = PhaseStats(phase, unit)
        bar = _Bar(phase, n + done if total is None else total, done, unit, self.progress, self.workers, outlook)
        stamped = (_with_budget(t, clock.budget()) for t in tasks)
        try:
            for r in self._results(stamped, bar, clock):
                stats.add(r)
                ratio = clock.add(r.index, r.seconds)
                if ratio is not None:
                    self.slow.append((phase, r.index, r.seconds, ratio))
                    log.warning("%s: %s %d took %.1f s, %.0fx the median %.2f s (%s); %s", phase, unit, r.index,
                                r.seconds, ratio, r.seconds / ratio, _outcome(r), _slow_advice(r))
                if "SolveTimeout" in r.reason:
                    self.stopped.append((phase, r.index))
                bar.update(r, clock)
                yield r
        finally:
            bar.close(clock)
            self.last_median = clock.median if clock.median is not None else self.last_median
            self.phases.append(stats.close(clock.median_so_far))

    def _results(self, items, bar: "_Bar", clock: SampleClock) -> Iterator[SampleResult]:
        """The executor's results one by one; an empty list from the executor (a wait that
        ended with nothing finished) lets the bar say that the phase is still solving."""
        for results in self.executor.imap_unordered(items):
            if not results:
                bar.waiting(clock)
            yield from results


def _with_budget(item: Task | Batch, budget: float) -> Task | Batch:
    if isinstance(item, Batch):
        return Batch(tuple(dataclasses.replace(t, budget=budget) for t in item.tasks))
    return dataclasses.replace(item, budget=budget)


def _outcome(r: SampleResult) -> str:
    if r.reason:
        return ("failed: " if r.status != SampleStatus.DONE else "") + r.reason[:300]
    return f"{r.iterations} Newton iterations, {r.factorizations} factorisations, {r.attempts} attempt(s)"


class _Bar:
    """tqdm bar on a terminal, plain log lines otherwise."""

    def __init__(self, phase: str, total: int, done: int, unit: str, enabled: bool, workers: int = 1,
                 outlook=None) -> None:
        self.phase, self.total, self.count, self.start, self.unit = phase, total, done, done, unit
        self.t0 = self.last = self.finished = time.monotonic()
        self.enabled, self.workers, self.outlook = enabled, workers, outlook
        self.failed = 0
        self.bar = None
        if enabled and total and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit=unit, desc=phase, dynamic_ncols=True)

    def eta(self, clock: SampleClock, now: float) -> float:
        """Seconds left in the phase: by the rate once every worker has returned a few
        results, before that by the median worker seconds and the waves of tasks left."""
        got = self.count - self.start
        left = self.total - self.count
        if got >= 3 * self.workers:
            return left * (now - self.t0) / got
        median = clock.median_so_far
        return float("inf") if median is None else work_seconds(left, median, self.workers)

    def update(self, r: SampleResult, clock: SampleClock) -> None:
        self.count += 1
        self.failed += int(r.status != SampleStatus.DONE)
        now = self.finished = time.monotonic()
        eta = self.eta(clock, now)
        more = self.outlook(eta, clock.median_so_far) if self.outlook is not None else ""
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(f"failed={self.failed}, slow={len(clock.slow)}{more}", refresh=False)
            return
        first = self.count == self.start + 1
        if self.enabled and (first or now - self.last > LOG_SECONDS or self.count == self.total):
            self.last = now
            got = self.count - self.start
            rate = got / max(now - self.t0, 1e-9)
            rough = (f" (rough: from {got} {self.unit}{'s' if got > 1 else ''})"
                     if got < 3 * self.workers and self.count < self.total else "")
            slow = f"; {len(clock.slow)} slow so far (warned above)" if clock.slow else ""
            log.info("%s: %d/%d %ss (%d failed), %.2f %ss/s, ETA %s%s%s%s", self.phase, self.count, self.total,
                     self.unit, self.failed, rate, self.unit, eta_text(eta), rough, more, slow)

    def waiting(self, clock: SampleClock) -> None:
        """Nothing finished in the last wait: once ``LOG_SECONDS`` have passed without a result
        and without a progress line, say what is running and for how long (on a terminal, in
        the bar's text)."""
        now = time.monotonic()
        if not self.enabled or now - max(self.last, self.finished) <= LOG_SECONDS:
            return
        self.last = now
        median, budget = clock.median_so_far, clock.budget()
        if self.count == self.start:
            quiet = f"no {self.unit} finished in the {now - self.t0:.0f} s since the phase began"
        else:
            quiet = f"none finished in the last {now - self.finished:.0f} s"
        typical = f"; the median {self.unit} took {median:.1f} s" if median is not None else ""
        limit = (f"; a solver attempt past {budget:.0f} s is stopped and the {self.unit} retried cautiously"
                 if budget > 0 else "")
        text = f"still solving ({quiet}{typical}{limit})"
        if self.bar is not None:
            self.bar.set_postfix_str(f"failed={self.failed}, {text}")
            return
        log.info("%s: %d/%d %ss (%d failed), %s", self.phase, self.count, self.total, self.unit, self.failed, text)

    def close(self, clock: SampleClock) -> None:
        if self.bar is not None:
            self.bar.close()
        n = self.count - self.start
        if self.enabled and n:
            median = clock.median
            log.info("%s: %d %ss in %.1f s%s%s", self.phase, n, self.unit, time.monotonic() - self.t0,
                     f", median {median:.2f} s of worker time" if median is not None else "", _slow_text(clock))


def _slow_text(clock: SampleClock) -> str:
    if not clock.slow:
        return ""
    worst = sorted(clock.slow, key=lambda s: -s[2])[:3]
    return f"; {len(clock.slow)} slow, the slowest " + ", ".join(f"{i} ({s:.1f} s, {x:.0f}x)" for i, s, x in worst)


def _slow_advice(r: SampleResult) -> str:
    """What a slow sample means for the user."""
    if r.status != SampleStatus.DONE:
        return "it is recorded failed with its reason, the data set goes on without it"
    return ("it is kept (it converged); nothing to do unless many are slow: large displacements near the solver's "
            "limit, lower [forces] target_max_displacement (or the scenario's loads) then")
