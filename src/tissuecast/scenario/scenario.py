"""A clinical scenario on a mesh: its supports, its materials and its per-sample loads.

:func:`build_scenario` resolves a :class:`~tissuecast.config.ScenarioConfig` on a mesh: the
pinned vertices (``[markers]`` fixed_*, if ``pins``), the attached surface region (all
components fixed), the elastic support (:class:`~tissuecast.fem.springs.NodalSprings`), the
per-element materials and the eligible indentation sites. It refuses supports that leave a
rigid-body motion free (:func:`free_rigid_motions`).

Per sample, :meth:`Scenario.draw` draws the gravity direction and the indentation from the
sample's scenario generator (:func:`scenario_rng`, a stream of its own, so that the LBO
weights drawn from the sample seed stay those of the paper's set-up), in that order; the
loads follow from the draw (:meth:`Scenario.body_loads`, :meth:`Scenario.prescribed`).
Ids are 0-based; mm, N, MPa, t/mm^3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config, ScenarioConfig
from ..errors import ConfigError
from ..fem.springs import NodalSprings
from ..fem.supports import free_rigid_motions
from ..mesh.tags import MeshTags
from ..mesh.tetmesh import TetMesh
from .gravity import body_loads, cone_direction, gravity_body_force
from .indentation import Indentation, IndentationSites, draw_indentation, indentation_sites
from .materials import ElementMaterials, element_materials, material_rng
from .regions import surface_region
from .springs import surface_springs
from ..mesh.surface import vertex_normals

__all__ = ["Scenario", "ScenarioDraw", "build_scenario", "restore_scenario", "scenario_from_config", "scenario_rng",
           "free_rigid_motions",
           "SCENARIO_STREAM"]

#: Second SeedSequence word of a sample's scenario draws: ``SeedSequence([sample_seed, SCENARIO_STREAM])``.
SCENARIO_STREAM = 2**63 - 3


def scenario_rng(sample_seed) -> np.random.Generator:
    """The generator of a sample's scenario draws (module notes)."""
    return np.random.default_rng(np.random.SeedSequence([int(sample_seed), SCENARIO_STREAM]))


@dataclass(frozen=True, eq=False)
class ScenarioDraw:
    """One sample's draws.

    Attributes:
        gravity_direction: (3,) unit surgery direction of gravity, or None (no gravity load).
        body_force: (3,) N/mm^3, ``rho |g| (d_surgery - d_imaging)``, or None.
        indentation: the sample's indentation, or None.
    """

    gravity_direction: np.ndarray | None = None
    body_force: np.ndarray | None = None
    indentation: Indentation | None = None

    def record(self) -> dict[str, float]:
        """Flat numbers for a data set (NaN where the load is absent): gravity direction x/y/z,
        indentation centre (vertex id), depth, slide (mm) and displacement x/y/z (mm)."""
        nan3 = [np.nan] * 3
        g = self.gravity_direction if self.gravity_direction is not None else nan3
        ind = self.indentation
        d = ind.displacement if ind is not None else nan3
        return {"gravity_x": float(g[0]), "gravity_y": float(g[1]), "gravity_z": float(g[2]),
                "indent_centre": float(ind.centre) if ind is not None else np.nan,
                "indent_depth": ind.depth if ind is not None else np.nan,
                "indent_slide": ind.slide if ind is not None else np.nan,
                "indent_x": float(d[0]), "indent_y": float(d[1]), "indent_z": float(d[2])}


