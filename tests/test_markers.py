"""Fiducial markers (revised k-center clustering) and fixed vertices."""

import numpy as np
import pytest

import tissuecast.mesh as tcmesh
from tissuecast.errors import MarkerError
from tissuecast.markers import (
    revised_k_center,
    select_fixed_vertices,
    select_markers,
    surface_depth,
    validate_vertex_ids,
)
from tissuecast.mesh.depth import point_triangle_distance
from tissuecast.mesh.tetmesh import TetMesh


def box_mesh(nx, ny, nz, h=1.0, jitter=0.0, seed=0):
    """Grid box [0, nx h] x [0, ny h] x [0, nz h], each cube cut into 6 Kuhn tets.

    ``jitter`` moves interior vertices by up to that many mm (keeps all tets valid when small).
    """
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    g = g.reshape(-1, 3).astype(float)

    def idx(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    kuhn = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
    tets = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                c = [idx(i + a, j + b, k + d) for a in (0, 1) for b in (0, 1) for d in (0, 1)]
                tets += [[c[q] for q in t] for t in kuhn]
    inner = np.all((g > 0) & (g < [nx, ny, nz]), axis=1)
    g[inner] += np.random.default_rng(seed).uniform(-jitter, jitter, (inner.sum(), 3))
    return TetMesh(g * h, np.array(tets))


def line_points(n):
    return np.c_[np.arange(float(n)), np.zeros(n), np.zeros(n)]


# ----------------------------------------------------------------------- k-center
# Points on a line at x = 0, 1, ..., 10 (id = x), start 0, d_min = 2.5:
#  (a) eligible: x > 2.5 -> {3..10}; average distance to {0} is x -> pick 10.
#  (b) eligible: min(x, 10 - x) > 2.5 -> {3..7}; distances (x, 10 - x) have variance
#      ((x - (10 - x)) / 2)^2 = (x - 5)^2 -> pick 5.  (A mean-only greedy sees the same
#      mean 5 for every candidate and would take the lowest id, 3.)
#  (a) eligible: no x has min(|x|, |x - 5|, |x - 10|) > 2.5 -> only 3 markers fit.
def test_line_picks_by_hand():
    np.testing.assert_array_equal(revised_k_center(line_points(11), 3, 0, 2.5), [0, 10, 5])
    assert revised_k_center(line_points(11), 3, 0, 2.5).dtype == np.int64


def test_line_too_many_markers_error_says_how_many():
    with pytest.raises(MarkerError, match=r"only 3 of 4 markers.*smaller min_distance or count"):
        revised_k_center(line_points(11), 4, 0, 2.5)


# A plane example (z = 0), ids 0..6:
#   0 (0,0)  1 (6,0)  2 (0,8)  3 (7,8)  4 (3,4)  5 (1,1)  6 (12,0);  start 0.
# d_min = 2:
#  (a) eligible: all but 5 (|0-5| = 1.41); mean distance = distance to 0: 6 is farthest (12).
#  (b) eligible {1,2,3,4}; distances to (0, 6): 1 (6, 6) var 0; 2 (8, 14.42) var 10.31;
#      3 (10.63, 9.43) var 0.36; 4 (5, 9.85) var 5.88 -> pick 1.  (mean-only would pick 2.)
#  (a) distances to (0, 6, 1): 2 (8, 14.42, 10) mean 10.81; 3 (10.63, 9.43, 8.06) mean 9.38;
#      4 (5, 9.85, 5) mean 6.62 -> pick 2.
#  (b) distances to (0, 6, 1, 2): 3 (10.63, 9.43, 8.06, 7) var 1.88; 4 (5, 9.85, 5, 5) var 4.41
#      -> pick 3.  Markers [0, 6, 1, 2, 3].
# d_min = 7.5: (a) eligible {2, 3, 6} -> 6; (b) eligible {2, 3} (1 and 4 are too close to 0):
#      var 2: 10.31, 3: 0.36 -> pick 3; (a) nothing is > 7.5 from {0, 6, 3} (2 is 7 from 3).
PLANE = np.array([(0, 0, 0), (6, 0, 0), (0, 8, 0), (7, 8, 0), (3, 4, 0), (1, 1, 0), (12, 0, 0)], float)


def test_plane_picks_by_hand():
    np.testing.assert_array_equal(revised_k_center(PLANE, 5, 0, 2.0), [0, 6, 1, 2, 3])
    # markers are a prefix of the pick order
    np.testing.assert_array_equal(revised_k_center(PLANE, 2, 0, 2.0), [0, 6])
    np.testing.assert_array_equal(revised_k_center(PLANE, 1, 4, 2.0), [4])


def test_min_distance_rule_excludes_near_points():
    np.testing.assert_array_equal(revised_k_center(PLANE, 3, 0, 7.5), [0, 6, 3])
    with pytest.raises(MarkerError, match="only 3 of 5"):
        revised_k_center(PLANE, 5, 0, 7.5)


def test_variance_step_differs_from_mean_only_greedy():
    picks = revised_k_center(PLANE, 3, 0, 2.0)
    # a mean-only greedy would take the eligible point with the largest mean distance to {0, 6}
    d = np.linalg.norm(PLANE[:, None] - PLANE[[0, 6]][None], axis=2)
    eligible = d.min(1) > 2.0
    mean_only = int(np.flatnonzero(eligible)[np.argmax(d.mean(1)[eligible])])
    assert mean_only == 2 and picks[2] == 1


def test_ties_go_to_lowest_id():
    # 1 and 2 are both 5 mm from 0: equal average distance -> the lower id, 1.
    pts = np.array([(0, 0, 0), (5, 0, 0), (-5, 0, 0), (0, 3, 0)], float)
    np.testing.assert_array_equal(revised_k_center(pts, 2, 0, 1.0), [0, 1])
    np.testing.assert_array_equal(revised_k_center(pts[[0, 2, 1, 3]], 2, 0, 1.0), [0, 1])


def test_matches_unvectorised_reference_on_random_points():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 50, (400, 3))
    got = revised_k_center(pts, 12, 7, 4.0)
    centers = [7]
    while len(centers) < 12:  # direct transcription of the algorithm, distances recomputed
        d = np.linalg.norm(pts[:, None] - pts[centers][None], axis=2)
        ok = d.min(1) > 4.0
        score = d.mean(1) if len(centers) % 2 == 1 else -d.var(1)
        centers.append(int(np.flatnonzero(ok)[np.argmax(score[ok])]))
    np.testing.assert_array_equal(got, centers)
    assert len(np.unique(got)) == 12
    d = np.linalg.norm(pts[got][:, None] - pts[got][None], axis=2)
    assert d[np.triu_indices(12, 1)].min() > 4.0


