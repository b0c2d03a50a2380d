"""Generate (or continue) a data set: plan, calibrate the force magnitude, solve, store.

``simulate(config)`` runs three phases, each skipped when the store already has its result:
the force calibration (:mod:`.calibrate`; its last round's pilots are kept as samples), the
reduced-order predictor (:mod:`.predictor`), and the solves of every pending sample. It is
resumable and exact: every sample is a pure function of the stored set-up (mesh, fixed
vertices, LBO basis, config, reduced model), its own seed and the calibrated alpha, solved
with single-threaded BLAS. Which worker solved it, in which order, and whether the run was
interrupted (``kill -9``) and resumed do not change a bit of the store (except
``samples/seconds``, the wall-clock times, and the ``created`` attribute).
"""

from __future__ import annotations

import dataclasses
import logging
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Config, DatasetConfig, config_from_dict, config_to_dict, config_to_toml, load_config
from ..errors import DatasetError
from .batch import Batch, chunk_batches, pending_batches
from .calibrate import MAX_ROUNDS, calibrate_alpha, initial_alpha, linear_alpha
from .codes import InitialGuess, SampleStatus
from .executors import make_executor
from .plan import generation_order, make_plan
from .predictor import build_reduced, keep_snapshots
from .reader import open_dataset
from .store import StoreWriter, open_root, read_lbo_basis, read_scenario_arrays
from .supervise import Supervisor
from .supports import MECHANISM_RATIO, check_supports
from .worker import Recipe, SampleContext, Task

__all__ = ["simulate", "recipe_from_store", "setup_from_config", "scenario_setup", "uses_scenario", "data_config",
           "SimulationRun", "Phase"]

log = logging.getLogger(__name__)

# config keys that do not change a data set's numbers (may differ when resuming); the mesh
# file may move: its content is checked by fingerprint instead
_RUNTIME_KEYS = {"dataset": ("store", "workers", "scheduler", "time_budget", "time_budget_min"), "mesh": ("path",)}
_DATA_SECTIONS = ("mesh", "markers", "material", "solver", "forces", "dataset", "scenario")


def data_config(cfg: Config) -> dict:
    """The part of a config that determines a data set's contents (nested dict)."""
    d = config_to_dict(cfg)
    out = {sec: dict(d[sec]) for sec in _DATA_SECTIONS}
    for sec, keys in _RUNTIME_KEYS.items():
        for k in keys:
            out[sec].pop(k, None)
    return out


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


def _check_same(writer: StoreWriter, cfg: Config, mesh, markers: np.ndarray, fixed: np.ndarray) -> None:
    stored = data_config(config_from_dict(tomllib.loads(writer.config_toml)))
    now = data_config(cfg)
    if writer.batches is not None:  # the store's own batches decide from here on (.batch)
        for key in ("batch_size", "batch_memory"):
            stored["dataset"].pop(key, None)
            now["dataset"].pop(key, None)
    diffs = [f"{sec}.{k}: {stored[sec].get(k)!r} in the store, {now[sec].get(k)!r} now"
             for sec in _DATA_SECTIONS for k in sorted(set(stored[sec]) | set(now[sec]))
             if stored[sec].get(k) != now[sec].get(k)]
    if diffs:
        raise DatasetError(
            f"data set {str(writer.path)!r} was made with a different configuration ({'; '.join(diffs[:4])}"
            f"{'; ...' if len(diffs) > 4 else ''}); resume it with its own config (`tissuecast dataset info` shows it) "
            "or choose another --store path; a store is never overwritten")
    fp = writer.root.attrs.get("mesh_fingerprint")
    if fp != mesh.fingerprint():
        raise DatasetError(
            f"data set {str(writer.path)!r} was made on a different mesh (fingerprint {str(fp)[:12]}..., this mesh "
            f"{mesh.fingerprint()[:12]}...); use the original mesh or another --store path; a store is never overwritten")
    for what, now in (("markers", markers), ("fixed", fixed)):
        stored_ids = np.asarray(writer.read(what), dtype=np.int64)
        if np.array_equal(stored_ids, now):
            continue
        if what == "markers" and not cfg.scenario.pins:
            # without pins the markers do not enter the simulation (pins are chosen around them):
            # the store keeps the markers it was made with, and the model is trained on those
            log.warning("data set %r was made with markers %s, this config chooses %s (e.g. a store from a version "
                        "whose marker rule did not avoid the attached region); the store keeps its own markers",
                        str(writer.path), stored_ids.tolist(), np.asarray(now).tolist())
            continue
        raise DatasetError(
            f"data set {str(writer.path)!r} has {what} vertices {stored_ids.tolist()} but this config gives "
            f"{np.asarray(now).tolist()} (e.g. a store from a version with another marker or pin rule), and "
            f"{'the pins are chosen around the markers' if what == 'markers' else 'the fixed vertices'} change the "
            "simulated fields: continue it with the tissuecast version that made it, or choose another --store path "
            "(a store is never overwritten)")


