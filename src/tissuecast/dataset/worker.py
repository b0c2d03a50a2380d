"""Solving one sample: the scenario's inputs of the sample, the nonlinear FEM solve, retries.

Everything a worker process needs travels once, as a :class:`Recipe` (plain arrays read
back from the store plus the config TOML). Each worker process rebuilds the data set's
scenario (:func:`~tissuecast.scenario.restore_scenario`), the FEM problem and its
:class:`~tissuecast.fem.Solver` once (:func:`context_for`) and reuses them for every sample it
is given, so per-sample cost is the solve alone.

A sample's result is a pure function of (recipe, task): everything that loads it (the force
field, the scenario's draws: gravity direction, indentation) comes from the scenario given
the sample's own seed (:meth:`~tissuecast.scenario.Scenario.sample`), the solve starts from
zero, the task's guess or the recipe's reduced-model prediction, and worker processes run
their BLAS single-threaded (see :mod:`.executors`). Hence the same sample gives the same bits
on any worker, in any order, in a first run or after a resume.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import logging
import time
import tomllib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..config import Config, SolverConfig, config_from_dict
from ..errors import ConvergenceError, SolveTimeout
from .codes import InitialGuess, SampleStatus

if TYPE_CHECKING:
    from ..forces import LBOBasis
    from ..mesh import TetMesh
    from ..scenario import SampleInputs, Scenario

__all__ = ["Recipe", "Task", "SampleResult", "SampleContext", "context_for", "solve_task", "retry_solver_config",
           "fem_solver_factory"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Recipe:
    """What a worker needs to build its solver (sent once per worker process).

    Attributes:
        config_toml: the data set's configuration as TOML text.
        points: (n, 3) float64 mesh vertices, mm.  tets: (m, 4) int64.
        basis: the stored :class:`~tissuecast.forces.LBOBasis`.
        scenario_arrays: the resolved scenario's :meth:`~tissuecast.scenario.Scenario.arrays`,
            as the store holds them (pins, attached region, springs, materials, indentation
            access; :func:`~.schema.read_scenario_arrays`).
        solver_factory: ``"module:function"`` building the solver (see :func:`fem_solver_factory`).
        reduced_basis, reduced_elements, reduced_weights: the data set's reduced-order
            predictor (:class:`~tissuecast.fem.reduced.ReducedModel`), or None (solve from zero).
    """

    config_toml: str
    points: np.ndarray
    tets: np.ndarray
    basis: "LBOBasis"
    scenario_arrays: dict
    solver_factory: str = "tissuecast.dataset.worker:fem_solver_factory"
    reduced_basis: np.ndarray | None = None
    reduced_elements: np.ndarray | None = None
    reduced_weights: np.ndarray | None = None

    @property
    def key(self) -> str:
        """Content hash identifying this recipe (worker processes cache contexts by it)."""
        h = hashlib.sha256(self.base_key.encode())
        for a in (self.reduced_basis, self.reduced_elements, self.reduced_weights):
            h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    @property
    def base_key(self) -> str:
        """Content hash of everything but the reduced-order predictor: recipes with the same
        base key have the same problem and solvers (:func:`context_for` keeps them)."""
        h = hashlib.sha256(self.config_toml.encode() + self.solver_factory.encode())
        scenario = [a for _, a in sorted(self.scenario_arrays.items())]
        for a in (self.points, self.tets, self.basis.vertices, self.basis.vectors, *scenario):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    @property
    def config(self) -> Config:
        """The data set's configuration."""
        return config_from_dict(tomllib.loads(self.config_toml))

    @property
    def mesh(self) -> "TetMesh":
        """The data set's mesh (built anew on each access)."""
        from ..mesh import TetMesh

        return TetMesh(self.points, self.tets)

    def scenario(self) -> "Scenario":
        """The data set's scenario, rebuilt from the stored arrays and LBO basis (anew on each call)."""
        from ..scenario import restore_scenario

        return restore_scenario(self.mesh, self.config, self.scenario_arrays, self.basis)

    def problem(self):
        """The data set's :class:`~tissuecast.fem.Problem` (its scenario's)."""
        return self.scenario().problem()


