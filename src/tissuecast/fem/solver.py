"""The nonlinear solver of one problem: the per-mesh set-up and the driving of its solves.

A :class:`Solver` holds the per-mesh set-up (assembler, constrained dofs, the linear-solver
backend with its symbolic analysis, :mod:`.linear`; the reference factorisation at zero
displacement, a pool of numeric factors). Each solve runs in its own
:class:`~tissuecast.fem.newton.SolveRun` (load-stepped Newton iterations with an energy line
search, described in :mod:`tissuecast.fem.newton`; their search directions in
:mod:`tissuecast.fem.directions`), a generator of preconditioner applications that this module
drives: the result of a solve depends only on the problem, the forces, the initial guess and
the configuration (nothing is carried from one solve to the next), and data sets are
reproducible bit for bit. :meth:`Solver.solve_batch` solves several force fields in lockstep
and gathers their preconditioner solves with the shared reference factorisation into
multi-right-hand-side solves; each sample's numbers then differ from its single solve by
round-off and depend only on the batch.

Design, measurements and the history of what was tried: ``docs/solver.md``.
"""

from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np

from ..config import SolverConfig
from ..errors import ConvergenceError, IterationLimit, SolverSetupError, SolveTimeout
from .assembly import Assembler
from .linear import LinearSolver, NotPositiveDefinite, make_linear_solver
from .newton import SolveRun
from .problem import Problem, check_forces
from .result import SolveResult

__all__ = ["Solver", "solve"]