def test_select_markers_on_mesh_is_deterministic_and_accepts_points():
    mesh = box_mesh(4, 5, 9)
    a = select_markers(mesh, count=5, start=3, min_distance=2.0)
    np.testing.assert_array_equal(a, select_markers(mesh, count=5, start=3, min_distance=2.0))
    np.testing.assert_array_equal(a, select_markers(mesh.points, count=5, start=3, min_distance=2.0))
    assert a[0] == 3 and len(set(a.tolist())) == 5


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"count": 0}, "count must be an integer >= 1"),
        ({"count": 2.5}, "count must be an integer"),
        ({"start": 11}, r"outside 0\.\.10.*0-based"),
        ({"start": -1}, "outside"),
        ({"min_distance": -1.0}, "min_distance"),
        ({"min_distance": float("nan")}, "min_distance"),
    ],
)
def test_bad_arguments(kwargs, message):
    args = {"count": 2, "start": 0, "min_distance": 1.0} | kwargs
    with pytest.raises(MarkerError, match=message):
        select_markers(line_points(11), **args)


def test_bad_points():
    with pytest.raises(MarkerError, match=r"\(n, 3\)"):
        select_markers(np.zeros((4, 2)))


# ----------------------------------------------------------------- surface depth
def test_point_triangle_distance_matches_dense_sampling():
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(3, 3))
    p = rng.normal(scale=2.0, size=(300, 3))
    got = point_triangle_distance(p, *(np.broadcast_to(t, p.shape) for t in tri))
    u, v = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    keep = u + v <= 1
    samples = tri[0] + np.outer(u[keep], tri[1] - tri[0]) + np.outer(v[keep], tri[2] - tri[0])
    brute = np.array([np.linalg.norm(samples - q, axis=1).min() for q in p])
    assert np.all(got <= brute + 1e-12)
    np.testing.assert_allclose(got, brute, atol=0.02)


