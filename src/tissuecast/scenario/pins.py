"""Pins: the interior vertices that hold the body in the paper's set-up (``scenario.pins``).

The pins are one of the scenario's supports (:mod:`.scenario`): chosen deep inside the body
and never on a marker (:func:`select_fixed_vertices`, the rules ``[markers]`` fixed_* name),
or given by the user (``markers.fixed_ids``). Vertex ids are 0-based; lengths in mm.
"""

from __future__ import annotations

import numpy as np

from ..config import FIXED_RULES, MarkerConfig
from ..errors import MarkerError
from ..mesh.depth import surface_depth
from ..mesh.tetmesh import TetMesh
from ..mesh.vertex_ids import best_index, validate_vertex_ids

__all__ = ["select_fixed_vertices", "pins_from_config"]


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
        return cand[[best_index(cdepth, np.ones(len(cand), bool), largest=True)]].astype(np.int64)
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
            "markers.fixed_ids, or remesh with at least two elements through its thinnest part (a vessel: "
            "configs/vessel.toml holds one by its ends and springs)"
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
    first = best_index(np.linalg.norm(pts - pts.mean(axis=0), axis=1), everyone, largest=True)
    second = best_index(np.linalg.norm(pts - pts[first], axis=1), everyone, largest=True)
    chosen = [first, second]
    if count >= 3:
        off_line = _distance_to_line(pts, pts[first], pts[second])
        eligible = everyone.copy()
        eligible[chosen] = False
        chosen.append(best_index(off_line, eligible, largest=True))
    nearest = np.min([np.linalg.norm(pts - pts[c], axis=1) for c in chosen], axis=0)
    while len(chosen) < count:
        free = np.ones(len(pts), bool)
        free[chosen] = False
        j = best_index(nearest, free, largest=True)
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
    chosen = [best_index(depth, everyone, largest=True)]
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
        j = best_index(dist.max(axis=0), eligible, largest=False)
        chosen.append(j)
        dist = np.vstack([dist, np.linalg.norm(pts - pts[j], axis=1)])
    return np.asarray(chosen)


def pins_from_config(mesh: TetMesh, config: MarkerConfig, markers: np.ndarray) -> np.ndarray:
    """The pins a :class:`~tissuecast.config.MarkerConfig` asks for: its ``fixed_ids``
    (validated, never a marker), else :func:`select_fixed_vertices` (``fixed_count``,
    ``fixed_depth_fraction``, ``fixed_rule``, ``fixed_spacing``) avoiding the markers.

    Args:
        mesh: the tetrahedral mesh.
        config: the marker settings.
        markers: (n_d,) int the fiducial markers (0-based).

    Returns:
        (k,) int64 pinned vertex ids, 0-based.

    Raises:
        MarkerError: bad ``fixed_ids`` or too few candidates.
    """
    if config.fixed_ids:
        return validate_vertex_ids(mesh, config.fixed_ids, "fixed vertices", other=markers)
    return select_fixed_vertices(mesh, count=config.fixed_count, exclude=markers,
                                 depth_fraction=config.fixed_depth_fraction, rule=config.fixed_rule,
                                 spacing=config.fixed_spacing)
