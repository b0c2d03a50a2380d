"""Nonlinear equilibrium by Newton iterations with automatic load incrementation: one solve.

The dead-load problem is conservative: equilibrium is a stationary point of the potential
energy ``Pi(u) = sum_e W(F) dV - f . u``, so the solver minimises ``Pi`` with Newton steps
and an energy line search. Per load increment (``lambda`` from 0 to 1; forces and
prescribed displacements scale with ``lambda``):

1. Predictor: the initial guess (first increment) or a linear extrapolation of the last
   converged increment; rejected if it inverts an element.
2. Direction ``d = -K^-1 r`` (``r``: internal minus external forces on the free dofs).
   Strategy ``"krylov"`` (default) assembles the tangent ``K`` at every iteration and solves
   with it by conjugate gradients preconditioned by the last factorisation, co-rotated by
   the rigid rotation applied since (``R K_old^-1 R^T``), to a relative residual of
   ``krylov_tolerance`` in at most ``krylov_iterations`` steps, deflated by the rigid
   rotations about the constrained nodes' centroid and the search directions of the solve's
   earlier iterations (``krylov_recycle``); only when that fails is ``K`` factorised.
   ``"newton"`` factorises at every iteration; ``"quasi-newton"`` reuses the last
   factorisation as it is while the residual falls by ``refactor_ratio`` per iteration. A
   tangent that is not positive definite is shifted, ``K + tau diag(K)``. A solve with an
   initial guess (``reference_preconditioner``) is preconditioned by the stiffness at zero
   displacement, factorised once per Solver and co-rotated by the guess's best-fit rotation.
3. Line search on ``Pi`` (Armijo, quadratic backtracking), rejecting any step that makes
   ``J <= 0`` at a quadrature point; with ``rotation_aware`` the step's rigid rotation about
   the constrained nodes' centroid is applied as a finite rotation.
4. Convergence (Abaqus-like; both must hold): the largest residual component
   ``<= force_tolerance * q`` (``q`` the mean magnitude of the applied nodal forces and
   support reactions) and the largest correction, scaled by ``rho / (1 - rho)`` when the
   corrections contract slowly, ``<= displacement_tolerance *`` the largest displacement of
   the increment.
5. Increment control: an increment converged within ``grow_iterations`` iterations makes the
   next one 1.5x larger; a failed one is retried with a quarter of the load step; below
   ``min_increment`` or after ``max_increments`` attempts
   :class:`~tissuecast.errors.ConvergenceError` is raised with the load fraction reached.
   With ``"krylov"``, an increment that fails right after a failed one is tried again at the
   same load step with exact Newton directions (a factorisation every iteration) and twice
   ``max_iterations``, until an increment converges: past a limit point the body snaps to a
   distant equilibrium, which smaller load steps do not bring closer and inexact directions
   approach only slowly.

A :class:`SolveRun` is made by :class:`~tissuecast.fem.solver.Solver` for every solve and
holds everything that lives for that solve only: the external loads and prescribed values
(also those of dofs that only this solve holds, e.g. an indenting patch), the initial guess
and the increment state; its search directions (step 2: the counters, the shift of the last
indefinite tangent, the rigid rotation applied since the active factorisation was made, the
recycled Krylov directions, the active factorisation and its own numeric factor) come from
:class:`~tissuecast.fem.directions.SearchDirections`, which it derives from. The Solver keeps
only per-mesh things (assembler, constrained dofs, symbolic analysis, reference
factorisation), so one Solver serves any number of runs, one by one or in lockstep.

:meth:`SolveRun.steps` is a generator of preconditioner applications (see
:func:`.krylov.corotated_solve`) that returns the :class:`~tissuecast.fem.result.SolveResult`;
the Solver drives it. The line search is :mod:`.linesearch`, the convergence test
:func:`.convergence.converged`. Design, measurements and the history of what was tried:
``docs/solver.md``.

Dofs held by this solve only (``held``: free in the Solver's pattern) are eliminated inside the
solve, so the sparsity pattern and its symbolic factorisation stay shared: their rows and
columns of every tangent are zeroed but for the diagonal, their residual is zero, and their
values follow the load fraction. Each increment first moves them to their new values with
the linear response of the rest of the body (the "lift": ``K_ff d_f = -K_fh delta_h``, one
linear solve with the tangent), so that the nodes next to them follow instead of being
overrun; then the Newton iterations run with them held.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConvergenceError
from .convergence import RESIDUAL_ALONE, IncrementFailed, converged, correction_estimate, reference_force
from .directions import SearchDirections
from .linesearch import line_search, residual, step_path
from .result import SolveCounts, SolveResult

if TYPE_CHECKING:
    from .solver import Solver

__all__ = ["SolveRun", "SolveCounts", "IncrementFailed", "best_rotation"]

log = logging.getLogger(__name__)

#: Next load step after an increment that converged within ``grow_iterations`` iterations.
INCREMENT_GROWTH = 1.5
#: Load step kept after a failed increment (retried from the last converged state).
CUTBACK = 0.25
#: A load fraction this close to 1 is 1 (no sliver of an increment left over by round-off).
LOAD_SNAP = 1e-9
#: Guards divisions by norms that may be exactly zero.
_TINY = 1e-300
#: Held dofs within this share of their largest target value are where they should be: no lift.
LIFT_ROUNDOFF = 1e-12


@dataclass
class _Iterations:
    """Book-keeping of the Newton iterations of one increment."""

    need_factor: bool  # the next direction needs a new factorisation
    start: np.ndarray  # (n_free,) mm, displacements at the start of the increment
    fresh: bool = False  # the direction was computed with a factorisation made this iteration
    reuses: int = 0  # iterations since the last factorisation (quasi-newton)
    last_correction: float | None = None  # largest correction of the previous iteration, mm


def best_rotation(nodes: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The rotation R (3, 3) that best maps the reference nodes onto the displaced ones
    (Kabsch): ``x + u - c' ~= R (x - c)`` in least squares over all nodes.

    Args:
        nodes: (n_nodes, 3) mm; u: (n_nodes, 3) or (3 n_nodes,) mm.
    """
    x = nodes - nodes.mean(axis=0)
    y = nodes + u.reshape(-1, 3)
    y = y - y.mean(axis=0)
    a, _, bt = np.linalg.svd(y.T @ x)
    d = np.sign(np.linalg.det(a @ bt)) or 1.0
    return a @ np.diag([1.0, 1.0, d]) @ bt


