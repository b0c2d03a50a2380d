"""Shared fixtures of the serve tests: a small box mesh and small fitted models (module-level caches)."""

from __future__ import annotations

import functools

import numpy as np

from tissuecast.mesh import TetMesh
from tissuecast.serve.synthetic import synthetic_model

# the six tetrahedra of a cube around its diagonal corner 0 -> corner 7 (corner = 4 a + 2 b + c)
_CUBE_TETS = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def box_mesh(n: int = 4, size: float = 30.0) -> TetMesh:
    """A cube of side ``size`` mm split into (n-1)^3 cubes of 6 tetrahedra each (n^3 vertices)."""
    g = np.linspace(0.0, size, n)
    points = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    ids = np.arange(n**3).reshape(n, n, n)
    corners = np.stack(
        [ids[a : n - 1 + a, b : n - 1 + b, c : n - 1 + c].ravel() for a in (0, 1) for b in (0, 1) for c in (0, 1)],
        axis=1,
    )
    return TetMesh(points, corners[:, _CUBE_TETS].reshape(-1, 4))


@functools.lru_cache(maxsize=None)
def small_model(kind: str = "single"):
    """A fitted DeformationModel on a 4x4x4 box: 'single', 'ensemble' (3 nets) or 'masked' (marker dropout)."""
    options = {"single": {}, "ensemble": {"ensemble": 3}, "masked": {"marker_dropout": 0.5}}[kind]
    return synthetic_model(box_mesh(), n_samples=60, n_markers=4, epochs=8, hidden=(16, 16), n_components=6, **options)
