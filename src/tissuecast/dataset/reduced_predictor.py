"""The data set's reduced-order predictor: which samples build it, their snapshots, the fit.

With ``dataset.predictor = "reduced"`` the first ``predictor_samples`` LBO samples are solved
in full (the calibration pilots among them count), their nodal solutions are kept in the
store (``reduced/snapshots``), and a :class:`~tissuecast.fem.reduced.ReducedModel` fitted to
them is stored too; every later sample's solve starts from its prediction. The basis samples
that are not pilots start from the prediction of an *interim* model fitted to the pilots'
solutions alone (``samples/predicted`` INTERIM_MODEL; from zero if it fails, or with fewer
than ``MIN_INTERIM`` pilot solutions): a few Newton iterations instead of a cold solve. Both
models depend only on stored snapshots (the interim one on the pilots', which the
calibration writes before), so a resumed run builds the same ones and solves the same.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from ..config import Config
from .codes import InitialGuess, SampleStatus
from .store import StoreWriter
from .worker import Recipe, SampleContext, Task

__all__ = ["basis_samples", "keep_snapshots", "build_reduced"]

log = logging.getLogger(__name__)

#: Fewest converged basis samples a reduced model is fitted to.
MIN_SNAPSHOTS = 2
#: Fewest pilot solutions an interim model (for the other basis samples' first guesses) is
#: fitted to.
MIN_INTERIM = 8


def basis_samples(writer: StoreWriter, cfg: Config) -> np.ndarray:
    """Ids (s,) int64 of the samples whose full solutions build the reduced model: the first
    LBO samples."""
    n_lbo = int(writer.root.attrs["n_lbo"])
    return np.arange(min(cfg.dataset.predictor_samples, n_lbo), dtype=np.int64)


def keep_snapshots(writer: StoreWriter, cfg: Config, results) -> None:
    """Store the nodal solutions of basis samples among ``results`` (none of which started
    from the reduced model)."""
    if cfg.dataset.predictor != "reduced" or writer.reduced is not None:
        return
    for r in results:
        if r.nodal is None or r.status != SampleStatus.DONE or r.predicted == InitialGuess.REDUCED_MODEL:
            continue
        rows = writer.snapshot_rows(basis_samples(writer, cfg), len(r.nodal))
        hit = np.flatnonzero(rows == r.index)
        if len(hit):
            writer.write_snapshot(int(hit[0]), r.nodal)


def build_reduced(writer: StoreWriter, ex, cfg: Config, recipe: Recipe, parent: dict | None = None) -> tuple[int, bool]:
    """Solve the basis samples (from zero) that have no stored snapshot, then fit and store
    the reduced model.

    Args:
        writer: the store.  ex: a :class:`~.supervise.Supervisor` of an executor holding ``recipe``.
            cfg: the data set's config.
        parent: optional dict that receives the parent process's own seconds: ``interim_model``
            (the interim model's fit and predictions) and ``reduced_fit`` (the model's fit).

    Returns:
        ``(samples, built)``: the samples solved and written here, and whether the model was
        built (False, with a log line saying why, when it cannot be).
    """
    from ..fem.reduced import ReducedModel

    parent = {} if parent is None else parent
    problem = recipe.problem()
    solved, complete = _solve_basis_samples(writer, ex, cfg, recipe, problem, parent)
    if not complete:
        log.warning("the solver returns no nodal displacements; data set solved without a predictor")
        return solved, False
    snaps = writer.read("reduced/snapshots")
    snaps = snaps[np.isfinite(snaps[:, 0, 0])]  # NaN rows: basis samples that failed
    if len(snaps) < MIN_SNAPSHOTS:
        log.warning("fewer than %d basis samples converged; data set solved without a predictor", MIN_SNAPSHOTS)
        return solved, False
    t0 = time.perf_counter()
    model = ReducedModel.fit(problem, snaps, tolerance=cfg.dataset.predictor_tolerance)
    parent["reduced_fit"] = time.perf_counter() - t0
    writer.set_reduced(model.basis, model.elements, model.weights, {
        "modes": model.n_modes, "elements": int(len(model.elements)), "fit_error": float(model.fit_error),
        "snapshots": len(snaps)})
    return solved, True


def _solve_basis_samples(writer: StoreWriter, ex, cfg: Config, recipe: Recipe, problem,
                         parent: dict) -> tuple[int, bool]:
    """Solve the basis samples without a stored snapshot (failed ones are not retried) and
    store them. Returns the number written and False if the solver gives no nodal
    displacements (then it stops there)."""
    rows = writer.snapshot_rows(basis_samples(writer, cfg), len(problem.nodes))
    have = writer.snapshot_done()
    todo = [int(i) for i, ok in zip(rows, have) if not ok and writer.status[i] != SampleStatus.FAILED]
    if not todo:
        return 0, True
    alpha = float(writer.calibration["alpha"])
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    tasks = [Task(i, int(seeds[i]), float(betas[i]), alpha) for i in todo]
    t0 = time.perf_counter()
    tasks = _interim_guesses(writer, cfg, recipe, problem, tasks, _pilot_rows(writer, rows, have))
    parent["interim_model"] = time.perf_counter() - t0
    log.info("solving %d samples for the reduced model (%d from an interim model's predictions, the rest from zero)",
             len(tasks), sum(t.guess is not None for t in tasks))
    written = 0
    for r in ex.run(tasks, "reduced-model basis samples"):
        if r.nodal is None and r.status == SampleStatus.DONE:
            return written, False
        if writer.status[r.index] == SampleStatus.PENDING:
            writer.write_sample(r)
            written += 1
        keep_snapshots(writer, cfg, [r])
    writer.flush()
    return written, True


def _pilot_rows(writer: StoreWriter, rows: np.ndarray, have: np.ndarray) -> list:
    """The rows of ``reduced/snapshots`` (``rows``: their sample ids, ``have``: stored or not)
    that hold a calibration pilot's solution."""
    pilots = set((writer.calibration or {}).get("pilots", []))
    return [k for k, (i, ok) in enumerate(zip(rows, have)) if ok and int(i) in pilots]


