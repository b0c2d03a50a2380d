"""Solving fixed batches of samples together (``dataset.batch_size``).

Once the reduced-order predictor exists, every pending sample starts from its prediction,
and such solves spend much of their time in triangular solves with the one shared
reference factorisation; :meth:`~tissuecast.fem.Solver.solve_batch` gathers those of
several samples into multi-right-hand-side solves. A worker handed a :class:`Batch` solves
its samples' tries from the prediction that way (:func:`solve_batch_tasks`).

The batches are fixed once, in the store, when the sample phase first starts
(:meth:`~.store.StoreWriter.set_batches`): consecutive chunks of ``batch_size`` samples of the
generation order of the samples pending then. A sample's bits depend on its batch (the
columns of a multi-right-hand-side solve are not bitwise single solves), never on the worker,
the executor or the order in which batches are run; a run that is stopped part-way solves a
partly written batch again in full and writes its missing samples (:func:`pending_batches`),
so resumed, Dask and local stores are identical bit for bit.

Samples fall back to :func:`~.worker.solve_task`, one at a time, when the solver has no
``solve_batch`` (a replacement factory) or the sample has no prediction (the reduced
problem did not converge). A sample whose try in the batch failed (did not converge, or ran
past its time budget) goes on alone with the attempts from zero and the cautious retries
(:attr:`~.worker.Task.batch_failure`) and, failing those, is recorded failed with every reason.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..errors import ConvergenceError
from .codes import InitialGuess, SampleStatus
from .worker import Recipe, SampleResult, Task, context_for, solve_task

__all__ = ["Batch", "solve_item", "solve_batch_tasks", "pending_batches", "chunk_batches"]


@dataclass(frozen=True)
class Batch:
    """Samples solved together; ``tasks`` in ascending sample index."""

    tasks: tuple[Task, ...]


def solve_item(recipe: Recipe, item: Task | Batch) -> list[SampleResult]:
    """Solve one work item (a :class:`~.worker.Task` or a :class:`Batch`); results in task order."""
    if isinstance(item, Batch):
        return solve_batch_tasks(recipe, list(item.tasks))
    return [solve_task(recipe, item)]


def solve_batch_tasks(recipe: Recipe, tasks: list[Task]) -> list[SampleResult]:
    """Solve ``tasks`` (samples without a task guess) together from the reduced model's predictions.

    Samples with a prediction are solved by one ``solver.solve_batch`` at the configured
    retry level, each stopped at ``task.budget`` seconds of its share of the batch's time;
    the others, and those whose try in the batch failed, continue one by one with
    :func:`~.worker.solve_task` (all of them, as without batches, should a numerical
    breakdown stop the batch). Results (one per task, in order) count the batch's work and
    time too.
    """
    ctx = context_for(recipe)
    solver = ctx.solver(0)
    if ctx.reduced is None or not hasattr(solver, "solve_batch"):
        return [solve_task(recipe, t) for t in tasks]
    t0, c0 = time.perf_counter(), time.process_time()
    inputs = [ctx.inputs(t) for t in tasks]
    keywords = [x.solve_keywords() for x in inputs]
    guesses = [x.reduced_guess(ctx.reduced) for x in inputs]
    together = [k for k, g in enumerate(guesses) if g is not None]
    budget = min((tasks[k].budget for k in together), default=0.0)
    try:
        extra = {}  # per-sample prescribed displacements and body loads, only where samples have them
        for key in ("prescribed", "body_loads"):
            values = [keywords[k].get(key) for k in together]
            if any(v is not None for v in values):
                extra[key] = values
        if any(inputs[k].parameters is not None for k in together):
            extra["parameters"] = [inputs[k].solver_parameters for k in together]
        outcomes = solver.solve_batch([inputs[k].surface for k in together], [guesses[k] for k in together],
                                      time_limit=budget if budget > 0 else None, **extra)
    except (ArithmeticError, np.linalg.LinAlgError):  # a numerical breakdown stops the whole lockstep
        return [solve_task(recipe, t) for t in tasks]
    prep = (time.perf_counter() - t0) / max(len(tasks), 1)  # inputs, predictions and the batch, per sample
    prep_cpu = (time.process_time() - c0) / max(len(tasks), 1)
    out: dict[int, SampleResult] = {}
    for k, res in zip(together, outcomes):
        t, forces, weights = tasks[k], inputs[k].forces, inputs[k].weights
        if not isinstance(res, ConvergenceError) and getattr(res, "converged", True):
            nodal = getattr(res, "nodal_displacement", None)
            out[k] = SampleResult(t.index, SampleStatus.DONE, np.asarray(res.displacement, dtype=np.float32),
                                  forces.astype(np.float32), weights, t.alpha, t.beta, t.seed, int(res.increments),
                                  int(res.iterations), int(res.factorizations), prep, 1.0, 1,
                                  predicted=InitialGuess.REDUCED_MODEL,
                                  nodal=None if nodal is None else np.asarray(nodal, dtype=np.float64),
                                  draw=inputs[k].draw, cpu_seconds=prep_cpu)
            continue
        what = res if isinstance(res, ConvergenceError) else f"not converged at load fraction {res.load_fraction:.4g}"
        reason = f"attempt 1 from the prediction, in a batch of {len(together)}: {type(res).__name__}: {what}"
        alone = solve_task(recipe, dataclasses.replace(t, batch_failure=reason))
        partial = getattr(res, "result", None) if isinstance(res, ConvergenceError) else res
        counts = [int(getattr(partial, name, 0)) for name in ("increments", "iterations", "factorizations")]
        out[k] = dataclasses.replace(alone, increments=alone.increments + counts[0],
                                     iterations=alone.iterations + counts[1],
                                     factorizations=alone.factorizations + counts[2], seconds=alone.seconds + prep,
                                     cpu_seconds=alone.cpu_seconds + prep_cpu,
                                     load_fraction=max(alone.load_fraction, float(getattr(res, "load_fraction", 0.0))))
    for k, t in enumerate(tasks):
        if k not in out:  # no prediction: alone, as without batches
            out[k] = solve_task(recipe, t)
    return [out[k] for k in range(len(tasks))]


def chunk_batches(order: np.ndarray, size: int, n_samples: int) -> np.ndarray:
    """The batch of every sample: (N,) int32, batch ``b`` = ``order[b*size:(b+1)*size]``;
    -1 for samples not in ``order``."""
    ids = np.full(n_samples, -1, dtype=np.int32)
    order = np.asarray(order, dtype=np.int64)
    ids[order] = np.arange(len(order), dtype=np.int32) // max(int(size), 1)
    return ids


def pending_batches(batch_of: np.ndarray, order: np.ndarray) -> list[np.ndarray]:
    """The batches (ascending sample ids, whole: their done samples too) holding the pending
    samples ``order`` (generation order), in the order of their first pending sample; a
    pending sample of no batch (-1) is a batch of its own."""
    seen: dict[int, np.ndarray] = {}
    out = []
    for i in np.asarray(order, dtype=np.int64):
        b = int(batch_of[i])
        if b < 0:
            out.append(np.array([i]))
        elif b not in seen:
            seen[b] = np.flatnonzero(batch_of == b)
            out.append(seen[b])
    return out