@dataclass(frozen=True, eq=False)
class Scenario:
    """A scenario resolved on a mesh (see :func:`build_scenario`).

    Attributes:
        config: the scenario settings.
        mesh: the mesh (mm).
        order: element order (1 or 2).
        pinned: (p,) int64 pinned vertices (empty without ``pins``).
        attached: (a,) int64 surface vertices of the attached region (all components fixed).
        spring_region: (s,) int64 surface vertices of the elastic support's region.
        springs: the nodal springs (none at held nodes), or None.
        materials: per-element constants, or None (the ``[material]`` section everywhere).
        normals: (n, 3) outward unit vertex normals (zero inside).
        sites: where indentations may be drawn, or None.
        gravity: ``(density t/mm^3, |g| mm/s^2)`` when the gravity change is on, else None.
    """

    config: ScenarioConfig
    mesh: TetMesh
    order: int
    pinned: np.ndarray
    attached: np.ndarray
    spring_region: np.ndarray
    springs: NodalSprings | None
    materials: ElementMaterials | None
    normals: np.ndarray
    sites: IndentationSites | None
    gravity: tuple | None

    @property
    def supported(self) -> np.ndarray:
        """(k,) int64 vertices held in all components by the static supports: the pins (in
        their order), then the attached region's other vertices (ascending)."""
        extra = self.attached[~np.isin(self.attached, self.pinned)]
        return np.concatenate([self.pinned, extra]).astype(np.int64)

    @property
    def n_nodes(self) -> int:
        """Number of element nodes (rows of nodal loads)."""
        return self.mesh.n_vertices if self.order == 1 else len(self.mesh.points10)

    @property
    def held_nodes(self) -> np.ndarray:
        """(h,) int64 element nodes fixed in all components: the supported vertices and, for
        P2, the mid-edge nodes between two of them."""
        return _held_nodes(self.mesh, self.order, self.supported)

    @property
    def plain(self) -> bool:
        """True for the paper's set-up: pins and LBO forces only (no attached region, springs,
        gravity change, indentation or material regions)."""
        return bool(self.config.pins and self.config.lbo_forces and not len(self.attached) and self.springs is None
                    and self.gravity is None and self.sites is None and self.materials is None)

    @property
    def draws_per_sample(self) -> bool:
        """Whether samples draw a gravity direction or an indentation."""
        return self.gravity is not None or self.sites is not None

    @property
    def can_swing(self) -> bool:
        """Whether the body is held by pins alone (so it may swing about them as a near-rigid
        body); False with springs or an attached region."""
        return self.springs is None and len(self.attached) == 0

    def problem(self, config: Config):
        """The finite-element problem (:class:`~tissuecast.fem.Problem`): the supported vertices
        fixed, the springs, the material regions; ``config`` gives the material and order."""
        from ..fem import build_problem
        from ..fem.material import NeoHookeanField

        field = None
        if self.materials is not None:
            field = NeoHookeanField(self.materials.youngs_modulus, self.materials.poisson_ratio)
        return build_problem(self.mesh, config, self.supported, order=self.order, springs=self.springs,
                             materials=field, can_swing=self.can_swing)

    def sample_loads(self, draw: "ScenarioDraw", vertex_forces: np.ndarray | None = None,
                     loading: str = "nodal") -> tuple[np.ndarray, np.ndarray]:
        """A sample's external loads on every element node: ``(surface (n_nodes, 3) N, body
        (n_nodes, 3) N)``, both zero at the held nodes (loads there go straight into the
        supports).

        ``surface``: the field ``vertex_forces`` ((n, 3) N: the LBO or test-2 field, or None)
        as nodal forces on the vertices (``loading = "nodal"``, the paper's) or as a traction
        (``"traction"``, :func:`~tissuecast.forces.traction_loads`); ``body``: the draw's
        consistent gravity-change loads (:meth:`body_loads`).
        """
        surface = np.zeros((self.n_nodes, 3))
        if vertex_forces is not None:
            vf = np.asarray(vertex_forces, dtype=np.float64)
            if loading == "traction":
                from ..forces import traction_loads

                surface += traction_loads(self.mesh, self.order, vf)
            else:
                surface[: self.mesh.n_vertices] += vf
        body = self.body_loads(draw)
        held = self.held_nodes
        surface[held] = 0.0
        body[held] = 0.0
        return surface, body

    def solve_inputs(self, draw: "ScenarioDraw", vertex_forces: np.ndarray | None = None,
                     loading: str = "nodal") -> tuple[np.ndarray, dict]:
        """What a solver takes for a sample: ``(surface loads (n_nodes, 3) N, keywords)`` with
        ``body_loads`` (n_nodes, 3) N when the draw has a gravity change and ``prescribed``
        ``(ids (k,), values (k, 3) mm)`` when it has an indentation, for
        :meth:`tissuecast.fem.Solver.solve` or :func:`tissuecast.fem.calculix.solve_calculix`."""
        surface, body = self.sample_loads(draw, vertex_forces, loading)
        extra = {"body_loads": body} if draw.body_force is not None else {}
        ids, values = self.prescribed(draw)
        if len(ids):
            extra["prescribed"] = (ids, values)
        return surface, extra

    def loads(self, draw: "ScenarioDraw", vertex_forces: np.ndarray | None = None, loading: str = "nodal") -> np.ndarray:
        """A sample's external loads on every element node, (n_nodes, 3) N: the sum of
        :meth:`sample_loads`."""
        surface, body = self.sample_loads(draw, vertex_forces, loading)
        return surface + body

    def arrays(self) -> dict:
        """The resolved supports and materials as plain arrays (what a data set stores):
        ``pinned``, ``attached``, ``spring_region`` (int64 vertex ids), ``spring_nodes`` (s,)
        and ``spring_stiffness`` (s, 3, 3) N/mm (with springs), ``youngs_modulus`` (m,) MPa,
        ``poisson_ratio`` (m,) and ``material_region`` (m,) int64 (with material regions),
        ``indent_access`` (a,) int64 surface vertex ids (with an indentation: its access region)."""
        out = {"pinned": self.pinned, "attached": self.attached, "spring_region": self.spring_region}
        if self.springs is not None:
            out.update(spring_nodes=self.springs.nodes, spring_stiffness=self.springs.stiffness)
        if self.materials is not None:
            out.update(youngs_modulus=self.materials.youngs_modulus, poisson_ratio=self.materials.poisson_ratio,
                       material_region=self.materials.region)
        if self.sites is not None:
            out["indent_access"] = self.sites.access
        return {k: np.asarray(v) for k, v in out.items()}

    def draw(self, rng: np.random.Generator) -> ScenarioDraw:
        """A sample's draws: the gravity direction (2 draws), then the indentation (4 draws)."""
        cfg = self.config
        direction = force = ind = None
        if self.gravity is not None:
            direction = cone_direction(rng, cfg.gravity.surgery_direction, cfg.gravity.cone_angle)
            force = gravity_body_force(*self.gravity, cfg.gravity.imaging_direction, direction)
        if self.sites is not None:
            ind = draw_indentation(rng, self.sites, cfg.indentation)
        return ScenarioDraw(direction, force, ind)

    def body_loads(self, draw: ScenarioDraw) -> np.ndarray:
        """(n_nodes, 3) N: the consistent nodal loads of the draw's gravity change (zero without)."""
        if draw.body_force is None:
            return np.zeros((self.n_nodes, 3))
        return body_loads(self.mesh, self.order, draw.body_force)

    def prescribed(self, draw: ScenarioDraw) -> tuple[np.ndarray, np.ndarray]:
        """``(vertex ids (k,), displacements (k, 3) mm)`` the draw prescribes (its indentation patch)."""
        ind = draw.indentation
        if ind is None:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        return ind.vertices.copy(), ind.values.copy()

    def summary(self) -> dict:
        """JSON-able description (for data sets, models and reports)."""
        cfg = self.config
        out = {"name": cfg.name, "pins": len(self.pinned), "attached_vertices": len(self.attached),
               "attached_rule": cfg.attached.rule, "lbo_forces": cfg.lbo_forces}
        if self.springs is not None:
            out["springs"] = {"rule": cfg.springs.rule, "region_vertices": len(self.spring_region),
                              "nodes": len(self.springs), "normal_stiffness_N_per_mm3": cfg.springs.normal_stiffness,
                              "tangential_stiffness_N_per_mm3": cfg.springs.tangential_stiffness}
        if self.gravity is not None:
            g = cfg.gravity
            out["gravity"] = {"density_t_per_mm3": g.density, "acceleration_mm_per_s2": g.acceleration,
                              "imaging_direction": list(g.imaging_direction),
                              "surgery_direction": list(g.surgery_direction), "cone_angle_degrees": g.cone_angle}
        if self.sites is not None:
            i = cfg.indentation
            out["indentation"] = {"radius_mm": i.radius, "depth_mm": list(i.depth), "slide_mm": list(i.slide),
                                  "sites": len(self.sites.centres), "access_rule": i.access.rule,
                                  "access_vertices": len(self.sites.access)}
        if self.materials is not None:
            out["materials"] = self.materials.draws
        return out


