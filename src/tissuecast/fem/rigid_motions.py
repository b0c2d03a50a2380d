"""Which rigid-body motions a set of supports leaves free.

A body must be held against all six rigid-body motions (three translations, three rotations)
for its equilibrium to be unique: by vertices fixed in all components (pins, an attached
region), by springs to ground (an elastic support), or both. :func:`free_rigid_motions` measures
the supports' stiffness along each rigid motion (a 6x6 Gram matrix of the motions at the held
nodes, plus the springs' stiffness along them) and returns the motions it does not resist.
"""

from __future__ import annotations

import numpy as np

from .springs import NodalSprings

__all__ = ["free_rigid_motions", "RIGID_MOTION_RTOL"]

#: A rigid-body motion counts as free when the supports' stiffness along it is below this
#: share of the stiffest one (dimensionless, rotations measured at the body's size).
RIGID_MOTION_RTOL = 1e-9


def free_rigid_motions(points: np.ndarray, held: np.ndarray, springs: NodalSprings | None = None) -> np.ndarray:
    """Rigid-body motions the supports leave free.

    Args:
        points: (n_nodes, 3) float, mm, node coordinates.
        held: (h,) int nodes fixed in all components.
        springs: nodal springs to ground, or None.

    Returns:
        (f, 6) float: each row a free motion ``(translation (3,), rotation (3,) rad per body
        size)`` about the nodes' centroid; no rows when every rigid motion is resisted.
    """
    c = points.mean(axis=0)
    size = max(float(np.ptp(points, axis=0).max()), 1e-300)

    def modes(ids):
        x = (points[ids] - c) / size
        r = np.zeros((len(ids), 3, 6))
        r[:, :, :3] = np.eye(3)
        r[:, 0, 4], r[:, 0, 5] = x[:, 2], -x[:, 1]  # omega x x
        r[:, 1, 3], r[:, 1, 5] = -x[:, 2], x[:, 0]
        r[:, 2, 3], r[:, 2, 4] = x[:, 1], -x[:, 0]
        return r

    g = np.zeros((6, 6))
    held = np.asarray(held, dtype=np.int64)
    if held.size:
        r = modes(held)
        g += np.einsum("aik,ail->kl", r, r)
    if springs is not None and len(springs):
        r = modes(springs.nodes)
        k = springs.stiffness / max(float(np.abs(springs.stiffness).max()), 1e-300)
        g += np.einsum("aik,aij,ajl->kl", r, k, r)
    lam, vec = np.linalg.eigh(g)
    return vec[:, lam <= RIGID_MOTION_RTOL * max(float(lam.max()), 1e-300)].T
