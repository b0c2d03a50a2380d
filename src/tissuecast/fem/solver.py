"""Nonlinear equilibrium by Newton iterations with automatic load incrementation.

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

The result of a solve depends only on the problem, the forces, the initial guess and the
configuration (no state is carried from one solve to the next), so data sets are
reproducible bit for bit. :meth:`Solver.solve_batch` solves several force fields in
lockstep and gathers their preconditioner solves with the shared reference factorisation
into multi-right-hand-side solves; each sample's numbers then differ from its single solve
by round-off and depend only on the batch.

Design, measurements and the history of what was tried: ``docs/solver.md``.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from ..config import SolverConfig
from ..errors import ConvergenceError, SolverSetupError
from .assembly import Assembler
from .linear import NotPositiveDefinite, make_linear_solver
from .linesearch import line_search, step_path
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
        self._tau = 0.0
        self._reference = None  # linear solver holding the factorised stiffness at u = 0 (on first use)
        self._active = self.linear  # the factorisation the preconditioner uses now
        self._recycled = None  # krylov: (n_free, k) directions of this solve's earlier iterations
        self._twins: list = []  # solve_batch: copies sharing the assembler and the reference factorisation

    # ------------------------------------------------------------------ helpers
    def nodal_field(self, vertex_values: np.ndarray) -> np.ndarray:
        """Extend a vertex field (n, 3) to all element nodes (n_nodes, 3) by linear interpolation."""
        v = np.asarray(vertex_values, dtype=np.float64)
        if self.problem.order == 1:
            return v.copy()
        e = self.problem.mesh.edges
        return np.vstack([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])

    def _factorize(self, u: np.ndarray, data: np.ndarray | None = None) -> None:
        """Factorise the tangent K at u; if it is not positive definite, K + tau diag(K).

        The shift starts at half the last one that worked in this solve (at least 1e-3)
        and grows 4x per failed attempt; past tau = 10 the projected stiffness (material
        tangent clamped to its positive-definite part at each quadrature point) is used.
        """
        if data is None:
            _, data, _ = self.assembler.tangent(u.reshape(-1, 3))
        self._active = self.linear
        self._stats["factorizations"] += 1
        try:
            self.linear.factorize(data)
            self._tau = 0.0
            return
        except NotPositiveDefinite:
            log.debug("tangent not positive definite")
        idx = self.assembler.diagonal_index
        diag = data[idx]
        tau = max(0.5 * self._tau, 1e-3)
        while tau <= 10.0:
            shifted = data.copy()
            shifted[idx] += tau * diag
            self._stats["factorizations"] += 1
            try:
                self.linear.factorize(shifted)
                self._tau = tau
                self._stats["shifted"] += 1
                return
            except NotPositiveDefinite:
                tau *= 4.0
        _, data, _ = self.assembler.tangent(u.reshape(-1, 3), project=True)
        self._stats["factorizations"] += 1
        try:
            self.linear.factorize(data)
            self._stats["projected"] += 1
            return
        except NotPositiveDefinite:
            raise _Failed("projected tangent stiffness could not be factorised") from None

    def _rotated_solve(self, v: np.ndarray):
        """K^-1 v with the last factorised tangent K, co-rotated by the rigid rotation R
        applied since it was factorised: R K^-1 R^T v (node by node).

        A generator (``yield from``): it yields ``(factorisation, R^T v)`` and receives
        ``K^-1 R^T v`` from whoever drives the solve, so that :meth:`solve_batch` can
        gather the triangular solves of several samples into one multi-right-hand-side
        solve.
        """
        rot = self._rotation
        z = yield self._active, (v.reshape(-1, 3) @ rot).ravel()
        self._stats["solves"] += 1
        return (z.reshape(-1, 3) @ rot.T).ravel()

    def _krylov(self, u: np.ndarray, r: np.ndarray):
        """-K^-1 r for the tangent K at u by preconditioned conjugate gradients.

        The preconditioner is the last factorisation, co-rotated (:meth:`_rotated_solve`).
        With ``krylov_recycle`` the search directions of the solve's earlier Newton
        iterations span a deflation subspace ``W`` (deflated CG; Saad, Yeung, Erhel and
        Guyomarc'h 2000): the iteration starts from the Galerkin solution in ``W`` with the
        *new* tangent and keeps its search directions K-conjugate to ``W``, so the modes
        the reused factorisation resolves badly (the soft swing of the body about its
        pins, mostly) are solved once and not again in every Newton iteration.
        Returns ``(d, None)`` when the relative residual fell below ``krylov_tolerance``
        within ``krylov_iterations`` steps (or negative curvature was met after some
        progress: the iterate so far is still a descent direction), else ``(None, K data)``
        so that the caller factorises the tangent already assembled.
        """
        cfg = self.config
        _, data, _ = self.assembler.tangent(u.reshape(-1, 3))
        k = self.assembler.matrix(data)
        b = -r
        target = cfg.krylov_tolerance * np.linalg.norm(b)
        space = self._deflation(u, k)
        if space is None:
            x, res, project = np.zeros_like(b), b.copy(), None
        else:
            w, aw, chol = space
            y = cho_solve(chol, w.T @ b)
            x, res = w @ y, b - aw @ y  # Galerkin start in W; K W is already known

            def project(z):  # z minus its K-orthogonal projection on W
                return z - w @ cho_solve(chol, aw.T @ z)

        found: list[np.ndarray] = []  # this solve's search directions, scaled to unit K-norm
        result = None
        if np.linalg.norm(res) <= target:
            result = (x, None)
        else:
            z = yield from self._rotated_solve(res)
            p = z if project is None else project(z)
            rz = float(res @ z)
            for step in range(cfg.krylov_iterations):
                kp = k @ p
                curvature = float(p @ kp)
                if not curvature > 0.0:  # indefinite tangent along p
                    self._stats["krylov"] += step
                    result = (x, None) if step or space is not None else (None, data)
                    break
                found.append(p / np.sqrt(curvature))
                a = rz / curvature
                x += a * p
                res -= a * kp
                if np.linalg.norm(res) <= target:
                    self._stats["krylov"] += step + 1
                    result = (x, None)
                    break
                z = yield from self._rotated_solve(res)
                rz_new = float(res @ z)
                p = (z if project is None else project(z)) + (rz_new / rz) * p
                rz = rz_new
            else:
                self._stats["krylov"] += cfg.krylov_iterations
                result = (None, data)
        self._recycle(found, space)
        return result

    def _deflation(self, u: np.ndarray, k):
        """``(W, K W, cho_factor(W^T K W))`` for the deflation subspace, or None.

        ``W`` holds the infinitesimal rigid rotations about the constrained nodes' centroid
        at the current configuration (the swing of a body held by a few pins is its softest
        motion) and the recycled directions. When ``K`` is not positive definite on ``W``
        the recycled directions are dropped and the rotations alone tried, then nothing.
        """
        if self.config.krylov_recycle == 0:
            return None
        x = self.problem.nodes + u.reshape(-1, 3)
        x = x - x[self._cnodes].mean(axis=0)
        spin = np.stack([np.cross(axis, x).ravel()[self._free] for axis in np.eye(3)], axis=1)
        spin = np.linalg.qr(spin)[0]
        for w in ((spin,) if self._recycled is None else (np.column_stack([spin, self._recycled]), spin)):
            if w.shape[1] >= len(self._free):  # a tiny problem: CG alone is as good
                continue
            aw = k @ w
            e = w.T @ aw
            try:
                return w, aw, cho_factor(0.5 * (e + e.T), lower=True)
            except np.linalg.LinAlgError:
                self._recycled = None
        return None

    def _recycle(self, found: list, space) -> None:
        """Keep the newest ``krylov_recycle`` directions: this solve's (K-orthonormal, and
        K-orthogonal to ``W``) and those of ``W`` beyond the rotations, made K-orthonormal
        and K-orthogonal to the rotations (``W L^-T``, ``W^T K W = L L^T``, lower ``L``)."""
        cap = self.config.krylov_recycle
        cols = found[::-1][:cap]
        if space is not None and len(cols) < cap:
            w, _, (lower, _) = space
            old = solve_triangular(lower, w.T, lower=True).T[:, 3:]
            cols += list(old.T[: cap - len(cols)])
        if cols:
            self._recycled = np.column_stack(cols)

    def _qref(self, fint: np.ndarray, fext: np.ndarray) -> float:
        mags = np.linalg.norm(fext.reshape(-1, 3), axis=1)
        reac = np.linalg.norm((fint - fext).reshape(-1, 3)[self._cnodes], axis=1)
        vals = np.concatenate([mags[mags > 0.0], reac])
        return float(vals.mean()) if len(vals) else 0.0

    def _line_search(self, u, d, pi0, r0, fext):
        path = step_path(self.problem.nodes, u, d, self._free, self._cnodes, self._cdofs, self.config.rotation_aware)
        return line_search(self.assembler, path, self._free, d, pi0, r0, fext)

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
        q0 = self._qref(fint, fext)
        if len(r) == 0 or float(np.abs(r).max()) <= 1e-3 * cfg.force_tolerance * q0:
            qhist.append(q0)
            return u  # already in equilibrium (e.g. no load at all)
        fresh = False
        need_factor = strategy == "newton" or not self._factor_valid
        prev_c = None
        reuses = 0
        x_start = u_start[free]
        for _ in range(cfg.max_iterations):
            d = data = None
            if strategy == "krylov" and not need_factor:
                d, data = yield from self._krylov(u, r)
                need_factor = d is None
            if need_factor:
                self._factorize(u, data)
                self._factor_valid = True
                self._rotation = np.eye(3)
                fresh = True
                reuses = 0
            if d is None:
                d = -(yield from self._rotated_solve(r))
            step = self._line_search(u, d, pi, r, fext)
            if step is None:
                if fresh:
                    raise _Failed("line search found no energy decrease along a fresh Newton direction")
                need_factor = True
                continue
            s, u_new, pi_new, fint, r_new, rot = step
            self._rotation = rot @ self._rotation
            self._stats["iterations"] += 1
            c = s * d
            rnorm_old = np.linalg.norm(r)
            u, pi, r = u_new, pi_new, r_new
            rmax = float(np.abs(r).max()) if len(r) else 0.0
            self._stats["history"].append(rmax)
            q = max(np.mean(qhist + [self._qref(fint, fext)]), 1e-300)
            cmax = float(np.abs(c).max())
            rho = cmax / prev_c if prev_c else 0.0
            est = cmax * max(1.0, rho / (1.0 - rho)) if rho < 0.95 else cmax
            dmax = float(np.abs(u[free] - x_start).max()) if len(r) else 0.0
            log.debug(
                "lam %.4g it: step %.3g |r|max %.3e (q %.3e) |c|max %.3e est %.3e du %.3e reuse %d",
                lam, s, rmax, q, cmax, est, dmax, reuses,
            )
            if rmax <= 1e-3 * cfg.force_tolerance * q or (
                rmax <= cfg.force_tolerance * q
                and (est <= cfg.displacement_tolerance * dmax or cmax <= 1e-12 * float(np.abs(u).max()))
            ):
                qhist.append(self._qref(fint, fext))
                return u
            prev_c = cmax
            ratio = np.linalg.norm(r) / max(rnorm_old, 1e-300)
            reuses += 0 if fresh else 1
            fresh = False
            need_factor = strategy == "newton" or (
                strategy == "quasi-newton" and (ratio > refactor_ratio or reuses >= max_qn))
        raise _Failed(f"no convergence in {cfg.max_iterations} iterations")

    # --------------------------------------------------------------------- solve
    def solve(self, forces: np.ndarray, initial_guess: np.ndarray | None = None) -> SolveResult:
        """Solve for the equilibrium under dead nodal forces.

        Args:
            forces: (n, 3) float, N, on the mesh vertices (zero on constrained vertices).
                For P2 they act on the corner nodes, like CalculiX ``*CLOAD`` on them.
            initial_guess: optional guess of the displacements at full load, mm: (n, 3) at
                the vertices (mid-edge nodes are then interpolated linearly) or (n_nodes, 3)
                at every element node (e.g. ``nodal_displacement`` of earlier samples, which
                is better for P2). A good guess cuts the work several-fold. With a guess
                the first increment is the full load (``initial_increment`` applies to
                cold starts only).

        Returns:
            The converged :class:`SolveResult`.

        Raises:
            SolverSetupError: invalid forces or initial guess.
            ConvergenceError: the minimum increment or the increment budget was reached;
                ``load_fraction`` and ``result`` (partial) are attached.
        """
        return _drive(self._steps(forces, initial_guess))

    def solve_batch(self, forces, initial_guesses=None) -> list:
        """Solve several force fields together, their triangular solves gathered.

        The samples are solved in lockstep: each round advances every unfinished sample to
        its next preconditioner application, and the applications that use the same
        factorisation (with ``reference_preconditioner``: the stiffness at zero, shared by
        all samples until one factorises its own tangent) are done as one
        multi-right-hand-side solve (a supernodal triangular solve is bound by reading the
        factor from memory, so k right-hand sides cost far less than k solves).
        Everything else (tangents, line searches, convergence tests) is per sample and
        exactly as in :meth:`solve`. Each sample beyond the first is solved by a copy of
        this solver (kept for later batches) that shares its assembler and reference
        factorisation; a copy that must factorise its own tangent holds that factor too.

        Each sample converges to the same tolerances as with :meth:`solve`; the numbers
        differ from its single solve by round-off (a column of a multi-right-hand-side solve
        is not bitwise the single solve), and depend only on the batch (the same batch gives
        the same bits).

        Args:
            forces: sequence of (n, 3) float arrays, N, as for :meth:`solve`.
            initial_guesses: None, or a sequence of the same length whose entries are None or
                guesses as for :meth:`solve`.

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
        for f in forces:
            check_forces(self.problem, f)
        # checked and extended to every element node once; _steps only checks them again
        guesses = [None if g is None else self._nodal_guess(g).reshape(-1, 3) for g in guesses]
        t0 = time.perf_counter()
        cfg = self.config
        if cfg.strategy == "krylov" and cfg.reference_preconditioner and any(g is not None for g in guesses):
            self._reference_factor()  # built once here, so that every sample shares it
        while len(self._twins) < len(forces) - 1:
            twin = copy.copy(self)
            twin.linear = twin._active = make_linear_solver(cfg.linear_solver, self.assembler)
            twin._twins = []
            self._twins.append(twin)
        solvers = [self] + self._twins[: len(forces) - 1]
        steps = [s._steps(f, g) for s, f, g in zip(solvers, forces, guesses)]
        out: list = [None] * len(forces)
        reply: list = [None] * len(forces)
        active = list(range(len(forces)))
        while active:
            groups: dict = {}  # factorisation -> [(sample, vector)], samples in order
            for i in active:
                try:
                    factor, v = steps[i].send(reply[i])
                except StopIteration as stop:
                    out[i] = stop.value
                    continue
                except ConvergenceError as exc:
                    out[i] = exc
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
        share = (time.perf_counter() - t0) / max(len(forces), 1)
        for i, r in enumerate(out):
            if isinstance(r, SolveResult):
                out[i] = dataclasses.replace(r, seconds=share)
        return out

    def _steps(self, forces, initial_guess):
        """The body of :meth:`solve` as a generator of preconditioner applications
        (see :meth:`_rotated_solve`); returns the :class:`SolveResult`."""
        t0 = time.perf_counter()
        cfg = self.config
        f = check_forces(self.problem, forces)
        n_dofs = self.assembler.n_dofs
        fext = np.zeros(n_dofs)
        fext[: 3 * self._n] = f.ravel()
        guess = self._nodal_guess(initial_guess)
        self._stats = {"iterations": 0, "factorizations": 0, "solves": 0, "shifted": 0, "projected": 0, "krylov": 0,
                       "history": []}
        self._tau = 0.0
        self._factor_valid = False
        self._active = self.linear
        self._recycled = None
        if (guess is not None and cfg.strategy == "krylov" and cfg.reference_preconditioner
                and self._reference_factor() is not None):
            self._active = self._reference
            self._factor_valid = True
            self._rotation = _best_rotation(self.problem.nodes, guess)
        u_conv = np.zeros(n_dofs)
        lam, dlam = 0.0, (1.0 if guess is not None else float(cfg.initial_increment))
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
                u = yield from self._increment(u, u_conv, lam_new, fext, qhist)
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

    def _nodal_guess(self, initial_guess) -> np.ndarray | None:
        """The checked initial guess at every element node, flattened (None stays None)."""
        if initial_guess is None:
            return None
        g = np.asarray(initial_guess, dtype=np.float64)
        n_nodes = len(self.problem.nodes)
        if g.shape not in ((self._n, 3), (n_nodes, 3)) or not np.all(np.isfinite(g)):
            raise SolverSetupError(
                f"initial_guess must be a finite ({self._n}, 3) array of vertex displacements in mm "
                f"(or ({n_nodes}, 3) at every element node), got shape {g.shape}"
            )
        return (g if len(g) == n_nodes else self.nodal_field(g)).ravel().copy()

    def _reference_factor(self):
        """The linear solver holding the factorised stiffness at zero displacement (built once;
        None if it is not positive definite, e.g. rigid-body motion left free)."""
        if self._reference is None:
            ref = make_linear_solver(self.config.linear_solver, self.assembler)
            _, data, _ = self.assembler.tangent(np.zeros((len(self.problem.nodes), 3)))
            try:
                ref.factorize(data)
            except NotPositiveDefinite:
                ref = False
            self._reference = ref
        return self._reference or None

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