def _check_springs(writer: StoreWriter, scenario) -> None:
    """Warn when a store's springs differ from those its config gives now (a store from a
    version that lumped P2 springs by ``integral(N_a) dA`` only); its workers go on with the
    stored springs (:func:`recipe_from_store`)."""
    stored = read_scenario_arrays(writer.root) or {}
    springs = scenario.springs
    if "spring_nodes" not in stored or springs is None:
        return
    if np.array_equal(stored["spring_nodes"], springs.nodes) and np.allclose(stored["spring_stiffness"],
                                                                            springs.stiffness, rtol=1e-12, atol=0.0):
        return
    log.warning("data set %r holds springs other than this config gives (%d nodes, now %d: e.g. made before P2 "
                "springs were lumped HRZ-style by default); it goes on with its own springs, so its samples stay "
                "one data set",
                str(writer.path), len(stored["spring_nodes"]), len(springs.nodes))


_FLUSH_SECONDS = 2.0  # per-sample values and statuses reach the disk at least this often ...
_FLUSH_SAMPLES = 32  # ... and at least every this many samples


def _flush_quietly(writer: StoreWriter) -> None:
    """Save finished samples while an exception (e.g. a full disk) is propagating."""
    try:
        writer.flush()
    except OSError as exc:
        log.warning("could not save the last finished samples (%s); they will be solved again on resume", exc)


def _open_or_create(cfg: Config, path: Path) -> StoreWriter:
    mesh, markers, _, scenario = scenario_setup(cfg)
    fixed = scenario.supported
    if path.exists():
        writer = StoreWriter.open(path)
        _check_same(writer, cfg, mesh, markers, fixed)
        _check_springs(writer, scenario)
        return writer
    from ..forces import lbo_basis

    basis = lbo_basis(mesh, cfg.forces.n_basis)
    # where the samples are solved (local workers, a Dask scheduler's address) is not part of the
    # data set: the store records the defaults, so a cluster run and a local run give one store
    default = DatasetConfig()
    recorded = dataclasses.replace(cfg, dataset=dataclasses.replace(cfg.dataset, workers=default.workers,
                                                                     scheduler=default.scheduler))
    return StoreWriter.create(path, config_toml=config_to_toml(recorded, comments=False), mesh=mesh, markers=markers,
                              fixed=fixed, basis=basis, plan=make_plan(cfg), scenario=scenario)


def uses_scenario(cfg: Config) -> bool:
    """Whether a data set's samples go through the scenario path (loads on every element node,
    per-sample draws): every set-up but the paper's (pins, LBO forces as nodal forces)."""
    sc = cfg.scenario
    plain = (sc.pins and sc.lbo_forces and sc.attached.rule == "none" and sc.springs.rule == "none"
             and not sc.gravity.enabled and not sc.indentation.enabled and not sc.materials.regions)
    return not plain or cfg.forces.loading != "nodal"


def recipe_from_store(store, solver_factory: str | None = None) -> Recipe:
    """Everything a worker needs to solve a stored data set's samples exactly as its run did.

    Args:
        store: the store's path (opened read-only), or an open :class:`~.store.StoreWriter`.
        solver_factory: ``"module:function"`` replacing the FEM solver factory (for testing).

    Returns:
        The :class:`~.worker.Recipe` (config, mesh, fixed vertices, LBO basis, scenario
        arrays and the reduced-order predictor, when the store has them); with
        :class:`~.worker.Task` and :func:`~.worker.solve_task` a sample (or a variant of it,
        e.g. another force magnitude) is solved in this process.
    """
    root = store.root if isinstance(store, StoreWriter) else open_root(Path(store))

    def read(name: str) -> np.ndarray:
        return np.asarray(root[name][...])

    kw = {"solver_factory": solver_factory} if solver_factory else {}
    if root.attrs.get("reduced") is not None:
        kw.update(reduced_basis=read("reduced/basis"), reduced_elements=read("reduced/elements"),
                  reduced_weights=read("reduced/weights"))
    config_toml = root.attrs["config_toml"]
    if uses_scenario(config_from_dict(tomllib.loads(config_toml))):
        kw["scenario"] = read_scenario_arrays(root)
    return Recipe(config_toml, read("mesh/points"), read("mesh/tets"), read("fixed"), read_lbo_basis(root), **kw)


