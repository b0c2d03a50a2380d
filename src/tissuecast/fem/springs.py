"""Linear springs from element nodes to fixed ground (an elastic support of the body).

Each spring holds one node with a constant symmetric 3x3 stiffness ``K_a`` (N/mm) in the
reference directions: force ``-K_a u_a``, energy ``u_a . K_a u_a / 2``. CalculiX's SPRING1
elements behave the same way under NLGEOM (one per principal direction of ``K_a``, oriented by
``*SPRING, ORIENTATION``), so a deck written from these springs describes the same discrete
problem. :mod:`tissuecast.scenario.elastic_support` builds them from a stiffness per unit area of a
surface region.
"""

from __future__ import annotations

import copy

from dataclasses import dataclass

import numpy as np

from ..errors import SolverSetupError

__all__ = ["NodalSprings"]


@dataclass(frozen=True, eq=False)
class NodalSprings:
    """Linear springs from element nodes to fixed ground.

    Attributes:
        nodes: (s,) int64 sorted node ids (P2: vertices first, then mid-edge nodes).
        stiffness: (s, 3, 3) float, N/mm, symmetric positive semi-definite per node.

    Raises:
        SolverSetupError: wrong shapes, repeated or negative node ids, non-finite, asymmetric
            or indefinite stiffness.
    """

    nodes: np.ndarray
    stiffness: np.ndarray

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=np.int64).ravel()
        k = np.asarray(self.stiffness, dtype=np.float64)
        if k.shape != (len(nodes), 3, 3):
            raise SolverSetupError(f"spring stiffness must have shape ({len(nodes)}, 3, 3) (one 3x3 N/mm per node), "
                                   f"got {k.shape}")
        if len(np.unique(nodes)) != len(nodes) or (nodes.size and nodes.min() < 0):
            raise SolverSetupError("spring nodes must be distinct non-negative node ids (0-based)")
        if not np.all(np.isfinite(k)) or not np.allclose(k, np.swapaxes(k, 1, 2), rtol=1e-12, atol=0.0):
            raise SolverSetupError("spring stiffness must be finite and symmetric per node")
        if k.size and np.linalg.eigvalsh(k).min() < -1e-12 * max(float(np.abs(k).max()), 1e-300):
            raise SolverSetupError("spring stiffness must be positive semi-definite per node (a spring never pushes "
                                   "the node away from where it is held)")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "stiffness", k)

    def __len__(self) -> int:
        return len(self.nodes)

    def without(self, nodes: np.ndarray) -> "NodalSprings":
        """The springs of the nodes not in ``nodes`` ((k,) int)."""
        keep = ~np.isin(self.nodes, nodes)
        return NodalSprings(self.nodes[keep], self.stiffness[keep])

    def forces(self, u: np.ndarray) -> np.ndarray:
        """Spring forces on the nodes, ``-K_a u_a``: (s, 3) N for nodal displacements ``u``
        ((n_nodes, 3) mm)."""
        return -np.einsum("sij,sj->si", self.stiffness, u[self.nodes])

    def energy(self, u: np.ndarray) -> float:
        """Stored energy ``sum_a u_a . K_a u_a / 2`` in mJ for ``u`` (n_nodes, 3) mm."""
        return float(-0.5 * np.sum(self.forces(u) * u[self.nodes]))

    def matrix(self, free: np.ndarray):
        """The springs' stiffness on the free dofs: (n_free, n_free) sparse CSR, N/mm.

        Args:
            free: (3 n_nodes,) bool, True for the free dofs (node-major, x/y/z).
        """
        import scipy.sparse as sp

        free = np.asarray(free, dtype=bool)
        local = np.full(len(free), -1, dtype=np.int64)
        local[free] = np.arange(int(free.sum()))
        dofs = local[(3 * self.nodes[:, None] + np.arange(3))]  # (s, 3)
        rows = np.repeat(dofs, 3, axis=1).ravel()
        cols = np.tile(dofs, (1, 3)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        n = int(free.sum())
        return sp.csr_matrix((self.stiffness.reshape(-1)[keep], (rows[keep], cols[keep])), shape=(n, n))


class SpringAssembly:
    """The springs' share of an :class:`~.assembly.Assembler`'s forces, energy and tangent.

    A spring couples the three dofs of one node, and that node's 3x3 block is already in the
    element stiffness pattern, so the springs add constant values at fixed positions of the
    CSR data (found once here): no new sparsity pattern, no new symbolic factorisation.
    Springs at constrained dofs only reach the reactions.

    Args:
        springs: the nodal springs.
        assembler: the assembler of the same nodes (its free dofs and CSR pattern).
    """

    def __init__(self, springs: NodalSprings, assembler) -> None:
        self.springs = springs
        n_dofs = assembler.n_dofs
        if len(springs) and springs.nodes.max() >= n_dofs // 3:
            raise SolverSetupError(f"spring node {int(springs.nodes.max())} is outside the {n_dofs // 3} element nodes")
        self.dofs = (3 * springs.nodes[:, None] + np.arange(3)).ravel()  # (3 s,)
        local = np.full(n_dofs, -1, dtype=np.int64)
        local[assembler.free_dofs] = np.arange(assembler.n_free)
        rows = np.repeat(local[self.dofs].reshape(-1, 3), 3, axis=1).ravel()  # (9 s,) (a, i, j) -> row of (a, i)
        cols = np.tile(local[self.dofs].reshape(-1, 3), (1, 3)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        n = assembler.n_free
        entry_rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(assembler.indptr))
        keys = entry_rows * n + assembler.indices  # ascending: CSR rows, then columns, sorted
        want = rows[keep] * n + cols[keep]
        pos = np.searchsorted(keys, want)
        if np.any(keys[np.minimum(pos, len(keys) - 1)] != want):  # pragma: no cover - a node's block is always there
            raise SolverSetupError("a spring's 3x3 block is not in the stiffness pattern")
        self.positions = pos
        self._keep = keep
        self.values = springs.stiffness.reshape(-1)[keep]

    def with_stiffness(self, springs: NodalSprings) -> "SpringAssembly":
        """The same nodes with other stiffnesses (``springs.nodes`` must be this one's): the
        positions found once are kept."""
        if not np.array_equal(springs.nodes, self.springs.nodes):
            raise SolverSetupError("with_stiffness: the springs must act at the same nodes")
        out = copy.copy(self)
        out.springs = springs
        out.values = springs.stiffness.reshape(-1)[self._keep]
        return out

    def add_tangent(self, data: np.ndarray) -> np.ndarray:
        """CSR stiffness data (nnz,) N/mm with the springs added (in place; returned)."""
        data[self.positions] += self.values  # distinct positions: one node's block each
        return data

    def forces(self, u: np.ndarray) -> np.ndarray:
        """(3 n_nodes,) N: the springs' pull-back ``K_a u_a`` on their nodes, the same sign as
        internal forces (their sum with them balances the applied loads); ``u`` (n_nodes, 3) mm."""
        out = np.zeros(u.size)
        out[self.dofs] = np.einsum("sij,sj->si", self.springs.stiffness, u[self.springs.nodes]).ravel()
        return out

    def energy(self, u: np.ndarray) -> float:
        """Stored energy in mJ for nodal displacements ``u`` (n_nodes, 3) mm."""
        return self.springs.energy(u)
