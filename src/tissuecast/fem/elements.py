"""Tetrahedral Lagrange elements: shape functions, quadrature rules and reference gradients.

Two elements are provided, both isoparametric on the reference tetrahedron
``{xi, eta, zeta >= 0, xi + eta + zeta <= 1}`` (volume 1/6) with barycentric coordinates
``L0 = 1 - xi - eta - zeta, L1 = xi, L2 = eta, L3 = zeta``:

* P1, 4 nodes (C3D4): ``N_i = L_i``.
* P2, 10 nodes (C3D10 / VTK ``QUADRATIC_TETRA`` order): corner ``N_i = L_i (2 L_i - 1)``,
  mid-edge ``N = 4 L_a L_b`` for the edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3) --
  the order of :data:`tissuecast.mesh.TET_EDGES` and of ``TetMesh.tets10``.

Quadrature: P1 uses the 1-point centroid rule (exact for its constant strain), P2 the
4-point degree-2 rule that C3D10 uses. A positive-weight 14-point degree-5 rule is
available for validation (``rule="high"``).

The geometry is always straight-sided (mid-edge nodes at the edge midpoints), so the
Jacobian is constant per element and the reference gradients are computed once per mesh by
:func:`reference_gradients`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MeshError
from ..mesh.tetmesh import TET_EDGES, TetMesh

__all__ = [
    "QuadratureRule",
    "quadrature",
    "shape_functions",
    "shape_gradients",
    "ElementGeometry",
    "reference_gradients",
    "element_nodes",
]


@dataclass(frozen=True)
class QuadratureRule:
    """Quadrature on the reference tetrahedron.

    Attributes:
        points: (q, 3) float, reference coordinates (xi, eta, zeta).
        weights: (q,) float, summing to 1/6 (the reference volume).
        degree: polynomial degree integrated exactly.
    """

    points: np.ndarray
    weights: np.ndarray
    degree: int


def _perm_points(base: tuple[float, float, float, float]) -> np.ndarray:
    """Distinct permutations of barycentric coordinates, returned as (k, 3) (L1, L2, L3)."""
    import itertools

    perms = sorted(set(itertools.permutations(base)))
    return np.array([p[1:] for p in perms], dtype=np.float64)


def quadrature(order: int, rule: str = "default") -> QuadratureRule:
    """The quadrature rule for an element order.

    Args:
        order: element order, 1 or 2.
        rule: ``"default"`` (P1: 1 point, degree 1; P2: 4 points, degree 2, as C3D10) or
            ``"high"`` (14 points, degree 5, positive weights).
    """
    if rule == "high":
        a, b = 0.0455037041256496, 0.4544962958743504
        c, d = 0.0927352503108912, 0.3108859192633006
        pts = np.vstack(
            [
                _perm_points((a, a, b, b)),
                _perm_points((c, c, c, 1 - 3 * c)),
                _perm_points((d, d, d, 1 - 3 * d)),
            ]
        )
        w = np.r_[np.full(6, 0.007091003462846911), np.full(4, 0.01224884051939366), np.full(4, 0.01878132095300264)]
        return QuadratureRule(pts, w / w.sum() / 6.0, 5)
    if rule != "default":
        raise ValueError(f"unknown quadrature rule {rule!r}; use 'default' or 'high'")
    if order == 1:
        return QuadratureRule(np.full((1, 3), 0.25), np.array([1.0 / 6.0]), 1)
    if order == 2:
        a, b = 0.5854101966249685, 0.1381966011250105
        return QuadratureRule(_perm_points((a, b, b, b)), np.full(4, 1.0 / 24.0), 2)
    raise ValueError(f"element order must be 1 or 2, got {order}")


def _barycentric(points: np.ndarray) -> np.ndarray:
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    return np.column_stack([1.0 - points.sum(axis=1), points])


def shape_functions(order: int, points: np.ndarray) -> np.ndarray:
    """Shape function values.

    Args:
        order: 1 (4 nodes) or 2 (10 nodes).
        points: (q, 3) float, reference coordinates.

    Returns:
        (q, nn) float, ``N[q, a]``.
    """
    lam = _barycentric(points)
    if order == 1:
        return lam
    if order == 2:
        corner = lam * (2.0 * lam - 1.0)
        mid = 4.0 * lam[:, TET_EDGES[:, 0]] * lam[:, TET_EDGES[:, 1]]
        return np.hstack([corner, mid])
    raise ValueError(f"element order must be 1 or 2, got {order}")


def shape_gradients(order: int, points: np.ndarray) -> np.ndarray:
    """Shape function gradients with respect to the reference coordinates.

    Args:
        order: 1 or 2.
        points: (q, 3) float, reference coordinates.

    Returns:
        (q, nn, 3) float, ``dN[q, a, j] = dN_a / dxi_j``.
    """
    lam = _barycentric(points)
    q = len(lam)
    dlam = np.vstack([-np.ones(3), np.eye(3)])  # (4, 3): d L_i / d xi_j
    if order == 1:
        return np.broadcast_to(dlam, (q, 4, 3)).copy()
    if order == 2:
        corner = (4.0 * lam - 1.0)[:, :, None] * dlam[None]
        a, b = TET_EDGES[:, 0], TET_EDGES[:, 1]
        mid = 4.0 * (lam[:, a, None] * dlam[None, b] + lam[:, b, None] * dlam[None, a])
        return np.concatenate([corner, mid], axis=1)
    raise ValueError(f"element order must be 1 or 2, got {order}")


def element_nodes(mesh: TetMesh, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Node coordinates and element connectivity for an element order.

    Returns:
        ``(nodes (n_nodes, 3) float mm, connectivity (m, nn) int)``; for order 2 the nodes
        are ``mesh.points10`` (vertices first) and the connectivity ``mesh.tets10``.
    """
    if order == 1:
        return mesh.points, mesh.tets
    if order == 2:
        return mesh.points10, mesh.tets10
    raise ValueError(f"element order must be 1 or 2, got {order}")


