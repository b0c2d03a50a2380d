"""Nonlinear equilibrium by Newton-type iterations with automatic load incrementation.

The dead-load problem is conservative: equilibrium is a stationary point of the potential
energy ``Pi(u) = sum_e W(F) dV - f . u``, so the solver minimises ``Pi`` with Newton-type
steps and an energy line search. Per load increment (``lambda`` from 0 to 1, forces and
prescribed displacements scale with ``lambda``):

1. Predictor: the initial guess (first increment) or a linear extrapolation of the last
   converged increment; rejected if it inverts an element.
2. Iterations: direction ``d = -H r`` where ``r`` is the residual (internal minus external
   forces on the free dofs) and ``H`` the inverse of the last factorised tangent stiffness,
   improved by BFGS updates from the iterations since (strategy ``"quasi-newton"``); the
   tangent is refactorised when the residual fell by less than ``refactor_ratio`` in the
   last iteration, after ``max_quasi_newton`` updates, or when the step fails. Strategy
   ``"newton"`` refactorises at every iteration (plain Newton-Raphson with line search).
   A tangent that is not positive definite is factorised with a diagonal shift
   ``K + beta diag(K)``, which keeps ``d`` a descent direction.
3. Line search on ``Pi`` (Armijo, quadratic backtracking), also rejecting any step that
   makes ``J <= 0`` at a quadrature point.
4. Convergence (Abaqus-like, both must hold): largest residual component
   ``<= force_tolerance * q`` where ``q`` is the mean magnitude of the applied nodal forces
   and support reactions (averaged over the increments so far), and the largest
   correction, multiplied by ``rho / (1 - rho)`` when the observed convergence rate ``rho``
   is linear, ``<= displacement_tolerance *`` the largest displacement of the increment.
   A residual below ``1e-8 q`` is accepted alone.
5. Increment control: after an increment converged within ``grow_iterations`` iterations
   the next one is 1.5x larger; a failed increment (``max_iterations`` reached, line
   search failure, inverted elements) is retried from the last converged state with a
   quarter of the load step. Below ``min_increment``, or after ``max_increments`` attempts,
   :class:`~tissuecast.errors.ConvergenceError` is raised with the load fraction reached.

The result of a solve depends only on the problem, the forces, the initial guess and the
configuration (no state is carried from one solve to the next), so data sets are
reproducible bit for bit.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..config import SolverConfig
from ..errors import ConvergenceError, SolverSetupError
from .assembly import Assembler
from .linear import NotPositiveDefinite, make_linear_solver
from .problem import Problem, check_forces
from .result import SolveResult

__all__ = ["Solver", "solve"]

log = logging.getLogger(__name__)

_GROW = 1.5
_CUT = 0.25


class _Failed(Exception):
    """An increment did not converge (internal control flow)."""


class Solver:
    """Reusable nonlinear solver for one :class:`Problem`.

    Building it does the per-mesh work once (reference gradients, sparsity pattern and
    scatter maps, symbolic factorisation); :meth:`solve` then handles one force field.

    Args:
        problem: the finite-element problem.
        config: solver settings (:class:`tissuecast.config.SolverConfig`); its ``order`` is
            ignored here (the problem's order is used).
    """

    def __init__(self, problem: Problem, config: SolverConfig | None = None) -> None:
        if not isinstance(problem, Problem):
            raise SolverSetupError(f"problem must be a tissuecast.fem.Problem, got {type(problem).__name__}")
        self.problem = problem
        self.config = config if config is not None else SolverConfig()
        self.assembler = Assembler(problem.nodes, problem.connectivity, problem.order, problem.material, problem.free_mask)
        self.linear = make_linear_solver(self.config.linear_solver, self.assembler)
        nodes, values = problem.constrained_nodes
        self._cnodes = nodes
        self._cdofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        self._cdisp = values.ravel()
        self._free = self.assembler.free_dofs
        self._n = problem.n_vertices

    # ------------------------------------------------------------------ helpers
    def nodal_field(self, vertex_values: np.ndarray) -> np.ndarray:
        """Extend a vertex field (n, 3) to all element nodes (n_nodes, 3) by linear interpolation."""
        v = np.asarray(vertex_values, dtype=np.float64)
        if self.problem.order == 1:
            return v.copy()
        e = self.problem.mesh.edges
        return np.vstack([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])

    def _factorize(self, u: np.ndarray) -> None:
        """Factorise the tangent at u; if it is not positive definite, its projected PD version."""
        for project in (False, True):
            _, data, _ = self.assembler.tangent(u.reshape(-1, 3), project=project)
            self._stats["factorizations"] += 1
            try:
                self.linear.factorize(data)
                if project:
                    self._stats["projected"] += 1
                return
            except NotPositiveDefinite:
                log.debug("tangent not positive definite%s", " even projected" if project else "")
        diag_idx = self.assembler.diagonal_index
        diag = np.abs(data[diag_idx])
        for beta in (1e-4, 1e-2, 1.0):
            shifted = data.copy()
            shifted[diag_idx] += beta * diag
            self._stats["factorizations"] += 1
            try:
                self.linear.factorize(shifted)
                return
            except NotPositiveDefinite:
                continue
        raise _Failed("tangent stiffness could not be factorised even projected and shifted")

    def _direction(self, r: np.ndarray, memory: list) -> np.ndarray:
        """-H r by the BFGS two-loop recursion on top of the factorised tangent."""
        q = r.copy()
        alphas = []
        for s, y, rho in reversed(memory):
            a = rho * (s @ q)
            q -= a * y
            alphas.append(a)
        z = self.linear.solve(q)
        self._stats["solves"] += 1
        for (s, y, rho), a in zip(memory, reversed(alphas)):
            b = rho * (y @ z)
            z += (a - b) * s
        return -z

    def _qref(self, fint: np.ndarray, fext: np.ndarray) -> float:
        mags = np.linalg.norm(fext.reshape(-1, 3), axis=1)
        reac = np.linalg.norm((fint - fext).reshape(-1, 3)[self._cnodes], axis=1)
        vals = np.concatenate([mags[mags > 0.0], reac])
        return float(vals.mean()) if len(vals) else 0.0

    def _path(self, u, d):
        """Trial states u(s) along d; with ``rotation_aware`` the rigid part of d is a finite rotation."""
        free = self._free
        if not self.config.rotation_aware:
            def straight(s):
                t = u.copy()
                t[free] += s * d
                return t
            return straight
        nodes = self.problem.nodes
        dd = np.zeros_like(u)
        dd[free] = d
        dd = dd.reshape(-1, 3)
        x = nodes + u.reshape(-1, 3)
        c = x[self._cnodes].mean(axis=0)
        y = x - c
        mask = np.ones(len(x), bool)
        mask[self._cnodes] = False
        ym = y[mask]
        k = len(ym)
        a = np.zeros((k, 3, 6))
        # omega x y = -[y]x omega
        a[:, 0, 1], a[:, 0, 2] = ym[:, 2], -ym[:, 1]
        a[:, 1, 0], a[:, 1, 2] = -ym[:, 2], ym[:, 0]
        a[:, 2, 0], a[:, 2, 1] = ym[:, 1], -ym[:, 0]
        a[:, :, 3:] = np.eye(3)
        sol = np.linalg.lstsq(a.reshape(-1, 6), dd[mask].ravel(), rcond=None)[0]
        w, tr = sol[:3], sol[3:]
        rest = dd - (np.cross(w, y) + tr)
        theta = np.linalg.norm(w)
        cn = self._cnodes

        def curved(s):
            ang = s * theta
            if ang > 1e-12:
                kx = w / theta
                kk = np.array([[0, -kx[2], kx[1]], [kx[2], 0, -kx[0]], [-kx[1], kx[0], 0]])
                rot = np.eye(3) + np.sin(ang) * kk + (1 - np.cos(ang)) * (kk @ kk)
            else:
                rot = np.eye(3)
            xn = c + s * tr + y @ rot.T + s * rest
            t = (xn - nodes).ravel()
            t[self._cdofs] = u[self._cdofs]
            return t

        return curved

    def _line_search(self, u, d, pi0, r0, fext):
        free = self._free
        g0 = float(d @ r0)
        if not g0 < 0.0:
            return None
        r0_norm = np.linalg.norm(r0)
        path = self._path(u, d)
        s = 1.0
        for _ in range(10):
            trial = path(s)
            energy, fint, jmin = self.assembler.energy_and_force(trial.reshape(-1, 3))
            if jmin > 0.0:
                work = float(fext @ trial)
                pi = energy - work
                r = fint[free] - fext[free]
                if pi <= pi0 + 1e-4 * s * g0:  # Armijo
                    return s, trial, pi, fint, r
                # near equilibrium (or at tiny strains) energy changes drown in round-off:
                # there accept a step that lowers the residual norm
                if -g0 * s <= 1e-8 * (abs(energy) + abs(work)) and np.linalg.norm(r) < r0_norm:
                    return s, trial, pi, fint, r
                denom = 2.0 * (pi - pi0 - g0 * s)
                s_new = -g0 * s * s / denom if denom > 0 else 0.5 * s
                s = min(0.5 * s, max(0.1 * s, s_new))
            else:
                s *= 0.25
        return None

    # ---------------------------------------------------------------- iterations
    def _increment(self, u: np.ndarray, u_start: np.ndarray, lam: float, forces: np.ndarray, qhist: list) -> np.ndarray:
        cfg = self.config
        strategy = cfg.strategy
        refactor_ratio = cfg.refactor_ratio
        max_qn = cfg.max_quasi_newton
        free = self._free
        fext = lam * forces
        energy, fint, jmin = self.assembler.energy_and_force(u.reshape(-1, 3))
        if not jmin > 0.0:
            raise _Failed("the predictor inverts an element")
        pi = energy - float(fext @ u)
        r = fint[free] - fext[free]
        memory: list = []
        fresh = False
        need_factor = not self._factor_valid
        prev_c = None
        x_start = u_start[free]
        for _ in range(cfg.max_iterations):
            if need_factor:
                self._factorize(u)
                self._factor_valid = True
                memory.clear()
                fresh = True
            d = self._direction(r, memory)
            step = self._line_search(u, d, pi, r, fext)
            if step is None:
                if fresh:
                    raise _Failed("line search found no energy decrease along a fresh Newton direction")
                need_factor = True
                continue
            s, u_new, pi_new, fint, r_new = step
            self._stats["iterations"] += 1
            c = s * d
            y = r_new - r
            sy = float(c @ y)
            if strategy != "newton" and sy > 0.0:
                memory.append((c, y, 1.0 / sy))
            rnorm_old = np.linalg.norm(r)
            u, pi, r = u_new, pi_new, r_new
            fresh = False
            rmax = float(np.abs(r).max()) if len(r) else 0.0
            self._stats["history"].append(rmax)
            q = max(np.mean(qhist + [self._qref(fint, fext)]), 1e-300)
            cmax = float(np.abs(c).max())
            rho = cmax / prev_c if prev_c else 0.0
            est = cmax * max(1.0, rho / (1.0 - rho)) if rho < 0.95 else cmax
            dmax = float(np.abs(u[free] - x_start).max()) if len(r) else 0.0
            log.debug(
                "lam %.4g it: step %.3g |r|max %.3e (q %.3e) |c|max %.3e est %.3e du %.3e mem %d",
                lam, s, rmax, q, cmax, est, dmax, len(memory),
            )
            if rmax <= 1e-3 * cfg.force_tolerance * q or (
                rmax <= cfg.force_tolerance * q
                and (est <= cfg.displacement_tolerance * dmax or cmax <= 1e-12 * float(np.abs(u).max()))
            ):
                qhist.append(self._qref(fint, fext))
                return u
            prev_c = cmax
            ratio = np.linalg.norm(r) / max(rnorm_old, 1e-300)
            need_factor = strategy == "newton" or ratio > refactor_ratio or len(memory) >= max_qn
        raise _Failed(f"no convergence in {cfg.max_iterations} iterations")

    # --------------------------------------------------------------------- solve
    def solve(self, forces: np.ndarray, initial_guess: np.ndarray | None = None) -> SolveResult:
        """Solve for the equilibrium under dead nodal forces.

        Args:
            forces: (n, 3) float, N, on the mesh vertices (zero on constrained vertices).
                For P2 they act on the corner nodes, like CalculiX ``*CLOAD`` on them.
            initial_guess: optional (n, 3) float, mm, a guess of the vertex displacements
                at full load (e.g. from a reduced model or nearby samples); mid-edge nodes
                are interpolated. A good guess cuts the work several-fold.

        Returns:
            The converged :class:`SolveResult`.

        Raises:
            SolverSetupError: invalid forces or initial guess.
            ConvergenceError: the minimum increment or the increment budget was reached;
                ``load_fraction`` and ``result`` (partial) are attached.
        """
        t0 = time.perf_counter()
        cfg = self.config
        f = check_forces(self.problem, forces)
        n_dofs = self.assembler.n_dofs
        fext = np.zeros(n_dofs)
        fext[: 3 * self._n] = f.ravel()
        guess = None
        if initial_guess is not None:
            g = np.asarray(initial_guess, dtype=np.float64)
            if g.shape != (self._n, 3) or not np.all(np.isfinite(g)):
                raise SolverSetupError(f"initial_guess must be a finite ({self._n}, 3) array of mm, got shape {g.shape}")
            guess = self.nodal_field(g).ravel()
        self._stats = {"iterations": 0, "factorizations": 0, "solves": 0, "projected": 0, "history": []}
        self._factor_valid = False
        u_conv = np.zeros(n_dofs)
        lam, dlam = 0.0, float(cfg.initial_increment)
        prev = None  # (increment displacement, increment size) of the last converged increment
        increments = cutbacks = attempts = 0
        qhist: list = []
        while lam < 1.0:
            attempts += 1
            lam_new = min(1.0, lam + dlam)
            if 1.0 - lam_new < 1e-9:
                lam_new = 1.0
            u = self._predict(u_conv, lam, lam_new, prev, guess)
            try:
                if attempts > cfg.max_increments:
                    raise _Failed(f"the budget of {cfg.max_increments} increments is spent")
                it0 = self._stats["iterations"]
                u = self._increment(u, u_conv, lam_new, fext, qhist)
            except _Failed as exc:
                cutbacks += 1
                self._factor_valid = False
                dlam *= _CUT
                if dlam < cfg.min_increment or attempts > cfg.max_increments:
                    result = self._result(u_conv, lam, False, increments, cutbacks, t0, fext)
                    raise ConvergenceError(
                        f"the solver stopped at load fraction {lam:.4g} ({exc}); the forces may be too large "
                        "for the supports (elements invert or the body buckles) -- reduce them, fix more "
                        "vertices, or allow smaller increments (solver.min_increment)",
                        load_fraction=lam,
                        result=result,
                    ) from None
                log.debug("increment to %.4g failed (%s); cutting back to %.4g", lam_new, exc, dlam)
                continue
            increments += 1
            prev = (u - u_conv, lam_new - lam)
            u_conv, lam = u, lam_new
            if self._stats["iterations"] - it0 <= cfg.grow_iterations:
                dlam = min(1.0, dlam * _GROW)
        return self._result(u_conv, 1.0, True, increments, cutbacks, t0, fext)

    def _predict(self, u_conv, lam, lam_new, prev, guess) -> np.ndarray:
        candidates = []
        if guess is not None and lam == 0.0:
            candidates.append(lam_new * guess)
        if prev is not None:
            candidates.append(u_conv + (lam_new - lam) / prev[1] * prev[0])
        candidates.append(u_conv.copy())
        for u in candidates:
            u[self._cdofs] = lam_new * self._cdisp
            if len(candidates) == 1 or self.assembler.internal_force(u.reshape(-1, 3))[1] > 0.0:
                return u
        return u

    def _result(self, u, lam, converged, increments, cutbacks, t0, fext) -> SolveResult:
        nodal = u.reshape(-1, 3).copy()
        fint, _ = self.assembler.internal_force(nodal)
        reaction = np.zeros_like(nodal)
        reaction.ravel()[self._cdofs] = (fint - lam * fext)[self._cdofs]
        st = self._stats
        return SolveResult(
            displacement=nodal[: self._n].copy(),
            converged=converged,
            load_fraction=float(lam),
            increments=increments,
            iterations=st["iterations"],
            factorizations=st["factorizations"],
            residual_history=list(st["history"]),
            seconds=time.perf_counter() - t0,
            nodal_displacement=nodal,
            nodal_reaction=reaction,
            cutbacks=cutbacks,
            solves=st["solves"],
        )


def solve(problem: Problem, forces: np.ndarray, config: SolverConfig | None = None, initial_guess=None) -> SolveResult:
    """One-off solve: ``Solver(problem, config).solve(forces, initial_guess)``.

    Args:
        problem: the finite-element problem.
        forces: (n, 3) float, N, dead loads on the mesh vertices.
        config: solver settings (defaults if None).
        initial_guess: optional (n, 3) float, mm.
    """
    return Solver(problem, config).solve(forces, initial_guess=initial_guess)
