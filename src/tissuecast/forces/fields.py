"""LBO force fields: random smooth surface loads f = alpha * B @ W (the paper's training fields).

Forces are dead nodal loads in N on the mesh vertices (zero off the outer surface).

Scale convention: the basis columns are M-orthonormal (``B.T @ diag(mass) @ B = I``), so a
column's nodal entries are ~ 1/sqrt(surface area) (1/mm), independent of the vertex count.
``alpha`` is in N per unit weight *of the basis as stored*: the force on surface vertex i is
``alpha * sum_k B[i, k] W[k, :]`` N (strictly alpha is in N mm, since B is in 1/mm).
Refining the mesh at a fixed area leaves the nodal forces' size unchanged, so the total force
grows with the number of surface vertices; calibrate alpha on the mesh at hand.
:func:`field_scale` gives the RMS nodal force magnitude of a random field per unit alpha, so
magnitude calibration can reason in N directly.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .lbo import LBOBasis

__all__ = ["random_lbo_weights", "lbo_field", "field_scale"]


def random_lbo_weights(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random weights W of an LBO field, independent U(-1, 1).

    Uses exactly one draw, ``rng.uniform(-1.0, 1.0, size=(n, 3))``, so a per-sample
    generator seeded from (base seed, sample index) reproduces the weights bit for bit.

    Args:
        rng: numpy random generator.
        n: number of basis vectors.

    Returns:
        (n, 3) float64, dimensionless; column j weighs the basis for force axis j.
    """
    return rng.uniform(-1.0, 1.0, size=(int(n), 3))


def lbo_field(basis: LBOBasis, weights: np.ndarray, alpha: float, n_vertices: int) -> np.ndarray:
    """Nodal force field ``alpha * B @ W`` on the surface vertices, zero elsewhere.

    Args:
        basis: the surface LBO basis (``vectors`` (s, n)).
        weights: (n, 3) float, dimensionless weights W.
        alpha: magnitude in N per unit weight of the basis as stored (see module notes).
        n_vertices: number of mesh vertices.

    Returns:
        (n_vertices, 3) float64, N.

    Raises:
        ConfigError: weights of the wrong shape, non-finite alpha, or ``n_vertices`` too small.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (basis.n_vectors, 3):
        raise ConfigError(f"LBO weights must have shape ({basis.n_vectors}, 3) to match the basis, got {w.shape}")
    if not np.isfinite(alpha):
        raise ConfigError(f"force magnitude alpha must be finite, got {alpha!r}")
    if n_vertices <= int(basis.vertices.max()):
        raise ConfigError(
            f"n_vertices={n_vertices} is too small for the basis (largest surface vertex id "
            f"{int(basis.vertices.max())}); pass the mesh's vertex count"
        )
    f = np.zeros((int(n_vertices), 3))
    f[basis.vertices] = float(alpha) * (basis.vectors @ w)
    return f


def field_scale(basis: LBOBasis) -> float:
    """RMS nodal force magnitude of a random LBO field per unit alpha (N per unit alpha).

    For W ~ U(-1, 1) (variance 1/3 per entry), the expected squared magnitude of the force
    on surface vertex i is ``sum_k B[i, k]^2`` (3 axes x 1/3); this returns the square root
    of its mean over the surface vertices, ``||B||_F / sqrt(s)``. So a random field
    ``lbo_field(basis, random_lbo_weights(rng, n), alpha, ...)`` has an RMS surface nodal
    force of about ``alpha * field_scale(basis)`` N.

    Returns:
        float, N per unit alpha.
    """
    b = basis.vectors
    return float(np.sqrt((b * b).sum() / b.shape[0]))