def _calibrate(writer: StoreWriter, ex: Supervisor, cfg: Config, recipe: Recipe) -> tuple[dict, list]:
    """Calibrate alpha on the pilot samples; returns the record and the last round's results."""
    ds = cfg.dataset
    if ds.alpha > 0:
        return {"rule": "given (dataset.alpha)", "alpha": ds.alpha, "converged": True, "rounds": []}, []
    if not cfg.scenario.lbo_forces:
        return {"rule": "none: the scenario has no LBO forces (scenario.lbo_forces = false)", "alpha": 0.0,
                "converged": True, "rounds": []}, []
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    n_lbo = int(writer.root.attrs["n_lbo"])
    pilots = list(range(min(ds.calibration_samples, n_lbo)))
    if not pilots:
        raise DatasetError("force calibration needs at least one LBO sample; set dataset.n_samples >= 1 or dataset.alpha")
    last: list = []
    rounds: list = []

    warm_zero = _warm_zero(cfg, recipe)

    def pilot_max(alpha: float) -> np.ndarray:
        # each pilot starts from its solution of the previous round (if it converged)
        prev = {r.index: r.nodal for r in last if r.status == SampleStatus.DONE and r.nodal is not None}
        phase = f"calibration round {len(rounds) + 1} (at most {MAX_ROUNDS}), alpha {alpha:.4g} N"
        rounds.append(alpha)
        tasks = [Task(i, int(seeds[i]), float(betas[i]), alpha, prev.get(i)) if i in prev or warm_zero is None
                 else Task(i, int(seeds[i]), float(betas[i]), alpha, warm_zero, int(InitialGuess.ZERO))
                 for i in pilots]
        last[:] = sorted(ex.run(tasks, phase, unit="pilot"), key=lambda r: r.index)
        return np.array([r.max_displacement for r in last])

    target = cfg.forces.target_max_displacement
    if recipe.scenario is None:
        alpha0 = initial_alpha(recipe.basis, recipe.mesh, recipe.fixed, cfg.material.youngs_modulus, target)
        # pins that leave a near-mechanism are refused (a scenario's supports are checked for
        # rigid motions when it is built)
        _check_supports(cfg, recipe, [(int(seeds[i]), float(betas[i])) for i in pilots[:SUPPORT_PILOTS]], alpha0)
    else:
        alpha0 = linear_alpha(recipe, [Task(i, int(seeds[i]), float(betas[i]), 1.0) for i in pilots], target)
    record = calibrate_alpha(pilot_max, alpha0, target, quantile=ds.calibration_quantile)
    record["pilots"] = pilots
    reusable = [r for r in last if r.alpha == record["alpha"]]
    return record, reusable


def _warm_zero(cfg: Config, recipe: Recipe) -> np.ndarray | None:
    """Zero displacements (n_nodes, 3) as a pilot's first guess where a guess changes the
    solver's path (``krylov`` with ``reference_preconditioner``: one full increment
    preconditioned by the shared stiffness at zero, no factorisation of its own), else None.
    A pilot that fails from it goes on with the usual attempts from zero
    (:func:`~.worker.solve_task`); timings in ``docs/scaling.md``.
    """
    sc = cfg.solver
    if recipe.scenario is not None or sc.strategy != "krylov" or not sc.reference_preconditioner:
        return None
    mesh = recipe.mesh
    return np.zeros_like(mesh.points if sc.order == 1 else mesh.points10, dtype=np.float64)


#: Pilots whose linear answers check the supports before the calibration (:mod:`.supports`).
SUPPORT_PILOTS = 4