def test_surface_depth_of_a_box_is_distance_to_its_faces():
    # interior vertices jittered off the grid: the nearest surface *vertex* is farther than
    # the nearest face, so this checks the point-to-triangle distance
    mesh = box_mesh(4, 5, 7, h=2.0, jitter=0.3)
    p = mesh.points
    exact = np.minimum.reduce([p[:, 0], 8 - p[:, 0], p[:, 1], 10 - p[:, 1], p[:, 2], 14 - p[:, 2]])
    np.testing.assert_allclose(surface_depth(mesh), exact, atol=1e-12)
    assert surface_depth(mesh, mesh.surface_vertices).max() == 0.0


# ---------------------------------------------------------------- fixed vertices
def test_fixed_vertices_on_a_box_by_hand():
    mesh = box_mesh(6, 8, 14)  # 945 vertices, depths 0..3 mm
    fixed = select_fixed_vertices(mesh, rule="spread")
    # deep = depth >= 1.5, i.e. x in [2, 4], y in [2, 6], z in [2, 12].
    # candidates: the 3 x 5 x 11 grid x in [2, 4], y in [2, 6], z in [2, 12]; centroid (3, 4, 7).
    # 1st: farthest from the centroid: the 8 corners tie (squared distance 30) -> lowest id (2, 2, 2).
    # 2nd: farthest from (2, 2, 2): (4, 6, 12), squared distance 4 + 16 + 100 = 120.
    # 3rd: farthest from the line along a = (2, 4, 10): squared distance |r|^2 - (r.a)^2 / 120
    #      is 100 - 100^2/120 = 16.67 for (2, 2, 12) and 20 - 20^2/120 = 16.67 for (4, 6, 2);
    #      every other candidate is closer -> lower id (2, 2, 12).
    np.testing.assert_array_equal(mesh.points[fixed], [[2, 2, 2], [4, 6, 12], [2, 2, 12]])
    assert fixed.dtype == np.int64
    # one pin: the deepest (depth 3), lowest id -> (3, 3, 3)
    np.testing.assert_array_equal(mesh.points[select_fixed_vertices(mesh, count=1)], [[3, 3, 3]])
    # a 4th pin: farthest-point, the candidate whose nearest pin is farthest away: (4, 6, 6),
    # 6 mm from each of (2, 2, 2), (4, 6, 12) and (2, 2, 12) (e.g. (4, 6, 7) is 5 mm from (4, 6, 12))
    four = select_fixed_vertices(mesh, count=4, rule="spread")
    np.testing.assert_array_equal(four[:3], fixed)
    np.testing.assert_array_equal(mesh.points[four[3]], [4, 6, 6])


