"""Two-level p-multigrid: a preconditioner whose cost per application grows like the mesh.

A sparse Cholesky factor of a 3D quadratic-tetrahedron stiffness fills in like ``n^(4/3)``
(nested dissection) and costs ``~n^2`` flops to make, so on patient-size meshes the direct
backends of :mod:`.direct` dominate every solve. :class:`PMultigrid` replaces the factor by
one symmetric two-level cycle for the same matrix ``K`` (free dofs of a P2 problem):

1. pre-smoothing: ``degree`` steps of Chebyshev acceleration of the Jacobi iteration
   (``D = diag K``) on the interval ``[lambda_max / CHEBYSHEV_RATIO, lambda_max]`` of
   ``D^-1 K`` (``lambda_max`` by power iterations, times ``SPECTRAL_MARGIN``);
2. coarse correction with the linear (P1) space of the same mesh: ``P Kc^-1 P^T`` where
   ``P`` interpolates vertex values to every element node (a mid-edge node takes the mean
   of its edge's two vertices) and ``Kc = P^T K P`` (Galerkin) is factorised by CHOLMOD
   (SuperLU without scikit-sparse) -- about a seventh of the unknowns and a far sparser
   pattern than the P2 matrix;
3. post-smoothing: the same Chebyshev polynomial (so the cycle is a symmetric positive
   definite operator and can precondition conjugate gradients).

With the coarse problem solved exactly, the number of conjugate-gradient steps does not grow
with the mesh; everything but the coarse solve is a few sparse products. It is an
*approximate* inverse (``exact = False``): the Newton solver runs conjugate gradients with
it where a direct backend would return ``K^-1 r`` in one application. Measurements and the
crossover with the direct backends: ``docs/solver.md`` and ``benchmarks/scaling.py``.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from ...errors import SolverSetupError
from ...mesh.tetmesh import TET_EDGES
from .base import LinearSolver, NotPositiveDefinite

__all__ = ["PMultigrid", "vertex_interpolation", "CHEBYSHEV_RATIO", "SPECTRAL_MARGIN", "POWER_ITERATIONS"]

#: The smoother damps the upper part ``[lambda_max / CHEBYSHEV_RATIO, lambda_max]`` of the
#: spectrum of ``D^-1 K``; the coarse space takes care of the rest.
CHEBYSHEV_RATIO = 10.0
#: Power iterations underestimate ``lambda_max``; a Chebyshev interval that ends below the
#: spectrum amplifies the modes beyond it, so the estimate is enlarged by this factor.
SPECTRAL_MARGIN = 1.1
#: Power iterations estimating ``lambda_max(D^-1 K)`` at each :meth:`PMultigrid.factorize`.
POWER_ITERATIONS = 20


def vertex_interpolation(connectivity: np.ndarray, n_nodes: int, free_dofs: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """The prolongation from the free vertex dofs to the free dofs of a P2 mesh.

    Args:
        connectivity: (m, 10) int, P2 element nodes (4 vertices, then the mid-edge nodes in
            :data:`~tissuecast.mesh.tetmesh.TET_EDGES` order).
        n_nodes: number of element nodes (vertices are nodes ``0 .. n_v - 1``).
        free_dofs: (n_free,) int, the free dofs (``3 node + component``), sorted.

    Returns:
        ``(P, coarse_dofs)``: ``P`` (n_free, n_coarse) CSR (1 from a vertex to itself, 1/2 from
        each end vertex to a mid-edge node, per component) and ``coarse_dofs`` (n_coarse,) int,
        the free dofs that belong to vertices.
    """
    conn = np.asarray(connectivity, dtype=np.int64)
    vertices = np.unique(conn[:, :4])
    mids = conn[:, 4:].ravel()
    ends = conn[:, TET_EDGES].reshape(-1, 2)
    mids, first = np.unique(mids, return_index=True)
    ends = ends[first]
    rows = np.r_[vertices, mids, mids]
    cols = np.r_[vertices, ends[:, 0], ends[:, 1]]
    vals = np.r_[np.ones(len(vertices)), np.full(2 * len(mids), 0.5)]
    rows = (3 * rows[:, None] + np.arange(3)).ravel()
    cols = (3 * cols[:, None] + np.arange(3)).ravel()
    vals = np.repeat(vals, 3)
    full = sp.csr_matrix((vals, (rows, cols)), shape=(3 * n_nodes, 3 * n_nodes))
    free_dofs = np.asarray(free_dofs, dtype=np.int64)
    vertex_dof = np.zeros(3 * n_nodes, dtype=bool)
    vertex_dof[(3 * vertices[:, None] + np.arange(3)).ravel()] = True
    coarse = free_dofs[vertex_dof[free_dofs]]
    return full[free_dofs][:, coarse].tocsr(), coarse


class PMultigrid(LinearSolver):
    """Two-level p-multigrid cycle for the P2 stiffness (see the module notes).

    Args:
        assembler: supplies the pattern; must be of order 2.
        degree: Chebyshev smoothing steps before and after the coarse correction (1-8).
        shared: the prolongation and the coarse symbolic analysis of another instance of
            the same pattern (see :meth:`spawn`).

    Raises:
        SolverSetupError: the assembler is not of quadratic elements.
    """

    name = "p-multigrid"
    exact = False

    def __init__(self, assembler, degree: int = 2, shared=None) -> None:
        super().__init__(assembler)
        if assembler.order != 2:
            raise SolverSetupError("linear_solver 'p-multigrid' needs quadratic elements (solver.order = 2): its coarse "
                                   "level is the linear space of the same mesh; use 'auto' or a direct backend for order 1")
        self.degree = int(degree)
        if shared is None:
            p, _ = vertex_interpolation(assembler.connectivity, assembler.n_nodes, assembler.free_dofs)
            shared = (p, p.T.tocsr(), _coarse_symbolic(p, assembler))
        self._shared = shared
        self._p, self._pt, symbolic = shared
        self._coarse = symbolic.copy() if symbolic is not None else None
        self._lu = None
        self._k = self._dinv = None
        self._lmax = 1.0

    def spawn(self) -> "PMultigrid":
        """Another instance sharing the prolongation and the coarse symbolic analysis."""
        return PMultigrid(self.assembler, self.degree, shared=self._shared)

    @property
    def coarse_size(self) -> int:
        """Unknowns of the coarse (vertex) level."""
        return self._p.shape[1]

    def factorize(self, data: np.ndarray) -> None:
        """Build the cycle for the matrix with CSR values ``data``.

        Raises:
            NotPositiveDefinite: a diagonal entry is not positive, or the coarse matrix
                ``P^T K P`` is not positive definite (then neither is ``K``).
        """
        k = self.assembler.matrix(data)
        diag = data[self.assembler.diagonal_index]
        if not np.all(diag > 0.0):
            raise NotPositiveDefinite("the stiffness has a non-positive diagonal entry")
        kc = (self._pt @ k @ self._p).tocsc()
        if self._coarse is not None:
            from sksparse import cholmod

            try:
                self._coarse.cholesky_inplace(sp.tril(kc, format="csc"))
            except cholmod.CholmodNotPositiveDefiniteError as exc:
                raise NotPositiveDefinite(str(exc)) from None
        else:
            try:
                self._lu = spl.splu(kc, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
            except RuntimeError as exc:
                raise NotPositiveDefinite(str(exc)) from None
        self._k, self._dinv = k, 1.0 / diag
        self._lmax = SPECTRAL_MARGIN * _spectral_radius(k, self._dinv)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """One symmetric two-level cycle applied to ``b`` ((n_free,) or (n_free, k))."""
        b = np.asarray(b, dtype=np.float64)
        x = self._smooth(b)
        x += self._p @ self._coarse_solve(self._pt @ (b - self._k @ x))
        return x + self._smooth(b - self._k @ x)

    def _coarse_solve(self, bc: np.ndarray) -> np.ndarray:
        return self._coarse(bc) if self._coarse is not None else self._lu.solve(bc)

    def _smooth(self, r: np.ndarray) -> np.ndarray:
        """Chebyshev-accelerated Jacobi from zero: ``x = q(D^-1 K) D^-1 r`` (a symmetric
        operator), ``degree`` steps on ``[lambda_max / CHEBYSHEV_RATIO, lambda_max]``."""
        dinv = self._dinv if r.ndim == 1 else self._dinv[:, None]
        hi = self._lmax
        lo = hi / CHEBYSHEV_RATIO
        theta, delta = 0.5 * (hi + lo), 0.5 * (hi - lo)
        sigma = theta / delta
        rho = 1.0 / sigma
        d = dinv * r / theta
        x = d.copy()
        res = r
        for _ in range(self.degree - 1):
            res = res - self._k @ d
            rho_new = 1.0 / (2.0 * sigma - rho)
            d = rho_new * rho * d + (2.0 * rho_new / delta) * (dinv * res)
            rho = rho_new
            x += d
        return x


def _coarse_symbolic(p: sp.csr_matrix, assembler):
    """CHOLMOD's symbolic analysis of the coarse pattern ``P^T |K| P`` (None without
    scikit-sparse: the coarse matrix is then factorised by SuperLU)."""
    if importlib.util.find_spec("sksparse") is None:
        return None
    from sksparse import cholmod

    pattern = assembler.matrix(np.ones(assembler.nnz))
    kc = (p.T @ pattern @ p).tocsc()
    kc.data[:] = 1.0
    return cholmod.analyze(sp.tril(kc, format="csc"), mode="supernodal", ordering_method="nesdis")


def _spectral_radius(k, dinv: np.ndarray) -> float:
    """Largest eigenvalue of ``D^-1 K`` by power iterations from a fixed start (deterministic)."""
    x = np.cos(np.arange(len(dinv)) * 0.7) + 1.5  # a fixed, non-smooth, positive start
    lam = 1.0
    for _ in range(POWER_ITERATIONS):
        y = dinv * (k @ x)
        lam = float(np.linalg.norm(y) / np.linalg.norm(x))
        x = y / np.linalg.norm(y)
    return lam
