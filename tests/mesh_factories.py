"""Small meshes with hand-countable figures, shared by the mesh, I/O and CLI tests."""

from __future__ import annotations

import itertools

import numpy as np

from tissuecast.mesh import TetMesh

#: the 8 corners of the unit cube; vertex id = x + 2 y + 4 z
CUBE_POINTS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
#: 5-tet split: the central tet on the odd corners plus four corner tets
CUBE_5_TETS = np.array([[1, 2, 4, 7], [0, 1, 2, 4], [3, 1, 2, 7], [5, 1, 4, 7], [6, 2, 4, 7]])
#: 6-tet (Kuhn) split along the main diagonal 0-7
CUBE_6_TETS = np.array(
    [[0, 1 << a, (1 << a) | (1 << b), 7] for a, b in itertools.permutations(range(3), 2)]
)


def cube(split: int = 5, side: float = 10.0) -> TetMesh:
    """A cube of the given side (mm) split into 5 or 6 tetrahedra."""
    return TetMesh(CUBE_POINTS * side, CUBE_5_TETS if split == 5 else CUBE_6_TETS)


def box_grid(nx: int, ny: int, nz: int, size=(1.0, 1.0, 1.0)) -> TetMesh:
    """A structured box of nx x ny x nz cells, each split into the same 6 Kuhn tetrahedra.

    Args:
        nx, ny, nz: cells per axis.
        size: (3,) cell size in mm.
    """
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    points = g.reshape(-1, 3) * np.asarray(size, dtype=np.float64)
    vid = np.arange(len(points)).reshape(nx + 1, ny + 1, nz + 1)
    corner = vid[:-1, :-1, :-1].ravel()
    offset = {c: vid[c & 1, (c >> 1) & 1, (c >> 2) & 1] - vid[0, 0, 0] for c in range(8)}
    tets = np.stack([np.stack([corner + offset[c] for c in t], axis=1) for t in CUBE_6_TETS], axis=1).reshape(-1, 4)
    return TetMesh(points, tets)


def regular_tet(edge: float = 1.0) -> TetMesh:
    """A regular tetrahedron with the given edge length (mm)."""
    p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    return TetMesh(p * edge / (2.0 * np.sqrt(2.0)), np.array([[0, 1, 2, 3]]))


def box_mesh(nx: int, ny: int, nz: int, size=(10.0, 10.0, 10.0)) -> TetMesh:
    """A box [0, size] split into nx*ny*nz cubes of 6 tetrahedra each (Kuhn split)."""
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, (nx, ny, nz))]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    corner = np.stack([idx[a : a + nx, b : b + ny, c : c + nz].ravel() for a in (0, 1) for b in (0, 1) for c in (0, 1)], 1)
    kuhn = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])
    return TetMesh(grid, corner[:, kuhn].reshape(-1, 4))
