"""Deflated, preconditioned conjugate gradients for the Newton directions of the solver.

The ``"krylov"`` strategy of :class:`~tissuecast.fem.solver.Solver` assembles the tangent
``K`` at every Newton iteration but solves ``K d = -r`` by conjugate gradients, preconditioned
by the last factorised tangent co-rotated by the rigid rotation applied since it was
factorised (:func:`corotated_solve`). The iterations are deflated (Saad, Yeung, Erhel and
Guyomarc'h 2000) by a subspace ``W``: the three infinitesimal rigid rotations about the
constrained nodes' centroid (:func:`rigid_rotations`; the swing of a body held by a few pins
is its softest motion) and the search directions of the solve's earlier Newton iterations
(:func:`recycle`); the rotations only where the body can swing about its supports (a few pins:
``Problem.can_swing``). Each system is first solved exactly in ``W`` with the *new* tangent
(Galerkin; ``K W`` is one sparse product), and the search directions then stay K-conjugate to
``W`` (:func:`deflated_cg`), so the modes the reused factorisation resolves badly are solved
once per solve instead of once per Newton iteration.

These are pure functions of arrays; the preconditioner is passed in as a generator function
(``v -> yield (factorisation, vector), receive the solve``), so that several solves can
gather their triangular solves into one (:meth:`~tissuecast.fem.solver.Solver.solve_batch`).
"""

from __future__ import annotations

from typing import Callable, Generator

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

__all__ = ["corotated_solve", "rigid_rotations", "deflation_space", "deflated_cg", "recycle", "N_ROTATIONS"]

#: Columns of the deflation subspace that are rigid rotations (about the x, y and z axes);
#: they come first in ``W`` and are rebuilt at every state, never recycled.
N_ROTATIONS = 3

#: A preconditioner application: yields ``(factorisation, vector)``, receives the solve.
Precondition = Callable[[np.ndarray], Generator]


def corotated_solve(factor, rotation: np.ndarray, v: np.ndarray):
    """``R K^-1 R^T v`` (node by node) with a factorised tangent ``K`` and a rotation ``R``.

    A generator (``yield from``): it yields ``(factor, R^T v)`` and receives ``K^-1 R^T v``
    from whoever drives the solve.

    Args:
        factor: a :class:`~tissuecast.fem.linear.LinearSolver` holding ``K``.
        rotation: (3, 3) rigid rotation applied since ``K`` was factorised.
        v: (n_free,) float, a vector over the free dofs (whole nodes, x/y/z).

    Returns:
        (n_free,) float.
    """
    z = yield factor, (v.reshape(-1, 3) @ rotation).ravel()
    return (z.reshape(-1, 3) @ rotation.T).ravel()


