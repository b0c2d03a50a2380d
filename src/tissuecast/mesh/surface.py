"""Outer-surface geometry: triangle areas and normals, vertex normals, the surface nodes of
quadratic elements, and a lumping of surface areas onto them (elastic supports, tractions).

Node numbering follows the element order: for P1 the nodes are the mesh vertices; for P2
(``TetMesh.points10``) vertex ``i`` is node ``i`` and the midpoint of ``mesh.edges[e]`` is node
``n + e``. Ids are 0-based; lengths in mm, areas in mm^2.

Lumping (:func:`lumped_areas`), two rules:

* ``"row-sum"``: the area of a surface triangle is shared by its nodes as ``integral(N_a) dA``,
  the row sums of the surface mass matrix, which are also the nodal loads of a uniform
  traction: P1, a third to each vertex; P2 (the 6-node triangle), nothing to the corners and a
  third to each mid-edge node. Springs lumped so carry a uniform pressure with a uniform
  displacement, exactly as the distributed spring (``p / k`` everywhere).
* ``"hrz"`` (Hinton, Rock and Zienkiewicz 1976): the diagonal of the surface mass matrix
  rescaled to the triangle's area. P1: a third to each vertex, as above; P2: the consistent
  diagonal ``A/30`` (corners) and ``8A/45`` (mid-edge nodes) rescaled, 1/19 of the area to each
  corner and 16/57 to each mid-edge node, all positive.

In small deformation row-sum springs are the closer to the consistent (non-diagonal) spring
matrix, and HRZ springs dimple a face under uniform pressure at its corners (less as the
elements shrink). But under large deformation the row-sum rule leaves the P2 corner nodes of
a spring-held surface with no spring at all, held by their elements alone: pushed in, such a
node can pop in or out, and the discrete problem stops having a unique solution (two Newton
solvers, ours and CalculiX, end on different branches). HRZ springs hold every surface node,
and the two solvers agree again. For P1 the rules are the same. Measurements of both:
``docs/scenarios.md`` (the elastic support).
"""

from __future__ import annotations

import numpy as np

from .tetmesh import TetMesh

__all__ = ["triangle_areas", "vertex_normals", "edge_ids", "surface_nodes", "lumped_areas", "P2_MIDEDGE_SHARE",
           "P2_HRZ_SHARES", "LUMPING_RULES"]

#: Share of a 6-node triangle's area at each mid-edge node, integral(N_mid) dA / A (the
#: corners' integral(N_corner) dA is 0).
P2_MIDEDGE_SHARE = 1.0 / 3.0
#: HRZ shares of a 6-node triangle's area: (each corner, each mid-edge node); 3 (1/19 + 16/57) = 1.
P2_HRZ_SHARES = (1.0 / 19.0, 16.0 / 57.0)
#: The lumping rules of :func:`lumped_areas`.
LUMPING_RULES = ("row-sum", "hrz")


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas and unit normals of triangles.

    Args:
        points: (n, 3) float, mm.
        triangles: (t, 3) int vertex ids (right-hand order gives the normal).

    Returns:
        ``(areas (t,) mm^2, normals (t, 3) unit)``.
    """
    p = points[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    twice = np.linalg.norm(cross, axis=1)
    return 0.5 * twice, cross / np.maximum(twice, 1e-300)[:, None]


def vertex_normals(mesh: TetMesh) -> np.ndarray:
    """(n, 3) float: area-weighted outward unit normal at each surface vertex, zero elsewhere."""
    tri = mesh.surface_triangles
    area, normal = triangle_areas(mesh.points, tri)
    acc = np.zeros((mesh.n_vertices, 3))
    for k in range(3):
        np.add.at(acc, tri[:, k], area[:, None] * normal)
    length = np.linalg.norm(acc, axis=1)
    return np.where(length[:, None] > 0.0, acc / np.maximum(length, 1e-300)[:, None], 0.0)


def edge_ids(mesh: TetMesh, pairs: np.ndarray) -> np.ndarray:
    """Rows of ``mesh.edges`` for vertex pairs (any order); (k, 2) int -> (k,) int.

    Raises:
        ValueError: a pair is not an edge of the mesh.
    """
    pairs = np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)
    n = mesh.n_vertices
    keys = mesh.edges[:, 0] * n + mesh.edges[:, 1]  # ascending: edges are sorted
    want = pairs[:, 0] * n + pairs[:, 1]
    pos = np.searchsorted(keys, want)
    if np.any(pos >= len(keys)) or np.any(keys[np.minimum(pos, len(keys) - 1)] != want):
        raise ValueError("vertex pairs that are not mesh edges")
    return pos


def surface_nodes(mesh: TetMesh, triangles: np.ndarray, order: int) -> np.ndarray:
    """Element nodes of surface triangles: (t, 3) for P1, (t, 6) for P2 (corners, then the
    mid-edge nodes of edges (0, 1), (1, 2), (2, 0))."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if order == 1:
        return tri
    mids = [mesh.n_vertices + edge_ids(mesh, tri[:, [a, b]]) for a, b in ((0, 1), (1, 2), (2, 0))]
    return np.column_stack([tri] + mids)


def lumped_areas(mesh: TetMesh, triangles: np.ndarray, order: int,
                 rule: str = "row-sum") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface area of triangles lumped onto their nodes (see the module notes).

    Args:
        mesh: the mesh.
        triangles: (t, 3) int, outer-surface triangles (outward order).
        order: element order, 1 or 2.
        rule: ``"row-sum"`` (``integral(N_a) dA``; P2: nothing at the corners) or ``"hrz"``
            (P2: 1/19 of each triangle at each corner, 16/57 at each mid-edge node); the same
            for P1.

    Returns:
        ``(nodes (s,) int sorted, areas (s,) mm^2, normals (s, 3))`` of the nodes with a
        positive share (P2 row-sum: the mid-edge nodes): each node's lumped area and the unit
        mean of its triangles' outward normals weighted by its shares; the areas sum to the
        triangles' total area.
    """
    if rule not in LUMPING_RULES:
        raise ValueError(f"lumping rule must be one of {LUMPING_RULES}, got {rule!r}")
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    area, normal = triangle_areas(mesh.points, tri)
    if order == 1:
        nodes, share = tri, np.full(3, 1.0 / 3.0)
    elif rule == "row-sum":
        nodes, share = surface_nodes(mesh, tri, order)[:, 3:], np.full(3, P2_MIDEDGE_SHARE)
    else:
        nodes, share = surface_nodes(mesh, tri, order), np.repeat(P2_HRZ_SHARES, 3)
    weight = area[:, None] * share[None, :]  # (t, k)
    ids, inverse = np.unique(nodes.ravel(), return_inverse=True)
    lumped = np.bincount(inverse, weights=weight.ravel(), minlength=len(ids))
    acc = np.zeros((len(ids), 3))
    np.add.at(acc, inverse, (weight[:, :, None] * normal[:, None, :]).reshape(-1, 3))
    length = np.linalg.norm(acc, axis=1)
    return ids, lumped, acc / np.maximum(length, 1e-300)[:, None]
