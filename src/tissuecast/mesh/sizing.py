"""Meshes sized for the simulation: a vertex budget met by searching the element size.

What a simulation costs follows the mesh's vertex count (docs/scaling.md), so a user asks for
at most ``max_vertices`` vertices rather than an edge length. :func:`mesh_to_budget` searches
the target edge length h: the first guess is h = (c V / N)^(1/3) (V the volume, N the
budget, c = :data:`VERTICES_PER_CUBIC_SIZE`), each next one follows from the counts so far
(N ~ h^-p, p fitted from the last two attempts, aiming at 0.95 N); the search stops at a mesh
within [:data:`BUDGET_FILL` N, N] or after :data:`MAX_ATTEMPTS` attempts, and returns the
finest mesh within the budget.

For a label map the surface handed to gmsh at size h is first made meshable at that size
(:func:`label_surface_at_size`): the label is closed, then opened, with a ball of radius h/2
(gaps and protrusions narrower than h, such as sulci or thin slivers, cannot be represented by
elements of size h, and gmsh's re-meshing of a surface whose sheets lie closer than h makes
overlapping facets), Gaussian-smoothed (sigma one voxel), cut by marching cubes on a grid of
about h/4 and Taubin-smoothed. The mesh then follows the label's outer envelope at the scale
of its elements; :func:`~tissuecast.mesh.from_image.label_map_fidelity` measures how closely.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import LabelMapError, MeshError
from .tetmesh import TetMesh

__all__ = ["VERTICES_PER_CUBIC_SIZE", "BUDGET_FILL", "MAX_ATTEMPTS", "SizedMesh", "size_for_budget",
           "mesh_to_budget", "mesh_to_tolerance", "label_surface_at_size", "mesh_label_map_to_budget",
           "mesh_label_map_to_tolerance", "surface_volume"]

log = logging.getLogger(__name__)

#: vertices per h^3 of volume in gmsh's meshes at target edge length h (bodies of a few
#: hundred to a few thousand elements across their surface; the first guess of the search)
VERTICES_PER_CUBIC_SIZE = 1.4
#: a mesh with at least this share of the budget ends the search
BUDGET_FILL = 0.85
#: most meshing attempts of one search
MAX_ATTEMPTS = 6
# the search aims this share of the budget (a little room for the count's scatter)
_AIM = 0.95
# bounds of the fitted exponent p in N ~ h^-p (2 = surface-dominated, 3 = volume-dominated)
_EXPONENT_SPAN = (1.5, 3.5)


@dataclass(frozen=True, eq=False)
class SizedMesh:
    """The result of a budget search.

    Attributes:
        mesh: the finest mesh found within the budget.
        size: the target edge length that gave it, mm.
        attempts: ``(size mm, vertices)`` of every attempt, in order (0 vertices: meshing failed).
    """

    mesh: TetMesh
    size: float
    attempts: tuple[tuple[float, int], ...]


def size_for_budget(volume_mm3: float, max_vertices: int) -> float:
    """First guess of the edge length (mm) giving ``max_vertices`` vertices on a body of this volume (mm^3)."""
    if not (isinstance(max_vertices, (int, np.integer)) and max_vertices >= 4):
        raise MeshError(f"max_vertices must be an integer of at least 4, got {max_vertices!r}")
    if not volume_mm3 > 0:
        raise MeshError(f"the body's volume must be positive to size its mesh, got {volume_mm3!r} mm^3")
    return float((VERTICES_PER_CUBIC_SIZE * volume_mm3 / (_AIM * max_vertices)) ** (1.0 / 3.0))


def _next_size(tried: list[tuple[float, int]], target: float) -> float:
    """The next edge length from the (size, vertices) pairs that meshed, aiming at ``target`` vertices."""
    (h1, n1) = tried[-1]
    p = 3.0
    if len(tried) >= 2:
        h0, n0 = tried[-2]
        if h0 != h1 and n0 != n1:
            p = float(np.clip(math.log(n0 / n1) / math.log(h1 / h0), *_EXPONENT_SPAN))
    return h1 * (n1 / target) ** (1.0 / p)


def mesh_to_budget(make_mesh: Callable[[float], TetMesh], max_vertices: int, volume_mm3: float, *,
                   max_attempts: int = MAX_ATTEMPTS) -> SizedMesh:
    """The finest mesh of at most ``max_vertices`` vertices that ``make_mesh`` gives (module notes).

    Args:
        make_mesh: edge length (mm) -> mesh; may raise :class:`MeshError` (that size is
            then recorded with 0 vertices and a finer one tried).
        max_vertices: the budget N.
        volume_mm3: the body's volume, for the first guess.
        max_attempts: most calls of ``make_mesh``.

    Raises:
        MeshError: no attempt gave a mesh within the budget (the message lists them).
    """
    h = size_for_budget(volume_mm3, max_vertices)
    meshed: list[tuple[float, int]] = []
    attempts: list[tuple[float, int]] = []
    best: tuple[TetMesh, float] | None = None
    for _ in range(max_attempts):
        try:
            mesh = make_mesh(h)
        except MeshError as exc:
            log.info("budget search: size %.3g mm failed (%s); trying finer", h, exc)
            attempts.append((h, 0))
            h *= 0.85
            continue
        n = mesh.n_vertices
        attempts.append((h, n))
        meshed.append((h, n))
        log.info("budget search: size %.3g mm -> %d vertices (budget %d)", h, n, max_vertices)
        if n <= max_vertices and (best is None or n > best[0].n_vertices):
            best = (mesh, h)
        if BUDGET_FILL * max_vertices <= n <= max_vertices:
            break
        following = _next_size(meshed, _AIM * max_vertices)
        if any(abs(following - s) <= 0.005 * s for s, _ in attempts):
            break  # the count does not move with the size any more
        h = following
    if best is None:
        tried = ", ".join(f"{s:.3g} mm: {n or 'failed'}" for s, n in attempts)
        raise MeshError(f"no mesh within {max_vertices} vertices after {len(attempts)} attempts ({tried}); "
                        "raise the budget")
    return SizedMesh(best[0], best[1], tuple(attempts))


def surface_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Volume (mm^3) enclosed by a closed triangle surface (duplicate vertices merged, triangles
    oriented first; divergence theorem).

    Raises:
        MeshError: the surface is not closed and manifold.
    """
    from .mesher import check_closed_surface, merge_duplicate_points, orient_surface

    points, triangles = merge_duplicate_points(points, triangles)
    check_closed_surface(points, triangles)
    p = points[orient_surface(points, triangles)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def _close_and_open(mask: np.ndarray, radius_mm: float, spacing: np.ndarray) -> tuple[np.ndarray, int]:
    """Morphological closing then opening with a ball of ``radius_mm``, on a padded copy; returns (mask, pad)."""
    from scipy import ndimage

    pad = int(math.ceil(radius_mm / float(spacing.min()))) + 2
    m = np.pad(mask, pad)

    def edt(a):
        return ndimage.distance_transform_edt(a, sampling=spacing)

    m = edt(edt(~m) <= radius_mm) > radius_mm  # closing: dilate, then erode
    m = edt(~(edt(m) > radius_mm)) <= radius_mm  # opening: erode, then dilate
    components, count = ndimage.label(m)
    if count > 1:
        sizes = np.bincount(components.ravel())[1:]
        log.info("the label opened at %.3g mm falls into %d pieces; the largest (%d of %d voxels) is meshed",
                 radius_mm, count, int(sizes.max()), int(sizes.sum()))
        m = components == int(np.argmax(sizes)) + 1
    return ndimage.binary_fill_holes(m), pad


def label_surface_at_size(labelmap, size: float, *, smoothing_iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface of a label that gmsh can re-mesh at edge length ``size`` (module notes).

    Args:
        labelmap: a :class:`~tissuecast.mesh.labelmap.LabelMap` (one piece, no cavities).
        size: target edge length, mm.
        smoothing_iterations: Taubin passes after marching cubes.

    Returns:
        ``(points (n, 3) float LPS mm, triangles (k, 3) int)``.

    Raises:
        LabelMapError: nothing of the label is left at this size (thinner than ``size`` everywhere).
    """
    from scipy import ndimage

    from ..errors import require
    from .from_image import taubin_smooth

    measure = require("skimage.measure", "image", "Surface extraction from label maps")
    spacing = np.asarray(labelmap.spacing, dtype=np.float64)
    mask, pad = _close_and_open(np.asarray(labelmap.mask, dtype=bool), 0.5 * size, spacing)
    if not mask.any():
        raise LabelMapError(f"{labelmap.source} is thinner than {size:.3g} mm everywhere; a mesh of that size "
                            "cannot represent it: allow more vertices")
    field = ndimage.gaussian_filter(mask.astype(np.float32), sigma=1.0)
    step = max(1, int(size / (4.0 * float(spacing.max()))))
    ijk, triangles, _, _ = measure.marching_cubes(np.pad(field, 1), level=0.5, step_size=step, method="lewiner",
                                                  allow_degenerate=False)
    points = labelmap.to_lps(ijk.astype(np.float64) - 1.0 - pad)
    return taubin_smooth(points, triangles, smoothing_iterations), np.asarray(triangles, dtype=np.int64)


def _label_map_mesher(labelmap, smoothing_iterations: int) -> Callable[[float], TetMesh]:
    from .mesher import tetrahedralize_surface

    def make(size: float) -> TetMesh:
        points, triangles = label_surface_at_size(labelmap, size, smoothing_iterations=smoothing_iterations)
        return tetrahedralize_surface(points, triangles, size, feature_angle=180.0)

    return make


def mesh_label_map_to_budget(labelmap, max_vertices: int, *, smoothing_iterations: int = 10,
                             max_attempts: int = MAX_ATTEMPTS) -> SizedMesh:
    """The finest tetrahedral mesh of a label within ``max_vertices`` vertices (LPS mm).

    Args:
        labelmap: the label, one piece without cavities (see
            :func:`~tissuecast.mesh.from_image.label_pieces`).
        max_vertices: the vertex budget.
        smoothing_iterations: Taubin passes of each attempt's surface.
        max_attempts: most meshing attempts.
    """
    make = _label_map_mesher(labelmap, smoothing_iterations)
    return mesh_to_budget(make, max_vertices, labelmap.volume, max_attempts=max_attempts)


def mesh_label_map_to_tolerance(labelmap, tolerance_mm: float, *, smoothing_iterations: int = 10,
                                max_attempts: int = MAX_ATTEMPTS) -> SizedMesh:
    """The coarsest mesh of a label whose surface lies within ``tolerance_mm`` of the label's
    voxel boundary at the 95th percentile (``surface_p95_mm`` of
    :func:`~tissuecast.mesh.from_image.label_map_fidelity`), LPS mm.

    The search starts at 4 ``tolerance_mm`` (at least two voxels).
    """
    from .from_image import label_map_fidelity

    make = _label_map_mesher(labelmap, smoothing_iterations)
    first = max(4.0 * float(tolerance_mm), 2.0 * float(np.max(labelmap.spacing)))
    return mesh_to_tolerance(make, lambda mesh: label_map_fidelity(mesh, labelmap).surface_p95_mm, tolerance_mm,
                             first, max_attempts=max_attempts)


def mesh_to_tolerance(make_mesh: Callable[[float], TetMesh], deviation: Callable[[TetMesh], float],
                      tolerance_mm: float, first_size: float, *, max_attempts: int = MAX_ATTEMPTS) -> SizedMesh:
    """The coarsest mesh ``make_mesh`` gives whose ``deviation`` (mm) is within ``tolerance_mm``.

    The edge length is doubled (or halved) from ``first_size`` until the tolerance is
    bracketed, then bisected in log scale; at most ``max_attempts`` meshes.

    Raises:
        MeshError: no attempt met the tolerance (the message lists them).
    """
    if not tolerance_mm > 0:
        raise MeshError(f"the surface tolerance must be a positive length in mm, got {tolerance_mm!r}")
    h, met, missed = float(first_size), None, None
    attempts: list[tuple[float, int]] = []
    for _ in range(max_attempts):
        try:
            mesh = make_mesh(h)
            d = float(deviation(mesh))
        except MeshError as exc:
            log.info("tolerance search: size %.3g mm failed (%s)", h, exc)
            attempts.append((h, 0))
            missed, h = h, (h / 2.0 if met is None else math.sqrt(h * met[1]))
            continue
        attempts.append((h, mesh.n_vertices))
        log.info("tolerance search: size %.3g mm -> %d vertices, deviation %.3g mm (tolerance %.3g)", h,
                 mesh.n_vertices, d, tolerance_mm)
        if d <= tolerance_mm:
            met = (mesh, h)
            h = 2.0 * h if missed is None else math.sqrt(h * missed)
        else:
            missed = h
            h = h / 2.0 if met is None else math.sqrt(h * met[1])
        if met is not None and missed is not None and missed / met[1] < 1.15:
            break
    if met is None:
        tried = ", ".join(f"{s:.3g} mm: {n or 'failed'}" for s, n in attempts)
        raise MeshError(f"no mesh met the surface tolerance {tolerance_mm:g} mm after {len(attempts)} attempts "
                        f"({tried}); allow a larger tolerance")
    return SizedMesh(met[0], met[1], tuple(attempts))