class Solver:
    """Reusable nonlinear solver for one :class:`Problem`.

    Building it does the per-mesh work once (reference gradients, sparsity pattern and
    scatter maps, symbolic factorisation); :meth:`solve` then handles one force field and
    :meth:`solve_batch` several. Each solve keeps its state in its own
    :class:`~tissuecast.fem.newton.SolveRun`.

    Args:
        problem: the finite-element problem.
        config: solver settings (:class:`tissuecast.config.SolverConfig`); its ``order`` is
            ignored here (the problem's order is used).

    Attributes:
        problem, config, assembler: as given / built.
        linear: the linear-solver backend holding the symbolic analysis of the tangent's
            pattern; solves factorise their own :meth:`~.linear.LinearSolver.spawn` of it.
        free_dofs: (n_free,) int, the unknown dofs (node-major, x/y/z).
        constrained_nodes: (c,) int, fixed or prescribed element nodes.
        constrained_dofs: (3 c,) int, their dofs.
        prescribed_values: (3 c,) float, mm, their displacements at full load.
    """

    def __init__(self, problem: Problem, config: SolverConfig | None = None) -> None:
        if not isinstance(problem, Problem):
            raise SolverSetupError(f"problem must be a tissuecast.fem.Problem, got {type(problem).__name__}")
        self.problem = problem
        self.config = config if config is not None else SolverConfig()
        self.assembler = Assembler(problem.nodes, problem.connectivity, problem.order, problem.element_material,
                                   problem.free_mask, springs=problem.springs)
        self.linear = make_linear_solver(self.config.linear_solver, self.assembler, self.config)
        nodes, values = problem.constrained_nodes
        self.constrained_nodes = nodes
        self.constrained_dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        self.prescribed_values = values.ravel()
        self.free_dofs = self.assembler.free_dofs
        self._reference: LinearSolver | bool | None = None  # stiffness at u = 0, factorised on first use
        self._idle_factors: list[LinearSolver] = []  # numeric factors no run holds now

    def with_parameters(self, materials=None, springs=None) -> "Solver":
        """This solver for the same problem with other material constants and/or spring
        stiffnesses (a sample's drawn parameters, :mod:`tissuecast.scenario.parameters`).

        The nodes, supports, sparsity pattern and symbolic factorisation are shared, and so is
        the reference factorisation (the stiffness at zero of this solver's own parameters):
        it only preconditions, so solves still converge to the new parameters' equilibrium.

        Args:
            materials: a :class:`~.material.NeoHookeanField` of the problem's m elements, or None.
            springs: :class:`~.springs.NodalSprings` at the problem's spring nodes, or None.
        """
        if materials is None and springs is None:
            return self
        if self.config.strategy == "krylov" and self.config.reference_preconditioner:
            self.reference_factor()  # factorised once, here, and shared by every view
        out = copy.copy(self)
        changes = {k: v for k, v in (("materials", materials), ("springs", springs)) if v is not None}
        out.problem = dataclasses.replace(self.problem, **changes)
        out.assembler = self.assembler.with_parameters(materials, springs)
        return out

    # ------------------------------------------------------------------ solves
    def solve(self, forces: np.ndarray, initial_guess: np.ndarray | None = None, *, prescribed=None,
              body_loads=None, time_limit: float | None = None, iteration_limit: int | None = None,
              factorization_limit: int | None = None) -> SolveResult:
        """Solve for the equilibrium under dead nodal forces.

        Args:
            forces: (n, 3) float, N, on the mesh vertices (zero on constrained vertices).
                For P2 they act on the corner nodes, like CalculiX ``*CLOAD`` on them. Or
                (n_nodes, 3) on every element node (consistent loads of tractions or gravity).
            initial_guess: optional guess of the displacements at full load, mm: (n, 3) at
                the vertices (mid-edge nodes are then interpolated linearly) or (n_nodes, 3)
                at every element node (e.g. ``nodal_displacement`` of earlier samples, which
                is better for P2). A good guess cuts the work several-fold. With a guess
                the first increment is the full load (``initial_increment`` applies to
                cold starts only).
            prescribed: optional displacements (mm) of vertices that the problem leaves free,
                for this solve only (e.g. an indenting patch), ``{vertex: (3,)}`` or
                ``(ids (k,), values (k, 3))``; reached in proportion to the load fraction, like
                the loads. They are eliminated inside the solve: the sparsity pattern and its
                symbolic factorisation are the Solver's (see :mod:`.newton`). Forces on these
                vertices go into their reactions.
            body_loads: optional (n_nodes, 3) float, N: distributed loads on every element node
                (the consistent loads of a body force such as a change of gravity), added to
                ``forces``. They are left out of the reference force of the convergence test
                (:func:`.convergence.reference_force`: thousands of small nodal shares would make
                the "typical force" tiny); they reach it through the reactions they cause.
            time_limit: optional wall-clock limit, s: the solve is stopped (at its next
                preconditioner application) once it has run longer.
            iteration_limit: optional number of equilibrium iterations (over all increments,
                cut-back ones included): a solve that has not converged within them is
                stopped before it starts another. Unlike ``time_limit`` the same solve stops
                at the same point on any machine under any load.
            factorization_limit: optional number of numeric factorisations (the dominant cost
                of a solve that factorises its tangents): the solve is stopped before it uses
                one more; machine-independent like ``iteration_limit``.

        Returns:
            The converged :class:`SolveResult` (``nodal_reaction`` also at the solve's
            prescribed nodes).

        Raises:
            SolverSetupError: invalid forces or initial guess.
            ConvergenceError: the minimum increment or the increment budget was reached;
                ``load_fraction`` and ``result`` (partial) are attached.
            SolveTimeout: (a ConvergenceError) the solve ran past ``time_limit``.
            IterationLimit: (a ConvergenceError) the solve needed more than ``iteration_limit``
                iterations or ``factorization_limit`` factorisations.
        """
        for name, n in (("iteration_limit", iteration_limit), ("factorization_limit", factorization_limit)):
            if n is not None and not (isinstance(n, (int, np.integer)) and n >= 0):
                raise SolverSetupError(f"{name} must be a non-negative whole number (or None), got {n!r}")
        fext, counted = self._external_forces(forces, body_loads)
        held = self.problem.solve_constraints(prescribed)
        run = SolveRun(self, fext, self._nodal_guess(initial_guess), held=held, counted=counted)
        return _drive(run.steps(), time_limit, run.counts, iteration_limit, factorization_limit)

    def solve_batch(self, forces, initial_guesses=None, prescribed=None, body_loads=None, *,
                    time_limit: float | None = None, parameters=None) -> list:
        """Solve several force fields together, their triangular solves gathered.

        The samples are solved in lockstep: each round advances every unfinished sample to
        its next preconditioner application, and the applications that use the same
        factorisation (with ``reference_preconditioner``: the stiffness at zero, shared by
        all samples until one factorises its own tangent) are done as one
        multi-right-hand-side solve (a supernodal triangular solve is bound by reading the
        factor from memory, so k right-hand sides cost far less than k solves).
        Everything else (tangents, line searches, convergence tests) is per sample and
        exactly as in :meth:`solve`; a sample that must factorise its own tangent gets a
        numeric factor of its own (kept by the Solver for later solves).

        Each sample converges to the same tolerances as with :meth:`solve`; the numbers
        differ from its single solve by round-off (a column of a multi-right-hand-side solve
        is not bitwise the single solve), and depend only on the batch (the same batch gives
        the same bits).

        Args:
            forces: sequence of (n, 3) float arrays, N, as for :meth:`solve`.
            initial_guesses: None, or a sequence of the same length whose entries are None or
                guesses as for :meth:`solve`.
            prescribed, body_loads: None, or sequences of the same length of per-solve
                prescribed displacements and body loads as for :meth:`solve` (entries may be None).
            parameters: None, or a sequence of the same length of ``(materials, springs)``
                pairs (entries may be None): each sample solved by :meth:`with_parameters`
                of them (its drawn parameters); the reference factorisation stays shared.
            time_limit: optional wall-clock limit per sample, s. Each round's wall time is
                shared out among the samples active in it; a sample whose share passes the
                limit is stopped at its next preconditioner application and gets a
                :class:`~tissuecast.errors.SolveTimeout` (the others go on; their columns in
                later rounds change, so their last bits may too).

        Returns:
            One entry per force field, in order: its :class:`SolveResult`, or the
            :class:`~tissuecast.errors.ConvergenceError` it raised (carrying the partial
            result), so that one sample that fails does not lose the others. ``seconds`` of
            each result is the batch's wall time divided by the number of samples.

        Raises:
            SolverSetupError: invalid forces or guesses (before anything is solved).
            Any other exception of a sample's solve (a bug, not a non-convergence) propagates.
        """
        forces = list(forces)
        guesses = [None] * len(forces) if initial_guesses is None else list(initial_guesses)
        if len(guesses) != len(forces):
            raise SolverSetupError(
                f"initial_guesses has {len(guesses)} entries for {len(forces)} force fields; "
                "give one per field (None for none)"
            )
        held = [None] * len(forces) if prescribed is None else list(prescribed)
        body = [None] * len(forces) if body_loads is None else list(body_loads)
        if len(held) != len(forces) or len(body) != len(forces):
            raise SolverSetupError(f"prescribed / body_loads have {len(held)} / {len(body)} entries for {len(forces)} "
                                   "force fields; give one per field (None for none)")
        views = [self] * len(forces) if parameters is None else [self.with_parameters(*p) for p in parameters]
        if len(views) != len(forces):
            raise SolverSetupError(f"parameters has {len(views)} entries for {len(forces)} force fields")
        loads = [self._external_forces(f, b) for f, b in zip(forces, body)]
        guesses = [self._nodal_guess(g) for g in guesses]
        held = [self.problem.solve_constraints(p) for p in held]
        t0 = time.perf_counter()
        out = _drive_lockstep([SolveRun(v, fext, g, held=h, counted=c).steps()
                               for v, (fext, c), g, h in zip(views, loads, guesses, held)], time_limit)
        share = (time.perf_counter() - t0) / max(len(forces), 1)
        return [dataclasses.replace(r, seconds=share) if isinstance(r, SolveResult) else r for r in out]

    # ------------------------------------------------------------------ helpers
    def nodal_field(self, vertex_values: np.ndarray) -> np.ndarray:
        """Extend a vertex field (n, 3) to all element nodes (n_nodes, 3) by linear interpolation."""
        v = np.asarray(vertex_values, dtype=np.float64)
        if self.problem.order == 1:
            return v.copy()
        e = self.problem.mesh.edges
        return np.vstack([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])

    def _external_forces(self, forces, body_loads=None) -> tuple[np.ndarray, np.ndarray | None]:
        """The checked vertex (or element-node) forces plus the body loads, as a (3 n_nodes,)
        vector over every element node, N, and the forces alone when there are body loads
        (the loads the convergence test counts; None = all)."""
        f = check_forces(self.problem, forces)
        fext = np.zeros(self.assembler.n_dofs)
        fext[: f.size] = f.ravel()
        if body_loads is None:
            return fext, None
        b = np.asarray(body_loads, dtype=np.float64)
        if b.shape != (len(self.problem.nodes), 3):
            raise SolverSetupError(f"body_loads must have shape ({len(self.problem.nodes)}, 3) (N per element node), "
                                   f"got {b.shape}")
        b = check_forces(self.problem, b)
        return fext + b.ravel(), fext

    def _nodal_guess(self, initial_guess) -> np.ndarray | None:
        """The checked initial guess at every element node, flattened (None stays None)."""
        if initial_guess is None:
            return None
        g = np.asarray(initial_guess, dtype=np.float64)
        n, n_nodes = self.problem.n_vertices, len(self.problem.nodes)
        if g.shape not in ((n, 3), (n_nodes, 3)) or not np.all(np.isfinite(g)):
            raise SolverSetupError(
                f"initial_guess must be a finite ({n}, 3) array of vertex displacements in mm "
                f"(or ({n_nodes}, 3) at every element node), got shape {g.shape}"
            )
        return (g if len(g) == n_nodes else self.nodal_field(g)).ravel().copy()

    def reference_factor(self) -> LinearSolver | None:
        """The linear solver holding the factorised stiffness at zero displacement (built once;
        None if it is not positive definite, e.g. rigid-body motion left free)."""
        if self._reference is None:
            ref = self.linear.spawn()
            _, data, _ = self.assembler.tangent(np.zeros((len(self.problem.nodes), 3)))
            try:
                ref.factorize(data)
            except NotPositiveDefinite:
                ref = False
            self._reference = ref
        return self._reference or None

    def borrow_factor(self) -> LinearSolver:
        """A numeric factor for a run to factorise its own tangents into (an idle one, or a new
        :meth:`~.linear.LinearSolver.spawn` of :attr:`linear`); give it back when done."""
        return self._idle_factors.pop() if self._idle_factors else self.linear.spawn()

    def give_back_factor(self, factor: LinearSolver) -> None:
        """Return a factor from :meth:`borrow_factor` for later runs."""
        self._idle_factors.append(factor)


