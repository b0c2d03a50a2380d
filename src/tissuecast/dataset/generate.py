"""Generate (or continue) a data set: plan, calibrate the force magnitude, solve, store.

``simulate(config)`` resolves the config's scenario, creates the store or resumes it (the
store's writer checks that it may: :meth:`~.store.StoreWriter.resume`), then runs three
phases, each skipped when the store already has its result: the force calibration
(:mod:`.calibrate`; its last round's pilots are kept as samples), the reduced-order predictor
(:mod:`.reduced_predictor`), and the solves of every pending sample. It is resumable and
exact: every sample is a pure function of the stored set-up (mesh, scenario arrays, LBO
basis, config, reduced model), its own seed and the calibrated alpha, solved with
single-threaded BLAS. Which worker solved it, in which order, and whether the run was
interrupted (``kill -9``) and resumed do not change a bit of the store (except
``samples/seconds``, the wall-clock times, and the ``created`` attribute).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Config, load_config
from ..errors import ConfigError
from .batch import Batch, chunk_batches, pending_batches
from .calibrate import calibrate_pilots
from .codes import SampleStatus
from .executors import make_executor, refuse_in_starting_worker, sigterm_as_interrupt
from .mechanism_check import check_thin_body
from .phase_stats import PREDICTED_SHARE, eta_text, whole_set_eta, work_seconds
from .reader import open_dataset, recipe_from_store
from .reduced_predictor import build_reduced, keep_snapshots
from .sample_plan import generation_order, make_plan
from .store import StoreWriter, data_config
from .supervise import Supervisor
from .worker import Recipe, Task

__all__ = ["simulate", "check_workers", "recipe_from_store", "setup_from_config", "scenario_setup", "data_config",
           "SimulationRun", "Phase"]

log = logging.getLogger(__name__)


def setup_from_config(cfg: Config):
    """The mesh, fiducial markers and fixed vertices a config describes.

    Returns:
        ``(mesh TetMesh, markers (n_d,) int64, fixed (k,) int64)``: the fixed vertices are
        those held in all components by the scenario (pins and attached region; the paper's
        set-up: the pins).
    """
    mesh, markers, _, scenario = scenario_setup(cfg)
    return mesh, markers, scenario.supported


def scenario_setup(cfg: Config):
    """The mesh, fiducial markers, pins and resolved scenario a config describes
    (:func:`tissuecast.scenario.scenario_from_config`).

    Returns:
        ``(mesh, markers (n_d,) int64, pins (k,) int64, scenario)``.
    """
    from ..scenario import scenario_from_config

    return scenario_from_config(cfg)


_FLUSH_SECONDS = 2.0  # per-sample values and statuses reach the disk at least this often ...
_FLUSH_SAMPLES = 32  # ... and at least every this many samples


def _flush_quietly(writer: StoreWriter) -> None:
    """Save finished samples while an exception (e.g. a full disk) is propagating."""
    try:
        writer.flush()
    except OSError as exc:
        log.warning("could not save the last finished samples (%s); they will be solved again on resume", exc)


def _open_or_create(cfg: Config, path: Path) -> StoreWriter:
    """The store's writer: the existing store, checked by its writer to be this config's
    (:meth:`~.store.StoreWriter.resume`), or a new one."""
    _, markers, _, scenario = scenario_setup(cfg)
    if path.exists():
        return StoreWriter.resume(path, config=cfg, markers=markers, scenario=scenario)
    check_thin_body(scenario, cfg.markers)  # before the store is made: a refused run leaves nothing behind
    return StoreWriter.create(path, config=cfg, markers=markers, plan=make_plan(cfg), scenario=scenario)


@dataclass(frozen=True)
class Phase:
    """What one phase of a :func:`simulate` call did."""

    samples: int = 0  # data-set samples solved and written in the phase
    seconds: float = 0.0  # wall-clock time of the phase's solves
    io_seconds: float = 0.0  # of which the parent process spent writing the store (sample phase)
    built: bool = False  # predictor phase: a reduced model was built and stored


@dataclass(frozen=True)
class SimulationRun:
    """What one :func:`simulate` call did, phase by phase."""

    executor: str = "nothing to do"  # where the samples were solved
    calibration: Phase = field(default_factory=Phase)  # force calibration (pilots kept as samples)
    predictor: Phase = field(default_factory=Phase)  # basis samples from zero and the reduced-model fit
    samples: Phase = field(default_factory=Phase)  # every other pending sample
    seconds: float = 0.0  # wall-clock time of the call
    slow: tuple = ()  # (phase, sample, seconds, x median) of samples slower than SLOW_FACTOR x the median
    stopped: tuple = ()  # (phase, sample) of samples whose solver attempts were stopped by the time budget
    phases: tuple = ()  # the counts of every phase (PhaseStats.as_dict(): calibration rounds, basis, samples)
    parent_seconds: dict = field(default_factory=dict)  # what the parent process did alone, s (e.g. "reduced_fit")

    @property
    def solved(self) -> int:
        """Samples solved and written in this call."""
        return self.calibration.samples + self.predictor.samples + self.samples.samples

    def as_dict(self) -> dict:
        """The ``run`` figures of :func:`simulate`'s summary (``reduced_seconds`` only when a
        reduced model was built; ``slow_samples`` and ``stopped_by_budget`` list the samples
        that took more than ``SLOW_FACTOR`` x their phase's median and those whose attempts
        the time budget stopped)."""
        run = {"solved": self.solved, "executor": self.executor, "calibration_seconds": self.calibration.seconds,
               "sample_phase_seconds": self.samples.seconds, "sample_phase_samples": self.samples.samples,
               "parent_io_seconds": self.samples.io_seconds}
        if self.predictor.built:
            run["reduced_seconds"] = self.predictor.seconds
        run["seconds"] = self.seconds
        run["samples_per_minute"] = 60.0 * self.solved / self.seconds if self.solved and self.seconds > 0 else 0.0
        phase = self.samples.seconds
        run["sample_phase_samples_per_minute"] = 60.0 * self.samples.samples / phase if phase > 0 else 0.0
        run["slow_samples"] = [{"phase": p, "sample": i, "seconds": s, "times_median": x} for p, i, s, x in self.slow]
        run["stopped_by_budget"] = [{"phase": p, "sample": i} for p, i in self.stopped]
        run["phases"] = list(self.phases)
        run["parent_seconds"] = dict(self.parent_seconds)
        return run


def check_workers(workers: int | None) -> None:
    """Refuse a negative number of local worker processes (None: the config's; 0: automatic).

    Raises:
        ConfigError: naming the fix.
    """
    if workers is not None and workers < 0:
        raise ConfigError(f"workers = {workers}: give 0 (one per usable CPU) or a number of worker processes; "
                          "nothing was simulated")


def simulate(config, store_path=None, *, progress: bool = True, scheduler: str | None = None,
             workers: int | None = None, solver_factory: str | None = None) -> dict:
    """Create or continue the data set described by ``config``.

    Args:
        config: a :class:`~tissuecast.config.Config` or a TOML file path.
        store_path: the store directory (default ``config.dataset.store``).
        progress: show a progress bar on a terminal (log lines otherwise).
        scheduler: Dask scheduler address ``tcp://HOST:PORT`` (default ``config.dataset.scheduler``;
            empty = local worker processes).
        workers: local worker processes (default ``config.dataset.workers``; 0 = one per usable CPU).
        solver_factory: ``"module:function"`` replacing the FEM solver factory (for testing).

    Returns:
        The data set's :meth:`~.reader.Dataset.summary` plus ``run``, the figures of this call
        (:meth:`SimulationRun.as_dict`: samples solved, seconds, samples per minute, executor).

    Raises:
        DatasetError: the store belongs to another config or mesh, or is of an unknown schema;
            or the call runs in a worker still importing a script without a main guard.
        ConfigError: a negative ``workers``.
    """
    refuse_in_starting_worker()  # before the store is opened: its I/O threads would keep the worker alive
    check_workers(workers)
    cfg = config if isinstance(config, Config) else load_config(config)
    path = Path(store_path or cfg.dataset.store)
    writer = _open_or_create(cfg, path)
    t0 = time.monotonic()
    run = SimulationRun()
    if len(writer.pending()) or writer.calibration is None:
        with sigterm_as_interrupt():
            try:
                run = _run_phases(writer, cfg, progress=progress, solver_factory=solver_factory,
                                  scheduler=cfg.dataset.scheduler if scheduler is None else scheduler,
                                  workers=cfg.dataset.workers if workers is None else workers)
            except KeyboardInterrupt:
                log.warning("stopped: %d of %d samples are in the store; run the same command again to continue "
                            "(the result is the same as without the stop)", int((writer.status != 0).sum()),
                            len(writer.status))
                raise
    run = dataclasses.replace(run, seconds=time.monotonic() - t0)
    summary = open_dataset(path).summary()
    summary["run"] = run.as_dict()
    return summary


def _run_phases(writer: StoreWriter, cfg: Config, *, progress: bool, solver_factory: str | None, scheduler: str,
                workers: int) -> SimulationRun:
    """Calibrate (if not done), build the predictor (if configured and not built), then solve
    every pending sample; the workers take the reduced model once it exists."""
    recipe = recipe_from_store(writer, solver_factory)
    ds = cfg.dataset
    parent: dict = {}
    with make_executor(recipe, scheduler=scheduler, workers=workers, memory_gib=ds.batch_memory) as pool:
        ex = Supervisor(pool, ds.time_budget, ds.time_budget_min, progress)
        executor = ex.executor.describe()
        log.info("simulating %d pending of %d samples on %s", len(writer.pending()), len(writer.status), executor)
        calibration = _calibration_phase(writer, ex, cfg, recipe) if writer.calibration is None else Phase()
        predictor = Phase()
        if ds.predictor == "reduced" and writer.reduced is None and len(writer.pending()):
            predictor = _predictor_phase(writer, ex, cfg, recipe, parent)
            if predictor.built:  # the same workers (and their solvers), now with the reduced model
                ex.executor.update(recipe_from_store(writer, solver_factory))
                remaining_outlook(writer, ex)
        if writer.batches is not None:  # fixed in the store: they decide, whatever the config says now
            size = int(writer.batches["size"])
        else:
            size = fitting_batch_size(ds.batch_size, ds.batch_memory, writer.root["mesh/tets"].shape[0],
                                      cfg.solver.order)
        batched = size > 1 and writer.reduced is not None
        samples = _solve_pending(writer, ex, size if batched else 1)
    return SimulationRun(executor, calibration, predictor, samples, slow=tuple(ex.slow), stopped=tuple(ex.stopped),
                         phases=tuple(s.as_dict() for s in ex.phases), parent_seconds=parent)


def _calibration_phase(writer: StoreWriter, ex, cfg: Config, recipe: Recipe) -> Phase:
    """Calibrate alpha, keep the last round's pilots as samples, then record the calibration."""
    tc = time.monotonic()
    rounds_before = len(ex.phases)
    record, reusable = calibrate_pilots(writer, ex, cfg, recipe)
    seconds = time.monotonic() - tc
    if len(ex.phases) > rounds_before:
        whole_set_outlook(writer, cfg, ex, seconds, len(ex.phases) - rounds_before, len(reusable))
    written = 0
    for r in reusable:  # pilot solves at the final alpha are the samples themselves
        if writer.status[r.index] == SampleStatus.PENDING:
            writer.write_sample(r)
            written += 1
    writer.flush()
    keep_snapshots(writer, cfg, reusable)
    # the record last: a run killed before it calibrates again (the same rounds, bit for bit)
    # instead of solving the written pilots again from zero
    writer.set_calibration(record)
    return Phase(samples=written, seconds=seconds)


