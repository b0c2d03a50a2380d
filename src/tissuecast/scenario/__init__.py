"""Clinical scenarios: how the tissue is held (pins, an attached region, an elastic support by
its surroundings) and what loads it per sample (LBO forces, a change of gravity, an
instrument's indentation), with per-element materials. Configured by ``[scenario]``
(:class:`~tissuecast.config.ScenarioConfig`).

Public API::

    from tissuecast.scenario import build_scenario, scenario_rng
    sc = build_scenario(mesh, config, fixed, tags=read_mesh_tags(path))
    draw = sc.draw(scenario_rng(sample_seed))
    loads = sc.body_loads(draw)            # (n_nodes, 3) N, consistent gravity-change loads
    ids, values = sc.prescribed(draw)      # the indentation patch, mm
    sc.springs                             # NodalSprings: (s,) nodes, (s, 3, 3) N/mm

Units: mm, N, MPa, t/mm^3; ids 0-based.
"""

from .gravity import body_loads, cone_direction, gravity_body_force
from .indentation import Indentation, IndentationSites, draw_indentation, indentation_sites
from .materials import ElementMaterials, element_materials, material_rng
from .regions import surface_region
from .scenario import (Scenario, ScenarioDraw, build_scenario, free_rigid_motions, restore_scenario, scenario_from_config,
                       scenario_markers, scenario_rng)
from .springs import region_triangles, surface_springs
from ..mesh.surface import lumped_areas, vertex_normals

__all__ = [
    "Scenario",
    "ScenarioDraw",
    "build_scenario",
    "scenario_markers",
    "restore_scenario",
    "scenario_from_config",
    "scenario_rng",
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