def _check_supports(cfg: Config, recipe: Recipe, pilots: list, alpha0: float) -> None:
    """Refuse supports that leave a near-mechanism (:func:`.supports.check_supports`), from
    the linear answers of the ``pilots`` ((seed, beta) pairs) at ``alpha0`` on linear elements."""
    from ..fem import build_problem

    ctx = SampleContext(recipe)
    forces = [ctx.forces(Task(-1, seed, beta, alpha0))[0] for seed, beta in pilots]
    peak = check_supports(build_problem(ctx.mesh, cfg, ctx.fixed, order=1), forces, alpha0,
                          cfg.forces.target_max_displacement)
    log.info("supports: the first pilots' linear answers at alpha %.3g N peak at %.3g mm (refused above %.3g mm)",
             alpha0, peak, MECHANISM_RATIO * cfg.forces.target_max_displacement)


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
        return run


def simulate(config, store_path=None, *, progress: bool = True, scheduler: str | None = None,
             workers: int | None = None, solver_factory: str | None = None) -> dict:
    """Create or continue the data set described by ``config``.

    Args:
        config: a :class:`~tissuecast.config.Config` or a TOML file path.
        store_path: the store directory (default ``config.dataset.store``).
        progress: show a progress bar on a terminal (log lines otherwise).
        scheduler: Dask scheduler address ``tcp://HOST:PORT`` (default ``config.dataset.scheduler``;
            empty = local worker processes).
        workers: local worker processes (default ``config.dataset.workers``; 0 = min(2, CPUs)).
        solver_factory: ``"module:function"`` replacing the FEM solver factory (for testing).

    Returns:
        The data set's :meth:`~.reader.Dataset.summary` plus ``run``, the figures of this call
        (:meth:`SimulationRun.as_dict`: samples solved, seconds, samples per minute, executor).

    Raises:
        DatasetError: the store belongs to another config or mesh, or is of an unknown schema.
    """
    cfg = config if isinstance(config, Config) else load_config(config)
    path = Path(store_path or cfg.dataset.store)
    writer = _open_or_create(cfg, path)
    t0 = time.monotonic()
    run = SimulationRun()
    if len(writer.pending()) or writer.calibration is None:
        run = _run_phases(writer, cfg, progress=progress, solver_factory=solver_factory,
                          scheduler=cfg.dataset.scheduler if scheduler is None else scheduler,
                          workers=cfg.dataset.workers if workers is None else workers)
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
    with make_executor(recipe, scheduler=scheduler, workers=workers) as pool:
        ex = Supervisor(pool, ds.time_budget, ds.time_budget_min, progress)
        executor = ex.executor.describe()
        log.info("simulating %d pending of %d samples on %s", len(writer.pending()), len(writer.status), executor)
        calibration = _calibration_phase(writer, ex, cfg, recipe) if writer.calibration is None else Phase()
        predictor = Phase()
        if ds.predictor == "reduced" and writer.reduced is None and len(writer.pending()):
            predictor = _predictor_phase(writer, ex, cfg, recipe)
            if predictor.built:  # the same workers (and their solvers), now with the reduced model
                ex.executor.update(recipe_from_store(writer, solver_factory))
        if writer.batches is not None:  # fixed in the store: they decide, whatever the config says now
            size = int(writer.batches["size"])
        else:
            size = fitting_batch_size(ds.batch_size, ds.batch_memory, writer.root["mesh/tets"].shape[0],
                                      cfg.solver.order)
        batched = size > 1 and writer.reduced is not None
        samples = _solve_pending(writer, ex, size if batched else 1)
    return SimulationRun(executor, calibration, predictor, samples, slow=tuple(ex.slow), stopped=tuple(ex.stopped))


def _calibration_phase(writer: StoreWriter, ex, cfg: Config, recipe: Recipe) -> Phase:
    """Calibrate alpha, keep the last round's pilots as samples, then record the calibration."""
    tc = time.monotonic()
    record, reusable = _calibrate(writer, ex, cfg, recipe)
    seconds = time.monotonic() - tc
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


def _predictor_phase(writer: StoreWriter, ex, cfg: Config, recipe: Recipe) -> Phase:
    """Solve the basis samples and fit the reduced model (:func:`.predictor.build_reduced`)."""
    tr = time.monotonic()
    solved, built = build_reduced(writer, ex, cfg, recipe)
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

    The splits are interleaved (:func:`~.plan.generation_order`), so a run stopped part-way
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