def _interim_guesses(writer: StoreWriter, cfg: Config, recipe: Recipe, problem, tasks: list, rows: list) -> list:
    """``tasks`` with first guesses from an interim reduced model of the calibration pilots'
    stored solutions (``rows``: their rows of ``reduced/snapshots``; ``guess_code``
    INTERIM_MODEL), or unchanged when there are fewer than ``MIN_INTERIM`` of them (no
    calibration, ``dataset.alpha`` given) or the fit fails; a task whose prediction fails
    keeps no guess (solved from zero)."""
    from ..errors import SolverSetupError
    from ..fem.reduced import ReducedModel

    if len(rows) < MIN_INTERIM or not tasks:
        return tasks
    t0 = time.perf_counter()
    stored = writer.root["reduced/snapshots"]
    snaps = np.stack([np.asarray(stored[k], dtype=np.float64) for k in rows])
    ctx = SampleContext(recipe)  # the inputs of each task, as a worker makes them
    try:
        model = ReducedModel.fit(problem, snaps, tolerance=cfg.dataset.predictor_tolerance)
    except (SolverSetupError, ArithmeticError, np.linalg.LinAlgError) as exc:
        log.info("no interim reduced model (%s): the basis samples start from zero", exc)
        return tasks
    out = []
    for task in tasks:
        guess = ctx.inputs(task).reduced_guess(model)
        out.append(task if guess is None else dataclasses.replace(task, guess=guess,
                                                                  guess_code=int(InitialGuess.INTERIM_MODEL)))
    log.info("interim reduced model of %d pilot solutions (%d modes, %d elements): %d of %d basis samples predicted "
             "in %.1f s", len(snaps), model.n_modes, len(model.elements), sum(t.guess is not None for t in out),
             len(out), time.perf_counter() - t0)
    return out
