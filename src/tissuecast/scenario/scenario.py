"""A clinical scenario on a mesh: its supports, its materials and its per-sample loads.

There is always a scenario; the paper's set-up (pins and LBO nodal forces) is the default
one. A :class:`Scenario` (resolved on a mesh by :func:`~.resolve.build_scenario`, or rebuilt
from a data set's arrays by :func:`~.resolve.restore_scenario`) holds the supports (the pins,
the attached surface region, the elastic support :class:`~tissuecast.fem.springs.NodalSprings`),
the per-element materials, the eligible indentation sites and the random surface force
fields (:class:`~.surface_forces.SurfaceForces`).

Per sample, :meth:`Scenario.sample` gives everything the solver needs and a data set records
(:class:`~.sample_inputs.SampleInputs`) from the sample's seed: the surface force field (from
``default_rng(seed)``), then the gravity direction and the indentation
(:meth:`Scenario.draw`, from the sample's scenario generator :func:`scenario_rng`, a stream of
its own, so that the LBO weights drawn from the sample seed stay those of the paper's
set-up), and the loads that follow from them. Ids are 0-based; mm, N, MPa, t/mm^3.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..config import UNCERTAIN_PARAMETERS, ScenarioConfig
from ..fem.material import NeoHookean
from ..fem.springs import NodalSprings
from ..instruments import InstrumentPose, ReferenceSurface
from ..mesh.tetmesh import TetMesh
from .gravity import body_loads, cone_direction, gravity_body_force
from .indentation import IndentationSites, draw_indentation, indentation_at
from .materials import ElementMaterials
from .parameters import UncertainParameters, parameter_rng
from .sample_inputs import SampleInputs, ScenarioDraw
from .surface_forces import SurfaceForces

__all__ = ["Scenario", "ScenarioDraw", "SampleInputs", "scenario_rng", "contact_rng", "SCENARIO_STREAM",
           "CONTACT_STREAM"]

#: Second SeedSequence word of a sample's scenario draws: ``SeedSequence([sample_seed, SCENARIO_STREAM])``.
SCENARIO_STREAM = 2**63 - 3
#: Second SeedSequence word of a sample's contact draw (``scenario.indentation.probability`` < 1).
CONTACT_STREAM = 2**63 - 5


def scenario_rng(sample_seed) -> np.random.Generator:
    """The generator of a sample's scenario draws (module notes)."""
    return np.random.default_rng(np.random.SeedSequence([int(sample_seed), SCENARIO_STREAM]))


def contact_rng(sample_seed) -> np.random.Generator:
    """The generator of a sample's contact draw: one uniform number u; the instrument touches
    the tissue when ``u < scenario.indentation.probability``."""
    return np.random.default_rng(np.random.SeedSequence([int(sample_seed), CONTACT_STREAM]))