class SolveRun(SearchDirections):
    """One solve of a :class:`~tissuecast.fem.solver.Solver`: its state and iterations.

    Args:
        solver: the Solver (per-mesh set-up) this run uses.
        fext: (3 n_nodes,) float, N: external nodal forces at full load, on every element node.
        guess: optional (3 n_nodes,) float, mm: initial guess at full load (None: from zero).
        prescribed: optional (3 c,) float, mm: values of the constrained dofs at full load
            (default the problem's).
        held: optional ``(node ids (p,), displacements at full load (p, 3) mm)`` of nodes free
            in the Solver's pattern that this solve holds (see the module notes), from
            :meth:`~tissuecast.fem.Problem.solve_constraints`.
        counted: optional (3 n_nodes,) float, N: the part of ``fext`` that counts as applied
            forces in the convergence test's reference force (default all of it; body loads
            are left out, see :meth:`~.solver.Solver.solve`).

    Attributes:
        fext, counted, guess, prescribed: as given (``prescribed`` the problem's by default).
        exact: the increment being tried takes exact Newton directions (step 5 of the module
            notes: ``"krylov"`` after two failed increments in a row).
        Those of :class:`~tissuecast.fem.directions.SearchDirections` (``counts``, ``tau``,
        ``rotation``, ``recycled``, ``active``, ``factor_valid``, ``linear``, the held dofs).
    """

    def __init__(self, solver: "Solver", fext: np.ndarray, guess: np.ndarray | None = None,
                 prescribed: np.ndarray | None = None, held: tuple | None = None,
                 counted: np.ndarray | None = None) -> None:
        self.t0 = time.perf_counter()
        super().__init__(solver, held)
        self.fext = fext
        self.counted = counted
        self.guess = guess
        self.prescribed = solver.prescribed_values if prescribed is None else prescribed
        self.exact = False
        cfg = self.config
        if guess is not None and cfg.strategy == "krylov" and cfg.reference_preconditioner:
            reference = solver.reference_factor()
            if reference is not None:
                self.active, self.factor_valid = reference, True
                if solver.problem.can_swing:
                    self.rotation = best_rotation(solver.problem.nodes, guess)

    @property
    def exact_steps(self) -> bool:
        """Whether every iteration factorises the tangent: strategy ``"newton"``, or an
        increment tried with exact Newton directions (:attr:`exact`)."""
        return self.config.strategy == "newton" or self.exact

    def _residual(self, fint: np.ndarray, fext: np.ndarray) -> np.ndarray:
        return residual(fint, fext, self.solver.free_dofs, self.held)

    # ------------------------------------------------------------------ load stepping
    def steps(self):
        """The solve as a generator of preconditioner applications; returns the
        :class:`SolveResult` or raises :class:`~tissuecast.errors.ConvergenceError`."""
        cfg = self.config
        u_conv = np.zeros(len(self.fext))
        lam, dlam = 0.0, (1.0 if self.guess is not None else float(cfg.initial_increment))
        prev = None  # (increment displacement, increment size) of the last converged increment
        increments = cutbacks = attempts = 0
        failed_last = False  # the last increment tried failed
        qhist: list = []
        try:
            while lam < 1.0:
                attempts += 1
                lam_new = min(1.0, lam + dlam)
                if 1.0 - lam_new < LOAD_SNAP:
                    lam_new = 1.0
                u = self._predict(u_conv, lam, lam_new, prev)
                try:
                    if attempts > cfg.max_increments:
                        raise IncrementFailed(f"the budget of {cfg.max_increments} increments is spent")
                    it0 = self.counts.iterations
                    u = yield from self._increment(u, u_conv, lam_new, qhist)
                except IncrementFailed as exc:
                    cutbacks += 1
                    self.factor_valid = False
                    failed_before, failed_last = failed_last, True
                    if failed_before and cfg.strategy == "krylov" and not self.exact:
                        self.exact = True
                        log.debug("increment to %.4g failed again (%s); trying it with exact Newton steps", lam_new, exc)
                        continue
                    dlam *= CUTBACK
                    if dlam < cfg.min_increment or attempts > cfg.max_increments:
                        raise self._stopped(u_conv, lam, increments, cutbacks, exc) from None
                    log.debug("increment to %.4g failed (%s); cutting back to %.4g", lam_new, exc, dlam)
                    continue
                increments += 1
                self.exact = failed_last = False
                prev = (u - u_conv, lam_new - lam)
                u_conv, lam = u, lam_new
                if self.counts.iterations - it0 <= cfg.grow_iterations:
                    dlam = min(1.0, dlam * INCREMENT_GROWTH)
            return self._result(u_conv, 1.0, True, increments, cutbacks)
        finally:
            self._give_back_factor()

    def _stopped(self, u_conv, lam: float, increments: int, cutbacks: int, exc) -> ConvergenceError:
        result = self._result(u_conv, lam, False, increments, cutbacks)
        return ConvergenceError(
            f"the solver stopped at load fraction {lam:.4g} ({exc}); the forces may be too large "
            "for the supports (elements invert or the body buckles) -- reduce them, fix more "
            "vertices, or allow smaller increments (solver.min_increment)",
            load_fraction=lam,
            result=result,
        )

    def _predict(self, u_conv, lam, lam_new, prev) -> np.ndarray:
        """Start of an increment: the guess, else the extrapolated last increment, else the
        last converged state; the first that inverts no element."""
        candidates = []
        if self.guess is not None and lam == 0.0:
            candidates.append(lam_new * self.guess)
        if prev is not None:
            candidates.append(u_conv + (lam_new - lam) / prev[1] * prev[0])
        candidates.append(u_conv.copy())
        for u in candidates:
            u[self.solver.constrained_dofs] = lam_new * self.prescribed  # held dofs: lifted by _increment
            if len(candidates) == 1 or self.assembler.internal_force(u.reshape(-1, 3))[1] > 0.0:
                return u
        return u

    def _result(self, u, lam, converged, increments, cutbacks) -> SolveResult:
        cdofs = self.cdofs
        nodal = u.reshape(-1, 3).copy()
        fint, _ = self.assembler.internal_force(nodal)
        reaction = np.zeros_like(nodal)
        reaction.ravel()[cdofs] = (fint - lam * self.fext)[cdofs]
        counts = self.counts
        return SolveResult(
            displacement=nodal[: self.solver.problem.n_vertices].copy(),
            converged=converged,
            load_fraction=float(lam),
            increments=increments,
            iterations=counts.iterations,
            factorizations=counts.factorizations,
            residual_history=list(counts.residual_history),
            seconds=time.perf_counter() - self.t0,
            nodal_displacement=nodal,
            nodal_reaction=reaction,
            cutbacks=cutbacks,
            solves=counts.solves,
        )

    # ------------------------------------------------------------------ one increment
    def _increment(self, u: np.ndarray, u_start: np.ndarray, lam: float, qhist: list):
        """Newton iterations to equilibrium at load fraction ``lam`` from ``u`` (a generator
        of preconditioner applications); returns the converged displacements."""
        cfg = self.config
        free = self.solver.free_dofs
        fext = lam * self.fext
        track = _Iterations(need_factor=self.exact_steps or not self.factor_valid,
                            start=u_start[free])
        u = yield from self._lift(u, lam, track)
        energy, fint, jmin = self.assembler.energy_and_force(u.reshape(-1, 3))
        if not jmin > 0.0:
            raise IncrementFailed("the predictor inverts an element")
        pi = energy - float(fext @ u)
        r = self._residual(fint, fext)
        q0 = self._reference_force(u, fint, fext, lam)
        if len(r) == 0 or float(np.abs(r).max()) <= RESIDUAL_ALONE * cfg.force_tolerance * q0:
            qhist.append(q0)
            return u  # already in equilibrium (e.g. no load at all)
        iterations = cfg.max_iterations * (2 if self.exact else 1)
        for _ in range(iterations):
            d = yield from self._direction(u, r, track)
            step = self._line_search(u, d, pi, r, fext)
            if step is None:
                if track.fresh:
                    raise IncrementFailed("line search found no energy decrease along a fresh Newton direction")
                track.need_factor = True
                continue
            s, u, pi, fint, r_new, rot = step
            self.rotation = rot @ self.rotation
            self.counts.iterations += 1
            rnorm_old = np.linalg.norm(r)
            r = r_new
            if self._converged(u, r, s * d, fint, fext, qhist, track, lam):
                qhist.append(self._reference_force(u, fint, fext, lam))
                return u
            self._next_iteration(track, np.linalg.norm(r) / max(rnorm_old, _TINY))
        raise IncrementFailed(f"no convergence in {iterations} iterations")

    def _lift(self, u: np.ndarray, lam: float, track: _Iterations):
        """Move the held dofs to ``lam`` times their values, the rest of the body by the linear
        response ``K_ff d_f = -K_fh delta_h`` of the tangent at ``u`` (a generator); returns
        the new displacements (``u`` itself when the held dofs are already there)."""
        if not len(self.held):
            return u
        target = lam * self.held_values
        delta = target - u[self.held_dofs]
        if float(np.abs(delta).max()) <= LIFT_ROUNDOFF * max(float(np.abs(target).max()), _TINY):
            u[self.held_dofs] = target
            return u
        _, data, jmin = self.assembler.tangent(u.reshape(-1, 3))
        if not jmin > 0.0:
            raise IncrementFailed("the state before moving the held dofs inverts an element")
        step = np.zeros(len(self.solver.free_dofs))
        step[self.held] = delta
        b = -(self.assembler.matrix(data) @ step)
        b[self.held] = 0.0
        d = yield from self._solve_tangent(u, b, track, self._eliminate(data))
        d[self.held] = delta
        self.counts.iterations += 1
        u = u.copy()
        u[self.solver.free_dofs] += d
        return u

    def _direction(self, u: np.ndarray, r: np.ndarray, track: _Iterations):
        """The Newton direction ``-K^-1 r`` by the configured strategy (a generator)."""
        d = yield from self._solve_tangent(u, -r, track)
        return d

    def _solve_tangent(self, u: np.ndarray, b: np.ndarray, track: _Iterations, data: np.ndarray | None = None):
        """``K^-1 b`` with the tangent K at ``u`` (CSR ``data`` with the held dofs eliminated, if
        already assembled), by the configured strategy (a generator)."""
        x = None
        if self.config.strategy == "krylov" and not track.need_factor:
            x, data = yield from self.krylov_solve(u, b, data)
            track.need_factor = x is None
        if track.need_factor:
            self.factorize(u, data)
            self.factor_valid = True
            self.rotation = np.eye(3)
            track.fresh, track.reuses = True, 0
        if x is None and not self.active.exact:  # an approximate inverse: CG with the fresh one
            x, _ = yield from self.krylov_solve(u, b, fresh=True)
        if x is None:
            x = yield from self._precondition(b)
        return x

    def _line_search(self, u, d, pi0, r0, fext):
        sv = self.solver
        path = step_path(sv.problem.nodes, u, d, sv.free_dofs, self.cnodes, self.cdofs,
                         self.config.rotation_aware and sv.problem.can_swing)
        return line_search(self.assembler, path, sv.free_dofs, d, pi0, r0, fext, self.held)

    def _reference_force(self, u: np.ndarray, fint: np.ndarray, fext: np.ndarray, lam: float) -> float:
        """:func:`reference_force` at load fraction ``lam`` (``fext = lam * self.fext``), with
        the reactions of the held nodes and of the springs, body loads left out."""
        springs = self.assembler.springs
        support = None if springs is None else springs.forces(u.reshape(-1, 3))[springs.dofs]
        counted = None if self.counted is None else lam * self.counted
        return reference_force(fint, fext, self.cnodes, support, counted)

    def _converged(self, u, r, c, fint, fext, qhist, track: _Iterations, lam: float) -> bool:
        """Record the iteration's residual and apply :func:`converged` to it."""
        cfg = self.config
        rmax = float(np.abs(r).max()) if len(r) else 0.0
        self.counts.residual_history.append(rmax)
        q = max(np.mean(qhist + [self._reference_force(u, fint, fext, lam)]), _TINY)
        cmax = float(np.abs(c).max())
        est = correction_estimate(cmax, track.last_correction)
        dmax = float(np.abs(u[self.solver.free_dofs] - track.start).max()) if len(r) else 0.0
        log.debug("lam %.4g it: |r|max %.3e (q %.3e) |c|max %.3e est %.3e du %.3e reuse %d",
                  lam, rmax, q, cmax, est, dmax, track.reuses)
        track.last_correction = cmax
        return converged(rmax, q, cmax, est, dmax, float(np.abs(u).max()), cfg.force_tolerance,
                         cfg.displacement_tolerance)

    def _next_iteration(self, track: _Iterations, ratio: float) -> None:
        """Whether the next iteration factorises (``ratio``: residual-norm reduction)."""
        cfg = self.config
        track.reuses += 0 if track.fresh else 1
        track.fresh = False
        track.need_factor = self.exact_steps or (
            cfg.strategy == "quasi-newton" and (ratio > cfg.refactor_ratio or track.reuses >= cfg.max_quasi_newton))

