"""Fiducial markers (the paper's revised k-center clustering) and fixed vertices.

Vertex ids are 0-based everywhere. The paper (Liu et al. 2020, Appendix A1) counts from 1:
its start vertex 97 is our ``start=96`` and its markers [97, 753, 1145, 5, 432] are our
[96, 752, 1144, 4, 431].
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from .config import FIXED_RULES
from .errors import MarkerError
from .mesh.tetmesh import TetMesh

log = logging.getLogger(__name__)

__all__ = [
    "select_markers",
    "revised_k_center",
    "select_fixed_vertices",
    "surface_depth",
    "validate_vertex_ids",
    "markers_and_fixed",
]

# Scores closer than this (relative to the best score) count as ties -> lowest vertex id.
_TIE_RTOL = 1e-12


def _points_of(mesh) -> np.ndarray:
    if isinstance(mesh, TetMesh):
        return mesh.points
    pts = np.asarray(mesh, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 1 or not np.isfinite(pts).all():
        raise MarkerError(f"expected a TetMesh or finite (n, 3) points in mm, got an array of shape {pts.shape}")
    return pts


def _pick(score: np.ndarray, eligible: np.ndarray, largest: bool) -> int:
    """Index of the best eligible score; near-ties (rtol 1e-12) go to the lowest index."""
    s = np.where(eligible, score if largest else -score, -np.inf)
    best = s.max()
    tol = _TIE_RTOL * max(abs(best), 1.0)
    return int(np.flatnonzero(s >= best - tol)[0])


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
            moved = _pick(-np.linalg.norm(pts - pts[start], axis=1), pool if pool.any() else allowed, largest=True)
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
            add(_pick(mean, eligible, largest=True))
        else:
            add(_pick(m2 / len(centers), eligible, largest=False))
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


# ----------------------------------------------------------------- fixed vertices
def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
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
    dist = _point_triangle_distance(pts[rows], tri[cols, 0], tri[cols, 1], tri[cols, 2])
    depth = np.full(len(pts), np.inf)
    np.minimum.at(depth, rows, dist)
    return np.minimum(depth, bound)


def select_fixed_vertices(
    mesh: TetMesh,
    count: int = 3,
    exclude=(),
    min_depth: float | None = None,
    depth_fraction: float = 0.5,
    rule: str = "compact",
    spacing: float = 5.0,
) -> np.ndarray:
    """Choose the pinned (fixed) vertices: interior, deep inside, never a marker.

    Candidates are interior vertices (not on the outer surface) that are not in
    ``exclude`` and whose distance to the outer surface (:func:`surface_depth`) is at least
    ``min_depth`` mm (default ``depth_fraction`` x the largest depth of any vertex).
    Two rules place the pins among them; they give two different learning problems
    (``benchmarks/pin_identifiability.py`` measures both):

    ``rule="compact"`` (a small anchor deep inside, like the paper's 3 interior vertices):
    the deepest candidate, then greedily the candidate that keeps the pinned group smallest
    (least largest distance to the pins so far) while lying at least ``spacing`` mm from every
    pin and, for the third, at least ``spacing / 2`` mm off the line through the first two (a
    real triangle, so no free hinge axis). The body is held at one small region and *swings*
    about it under dead loads: the fields are dominated by a few near-rigid rotations, which
    5 markers identify well.

    ``rule="spread"``: the pins are spread as widely as possible, so that together they hold
    the body against rotation about *every* axis:

    1. the candidate farthest from the candidates' centroid, then the candidate farthest
       from that one (the two ends of the candidate cloud's longest extent);
    2. the candidate farthest from the straight line through those two (the largest
       pinned triangle);
    3. any further ones by greedy farthest-point (largest distance to the nearest chosen).

    ``count == 1`` takes the deepest candidate. Ties go to the lowest id.

    Displacements then come from strain in many independent directions: the fields are
    high-dimensional and 5 markers cannot pin them down. Three pins close to one *line*
    (neither rule) leave a hinge the solver struggles with. Measured figures of both rules:
    ``docs/solver.md`` and ``benchmarks/pin_identifiability.py``.

    Args:
        mesh: the tetrahedral mesh.
        count: number of fixed vertices (paper: 3).
        exclude: 0-based ids never to choose (the markers).
        min_depth: minimum distance to the surface in mm; overrides ``depth_fraction``.
        depth_fraction: fraction (0..1) of the maximum depth used when ``min_depth`` is None.
        rule: ``"compact"`` or ``"spread"`` (see above).
        spacing: smallest distance between compact pins, mm.

    Returns:
        (count,) int64, 0-based vertex ids in pick order.

    Raises:
        MarkerError: bad arguments, or fewer than ``count`` candidates.
    """
    _check_fixed_arguments(mesh, count, depth_fraction, rule, spacing)
    exclude = validate_vertex_ids(mesh, exclude, "excluded vertices", allow_empty=True)
    cand, cdepth = _fixed_candidates(mesh, count, exclude, min_depth, depth_fraction)
    pts = mesh.points[cand]
    if count == 1:
        return cand[[_pick(cdepth, np.ones(len(cand), bool), largest=True)]].astype(np.int64)
    if rule == "compact":
        return cand[_compact_pins(pts, cdepth, count, spacing)].astype(np.int64)
    return cand[_spread_pins(pts, count)].astype(np.int64)


def _check_fixed_arguments(mesh, count, depth_fraction, rule, spacing) -> None:
    """Raise MarkerError for arguments of :func:`select_fixed_vertices` out of their range."""
    if not isinstance(mesh, TetMesh):
        raise MarkerError(f"select_fixed_vertices needs a TetMesh, got {type(mesh).__name__}")
    if isinstance(count, bool) or int(count) != count or count < 1:
        raise MarkerError(f"fixed vertex count must be an integer >= 1, got {count!r}")
    if not 0.0 <= depth_fraction <= 1.0:
        raise MarkerError(f"depth_fraction must lie in [0, 1], got {depth_fraction!r}")
    if rule not in FIXED_RULES:
        raise MarkerError(f"unknown fixed-vertex rule {rule!r}; use one of {', '.join(FIXED_RULES)}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise MarkerError(f"fixed-vertex spacing must be a positive length in mm, got {spacing!r}")


def _fixed_candidates(mesh: TetMesh, count: int, exclude: np.ndarray, min_depth, depth_fraction: float):
    """``(ids (c,), depth (c,) mm)`` of the interior vertices deep enough and not excluded."""
    interior = mesh.interior_vertices
    if len(interior) == 0:
        raise MarkerError(
            f"the mesh has no interior vertices (all {mesh.n_vertices} lie on its surface: a wall or body one "
            "element thick), so no fixed vertices can be chosen inside it; hold it by a surface region instead "
            "([scenario.attached] or [scenario.springs], with scenario.pins = false), give surface vertex ids in "
            "markers.fixed_ids, or remesh with at least two elements through its thinnest part"
        )
    depth = surface_depth(mesh, interior)
    limit = depth_fraction * float(depth.max()) if min_depth is None else float(min_depth)
    ok = (depth >= limit) & ~np.isin(interior, exclude)
    if ok.sum() < count:
        raise MarkerError(
            f"only {int(ok.sum())} interior vertices are at least {limit:.3g} mm deep and not excluded, "
            f"but {count} fixed vertices were asked for; use a smaller count, min_depth or "
            f"depth_fraction, or give fixed vertex ids explicitly"
        )
    return interior[ok], depth[ok]


def _spread_pins(pts: np.ndarray, count: int) -> np.ndarray:
    """Indices into ``pts`` of the spread rule (see :func:`select_fixed_vertices`)."""
    everyone = np.ones(len(pts), bool)
    first = _pick(np.linalg.norm(pts - pts.mean(axis=0), axis=1), everyone, largest=True)
    second = _pick(np.linalg.norm(pts - pts[first], axis=1), everyone, largest=True)
    chosen = [first, second]
    if count >= 3:
        off_line = _distance_to_line(pts, pts[first], pts[second])
        eligible = everyone.copy()
        eligible[chosen] = False
        chosen.append(_pick(off_line, eligible, largest=True))
    nearest = np.min([np.linalg.norm(pts - pts[c], axis=1) for c in chosen], axis=0)
    while len(chosen) < count:
        free = np.ones(len(pts), bool)
        free[chosen] = False
        j = _pick(nearest, free, largest=True)
        chosen.append(j)
        nearest = np.minimum(nearest, np.linalg.norm(pts - pts[j], axis=1))
    return np.asarray(chosen)


def _distance_to_line(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) distances of ``pts`` to the straight line through ``a`` and ``b``."""
    axis = b - a
    axis = axis / max(float(np.linalg.norm(axis)), 1e-300)
    rel = pts - a
    return np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)


def _compact_pins(pts: np.ndarray, depth: np.ndarray, count: int, spacing: float) -> np.ndarray:
    """Indices into ``pts`` of the compact rule (see :func:`select_fixed_vertices`)."""
    everyone = np.ones(len(pts), bool)
    chosen = [_pick(depth, everyone, largest=True)]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)[None]  # (chosen, candidates)
    while len(chosen) < count:
        eligible = dist.min(axis=0) >= spacing
        if len(chosen) == 2:
            eligible &= _distance_to_line(pts, pts[chosen[0]], pts[chosen[1]]) >= 0.5 * spacing
        if not eligible.any():
            raise MarkerError(
                f"no room for {count} compact fixed vertices {spacing:g} mm apart among the deep "
                "interior vertices; use a smaller spacing, fewer fixed vertices, a smaller "
                "depth_fraction or rule 'spread'"
            )
        j = _pick(dist.max(axis=0), eligible, largest=False)
        chosen.append(j)
        dist = np.vstack([dist, np.linalg.norm(pts - pts[j], axis=1)])
    return np.asarray(chosen)


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