@dataclass(frozen=True)
class Task:
    """One sample to solve: its index, seed, kind and force magnitude alpha (N).

    ``guess``: optional (n_nodes, 3) mm nodal displacements to start from (a calibration
    pilot's solution of the previous round or its own linear answer, or a basis sample's
    interim prediction), recorded
    as ``guess_code``; without it the reduced model predicts, if any.
    ``budget``: wall-clock seconds each solver attempt may run (0 = no limit); an attempt
    stopped by it is followed by the cautious retries only (see :func:`solve_task`).
    ``batch_failure``: why the sample's try from the reduced model's prediction failed in a
    batch (:mod:`.batch`); non-empty, :func:`solve_task` records it as attempt 1 and goes on
    with the attempts from zero (only the cautious ones if it was a SolveTimeout).
    ``nominal``: solve at the scenario's nominal parameters, none drawn (the force calibration's
    pilots of a scenario with uncertain parameters: the loads' size is set at the nominal tissue).
    """

    index: int
    seed: int
    beta: float  # NaN for LBO samples, the LBO share for test-2 samples
    alpha: float
    guess: np.ndarray | None = field(default=None, compare=False, repr=False)
    guess_code: int = field(default=int(InitialGuess.PREVIOUS_ROUND), compare=False)
    budget: float = field(default=0.0, compare=False)
    batch_failure: str = field(default="", compare=False)
    nominal: bool = field(default=False, compare=False)


@dataclass(frozen=True, eq=False)
class SampleResult:
    """Outcome of one sample.

    Attributes:
        displacement: (n, 3) float32 mm at the vertices; None when the sample failed.
        forces: (n, 3) float32 nodal forces, N.  weights: (n_b, 3) float64 LBO weights W.
        status: :class:`~.codes.SampleStatus` DONE or FAILED.  reason: failure message ('' when done).
        load_fraction: share of the load reached (1.0 when done).
        attempts: solver attempts used (1 + retries used).
        draw: the sample's scenario draws (:class:`~tissuecast.scenario.ScenarioDraw`; no
            gravity change or indentation in the paper's set-up).
        predicted: :class:`~.codes.InitialGuess`: ZERO solved from zero (no reduced model),
            REDUCED_MODEL converged from the reduced model's prediction, GUESS_FAILED the
            initial guess did not work (the reduced problem or the solve from the guess did
            not converge) and the sample was solved from zero, PREVIOUS_ROUND converged from
            the task's guess (a calibration pilot started from its solution of the previous
            round), INTERIM_MODEL from the task's guess too (a reduced-model basis sample
            started from the prediction of an interim model of the calibration pilots),
            LINEAR_ANSWER from the task's guess too (a first-round calibration pilot started
            from its own linear answer).
        nodal: (n_nodes, 3) float64 mm at every element node (P2: mid-edge nodes too), or
            None; the reduced model is built from these.
        cpu_seconds: CPU time of the worker process spent on the sample, s (its share of a
            batch's); not stored (``seconds``, the wall-clock time, is), reported per phase.
    """

    index: int
    status: SampleStatus
    displacement: np.ndarray | None
    forces: np.ndarray
    weights: np.ndarray
    alpha: float
    beta: float
    seed: int
    increments: int
    iterations: int
    factorizations: int
    seconds: float
    load_fraction: float
    attempts: int
    reason: str = ""
    predicted: InitialGuess = InitialGuess.ZERO
    nodal: np.ndarray | None = None
    draw: object = None
    cpu_seconds: float = 0.0

    @property
    def max_displacement(self) -> float:
        """Largest vertex displacement magnitude, mm (inf for a failed sample)."""
        if self.displacement is None:
            return float("inf")
        return float(np.sqrt((self.displacement.astype(np.float64) ** 2).sum(axis=1)).max())


def retry_solver_config(base: SolverConfig, attempt: int) -> SolverConfig:
    """Solver settings of attempt ``attempt`` (0 = as configured).

    Each retry divides the first increment and the smallest increment by 4, doubles the
    allowed numbers of increments and of iterations per increment, and solves with exact
    Newton directions (``strategy = "newton"``): a different, more cautious path that is
    still deterministic. (Retrying with the same strategy and iteration cap stalled at the
    same load fraction: the cap, not the increment size, was what failed.)
    """
    if attempt == 0:
        return base
    k = 4.0**attempt
    return dataclasses.replace(
        base,
        strategy="newton",
        initial_increment=base.initial_increment / k,
        min_increment=base.min_increment / k,
        max_increments=base.max_increments * 2**attempt,
        max_iterations=base.max_iterations * 2**attempt,
    )


