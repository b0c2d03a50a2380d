"""Test-2 force fields: concentrated loads spread by local Laplacian smoothing (LSC), and
their blend with an LBO field (the paper's out-of-distribution test set, method step 11).

Smoothing operator: the uniform ("umbrella") graph Laplacian of the outer surface, on the
edges of the surface triangles: ``(L f)_i = mean_{j ~ i} f_j - f_i``. One step
``f <- f + gamma L f`` replaces each nodal force by ``(1 - gamma) f_i + gamma mean_j f_j``
(a convex combination for 0 < gamma <= 1), so after k steps the load covers exactly the
k-ring of the loaded vertices, no nodal magnitude grows, and the degree-weighted total
``sum_i deg_i f_i`` is preserved (the plain sum is not).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import ConfigError
from ..mesh.tetmesh import TetMesh

__all__ = ["surface_graph_laplacian", "smooth", "lsc_field", "blend"]


def surface_graph_laplacian(mesh: TetMesh) -> sp.csr_matrix:
    """Uniform graph Laplacian of the outer surface, over all mesh vertices.

    Args:
        mesh: the tetrahedral mesh.

    Returns:
        (n, n) sparse float, ``D^-1 A - I`` on the surface-triangle edges; rows and columns
        of interior vertices are zero (their forces stay zero).
    """
    tri = mesh.surface_triangles
    i = tri[:, [0, 1, 2]].ravel()
    j = tri[:, [1, 2, 0]].ravel()
    n = mesh.n_vertices
    adj = sp.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0  # each surface edge is shared by two triangles: count it once
    deg = np.asarray(adj.sum(axis=1)).ravel()
    on = deg > 0
    inv = np.zeros(n)
    inv[on] = 1.0 / deg[on]
    return (sp.diags(inv) @ adj - sp.diags(on.astype(float))).tocsr()


def smooth(forces: np.ndarray, laplacian: sp.spmatrix, iterations: int = 20, rate: float = 0.1) -> np.ndarray:
    """Apply ``iterations`` steps of ``f <- f + rate * L f``.

    Args:
        forces: (n, 3) float, N.
        laplacian: (n, n) sparse, from :func:`surface_graph_laplacian`.
        iterations: number of steps (paper: 20).
        rate: gamma (paper: 0.1), 0 < gamma <= 1.

    Returns:
        (n, 3) float64, N.
    """
    if not 0.0 < rate <= 1.0:
        raise ConfigError(f"smoothing rate gamma must lie in (0, 1], got {rate!r}")
    if iterations < 0:
        raise ConfigError(f"smoothing iterations must be >= 0, got {iterations!r}")
    f = np.array(forces, dtype=np.float64)
    for _ in range(int(iterations)):
        f = f + rate * (laplacian @ f)
    return f


def lsc_field(
    mesh: TetMesh,
    rng: np.random.Generator,
    n_forces: int = 3,
    iterations: int = 20,
    rate: float = 0.1,
    magnitude: float = 1.0,
    exclude=(),
    reference: np.ndarray | None = None,
    laplacian: sp.spmatrix | None = None,
) -> np.ndarray:
    """A random test-2 field: ``n_forces`` concentrated forces, smoothed on the surface.

    Random draws, in this order: ``rng.choice(candidates, n_forces, replace=False)`` picks
    the loaded vertices among the surface vertices not in ``exclude`` (sorted ids);
    ``rng.standard_normal((n_forces, 3))``, normalised, gives directions uniform on the sphere.
    Each loaded vertex gets a force of ``magnitude`` N, then :func:`smooth` spreads them.

    Magnitude rule: if ``reference`` is given (typically the LBO field it will be blended
    with), the smoothed field is rescaled so that its nodal L2 norm ``||f||_F`` equals that
    of ``reference`` (then ``magnitude`` only fixes the pre-smoothing scale and cancels out).

    Args:
        mesh: the tetrahedral mesh.
        rng: numpy random generator.
        n_forces: number of concentrated forces (paper: 3).
        iterations: smoothing steps (paper: 20).
        rate: smoothing rate gamma (paper: 0.1).
        magnitude: concentrated force magnitude in N (before smoothing).
        exclude: vertex ids never loaded (the fixed vertices).
        reference: optional (n, 3) field, N, whose nodal L2 norm the result matches.
        laplacian: optional precomputed :func:`surface_graph_laplacian` (saves time in loops).

    Returns:
        (n, 3) float64 nodal forces in N, zero off the surface.

    Raises:
        ConfigError: too few candidate vertices, bad magnitude or reference.
    """
    cand = np.setdiff1d(mesh.surface_vertices, np.asarray(exclude, dtype=np.int64))
    if not 1 <= n_forces <= len(cand):
        raise ConfigError(f"test-2 fields need 1 <= n_forces <= {len(cand)} loadable surface vertices, got {n_forces}")
    if not np.isfinite(magnitude) or magnitude <= 0:
        raise ConfigError(f"concentrated force magnitude must be > 0 N, got {magnitude!r}")
    ids = rng.choice(cand, size=int(n_forces), replace=False)
    d = rng.standard_normal((int(n_forces), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f = np.zeros((mesh.n_vertices, 3))
    np.add.at(f, ids, float(magnitude) * d)
    lap = surface_graph_laplacian(mesh) if laplacian is None else laplacian
    f = smooth(f, lap, iterations, rate)
    if reference is not None:
        ref = np.asarray(reference, dtype=np.float64)
        if ref.shape != f.shape or not np.isfinite(ref).all():
            raise ConfigError(f"reference field must be a finite ({f.shape[0]}, 3) array, got shape {ref.shape}")
        f *= np.linalg.norm(ref) / np.linalg.norm(f)
    return f


def blend(f_lbo: np.ndarray, f_lsc: np.ndarray, beta: float) -> np.ndarray:
    """The test-2 interpolation ``beta * f_lbo + (1 - beta) * f_lsc``.

    Args:
        f_lbo: (n, 3) float, N.
        f_lsc: (n, 3) float, N.
        beta: LBO share in [0, 1].

    Returns:
        (n, 3) float64, N.
    """
    a, b = np.asarray(f_lbo, dtype=np.float64), np.asarray(f_lsc, dtype=np.float64)
    if a.shape != b.shape:
        raise ConfigError(f"fields to blend must have the same shape, got {a.shape} and {b.shape}")
    if not 0.0 <= beta <= 1.0:
        raise ConfigError(f"beta must lie in [0, 1], got {beta!r}")
    return beta * a + (1.0 - beta) * b
