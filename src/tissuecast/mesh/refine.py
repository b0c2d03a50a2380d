"""Uniform refinement of a tetrahedral mesh: every tetrahedron split into eight.

The refined mesh's vertices are the coarse mesh's quadratic nodes (``TetMesh.points10``): the
coarse vertices keep their ids ``0..n-1`` and edge ``e`` of ``mesh.edges`` becomes vertex
``n + e`` at its midpoint. So a field computed on the refined mesh is read back on the coarse
vertices as its first ``n`` rows, with no interpolation, and a coarse quadratic field is a
linear field on the refined mesh node for node.

Each tetrahedron gives its four corner tetrahedra (half its size, same shape) and splits the
octahedron left in its middle along the shortest of the octahedron's three diagonals into
four (Bey's red refinement with the shortest-diagonal rule), so the elements' shapes stay
within a few classes and no element degenerates on repeated refinement. Children are
numbered parent by parent: child ``k`` belongs to coarse element ``k // 8``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .tetmesh import TET_EDGES, TetMesh

__all__ = ["RefinedMesh", "refine_uniformly", "refine_vertex_set"]

#: barycentric coordinates of the 10 quadratic nodes of a tetrahedron (vertices, then mid-edges)
_LOCAL_BARYCENTRIC = np.vstack([np.eye(4), 0.5 * (np.eye(4)[TET_EDGES[:, 0]] + np.eye(4)[TET_EDGES[:, 1]])])


def _quadratic_shapes(bary: np.ndarray) -> np.ndarray:
    """(k, 10) the 10-node tetrahedron's shape functions at barycentric points (k, 4)."""
    corner = bary * (2.0 * bary - 1.0)
    edge = 4.0 * bary[:, TET_EDGES[:, 0]] * bary[:, TET_EDGES[:, 1]]
    return np.hstack([corner, edge])


