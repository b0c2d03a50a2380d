"""Indentation: an instrument pushing a small surface patch by a prescribed displacement.

Per sample a patch centre is drawn on the outer surface (uniformly by area, among the
surface vertices of the access region, ``scenario.indentation.access``, that lie at least
``clearance`` mm from every supported vertex); the patch is the
surface vertices within ``radius`` mm of the centre whose outward normals face the same side
(within 60 degrees of the centre's), supported vertices left out. Every patch vertex moves by
the same displacement

    d = depth (-n_c) + slide (cos phi t_1 + sin phi t_2),

``n_c`` the centre's outward normal and ``t_1, t_2`` a tangent frame there: a rigid,
non-slipping tool face pressed in and dragged along (``tool = "flat"``). A flat punch's rim is
a singularity of the elastic field (the strain there grows without bound as the mesh is
refined), so quadratic elements meet elements squeezed to J ~ 0.3 at the rim. With
``tool = "rounded"`` the instrument is a ball-ended tip of radius ``R`` (``tool_radius``): as
in Hertz's contact of a sphere, the surface is in contact within ``a = sqrt(R depth)`` of the
centre and follows the tip there, a patch vertex at distance ``r`` from the centre (in the
tangent plane) moving by

    d(r) = (depth - r^2 / (2 R)) (-n_c) + slide (cos phi t_1 + sin phi t_2),

so the push falls smoothly to half the depth at the contact's rim (at least
:data:`PATCH_MIN_VERTICES` vertices, the nearest, are always in contact). The solver reaches
the displacements in proportion to the load fraction, like every load.

Draws (from the sample's scenario generator, in this order): the centre (``rng.choice`` with
area weights), the depth (``rng.uniform(*depth)``), the slide (``rng.uniform(*slide)``) and its
angle ``phi`` (``2 pi rng.random()``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import IndentationConfig
from ..errors import ConfigError
from ..mesh.tetmesh import TetMesh
from ..mesh.surface import lumped_areas

__all__ = ["Indentation", "IndentationSites", "indentation_sites", "draw_indentation", "indentation_at", "contact_profile",
           "PATCH_MIN_VERTICES", "PATCH_FACING_COS"]

#: A patch holds at least this many vertices (fewer would be a point load, singular in 3-D).
PATCH_MIN_VERTICES = 3
#: Patch vertices' normals lie within 60 degrees of the centre's (cos 60 = 0.5), so a patch
#: never reaches round a sharp edge or through a thin part to the far side.
PATCH_FACING_COS = 0.5


@dataclass(frozen=True, eq=False)
class Indentation:
    """One sample's indentation.

    Attributes:
        centre: vertex id of the patch centre.
        vertices: (p,) int64 sorted ids of the patch vertices (those in contact).
        displacement: (3,) float, mm, the tool tip's displacement (the centre's).
        depth: mm along the inward normal.  slide: mm along the surface.
        normal: (3,) unit outward normal at the centre.
        values: (p, 3) float, mm, each patch vertex's displacement (all ``displacement`` for a
            flat tool; the rounded tip's profile otherwise).
    """

    centre: int
    vertices: np.ndarray
    displacement: np.ndarray
    depth: float
    slide: float
    normal: np.ndarray
    values: np.ndarray


@dataclass(frozen=True, eq=False)
class IndentationSites:
    """Where patch centres may be drawn, and the patch of each.

    Attributes:
        centres: (c,) int64 eligible centre vertices.
        access: (a,) int64 sorted surface vertices of the access region (the centres are
            those of them far enough from the supports with a large enough patch).
        weights: (c,) float, probabilities (lumped vertex areas, normalised).
        patches: list of (p,) int64 patch vertices, one per centre (the tool's reach).
        normals: (c, 3) outward unit normals at the centres.
        radii: list of (p,) float, mm: each patch vertex's distance from its centre in the
            centre's tangent plane.
    """

    centres: np.ndarray
    weights: np.ndarray
    patches: list
    normals: np.ndarray
    access: np.ndarray
    radii: list


def indentation_sites(mesh: TetMesh, config: IndentationConfig, normals: np.ndarray, supported: np.ndarray,
                      key: str = "scenario.indentation", access: np.ndarray | None = None) -> IndentationSites:
    """The eligible patch centres and their patches (module notes).

    Args:
        mesh: the mesh (mm).
        config: the indentation settings.
        normals: (n, 3) outward vertex normals.
        supported: (k,) int vertices held by the supports (pins, attached region).
        key: config key for messages.
        access: (a,) int surface vertices where centres may lie (the resolved
            ``config.access`` region); None = the whole outer surface.

    Raises:
        ConfigError: no access vertex is far enough from the supports, or no patch holds
            :data:`PATCH_MIN_VERTICES` vertices (radius too small: in metres?).
    """
    surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
    access = surface if access is None else np.intersect1d(np.asarray(access, dtype=np.int64), surface)
    supported = np.asarray(supported, dtype=np.int64)
    pts = mesh.points
    if supported.size:
        far = np.array([np.linalg.norm(pts[supported] - pts[v], axis=1).min() >= config.clearance for v in access],
                       dtype=bool)
    else:
        far = np.ones(len(access), dtype=bool)
    if not far.any():
        where = "surface vertex" if len(access) == len(surface) else f"vertex of the access region ({key}.access)"
        raise ConfigError(f"{key}: no {where} is {config.clearance:g} mm away from the supported vertices; "
                          f"reduce {key}.clearance, widen {key}.access or shrink the supported region")
    nodes, area, _ = lumped_areas(mesh, mesh.surface_triangles, 1)
    vertex_area = np.zeros(mesh.n_vertices)
    vertex_area[nodes] = area
    centres, patches = [], []
    free_surface = surface[~np.isin(surface, supported)]
    for c in access[far]:
        near = free_surface[np.linalg.norm(pts[free_surface] - pts[c], axis=1) <= config.radius]
        patch = near[normals[near] @ normals[c] >= PATCH_FACING_COS]
        if len(patch) >= PATCH_MIN_VERTICES:
            centres.append(int(c))
            patches.append(np.sort(patch))
    if not centres:
        raise ConfigError(f"{key}.radius = {config.radius:g} mm holds fewer than {PATCH_MIN_VERTICES} surface vertices "
                          "around every eligible centre; lengths are in mm: use a radius of a few mean edge lengths "
                          f"({mesh.quality.edge_length_mean:.3g} mm on this mesh)")
    centres = np.asarray(centres, dtype=np.int64)
    w = vertex_area[centres]
    radii = [_tangent_distances(pts[p] - pts[c], normals[c]) for c, p in zip(centres, patches)]
    return IndentationSites(centres, w / w.sum(), patches, normals[centres], access, radii)


def _tangent_distances(offsets: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(p,) float: lengths of the ``offsets`` (p, 3) projected on the plane normal to ``normal``."""
    return np.linalg.norm(offsets - np.outer(offsets @ normal, normal), axis=1)


def contact_profile(radii: np.ndarray, depth: float, tool_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The rounded tip's contact (module notes): ``(in contact (p,) bool, push (p,) mm along
    the inward normal)`` of patch vertices at tangent-plane distances ``radii`` (p,) mm;
    the :data:`PATCH_MIN_VERTICES` nearest are always in contact."""
    radii = np.asarray(radii, dtype=np.float64)
    inside = radii <= np.sqrt(tool_radius * depth)
    inside[np.argsort(radii, kind="stable")[:PATCH_MIN_VERTICES]] = True
    return inside, depth - radii**2 / (2.0 * tool_radius)


def draw_indentation(rng: np.random.Generator, sites: IndentationSites, config: IndentationConfig) -> Indentation:
    """One indentation, drawn as the module notes say."""
    k = int(rng.choice(len(sites.centres), p=sites.weights))
    depth = float(rng.uniform(*config.depth))
    slide = float(rng.uniform(*config.slide))
    phi = 2.0 * np.pi * float(rng.random())
    n = sites.normals[k]
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    tangential = slide * (np.cos(phi) * t1 + np.sin(phi) * t2)
    return _pushed_patch(sites, config, k, -depth * n + tangential, depth, slide, tangential)


def indentation_at(sites: IndentationSites, config: IndentationConfig, points: np.ndarray, tip) -> Indentation:
    """The indentation of a tool tip tracked at ``tip`` (3,) mm (model frame): the inverse of
    the draw, for a tracked frame's known loads.

    The tip is the patch centre's reference position plus the tool's displacement, so each site
    ``k`` explains it with the displacement ``d = tip - X_k``: a depth ``-d . n_k`` along the
    inward normal and a slide, the rest of ``d``. The site taken is the nearest one (the
    smallest ``|d|``) with the tip below its surface (depth > 0): the tracked pose does not say
    where the tool first touched, so where sites lie closer together than the tool slid, the
    nearest is taken. Its patch is pushed as a drawn one is.

    Args:
        sites: the scenario's :class:`IndentationSites`.
        config: the indentation settings (the tool).
        points: (n, 3) mesh vertices, mm.
        tip: (3,) the tracked tip, mm.

    Raises:
        ConfigError: the tip lies below no site's surface (no depth above 0), or farther
            along the surface from the nearest site than the patch radius.
    """
    tip = np.asarray(tip, dtype=np.float64).reshape(3)
    d = tip[None, :] - points[sites.centres]  # (c, 3)
    depth = -(d * sites.normals).sum(axis=1)
    tangential = d + depth[:, None] * sites.normals
    slide = np.linalg.norm(tangential, axis=1)
    below = depth > 0.0
    if not below.any():
        k = int(np.argmin(np.linalg.norm(d, axis=1)))
        raise ConfigError(f"the instrument's tip lies {-depth[k]:.2f} mm outside the tissue at vertex "
                          f"{int(sites.centres[k])} yet is reported in contact; check the tracked pose's frame (LPS mm)")
    k = int(np.flatnonzero(below)[np.argmin(np.linalg.norm(d[below], axis=1))])
    if slide[k] > config.radius:
        raise ConfigError(f"the instrument's tip lies {slide[k]:.2f} mm along the surface from the nearest place the "
                          f"scenario pushes it (vertex {int(sites.centres[k])}; patch radius {config.radius:g} mm, "
                          "scenario.indentation.access): the simulator cannot push the tissue there")
    return _pushed_patch(sites, config, k, d[k], float(depth[k]), float(slide[k]), tangential[k])


def _pushed_patch(sites: IndentationSites, config: IndentationConfig, k: int, d: np.ndarray, depth: float,
                  slide: float, tangential: np.ndarray) -> Indentation:
    """Site ``k``'s patch pushed by the tool displacement ``d`` (3,) mm: ``depth`` along the
    inward normal, ``tangential`` (3,) mm of length ``slide`` along the surface."""
    n = sites.normals[k]
    patch = sites.patches[k]
    if config.tool == "flat":
        return Indentation(int(sites.centres[k]), patch, d, depth, slide, n.copy(), np.repeat(d[None, :], len(patch), 0))
    inside, push = contact_profile(sites.radii[k], depth, config.tool_radius)
    values = -push[inside, None] * n[None, :] + tangential[None, :]
    return Indentation(int(sites.centres[k]), patch[inside], d, depth, slide, n.copy(), values)
