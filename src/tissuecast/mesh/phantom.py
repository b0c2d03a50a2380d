"""The built-in phantom: an irregular, tumour-like solid of the paper's size.

The paper's head-and-neck tumour mesh may not be redistributed, so tissuecast ships its own
stand-in: an ellipsoid-like body (about 22 x 39 x 70 mm) with a few smooth lobes, a gentle
bend and low-order harmonic ripples, so that it has no symmetry. Its closed surface is
defined analytically here (:func:`phantom_surface`); ``scripts/make_phantom.py`` fills it
with tetrahedra using gmsh and stores the result in ``tissuecast/data/phantom.npz``.
:func:`phantom` only loads that file, so the mesh is bit-identical on every machine.
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources

import numpy as np

from .tetmesh import TetMesh

__all__ = ["phantom", "phantom_surface", "icosphere", "PHANTOM_EXTENT", "PHANTOM_MESH_SIZE", "PHANTOM_INTERIOR_SIZE"]

#: (3,) mm: side lengths of the phantom's bounding box before meshing (x, y, z).
PHANTOM_EXTENT = (22.0, 39.0, 70.0)
#: target edge lengths (mm) on the surface and inside, used by scripts/make_phantom.py.
PHANTOM_MESH_SIZE = 4.6
PHANTOM_INTERIOR_SIZE = 2.8

# Smooth lobes: (direction on the unit sphere, height, angular width). Fixed numbers chosen
# by hand so that no two lobes mirror each other.
_LOBES = (
    ((0.55, 0.62, 0.56), 0.24, 0.42),
    ((-0.70, 0.20, -0.68), 0.20, 0.38),
    ((0.10, -0.85, 0.52), 0.18, 0.33),
    ((-0.30, -0.40, -0.87), 0.16, 0.45),
    ((0.90, -0.30, -0.31), 0.15, 0.30),
    ((-0.45, 0.80, 0.10), 0.12, 0.32),
)


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere triangulated by repeatedly splitting an icosahedron's faces in four.

    Args:
        subdivisions: number of splits (0 = the icosahedron, 12 vertices).

    Returns:
        (points (10 * 4**s + 2, 3) float on the unit sphere, triangles (20 * 4**s, 3) int),
        triangles counter-clockwise seen from outside.
    """
    t = (1.0 + 5.0**0.5) / 2.0
    pts = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64
    )
    tri = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64
    )
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    for _ in range(subdivisions):
        e = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, inv = np.unique(e, axis=0, return_inverse=True)
        mid = pts[edges].sum(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(pts) + inv.reshape(-1, 3)  # midpoints of edges (0,1), (1,2), (2,0)
        pts = np.vstack([pts, mid])
        a, b, c = tri.T
        tri = np.vstack(
            [np.c_[a, m[:, 0], m[:, 2]], np.c_[b, m[:, 1], m[:, 0]], np.c_[c, m[:, 2], m[:, 1]], m]
        )
    return pts, tri


def phantom_surface(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """The phantom's closed outer surface, finely triangulated.

    Each direction ``d`` of the unit sphere is moved to ``r(d) * d`` with
    ``r = 1 + lobes + ripples`` (always positive, so the body is star-shaped and the
    surface cannot intersect itself), stretched to an ellipsoid, bent along its long axis
    by a shear (a bijection, so still embedded), then scaled to exactly
    :data:`PHANTOM_EXTENT`, with the lower corner of the bounding box at the origin.

    Args:
        subdivisions: icosphere refinement (5 gives 10242 vertices).

    Returns:
        (points (n, 3) float mm, triangles (k, 3) int, outward).
    """
    d, tri = icosphere(subdivisions)
    r = np.ones(len(d))
    for centre, height, width in _LOBES:
        c = np.asarray(centre) / np.linalg.norm(centre)
        r += height * np.exp((d @ c - 1.0) / width**2)
    x, y, z = d.T
    r += 0.05 * x * y + 0.04 * y * z**2 - 0.035 * x**3 + 0.03 * np.sin(2.0 * z + 0.7) * y
    p = r[:, None] * d * np.array([1.0, 1.75, 3.1])
    p[:, 0] += 0.12 * p[:, 2] ** 2 / 3.1 - 0.06 * p[:, 2]  # bend in x along z
    p[:, 1] += 0.05 * p[:, 2] ** 2 / 3.1  # and a little in y
    p -= p.min(axis=0)
    p *= np.asarray(PHANTOM_EXTENT) / p.max(axis=0)
    return p, tri


@lru_cache(maxsize=1)
def _load() -> TetMesh:
    with resources.files("tissuecast").joinpath("data").joinpath("phantom.npz").open("rb") as fh:
        data = np.load(fh, allow_pickle=False)
        return TetMesh(data["points"], data["tets"])


def phantom() -> TetMesh:
    """The built-in tumour-like phantom (coordinates in mm, 0-based ids).

    About 22 x 39 x 70 mm, 1100-1200 vertices; identical on every machine (it is loaded
    from the packaged file ``tissuecast/data/phantom.npz``, made by
    ``scripts/make_phantom.py``). Vertex 96 is the default marker start vertex.

    Returns:
        The phantom mesh (a shared immutable object).
    """
    return _load()
