"""Search directions of the Newton solver: solves with the tangent stiffness.

:class:`SearchDirections` is the part of a solve (:class:`~tissuecast.fem.newton.SolveRun`
derives from it) that turns a tangent into directions ``K^-1 b``: the tangent assembled with
the solve's held dofs eliminated, its factorisation into the run's own numeric factor (borrowed
from the :class:`~tissuecast.fem.solver.Solver`, given back when the run ends) with the shift
ladder ``K + tau diag(K)`` and, past it, the projected stiffness for a tangent that is not
positive definite; the preconditioner application ``R K_old^-1 R^T`` with the rigid rotation
applied since the active factorisation was made; and the deflated, preconditioned conjugate
gradients of the ``"krylov"`` strategy (:mod:`.krylov`) with the directions recycled from the
solve's earlier iterations. The linear-solver backends themselves are in :mod:`.linear`.

Every preconditioner application is yielded (``(factor, vector)``, see
:func:`.krylov.corotated_solve`), so the methods that apply it are generators that the Solver
drives, one solve at a time or several in lockstep.
"""

from __future__ import annotations

import logging

import numpy as np

from .convergence import IncrementFailed
from .krylov import N_ROTATIONS, corotated_solve, deflated_cg, deflation_space, recycle, rigid_rotations
from .linear import NotPositiveDefinite
from .result import SolveCounts

__all__ = ["SearchDirections", "SHIFT_FIRST", "SHIFT_RESTART", "SHIFT_GROWTH", "SHIFT_LAST", "FRESH_STEPS_FACTOR"]

log = logging.getLogger(__name__)

#: First shift ``tau`` of an indefinite tangent, ``K + tau diag(K)``: a mild regularisation.
SHIFT_FIRST = 1e-3
#: A new ladder starts at this share of the last shift that worked in the solve.
SHIFT_RESTART = 0.5
#: Growth of the shift per failed factorisation.
SHIFT_GROWTH = 4.0
#: Beyond this shift the tangent has little left of K: the projected stiffness is used.
SHIFT_LAST = 10.0
#: With an approximate preconditioner just made from the current tangent, conjugate gradients
#: may take this many times ``krylov_iterations`` steps before settling for their iterate.
FRESH_STEPS_FACTOR = 4


