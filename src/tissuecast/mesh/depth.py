"""Depth of vertices below the outer surface: the distance to the nearest point of a surface
triangle (mm), e.g. to place pins deep inside a body (:mod:`tissuecast.scenario.pins`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .tetmesh import TetMesh

__all__ = ["surface_depth", "point_triangle_distance"]


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distances (k,) from points p (k, 3) to triangles (a, b, c) (k, 3 each); Ericson's regions."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        q = a + ab * v_in[:, None] + ac * w_in[:, None]  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [  # (mask, closest point), earlier entries win
        ((d1 <= 0) & (d2 <= 0), a),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[:, None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[:, None]),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[:, None]),
    ]
    done = np.zeros(len(p), dtype=bool)
    for mask, point in regions:
        use = mask & ~done
        q[use] = point[use]
        done |= use
    return np.linalg.norm(p - q, axis=1)




def surface_depth(mesh: TetMesh, ids: np.ndarray | None = None) -> np.ndarray:
    """Distance from vertices to the outer surface (nearest point on a surface triangle).

    Args:
        mesh: the tetrahedral mesh.
        ids: (k,) int vertex ids; default all vertices.

    Returns:
        (k,) float, mm; 0 for surface vertices.
    """
    ids = np.arange(mesh.n_vertices) if ids is None else np.asarray(ids, dtype=np.int64)
    pts = mesh.points[ids]
    tri = mesh.points[mesh.surface_triangles]  # (t, 3, 3)
    cen = tri.mean(axis=1)
    reach = np.linalg.norm(tri - cen[:, None], axis=2).max()
    # The nearest surface vertex bounds the distance; only triangles whose centroid lies
    # within that bound plus the largest centroid-to-corner distance can be closer.
    bound, _ = cKDTree(mesh.points[mesh.surface_vertices]).query(pts)
    cand = cKDTree(cen).query_ball_point(pts, bound + reach + 1e-9)
    lengths = np.fromiter((len(c) for c in cand), dtype=np.int64, count=len(cand))
    rows = np.repeat(np.arange(len(pts)), lengths)
    cols = np.concatenate([np.asarray(c, dtype=np.int64) for c in cand]) if len(cand) else np.zeros(0, np.int64)
    dist = point_triangle_distance(pts[rows], tri[cols, 0], tri[cols, 1], tri[cols, 2])
    depth = np.full(len(pts), np.inf)
    np.minimum.at(depth, rows, dist)
    return np.minimum(depth, bound)