def whole_set_outlook(writer: StoreWriter, cfg: Config, ex: Supervisor, seconds: float, rounds: int,
                      kept: int) -> None:
    """Log, at the calibration's end (``seconds`` long, ``rounds`` rounds, ``kept`` pilots kept
    as samples), the ETA of the whole data set (:func:`.phase_stats.whole_set_eta` from the
    last round's median pilot)."""
    median = ex.phases[-1].median_seconds
    if median is None:
        return
    n_pending = len(writer.pending()) - kept  # the kept pilots are written after this
    basis = 0
    if cfg.dataset.predictor == "reduced" and writer.reduced is None:
        basis = max(min(cfg.dataset.predictor_samples, int(writer.root.attrs["n_lbo"])) - kept, 0)
    rest = max(n_pending - basis, 0)
    low, high = whole_set_eta(median, basis, rest, ex.workers)
    closer = "; a closer estimate follows the basis samples" if basis else ""
    log.info("calibration done in %s (%d rounds); ETA for the whole set %s to %s: %d reduced-model basis samples and "
             "%d more samples, each %g-%gx the last round's median pilot (%.2f s of worker time; the range measured "
             "on four runs of three meshes)%s", eta_text(seconds), rounds, eta_text(low), eta_text(high), basis, rest,
             *PREDICTED_SHARE, median, closer)


