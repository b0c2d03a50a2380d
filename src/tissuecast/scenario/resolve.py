"""Resolving a scenario on a mesh: from its configuration (:func:`build_scenario`), or from the
arrays a data set stored (:func:`restore_scenario`).

:func:`build_scenario` resolves a :class:`~tissuecast.config.ScenarioConfig` on a mesh: the
pinned vertices (``[markers]`` fixed_*, if ``pins``: :mod:`.pins`), the attached surface region
(all components fixed), the elastic support (:mod:`.elastic_support`), the per-element
materials, the eligible indentation sites and the surface force fields. It refuses supports
that leave a rigid-body motion free (:func:`~tissuecast.fem.rigid_motions.free_rigid_motions`).
Ids are 0-based; mm, N, MPa, t/mm^3.
"""

from __future__ import annotations

import numpy as np

from ..config import UNCERTAIN_PARAMETERS, Config, ScenarioConfig
from ..errors import ConfigError
from ..fem.material import NeoHookean
from ..fem.rigid_motions import free_rigid_motions
from ..fem.springs import NodalSprings
from ..forces import LBOBasis
from ..mesh.surface import vertex_normals
from ..mesh.tags import MeshTags
from ..mesh.tetmesh import TetMesh
from .elastic_support import surface_springs
from .indentation import IndentationSites, indentation_sites
from .materials import ElementMaterials, element_materials, material_rng
from .parameters import UncertainParameters, attached_distance
from .pins import pins_from_config
from .regions import surface_region
from .scenario import Scenario, held_nodes_of
from .surface_forces import SurfaceForces

__all__ = ["build_scenario", "restore_scenario", "scenario_markers", "scenario_from_config", "base_material"]


def build_scenario(mesh: TetMesh, config: Config, fixed: np.ndarray, tags: MeshTags | None = None,
                   material_seed: int | None = None, basis: LBOBasis | None = None) -> Scenario:
    """Resolve ``config.scenario`` on a mesh.

    Args:
        mesh: the mesh (mm).
        config: the whole configuration (``scenario``, ``forces``, ``material`` and
            ``solver.order`` are used).
        fixed: (k,) int the pinned vertices ``[markers]`` gives (used when ``scenario.pins``).
        tags: the mesh file's named regions (:func:`~tissuecast.mesh.tags.read_mesh_tags`).
        material_seed: seed of the per-data-set material draws (:func:`~.materials.material_rng`);
            None = the regions' nominal constants.
        basis: the LBO basis of the surface force fields; None = computed from the mesh
            (``forces.n_basis`` vectors, :func:`~tissuecast.forces.lbo_basis`).

    Raises:
        ConfigError: an empty or unknown region, supports that leave a rigid-body motion
            free, no eligible indentation site.
    """
    sc = config.scenario
    order = config.solver.order
    normals = vertex_normals(mesh)
    pinned = np.asarray(fixed, dtype=np.int64) if sc.pins else np.zeros(0, dtype=np.int64)
    attached = surface_region(mesh, sc.attached, "scenario.attached", tags, normals)
    distance = attached_distance(mesh, attached) if sc.uncertain.attached_margin else None
    attached, reach = _attached_extents(attached, distance, sc.uncertain.attached_margin)
    region = surface_region(mesh, sc.springs, "scenario.springs", tags, normals)
    supported = np.union1d(pinned, attached)
    held = held_nodes_of(mesh, order, supported)
    springs = spring_parts = None
    if region.size:
        springs = surface_springs(mesh, region, order, sc.springs.normal_stiffness,
                                  sc.springs.tangential_stiffness, sc.springs.lumping).without(held)
        if len(springs) == 0:
            raise ConfigError("scenario.springs: the region holds no whole surface triangle outside the attached "
                              "region; widen it")
        if sc.uncertain.spring_normal or sc.uncertain.spring_tangential:
            spring_parts = tuple(surface_springs(mesh, region, order, kn, kt, sc.springs.lumping).without(held).stiffness
                                 for kn, kt in ((sc.springs.normal_stiffness, 0.0), (0.0, sc.springs.tangential_stiffness)))
    points = mesh.points if order == 1 else mesh.points10
    free = free_rigid_motions(points, held, springs)
    if len(free):
        kinds = ["a rotation" if np.linalg.norm(v[3:]) > np.linalg.norm(v[:3]) else "a translation" for v in free]
        raise ConfigError(
            f"the scenario's supports leave {len(free)} rigid-body motion(s) free ({', '.join(sorted(set(kinds)))}): "
            "the body could move without straining; pin at least 3 non-collinear vertices (scenario.pins), attach a "
            "surface region (scenario.attached) or give the elastic support tangential stiffness / a wider region "
            "(scenario.springs)")
    materials = None
    if sc.materials.regions:
        rng = material_rng(material_seed) if material_seed is not None else None
        materials = element_materials(mesh, config.material, sc.materials, tags, rng)
    sites = _sites(mesh, sc, normals, np.union1d(pinned, reach), tags=tags)
    gravity = (sc.gravity.density, sc.gravity.acceleration) if sc.gravity.enabled else None
    forces = _surface_forces(mesh, config, pinned, attached, basis)
    uncertain = _uncertain(mesh, config, materials, distance, spring_parts)
    return Scenario(sc, mesh, order, base_material(config), pinned, attached, region, springs, materials, normals, sites,
                    gravity, forces, uncertain)