def test_compact_fixed_vertices_on_a_box_by_hand():
    mesh = box_mesh(6, 8, 14)  # ids grow with x, then y, then z fastest; candidates as above
    # 1st: the deepest candidate (depth 3), lowest id: (3, 3, 3).
    # spacing 1: 2nd: the six neighbours at 1 mm tie -> lowest id (2, 3, 3); 3rd: >= 1 mm from
    # both and >= 0.5 mm off their line, least largest distance: on this grid no point is 1 mm
    # from both, sqrt(2) is the least (8 ties) -> lowest id (2, 2, 3).
    fixed = select_fixed_vertices(mesh, rule="compact", spacing=1.0)
    np.testing.assert_array_equal(mesh.points[fixed], [[3, 3, 3], [2, 3, 3], [2, 2, 3]])
    # spacing 2: 2nd: only (3, 3, 5) and (3, 5, 3) are exactly 2 mm away (x in [2, 4]) -> (3, 3, 5);
    # 3rd: a point at squared distance 4 from both would need z = 4 and dx^2 + dy^2 = 3: none;
    # squared distance 5 from both: z = 4 and (dx, dy) = (0, +-2) -> (3, 5, 4) (y = 1 is too shallow).
    fixed = select_fixed_vertices(mesh, rule="compact", spacing=2.0)
    np.testing.assert_array_equal(mesh.points[fixed], [[3, 3, 3], [3, 3, 5], [3, 5, 4]])
    sep = np.linalg.norm(mesh.points[fixed][:, None] - mesh.points[fixed][None], axis=2)
    assert sep[np.triu_indices(3, 1)].min() >= 2.0
    # pinned triangle area: compact |(0, 0, 2) x (0, 2, 1)| / 2 = 2 mm^2; spread (see above)
    # |(2, 4, 10) x (0, 0, 10)| / 2 = 22.36 mm^2
    area = lambda f: np.linalg.norm(np.cross(*(mesh.points[f[1:]] - mesh.points[f[0]]))) / 2  # noqa: E731
    assert area(fixed) == pytest.approx(2.0)
    assert area(select_fixed_vertices(mesh, rule="spread")) == pytest.approx(22.36, abs=0.01)
    with pytest.raises(MarkerError, match=r"no room for 3 compact fixed vertices 20 mm apart.*smaller spacing"):
        select_fixed_vertices(mesh, rule="compact", spacing=20.0)
    with pytest.raises(MarkerError, match=r"unknown fixed-vertex rule 'tight'; use one of compact, spread"):
        select_fixed_vertices(mesh, rule="tight")
    with pytest.raises(MarkerError, match="spacing must be a positive length"):
        select_fixed_vertices(mesh, rule="compact", spacing=0.0)


def test_fixed_vertices_exclude_and_min_depth():
    mesh = box_mesh(6, 8, 14)
    first = select_fixed_vertices(mesh, rule="spread")[0]
    fixed = select_fixed_vertices(mesh, count=4, exclude=[first], rule="spread")
    assert first not in fixed
    assert np.all(surface_depth(mesh, fixed) >= 1.5)
    fixed = select_fixed_vertices(mesh, count=2, min_depth=3.0, rule="spread")
    np.testing.assert_allclose(surface_depth(mesh, fixed), 3.0)
    with pytest.raises(MarkerError, match=r"only 27 interior vertices.*smaller count"):
        select_fixed_vertices(mesh, count=28, min_depth=3.0)  # depth 3: 1 x 3 x 9 vertices


def test_fixed_vertices_need_interior_vertices():
    mesh = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]]))
    with pytest.raises(MarkerError, match="no interior vertices"):
        select_fixed_vertices(mesh)


# ------------------------------------------------------------------ validation
def test_validate_vertex_ids():
    mesh = box_mesh(2, 2, 2)  # 27 vertices
    np.testing.assert_array_equal(validate_vertex_ids(mesh, [3, 1, 26], "markers"), [3, 1, 26])
    with pytest.raises(MarkerError, match=r"markers \[27\] are outside 0\.\.26.*0-based"):
        validate_vertex_ids(mesh, [1, 27], "markers")
    with pytest.raises(MarkerError, match=r"repeat vertex ids \[4\]"):
        validate_vertex_ids(mesh, [4, 2, 4], "fixed vertices")
    with pytest.raises(MarkerError, match=r"vertices \[2\] are both fixed vertices and markers"):
        validate_vertex_ids(mesh, [2, 5], "fixed vertices", other=[2, 9])
    with pytest.raises(MarkerError, match="integer"):
        validate_vertex_ids(mesh, [1.5], "markers")
    with pytest.raises(MarkerError, match="no markers given"):
        validate_vertex_ids(mesh, [], "markers")
    with pytest.raises(MarkerError, match="flat list"):
        validate_vertex_ids(mesh, [[1, 2]], "markers")


