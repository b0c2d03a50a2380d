"""Which vertices may carry a fiducial marker: surface only (optical tracking), any vertex
(ultrasound fiducials may sit inside), interior only, further restricted by a user mask.

Vertex ids are 0-based.
"""

from __future__ import annotations

import numpy as np

from ..errors import MarkerError

__all__ = ["REGIONS", "candidate_vertices"]

#: Candidate regions: 'surface' = outer-surface vertices (a tracked pointer or camera must see
#: the marker), 'any' = every vertex (interior fiducials seen by ultrasound), 'interior' =
#: vertices not on the surface.
REGIONS = ("surface", "any", "interior")


def candidate_vertices(mesh, *, region: str = "surface", allowed=None, exclude=()) -> np.ndarray:
    """Vertices a marker may be placed on.

    Args:
        mesh: the :class:`~tissuecast.mesh.TetMesh` (n vertices).
        region: one of :data:`REGIONS`.
        allowed: optional user mask: (n,) bool, or 0-based vertex ids; only these vertices
            (within ``region``) are candidates.
        exclude: 0-based ids never used (e.g. the fixed vertices, which do not move).

    Returns:
        (k,) int64 sorted 0-based candidate ids.

    Raises:
        MarkerError: unknown region, a mask of the wrong shape or with ids outside the mesh,
            or no candidate left.
    """
    n = int(mesh.n_points)
    if region not in REGIONS:
        raise MarkerError(f"unknown candidate region {region!r}; use one of {', '.join(REGIONS)}")
    keep = np.zeros(n, dtype=bool)
    if region == "any":
        keep[:] = True
    else:
        keep[np.asarray(mesh.surface_vertices, dtype=np.int64)] = True
        if region == "interior":
            keep = ~keep
    if allowed is not None:
        a = np.asarray(allowed)
        if a.dtype == bool:
            if a.shape != (n,):
                raise MarkerError(f"a candidate mask of booleans must have one entry per vertex ({n}), got shape {a.shape}")
            keep &= a
        else:
            ids = a.astype(np.int64).ravel()
            if ids.size and (ids.min() < 0 or ids.max() >= n):
                raise MarkerError(f"allowed vertex ids must be 0-based in [0, {n}), got ids from {ids.min()} to {ids.max()}")
            mask = np.zeros(n, dtype=bool)
            mask[ids] = True
            keep &= mask
    ex = np.asarray(exclude, dtype=np.int64).ravel()
    keep[ex[(ex >= 0) & (ex < n)]] = False
    out = np.flatnonzero(keep).astype(np.int64)
    if out.size == 0:
        raise MarkerError(f"no candidate vertex is left (region {region!r}, {0 if allowed is None else np.size(allowed)} "
                          "allowed entries, fixed vertices excluded); widen the region or the mask")
    return out
