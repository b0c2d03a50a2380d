"""Vertex ids chosen or given by a user: validation (0-based, in range, unique, disjoint) and
the choice of the best-scoring vertex with a fixed tie rule (markers and pins alike)."""

from __future__ import annotations

import numpy as np

from ..errors import MarkerError
from .tetmesh import TetMesh

__all__ = ["validate_vertex_ids", "best_index", "TIE_RTOL"]

#: Scores closer than this (relative to the best score) count as ties -> lowest index.
TIE_RTOL = 1e-12


def best_index(score: np.ndarray, eligible: np.ndarray, largest: bool) -> int:
    """Index of the best eligible score; near-ties (rtol 1e-12) go to the lowest index."""
    s = np.where(eligible, score if largest else -score, -np.inf)
    best = s.max()
    tol = TIE_RTOL * max(abs(best), 1.0)
    return int(np.flatnonzero(s >= best - tol)[0])



def validate_vertex_ids(mesh: TetMesh, ids, what: str = "vertex ids", *, other=None,
                        other_what: str = "markers", allow_empty: bool = False) -> np.ndarray:
    """Check user-given vertex ids (markers or fixed vertices) and return them as int64.

    Args:
        mesh: the mesh the ids refer to.
        ids: sequence of 0-based vertex ids.
        what: what the ids are, for messages (e.g. ``"fixed vertices"``).
        other: optional ids that must not overlap ``ids`` (e.g. the markers).
        other_what: what ``other`` is, for messages.
        allow_empty: accept an empty sequence.

    Returns:
        (k,) int64 copy of ``ids``, order kept.

    Raises:
        MarkerError: not integers, not 1-D, empty, out of range, repeated, or overlapping
            ``other``.
    """
    arr = np.asarray(ids)
    if arr.size == 0:
        if allow_empty:
            return np.zeros(0, dtype=np.int64)
        raise MarkerError(f"no {what} given; give at least one 0-based vertex id")
    if arr.ndim != 1:
        raise MarkerError(f"{what} must be a flat list of vertex ids, got an array of shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        if not np.issubdtype(arr.dtype, np.number) or not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise MarkerError(f"{what} must be integer vertex ids, got {arr.tolist()}")
    arr = arr.astype(np.int64)
    n = mesh.n_vertices
    bad = arr[(arr < 0) | (arr >= n)]
    if bad.size:
        raise MarkerError(
            f"{what} {bad.tolist()} are outside 0..{n - 1}; ids are 0-based (subtract 1 from "
            "1-based ids of the paper, Abaqus or CalculiX)"
        )
    uniq, cnt = np.unique(arr, return_counts=True)
    if (cnt > 1).any():
        raise MarkerError(f"{what} repeat vertex ids {uniq[cnt > 1].tolist()}; give each vertex once")
    if other is not None:
        both = np.intersect1d(arr, np.asarray(other, dtype=np.int64))
        if both.size:
            raise MarkerError(
                f"vertices {both.tolist()} are both {what} and {other_what}; a vertex cannot be both, "
                "choose different ids"
            )
    return arr
