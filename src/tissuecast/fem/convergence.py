"""When a Newton iteration has converged: the Abaqus-like test of the nonlinear solver.

Both must hold: the largest residual force component is at most ``force_tolerance * q``
(``q`` the mean magnitude of the applied nodal forces and support reactions, averaged over the
increments so far) and the largest correction, scaled by ``rho / (1 - rho)`` when the
corrections contract slowly (``rho`` the ratio of successive corrections), is at most
``displacement_tolerance *`` the largest displacement of the increment. Defaults 5e-3 and
1e-2 are Abaqus' R_n and C_n (``SolverConfig.force_tolerance`` / ``displacement_tolerance``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["IncrementFailed", "converged", "correction_estimate", "reference_force", "RESIDUAL_ALONE", "CORRECTION_ROUNDOFF",
           "SLOW_CONTRACTION"]

#: A residual below this share of the force tolerance is converged without the correction
#: test (e.g. an increment that starts in equilibrium, or a residual at round-off).
RESIDUAL_ALONE = 1e-3
#: A correction below this share of the largest displacement is round-off: it cannot shrink.
CORRECTION_ROUNDOFF = 1e-12
#: Corrections contracting by more than this ratio per iteration are not converging
#: linearly, and ``rho / (1 - rho)`` would blow up: the raw correction is tested instead.
SLOW_CONTRACTION = 0.95


class IncrementFailed(Exception):
    """An increment did not converge (internal control flow: it is retried smaller)."""



def correction_estimate(cmax: float, previous: float | None) -> float:
    """The largest correction ``cmax`` (mm), scaled by ``rho / (1 - rho)`` when the corrections
    contract slowly (``rho = cmax / previous``), as an estimate of the remaining error."""
    rho = cmax / previous if previous else 0.0
    return cmax * max(1.0, rho / (1.0 - rho)) if rho < SLOW_CONTRACTION else cmax


def converged(rmax: float, q: float, cmax: float, estimate: float, dmax: float, umax: float,
              force_tolerance: float, displacement_tolerance: float) -> bool:
    """The Abaqus-like convergence test of a Newton iteration.

    Args:
        rmax: largest residual force component, N.
        q: reference force (mean magnitude of applied forces and reactions), N.
        cmax: largest correction of the iteration, mm; estimate: it, scaled by the
            contraction (:func:`correction_estimate`).
        dmax: largest displacement of the increment, mm; umax: largest displacement, mm.
        force_tolerance, displacement_tolerance: R_n and C_n.

    Returns:
        True when the residual is small (``rmax <= force_tolerance * q``) and so is the
        correction (``estimate <= displacement_tolerance * dmax``, or round-off), or when the
        residual alone is far below its tolerance.
    """
    if rmax <= RESIDUAL_ALONE * force_tolerance * q:
        return True
    return rmax <= force_tolerance * q and (estimate <= displacement_tolerance * dmax
                                            or cmax <= CORRECTION_ROUNDOFF * umax)


def reference_force(fint: np.ndarray, fext: np.ndarray, cnodes: np.ndarray, springs: np.ndarray | None = None,
                    counted: np.ndarray | None = None) -> float:
    """Mean magnitude (N) of the applied nodal forces and the support reactions.

    Args:
        fint, fext: (3 n_nodes,) internal and external nodal forces, N.
        cnodes: (c,) constrained node ids.
        springs: optional (3 s,) forces of the springs of an elastic support on their nodes, N
            (the reactions of that support).
        counted: optional (3 n_nodes,) the applied forces to count (default ``fext``; body
            loads are left out: they show in the reactions).
    """
    mags = np.linalg.norm((fext if counted is None else counted).reshape(-1, 3), axis=1)
    reac = np.linalg.norm((fint - fext).reshape(-1, 3)[cnodes], axis=1)
    parts = [mags[mags > 0.0], reac]
    if springs is not None:
        mags = np.linalg.norm(springs.reshape(-1, 3), axis=1)
        parts.append(mags[mags > 0.0])
    vals = np.concatenate(parts)
    return float(vals.mean()) if len(vals) else 0.0