def base_material(config: Config) -> NeoHookean:
    """The neo-Hookean constants of ``config.material`` (MPa): every element without a region of its own."""
    return NeoHookean(youngs_modulus=config.material.youngs_modulus, poisson_ratio=config.material.poisson_ratio)


def _attached_extents(nominal: np.ndarray, distance: np.ndarray | None, margin: tuple) -> tuple[np.ndarray, np.ndarray]:
    """``(smallest, largest)`` extents (vertex ids) of an attached region whose margin is drawn
    in ``margin`` mm (:func:`~.parameters.attached_distance`); ``(nominal, nominal)`` without."""
    if distance is None:
        return nominal, nominal
    lo, hi = float(margin[0]), float(margin[1])
    return np.flatnonzero(distance <= lo).astype(np.int64), np.flatnonzero(distance <= hi).astype(np.int64)


def _uncertain(mesh: TetMesh, config: Config, materials: ElementMaterials | None, distance: np.ndarray | None,
               spring_parts: tuple | None) -> UncertainParameters | None:
    """The scenario's uncertain parameters (None when ``scenario.uncertain`` draws nothing)."""
    u = config.scenario.uncertain
    if not any(getattr(u, name) for name in UNCERTAIN_PARAMETERS):
        return None
    m = mesh.n_tets
    if materials is not None:
        e, nu, region = materials.youngs_modulus, materials.poisson_ratio, materials.region
    else:
        e, nu = np.full(m, config.material.youngs_modulus), np.full(m, config.material.poisson_ratio)
        region = np.full(m, -1, dtype=np.int64)
    return UncertainParameters(u, np.asarray(e, dtype=np.float64), np.asarray(nu, dtype=np.float64),
                               np.asarray(region, dtype=np.int64), len(config.scenario.materials.regions), distance,
                               spring_parts)


def _surface_forces(mesh: TetMesh, config: Config, pinned: np.ndarray, attached: np.ndarray,
                    basis: LBOBasis | None) -> SurfaceForces:
    """The scenario's surface force fields: ``basis`` (None = computed from the mesh), no LSC
    force on the supported vertices."""
    from ..forces import lbo_basis

    basis = lbo_basis(mesh, config.forces.n_basis) if basis is None else basis
    supported = np.concatenate([pinned, attached[~np.isin(attached, pinned)]]).astype(np.int64)
    return SurfaceForces(mesh, basis, config.forces, supported, enabled=config.scenario.lbo_forces)


def _sites(mesh: TetMesh, sc: ScenarioConfig, normals: np.ndarray, supported: np.ndarray, tags: MeshTags | None = None,
           access: np.ndarray | None = None) -> IndentationSites | None:
    """The indentation's sites (None without one); ``access`` (a,) int the stored access region,
    or None to resolve ``sc.indentation.access`` on the mesh (with ``tags`` for rule ``tag``)."""
    if not sc.indentation.enabled:
        return None
    if access is None:
        access = surface_region(mesh, sc.indentation.access, "scenario.indentation.access", tags, normals)
    return indentation_sites(mesh, sc.indentation, normals, supported, access=np.asarray(access, dtype=np.int64))