def _drive(steps, time_limit: float | None = None, counts=None, iteration_limit: int | None = None,
           factorization_limit: int | None = None):
    """Run a generator of preconditioner applications (:meth:`SolveRun.steps`) with one
    solve each; returns the generator's return value. With ``time_limit`` (s), the generator
    is closed and :class:`~tissuecast.errors.SolveTimeout` raised at the first application
    after that much wall-clock time; with ``iteration_limit`` (and the run's
    :class:`~.result.SolveCounts` ``counts``), :class:`~tissuecast.errors.IterationLimit` at the
    first application once ``counts.iterations`` reached it (the application would start
    one more iteration), and with ``factorization_limit`` at the first application of a
    factorisation past it."""
    t0 = time.perf_counter()
    reply = None
    try:
        while True:
            factor, v = steps.send(reply)
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                steps.close()  # the run gives back its factor
                seconds = time.perf_counter() - t0
                raise SolveTimeout(f"stopped after {seconds:.1f} s, past its time limit of {time_limit:.1f} s",
                                   seconds, time_limit)
            if iteration_limit is not None and counts.iterations >= iteration_limit:  # v would start one more
                steps.close()
                raise IterationLimit(f"stopped after {counts.iterations} iterations without converging, its limit "
                                     f"of {iteration_limit} spent", counts.iterations, iteration_limit)
            if factorization_limit is not None and counts.factorizations > factorization_limit:
                steps.close()
                raise IterationLimit(f"stopped after {counts.iterations} iterations without converging, its limit "
                                     f"of {factorization_limit} factorisations spent", counts.iterations,
                                     factorization_limit)
            reply = factor.solve(v)
    except StopIteration as stop:
        return stop.value


