"""A nodal surface force field read as a traction and applied with the elements' shape functions.

The paper applies its LBO fields as forces on the mesh vertices (for quadratic elements: on the
corner nodes only). A body held by a few pins mostly swings under them, but a body held by its
surroundings responds locally, and a force on a corner node of 10-node tetrahedra is a point
load: the vertex dents 2-3x more than its neighbours (measured on the embedded phantom,
linear elasticity). :func:`traction_loads` instead reads the field as a traction
``t_v = f_v / A_v`` (N/mm^2; ``A_v`` the vertex's lumped area, a third of its triangles'),
interpolates it linearly over each surface triangle and integrates it with the surface shape
functions: for the 6-node triangle of area A, corner ``i`` gets ``A (t_i / 30 - (t_j + t_k) / 60)``
and the mid-edge node of edge ``(i, j)`` gets ``A (2 (t_i + t_j) / 15 + t_k / 15)``; for the
3-node triangle vertex ``i`` gets ``A (2 t_i + t_j + t_k) / 12``. The field's total force is kept.
Forces in N, lengths in mm.
"""

from __future__ import annotations

import numpy as np

from ..mesh.surface import lumped_areas, surface_nodes, triangle_areas
from ..mesh.tetmesh import TetMesh

__all__ = ["traction_loads"]

#: Consistent loads of a linear traction on the 3-node triangle: row = node, column = corner value, times A.
_P1 = np.array([[2.0, 1.0, 1.0], [1.0, 2.0, 1.0], [1.0, 1.0, 2.0]]) / 12.0
#: ... on the 6-node triangle (corners, then the mid-edge nodes of edges (0, 1), (1, 2), (2, 0)).
_P2 = np.array([
    [1 / 30, -1 / 60, -1 / 60],
    [-1 / 60, 1 / 30, -1 / 60],
    [-1 / 60, -1 / 60, 1 / 30],
    [2 / 15, 2 / 15, 1 / 15],
    [1 / 15, 2 / 15, 2 / 15],
    [2 / 15, 1 / 15, 2 / 15],
])


def traction_loads(mesh: TetMesh, order: int, vertex_forces: np.ndarray) -> np.ndarray:
    """Consistent element-node loads of a vertex force field read as a traction (module notes).

    Args:
        mesh: the mesh (mm).
        order: 1 (loads on the vertices) or 2 (on vertices and mid-edge nodes).
        vertex_forces: (n, 3) float, N, non-zero on outer-surface vertices only.

    Returns:
        (n_nodes, 3) float, N (node order of ``mesh.points10`` for P2), same total force.
    """
    f = np.asarray(vertex_forces, dtype=np.float64)
    tri = mesh.surface_triangles
    nodes, area, _ = lumped_areas(mesh, tri, 1)
    traction = np.zeros_like(f)
    traction[nodes] = f[nodes] / area[:, None]
    tri_area, _ = triangle_areas(mesh.points, tri)
    shares, targets = (_P1, tri) if order == 1 else (_P2, surface_nodes(mesh, tri, 2))
    loads = np.einsum("ij,tjk->tik", shares, traction[tri]) * tri_area[:, None, None]
    out = np.zeros((mesh.n_vertices if order == 1 else len(mesh.points10), 3))
    np.add.at(out, targets.ravel(), loads.reshape(-1, 3))
    return out
