"""Fiducial markers (the paper's revised k-center clustering).

Vertex ids are 0-based everywhere. The paper (Liu et al. 2020, Appendix A1) counts from 1:
its start vertex 97 is our ``start=96`` and its markers [97, 753, 1145, 5, 432] are our
[96, 752, 1144, 4, 431].

The pins (fixed vertices) are one of the scenario's supports and live in
:mod:`tissuecast.scenario.pins`; ``select_fixed_vertices`` and :func:`markers_and_fixed`
stay importable from here.
"""

from __future__ import annotations

import logging

import numpy as np

from .errors import MarkerError
from .mesh.depth import surface_depth
from .mesh.tetmesh import TetMesh
from .mesh.vertex_ids import best_index, validate_vertex_ids

log = logging.getLogger(__name__)

__all__ = [
    "select_markers",
    "revised_k_center",
    "markers_from_config",
    "select_fixed_vertices",  # noqa: F822 - from the scenario on first use (__getattr__)
    "surface_depth",
    "validate_vertex_ids",
    "markers_and_fixed",
    "write_markers_markups",
    "MARKERS_LIST",
    "FIXED_LIST",
]


def __getattr__(name: str):
    # the pins moved to the scenario (one owner of the supports); imported on first use, so
    # that importing the markers does not import the scenario and the FEM
    if name == "select_fixed_vertices":
        from .scenario.pins import select_fixed_vertices

        return select_fixed_vertices
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _points_of(mesh) -> np.ndarray:
    if isinstance(mesh, TetMesh):
        return mesh.points
    pts = np.asarray(mesh, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 1 or not np.isfinite(pts).all():
        raise MarkerError(f"expected a TetMesh or finite (n, 3) points in mm, got an array of shape {pts.shape}")
    return pts


def revised_k_center(points: np.ndarray, count: int = 5, start: int = 96, min_distance: float = 10.0,
                     exclude=None, start_pool=None) -> np.ndarray:
    """The paper's revised k-center clustering on raw points (see :func:`select_markers`).

    Args:
        points: (n, 3) float, mm.
        count: number of centers to return (>= 1).
        start: 0-based id of the first center v0.
        min_distance: d_min in mm; a candidate must be *farther* than this from every
            chosen center.
        exclude: optional 0-based ids never chosen (e.g. vertices the supports hold: their
            displacement is always zero). If ``start`` is among them, the nearest point not
            excluded starts instead (logged).
        start_pool: optional 0-based ids that replacement is taken from (e.g. the surface
            vertices, when ``start`` is one); default (or none of them free) every point.

    Returns:
        (count,) int64 point ids in pick order, ``start`` (or its replacement) first.

    Raises:
        MarkerError: bad ``count``/``start``/``min_distance``/``exclude``, or fewer than
            ``count`` points satisfy the distance rule.
    """
    pts = _points_of(points)
    n = len(pts)
    if isinstance(count, bool) or int(count) != count or count < 1:
        raise MarkerError(f"marker count must be an integer >= 1, got {count!r}")
    if isinstance(start, bool) or int(start) != start or not 0 <= start < n:
        raise MarkerError(
            f"start vertex {start!r} is outside 0..{n - 1}; ids are 0-based (the paper's 1-based 97 is 96)"
        )
    d_min = float(min_distance)
    if not np.isfinite(d_min) or d_min < 0:
        raise MarkerError(f"min_distance must be a finite distance >= 0 mm, got {min_distance!r}")
    count, start = int(count), int(start)
    allowed = np.ones(n, dtype=bool)
    if exclude is not None:
        ex = np.asarray(exclude).ravel()
        if ex.size and not np.issubdtype(ex.dtype, np.integer):
            raise MarkerError(f"excluded vertex ids must be integers, got {ex.dtype} values such as {ex[:3].tolist()}")
        bad = ex[(ex < 0) | (ex >= n)]
        if bad.size:
            raise MarkerError(f"excluded vertex ids {bad[:5].tolist()} are outside 0..{n - 1} (ids are 0-based)")
        allowed[ex] = False
        if not allowed.any():
            raise MarkerError("every vertex is excluded from the markers (all are held by the supports)")
        if not allowed[start]:
            pool = allowed.copy()
            if start_pool is not None:
                pool[np.setdiff1d(np.arange(n), np.asarray(start_pool, dtype=np.int64))] = False
            moved = best_index(-np.linalg.norm(pts - pts[start], axis=1), pool if pool.any() else allowed, largest=True)
            log.info("marker start vertex %d is held by the supports (its displacement is always zero); starting "
                     "from the nearest free vertex %d instead", start, moved)
            start = moved

    centers = [start]
    d = np.linalg.norm(pts - pts[start], axis=1)
    # Welford running statistics of the distances of every point to the chosen centers.
    mean = d.copy()
    m2 = np.zeros(n)
    nearest = d.copy()

    def add(c: int) -> None:
        nonlocal mean, m2, nearest
        centers.append(c)
        d = np.linalg.norm(pts - pts[c], axis=1)
        delta = d - mean
        mean = mean + delta / len(centers)
        m2 = m2 + delta * (d - mean)
        nearest = np.minimum(nearest, d)

    while len(centers) < count:
        # (a) largest average distance; (b) smallest variance of distances, alternating.
        step_a = len(centers) % 2 == 1
        eligible = (nearest > d_min) & allowed
        if not eligible.any():
            raise MarkerError(
                f"only {len(centers)} of {count} markers could be placed: no vertex is farther than "
                f"min_distance={d_min:g} mm from all chosen centers {centers}"
                f"{'' if allowed.all() else f' among the {int(allowed.sum())} not held by the supports'}; "
                "use a smaller min_distance or count"
            )
        if step_a:
            add(best_index(mean, eligible, largest=True))
        else:
            add(best_index(m2 / len(centers), eligible, largest=False))
    return np.asarray(centers, dtype=np.int64)


def select_markers(
    mesh: TetMesh | np.ndarray, count: int = 5, start: int = 96, min_distance: float = 10.0, exclude=None
) -> np.ndarray:
    """Choose fiducial markers by the paper's revised k-center clustering (Appendix A1).

    Centers start as [v0 = ``start``]. Then, alternately until ``count`` centers exist:
    (a) among the vertices whose minimum Euclidean distance to all chosen centers exceeds
    ``min_distance``, add the one with the largest *average* distance to the chosen centers;
    (b) among the vertices satisfying the same rule (re-evaluated with the center just
    added), add the one with the smallest *variance* (population variance) of its distances
    to the chosen centers. The markers are the centers in pick order. Ties (scores equal to
    a relative 1e-12) go to the lowest vertex id. Markers may be interior vertices.

    With the paper's values (``count=5, start=96, min_distance=10``; 1-based start 97) the
    authors' H&N mesh gives [96, 752, 1144, 4, 431] (0-based).

    Args:
        mesh: a TetMesh, or (n, 3) float points in mm.
        count: number of markers n_d (>= 1).
        start: 0-based id of v0.
        min_distance: d_min in mm.
        exclude: optional 0-based vertex ids never chosen: the vertices the supports hold (an
            attached region, pins), whose displacement is always zero; a ``start`` among them is
            replaced by the nearest free vertex (a surface vertex if ``start`` is on the surface).

    Returns:
        (count,) int64, 0-based vertex ids in pick order.

    Raises:
        MarkerError: invalid arguments or too few vertices satisfying the distance rule
            (the message says how many could be placed).
    """
    # a held start vertex is replaced by the nearest free vertex of its kind (a surface start stays on the surface)
    pool = mesh.surface_vertices if isinstance(mesh, TetMesh) and np.isin(start, mesh.surface_vertices) else None
    return revised_k_center(_points_of(mesh), count=count, start=start, min_distance=min_distance, exclude=exclude,
                            start_pool=pool)


def markers_from_config(mesh: TetMesh, config=None, held=None) -> np.ndarray:
    """The fiducial markers a :class:`~tissuecast.config.MarkerConfig` asks for: its ``ids``
    (validated), else :func:`select_markers` (``count``, ``start``, ``min_distance``).

    Args:
        mesh: the tetrahedral mesh.
        config: a MarkerConfig; None = the paper's defaults.
        held: optional 0-based ids of vertices the supports hold (an attached region): chosen
            markers avoid them; user-given ``ids`` there are refused.

    Returns:
        (n_d,) int64 marker vertex ids, 0-based, in pick order.

    Raises:
        MarkerError: bad ``ids``, ``ids`` in the held region, or too few vertices for the rule.
    """
    if config is None:
        from .config import MarkerConfig

        config = MarkerConfig()
    if not config.ids:
        return select_markers(mesh, count=config.count, start=config.start, min_distance=config.min_distance,
                              exclude=held)
    markers = validate_vertex_ids(mesh, config.ids, "markers")
    if held is not None and np.isin(markers, held).any():
        raise MarkerError(f"markers {markers[np.isin(markers, held)].tolist()} lie in the attached region "
                          "(scenario.attached): their displacement is always zero, so they tell the model nothing; "
                          "choose other markers.ids or leave them out to let the k-center rule choose")
    return markers


def markers_and_fixed(mesh: TetMesh, config=None, pins: bool = True, held=None) -> tuple[np.ndarray, np.ndarray]:
    """Markers and pinned (fixed) vertices as a :class:`~tissuecast.config.MarkerConfig` asks:
    :func:`markers_from_config`, then :func:`tissuecast.scenario.pins.pins_from_config`
    (never overlapping the markers).

    Args:
        mesh: the tetrahedral mesh.
        config: a MarkerConfig; None = the paper's defaults.
        pins: False when the body is not held by pins (``scenario.pins = false``): no fixed
            vertices are chosen (so a mesh without interior vertices is fine), and
            ``fixed_ids`` are not used.
        held: optional 0-based ids of vertices other supports hold (an attached region):
            chosen markers avoid them; user-given ``ids`` there are refused.

    Returns:
        ``(markers (n_d,) int64, fixed (k,) int64)``, 0-based ids (``fixed`` empty without pins).
    """
    from .config import MarkerConfig
    from .scenario.pins import pins_from_config

    config = MarkerConfig() if config is None else config
    markers = markers_from_config(mesh, config, held)
    if not pins:
        return markers, np.zeros(0, dtype=np.int64)
    return markers, pins_from_config(mesh, config, markers)


#: Names of the two point lists of a markers markups file (3D Slicer node names).
MARKERS_LIST, FIXED_LIST = "FiducialMarkers", "FixedVertices"


def write_markers_markups(path, mesh: TetMesh, markers, fixed=()):
    """Markers and fixed vertices as two 3D Slicer point lists (``.mrk.json``, LPS mm, the mesh's frame).

    Point labels are ``M0``.. / ``F0``.. in the model's marker order, 0-based as the API, the
    markers CSV's ``order``, OpenIGTLink's ``Marker0``.. and every error message count them;
    descriptions give the 0-based vertex id. Returns the path written.
    """
    from .slicer.markups import MarkupList, write_markups

    lists = [
        MarkupList(name, mesh.points[np.asarray(ids, dtype=np.int64)], tuple(f"{tag}{k}" for k in range(len(ids))),
                   tuple(f"vertex {int(i)} (0-based)" for i in ids))
        for name, tag, ids in ((MARKERS_LIST, "M", markers), (FIXED_LIST, "F", fixed))
    ]
    return write_markups(path, lists, "LPS")