def remaining_outlook(writer: StoreWriter, ex: Supervisor) -> None:
    """Log, once the reduced model's basis samples are solved, the ETA of the pending samples at
    the basis samples' median (worker seconds; :func:`.phase_stats.work_seconds`): a closer guide
    than the calibration's estimate, whose last-round pilots start from their previous round's
    solutions (the comparison on several meshes: docs/scaling.md)."""
    median = ex.phases[-1].median_seconds if ex.phases else None
    pending = len(writer.pending())
    if median is None or not pending:
        return
    log.info("reduced-model basis samples solved: ETA for the %d remaining samples %s, counting their median "
             "(%.2f s of worker time) for each", pending, eta_text(work_seconds(pending, median, ex.workers)), median)


def _predictor_phase(writer: StoreWriter, ex, cfg: Config, recipe: Recipe, parent: dict) -> Phase:
    """Solve the basis samples and fit the reduced model (:func:`.reduced_predictor.build_reduced`;
    the parent's own seconds go into ``parent``)."""
    tr = time.monotonic()
    solved, built = build_reduced(writer, ex, cfg, recipe, parent)
    seconds = time.monotonic() - tr
    if built:
        log.info("reduced model: %d modes, %d elements (ECSW error %.3g), built in %.1f s",
                 writer.reduced["modes"], writer.reduced["elements"], writer.reduced["fit_error"], seconds)
    return Phase(samples=solved, seconds=seconds, built=built)


