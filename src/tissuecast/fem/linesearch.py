"""Trial paths and the energy line search of the Newton solver.

A Newton correction ``d`` of a body that swings about a few pinned points is mostly an
infinitesimal rigid rotation; moving along the straight line ``u + s d`` stretches the body
(the tangent of a circle leaves the circle), so the line search would only accept short
steps. :func:`step_path` therefore fits the best rigid motion ``omega x (x - c) + t`` to
``d`` (least squares over the free nodes, ``c`` the centroid of the constrained nodes) and
replaces its rotational part by the finite rotation ``R(s omega)``: the trial states lie on
an arc. The path's derivative at ``s = 0`` is still ``d``, so the Armijo test is unchanged.
"""

from __future__ import annotations

import numpy as np

from .assembly import Assembler

__all__ = ["step_path", "line_search", "rotation_matrix", "residual"]

#: A rotation by less than this angle (radians) is the identity (Rodrigues' formula would
#: divide by it).
_SMALL_ANGLE = 1e-12
#: Armijo's sufficient-decrease constant.
ARMIJO = 1e-4
#: Trial steps before the search gives up.
MAX_TRIALS = 10
#: Quadratic backtracking keeps the next step within these shares of the last one.
BACKTRACK_MIN, BACKTRACK_MAX = 0.1, 0.5
#: Step cut after a trial that inverted an element (no energy to interpolate).
INVERTED_CUT = 0.25
#: An expected decrease below this share of the energy's magnitude is round-off: the
#: residual norm decides instead.
ENERGY_ROUNDOFF = 1e-8
#: A full step is stretched when the slope at s = 1 is still below this share of the slope
#: at s = 0 (still running downhill) ...
STRETCH_SLOPE = 0.5
#: ... to the secant minimiser of the slopes, clamped to this range.
STRETCH_MIN, STRETCH_MAX = 1.5, 4.0


def rotation_matrix(omega: np.ndarray) -> np.ndarray:
    """Rotation by the vector ``omega`` (axis * angle in radians), Rodrigues' formula; (3, 3)."""
    ang = float(np.linalg.norm(omega))
    if ang <= _SMALL_ANGLE:
        return np.eye(3)
    k = omega / ang
    kk = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(ang) * kk + (1.0 - np.cos(ang)) * (kk @ kk)


def step_path(nodes, u, d, free, cnodes, cdofs, rotation_aware: bool):
    """Trial states ``u(s)`` along a correction.

    Args:
        nodes: (n_nodes, 3) float, mm, reference node coordinates.
        u: (3 n_nodes,) float, mm, current displacements.
        d: (n_free,) float, mm, the correction on the free dofs.
        free: (n_free,) int, free dof ids; whole nodes are either free or constrained.
        cnodes: (c,) int, constrained node ids; cdofs: (3 c,) their dof ids.
        rotation_aware: arc (True) or straight line (False).

    Returns:
        A function ``s -> (3 n_nodes,) displacements`` whose attribute ``rotation`` is the
        (3, 3) rigid rotation applied by the last call (identity for a straight path).
    """
    if not rotation_aware or len(cnodes) == 0:

        def straight(s):
            t = u.copy()
            t[free] += s * d
            return t

        straight.rotation = np.eye(3)
        return straight
    dd = np.zeros_like(u)
    dd[free] = d
    dd = dd.reshape(-1, 3)
    x = nodes + u.reshape(-1, 3)
    y = x - x[cnodes].mean(axis=0)
    mask = np.ones(len(x), bool)
    mask[cnodes] = False
    ym = y[mask]
    a = np.zeros((len(ym), 3, 6))  # omega x y + t = -[y]x omega + t
    a[:, 0, 1], a[:, 0, 2] = ym[:, 2], -ym[:, 1]
    a[:, 1, 0], a[:, 1, 2] = -ym[:, 2], ym[:, 0]
    a[:, 2, 0], a[:, 2, 1] = ym[:, 1], -ym[:, 0]
    a[:, :, 3:] = np.eye(3)
    omega = np.linalg.lstsq(a.reshape(-1, 6), dd[mask].ravel(), rcond=None)[0][:3]
    linear_rotation = np.cross(omega, y)

    def curved(s):
        rot = rotation_matrix(s * omega)
        curved.rotation = rot
        # the straight step with its rigid-rotation part replaced by the finite rotation
        xn = x + s * dd + y @ (rot - np.eye(3)).T - s * linear_rotation
        t = (xn - nodes).ravel()
        t[cdofs] = u[cdofs]
        return t

    curved.rotation = np.eye(3)
    return curved