def restore_scenario(mesh: TetMesh, config: Config, arrays: dict, basis: LBOBasis | None = None) -> Scenario:
    """A scenario from its :meth:`Scenario.arrays` (e.g. read back from a data set), without
    the mesh file's named regions: the supports, materials and the indentation's access region
    are the stored ones (a store without ``indent_access`` resolves ``config``'s); normals and
    indentation sites are recomputed from them, the mesh and ``config``. ``basis``: the LBO
    basis of the surface force fields (a data set's stored one; None = computed from the mesh)."""
    sc = config.scenario
    order = config.solver.order
    normals = vertex_normals(mesh)
    pinned, attached = (np.asarray(arrays[k], dtype=np.int64) for k in ("pinned", "attached"))
    springs = None
    if "spring_nodes" in arrays:
        springs = NodalSprings(arrays["spring_nodes"], arrays["spring_stiffness"])
    materials = None
    if "youngs_modulus" in arrays:
        e, nu = (np.asarray(arrays[k], dtype=np.float64) for k in ("youngs_modulus", "poisson_ratio"))
        region = np.asarray(arrays["material_region"], dtype=np.int64)
        names = tuple(r.name for r in sc.materials.regions)
        draws = {}
        for k, name in enumerate(names):
            inside = np.flatnonzero(region == k)
            if inside.size:
                draws[name] = {"youngs_modulus": float(e[inside[0]]), "poisson_ratio": float(nu[inside[0]])}
        materials = ElementMaterials(e, nu, region, names, draws)
    distance = arrays.get("attached_distance")
    _, reach = _attached_extents(attached, distance, sc.uncertain.attached_margin)
    sites = _sites(mesh, sc, normals, np.union1d(pinned, np.union1d(attached, reach)),
                   access=arrays.get("indent_access"))
    gravity = (sc.gravity.density, sc.gravity.acceleration) if sc.gravity.enabled else None
    forces = _surface_forces(mesh, config, pinned, attached, basis)
    parts = None
    if "spring_normal_part" in arrays:
        parts = (np.asarray(arrays["spring_normal_part"]), np.asarray(arrays["spring_tangential_part"]))
    uncertain = _uncertain(mesh, config, materials, distance, parts)
    return Scenario(sc, mesh, order, base_material(config), pinned, attached,
                    np.asarray(arrays["spring_region"], dtype=np.int64), springs, materials, normals, sites, gravity,
                    forces, uncertain)


def scenario_markers(mesh: TetMesh, config: Config, tags: MeshTags | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The markers ``[markers]`` gives with this scenario, and its pins: no marker on the
    vertices ``scenario.attached`` holds (they never move; :func:`~tissuecast.markers.markers_from_config`),
    and the pins around the markers (:func:`~.pins.pins_from_config`), none with
    ``scenario.pins = false``.

    Returns:
        ``(markers (n_d,) int64, pins (k,) int64)``, 0-based.
    """
    from ..markers import markers_from_config

    held = surface_region(mesh, config.scenario.attached, "scenario.attached", tags)
    markers = markers_from_config(mesh, config.markers, held=held)
    pins = pins_from_config(mesh, config.markers, markers) if config.scenario.pins else np.zeros(0, dtype=np.int64)
    return np.asarray(markers, dtype=np.int64), np.asarray(pins, dtype=np.int64)


def scenario_from_config(config: Config):
    """The mesh, fiducial markers, pinned vertices and resolved scenario a config describes.

    The mesh is ``mesh.path`` (with its named regions, :func:`~tissuecast.mesh.tags.read_mesh_tags`)
    or the built-in phantom; material draws use ``dataset.seed``.

    Returns:
        ``(mesh, markers (n_d,) int64, fixed (k,) int64, scenario)``: ``fixed`` are the pins
        (empty with ``scenario.pins = false``, when none are chosen); the scenario's LBO basis
        is computed from the mesh.
    """
    from ..mesh.source import mesh_from_config
    from ..mesh.tags import mesh_file_tags

    mesh = mesh_from_config(config.mesh)
    tags = mesh_file_tags(config.mesh.path)
    markers, fixed = scenario_markers(mesh, config, tags)
    return mesh, markers, fixed, build_scenario(mesh, config, fixed, tags, material_seed=config.dataset.seed)
