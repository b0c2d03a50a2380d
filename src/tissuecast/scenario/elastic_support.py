"""Elastic support: distributed linear springs tying a surface region to fixed surroundings.

A surface region with stiffness per unit area ``k_n`` normal to it and ``k_t`` along it
(N/mm^3 = MPa/mm) becomes one linear spring per surface node: node ``a`` with lumped area
``A_a`` (P1: a third of each triangle at each vertex; P2 by default HRZ lumping, 1/19 of each
triangle at each corner and 16/57 at each mid-edge node, or ``integral(N_a) dA``, none at the
corners; :func:`~tissuecast.mesh.surface.lumped_areas` says why HRZ: with no spring at the
corners a strongly compressed P2 surface has no unique solution) and unit normal ``n_a`` gets
the 3x3 stiffness

    K_a = A_a (k_t I + (k_n - k_t) n_a n_a^T)   N/mm,

so that its spring force is ``-K_a u_a`` (energy ``u_a . K_a u_a / 2``). The springs act in
the reference directions (a dead, linear support, whatever the deformation), which is also
what CalculiX's SPRING1 elements do (with ``*SPRING, ORIENTATION`` for ``k_n != k_t``), so
the deck written from these tensors describes the same discrete problem.

What the stiffness means: surroundings of modulus E over a length L push back about
``k = E / L``: the default 0.0021 N/mm^3 is tissue of 0.021 MPa (like the body's) over
10 mm. A uniform pressure p on a supported face then moves it by ``p / k`` (0.001 MPa, about
the weight of 10 cm of tissue, moves it 0.48 mm); k_t = 0 lets the surface slide freely.
"""

from __future__ import annotations

import numpy as np

from ..fem.springs import NodalSprings
from ..mesh.tetmesh import TetMesh
from ..mesh.surface import lumped_areas

__all__ = ["surface_springs", "region_triangles"]


def region_triangles(mesh: TetMesh, vertices: np.ndarray) -> np.ndarray:
    """(t, 3) the outer-surface triangles whose three vertices all lie in ``vertices``."""
    tri = mesh.surface_triangles
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[np.asarray(vertices, dtype=np.int64)] = True
    return tri[inside[tri].all(axis=1)]


def surface_springs(mesh: TetMesh, vertices: np.ndarray, order: int, normal_stiffness: float,
                    tangential_stiffness: float, lumping: str = "hrz") -> NodalSprings:
    """Springs of a surface region, lumped to its nodes by area (module notes).

    Args:
        mesh: the mesh (mm).
        vertices: (k,) int surface vertex ids of the region; its triangles are those with
            all three vertices in it.
        order: element order, 1 (vertices) or 2 (vertices and mid-edge nodes).
        normal_stiffness: k_n, N/mm^3.
        tangential_stiffness: k_t, N/mm^3.
        lumping: ``"hrz"`` or ``"row-sum"`` (:func:`~tissuecast.mesh.surface.lumped_areas`;
            the same for P1).

    Returns:
        The nodal springs (empty when the region holds no whole triangle).
    """
    nodes, area, normal = lumped_areas(mesh, region_triangles(mesh, vertices), order, lumping)
    kt = float(tangential_stiffness)
    kn = float(normal_stiffness)
    stiffness = area[:, None, None] * (kt * np.eye(3)[None] + (kn - kt) * normal[:, :, None] * normal[:, None, :])
    return NodalSprings(nodes, stiffness)
