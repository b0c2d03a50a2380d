"""Clinical scenarios: how the tissue is held (pins, an attached region, an elastic support by
its surroundings) and what loads it per sample (LBO forces, a change of gravity, an
instrument's indentation), with per-element materials. Configured by ``[scenario]``
(:class:`~tissuecast.config.ScenarioConfig`). There is always a scenario: the paper's set-up
(pins and LBO nodal forces) is the default one.

Public API::

    from tissuecast.scenario import build_scenario, scenario_rng
    sc = build_scenario(mesh, config, fixed, tags=read_mesh_tags(path))
    inputs = sc.sample(sample_seed, alpha, beta)   # SampleInputs: everything one sample needs
    inputs.surface, inputs.solve_keywords()        # (n_nodes, 3) N; body_loads, prescribed
    inputs.forces, inputs.weights, inputs.draw     # what a data set records
    problem = sc.problem()                         # supports, springs, material regions
    sc.springs                                     # NodalSprings: (s,) nodes, (s, 3, 3) N/mm

Units: mm, N, MPa, t/mm^3; ids 0-based.
"""

from .elastic_support import region_triangles, surface_springs
from .gravity import body_loads, cone_direction, gravity_body_force
from .indentation import Indentation, IndentationSites, draw_indentation, indentation_sites
from .materials import ElementMaterials, element_materials, material_rng
from .pins import pins_from_config, select_fixed_vertices
from .regions import surface_region
from .resolve import build_scenario, restore_scenario, scenario_from_config, scenario_markers
from .sample_inputs import SampleInputs, ScenarioDraw
from .scenario import Scenario, contact_rng, scenario_rng
from .surface_forces import SurfaceForces
from ..fem.rigid_motions import free_rigid_motions
from ..mesh.surface import lumped_areas, vertex_normals

__all__ = [
    "Scenario",
    "ScenarioDraw",
    "SampleInputs",
    "SurfaceForces",
    "select_fixed_vertices",
    "pins_from_config",
    "build_scenario",
    "scenario_markers",
    "restore_scenario",
    "scenario_from_config",
    "scenario_rng",
    "contact_rng",
    "free_rigid_motions",
    "surface_region",
    "surface_springs",
    "region_triangles",
    "lumped_areas",
    "vertex_normals",
    "body_loads",
    "cone_direction",
    "gravity_body_force",
    "Indentation",
    "IndentationSites",
    "indentation_sites",
    "draw_indentation",
    "ElementMaterials",
    "element_materials",
    "material_rng",
]
