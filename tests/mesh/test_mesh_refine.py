"""Uniform refinement: geometry, numbering, and finite-element solutions that converge."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.fem import Problem, Solver
from tissuecast.fem.material import NeoHookean
from tissuecast.mesh import phantom
from tissuecast.mesh.refine import refine_uniformly, refine_vertex_set
from tissuecast.scenario.gravity import body_loads


def test_refinement_keeps_volume_numbering_orientation_and_shape():
    coarse = phantom()
    r = refine_uniformly(coarse)
    fine = r.mesh
    assert fine.n_tets == 8 * coarse.n_tets and fine.n_vertices == coarse.n_vertices + len(coarse.edges)
    assert fine.volume == pytest.approx(coarse.volume, rel=1e-12)
    assert (fine.tet_volumes > 0).all()
    np.testing.assert_array_equal(fine.points[: coarse.n_vertices], coarse.points)  # coarse ids kept
    np.testing.assert_array_equal(fine.points, coarse.points10)
    # children fill their parent: per-parent volumes add up
    np.testing.assert_allclose(np.bincount(r.parent, weights=fine.tet_volumes), coarse.tet_volumes, rtol=1e-12)
    assert len(fine.surface_triangles) == 4 * len(coarse.surface_triangles)
    # the shortest-diagonal rule keeps the shapes: a second refinement loses no quality
    twice = refine_uniformly(fine).mesh
    assert twice.quality.radius_ratio_min >= 0.95 * coarse.quality.radius_ratio_min
    assert twice.quality.edge_length_mean == pytest.approx(coarse.quality.edge_length_mean / 4, rel=0.05)


def test_vertex_fields_and_sets_map_between_the_levels():
    coarse = box_grid(2, 2, 3, (5.0, 5.0, 5.0))
    r = refine_uniformly(coarse)
    linear = coarse.points @ np.array([[1.0, 0.0, 2.0], [0.5, -1.0, 0.0], [0.0, 3.0, 1.0]])
    np.testing.assert_allclose(r.from_coarse(linear), r.mesh.points @ np.array([[1.0, 0.0, 2.0], [0.5, -1.0, 0.0],
                                                                                [0.0, 3.0, 1.0]]), atol=1e-12)
    np.testing.assert_array_equal(r.coarse_values(r.from_coarse(linear)), linear)
    # a quadratic field of the coarse nodes is the same quadratic on the refined nodes
    def quadratic(x):
        return np.column_stack([x[:, 0] ** 2 - x[:, 1] * x[:, 2], 3.0 * x[:, 1] + x[:, 0] * x[:, 2], x[:, 2] ** 2])

    np.testing.assert_allclose(r.from_coarse_quadratic(quadratic(coarse.points10)), quadratic(r.mesh.points10),
                               atol=1e-9)
    face = np.flatnonzero(np.isclose(coarse.points[:, 2], 0.0))
    np.testing.assert_array_equal(refine_vertex_set(r, face), np.flatnonzero(np.isclose(r.mesh.points[:, 2], 0.0)))


def _sagging_block(mesh, order: int) -> np.ndarray:
    """A 10 x 10 x 30 mm block held at its base, bending under a sideways body force."""
    base = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.0))
    problem = Problem(mesh, NeoHookean(), base, order=order)
    loads = body_loads(mesh, order, np.array([2.0e-6, 0.0, 0.0]))
    loads[problem.constrained_nodes[0]] = 0.0  # the base's share goes straight into the support
    return Solver(problem).solve(np.zeros((mesh.n_vertices, 3)), body_loads=loads).displacement


def test_solutions_on_refined_meshes_converge_and_linear_tetrahedra_lock():
    """Quadratic tetrahedra: the error at the coarse vertices against the twice-refined answer
    falls > 3x per halving of h; linear ones at nu = 0.45 lock: twice refined, still worse than
    quadratic ones on the coarsest mesh."""
    levels = [box_grid(1, 1, 3, (10.0, 10.0, 10.0))]
    for _ in range(2):
        levels.append(refine_uniformly(levels[-1]).mesh)
    n = levels[0].n_vertices
    reference = _sagging_block(levels[2], 2)[:n]
    assert reference[:, 0].max() > 1.0  # a real bend (mm)
    p2 = [np.abs(_sagging_block(m, 2)[:n] - reference).max() for m in levels[:2]]
    assert p2[0] / p2[1] > 3.0
    p1_finest = np.abs(_sagging_block(levels[2], 1)[:n] - reference).max()
    assert p1_finest > 1.5 * p2[0]
