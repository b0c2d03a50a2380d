"""Where a data-set run's time goes: the counts of each phase, and the estimates of what is left.

:class:`PhaseStats` sums the results of one phase of :func:`~.generate.simulate` (a calibration
round, the reduced model's basis samples, the sample phase): wall-clock and worker seconds,
worker CPU seconds, Newton iterations, factorisations, retried and failed samples, and the
failures grouped by their kind. The run's summary lists them (``run["phases"]``;
``benchmarks/organ_speed.py`` prints them as a table). Nothing here is stored: a store's
bits do not depend on it.

:func:`eta_text` and :func:`work_seconds` turn a median of worker seconds into the wall-clock
seconds of work spread over the workers, for the progress lines' estimates.
"""

from __future__ import annotations

import re
import time
from collections import Counter
from dataclasses import dataclass, field

from ..mesh.run_cost import duration_text
from .codes import SampleStatus

__all__ = ["PhaseStats", "failure_kind", "work_seconds", "eta_text", "whole_set_eta", "PREDICTED_SHARE"]

#: A sample solved from the reduced model's prediction (in a batch) takes between these shares of
#: the worker seconds of a calibration pilot of the last round, which starts from its previous
#: round's solution (measured: 0.68 on a 3465-vertex brain mesh with the paper preset, 2.4 on the
#: phantom and 3.3 on the brain with the embedded preset, 3.9 on a thin-walled vessel with a soft wall;
#: docs/scaling.md); a basis sample, from the interim model's prediction, between 1 and the upper one.
PREDICTED_SHARE = (0.5, 4.0)

_NUMBER = re.compile(r"[-+]?\d+(\.\d+)?([eE][-+]?\d+)?")
_ATTEMPT = re.compile(r"\d+[^:]*: (.*)", re.S)  # "N from the prediction, ...: <what>" of an attempt


def failure_kind(reason: str) -> str:
    """The kind of a failed sample's reason (its last attempt's exception and the first words of
    its message, numbers replaced by ``#``), so that failures group by what stopped them."""
    last = reason.rsplit("; attempt ", 1)[-1] if "; attempt " in reason else reason.removeprefix("attempt ")
    found = _ATTEMPT.match(last)
    what = found.group(1) if found else last
    what = _NUMBER.sub("#", what.split(" (", 1)[0].split(";", 1)[0])
    return what.strip()[:90] or "unknown"


def work_seconds(tasks: int, median: float, workers: int) -> float:
    """Wall-clock seconds of ``tasks`` tasks of ``median`` worker seconds each on ``workers``
    workers (whole waves: the last wave takes as long as a full one)."""
    if tasks <= 0:
        return 0.0
    waves = -(-int(tasks) // max(int(workers), 1))
    return waves * float(median)


def whole_set_eta(median: float, basis: int, samples: int, workers: int) -> tuple[float, float]:
    """The range of seconds the rest of a data set takes after its calibration, (low, high):
    ``basis`` reduced-model basis samples at 1 to ``PREDICTED_SHARE[1]`` times ``median`` (the
    last calibration round's median pilot, worker seconds) and ``samples`` more at
    ``PREDICTED_SHARE`` of it, on ``workers`` workers (the reduced model's fit in the parent not
    counted)."""
    low, high = PREDICTED_SHARE
    return (work_seconds(basis, median, workers) + work_seconds(samples, low * median, workers),
            work_seconds(basis, high * median, workers) + work_seconds(samples, high * median, workers))


def eta_text(seconds: float) -> str:
    """``seconds`` left as a short duration (``45 s``, ``12 min``, ``2.3 h``: ``duration_text``),
    ``unknown`` where it is NaN or infinite."""
    if seconds != seconds or seconds == float("inf"):
        return "unknown"
    return duration_text(seconds)


@dataclass
class PhaseStats:
    """The summed results of one phase (see the module notes)."""

    phase: str
    unit: str = "sample"
    tasks: int = 0  # results received
    failed: int = 0
    retried: int = 0  # results that needed more than one solver attempt
    worker_seconds: float = 0.0  # wall-clock seconds of the workers' solves, summed
    cpu_seconds: float = 0.0  # the workers' CPU seconds, summed
    iterations: int = 0  # Newton iterations, summed
    factorizations: int = 0  # numeric factorisations, summed
    max_seconds: float = 0.0  # the slowest result's worker seconds
    median_seconds: float | None = None  # of the results' worker seconds (set by close())
    wall: float = 0.0  # wall-clock seconds from the first hand-out to the last result
    failures: Counter = field(default_factory=Counter)  # failure kind -> count
    _t0: float = field(default_factory=time.monotonic, repr=False)

    def add(self, r) -> None:
        """Count one :class:`~.worker.SampleResult`."""
        self.tasks += 1
        self.worker_seconds += float(r.seconds)
        self.cpu_seconds += float(r.cpu_seconds)
        self.iterations += int(r.iterations)
        self.factorizations += int(r.factorizations)
        self.max_seconds = max(self.max_seconds, float(r.seconds))
        self.retried += int(r.attempts > 1)
        if r.status != SampleStatus.DONE:
            self.failed += 1
            self.failures[failure_kind(r.reason)] += 1

    def close(self, median: float | None) -> "PhaseStats":
        """Set the wall-clock time and the median; returns self."""
        self.wall = time.monotonic() - self._t0
        self.median_seconds = median
        return self

    def as_dict(self) -> dict:
        """JSON-able figures (means per result where that is what one reads)."""
        n = max(self.tasks, 1)
        return {"phase": self.phase, "unit": self.unit, "tasks": self.tasks, "failed": self.failed,
                "retried": self.retried, "wall_seconds": self.wall, "worker_seconds": self.worker_seconds,
                "cpu_seconds": self.cpu_seconds, "median_seconds": self.median_seconds,
                "max_seconds": self.max_seconds, "iterations_mean": self.iterations / n,
                "factorizations_mean": self.factorizations / n, "failures": dict(self.failures)}