def _drive_lockstep(steps: list, time_limit: float | None = None) -> list:
    """Run several generators of preconditioner applications in lockstep: each round
    advances every unfinished one to its next application, and the applications with the
    same factorisation are done as one multi-right-hand-side solve (columns in generator
    order). Returns each generator's return value, or the ConvergenceError it raised. With
    ``time_limit`` (s), each round's wall time is charged in equal shares to the generators
    active in it, and one whose charge passes the limit is closed and given a
    :class:`~tissuecast.errors.SolveTimeout`."""
    out: list = [None] * len(steps)
    reply: list = [None] * len(steps)
    charged = [0.0] * len(steps)
    active = list(range(len(steps)))
    while active:
        t_round = time.perf_counter()
        groups: dict = {}  # factorisation -> [(generator, vector)], generators in order
        for i in active:
            try:
                factor, v = steps[i].send(reply[i])
            except StopIteration as stop:
                out[i] = stop.value
                continue
            except ConvergenceError as exc:
                out[i] = exc
                continue
            if time_limit is not None and charged[i] > time_limit:
                steps[i].close()  # the run gives back its factor
                out[i] = SolveTimeout(f"stopped after {charged[i]:.1f} s (its share of a batch's time), past its "
                                      f"time limit of {time_limit:.1f} s", charged[i], time_limit)
                continue
            groups.setdefault(id(factor), (factor, []))[1].append((i, v))
        active = []
        for factor, items in groups.values():
            if len(items) == 1:
                reply[items[0][0]] = factor.solve(items[0][1])
            else:
                z = factor.solve(np.column_stack([v for _, v in items]))
                for k, (i, _) in enumerate(items):
                    reply[i] = np.ascontiguousarray(z[:, k])
            active += [i for i, _ in items]
        active.sort()
        share = (time.perf_counter() - t_round) / max(len(active), 1)
        for i in active:
            charged[i] += share
    return out


def solve(problem: Problem, forces: np.ndarray, config: SolverConfig | None = None, initial_guess=None, *,
          prescribed=None, body_loads=None) -> SolveResult:
    """One-off solve: ``Solver(problem, config).solve(forces, initial_guess, prescribed=..., body_loads=...)``.

    Args:
        problem: the finite-element problem.
        forces: (n, 3) float, N, dead loads on the mesh vertices (or (n_nodes, 3) on every node).
        config: solver settings (defaults if None).
        initial_guess: optional (n, 3) float, mm.
        prescribed, body_loads: optional per-solve prescribed vertex displacements and body
            loads (see :meth:`Solver.solve`).
    """
    return Solver(problem, config).solve(forces, initial_guess=initial_guess, prescribed=prescribed,
                                         body_loads=body_loads)
