"""Scenario building blocks: surface lumping, regions, mesh-file tags, springs, gravity loads,
indentation draws, material regions, the rigid-motion check and tractions."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import box_grid, regular_tet

from tissuecast.config import Config, IndentationConfig, RegionConfig, config_to_dict, with_overrides
from tissuecast.errors import ConfigError, MeshError, SolverSetupError
from tissuecast.fem.springs import NodalSprings
from tissuecast.forces import traction_loads
from tissuecast.mesh import phantom, write_mesh
from tissuecast.mesh.surface import lumped_areas, surface_nodes, vertex_normals
from tissuecast.mesh.tags import MeshTags, read_mesh_tags
from tissuecast.scenario import (
    body_loads,
    build_scenario,
    cone_direction,
    draw_indentation,
    element_materials,
    free_rigid_motions,
    gravity_body_force,
    indentation_sites,
    material_rng,
    scenario_rng,
    surface_region,
    surface_springs,
)

BOX = box_grid(3, 4, 5, (2.0, 2.0, 2.0))  # 6 x 8 x 10 mm


def _face(mesh, axis, value):
    return np.flatnonzero(np.isclose(mesh.points[:, axis], value))


# ------------------------------------------------------------------------ surface lumping
def test_hrz_lumping_is_the_rescaled_diagonal_of_the_6_node_triangles_mass_matrix():
    """HRZ: integral(N_a^2) dA of the 6-node triangle's shape functions (a degree-5 rule, exact
    for these degree-4 integrands), rescaled to sum to the area: positive at the corners too."""
    mesh = regular_tet(3.0)
    tri = mesh.surface_triangles[:1]
    area = 0.25 * np.sqrt(3.0) * 9.0
    a, b, c1, c2 = 0.059715871789770, 0.470142064105115, 0.797426985353087, 0.101286507323456
    pts = np.array([[1 / 3, 1 / 3, 1 / 3], [a, b, b], [b, a, b], [b, b, a], [c1, c2, c2], [c2, c1, c2], [c2, c2, c1]])
    w = np.array([0.225] + [0.132394152788506] * 3 + [0.125939180544827] * 3)
    lam = pts.T  # (3, q) barycentric coordinates
    shape = np.vstack([lam * (2.0 * lam - 1.0), 4.0 * lam[0] * lam[1], 4.0 * lam[1] * lam[2], 4.0 * lam[2] * lam[0]])
    diagonal = (shape**2 * w).sum(axis=1)  # per unit area
    np.testing.assert_allclose(diagonal[:3], 1.0 / 30.0, rtol=1e-12)  # the textbook 6/180 and 32/180
    np.testing.assert_allclose(diagonal[3:], 8.0 / 45.0, rtol=1e-12)
    expected = area * diagonal / diagonal.sum()
    nodes, lumped, _ = lumped_areas(mesh, tri, 2, "hrz")
    corners_then_mids = surface_nodes(mesh, tri, 2)[0]
    np.testing.assert_array_equal(nodes, np.sort(corners_then_mids))
    np.testing.assert_allclose(lumped[np.searchsorted(nodes, corners_then_mids)], expected, rtol=1e-12)
    np.testing.assert_allclose(lumped_areas(mesh, tri, 1, "hrz")[1], lumped_areas(mesh, tri, 1)[1], rtol=0)  # P1: same
    with pytest.raises(ValueError, match="lumping rule"):
        lumped_areas(mesh, tri, 2, "consistent")


def test_lumped_areas_are_the_integrals_of_the_shape_functions_on_one_triangle():
    mesh = regular_tet(3.0)
    tri = mesh.surface_triangles[:1]
    area = 0.25 * np.sqrt(3.0) * 9.0
    nodes, lumped, normal = lumped_areas(mesh, tri, 1)
    np.testing.assert_array_equal(nodes, np.sort(tri[0]))
    np.testing.assert_allclose(lumped, area / 3.0, rtol=1e-14)
    nodes, lumped, normal = lumped_areas(mesh, tri, 2)  # 6-node triangle: 0 at corners, A/3 at mid-edge nodes
    assert len(nodes) == 3 and np.all(nodes >= mesh.n_vertices)
    np.testing.assert_allclose(lumped, area / 3.0, rtol=1e-14)
    # the outward normal of the face, at every node
    p = mesh.points[tri[0]]
    n = np.cross(p[1] - p[0], p[2] - p[0])
    np.testing.assert_allclose(normal, np.tile(n / np.linalg.norm(n), (3, 1)), atol=1e-14)
    assert np.dot(n, p[0] - mesh.points.mean(axis=0)) > 0.0


@pytest.mark.parametrize("order", [1, 2])
def test_lumped_areas_are_positive_and_sum_to_the_surface_area(order):
    mesh = phantom()
    nodes, lumped, normal = lumped_areas(mesh, mesh.surface_triangles, order)
    assert np.all(lumped > 0.0)
    assert lumped.sum() == pytest.approx(mesh.surface_area, rel=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    assert len(nodes) == (len(mesh.surface_vertices) if order == 1 else 3 * len(mesh.surface_triangles) // 2)
    mids = surface_nodes(mesh, mesh.surface_triangles, 2)[:, 3:]
    np.testing.assert_allclose(mesh.points10[mids[:, 0]],
                               0.5 * (mesh.points[mesh.surface_triangles[:, 0]] + mesh.points[mesh.surface_triangles[:, 1]]))


def test_vertex_normals_of_a_box_face_point_out():
    n = vertex_normals(BOX)
    top = _face(BOX, 2, 10.0)
    inner_top = top[(BOX.points[top, 0] > 0) & (BOX.points[top, 0] < 6) & (BOX.points[top, 1] > 0)
                    & (BOX.points[top, 1] < 8)]
    np.testing.assert_allclose(n[inner_top], np.tile([0.0, 0.0, 1.0], (len(inner_top), 1)), atol=1e-12)
    assert np.all(n[BOX.interior_vertices] == 0.0)


# -------------------------------------------------------------------------------- regions
def test_region_rules_select_the_expected_surface_vertices():
    top = _face(BOX, 2, 10.0)
    inner = top[(BOX.points[top, 0] % 6.0 > 0) & (BOX.points[top, 1] % 8.0 > 0)]
    np.testing.assert_array_equal(
        surface_region(BOX, RegionConfig(rule="normal", direction=(0.0, 0.0, 2.0), angle=1.0), "k"), inner)
    sel = surface_region(BOX, RegionConfig(rule="normal", direction=(0.0, 0.0, 2.0), angle=60.0), "k")
    assert np.isin(inner, sel).all() and np.isin(sel, top).all() and len(sel) > len(inner)  # edges lean 27-55 degrees
    near = surface_region(BOX, RegionConfig(rule="distance", point=(0.0, 0.0, 0.0), distance=2.01), "k")
    np.testing.assert_array_equal(near, np.flatnonzero(np.linalg.norm(BOX.points, axis=1) <= 2.01))
    ids = surface_region(BOX, RegionConfig(rule="ids", ids=tuple(int(i) for i in np.r_[BOX.interior_vertices[:2], top[:3]])), "k")
    np.testing.assert_array_equal(ids, np.sort(top[:3]))  # interior ids are dropped
    np.testing.assert_array_equal(surface_region(BOX, RegionConfig(rule="surface"), "k"), BOX.surface_vertices)
    assert surface_region(BOX, RegionConfig(), "k").size == 0


def test_region_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"scenario.attached: rule 'distance' selects no surface vertex.*nearest"):
        surface_region(BOX, RegionConfig(rule="distance", point=(50.0, 0.0, 0.0), distance=1.0), "scenario.attached")
    with pytest.raises(ConfigError, match="scenario.attached: rule 'ids' selects no surface vertex"):
        surface_region(BOX, RegionConfig(rule="ids", ids=(int(BOX.interior_vertices[0]),)), "scenario.attached")
    with pytest.raises(ConfigError, match=r"scenario.springs.ids \[9999\] are outside"):
        surface_region(BOX, RegionConfig(rule="ids", ids=(9999,)), "scenario.springs")
    with pytest.raises(ConfigError, match=r"scenario.attached.tag: the mesh has no region named 'back'.*: none"):
        surface_region(BOX, RegionConfig(rule="tag", tag="back"), "scenario.attached")


def test_mesh_file_tags_round_trip_through_vtu_and_abaqus(tmp_path):
    pytest.importorskip("meshio")
    from tissuecast.fem import calculix as cx
    from tissuecast.fem.material import NeoHookean

    mesh = BOX
    back = np.isclose(mesh.points[:, 1], 0.0).astype(np.int32) * 3
    region = np.where(mesh.points[mesh.tets].mean(axis=1)[:, 2] < 5.0, 1, 2).astype(np.int32)
    write_mesh(tmp_path / "m.vtu", mesh, point_data={"back": back}, cell_data={"region": region})
    tags = read_mesh_tags(tmp_path / "m.vtu")
    assert set(tags.names()) >= {"back", "region"}
    np.testing.assert_array_equal(tags.vertices("back"), _face(mesh, 1, 0.0))
    np.testing.assert_array_equal(tags.vertices("back", 3), _face(mesh, 1, 0.0))
    assert tags.vertices("back", 2).size == 0
    np.testing.assert_array_equal(tags.tet_data["region"], region)
    np.testing.assert_array_equal(tags.vertices("region", 2), np.unique(mesh.tets[region == 2]))
    sel = surface_region(mesh, RegionConfig(rule="tag", tag="back", tag_value=3), "k", tags)
    np.testing.assert_array_equal(sel, _face(mesh, 1, 0.0))
    with pytest.raises(MeshError, match=r"no region named 'front'.*'back', 'region'"):
        tags.vertices("front")
    # a C3D10 deck: the mid-edge nodes are dropped on reading, the NSET keeps the vertex ids
    deck = cx.write_inp(tmp_path / "m.inp", mesh, NeoHookean(), [0], np.zeros((mesh.n_vertices, 3)),
                        node_sets={"TOP": _face(mesh, 2, 10.0)})
    tags = read_mesh_tags(deck)
    np.testing.assert_array_equal(tags.vertices("TOP"), _face(mesh, 2, 10.0))
    assert read_mesh_tags(tmp_path / "m.vtu").point_sets == {} and MeshTags().names() == []


# -------------------------------------------------------------------------------- springs
@pytest.mark.parametrize("order", [1, 2])
def test_springs_hold_a_face_with_its_area_times_the_stiffness(order):
    bottom = _face(BOX, 2, 0.0)
    springs = surface_springs(BOX, bottom, order, 0.003, 0.001)
    k = springs.stiffness
    # a uniform translation u is resisted by (k_n u_n + k_t u_t) times the face's area (48 mm^2)
    u = np.zeros((BOX.n_points if order == 1 else len(BOX.points10), 3))
    u[:] = [0.5, -0.2, 0.4]
    total = springs.forces(u).sum(axis=0)
    np.testing.assert_allclose(total, -48.0 * np.array([0.001 * 0.5, 0.001 * -0.2, 0.003 * 0.4]), rtol=1e-12)
    assert springs.energy(u) == pytest.approx(-0.5 * total @ [0.5, -0.2, 0.4], rel=1e-12)
    # normal (-z) eigenvalue k_n A_a, tangential k_t A_a, at every node
    lam = np.linalg.eigvalsh(k)
    np.testing.assert_allclose(lam[:, 2] / lam[:, 0], 3.0, rtol=1e-12)
    iso = surface_springs(BOX, bottom, order, 0.002, 0.002).stiffness
    np.testing.assert_allclose(iso, iso[:, :1, :1] * np.eye(3)[None], atol=1e-15)
    # 4x5 vertices; P2 (HRZ, the default): and the face's 15 + 16 + 12 mid-edge nodes
    assert len(springs) == (20 if order == 1 else 63)
    row_sum = surface_springs(BOX, bottom, order, 0.003, 0.001, lumping="row-sum")
    assert len(row_sum) == (20 if order == 1 else 43)  # P2: the mid-edge nodes alone
    np.testing.assert_allclose(row_sum.forces(u).sum(axis=0), total, rtol=1e-12)


def test_nodal_springs_refuse_bad_stiffness():
    with pytest.raises(SolverSetupError, match="shape"):
        NodalSprings([0, 1], np.zeros((1, 3, 3)))
    with pytest.raises(SolverSetupError, match="symmetric"):
        NodalSprings([0], np.triu(np.ones((3, 3)))[None])
    with pytest.raises(SolverSetupError, match="positive semi-definite"):
        NodalSprings([0], -np.eye(3)[None])
    with pytest.raises(SolverSetupError, match="distinct"):
        NodalSprings([1, 1], np.zeros((2, 3, 3)))


# -------------------------------------------------------------------------------- gravity
def test_consistent_body_loads_of_one_tetrahedron():
    mesh = regular_tet(2.0)
    b = np.array([0.0, 1e-5, -2e-5])
    v = mesh.volume
    p2 = body_loads(mesh, 2, b)
    np.testing.assert_allclose(p2[:4], np.tile(-v / 20.0 * b, (4, 1)), rtol=1e-14, atol=1e-20)
    np.testing.assert_allclose(p2[4:], np.tile(v / 5.0 * b, (6, 1)), rtol=1e-14, atol=1e-20)
    np.testing.assert_allclose(body_loads(mesh, 1, b), np.tile(v / 4.0 * b, (4, 1)), rtol=1e-14, atol=1e-20)
    mesh = phantom()
    for order in (1, 2):
        np.testing.assert_allclose(body_loads(mesh, order, b).sum(axis=0), b * mesh.volume, rtol=1e-12)


def test_gravity_change_and_its_cone():
    g = gravity_body_force(1e-9, 9810.0, (0.0, 0.0, -1.0), (0.0, -2.0, 0.0))
    np.testing.assert_allclose(g, 9.81e-6 * np.array([0.0, -1.0, 1.0]), rtol=1e-14)
    rng = np.random.default_rng(0)
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    d = np.array([cone_direction(rng, axis * 3.0, 30.0) for _ in range(4000)])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-14)
    cos = d @ axis
    assert cos.min() >= np.cos(np.radians(30.0)) - 1e-12
    # uniform on the cap: cos of the polar angle is uniform in [cos 30, 1] (mean 0.933, sd 0.0387)
    assert abs(cos.mean() - 0.5 * (1.0 + np.cos(np.radians(30.0)))) < 4 * 0.0387 / np.sqrt(4000)
    # azimuth spread evenly: the mean direction lies on the axis
    assert np.linalg.norm(d.mean(axis=0) / np.linalg.norm(d.mean(axis=0)) - axis) < 0.01
    np.testing.assert_allclose(cone_direction(rng, axis, 0.0), axis, atol=1e-15)


# ---------------------------------------------------------------------------- indentation
def test_indentation_sites_and_draws():
    mesh = phantom()
    normals = vertex_normals(mesh)
    supported = surface_region(mesh, RegionConfig(rule="normal", direction=(0.0, -1.0, 0.0), angle=30.0), "k")
    cfg = IndentationConfig(enabled=True, radius=5.0, depth=(2.0, 6.0), slide=(0.5, 2.0), clearance=8.0)
    sites = indentation_sites(mesh, cfg, normals, supported)
    gap = np.array([np.linalg.norm(mesh.points[supported] - mesh.points[c], axis=1).min() for c in sites.centres])
    assert gap.min() >= 8.0 and sites.weights.sum() == pytest.approx(1.0)
    for patch, c in zip(sites.patches, sites.centres):
        assert len(patch) >= 3 and not np.isin(patch, supported).any()
        assert np.linalg.norm(mesh.points[patch] - mesh.points[c], axis=1).max() <= 5.0
    draws = [draw_indentation(np.random.default_rng(s), sites, cfg) for s in range(50)]
    for ind in draws:
        n = ind.normal
        assert 2.0 <= ind.depth <= 6.0 and 0.5 <= ind.slide <= 2.0
        assert -ind.displacement @ n == pytest.approx(ind.depth, rel=1e-12)
        tangential = ind.displacement + ind.depth * n
        assert np.linalg.norm(tangential) == pytest.approx(ind.slide, rel=1e-12)
        assert ind.centre in ind.vertices
    again = draw_indentation(np.random.default_rng(7), sites, cfg)
    np.testing.assert_array_equal(again.displacement, draws[7].displacement)
    assert len({d.centre for d in draws}) > 30
    with pytest.raises(ConfigError, match=r"radius = 0.1 mm holds fewer than 3"):
        indentation_sites(mesh, IndentationConfig(radius=0.1), normals, supported)
    with pytest.raises(ConfigError, match="no surface vertex is 500 mm away"):
        indentation_sites(mesh, IndentationConfig(clearance=500.0), normals, supported)


def test_a_rounded_tool_follows_the_hertz_profile_and_a_flat_one_moves_its_patch_together():
    from tissuecast.scenario.indentation import contact_profile

    mesh = phantom()
    normals = vertex_normals(mesh)
    supported = surface_region(mesh, RegionConfig(rule="normal", direction=(0.0, -1.0, 0.0), angle=30.0), "k")
    flat = IndentationConfig(enabled=True, radius=8.0, depth=(2.0, 6.0), slide=(0.5, 2.0))
    rounded = IndentationConfig(enabled=True, radius=8.0, depth=(2.0, 6.0), slide=(0.5, 2.0), tool="rounded",
                                tool_radius=5.0)
    sites = indentation_sites(mesh, flat, normals, supported)
    for seed in range(20):
        f = draw_indentation(np.random.default_rng(seed), sites, flat)
        r = draw_indentation(np.random.default_rng(seed), sites, rounded)
        # the same draws: centre, depth, slide and the tip's displacement
        assert f.centre == r.centre and f.depth == r.depth
        np.testing.assert_array_equal(f.displacement, r.displacement)
        np.testing.assert_array_equal(f.values, np.repeat(f.displacement[None, :], len(f.vertices), axis=0))
        assert set(r.vertices) <= set(f.vertices) and len(r.vertices) >= 3
        n = r.normal
        tangential = r.displacement + r.depth * n
        rel = mesh.points[r.vertices] - mesh.points[r.centre]
        rt = np.linalg.norm(rel - np.outer(rel @ n, n), axis=1)
        # push along the inward normal: depth - r^2 / 2R; the tangential slide is the tip's
        np.testing.assert_allclose(-(r.values - tangential) @ n, r.depth - rt**2 / 10.0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r.values - np.outer(r.values @ n, n), np.repeat(tangential[None], len(rt), 0),
                                   atol=1e-12)
        a = np.sqrt(5.0 * r.depth)
        outside = rt > a + 1e-12
        assert outside.sum() <= 3  # only the nearest three are kept beyond the Hertz radius
    inside, push = contact_profile(np.array([0.0, 1.0, 2.0, 3.0, 4.0]), 3.2, 5.0)  # a = 4 mm
    np.testing.assert_array_equal(inside, [True] * 5)
    np.testing.assert_allclose(push, [3.2, 3.1, 2.8, 2.3, 1.6])  # half the depth at the contact's rim
    assert contact_profile(np.array([4.5, 5.0, 6.0, 7.0]), 3.2, 5.0)[0].tolist() == [True, True, True, False]
    with pytest.raises(ConfigError, match=r"scenario.indentation.radius = 4 mm is smaller than the rounded tool's "
                                          r"largest contact radius .* = 5.48 mm"):
        with_overrides(Config(), scenario={"indentation": {"enabled": True, "radius": 4.0, "depth": [2.0, 6.0],
                                                           "tool": "rounded", "tool_radius": 5.0}})


def test_indentation_centres_lie_in_the_access_region_and_survive_a_store_round_trip():
    from tissuecast.scenario import restore_scenario

    mesh = phantom()
    access = {"rule": "normal", "direction": [0.0, -1.0, 0.0], "angle": 35.0}
    scenario = {"pins": False, "attached": {"rule": "normal", "direction": [0.0, 1.0, 0.0], "angle": 45.0},
                "springs": {"rule": "surface"}, "indentation": {"enabled": True, "access": access}}
    cfg = with_overrides(Config(), scenario=scenario)
    sc = build_scenario(mesh, cfg, np.zeros(0, dtype=int))
    normals = vertex_normals(mesh)
    region = surface_region(mesh, RegionConfig(**access), "k")
    np.testing.assert_array_equal(sc.sites.access, region)
    assert np.isin(sc.sites.centres, region).all() and 0 < len(sc.sites.centres) <= len(region)
    assert (normals[sc.sites.centres] @ [0.0, -1.0, 0.0] >= np.cos(np.radians(35.0)) - 1e-12).all()
    anywhere = build_scenario(mesh, with_overrides(cfg, scenario={"indentation": {"access": {"rule": "surface"}}}),
                              np.zeros(0, dtype=int))
    assert len(anywhere.sites.centres) > 2 * len(sc.sites.centres)
    # a data set stores the access region; restoring gives the same sites and the same draws
    again = restore_scenario(mesh, cfg, sc.arrays())
    np.testing.assert_array_equal(again.sites.centres, sc.sites.centres)
    d1, d2 = sc.draw(scenario_rng(11)), again.draw(scenario_rng(11))
    assert d1.indentation.centre == d2.indentation.centre
    summary = sc.summary()["indentation"]
    assert summary["access_rule"] == "normal" and summary["access_vertices"] == len(region)
    with pytest.raises(ConfigError, match=r"scenario.indentation.access.rule = 'none' is not allowed"):
        with_overrides(cfg, scenario={"indentation": {"access": {"rule": "none"}}})
    with pytest.raises(ConfigError, match=r"scenario.indentation.access: rule 'distance' selects no surface vertex"):
        build_scenario(mesh, with_overrides(cfg, scenario={"indentation": {"access": {
            "rule": "distance", "point": [500.0, 0.0, 0.0], "distance": 5.0}}}), np.zeros(0, dtype=int))
    with pytest.raises(ConfigError, match=r"no vertex of the access region \(scenario.indentation.access\) is 8 mm away"):
        build_scenario(mesh, with_overrides(cfg, scenario={"indentation": {"access": {
            "rule": "normal", "direction": [0.0, 1.0, 0.0], "angle": 30.0}}}), np.zeros(0, dtype=int))


# ------------------------------------------------------------------------------ materials
def test_material_regions_by_cell_data_and_distance():
    from tissuecast.config import MaterialConfig, MaterialRegionConfig, MaterialRegionsConfig

    mesh = BOX
    centroid = mesh.points[mesh.tets].mean(axis=1)
    region = np.where(centroid[:, 2] < 5.0, 1, 2)
    tags = MeshTags(tet_data={"region": region})
    cfg = MaterialRegionsConfig(cell_data="region", regions=(
        MaterialRegionConfig(name="low", value=1, youngs_modulus=0.05, youngs_modulus_range=(0.04, 0.08)),
        MaterialRegionConfig(name="ball", rule="distance", point=(3.0, 4.0, 5.0), distance=2.5, poisson_ratio=0.3)))
    mats = element_materials(mesh, MaterialConfig(), cfg, tags)
    ball = np.linalg.norm(centroid - [3.0, 4.0, 5.0], axis=1) <= 2.5
    assert ball.any() and (ball & (region == 1)).any()
    np.testing.assert_array_equal(mats.youngs_modulus[(region == 1) & ~ball], 0.05)  # nominal without a generator
    np.testing.assert_array_equal(mats.youngs_modulus[ball], 0.021)  # the later region wins
    np.testing.assert_array_equal(mats.poisson_ratio[ball], 0.3)
    np.testing.assert_array_equal(mats.region[(region == 2) & ~ball], -1)
    drawn = element_materials(mesh, MaterialConfig(), cfg, tags, material_rng(5))
    e = drawn.draws["low"]["youngs_modulus"]
    again = element_materials(mesh, MaterialConfig(), cfg, tags, material_rng(5)).draws["low"]["youngs_modulus"]
    assert 0.04 <= e <= 0.08 and e == again
    assert e != element_materials(mesh, MaterialConfig(), cfg, tags, material_rng(6)).draws["low"]["youngs_modulus"]
    groups = drawn.groups()
    assert sorted(len(ids) for _, _, ids in groups) == sorted(np.unique(drawn.region, return_counts=True)[1].tolist())
    with pytest.raises(ConfigError, match=r"no cell data 'regions' per tetrahedron \(it has: 'region'\)"):
        element_materials(mesh, MaterialConfig(), MaterialRegionsConfig(cell_data="regions", regions=cfg.regions), tags)
    empty = MaterialRegionsConfig(cell_data="region", regions=(MaterialRegionConfig(name="x", value=7),))
    with pytest.raises(ConfigError, match=r"regions\[0\] \('x'\): no element has region = 7"):
        element_materials(mesh, MaterialConfig(), empty, tags)


# ---------------------------------------------------------------------- whole scenario
EMBEDDED = {"pins": False, "attached": {"rule": "normal", "direction": [0, -1, 0], "angle": 30.0},
            "springs": {"rule": "surface"}, "gravity": {"enabled": True}, "indentation": {"enabled": True}}


def test_free_rigid_motions_counts_what_the_supports_leave():
    pts = BOX.points
    line = np.flatnonzero(np.isclose(pts[:, 0], 0.0) & np.isclose(pts[:, 1], 0.0))  # a straight edge
    free = free_rigid_motions(pts, line)
    assert len(free) == 1 and np.allclose(free[0][3:5], 0.0, atol=1e-12) and abs(free[0][5]) > 0.5  # turning about z
    size = np.ptp(pts, axis=0).max()
    moved = free[0][:3] + np.cross(free[0][3:], (pts[line] - pts.mean(axis=0)) / size)
    np.testing.assert_allclose(moved, 0.0, atol=1e-12)  # ... about the held edge itself
    off = np.flatnonzero(np.isclose(pts, [2.0, 0.0, 0.0]).all(axis=1))
    assert len(free_rigid_motions(pts, np.r_[line, off])) == 0
    assert len(free_rigid_motions(pts, np.zeros(0, dtype=int))) == 6
    top = _face(BOX, 2, 10.0)
    normal_only = surface_springs(BOX, top, 1, 0.002, 0.0)
    assert len(free_rigid_motions(pts, np.zeros(0, dtype=int), normal_only)) == 3  # slides and turns in its plane
    assert len(free_rigid_motions(pts, np.zeros(0, dtype=int), surface_springs(BOX, top, 1, 0.002, 0.002))) == 0


def test_build_scenario_paper_and_embedded():
    mesh = phantom()
    cfg = Config()
    fixed = np.array([100, 200, 300])
    sc = build_scenario(mesh, cfg, fixed)
    np.testing.assert_array_equal(sc.pinned, fixed)
    assert sc.springs is None and sc.sites is None and sc.gravity is None and sc.materials is None
    draw = sc.draw(scenario_rng(1))
    assert draw.gravity_direction is None and draw.indentation is None
    assert np.isnan(draw.record()["indent_depth"]) and sc.prescribed(draw)[0].size == 0
    assert not sc.body_loads(draw).any()

    cfg = with_overrides(Config(), scenario=EMBEDDED)
    sc = build_scenario(mesh, cfg, fixed)
    assert sc.pinned.size == 0 and len(sc.attached) > 10
    held = np.r_[sc.attached, mesh.n_vertices + np.flatnonzero(np.isin(mesh.edges, sc.attached).all(axis=1))]
    assert not np.isin(sc.springs.nodes, held).any()  # no spring where the tissue is attached
    draw = sc.draw(scenario_rng(11))
    again = sc.draw(scenario_rng(11))
    assert draw.record() == again.record()
    g = draw.gravity_direction
    assert g @ [0.0, 0.0, -1.0] >= np.cos(np.radians(30.0)) - 1e-12
    np.testing.assert_allclose(sc.body_loads(draw).sum(axis=0), 1e-9 * 9810.0 * (g - [0, 0, -1]) * mesh.volume,
                               rtol=1e-12)
    ids, values = sc.prescribed(draw)
    np.testing.assert_array_equal(ids, draw.indentation.vertices)
    np.testing.assert_array_equal(values, np.tile(draw.indentation.displacement, (len(ids), 1)))
    summary = sc.summary()
    assert summary["springs"]["nodes"] == len(sc.springs) and summary["indentation"]["sites"] == len(sc.sites.centres)


def test_build_scenario_refuses_supports_that_leave_rigid_motion():
    flat = {"pins": False, "springs": {"rule": "normal", "direction": [0, -1, 0], "angle": 1.0,
                                       "tangential_stiffness": 0.0}}  # normal springs on one flat face
    with pytest.raises(ConfigError, match=r"leave 3 rigid-body motion\(s\) free \(a rotation, a translation\)"):
        build_scenario(BOX, with_overrides(Config(), scenario=flat), np.zeros(0, dtype=int))
    mesh = phantom()
    two = {"pins": False, "attached": {"rule": "ids", "ids": [int(v) for v in mesh.surface_vertices[:2]]}}
    with pytest.raises(ConfigError, match=r"leave 1 rigid-body motion\(s\) free \(a rotation\)"):
        build_scenario(mesh, with_overrides(Config(), scenario=two), np.zeros(0, dtype=int))
    whole = {"pins": False, "springs": {"rule": "surface", "tangential_stiffness": 0.0}}
    assert len(build_scenario(mesh, with_overrides(Config(), scenario=whole), np.zeros(0, dtype=int)).springs) > 0


# ------------------------------------------------------------------------------- tractions
@pytest.mark.parametrize("order", [1, 2])
def test_a_uniform_traction_gives_the_textbook_consistent_loads(order):
    """Vertex forces t A_v read as a traction are the uniform traction t: P1 loads t A/3 per
    triangle vertex; P2 nothing on the corners and t A/3 on each mid-edge node."""
    mesh = phantom()
    t = np.array([0.002, -0.001, 0.003])
    nodes, area, _ = lumped_areas(mesh, mesh.surface_triangles, 1)
    f = np.zeros((mesh.n_vertices, 3))
    f[nodes] = area[:, None] * t
    loads = traction_loads(mesh, order, f)
    np.testing.assert_allclose(loads.sum(axis=0), f.sum(axis=0), rtol=1e-12)
    if order == 1:
        np.testing.assert_allclose(loads, f, rtol=1e-12, atol=1e-18)
    else:
        np.testing.assert_allclose(loads[: mesh.n_vertices], 0.0, atol=1e-17)
        mids = surface_nodes(mesh, mesh.surface_triangles, 2)[:, 3:]
        tri_area = np.zeros(len(mesh.points10))
        corners = mesh.points[mesh.surface_triangles]
        a = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        for k in range(3):
            np.add.at(tri_area, mids[:, k], a / 3.0)
        np.testing.assert_allclose(loads[mesh.n_vertices:], tri_area[mesh.n_vertices:, None] * t, rtol=1e-12, atol=1e-18)


def test_embedded_preset_is_the_paper_set_up_held_by_its_surroundings():
    from tissuecast.app.presets import preset_config
    from tissuecast.config import DEFAULT_SUPPORT_STIFFNESS
    from tissuecast.scenario import scenario_from_config
    from tissuecast.scenario.regions import surface_region

    emb, paper = preset_config("embedded"), preset_config("paper")
    # paper-size set, the paper's elements, material and surrogate (but the networks' training)
    for section in ("dataset", "surrogate", "material", "markers"):
        a, b = (config_to_dict(getattr(c, section)) for c in (emb, paper))
        a.pop("store", None), b.pop("store", None)
        a.pop("count", None), b.pop("count", None)  # 10 markers: 5 leave most of this strain unseen (docs/scenarios.md)
        a.pop("rule", None), b.pop("rule", None)  # planned: they see where the tissue is attached (docs/uncertainty.md)
        for key in ("calibration", "calibration_folds", "calibration_share"):  # both calibrate bounds and alarm
            a.pop(key, None), b.pop(key, None)
        for key in ("batch_size", "predictor_tolerance"):  # speed settings of the paper preset (32, 0.04)
            a.pop(key, None), b.pop(key, None)
        a.pop("predictor", None), b.pop("predictor", None)  # the embedded samples solved along their load path
        # the networks train on the simulator's sensitivities (docs/surrogate.md): wider, smooth, shorter
        for key in ("hidden", "activation", "sensitivity_weight", "sensitivity_directions", "epochs"):
            a.pop(key, None), b.pop(key, None)
        # a nominal expert beside the uncertainty-trained model (docs/uncertainty.md)
        for key in ("nominal_expert", "nominal_samples"):
            a.pop(key, None), b.pop(key, None)
        a.pop("fallback_epochs", None), b.pop("fallback_epochs", None)  # the retractor's fallback: docs/surrogate.md
        assert a == b, section
    assert emb.surrogate.nominal_expert and 0 < emb.surrogate.nominal_samples < emb.dataset.n_samples
    assert 0 < emb.surrogate.fallback_epochs < emb.surrogate.epochs and not paper.scenario.instruments
    assert emb.scenario.uncertain.arcsine == ("attached_margin",)  # the attached rim: docs/uncertainty.md
    assert emb.surrogate.calibration_share > 0.0 and paper.surrogate.calibration == "cross-validation"
    assert emb.surrogate.sensitivity_weight > 0 and emb.surrogate.activation == "silu"
    assert paper.surrogate.sensitivity_weight == 0 and paper.surrogate.activation == "relu"  # the paper's network
    # linear tetrahedra: P2 solves of this spring-held body stall near a local instability (docs/scenarios.md);
    # each sample along its load path from zero, so that it lands on the equilibrium the loading reaches
    assert emb.solver.order == 1 and emb.solver.strategy == "krylov" and emb.forces.loading == "traction"
    assert emb.solver.initial_increment <= 0.1 and emb.dataset.predictor == "none"
    assert 15.0 <= emb.forces.target_max_displacement <= 30.0 and emb.forces.n_basis == 6
    sc = emb.scenario
    assert not sc.pins and sc.lbo_forces and sc.gravity.enabled and sc.indentation.enabled
    assert sc.springs.rule == "surface" and sc.attached.rule == "normal"
    # loose surroundings: the tissue's modulus over 40 mm (the default support is over 10 mm)
    assert sc.springs.normal_stiffness == sc.springs.tangential_stiffness == pytest.approx(DEFAULT_SUPPORT_STIFFNESS / 4)
    assert DEFAULT_SUPPORT_STIFFNESS == pytest.approx(emb.material.youngs_modulus / 10.0)
    mesh, markers, fixed, built = scenario_from_config(emb)
    assert len(fixed) == 0 and not np.isin(markers, built.attached).any()  # no marker where nothing moves
    # the nominal attached face, and the static support at its smallest extent (the uncertain margin's lower end)
    nominal = surface_region(mesh, sc.attached, "scenario.attached")
    assert built.pinned.size == 0 and 0.05 * mesh.n_vertices < len(nominal) < 0.25 * len(mesh.surface_vertices)
    assert emb.scenario.uncertain.attached_margin[0] < 0.0 and 0 < len(built.attached) < len(nominal)
    assert np.isin(built.attached, nominal).all() and emb.markers.count == 10
    assert built.springs is not None and built.sites is not None and built.gravity == (1.0e-9, 9810.0)
    # the retractor's access point lies on the anterior face (opposite the attached one), clear of the supports
    assert sc.indentation.access.rule == "distance" and len(built.sites.centres) >= 1
    normals = built.normals[built.sites.centres]
    assert (normals @ [0.0, -1.0, 0.0] > np.cos(np.radians(45.0))).all()
