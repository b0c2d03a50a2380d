"""Points inside a tetrahedral mesh: the tetrahedron holding each, and its barycentric weights.

A vertex field (n, 3) is linear (P1) in every tetrahedron, so its value at a point ``p``
inside tetrahedron ``t`` with barycentric coordinates ``w`` (4,) is
``sum_j w_j * u[tets[t, j]]``: :func:`interpolate` applies that to one field or a batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import MeshError
from .tetmesh import TetMesh

__all__ = ["PointLocation", "locate_points", "contains_points", "interpolate", "barycentric", "CANDIDATES", "TOLERANCE"]

#: Tetrahedra tried per point first (nearest centroids); points not inside any of them are
#: checked against every tetrahedron.
CANDIDATES = 24
#: A point belongs to a tetrahedron when its smallest barycentric coordinate is above -TOLERANCE
#: (points on a shared face or on the outer surface, up to rounding).
TOLERANCE = 1e-9


@dataclass(frozen=True, eq=False)
class PointLocation:
    """Where points lie in a mesh.

    Attributes:
        tets: (k,) int, 0-based id of the tetrahedron holding each point.
        weights: (k, 4) float, barycentric coordinates in that tetrahedron (sum 1, each >= 0
            up to :data:`TOLERANCE`).
    """

    tets: np.ndarray
    weights: np.ndarray


def barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points in tetrahedra.

    Args:
        corners: (k, 4, 3) float, mm: each point's tetrahedron.
        points: (k, 3) float, mm.

    Returns:
        (k, 4) float; all >= 0 for a point inside its tetrahedron.
    """
    corners = np.asarray(corners, dtype=np.float64)
    edges = (corners[:, 1:] - corners[:, :1]).transpose(0, 2, 1)  # (k, 3, 3): columns x1-x0, x2-x0, x3-x0
    rhs = (np.asarray(points, dtype=np.float64) - corners[:, 0])[..., None]
    w123 = np.linalg.solve(edges, rhs)[..., 0]
    return np.concatenate([1.0 - w123.sum(axis=1, keepdims=True), w123], axis=1)


def _best(mesh: TetMesh, points: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Among (k, c) candidate tetrahedra per point, the one where the point lies deepest inside."""
    k, c = candidates.shape
    w = barycentric(mesh.points[mesh.tets[candidates.ravel()]], np.repeat(points, c, axis=0)).reshape(k, c, 4)
    pick = np.argmax(w.min(axis=2), axis=1)
    rows = np.arange(k)
    return candidates[rows, pick], w[rows, pick]


def _candidates(mesh: TetMesh, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedron and weights of each point among its :data:`CANDIDATES` nearest tetrahedra."""
    centroids = mesh.points[mesh.tets].mean(axis=1)
    c = min(CANDIDATES, mesh.n_tets)
    _, near = cKDTree(centroids).query(p, k=c)
    return _best(mesh, p, np.asarray(near, dtype=np.int64).reshape(len(p), c))


def _checked(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
        raise MeshError(f"points to locate must be finite (k, 3) mm, got shape {p.shape}")
    return p


def locate_points(mesh: TetMesh, points) -> PointLocation:
    """The tetrahedron holding each point and the point's barycentric coordinates in it.

    Args:
        mesh: the tetrahedral mesh (mm).
        points: (k, 3) float, mm, in the mesh's frame.

    Returns:
        The :class:`PointLocation` of the k points.

    Raises:
        MeshError: points of the wrong shape or not finite, or a point outside the mesh (the
            message gives its index, position and distance to the nearest vertex).
    """
    p = _checked(points)
    if len(p) == 0:
        return PointLocation(np.zeros(0, dtype=np.int64), np.zeros((0, 4)))
    tets, w = _candidates(mesh, p)
    for i in np.flatnonzero(w.min(axis=1) < -TOLERANCE):  # rare: not in its nearest tetrahedra; try them all
        t, wi = _best(mesh, p[i:i + 1], np.arange(mesh.n_tets)[None])
        tets[i], w[i] = t[0], wi[0]
    outside = np.flatnonzero(w.min(axis=1) < -TOLERANCE)
    if outside.size:
        i = int(outside[0])
        gap, _ = cKDTree(mesh.points).query(p[i])
        raise MeshError(f"{outside.size} of {len(p)} points lie outside the mesh, the first (index {i}) at "
                        f"{np.round(p[i], 3).tolist()} mm, {gap:.3g} mm from the nearest vertex; give points inside "
                        "the tissue, in the mesh's frame (LPS mm)")
    return PointLocation(tets.astype(np.int64), w)


def contains_points(mesh: TetMesh, points, chunk: int = 20000) -> np.ndarray:
    """(k,) bool: which points lie inside the mesh (in one of their :data:`CANDIDATES` nearest
    tetrahedra; for many points, e.g. a label map's voxel centres)."""
    p = _checked(points)
    lo, hi = mesh.bounding_box
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    idx = np.flatnonzero(inside)
    for s in range(0, idx.size, chunk):
        part = idx[s:s + chunk]
        inside[part] = _candidates(mesh, p[part])[1].min(axis=1) >= -TOLERANCE
    return inside


def interpolate(mesh: TetMesh, location: PointLocation, field) -> np.ndarray:
    """A vertex field at located points, linear in each tetrahedron (P1).

    Args:
        mesh: the mesh the points were located in.
        location: from :func:`locate_points`.
        field: (n, d) or (B, n, d) float vertex values (e.g. displacements in mm).

    Returns:
        (k, d) or (B, k, d) float64.
    """
    f = np.asarray(field, dtype=np.float64)
    corners = mesh.tets[location.tets]  # (k, 4)
    return np.einsum("kj,...kjd->...kd", location.weights, f[..., corners, :])
