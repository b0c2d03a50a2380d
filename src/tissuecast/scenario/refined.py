"""A scenario's sample on a uniformly refined mesh: the same loads, resolved finer.

A mesh-converged reference of a sample (how far a data set's "truth" is from the physics)
solves the same sample on the refined mesh (:func:`~tissuecast.mesh.refine.refine_uniformly`,
each tetrahedron into eight; the coarse vertices keep their ids, so the answer is read on them
directly) with quadratic elements. "The same loads" means:

* the surface field read as a traction ``t_v = f_v / A_v`` on the coarse vertices, linear on
  each coarse triangle, is the same linear traction on the refined triangles (``"traction"``
  loading); nodal forces (``"nodal"``, the paper's) stay point loads on the same vertices;
* the gravity change is the same body force; the density's factor scales it;
* the supports are the refined vertices of the coarse regions (a coarse edge's midpoint
  belongs to a region when both its ends do): the pins, the attached region at the sample's
  extent, the elastic support's region with the sample's stiffnesses per unit area, lumped
  afresh on the refined surface;
* every refined element has its coarse parent's E and nu (the sample's);
* the indentation is the same instrument at the same place: the tool tip pushed by the same
  displacement at the same centre point, its patch resolved on the refined surface (a flat
  tool: the refined vertices of the coarse patch; a rounded tip: every refined surface vertex
  within the Hertz contact radius, :func:`~.indentation.contact_profile`).

Ids are 0-based; mm, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..fem.material import NeoHookeanField
from ..mesh.refine import RefinedMesh, refine_vertex_set
from ..mesh.surface import lumped_areas, vertex_normals
from .elastic_support import surface_springs
from .gravity import body_loads
from .indentation import PATCH_FACING_COS, contact_profile
from .sample_inputs import SampleInputs
from .scenario import Scenario, held_nodes_of

__all__ = ["RefinedSample", "refined_sample"]


@dataclass(frozen=True, eq=False)
class RefinedSample:
    """A sample on the refined mesh: its problem and what its solver takes.

    Attributes:
        problem: the :class:`~tissuecast.fem.Problem` on the refined mesh.
        surface: (n_nodes, 3) float64 N, the surface loads on every refined element node.
        keywords: ``body_loads`` and ``prescribed`` for :meth:`tissuecast.fem.Solver.solve`.
    """

    problem: object
    surface: np.ndarray
    keywords: dict


def _traction_field(scenario: Scenario, refined: RefinedMesh, forces: np.ndarray) -> np.ndarray:
    """The coarse vertex forces (n, 3) N as refined vertex forces carrying the same linear traction."""
    coarse, fine = scenario.mesh, refined.mesh
    nodes_c, area_c, _ = lumped_areas(coarse, coarse.surface_triangles, 1)
    nodes_f, area_f, _ = lumped_areas(fine, fine.surface_triangles, 1)
    traction = np.zeros_like(forces)
    traction[nodes_c] = forces[nodes_c] / area_c[:, None]
    traction = refined.from_coarse(traction)
    out = np.zeros_like(traction)
    out[nodes_f] = traction[nodes_f] * area_f[:, None]
    return out


def _surface_loads(scenario: Scenario, refined: RefinedMesh, inputs: SampleInputs, order: int) -> np.ndarray:
    fine = refined.mesh
    n_nodes = fine.n_vertices if order == 1 else len(fine.points10)
    out = np.zeros((n_nodes, 3))
    if scenario.loading == "traction":
        from ..forces import traction_loads

        out += traction_loads(fine, order, _traction_field(scenario, refined, inputs.forces))
    else:
        out[: scenario.mesh.n_vertices] += inputs.forces
    return out


def _indentation(scenario: Scenario, refined: RefinedMesh, inputs: SampleInputs,
                 free_surface: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(refined vertex ids, displacements (k, 3) mm)`` of the sample's indentation."""
    ind = inputs.draw.indentation
    if ind is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    cfg = scenario.config.indentation
    fine = refined.mesh
    if cfg.tool == "flat":
        ids = refine_vertex_set(refined, ind.vertices)
        return ids, np.repeat(ind.displacement[None, :], len(ids), axis=0)
    centre, n = scenario.mesh.points[ind.centre], ind.normal
    normals = vertex_normals(fine)
    near = free_surface[np.linalg.norm(fine.points[free_surface] - centre, axis=1) <= cfg.radius]
    near = near[normals[near] @ normals[ind.centre] >= PATCH_FACING_COS]
    rel = fine.points[near] - centre
    inside, push = contact_profile(np.linalg.norm(rel - np.outer(rel @ n, n), axis=1), ind.depth, cfg.tool_radius)
    tangential = ind.displacement + ind.depth * n
    return near[inside], -push[inside, None] * n[None, :] + tangential[None, :]