def fitting_batch_size(requested: int, memory_gib: float, n_tets: int, order: int) -> int:
    """Samples a worker solves together: ``requested``, cut so that their tangents fit in
    ``memory_gib`` GiB (a batch solves in lockstep, and each of its samples holds its own
    element matrices, ``n_tets x (3 nodes per element)^2`` float64). A function of the config
    and the mesh alone, so stores stay reproducible on any machine; at least 1."""
    nodes = 10 if order == 2 else 4
    per_sample = n_tets * (3 * nodes) ** 2 * 8.0
    fits = int(memory_gib * 2.0**30 // max(per_sample, 1.0))
    return max(1, min(int(requested), fits))


def _work_items(writer: StoreWriter, order: np.ndarray, batch_size: int, task) -> list:
    """The work items of the pending samples ``order`` (generation order): one
    :class:`~.worker.Task` each (``batch_size`` 1), else the stored batches holding them
    (:mod:`.batch`; fixed in the store on first use)."""
    if batch_size <= 1:
        return [task(i) for i in order]
    if writer.batches is None:
        writer.set_batches(chunk_batches(order, batch_size, len(writer.status)), batch_size)
    items = []
    for members in pending_batches(writer.read("samples/batch"), order):
        tasks = tuple(task(i) for i in members)
        items.append(Batch(tasks) if len(tasks) > 1 else tasks[0])
    return items


def _solve_pending(writer: StoreWriter, ex: Supervisor, batch_size: int = 1) -> Phase:
    """Solve every pending sample at the calibrated alpha, writing results as they come.

    The splits are interleaved (:func:`~.sample_plan.generation_order`), so a run stopped part-way
    leaves a store whose done samples already cover every split in proportion. With
    ``batch_size`` > 1 workers solve the stored batches (:mod:`.batch`); the done samples of
    a partly written batch are solved again with it and not written again.
    """
    alpha = float(writer.calibration["alpha"])
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    pending = generation_order(writer.read("samples/split"), writer.pending())
    t_start = last_flush = time.monotonic()
    unflushed = solved = 0
    io_seconds = 0.0
    items = _work_items(writer, pending, batch_size,
                        lambda i: Task(int(i), int(seeds[i]), float(betas[i]), alpha))
    n = sum(len(t.tasks) if isinstance(t, Batch) else 1 for t in items)
    try:
        for r in ex.run(items, "simulate", total=len(writer.status) - len(pending) + n,
                        done=len(writer.status) - len(pending)):
            if writer.status[r.index] != SampleStatus.PENDING:
                continue  # solved again with its batch; written before
            tw = time.monotonic()
            writer.write_sample(r)
            solved += 1
            unflushed += 1
            if tw - last_flush > _FLUSH_SECONDS or unflushed >= _FLUSH_SAMPLES:
                writer.flush()
                last_flush, unflushed = time.monotonic(), 0
            io_seconds += time.monotonic() - tw
        writer.flush()
    finally:
        _flush_quietly(writer)
    return Phase(samples=solved, seconds=time.monotonic() - t_start, io_seconds=io_seconds)