def rigid_rotations(x: np.ndarray, cnodes: np.ndarray, free: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
    """Orthonormal basis (n_free, 3) of the infinitesimal rigid rotations about the centroid
    of the constrained nodes.

    Args:
        x: (n_nodes, 3) float, mm, current node positions.
        cnodes: (c,) int, constrained node ids.
        free: (n_free,) int, free dof ids.
        held: optional (p,) int positions in the free vector held by the solve (their rows are zero).
    """
    x = x - x[cnodes].mean(axis=0)
    spin = np.stack([np.cross(axis, x).ravel()[free] for axis in np.eye(3)], axis=1)
    if held is not None and len(held):
        spin[held] = 0.0
    return np.linalg.qr(spin)[0]


def deflation_space(k, spin: np.ndarray, recycled: np.ndarray | None):
    """``((W, K W, cho_factor(W^T K W)) or None, recycled)`` for the deflation subspace.

    ``W`` holds the rotations and the recycled directions. When ``K`` is not positive definite
    on ``W`` the recycled directions are dropped (the second value is then None) and the
    rotations alone tried, then nothing. A subspace as wide as the problem is not used (a tiny
    problem: plain CG is as good).

    Args:
        k: (n_free, n_free) sparse tangent.
        spin: (n_free, 3) from :func:`rigid_rotations`, or (n_free, 0) where the body cannot swing.
        recycled: (n_free, j) directions kept from earlier iterations, or None.
    """
    for w in ((spin,) if recycled is None else (np.column_stack([spin, recycled]), spin)):
        if w.shape[1] >= w.shape[0] or w.shape[1] == 0:
            continue
        aw = k @ w
        e = w.T @ aw
        try:
            return (w, aw, cho_factor(0.5 * (e + e.T), lower=True)), recycled
        except np.linalg.LinAlgError:
            recycled = None
    return None, recycled


def deflated_cg(k, b: np.ndarray, space, precondition: Precondition, tolerance: float, max_steps: int,
                best_effort: bool = False):
    """Solve ``K x = b`` by preconditioned conjugate gradients deflated by ``space``.

    A generator (``yield from``) of the preconditioner's applications. The iteration starts
    from the Galerkin solution in ``W`` and keeps its search directions K-conjugate to ``W``.

    Args:
        k: (n, n) sparse matrix.  b: (n,) right-hand side.
        space: ``(W, K W, cho_factor(W^T K W))`` from :func:`deflation_space`, or None.
        precondition: ``v -> generator`` applying the preconditioner (see the module notes).
        tolerance: relative residual ``||b - K x|| / ||b||`` that ends the iteration.
        max_steps: most conjugate-gradient steps.
        best_effort: after ``max_steps`` steps without meeting the tolerance, return the
            iterate so far instead of None (it still lowers the quadratic model; what an
            approximate preconditioner's last resort needs).

    Returns:
        ``(x, steps, found)``: ``x`` (n,) when the tolerance was met within ``max_steps``
        steps, or when ``K`` showed a non-positive curvature after some progress (the iterate
        so far; with ``space`` the Galerkin start counts as progress), or with
        ``best_effort``, else None; ``steps`` taken; ``found`` the search directions scaled
        to unit K-norm, oldest first.
    """
    target = tolerance * np.linalg.norm(b)
    if space is None:
        x, res, project = np.zeros_like(b), b.copy(), None
    else:
        w, aw, chol = space
        y = cho_solve(chol, w.T @ b)
        x, res = w @ y, b - aw @ y  # Galerkin start in W; K W is already known

        def project(z):  # z minus its K-orthogonal projection on W
            return z - w @ cho_solve(chol, aw.T @ z)

    found: list[np.ndarray] = []
    if np.linalg.norm(res) <= target:
        return x, 0, found
    z = yield from precondition(res)
    p = z if project is None else project(z)
    rz = float(res @ z)
    for step in range(max_steps):
        kp = k @ p
        curvature = float(p @ kp)
        if not curvature > 0.0:  # indefinite along p
            return (x if step or space is not None else None), step, found
        found.append(p / np.sqrt(curvature))
        a = rz / curvature
        x += a * p
        res -= a * kp
        if np.linalg.norm(res) <= target:
            return x, step + 1, found
        z = yield from precondition(res)
        rz_new = float(res @ z)
        p = (z if project is None else project(z)) + (rz_new / rz) * p
        rz = rz_new
    return (x if best_effort else None), max_steps, found


def recycle(found: list, space, cap: int, previous: np.ndarray | None, rotations: int = N_ROTATIONS) -> np.ndarray | None:
    """The directions to deflate the next system with: the newest ``cap`` of this system's
    search directions (K-orthonormal, and K-orthogonal to ``W``) and, to fill up, those of
    ``W`` beyond its first ``rotations`` columns (the rigid rotations) made K-orthonormal and
    K-orthogonal to the rotations (``W L^-T``, ``W^T K W = L L^T``, lower ``L``). ``previous``
    when there is nothing new.

    Returns:
        (n, j) float with ``j <= cap``, or ``previous``.
    """
    cols = found[::-1][:cap]
    if space is not None and len(cols) < cap:
        w, _, (lower, _) = space
        old = solve_triangular(lower, w.T, lower=True).T[:, rotations:]
        cols += list(old.T[: cap - len(cols)])
    return np.column_stack(cols) if cols else previous