def line_search(assembler: Assembler, path, free, d, pi0: float, r0: np.ndarray, fext: np.ndarray, held=None):
    """Backtracking search on the potential energy along ``path``.

    Accepts the first trial (``s = 1, ...``) with every ``J > 0`` that satisfies Armijo's
    condition ``Pi(s) <= Pi(0) + ARMIJO s g0`` (``g0 = d . r0 < 0``), or, when the expected
    decrease is below round-off of the energy, that lowers the residual norm. Backtracks by
    quadratic interpolation (clamped to [0.1, 0.5] s), by 4x after an inverted element
    (the constants above).

    Args:
        assembler: evaluates energy and internal forces.
        path: from :func:`step_path`.
        free: (n_free,) int, free dof ids.
        d: (n_free,) float, the correction (mm).
        pi0: potential energy at s = 0 (mJ); r0: (n_free,) residual there (N).
        fext: (3 n_nodes,) float, external forces (N).
        held: optional (p,) int positions in the free vector that the solve holds at prescribed
            values: the residual is zero there (the reaction is not a residual).

    Returns:
        ``(s, u (3 n_nodes,), Pi, f_int (3 n_nodes,), r (n_free,), rotation (3, 3))`` or None
        if ``d`` is not a descent direction or no acceptable step was found in ``MAX_TRIALS`` trials.
    """
    g0 = float(d @ r0)
    if not g0 < 0.0:
        return None
    r0_norm = np.linalg.norm(r0)
    s = 1.0
    for _ in range(MAX_TRIALS):
        trial = path(s)
        energy, fint, jmin = assembler.energy_and_force(trial.reshape(-1, 3))
        if jmin > 0.0:
            work = float(fext @ trial)
            pi = energy - work
            r = residual(fint, fext, free, held)
            if pi <= pi0 + ARMIJO * s * g0:
                if s == 1.0:
                    return _extrapolate(assembler, path, free, d, g0, fext, (s, trial, pi, fint, r, path.rotation), held)
                return s, trial, pi, fint, r, path.rotation
            if -g0 * s <= ENERGY_ROUNDOFF * (abs(energy) + abs(work)) and np.linalg.norm(r) < r0_norm:
                return s, trial, pi, fint, r, path.rotation
            denom = 2.0 * (pi - pi0 - g0 * s)
            s_new = -g0 * s * s / denom if denom > 0 else BACKTRACK_MAX * s
            s = min(BACKTRACK_MAX * s, max(BACKTRACK_MIN * s, s_new))
        else:
            s *= INVERTED_CUT
    return None


def residual(fint: np.ndarray, fext: np.ndarray, free, held) -> np.ndarray:
    """(n_free,) N: internal minus external forces on the free dofs, zero at ``held`` positions."""
    r = fint[free] - fext[free]
    if held is not None and len(held):
        r[held] = 0.0
    return r


def _extrapolate(assembler: Assembler, path, free, d, g0: float, fext: np.ndarray, accepted, held=None):
    """A full step that still runs downhill may be lengthened (softening responses).

    When the slope of the energy along ``d`` at ``s = 1`` is still below half the one at
    ``s = 0`` (a Newton model that underestimates the step, as when the body softens while it
    swings), one more trial at the secant minimiser of the slopes (clamped to [1.5, 4]) is
    taken if it lowers the energy further. Costs one energy evaluation when tried.
    """
    g1 = float(d @ accepted[4])
    if not g1 < STRETCH_SLOPE * g0:
        return accepted
    s = min(STRETCH_MAX, max(STRETCH_MIN, -g0 / max(g1 - g0, 1e-300)))
    trial = path(s)
    energy, fint, jmin = assembler.energy_and_force(trial.reshape(-1, 3))
    if not jmin > 0.0:
        return accepted
    pi = energy - float(fext @ trial)
    if pi < accepted[2]:
        return s, trial, pi, fint, residual(fint, fext, free, held), path.rotation
    return accepted
