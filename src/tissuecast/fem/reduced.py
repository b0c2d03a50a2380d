"""A reduced-order model of the nonlinear problem, used to predict a full solve's answer.

A data set solves thousands of problems that differ only in their forces, and their
solutions live near a low-dimensional subspace. :class:`ReducedModel` exploits that to give
the full Newton solver an initial guess close to the answer, which turns a cold solve (load
increments, globalisation, several factorisations) into a few Newton iterations, usually
without a factorisation of its own. The guess is only a guess: every sample is still
converged by the full solver to its usual tolerances, so a data set's displacements are full
finite-element solutions either way.

Construction (:meth:`ReducedModel.fit`), from full solutions ("snapshots") of the same
problem:

1. Basis ``V`` (n_free, r): left singular vectors of the snapshot matrix (free dofs, every
   element node), the modes with singular value above ``MODE_CUTOFF`` of the largest.
2. Hyper-reduction by energy-conserving sampling and weighting (ECSW; Farhat, Avery, Chapman
   and Cortial 2014): non-negative element weights ``xi`` with few non-zeros such that
   ``sum_e xi_e V_e^T f_e(u) ~= V^T f_int(u)`` on the (projected) snapshots and on half of
   them, to a relative error ``tolerance``, plus the total volume. Solved by a
   non-negative least-squares active-set method that stops at the tolerance.

Solve (:meth:`ReducedModel.predict`): Galerkin projection ``u = V q`` with the internal
forces and energy evaluated on the sampled elements only (weighted), minimising the reduced
energy in ``r`` unknowns by BFGS from the reduced linear-elastic answer (inverse reduced
stiffness at zero as the first inverse Hessian, Armijo line search): one energy-and-forces
pass on the sampled elements per iteration, no tangent. If that fails, Newton with the
reduced tangent, an Armijo line search and load increments with cut-backs. Returns the nodal displacement
field, or None when the reduced problem does not converge (the caller then solves from zero,
as without a predictor).

Linear springs to ground (an elastic support) are exact in the reduced model: their reduced
stiffness ``V^T K_s V`` is a constant (r, r) matrix added to the sampled elements' energy,
forces and tangent; :meth:`ReducedModel.with_springs` swaps it for a sample's own springs.
Per-element materials are those of the sampled elements. Per-solve
prescribed displacements (an indentation) are not part of the model: it predicts the response
to loads and springs, so a data set's guess pulls the prescribed vertices to their values with
stiff springs (:meth:`tissuecast.scenario.SampleInputs.reduced_guess`), and the full solver
imposes them exactly (its lift, :mod:`.newton`).

Galerkin solutions are only roughly right (a linear subspace represents the swing of the body
about its pins only roughly) but well inside Newton's quadratic basin. Measurements and the
history of the predictor: ``docs/solver.md``.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..errors import SolverSetupError
from .assembly import Assembler
from .problem import Problem, check_forces
from .springs import NodalSprings

__all__ = ["ReducedModel", "ecsw_weights"]

log = logging.getLogger(__name__)

#: Basis modes keep singular values above this share of the largest (the rest is round-off).
MODE_CUTOFF = 1e-6
#: Load scales of the snapshots on which the ECSW weights are fitted (the states and half of
#: them, so that the weights also hold on the way to the answer).
ECSW_SCALES = (1.0, 0.5)
#: Tikhonov term of the NNLS Gram matrix, relative to its mean diagonal (near-duplicate columns).
_GRAM_REGULARISATION = 1e-14
#: NNLS weights below this share of the largest are dropped from the active set.
_WEIGHT_DROP = 1e-12
#: Armijo's sufficient-decrease constant of both reduced line searches.
ARMIJO = 1e-4
#: Smallest line-search step of the BFGS / Newton iterations before they give up.
BFGS_MIN_STEP = 1e-6
NEWTON_MIN_STEP = 1e-4
#: BFGS may take this many times the Newton iteration budget (its iterations are far cheaper).
BFGS_ITERATION_FACTOR = 5
#: BFGS skips an update whose curvature ``s . y`` is below this share of ``|s| |y|``.
BFGS_CURVATURE = 1e-12
#: An indefinite reduced tangent is replaced by its |eigenvalues|, floored at this share of the
#: largest (a descent direction of bounded length).
EIGENVALUE_FLOOR = 1e-8
#: Reduced Newton load stepping: growth after a converged increment, cut after a failed one,
#: and the smallest increment before the prediction gives up.
INCREMENT_GROWTH = 1.5
CUTBACK = 0.25
MIN_INCREMENT = 1.0 / 64.0
_TINY = 1e-300  # guards divisions by norms that may be zero


def ecsw_weights(g: np.ndarray, b: np.ndarray, tolerance: float, max_elements: int | None = None) -> np.ndarray:
    """Sparse non-negative ``x`` with ``||g x - b|| <= tolerance ||b||`` (Lawson-Hanson, stopped early).

    Args:
        g: (rows, n) float, one column per element.
        b: (rows,) float target (usually ``g @ 1``).
        tolerance: relative residual at which to stop adding elements.
        max_elements: most non-zeros (default: all columns).

    Returns:
        (n,) float, >= 0.
    """
    rows, n = g.shape
    max_elements = n if max_elements is None else int(max_elements)
    x = np.zeros(n)
    gt = np.ascontiguousarray(g.T)  # (n, rows): a column of g is a contiguous row here
    gtb = gt @ b
    bnorm = float(np.linalg.norm(b))
    cols: list[int] = []  # active columns, in the order of the Gram matrix below
    gram = np.zeros((0, 0))
    cross = np.zeros((min(n, 64), n))  # rows: (g^T g[:, c])^T for c in cols, in order (grown by doubling)
    active = np.zeros(n, dtype=bool)

    def add(j):
        nonlocal gram, cross
        cj = gt @ gt[j]
        k = len(cols)
        new = np.empty((k + 1, k + 1))
        new[:k, :k] = gram
        new[:k, k] = new[k, :k] = cj[cols]
        new[k, k] = cj[j]
        if k == cross.shape[0]:
            cross = np.concatenate([cross, np.zeros((min(k, n - k), n))])
        gram = new
        cross[k] = cj
        cols.append(j)
        active[j] = True

    def drop(keep):
        nonlocal gram, cols
        for j in np.asarray(cols)[~keep]:
            active[j] = False
            x[j] = 0.0
        k = len(cols)
        gram = gram[np.ix_(keep, keep)]
        cross[:int(keep.sum())] = cross[:k][keep]
        cols = [c for c, kept in zip(cols, keep) if kept]

    res_norm = bnorm
    while res_norm > tolerance * bnorm and len(cols) < max_elements:
        w = gtb - x[cols] @ cross[:len(cols)]  # g^T (b - g x)
        w[active] = -np.inf
        j = int(np.argmax(w))
        if not w[j] > 0.0:
            break
        add(j)
        for _ in range(4 * n):  # inner loop: keep the least-squares solution feasible
            z = np.linalg.solve(gram + _GRAM_REGULARISATION * np.trace(gram) / len(cols) * np.eye(len(cols)), gtb[cols])
            if np.all(z > 0.0):
                x[cols] = z
                break
            xa = x[cols]
            neg = z <= 0.0
            step = np.min(xa[neg] / np.maximum(xa[neg] - z[neg], _TINY))
            xa = xa + step * (z - xa)
            x[cols] = xa
            drop(xa > _WEIGHT_DROP * max(float(xa.max()), _TINY))
        xc = x[cols]
        res_norm = float(np.sqrt(max(bnorm**2 - 2.0 * xc @ gtb[cols] + xc @ gram @ xc, 0.0)))
    return x


@dataclass
class _Sub:
    """The sampled elements as a small mesh of their own (weights folded into the quadrature)."""

    assembler: Assembler
    basis: np.ndarray  # (n_sub_free, r) rows of V at the sub-mesh's free dofs
    springs: np.ndarray  # (r, r) reduced stiffness V^T K_s V of the springs, N/mm (zero without)


def _free_position(free_mask: np.ndarray) -> np.ndarray:
    """(3 n_nodes,) int: each dof's row in the free-dof vector (and of the basis), -1 if constrained."""
    pos = np.full(len(free_mask), -1, dtype=np.int64)
    pos[free_mask] = np.arange(int(free_mask.sum()))
    return pos