@dataclass(frozen=True, eq=False)
class Scenario:
    """A scenario resolved on a mesh (see :func:`~.resolve.build_scenario`).

    Attributes:
        config: the scenario settings.
        mesh: the mesh (mm).
        order: element order (1 or 2).
        material: the neo-Hookean constants of ``[material]`` (MPa): every element without a
            material region of its own.
        pinned: (p,) int64 pinned vertices (empty without ``pins``).
        attached: (a,) int64 surface vertices of the attached region (all components fixed).
        spring_region: (s,) int64 surface vertices of the elastic support's region.
        springs: the nodal springs (none at held nodes), or None.
        materials: per-element constants, or None (the ``[material]`` section everywhere).
        normals: (n, 3) outward unit vertex normals (zero inside).
        sites: where indentations may be drawn, or None.
        gravity: ``(density t/mm^3, |g| mm/s^2)`` when the gravity change is on, else None.
        surface_forces: the random surface force fields of the samples (LBO, test-2 LSC).
        uncertain: the parameters drawn per sample (:mod:`.parameters`), or None. With an
            uncertain attached extent, ``attached`` is the region at its smallest extent.
    """

    config: ScenarioConfig
    mesh: TetMesh
    order: int
    material: NeoHookean
    pinned: np.ndarray
    attached: np.ndarray
    spring_region: np.ndarray
    springs: NodalSprings | None
    materials: ElementMaterials | None
    normals: np.ndarray
    sites: IndentationSites | None
    gravity: tuple | None
    surface_forces: SurfaceForces
    uncertain: UncertainParameters | None = None

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
        return held_nodes_of(self.mesh, self.order, self.supported)

    @property
    def loading(self) -> str:
        """How the surface force field loads the body: ``"nodal"`` (forces on the vertices, the
        paper's) or ``"traction"`` (``forces.loading``)."""
        return self.surface_forces.settings.loading

    @property
    def hangs_on_pins(self) -> bool:
        """Whether the body hangs on its pins under the surface force field alone: pins are its
        only support (:attr:`can_swing`), the LBO field applied as nodal forces is its only
        load (no gravity change, no indentation) and one material fills it (the paper's
        set-up). Such a body swings about its pins as a near-rigid body, which the linear
        response misjudges: the force calibration then starts from a small dimensional
        estimate (nearly linear first pilots), checks that the pins leave no near-mechanism,
        and starts those pilots warm from zero (:mod:`tissuecast.dataset.calibrate`)."""
        return bool(self.can_swing and self.config.pins and self.config.lbo_forces and self.loading == "nodal"
                    and not self.draws_per_sample and self.materials is None)

    @property
    def draws_per_sample(self) -> bool:
        """Whether samples draw a gravity direction or an indentation."""
        return self.gravity is not None or self.sites is not None

    @property
    def can_swing(self) -> bool:
        """Whether the body is held by pins alone (so it may swing about them as a near-rigid
        body); False with springs or an attached region."""
        return self.springs is None and len(self.attached) == 0

    def problem(self, material: NeoHookean | None = None):
        """The finite-element problem (:class:`~tissuecast.fem.Problem`): the supported vertices
        fixed, the springs, the material regions, the scenario's element order.

        Args:
            material: the constants of elements without a region of their own; None = the
                scenario's :attr:`material`.
        """
        from ..fem import build_problem
        from ..fem.material import NeoHookeanField

        field = None
        if self.materials is not None:
            field = NeoHookeanField(self.materials.youngs_modulus, self.materials.poisson_ratio)
        return build_problem(self.mesh, self.material if material is None else material, self.supported,
                             order=self.order, springs=self.springs, materials=field, can_swing=self.can_swing)

    def sample(self, seed: int, alpha: float, beta: float = float("nan"), *, nominal: bool = False) -> SampleInputs:
        """Everything one sample is solved with and recorded by, from its seed alone.

        Args:
            seed: the sample's seed (``samples/seed`` of a data set).
            alpha: the surface force field's magnitude, N.
            beta: the LBO share of a test-2 sample; NaN for an LBO sample.
            nominal: keep the nominal parameters (draw no uncertain parameter).

        Returns:
            The sample's :class:`~.sample_inputs.SampleInputs`: its surface force field
            (:meth:`.SurfaceForces.field`, from ``default_rng(seed)``), its draws
            (:meth:`draw`, from :func:`scenario_rng`) and the loads and prescribed
            displacements they give.
        """
        forces, weights = self.surface_forces.field(seed, alpha, beta)
        return self.inputs_for(seed, forces, weights, nominal=nominal)

    def inputs_for(self, seed: int, forces: np.ndarray, weights: np.ndarray | None = None, *,
                   nominal: bool = False) -> SampleInputs:
        """A sample's inputs with a given surface force field ``forces`` ((n, 3) N, e.g. a data
        set's stored one) and the draws of its ``seed`` (:meth:`sample` draws the field too);
        ``nominal``: no uncertain parameter drawn."""
        forces = np.asarray(forces, dtype=np.float64)
        weights = np.zeros((0, 3)) if weights is None else weights
        draw = self.draw_for(seed, nominal=nominal)
        surface, body = self.sample_loads(draw, forces)
        ids, values = self.prescribed(draw)
        inputs = SampleInputs(forces, weights, surface, body if draw.body_force is not None else None, ids, values, draw)
        return inputs if draw.parameters is None else self.with_parameters(inputs, draw.parameters)

    def with_parameters(self, inputs: SampleInputs, p) -> SampleInputs:
        """``inputs`` under the parameters ``p`` (a :class:`~.parameters.ParameterDraw`, drawn or
        given): the density's factor on the body loads, the attached extent's vertices held at
        zero, and the sample's materials and springs."""
        u, c = self.uncertain, self.config.uncertain
        extra = u.extra_held(p, self.attached)
        ids = np.concatenate([inputs.prescribed_ids, extra]).astype(np.int64)
        values = np.vstack([inputs.prescribed_values, np.zeros((len(extra), 3))])
        body = None if inputs.body is None else inputs.body * p.density
        materials = springs = None
        if c.youngs_modulus or c.poisson_ratio or c.region_youngs_modulus:
            from ..fem.material import NeoHookeanField

            materials = NeoHookeanField(*u.element_constants(p))
        if c.spring_normal or c.spring_tangential:
            springs = u.springs(self.springs, p)
        return dataclasses.replace(inputs, body=body, prescribed_ids=ids, prescribed_values=values, parameters=p,
                                   materials=materials, springs=springs, extra_held=np.asarray(extra, dtype=np.int64))

    def sample_loads(self, draw: "ScenarioDraw", vertex_forces: np.ndarray | None = None,
                     loading: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A sample's external loads on every element node: ``(surface (n_nodes, 3) N, body
        (n_nodes, 3) N)``, both zero at the held nodes (loads there go straight into the
        supports).

        ``surface``: the field ``vertex_forces`` ((n, 3) N: the LBO or test-2 field, or None)
        as nodal forces on the vertices (``loading = "nodal"``, the paper's) or as a traction
        (``"traction"``, :func:`~tissuecast.forces.traction_loads`); None = the scenario's own
        :attr:`loading`. ``body``: the draw's consistent gravity-change loads (:meth:`body_loads`).
        """
        loading = self.loading if loading is None else loading
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
                     loading: str | None = None) -> tuple[np.ndarray, dict]:
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

    def loads(self, draw: "ScenarioDraw", vertex_forces: np.ndarray | None = None,
              loading: str | None = None) -> np.ndarray:
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
        if self.uncertain is not None and self.uncertain.distance is not None:
            out["attached_distance"] = self.uncertain.distance
        if self.uncertain is not None and self.uncertain.spring_parts is not None:
            out.update(spring_normal_part=self.uncertain.spring_parts[0],
                       spring_tangential_part=self.uncertain.spring_parts[1])
        return {k: np.asarray(v) for k, v in out.items()}

    def draw_for(self, seed: int, *, nominal: bool = False) -> ScenarioDraw:
        """Every draw of the sample with seed ``seed``: :meth:`draw` from :func:`scenario_rng`,
        the indentation dropped when the contact draw (:func:`contact_rng`, only with
        ``indentation.probability`` < 1) says the instrument is away, the uncertain parameters
        (:func:`~.parameters.parameter_rng`; none with ``nominal``) and the instruments' poses
        (:meth:`instrument_poses`)."""
        draw = self.draw(scenario_rng(seed))
        if draw.indentation is not None and self.config.indentation.probability < 1.0:
            if contact_rng(seed).random() >= self.config.indentation.probability:
                draw = dataclasses.replace(draw, indentation=None)
        if self.uncertain is not None and not nominal:
            draw = dataclasses.replace(draw, parameters=self.uncertain.draw(parameter_rng(seed)))
        if self.config.instruments:
            draw = dataclasses.replace(draw, instruments=self.instrument_poses(draw))
        return draw

    @cached_property
    def reference_surface(self) -> ReferenceSurface:
        """The mesh's outer surface (the depth and contact of an instrument tip)."""
        return ReferenceSurface.of(self.mesh)

    def instrument_poses(self, draw: ScenarioDraw) -> tuple[tuple[str, InstrumentPose], ...]:
        """``(name, pose)`` of each of ``scenario.instruments`` in a draw
        (:mod:`tissuecast.instruments`): an indentation's tool tip at the patch centre's
        reference position plus its displacement, pushing along the inward normal; away from
        the tissue when the draw has no indentation."""
        out = []
        for inst in self.config.instruments:  # load "indentation", the only one (config.INSTRUMENT_LOADS)
            ind = draw.indentation
            pose = InstrumentPose.away() if ind is None else self.reference_surface.pose(
                self.mesh.points[ind.centre] + ind.displacement, -ind.normal)
            out.append((inst.name, pose))
        return tuple(out)

    def frame_draw(self, poses: dict | None = None, gravity_direction=None) -> ScenarioDraw:
        """The loads navigation knows in a tracked frame, as a :class:`ScenarioDraw` without
        uncertain parameters: each instrument's indentation from its tracked pose
        (:func:`~.indentation.indentation_at`; none for an instrument away from the tissue) and
        the gravity change for the patient's position.

        Args:
            poses: ``{instrument name: InstrumentPose}`` in the model frame (LPS mm), one for
                each of ``scenario.instruments``.
            gravity_direction: (3,) the direction of gravity in surgery, model frame; None: the
                planned one (``scenario.gravity.surgery_direction``, the drawn cone's axis).

        Raises:
            ConfigError: an instrument's pose missing or not given as a pose, a pose the
                simulator cannot push with (:func:`~.indentation.indentation_at`), or a
                gravity direction that is not a non-zero finite vector.
        """
        from ..errors import ConfigError

        cfg = self.config
        poses = dict(poses or {})
        unknown = sorted(set(poses) - {inst.name for inst in cfg.instruments})
        if unknown:
            raise ConfigError(f"unknown instruments {unknown}; the scenario has {[i.name for i in cfg.instruments]}")
        ind = None
        for inst in cfg.instruments:  # load "indentation", the only one (config.INSTRUMENT_LOADS)
            pose = poses.get(inst.name)
            if not isinstance(pose, InstrumentPose):
                raise ConfigError(f"the pose of instrument {inst.name!r} is needed: where it pushes is a load of the "
                                  "simulator; give its tip and direction, or contact false when it is away")
            if pose.contact:
                ind = indentation_at(self.sites, cfg.indentation, self.mesh.points, pose.tip)
        direction = force = None
        if self.gravity is not None:
            g = cfg.gravity.surgery_direction if gravity_direction is None else gravity_direction
            direction = np.asarray(g, dtype=np.float64).reshape(-1)
            norm = float(np.linalg.norm(direction)) if direction.size == 3 else 0.0
            if not (np.isfinite(direction).all() and norm > 0.0):
                raise ConfigError(f"the gravity direction must be a non-zero finite (x, y, z) vector, got {g!r}")
            direction = direction / norm
            force = gravity_body_force(*self.gravity, cfg.gravity.imaging_direction, direction)
        draw = ScenarioDraw(direction, force, ind)
        if cfg.instruments:
            draw = dataclasses.replace(draw, instruments=tuple((i.name, poses[i.name]) for i in cfg.instruments))
        return draw

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
            if i.probability < 1.0:
                out["indentation"]["probability"] = i.probability
        if cfg.instruments:
            out["instruments"] = [{"name": x.name, "load": x.load} for x in cfg.instruments]
        if self.materials is not None:
            out["materials"] = self.materials.draws
        if self.uncertain is not None:
            u = cfg.uncertain
            out["uncertain"] = {name: list(getattr(u, name)) for name in UNCERTAIN_PARAMETERS if getattr(u, name)}
            out["uncertain"]["measured"] = list(u.measured)
            if u.nominal_share:
                out["uncertain"]["nominal_share"] = u.nominal_share
            if u.arcsine:
                out["uncertain"]["arcsine"] = list(u.arcsine)
        return out


def held_nodes_of(mesh: TetMesh, order: int, vertices: np.ndarray) -> np.ndarray:
    """Vertices held in all components and, for P2, the mid-edge nodes between two of them."""
    vertices = np.asarray(vertices, dtype=np.int64)
    if order == 1:
        return vertices
    both = np.isin(mesh.edges, vertices).all(axis=1)
    return np.concatenate([vertices, mesh.n_vertices + np.flatnonzero(both)])