def fem_solver_factory(scenario: "Scenario", cfg: Config) -> Callable[[SolverConfig], object]:
    """The default solver factory: tissuecast's nonlinear neo-Hookean FEM.

    Args:
        scenario: the data set's :class:`~tissuecast.scenario.Scenario` (mesh, supports,
            springs, material regions).
        cfg: the data set's config (what a replacement factory may read; the default reads
            the material and element order from the scenario).

    Returns a function mapping solver settings to a reusable ``Solver`` with
    ``.solve(loads (n_nodes, 3) N, initial_guess=None, prescribed=None, body_loads=None,
    time_limit=None) -> SolveResult`` (raising ConvergenceError on failure, SolveTimeout past
    ``time_limit`` seconds); a replacement factory takes the same two arguments and must give
    solvers with the same call (``prescribed`` and ``body_loads`` are passed only to samples
    that have them).
    """
    from ..fem import Solver

    problem = scenario.problem()
    return lambda solver_cfg: Solver(problem, solver_cfg)


class SampleContext:
    """Per-process state: config, the data set's scenario and the solvers (one per retry level)."""

    def __init__(self, recipe: Recipe):
        self.config = recipe.config
        self.scenario = recipe.scenario()
        self.mesh = self.scenario.mesh
        module, _, name = recipe.solver_factory.partition(":")
        factory = getattr(importlib.import_module(module), name)
        self._make_solver = factory(self.scenario, self.config)
        self._solvers: dict[int, object] = {}
        self.base_key = recipe.base_key
        self.reduced = None
        self.use_predictor(recipe)

    def use_predictor(self, recipe: Recipe) -> None:
        """Take ``recipe``'s reduced-order predictor (None if it has none); ``recipe`` must have
        this context's base key (the same problem), whose solvers are kept."""
        if recipe.base_key != self.base_key:
            raise ValueError("use_predictor: the recipe is for another problem")
        self.reduced = None
        if recipe.reduced_basis is not None:
            from ..fem.reduced import ReducedModel

            self.reduced = ReducedModel(self.solver(0).problem, recipe.reduced_basis, recipe.reduced_elements,
                                        recipe.reduced_weights)

    def solver(self, attempt: int):
        """The solver of retry level ``attempt`` (built on first use, then reused)."""
        if attempt not in self._solvers:
            self._solvers[attempt] = self._make_solver(retry_solver_config(self.config.solver, attempt))
        return self._solvers[attempt]

    def inputs(self, task: Task) -> "SampleInputs":
        """Everything the sample of ``task`` is solved with and recorded by, from its seed
        (:meth:`tissuecast.scenario.Scenario.sample`: its force field, LBO weights, loads on
        every element node, prescribed displacements and scenario draws)."""
        return self.scenario.sample(task.seed, task.alpha, task.beta, nominal=task.nominal)


_CONTEXTS: dict[str, SampleContext] = {}


def context_for(recipe: Recipe) -> SampleContext:
    """This process's context for ``recipe`` (built once, then cached; a recipe that differs
    from the cached one only in its reduced-order predictor keeps the cached solvers)."""
    key = recipe.key
    if key not in _CONTEXTS:
        old = next(iter(_CONTEXTS.values()), None)
        _CONTEXTS.clear()
        if old is not None and old.base_key == recipe.base_key:
            old.use_predictor(recipe)  # only the predictor changed: keep mesh, problem and solvers
            _CONTEXTS[key] = old
        else:
            _CONTEXTS[key] = SampleContext(recipe)
    return _CONTEXTS[key]


def _counts(res) -> tuple[int, int, int]:
    if res is None:
        return 0, 0, 0
    return int(getattr(res, "increments", 0)), int(getattr(res, "iterations", 0)), int(getattr(res, "factorizations", 0))


def _tries(ctx: SampleContext, task: Task, inputs: "SampleInputs") -> tuple[list, InitialGuess]:
    """The solver attempts of a sample, in order, as ``(retry level, initial guess or None)``,
    and the initial-guess code they start with: the task's guess or else the reduced model's
    prediction first (if any), then the usual attempts from zero."""
    tries = [(attempt, None) for attempt in range(ctx.config.solver.retries + 1)]
    if task.batch_failure:  # its try from the prediction was made in a batch
        return tries, InitialGuess.GUESS_FAILED
    if task.guess is not None:
        return [(0, np.asarray(task.guess, dtype=np.float64))] + tries, InitialGuess(task.guess_code)
    if ctx.reduced is None:
        return tries, InitialGuess.ZERO
    guess = inputs.reduced_guess(ctx.reduced)
    if guess is None:
        return tries, InitialGuess.GUESS_FAILED
    return [(0, guess)] + tries, InitialGuess.REDUCED_MODEL