class ReducedModel:
    """Galerkin reduced-order model with ECSW hyper-reduction (a predictor for :class:`Solver`).

    Args:
        problem: the full problem (no prescribed non-zero displacements; springs and
            per-element materials are taken into account).
        basis: (n_free, r) float, orthonormal columns over the problem's free dofs (the order
            of ``Assembler(...).free_dofs``: node-major, x/y/z).
        elements: (k,) int, 0-based ids of the sampled elements.
        weights: (k,) float > 0, their ECSW weights.
    """

    def __init__(self, problem: Problem, basis: np.ndarray, elements: np.ndarray, weights: np.ndarray) -> None:
        if np.any(problem.constrained_nodes[1] != 0.0):
            raise SolverSetupError("the reduced model supports fixed (zero) displacements only, not prescribed ones")
        self.problem = problem
        free_mask = problem.free_mask
        self.free_dofs = np.flatnonzero(free_mask)
        self.basis = np.ascontiguousarray(basis, dtype=np.float64)
        self.elements = np.asarray(elements, dtype=np.int64)
        self.weights = np.asarray(weights, dtype=np.float64)
        if self.basis.ndim != 2 or self.basis.shape[0] != len(self.free_dofs):
            raise SolverSetupError(f"basis must be ({len(self.free_dofs)}, r), got {self.basis.shape}")
        if self.elements.shape != self.weights.shape or len(self.elements) == 0:
            raise SolverSetupError("elements and weights must be equally long and not empty")
        conn = problem.connectivity[self.elements]
        sub_nodes, local = np.unique(conn, return_inverse=True)
        local = local.reshape(conn.shape)
        sub_free = free_mask.reshape(-1, 3)[sub_nodes].ravel()
        material = problem.materials.subset(self.elements) if problem.materials is not None else problem.material
        asm = Assembler(problem.nodes[sub_nodes], local, problem.order, material, sub_free)
        asm.geometry = dataclasses.replace(asm.geometry, weight=asm.geometry.weight * self.weights[:, None])
        full_dofs = (3 * sub_nodes[:, None] + np.arange(3)).ravel()[sub_free]
        ks = np.zeros((self.n_modes, self.n_modes))
        if problem.springs is not None and len(problem.springs):
            ks = self.basis.T @ (problem.springs.matrix(free_mask) @ self.basis)
        self._sub = _Sub(asm, self.basis[_free_position(free_mask)[full_dofs]], 0.5 * (ks + ks.T))
        self._n = problem.n_vertices
        self.fit_error: float | None = None  # ECSW force error of fit(), if fitted here
        self.last_iterations, self.last_seconds = 0, 0.0  # of the last predict()
        self._h0 = None  # reduced stiffness at zero displacement (the linear start), on first use
        self._h0_elastic = None  # its sampled elements' part

    @property
    def n_modes(self) -> int:
        return self.basis.shape[1]

    def with_springs(self, springs: NodalSprings | None) -> "ReducedModel":
        """This model with other springs to ground in place of the problem's: a sample's own
        stiffnesses, or more nodes held by stiff springs. The basis, the sampled elements and
        their reduced stiffness are shared; only the springs' ``V^T K_s V`` is new.

        Args:
            springs: the springs of the view (node ids of the problem's element nodes), or
                None for none.
        """
        ks = np.zeros((self.n_modes, self.n_modes))
        if springs is not None and len(springs):
            ks = self.basis.T @ (springs.matrix(self.problem.free_mask) @ self.basis)
            ks = 0.5 * (ks + ks.T)
        h0 = self._elastic_h0()
        out = copy.copy(self)
        out._sub = dataclasses.replace(self._sub, springs=ks)
        out._h0 = h0 + ks
        return out

    # ------------------------------------------------------------------ building
    @classmethod
    def fit(cls, problem: Problem, snapshots: np.ndarray, tolerance: float = 0.01,
            max_modes: int | None = None) -> "ReducedModel":
        """Build the model from full solutions of ``problem``.

        Args:
            problem: the full problem.
            snapshots: (s, n_nodes, 3) float, mm, nodal displacements at every element node
                (``SolveResult.nodal_displacement``).
            tolerance: ECSW relative error of the reduced internal forces.
            max_modes: most basis vectors (default: every significant one).
        """
        snaps = np.asarray(snapshots, dtype=np.float64)
        n_nodes = len(problem.nodes)
        if snaps.ndim != 3 or snaps.shape[1:] != (n_nodes, 3) or len(snaps) == 0 or not np.all(np.isfinite(snaps)):
            raise SolverSetupError(f"snapshots must be a finite (s, {n_nodes}, 3) array of nodal displacements, "
                                   f"got shape {snaps.shape}")
        free = np.flatnonzero(problem.free_mask)
        x = snaps.reshape(len(snaps), -1)[:, free].T
        u, s, _ = np.linalg.svd(x, full_matrices=False)
        keep = int(np.sum(s > MODE_CUTOFF * s[0])) if s[0] > 0 else 0
        if max_modes is not None:
            keep = min(keep, int(max_modes))
        if keep == 0:
            raise SolverSetupError("the snapshots are all zero: no basis to build")
        basis = u[:, :keep]
        asm = Assembler(problem.nodes, problem.connectivity, problem.order, problem.element_material,
                        problem.free_mask)
        m, nn = problem.connectivity.shape
        erows = _free_position(problem.free_mask)[asm.element_dofs]  # (m, 3nn), -1 at constrained dofs
        vfull = np.vstack([basis, np.zeros((1, keep))])  # row -1 -> zeros
        ve = vfull[erows]  # (m, 3nn, r)
        blocks = []
        for scale in ECSW_SCALES:
            for snap in x.T:
                q = basis.T @ (scale * snap)
                uu = np.zeros(asm.n_dofs)
                uu[free] = basis @ q
                fe = asm.element_forces(uu.reshape(-1, 3)).reshape(m, 3 * nn)
                c = np.einsum("mar,ma->rm", ve, fe)  # (r, m): element contributions to V^T f
                scale_c = np.linalg.norm(c.sum(axis=1))
                if scale_c > 0:
                    blocks.append(c / scale_c)
        vol = asm.geometry.weight.sum(axis=1)
        blocks.append((vol / vol.sum() * np.sqrt(keep))[None, :])
        # g (rows, m) stored column-major: ecsw_weights reads its columns as contiguous rows of
        # g.T without a copy (g is rows x elements float64: one copy fewer counts on large meshes)
        g = np.empty((sum(len(b) for b in blocks), m), order="F")
        np.concatenate(blocks, out=g)
        del blocks
        w = ecsw_weights(g, g.sum(axis=1), tolerance)
        elements = np.flatnonzero(w > 0.0)
        err = float(np.linalg.norm(g @ w - g.sum(axis=1)) / np.linalg.norm(g.sum(axis=1)))
        log.info("reduced model: %d modes, %d of %d elements (ECSW error %.3g)", keep, len(elements), m, err)
        model = cls(problem, basis, elements, w[elements])
        model.fit_error = err
        return model

    # -------------------------------------------------------------------- solve
    def _state(self, q: np.ndarray) -> np.ndarray:
        sub = self._sub
        u = np.zeros(sub.assembler.n_dofs)
        u[sub.assembler.free_dofs] = sub.basis @ q
        return u.reshape(-1, 3)

    def _energy(self, q: np.ndarray, fr: np.ndarray) -> float:
        return self._sub.assembler.energy(self._state(q)) + 0.5 * float(q @ self._sub.springs @ q) - float(fr @ q)

    def predict(self, forces: np.ndarray, max_iterations: int = 40, tolerance: float = 1e-2,
                first_increment: float = 1.0, method: str = "bfgs",
                bfgs_tolerance: float = 3e-4) -> np.ndarray | None:
        """Reduced equilibrium under ``forces``: (n_nodes, 3) nodal displacements, mm, or None.

        Args:
            forces: (n, 3) float, N, dead loads on the vertices, or (n_nodes, 3) on every
                element node (as for :meth:`Solver.solve`).
            max_iterations: reduced Newton iterations per load increment (``5 x`` that for
                the quasi-Newton iterations of ``method="bfgs"``).
            tolerance: Newton: stop when the reduced residual is below ``tolerance`` times the
                reduced load, or the last correction below ``tolerance`` times the solution.
            first_increment: Newton: load fraction of the first increment (cut by 4 on failure).
            method: ``"bfgs"`` (default): quasi-Newton on the reduced energy from the reduced
                linear-elastic answer, with the inverse reduced stiffness at zero displacement
                as the first inverse Hessian and BFGS updates, so that each iteration costs
                one energy-and-forces evaluation on the sampled elements and no tangent; it
                falls back to Newton (below) if its line search fails. ``"newton"``: reduced
                Newton with load increments.
            bfgs_tolerance: BFGS: the same stopping tests with this factor.

        Newton's first increment starts from the reduced linear-elastic answer (from zero if
        that inverts a sampled element).
        """
        t0 = time.perf_counter()
        if method not in ("bfgs", "newton"):
            raise SolverSetupError(f"method must be 'bfgs' or 'newton', got {method!r}")
        fr = self._reduced_forces(forces)
        q_lin = self._linear_answer(fr)
        if method == "bfgs":
            found = self._bfgs(q_lin, fr, bfgs_tolerance, BFGS_ITERATION_FACTOR * max_iterations)
            if found is not None:
                return self._done(*found, t0)
            log.debug("reduced model: quasi-Newton line search failed; reduced Newton instead")
        found = self._newton(q_lin, fr, max_iterations, tolerance, first_increment)
        return None if found is None else self._done(*found, t0)

    def _reduced_forces(self, forces: np.ndarray) -> np.ndarray:
        """(r,) reduced external forces ``V^T f`` of checked vertex (n, 3) or element-node
        (n_nodes, 3) forces, N."""
        f = check_forces(self.problem, forces)
        fext = np.zeros(3 * len(self.problem.nodes))
        fext[: f.size] = f.ravel()
        return self.basis.T @ fext[self.free_dofs]

    def _linear_answer(self, fr: np.ndarray) -> np.ndarray:
        """(r,) reduced linear-elastic answer ``H0^-1 fr`` (zero if ``H0`` is singular); the
        reduced stiffness at zero displacement ``H0`` is built on first use."""
        sub = self._sub
        if self._h0 is None:
            self._h0 = self._elastic_h0() + sub.springs
        try:
            return np.linalg.solve(self._h0, fr)
        except np.linalg.LinAlgError:
            return np.zeros(self.n_modes)

    def _elastic_h0(self) -> np.ndarray:
        """(r, r) reduced stiffness of the sampled elements at zero displacement, N/mm (built
        once, shared by the views of :meth:`with_springs`)."""
        if self._h0_elastic is None:
            sub = self._sub
            _, data, _ = sub.assembler.tangent(self._state(np.zeros(self.n_modes)))
            self._h0_elastic = sub.basis.T @ (sub.assembler.matrix(data) @ sub.basis)
        return self._h0_elastic

    def _newton(self, q_lin: np.ndarray, fr_full: np.ndarray, max_iterations: int, tolerance: float,
                first_increment: float):
        """Reduced Newton with load increments and cut-backs (the first increment starts from
        its share of ``q_lin``). Returns ``(q, iterations)``, or None when the increment
        falls below ``MIN_INCREMENT``."""
        q = np.zeros(self.n_modes)
        lam, dlam = 0.0, float(first_increment)
        prev = None
        iterations = 0
        while lam < 1.0:
            lam_new = min(1.0, lam + dlam)
            fr = lam_new * fr_full
            qn = q + (lam_new - lam) / prev[1] * prev[0] if prev is not None else lam_new * q_lin
            qn, taken, ok = self._newton_increment(q, qn, fr, max_iterations, tolerance)
            iterations += taken
            if ok:
                prev = (qn - q, lam_new - lam)
                q, lam = qn, lam_new
                dlam = min(1.0, INCREMENT_GROWTH * dlam)
            else:
                dlam *= CUTBACK
                if dlam < MIN_INCREMENT:
                    log.debug("reduced model: no convergence at load fraction %.3g", lam)
                    return None
        return q, iterations

    def _newton_increment(self, q: np.ndarray, qn: np.ndarray, fr: np.ndarray, max_iterations: int,
                          tolerance: float):
        """Newton iterations with an Armijo line search from ``qn`` (from ``q``, the last
        converged state, if ``qn`` inverts a sampled element) under reduced forces ``fr``.
        Returns ``(q, iterations, converged)``."""
        e0 = self._energy(qn, fr)
        if not np.isfinite(e0):
            qn = q.copy()
            e0 = self._energy(qn, fr)
        for iteration in range(1, max_iterations + 1):
            dq, grad = self._newton_direction(qn, fr)
            slope = float(grad @ dq)
            step = 1.0
            while step > NEWTON_MIN_STEP:
                e1 = self._energy(qn + step * dq, fr)
                if e1 <= e0 + ARMIJO * step * slope:
                    break
                step *= 0.5
            else:
                return qn, iteration, False
            qn, e0 = qn + step * dq, e1
            if (np.linalg.norm(grad) <= tolerance * np.linalg.norm(fr)
                    or np.linalg.norm(step * dq) <= tolerance * max(np.linalg.norm(qn), _TINY)):
                return qn, iteration, True
        return qn, max_iterations, False

    def _newton_direction(self, q: np.ndarray, fr: np.ndarray):
        """``(dq, gradient)``: the reduced Newton direction at ``q``, a descent direction also
        where the reduced tangent is indefinite (its |eigenvalues| are used then)."""
        asm, basis = self._sub.assembler, self._sub.basis
        fint, data, _ = asm.tangent(self._state(q))
        grad = basis.T @ fint[asm.free_dofs] + self._sub.springs @ q - fr
        h = basis.T @ (asm.matrix(data) @ basis) + self._sub.springs
        try:
            return -cho_solve(cho_factor(h), grad), grad
        except np.linalg.LinAlgError:
            ev, vec = np.linalg.eigh(0.5 * (h + h.T))
            ev = np.maximum(np.abs(ev), EIGENVALUE_FLOOR * max(float(np.abs(ev).max()), _TINY))
            return -vec @ ((vec.T @ grad) / ev), grad

    def _done(self, q: np.ndarray, iterations: int, t0: float) -> np.ndarray:
        u = np.zeros(3 * len(self.problem.nodes))
        u[self.free_dofs] = self.basis @ q
        self.last_iterations = iterations
        self.last_seconds = time.perf_counter() - t0
        return u.reshape(-1, 3)

    def _bfgs(self, q: np.ndarray, fr: np.ndarray, tolerance: float, max_iterations: int):
        """Minimise the reduced energy from ``q`` by BFGS (inverse Hessian from the reduced
        stiffness at zero, Armijo backtracking, updates skipped without positive curvature).
        Returns ``(q, iterations)``, or None when the line search fails."""
        sub = self._sub
        asm = sub.assembler
        free = asm.free_dofs

        def energy_gradient(q):
            e, fint, jmin = asm.energy_and_force(self._state(q))
            if not jmin > 0.0:
                return np.inf, None
            ks_q = sub.springs @ q
            return e + 0.5 * float(q @ ks_q) - float(fr @ q), sub.basis.T @ fint[free] + ks_q - fr

        e, g = energy_gradient(q)
        if not np.isfinite(e):  # the linear answer inverts a sampled element: start from zero
            q = np.zeros_like(q)
            e, g = energy_gradient(q)
        try:
            h0 = np.linalg.inv(self._h0)
        except np.linalg.LinAlgError:
            return None
        h = h0.copy()
        fnorm = np.linalg.norm(fr)
        for iteration in range(1, max_iterations + 1):
            d = -h @ g
            slope = float(g @ d)
            if not slope < 0.0:  # not a descent direction: restart from the initial inverse
                h = h0.copy()
                d = -h @ g
                slope = float(g @ d)
            step = 1.0
            while step > BFGS_MIN_STEP:
                e1, g1 = energy_gradient(q + step * d)
                if e1 <= e + ARMIJO * step * slope:
                    break
                step *= 0.5
            else:
                return None
            s, y = step * d, g1 - g
            q, e, g = q + s, e1, g1
            sy = float(s @ y)
            if sy > BFGS_CURVATURE * np.linalg.norm(s) * np.linalg.norm(y):
                # (I - rho s y^T) h (I - rho y s^T) + rho s s^T, expanded (h symmetric): O(r^2)
                rho, hy = 1.0 / sy, h @ y
                h = h - rho * (np.outer(s, hy) + np.outer(hy, s)) + (rho * rho * float(y @ hy) + rho) * np.outer(s, s)
            if np.linalg.norm(g) <= tolerance * fnorm or np.linalg.norm(s) <= tolerance * max(np.linalg.norm(q), _TINY):
                return q, iteration
        return None