# ------------------------------------------------------------------- phantom
@pytest.mark.skipif(not hasattr(tcmesh, "phantom"), reason="tissuecast.mesh.phantom not available yet")
def test_phantom_markers_and_fixed_vertices():
    mesh = tcmesh.phantom()
    markers = select_markers(mesh, count=5, start=96, min_distance=10.0)
    assert markers[0] == 96 and len(np.unique(markers)) == 5
    d = np.linalg.norm(mesh.points[markers][:, None] - mesh.points[markers][None], axis=2)
    assert d[np.triu_indices(5, 1)].min() > 10.0
    deepest = surface_depth(mesh, mesh.interior_vertices).max()
    fixed = select_fixed_vertices(mesh, count=3, exclude=markers, rule="spread")
    assert not np.isin(fixed, markers).any()
    assert np.isin(fixed, mesh.interior_vertices).all()
    depth = surface_depth(mesh, fixed)
    assert depth.min() >= 0.5 * deepest
    sep = np.linalg.norm(mesh.points[fixed][:, None] - mesh.points[fixed][None], axis=2)
    assert sep[np.triu_indices(3, 1)].min() > 10.0
    # a wide pinned triangle (the earlier rule's was 29 x 10 mm: the body swung about it)
    a, b, c = mesh.points[fixed]
    assert np.linalg.norm(b - a) > 50.0
    assert np.linalg.norm(np.cross(b - a, c - a)) / np.linalg.norm(b - a) > 14.0
    np.testing.assert_array_equal(fixed, [1129, 615, 646])
    # the default, compact: the deepest vertex and two more 5-6.3 mm away (a small real triangle)
    compact = select_fixed_vertices(mesh, count=3, exclude=markers)
    np.testing.assert_array_equal(compact, [769, 801, 703])
    assert surface_depth(mesh, compact[:1])[0] == pytest.approx(deepest)
    assert np.all(surface_depth(mesh, compact) >= 0.5 * deepest) and not np.isin(compact, markers).any()
    sep = np.linalg.norm(mesh.points[compact][:, None] - mesh.points[compact][None], axis=2)[np.triu_indices(3, 1)]
    assert 5.0 <= sep.min() and sep.max() < 6.5


# ------------------------------------------------------------ config-driven choice
def test_markers_and_fixed_from_config():
    from tissuecast.config import MarkerConfig
    from tissuecast.markers import markers_and_fixed

    mesh = box_mesh(6, 8, 14)
    cfg = MarkerConfig(count=4, start=5, min_distance=3.0, fixed_count=3)
    markers, fixed = markers_and_fixed(mesh, cfg)
    np.testing.assert_array_equal(markers, select_markers(mesh, count=4, start=5, min_distance=3.0))
    np.testing.assert_array_equal(fixed, select_fixed_vertices(mesh, count=3, exclude=markers))
    _, spread = markers_and_fixed(mesh, MarkerConfig(count=4, start=5, min_distance=3.0, fixed_rule="spread"))
    np.testing.assert_array_equal(spread, select_fixed_vertices(mesh, count=3, exclude=markers, rule="spread"))
    _, wide = markers_and_fixed(mesh, MarkerConfig(count=4, start=5, min_distance=3.0, fixed_spacing=2.0))
    np.testing.assert_array_equal(wide, select_fixed_vertices(mesh, count=3, exclude=markers, spacing=2.0))
    assert not np.array_equal(wide, fixed)
    markers, fixed = markers_and_fixed(mesh, MarkerConfig(ids=(1, 2), fixed_ids=(453, 7)))
    np.testing.assert_array_equal(markers, [1, 2])
    np.testing.assert_array_equal(fixed, [453, 7])
    with pytest.raises(MarkerError, match=r"\[2\] are both fixed vertices and markers"):
        markers_and_fixed(mesh, MarkerConfig(ids=(1, 2), fixed_ids=(2,)))
    # a deeper fixed-vertex rule
    _, fixed = markers_and_fixed(mesh, MarkerConfig(ids=(0,), fixed_depth_fraction=1.0, fixed_rule="spread"))
    np.testing.assert_allclose(surface_depth(mesh, fixed), 3.0)


