"""TetMesh: orientation, outer surface, edges, quadratic nodes, volume and quality on known meshes."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import CUBE_6_TETS, CUBE_POINTS, box_grid, cube, regular_tet

from tissuecast.errors import MeshError
from tissuecast.mesh import TET_EDGES, TetMesh, phantom


def enclosed_volume(mesh: TetMesh) -> float:
    """Divergence theorem: V = sum over outward triangles (a, b, c) of a . (b x c) / 6."""
    p = mesh.points[mesh.surface_triangles]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("split, n_edges, n_flipped", [(5, 18, 2), (6, 19, 3)])
def test_cube_split_counts(split, n_edges, n_flipped):
    m = cube(split, side=10.0)
    assert m.n_vertices == m.n_points == 8 and m.n_tets == split
    assert len(m.surface_triangles) == 12
    assert m.surface_vertices.tolist() == list(range(8))
    assert m.interior_vertices.size == 0
    assert len(m.edges) == n_edges
    assert m.n_flipped == n_flipped  # these hand-written tets are partly inverted
    assert m.volume == pytest.approx(1000.0, rel=1e-12)
    assert m.surface_area == pytest.approx(600.0, rel=1e-12)
    assert np.all(m.tet_volumes > 0)
    assert enclosed_volume(m) == pytest.approx(1000.0, rel=1e-12)


def test_cube5_volumes_are_one_third_and_sixths():
    m = cube(5, side=1.0)
    assert sorted(np.round(m.tet_volumes, 12).tolist()) == pytest.approx([1 / 6] * 4 + [1 / 3])


def test_orientation_fix_is_counted_and_idempotent():
    good = TetMesh(CUBE_POINTS, CUBE_6_TETS)
    fixed = good.tets.copy()
    bad = fixed.copy()
    bad[[0, 2, 5]] = bad[[0, 2, 5]][:, [1, 0, 2, 3]]  # invert three tets
    m = TetMesh(CUBE_POINTS, bad)
    assert m.n_flipped == 3
    assert np.all(m.tet_volumes > 0)
    assert TetMesh(m.points, m.tets).n_flipped == 0
    np.testing.assert_allclose(m.tet_volumes, good.tet_volumes)


def test_surface_normals_point_outward_on_phantom():
    m = phantom()
    assert enclosed_volume(m) == pytest.approx(m.volume, rel=1e-10)
    # and each surface normal points away from the tet that owns the face
    p = m.points[m.surface_triangles]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    centre = m.points.mean(axis=0)
    assert (np.einsum("ij,ij->i", normal, p.mean(axis=1) - centre) > 0).mean() > 0.95


@pytest.mark.parametrize("nx, ny, nz", [(1, 1, 1), (2, 3, 4), (5, 2, 3)])
def test_structured_box_counts_follow_formulas(nx, ny, nz):
    h = (0.5, 2.0, 1.5)
    m = box_grid(nx, ny, nz, size=h)
    assert m.n_vertices == (nx + 1) * (ny + 1) * (nz + 1)
    assert m.n_tets == 6 * nx * ny * nz
    assert len(m.surface_triangles) == 4 * (nx * ny + ny * nz + nx * nz)
    assert len(m.surface_vertices) == m.n_vertices - (nx - 1) * (ny - 1) * (nz - 1)
    assert len(m.interior_vertices) == (nx - 1) * (ny - 1) * (nz - 1)
    axis = nx * (ny + 1) * (nz + 1) + (nx + 1) * ny * (nz + 1) + (nx + 1) * (ny + 1) * nz
    face = nx * ny * (nz + 1) + nx * (ny + 1) * nz + (nx + 1) * ny * nz
    assert len(m.edges) == axis + face + nx * ny * nz
    lx, ly, lz = nx * h[0], ny * h[1], nz * h[2]
    assert m.volume == pytest.approx(lx * ly * lz, rel=1e-12)
    assert m.surface_area == pytest.approx(2 * (lx * ly + ly * lz + lx * lz), rel=1e-12)
    np.testing.assert_allclose(m.extent, [lx, ly, lz])
    # Euler characteristic of a sphere-like surface
    s = m.surface_triangles
    e = np.unique(np.sort(s[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    assert len(m.surface_vertices) - len(e) + len(s) == 2
    assert enclosed_volume(m) == pytest.approx(m.volume, rel=1e-12)


def test_edges_are_sorted_unique_pairs():
    m = box_grid(2, 2, 2)
    e = m.edges
    assert np.all(e[:, 0] < e[:, 1])
    assert len(np.unique(e, axis=0)) == len(e)
    assert m.vertex_adjacency.nnz == 2 * len(e)


def test_tets10_midpoints():
    m = box_grid(2, 1, 1, size=(1.0, 2.0, 3.0))
    t10, p10 = m.tets10, m.points10
    assert t10.shape == (m.n_tets, 10) and p10.shape == (m.n_vertices + len(m.edges), 3)
    np.testing.assert_array_equal(t10[:, :4], m.tets)
    for k, (a, b) in enumerate(TET_EDGES):
        np.testing.assert_allclose(p10[t10[:, 4 + k]], 0.5 * (m.points[m.tets[:, a]] + m.points[m.tets[:, b]]))
    # every mid-edge node is shared by all tets around its edge: n + e distinct nodes in total
    assert len(np.unique(t10)) == m.n_vertices + len(m.edges)


def test_quality_of_regular_tet_is_one():
    q = regular_tet(edge=2.0).quality
    assert q.radius_ratio_min == pytest.approx(1.0, abs=1e-12)
    assert q.edge_ratio_max == pytest.approx(1.0, abs=1e-12)
    assert q.edge_length_mean == pytest.approx(2.0)
    assert q.volume_min == pytest.approx(2.0**3 / (6 * np.sqrt(2)))


def test_radius_ratio_of_cube_tets():
    # all tets inscribed in the cube's circumsphere, R = sqrt(3)/2; inradius r = 3 V / A
    kuhn = cube(6, side=1.0).quality  # V = 1/6, A = 1 + sqrt 2
    assert kuhn.radius_ratio_min == pytest.approx(3 * (0.5 / (1 + np.sqrt(2))) / (np.sqrt(3) / 2), rel=1e-12)
    assert kuhn.radius_ratio_mean == pytest.approx(kuhn.radius_ratio_min, rel=1e-12)
    five = cube(5, side=1.0).quality  # corner tets: V = 1/6, A = 3/2 + sqrt(3)/2
    assert five.radius_ratio_min == pytest.approx(np.sqrt(3) - 1, rel=1e-12)
    assert five.edge_ratio_max == pytest.approx(np.sqrt(2), rel=1e-12)


def test_deformed_and_scaled():
    m = cube(5)
    u = np.zeros((8, 3))
    u[:, 2] = m.points[:, 2]  # stretch z by 2
    assert m.deformed(u).volume == pytest.approx(2000.0)
    assert m.scaled(0.1).volume == pytest.approx(1.0)
    with pytest.raises(MeshError, match="displacement must have shape"):
        m.deformed(np.zeros((7, 3)))


def test_fingerprint_changes_with_coordinates_and_ignores_tiny_noise():
    m = cube(5)
    assert m.fingerprint() == TetMesh(m.points + 1e-9, m.tets).fingerprint()
    assert m.fingerprint() != TetMesh(m.points + 1e-3, m.tets).fingerprint()