class SearchDirections:
    """The tangent solves of one solve: its held dofs, its factorisation state and counters.

    Args:
        solver: the :class:`~tissuecast.fem.solver.Solver` (per-mesh set-up) the solve uses.
        held: optional ``(node ids (p,), displacements at full load (p, 3) mm)`` of nodes free
            in the Solver's pattern that this solve holds (see :mod:`.newton`), from
            :meth:`~tissuecast.fem.Problem.solve_constraints`.

    Attributes:
        counts: :class:`~tissuecast.fem.result.SolveCounts`.
        tau: shift of the last indefinite tangent that factorised (0 after a plain one).
        rotation: (3, 3) rigid rotation applied since the active factorisation was made.
        recycled: (n_free, j) Krylov directions kept from earlier iterations, or None.
        active: the factorisation the preconditioner uses now (None before the first).
        factor_valid: whether ``active`` may still be used (False after a failed increment).
        linear: this solve's own numeric factor, borrowed from the Solver on first need.
        held_dofs, held_values: (3 p,) the held dofs and their values at full load, mm.
        held: (3 p,) int, their positions in the free-dof vector.
        cnodes, cdofs: the Solver's constrained nodes / dofs with the held ones.
    """

    def __init__(self, solver, held: tuple | None = None) -> None:
        self.solver = solver
        self.config = solver.config
        self.assembler = solver.assembler
        self.counts = SolveCounts()
        self.tau = 0.0
        self.rotation = np.eye(3)
        self.recycled: np.ndarray | None = None
        self.active = None
        self.factor_valid = False
        self.linear = None
        self._held_setup(held)

    def _held_setup(self, held) -> None:
        """The solve's own held dofs: global ids, values, positions in the free vector, the CSR
        entries that couple them, and the constrained nodes / dofs with them."""
        sv = self.solver
        nodes = np.zeros(0, dtype=np.int64) if held is None else np.asarray(held[0], dtype=np.int64)
        values = np.zeros((0, 3)) if held is None else np.asarray(held[1], dtype=np.float64).reshape(-1, 3)
        self.held_dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        self.held_values = values.ravel()
        self.held = self.assembler.free_position[self.held_dofs]
        if np.any(self.held < 0):
            raise ValueError("held nodes must be free in the Solver's problem")  # Problem.solve_constraints checks
        self._coupling = self.assembler.coupling_entries(self.held) if len(self.held) else None
        self.cnodes = np.concatenate([sv.constrained_nodes, nodes])
        self.cdofs = np.concatenate([sv.constrained_dofs, self.held_dofs])

    def _tangent(self, u: np.ndarray, project: bool = False) -> np.ndarray:
        """CSR data (nnz,) of the tangent at ``u`` (3 n_nodes,) with the held dofs eliminated."""
        _, data, _ = self.assembler.tangent(u.reshape(-1, 3), project=project)
        return self._eliminate(data)

    def _eliminate(self, data: np.ndarray) -> np.ndarray:
        """Zero (in place) the entries coupling the held dofs; their diagonal stays."""
        if self._coupling is not None:
            data[self._coupling] = 0.0
        return data

    def _precondition(self, v: np.ndarray):
        """``R K^-1 R^T v`` with the active factorisation (a generator, see
        :func:`.krylov.corotated_solve`), zero at the held dofs (the factorisation may be the
        shared reference one, which does not eliminate them)."""
        if len(self.held):
            v = v.copy()
            v[self.held] = 0.0
        z = yield from corotated_solve(self.active, self.rotation, v)
        if len(self.held):
            z[self.held] = 0.0
        self.counts.solves += 1
        return z

    def krylov_direction(self, u: np.ndarray, r: np.ndarray):
        """-K^-1 r for the tangent K at u (a generator): :meth:`krylov_solve` with ``b = -r``."""
        d, data = yield from self.krylov_solve(u, -r)
        return d, data

    def krylov_solve(self, u: np.ndarray, b: np.ndarray, data: np.ndarray | None = None, fresh: bool = False):
        """K^-1 b for the tangent K at u by deflated preconditioned conjugate gradients
        (a generator, :mod:`.krylov`).

        Args:
            u: (3 n_nodes,) mm, current displacements.  b: (n_free,) N, right-hand side
                (zero at the held dofs).
            data: the tangent's CSR data with the held dofs eliminated, if already assembled.
            fresh: the preconditioner was just made from this tangent but is an approximate
                inverse (:attr:`.linear.LinearSolver.exact` False): up to
                ``FRESH_STEPS_FACTOR`` times more steps, and the iterate so far if the
                tolerance is still not met.

        Returns:
            ``(x, None)`` when the relative residual fell below ``krylov_tolerance`` within
            ``krylov_iterations`` steps (or negative curvature was met after some progress:
            the iterate so far is still a descent direction), else ``(None, K data)`` so that
            the caller factorises the tangent already assembled.
        """
        cfg = self.config
        sv = self.solver
        if data is None:
            data = self._tangent(u)
        k = self.assembler.matrix(data)
        space = None
        if cfg.krylov_recycle:
            if sv.problem.can_swing:
                spin = rigid_rotations(sv.problem.nodes + u.reshape(-1, 3), sv.constrained_nodes, sv.free_dofs,
                                       self.held)
            else:
                spin = np.zeros((len(sv.free_dofs), 0))
            space, self.recycled = deflation_space(k, spin, self.recycled)
        steps_cap = cfg.krylov_iterations * (FRESH_STEPS_FACTOR if fresh else 1)
        x, steps, found = yield from deflated_cg(k, b, space, self._precondition, cfg.krylov_tolerance, steps_cap,
                                                 best_effort=fresh)
        self.counts.krylov_steps += steps
        self.recycled = recycle(found, space, cfg.krylov_recycle, self.recycled,
                                N_ROTATIONS if sv.problem.can_swing else 0)
        return (x, None) if x is not None else (None, data)

    def factorize(self, u: np.ndarray, data: np.ndarray | None = None) -> None:
        """Factorise the tangent K at u (CSR values ``data`` if already assembled) into this
        run's own factor; if K is not positive definite, ``K + tau diag(K)`` with the smallest
        working ``tau`` of the ladder ``max(SHIFT_FIRST, SHIFT_RESTART * last) * SHIFT_GROWTH^k``
        up to ``SHIFT_LAST``; past that, the projected stiffness (material tangent clamped to
        its positive-definite part at each quadrature point).

        Raises:
            IncrementFailed: not even the projected stiffness factorises.
        """
        if data is None:
            data = self._tangent(u)
        if self.linear is None:
            self.linear = self.solver.borrow_factor()
        self.active = self.linear
        self.counts.factorizations += 1
        try:
            self.linear.factorize(data)
            self.tau = 0.0
            return
        except NotPositiveDefinite:
            log.debug("tangent not positive definite")
        if self._factorize_shifted(data):
            return
        data = self._tangent(u, project=True)
        self.counts.factorizations += 1
        try:
            self.linear.factorize(data)
            self.counts.projected += 1
        except NotPositiveDefinite:
            raise IncrementFailed("projected tangent stiffness could not be factorised") from None

    def _factorize_shifted(self, data: np.ndarray) -> bool:
        """Climb the shift ladder; True once a shifted tangent factorised."""
        idx = self.assembler.diagonal_index
        diag = data[idx]
        tau = max(SHIFT_RESTART * self.tau, SHIFT_FIRST)
        while tau <= SHIFT_LAST:
            shifted = data.copy()
            shifted[idx] += tau * diag
            self.counts.factorizations += 1
            try:
                self.linear.factorize(shifted)
            except NotPositiveDefinite:
                tau *= SHIFT_GROWTH
                continue
            self.tau = tau
            self.counts.shifted += 1
            return True
        return False

    def _give_back_factor(self) -> None:
        if self.linear is not None:
            self.solver.give_back_factor(self.linear)
            self.linear = self.active = None
            self.factor_valid = False