def _drive(steps):
    """Run a generator of preconditioner applications (:meth:`Solver._rotated_solve`) with
    one solve each; returns the generator's return value."""
    reply = None
    try:
        while True:
            factor, v = steps.send(reply)
            reply = factor.solve(v)
    except StopIteration as stop:
        return stop.value


def _best_rotation(nodes: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The rotation R that best maps the reference nodes onto the displaced ones (Kabsch):
    ``x + u - c' ~= R (x - c)`` in least squares over all nodes."""
    x = nodes - nodes.mean(axis=0)
    y = nodes + u.reshape(-1, 3)
    y = y - y.mean(axis=0)
    a, _, bt = np.linalg.svd(y.T @ x)
    d = np.sign(np.linalg.det(a @ bt)) or 1.0
    return a @ np.diag([1.0, 1.0, d]) @ bt


def solve(problem: Problem, forces: np.ndarray, config: SolverConfig | None = None, initial_guess=None) -> SolveResult:
    """One-off solve: ``Solver(problem, config).solve(forces, initial_guess)``.

    Args:
        problem: the finite-element problem.
        forces: (n, 3) float, N, dead loads on the mesh vertices.
        config: solver settings (defaults if None).
        initial_guess: optional (n, 3) float, mm.
    """
    return Solver(problem, config).solve(forces, initial_guess=initial_guess)