def _held_nodes(mesh: TetMesh, order: int, vertices: np.ndarray) -> np.ndarray:
    """Vertices held in all components and, for P2, the mid-edge nodes between two of them."""
    vertices = np.asarray(vertices, dtype=np.int64)
    if order == 1:
        return vertices
    both = np.isin(mesh.edges, vertices).all(axis=1)
    return np.concatenate([vertices, mesh.n_vertices + np.flatnonzero(both)])


def build_scenario(mesh: TetMesh, config: Config, fixed: np.ndarray, tags: MeshTags | None = None,
                   material_seed: int | None = None) -> Scenario:
    """Resolve ``config.scenario`` on a mesh.

    Args:
        mesh: the mesh (mm).
        config: the whole configuration (``scenario``, ``material`` and ``solver.order`` are used).
        fixed: (k,) int the pinned vertices ``[markers]`` gives (used when ``scenario.pins``).
        tags: the mesh file's named regions (:func:`~tissuecast.mesh.tags.read_mesh_tags`).
        material_seed: seed of the per-data-set material draws (:func:`~.materials.material_rng`);
            None = the regions' nominal constants.

    Raises:
        ConfigError: an empty or unknown region, supports that leave a rigid-body motion
            free, no eligible indentation site.
    """
    sc = config.scenario
    order = config.solver.order
    normals = vertex_normals(mesh)
    pinned = np.asarray(fixed, dtype=np.int64) if sc.pins else np.zeros(0, dtype=np.int64)
    attached = surface_region(mesh, sc.attached, "scenario.attached", tags, normals)
    region = surface_region(mesh, sc.springs, "scenario.springs", tags, normals)
    supported = np.union1d(pinned, attached)
    held = _held_nodes(mesh, order, supported)
    springs = None
    if region.size:
        springs = surface_springs(mesh, region, order, sc.springs.normal_stiffness,
                                  sc.springs.tangential_stiffness, sc.springs.lumping).without(held)
        if len(springs) == 0:
            raise ConfigError("scenario.springs: the region holds no whole surface triangle outside the attached "
                              "region; widen it")
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
    sites = _sites(mesh, sc, normals, supported, tags=tags)
    gravity = (sc.gravity.density, sc.gravity.acceleration) if sc.gravity.enabled else None
    return Scenario(sc, mesh, order, pinned, attached, region, springs, materials, normals, sites, gravity)