# local node ids in a tets10 row: 0-3 vertices, 4 (0,1), 5 (1,2), 6 (0,2), 7 (0,3), 8 (1,3), 9 (2,3)
_CORNERS = np.array([[0, 4, 6, 7], [4, 1, 5, 8], [6, 5, 2, 9], [7, 8, 9, 3]], dtype=np.int64)
# the octahedron's three diagonals and, for each, the cycle of the four other nodes around it
_DIAGONALS = np.array([[4, 9], [6, 8], [7, 5]], dtype=np.int64)
_CYCLES = np.array([[6, 5, 8, 7], [4, 5, 9, 7], [4, 6, 9, 8]], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class RefinedMesh:
    """A uniformly refined mesh and where its parts come from.

    Attributes:
        mesh: the refined :class:`TetMesh` (8 m tetrahedra, ``n + e`` vertices, mm).
        parent: (8 m,) int64 coarse element of each refined element.
        n_coarse: n, the coarse mesh's vertex count (its vertices are the refined ids ``0..n-1``).
        edges: (e, 2) int64 the coarse edges; refined vertex ``n + k`` is the midpoint of ``edges[k]``.
        local: (8 m, 4) int64 each refined element's vertices as nodes 0-9 of its parent's
            quadratic element (``TetMesh.tets10`` order).
        coarse_tets10: (m, 10) int64 the coarse quadratic connectivity.
    """

    mesh: TetMesh
    parent: np.ndarray
    n_coarse: int
    edges: np.ndarray
    local: np.ndarray
    coarse_tets10: np.ndarray

    def coarse_values(self, values: np.ndarray) -> np.ndarray:
        """A refined vertex field (n + e, ...) read on the coarse vertices: its first n rows."""
        return np.asarray(values)[: self.n_coarse]

    def from_coarse(self, values: np.ndarray) -> np.ndarray:
        """A coarse vertex field (n, ...) on the refined vertices, linear along each coarse edge."""
        v = np.asarray(values, dtype=np.float64)
        return np.concatenate([v, 0.5 * (v[self.edges[:, 0]] + v[self.edges[:, 1]])])

    def from_coarse_quadratic(self, nodal: np.ndarray) -> np.ndarray:
        """A coarse quadratic field at the coarse element nodes ((n + e, 3), ``points10``
        order) on the refined mesh's quadratic nodes ((len(mesh.points10), 3)): exact, the
        coarse field is quadratic in each coarse element (e.g. a coarse solution as a start
        for the refined solve)."""
        u = np.asarray(nodal, dtype=np.float64)
        fine = self.mesh
        first = np.full(len(fine.edges), -1, dtype=np.int64)
        child_edges = fine.tets10[:, 4:] - fine.n_vertices  # (8m, 6) refined edge ids
        order = np.argsort(child_edges.ravel(), kind="stable")
        keys = child_edges.ravel()[order]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        first[keys[starts]] = order[starts]
        child, slot = np.divmod(first, 6)
        a, b = TET_EDGES[slot, 0], TET_EDGES[slot, 1]
        bary = _LOCAL_BARYCENTRIC[self.local[child]]  # (e_f, 4 vertices, 4)
        point = 0.5 * (bary[np.arange(len(child)), a] + bary[np.arange(len(child)), b])  # (e_f, 4)
        parent_nodes = self.coarse_tets10[self.parent[child]]  # (e_f, 10)
        mid = np.einsum("ek,eki->ei", _quadratic_shapes(point), u[parent_nodes])
        return np.vstack([u, mid])


def _negative(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(k,) bool: the tetrahedra (k, 4) whose signed volume is negative."""
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0.0


def refine_uniformly(mesh: TetMesh) -> RefinedMesh:
    """Split every tetrahedron of ``mesh`` into eight (module notes).

    Args:
        mesh: the coarse mesh (mm).

    Returns:
        The :class:`RefinedMesh`; its volume equals the coarse volume (straight edges).
    """
    points = np.asarray(mesh.points10, dtype=np.float64)
    t10 = np.asarray(mesh.tets10, dtype=np.int64)
    m = len(t10)
    corners = t10[:, _CORNERS]  # (m, 4, 4)
    lengths = np.linalg.norm(points[t10[:, _DIAGONALS[:, 0]]] - points[t10[:, _DIAGONALS[:, 1]]], axis=2)
    k = np.argmin(lengths, axis=1)  # (m,) the shortest diagonal
    diag = t10[np.arange(m)[:, None], _DIAGONALS[k]]  # (m, 2)
    ring = t10[np.arange(m)[:, None], _CYCLES[k]]  # (m, 4)
    inner = np.stack([np.column_stack([diag, ring[:, j], ring[:, (j + 1) % 4]]) for j in range(4)], axis=1)
    local = np.concatenate([np.broadcast_to(_CORNERS, (m, 4, 4)),
                            np.stack([np.column_stack([np.broadcast_to(_DIAGONALS[k], (m, 2)), _CYCLES[k][:, j],
                                                       _CYCLES[k][:, (j + 1) % 4]]) for j in range(4)], axis=1)],
                           axis=1)
    tets = np.concatenate([corners, inner], axis=1).reshape(8 * m, 4)
    local = local.reshape(8 * m, 4)
    flip = _negative(points, tets)
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    local[flip, 2], local[flip, 3] = local[flip, 3].copy(), local[flip, 2].copy()
    parent = np.repeat(np.arange(m, dtype=np.int64), 8)
    return RefinedMesh(TetMesh(points, tets), parent, mesh.n_vertices, np.asarray(mesh.edges, dtype=np.int64), local,
                       t10)


def refine_vertex_set(refined: RefinedMesh, vertices: np.ndarray) -> np.ndarray:
    """The refined vertices of a coarse vertex set: its vertices and the midpoints of the coarse
    edges whose two ends are in it (e.g. a surface region), (k,) int64 sorted."""
    vertices = np.asarray(vertices, dtype=np.int64)
    both = np.isin(refined.edges, vertices).all(axis=1)
    return np.sort(np.concatenate([vertices, refined.n_coarse + np.flatnonzero(both)]))
