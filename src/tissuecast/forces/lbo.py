"""Laplace-Beltrami eigenbasis of a mesh's outer surface (the paper's "LBO" force basis).

The operator is the intrinsic-Delaunay cotangent Laplacian of the outer surface triangles
with a lumped (diagonal) mass matrix, built by ``robust_laplacian`` (Sharp & Crane 2020).
The basis is the ``n`` smoothest solutions of the generalised problem ``L v = lambda M v``,
found with sparse shift-invert ARPACK (``scipy.sparse.linalg.eigsh``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from ..errors import MeshError, require
from ..mesh.tetmesh import TetMesh

__all__ = ["LBOBasis", "lbo_basis", "surface_operator"]

# Entries within this relative tolerance of the largest |entry| count as tied for the sign rule.
_SIGN_RTOL = 1e-8
# Extra eigenpairs computed beyond the n requested (see lbo_basis).
_EXTRA_VECTORS = 10


@dataclass(frozen=True, eq=False)
class LBOBasis:
    """The smoothest Laplace-Beltrami eigenvectors of a mesh's outer surface.

    Attributes:
        vertices: (s,) int64, mesh ids of the surface vertices (sorted); row ``i`` of
            ``vectors`` belongs to mesh vertex ``vertices[i]``.
        vectors: (s, n) float64 eigenvectors, smoothest first, M-orthonormal:
            ``vectors.T @ diag(mass) @ vectors = I``. Entries have units of 1/mm
            (they scale like 1/sqrt(surface area)). Sign rule: the entry of largest
            magnitude of each column is positive (near-ties, 1e-8 relative, go to the
            lowest row).
        eigenvalues: (n,) float64, 1/mm^2, ascending; the first is ~0 (constant vector).
        mass: (s,) float64, mm^2, lumped (Voronoi-like) vertex areas; sum = surface area.
    """

    vertices: np.ndarray
    vectors: np.ndarray
    eigenvalues: np.ndarray
    mass: np.ndarray

    @property
    def n_vectors(self) -> int:
        """Number of basis vectors n."""
        return self.vectors.shape[1]


def surface_operator(mesh: TetMesh) -> tuple[np.ndarray, sp.csr_matrix, sp.dia_matrix]:
    """Cotangent Laplacian and lumped mass of the outer surface.

    Args:
        mesh: the tetrahedral mesh.

    Returns:
        ``(vertices (s,) int64, L (s, s) sparse 1, M (s, s) diagonal sparse mm^2)``; ``L`` is
        the positive semi-definite weak Laplacian (``L @ ones = 0``).
    """
    rl = require("robust_laplacian", "forces", "the surface Laplace-Beltrami operator")
    verts = np.asarray(mesh.surface_vertices, dtype=np.int64)
    faces = np.searchsorted(verts, mesh.surface_triangles).astype(np.int64)
    lap, mass = rl.mesh_laplacian(np.ascontiguousarray(mesh.points[verts]), np.ascontiguousarray(faces))
    return verts, sp.csr_matrix(lap), sp.diags(mass.diagonal())


def _fix_signs(vectors: np.ndarray) -> np.ndarray:
    mag = np.abs(vectors)
    top = mag.max(axis=0)
    first = np.argmax(mag >= top * (1.0 - _SIGN_RTOL), axis=0)
    sign = np.sign(vectors[first, np.arange(vectors.shape[1])])
    sign[sign == 0] = 1.0
    return vectors * sign


def lbo_basis(mesh: TetMesh, n: int = 20) -> LBOBasis:
    """The ``n`` smoothest Laplace-Beltrami eigenvectors of the mesh's outer surface.

    Solves ``L v = lambda M v`` (cotangent Laplacian, lumped mass) for the ``n`` smallest
    eigenvalues by shift-invert Lanczos about ``sigma = -1 / area`` (slightly below zero,
    so ``L - sigma M`` is positive definite), from a fixed start vector, computing
    ``n + max(10, n // 2)`` pairs and keeping the ``n`` smallest (Lanczos may miss a copy of
    a repeated eigenvalue at the end of the range it returns). Eigenvectors are
    then M-orthonormalised (Cholesky of the Gram matrix, which keeps their order) and given
    a deterministic sign (see :class:`LBOBasis`). On surfaces with repeated eigenvalues
    (a sphere) any basis of the repeated eigenspace is valid; on real, irregular meshes the
    eigenvalues are distinct and the basis is unique up to that sign rule.

    Args:
        mesh: the tetrahedral mesh (its outer surface must be closed and manifold).
        n: number of eigenvectors (paper: 20); at most (surface vertices - 2).

    Returns:
        :class:`LBOBasis`.

    Raises:
        MeshError: ``n`` out of range for this surface.
    """
    verts, lap, mass = surface_operator(mesh)
    s = len(verts)
    if isinstance(n, bool) or int(n) != n or not 1 <= n <= s - 2:
        raise MeshError(
            f"the LBO basis needs 1 <= n <= {s - 2} (surface vertices - 2) on this mesh, got n={n!r}; "
            "use fewer basis vectors or a finer mesh"
        )
    n = int(n)
    area = float(mass.diagonal().sum())
    v0 = np.random.default_rng(20200).uniform(0.5, 1.5, size=s)  # fixed start -> same Krylov space each run
    # Lanczos can miss copies of a repeated eigenvalue among the last ones it returns, so ask
    # for more than needed and keep the n smallest.
    k = min(s - 2, n + max(_EXTRA_VECTORS, n // 2))
    vals, vecs = eigsh(lap.tocsc(), k=k, M=mass.tocsc(), sigma=-1.0 / area, which="LM", v0=v0, tol=1e-12)
    order = np.argsort(vals)[:n]
    vals, vecs = vals[order], vecs[:, order]
    m = mass.diagonal()
    gram = vecs.T @ (m[:, None] * vecs)
    chol = scipy.linalg.cholesky(gram, lower=False)  # gram = R^T R; vecs R^-1 is M-orthonormal
    vecs = scipy.linalg.solve_triangular(chol, vecs.T, trans="T", lower=False).T
    vecs = _fix_signs(vecs)
    out = {
        "vertices": verts,
        "vectors": np.ascontiguousarray(vecs),
        "eigenvalues": np.ascontiguousarray(vals),
        "mass": np.ascontiguousarray(m),
    }
    for a in out.values():
        a.setflags(write=False)
    return LBOBasis(**out)
