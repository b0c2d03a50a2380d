"""Change of gravity between imaging and surgery, as consistent nodal body loads.

The reference mesh was imaged under gravity along ``d_imaging``; during surgery gravity acts
along ``d_surgery``. Relative to the imaged (equilibrium) shape the tissue feels the body
force per unit volume

    b = rho |g| (d_surgery - d_imaging)   N/mm^3,

with the density rho in t/mm^3 (1000 kg/m^3 = 1e-9 t/mm^3) and |g| = 9810 mm/s^2; it is a
dead load (mass is conserved, so each element's weight does not change as it deforms).
``d_surgery`` is drawn per sample uniformly on the cap of directions within ``cone_angle`` of
a nominal one.

Consistent nodal loads (:func:`body_loads`): node ``a`` of an element of volume V receives
``b * integral(N_a) dV``: for the 10-node tetrahedron (C3D10) ``-V/20`` at each corner and
``+V/5`` at each mid-edge node (the corner share is negative: the quadratic shape functions
dip below zero), for the 4-node one ``V/4``. CalculiX's ``*DLOAD, GRAV`` integrates the same
functions exactly, so both programs load the mesh identically.
"""

from __future__ import annotations

import numpy as np

from ..mesh.tetmesh import TetMesh

__all__ = ["body_loads", "cone_direction", "gravity_body_force", "P2_CORNER_VOLUME_SHARE", "P2_MIDEDGE_VOLUME_SHARE"]

#: integral of a corner shape function of the 10-node tetrahedron over it, per unit volume
P2_CORNER_VOLUME_SHARE = -1.0 / 20.0
#: ... and of a mid-edge shape function (4 x (-1/20) + 6 x 1/5 = 1)
P2_MIDEDGE_VOLUME_SHARE = 1.0 / 5.0


def body_loads(mesh: TetMesh, order: int, body_force: np.ndarray, element_scale: np.ndarray | None = None) -> np.ndarray:
    """Consistent nodal loads of a uniform body force.

    Args:
        mesh: the mesh (mm).
        order: 1 (loads on the vertices) or 2 (on the vertices and mid-edge nodes).
        body_force: (3,) float, N/mm^3.
        element_scale: optional (m,) factor per element (e.g. a density ratio); default 1.

    Returns:
        (n_nodes, 3) float, N: ``(n, 3)`` for P1, ``(n + n_edges, 3)`` for P2 (node order of
        ``mesh.points10``). They sum to ``body_force * volume``.
    """
    b = np.asarray(body_force, dtype=np.float64).reshape(3)
    vol = mesh.tet_volumes if element_scale is None else mesh.tet_volumes * np.asarray(element_scale, dtype=np.float64)
    if order == 1:
        conn, share = mesh.tets, np.full(4, 0.25)
        n_nodes = mesh.n_vertices
    else:
        conn = mesh.tets10
        share = np.r_[np.full(4, P2_CORNER_VOLUME_SHARE), np.full(6, P2_MIDEDGE_VOLUME_SHARE)]
        n_nodes = len(mesh.points10)
    weight = np.bincount(conn.ravel(), weights=(vol[:, None] * share[None, :]).ravel(), minlength=n_nodes)
    return weight[:, None] * b[None, :]


def cone_direction(rng: np.random.Generator, axis, angle_degrees: float) -> np.ndarray:
    """A unit vector drawn uniformly on the spherical cap within ``angle_degrees`` of ``axis``.

    Draws, in order: ``u = rng.random()`` (cos of the polar angle uniform in [cos a, 1]) and
    ``phi = 2 pi rng.random()`` (azimuth), so the draws are reproducible from the generator.

    Args:
        rng: numpy generator.
        axis: (3,) float, the cap's axis (any length > 0).
        angle_degrees: half-angle of the cap, 0..180.

    Returns:
        (3,) float, unit length.
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    cos_t = 1.0 - rng.random() * (1.0 - np.cos(np.radians(angle_degrees)))
    phi = 2.0 * np.pi * rng.random()
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    sin_t = np.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    d = cos_t * a + sin_t * (np.cos(phi) * e1 + np.sin(phi) * e2)
    return d / np.linalg.norm(d)


def gravity_body_force(density: float, acceleration: float, imaging_direction, surgery_direction) -> np.ndarray:
    """``rho |g| (d_surgery - d_imaging)``, (3,) N/mm^3 (directions are normalised first).

    Args:
        density: t/mm^3.
        acceleration: |g|, mm/s^2.
        imaging_direction, surgery_direction: (3,) gravity directions.
    """
    di = np.asarray(imaging_direction, dtype=np.float64)
    ds = np.asarray(surgery_direction, dtype=np.float64)
    return float(density) * float(acceleration) * (ds / np.linalg.norm(ds) - di / np.linalg.norm(di))