def _sites(mesh: TetMesh, sc: ScenarioConfig, normals: np.ndarray, supported: np.ndarray, tags: MeshTags | None = None,
           access: np.ndarray | None = None) -> IndentationSites | None:
    """The indentation's sites (None without one); ``access`` (a,) int the stored access region,
    or None to resolve ``sc.indentation.access`` on the mesh (with ``tags`` for rule ``tag``)."""
    if not sc.indentation.enabled:
        return None
    if access is None:
        access = surface_region(mesh, sc.indentation.access, "scenario.indentation.access", tags, normals)
    return indentation_sites(mesh, sc.indentation, normals, supported, access=np.asarray(access, dtype=np.int64))


def restore_scenario(mesh: TetMesh, config: Config, arrays: dict) -> Scenario:
    """A scenario from its :meth:`Scenario.arrays` (e.g. read back from a data set), without
    the mesh file's named regions: the supports, materials and the indentation's access region
    are the stored ones (a store without ``indent_access`` resolves ``config``'s); normals and
    indentation sites are recomputed from them, the mesh and ``config``."""
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
    supported = np.union1d(pinned, attached)
    sites = _sites(mesh, sc, normals, supported, access=arrays.get("indent_access"))
    gravity = (sc.gravity.density, sc.gravity.acceleration) if sc.gravity.enabled else None
    return Scenario(sc, mesh, order, pinned, attached, np.asarray(arrays["spring_region"], dtype=np.int64), springs,
                    materials, normals, sites, gravity)


def scenario_markers(mesh: TetMesh, config: Config, tags: MeshTags | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The markers and pins ``[markers]`` gives with this scenario
    (:func:`~tissuecast.markers.markers_and_fixed`): no pins with ``scenario.pins = false``,
    and no marker on the vertices ``scenario.attached`` holds (they never move).

    Returns:
        ``(markers (n_d,) int64, pins (k,) int64)``, 0-based.
    """
    from ..markers import markers_and_fixed

    held = surface_region(mesh, config.scenario.attached, "scenario.attached", tags)
    markers, fixed = markers_and_fixed(mesh, config.markers, pins=config.scenario.pins, held=held)
    return np.asarray(markers, dtype=np.int64), np.asarray(fixed, dtype=np.int64)


def scenario_from_config(config: Config):
    """The mesh, fiducial markers, pinned vertices and resolved scenario a config describes.

    The mesh is ``mesh.path`` (with its named regions, :func:`~tissuecast.mesh.tags.read_mesh_tags`)
    or the built-in phantom; material draws use ``dataset.seed``.

    Returns:
        ``(mesh, markers (n_d,) int64, fixed (k,) int64, scenario)``: ``fixed`` are the pins
        (empty with ``scenario.pins = false``, when none are chosen).
    """
    from ..mesh.source import mesh_from_config
    from ..mesh.tags import mesh_file_tags

    mesh = mesh_from_config(config.mesh)
    tags = mesh_file_tags(config.mesh.path)
    markers, fixed = scenario_markers(mesh, config, tags)
    return mesh, markers, fixed, build_scenario(mesh, config, fixed, tags, material_seed=config.dataset.seed)