def solve_task(recipe: Recipe, task: Task) -> SampleResult:
    """Solve one sample, retrying with more cautious increments ``solver.retries`` times.

    An attempt that runs past ``task.budget`` seconds is stopped
    (:class:`~tissuecast.errors.SolveTimeout`, its reason recorded) and the sample goes on
    with the retries of a higher level only (the cautious path), not with the others of the
    same level.

    With a guess in the task (``predicted`` its ``guess_code``), or else a reduced model in the
    recipe, a first try starts from it (``predicted`` REDUCED_MODEL; GUESS_FAILED when the
    reduced problem did not converge and there is no prediction); should that try fail, the
    usual attempts from zero follow, so a guess never makes a sample fail. A
    ConvergenceError (or a numerical breakdown: ArithmeticError, LinAlgError) after the last
    retry makes a failed result carrying the reason; any other exception propagates.
    """
    ctx = context_for(recipe)
    inputs = ctx.inputs(task)
    loads, extra = inputs.surface, inputs.solve_keywords()
    forces, weights, draw = inputs.forces, inputs.weights, inputs.draw
    t0, c0 = time.perf_counter(), time.process_time()
    totals = np.zeros(3, dtype=np.int64)
    reasons = [task.batch_failure] if task.batch_failure else []
    load_fraction = 0.0
    tries, predicted = _tries(ctx, task, inputs)
    limit = {"time_limit": task.budget} if task.budget > 0 else {}
    stopped_at = 0 if "SolveTimeout" in task.batch_failure else -1  # retry level of the last attempt stopped by the time budget
    for attempt, guess in tries:
        if attempt <= stopped_at:
            continue  # a stalled sample goes on with its cautious retries only
        try:
            solver = ctx.solver(attempt)
            if inputs.parameters is not None:  # the sample's own materials and springs
                solver = solver.with_parameters(*inputs.solver_parameters)
            kw = {**extra, **limit}
            res = solver.solve(loads, **kw) if guess is None else solver.solve(loads, initial_guess=guess, **kw)
        except (ConvergenceError, ArithmeticError, np.linalg.LinAlgError) as exc:
            if isinstance(exc, SolveTimeout):
                stopped_at = attempt
            totals += _counts(getattr(exc, "result", None))
            load_fraction = max(load_fraction, float(getattr(exc, "load_fraction", 0.0)))
            start = {InitialGuess.PREVIOUS_ROUND: " from the previous round's solution",
                     InitialGuess.INTERIM_MODEL: " from the interim model's prediction",
                     InitialGuess.LINEAR_ANSWER: " from its linear answer",
                     InitialGuess.ZERO: " from zero in one increment"}.get(predicted, " from the prediction")
            reasons.append(f"attempt {attempt + 1}{start if guess is not None else ''}: "
                           f"{type(exc).__name__}: {exc}")
            predicted = InitialGuess.GUESS_FAILED if guess is not None else predicted
            continue
        totals += _counts(res)
        if not getattr(res, "converged", True):  # a solver that reports instead of raising
            load_fraction = max(load_fraction, float(getattr(res, "load_fraction", 0.0)))
            reasons.append(f"attempt {attempt + 1}: not converged at load fraction {load_fraction:.4g}")
            predicted = InitialGuess.GUESS_FAILED if guess is not None else predicted
            continue
        nodal = getattr(res, "nodal_displacement", None)
        return SampleResult(task.index, SampleStatus.DONE, np.asarray(res.displacement, dtype=np.float32),
                            forces.astype(np.float32), weights, task.alpha, task.beta, task.seed, *map(int, totals),
                            time.perf_counter() - t0, 1.0, attempt + 1, predicted=predicted,
                            nodal=None if nodal is None else np.asarray(nodal, dtype=np.float64), draw=draw,
                            cpu_seconds=time.process_time() - c0)
    log.debug("sample %d failed: %s", task.index, reasons[-1])
    return SampleResult(task.index, SampleStatus.FAILED, None, forces.astype(np.float32), weights, task.alpha,
                        task.beta, task.seed, *map(int, totals), time.perf_counter() - t0, load_fraction,
                        ctx.config.solver.retries + 1, "; ".join(reasons), predicted=predicted, draw=draw,
                        cpu_seconds=time.process_time() - c0)