@dataclass(frozen=True)
class ElementGeometry:
    """Reference-configuration gradients of all elements, computed once per mesh.

    Attributes:
        grad: (m, q, nn, 3) float, 1/mm: ``dN_a/dX_J`` at each quadrature point.
        weight: (m, q) float, mm^3: quadrature weight times ``det(dX/dxi)``.
        shape: (q, nn) float, shape function values at the quadrature points.
        rule: the quadrature rule used.
    """

    grad: np.ndarray
    weight: np.ndarray
    shape: np.ndarray
    rule: QuadratureRule


def reference_gradients(nodes: np.ndarray, connectivity: np.ndarray, order: int, rule: str = "default") -> ElementGeometry:
    """Gradients ``dN/dX`` and weights ``w det J`` of every element, vectorised.

    Args:
        nodes: (n_nodes, 3) float, mm, reference coordinates.
        connectivity: (m, nn) int, node ids per element (nn = 4 or 10).
        order: 1 or 2.
        rule: quadrature rule name (see :func:`quadrature`).

    Raises:
        MeshError: an element has a non-positive Jacobian at a quadrature point.
    """
    qr = quadrature(order, rule)
    dn = shape_gradients(order, qr.points)  # (q, nn, 3)
    x = nodes[connectivity]  # (m, nn, 3)
    jac = np.einsum("mai,qaj->mqij", x, dn)  # dX_i / dxi_j
    det = np.linalg.det(jac)
    if np.any(det <= 0.0):
        j = int(np.flatnonzero((det <= 0.0).any(axis=1))[0])
        raise MeshError(f"element {j} has a non-positive Jacobian; the mesh is inverted or degenerate there")
    inv = np.linalg.inv(jac)  # dxi_j / dX_k
    grad = np.einsum("qaj,mqjk->mqak", dn, inv)
    weight = det * qr.weights[None, :]
    return ElementGeometry(grad=np.ascontiguousarray(grad), weight=weight, shape=shape_functions(order, qr.points), rule=qr)