def _materials(scenario: Scenario, config: Config, inputs: SampleInputs, refined: RefinedMesh) -> NeoHookeanField:
    """Every refined element with its coarse parent's (the sample's) E and nu."""
    if inputs.materials is not None:
        e, nu = inputs.materials.youngs_modulus, inputs.materials.poisson_ratio
    elif scenario.materials is not None:
        e, nu = scenario.materials.youngs_modulus, scenario.materials.poisson_ratio
    else:
        m = scenario.mesh.n_tets
        e, nu = np.full(m, config.material.youngs_modulus), np.full(m, config.material.poisson_ratio)
    return NeoHookeanField(np.asarray(e)[refined.parent], np.asarray(nu)[refined.parent])


def _springs(scenario: Scenario, refined: RefinedMesh, inputs: SampleInputs, order: int, held: np.ndarray):
    """The elastic support on the refined surface at the sample's stiffnesses (None without one)."""
    if scenario.springs is None:
        return None
    s = scenario.config.springs
    p = inputs.parameters
    kn = s.normal_stiffness * (1.0 if p is None else p.spring_normal)
    kt = s.tangential_stiffness * (1.0 if p is None else p.spring_tangential)
    region = refine_vertex_set(refined, scenario.spring_region)
    return surface_springs(refined.mesh, region, order, kn, kt, s.lumping).without(held)


def refined_sample(scenario: Scenario, config: Config, refined: RefinedMesh, inputs: SampleInputs,
                   order: int = 2) -> RefinedSample:
    """A sample of ``scenario`` (its :class:`~.sample_inputs.SampleInputs`) on ``refined``,
    the uniform refinement of the scenario's mesh, with elements of ``order`` (module notes)."""
    from ..fem import Problem

    fine = refined.mesh
    held_extra = np.zeros(0, dtype=np.int64)
    if inputs.parameters is not None:  # the attached region at the sample's extent
        held_extra = scenario.uncertain.extra_held(inputs.parameters, scenario.attached)
    supported = refine_vertex_set(refined, np.union1d(scenario.attached, held_extra))
    supported = np.union1d(scenario.pinned, supported)
    held_nodes = held_nodes_of(fine, order, supported)
    free_surface = fine.surface_vertices[~np.isin(fine.surface_vertices, supported)]
    ids, values = _indentation(scenario, refined, inputs, free_surface)
    problem = Problem(fine, scenario.material, supported, order=order,
                      springs=_springs(scenario, refined, inputs, order, held_nodes),
                      materials=_materials(scenario, config, inputs, refined), can_swing=scenario.can_swing)
    surface = _surface_loads(scenario, refined, inputs, order)
    surface[held_nodes] = 0.0
    keywords = {}
    if inputs.body is not None:
        body = body_loads(fine, order, inputs.draw.body_force) * (1.0 if inputs.parameters is None
                                                                  else inputs.parameters.density)
        body[held_nodes] = 0.0
        keywords["body_loads"] = body
    if len(ids):
        keywords["prescribed"] = (ids, values)
    return RefinedSample(problem, surface, keywords)