def markers_and_fixed(mesh: TetMesh, config=None, pins: bool = True, held=None) -> tuple[np.ndarray, np.ndarray]:
    """Markers and fixed vertices as a :class:`~tissuecast.config.MarkerConfig` asks.

    User-given ``ids`` / ``fixed_ids`` are validated (and win); otherwise the markers come
    from :func:`select_markers` (``count``, ``start``, ``min_distance``) and the fixed
    vertices from :func:`select_fixed_vertices` (``fixed_count``, ``fixed_depth_fraction``),
    never overlapping the markers.

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
    if config is None:
        from .config import MarkerConfig

        config = MarkerConfig()
    if config.ids:
        markers = validate_vertex_ids(mesh, config.ids, "markers")
        if held is not None and np.isin(markers, held).any():
            raise MarkerError(f"markers {markers[np.isin(markers, held)].tolist()} lie in the attached region "
                              "(scenario.attached): their displacement is always zero, so they tell the model nothing; "
                              "choose other markers.ids or leave them out to let the k-center rule choose")
    else:
        markers = select_markers(mesh, count=config.count, start=config.start, min_distance=config.min_distance,
                                 exclude=held)
    if not pins:
        return markers, np.zeros(0, dtype=np.int64)
    if config.fixed_ids:
        fixed = validate_vertex_ids(mesh, config.fixed_ids, "fixed vertices", other=markers)
    else:
        fixed = select_fixed_vertices(mesh, count=config.fixed_count, exclude=markers,
                                      depth_fraction=config.fixed_depth_fraction,
                                      rule=config.fixed_rule, spacing=config.fixed_spacing)
    return markers, fixed