def test_k_center_avoids_excluded_points_and_moves_an_excluded_start():
    pts = line_points(11)  # 0..10 mm on a line
    # by hand: 0, 10, 5 without exclusions; excluding 10 and 0 the ends become 9 and 1
    np.testing.assert_array_equal(revised_k_center(pts, 3, 1, 2.5, exclude=[0, 10]), [1, 9, 5])
    # a start among the excluded moves to the nearest free point (the lower id on a tie)
    np.testing.assert_array_equal(revised_k_center(pts, 3, 0, 2.5, exclude=[0, 10]), [1, 9, 5])
    with pytest.raises(MarkerError, match="every vertex is excluded"):
        revised_k_center(pts, 1, 0, 2.5, exclude=np.arange(11))
    np.testing.assert_array_equal(revised_k_center(pts, 3, 5, 2.5, exclude=[0, 1, 9, 10]), [5, 2, 8])
    with pytest.raises(MarkerError, match=r"only 1 of 2 markers"):
        revised_k_center(pts, 2, 5, 2.5, exclude=[0, 1, 2, 8, 9, 10])  # the free 3, 4, 6, 7 are within 2 mm of 5


def test_markers_and_fixed_avoid_held_vertices():
    from tissuecast.config import MarkerConfig
    from tissuecast.markers import markers_and_fixed

    mesh = box_mesh(6, 8, 14)  # 1 mm grid
    held = np.flatnonzero(mesh.points[:, 2] < 1e-9)  # the z = 0 face, attached
    markers, fixed = markers_and_fixed(mesh, MarkerConfig(count=4, start=0, min_distance=3.0), held=held)
    # the start vertex (0, 0, 0) is held: the nearest free surface vertex, (0, 0, 1), starts instead
    np.testing.assert_allclose(mesh.points[markers[0]], [0.0, 0.0, 1.0])
    assert not np.isin(markers, held).any() and len(markers) == 4 and not np.isin(fixed, markers).any()
    # the next pick (largest mean distance) is the far corner, as without the attached face
    np.testing.assert_allclose(mesh.points[markers[1]], [6.0, 8.0, 14.0])
    markers, fixed = markers_and_fixed(mesh, MarkerConfig(count=4, start=0, min_distance=3.0), pins=False, held=held)
    assert len(fixed) == 0
    # a surface start stays on the surface: with the surface held up to z = 1 the nearest free
    # vertex is the interior (1, 1, 1), 1.73 mm away, but the start moves to (0, 0, 2), 2 mm away
    surface = mesh.surface_vertices
    deeper = surface[mesh.points[surface, 2] < 1.0 + 1e-9]
    np.testing.assert_allclose(mesh.points[select_markers(mesh, count=1, start=0, exclude=deeper)[0]], [0.0, 0.0, 2.0])
    np.testing.assert_allclose(mesh.points[revised_k_center(mesh.points, 1, 0, exclude=deeper)[0]], [1.0, 1.0, 1.0])
    with pytest.raises(MarkerError, match=r"markers \[0\] lie in the attached region"):
        markers_and_fixed(mesh, MarkerConfig(ids=(0, 50)), held=held)
    with pytest.raises(MarkerError, match=r"excluded vertex ids \[9999\] are outside"):
        select_markers(mesh, count=2, start=5, exclude=[9999])
    with pytest.raises(MarkerError, match=r"excluded vertex ids must be integers, got float64"):
        select_markers(mesh, count=2, start=5, exclude=[1.5])


def test_the_pins_live_in_the_scenario_and_stay_importable_from_the_markers():
    """Pin selection is one of the scenario's supports (tissuecast.scenario.pins); the public
    names tissuecast.select_fixed_vertices and tissuecast.markers.select_fixed_vertices are it."""
    import tissuecast
    import tissuecast.markers as tm
    from tissuecast.scenario import pins

    assert tm.select_fixed_vertices is pins.select_fixed_vertices is tissuecast.select_fixed_vertices
    assert "select_fixed_vertices" in tm.__all__
    with pytest.raises(AttributeError, match="no attribute 'select_pins'"):
        tm.select_pins  # noqa: B018 - the module's __getattr__ refuses other names

