"""Surface LBO basis, LBO force fields, test-2 (LSC) fields and their blend."""

import numpy as np
import pytest
import scipy.linalg
from scipy.sparse.csgraph import shortest_path

from tissuecast.errors import ConfigError, MeshError
from tissuecast.forces import (
    blend,
    field_scale,
    lbo_basis,
    lbo_field,
    lsc_field,
    random_lbo_weights,
    smooth,
    surface_graph_laplacian,
    surface_operator,
)
import tissuecast.mesh as tcmesh
from tissuecast.mesh.tetmesh import TetMesh


def icosphere(level):
    """Unit icosphere: (v, 3) points, (f, 3) outward triangles."""
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(level):
        cache = {}

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts), np.array(faces)


def coned_ball(level, radius=10.0, bumpy=False):
    """Star-shaped solid: every surface triangle of an icosphere joined to the centre (last vertex)."""
    v, f = icosphere(level)
    r = radius * np.ones(len(v))
    if bumpy:  # an irregular, asymmetric "potato" (distinct eigenvalues)
        x, y, z = v.T
        r = radius * (1 + 0.25 * x**2 + 0.15 * np.sin(2 * y + 0.4) + 0.1 * z * x + 0.12 * x + 0.07 * z**3)
    pts = np.vstack([v * r[:, None], [[0.0, 0.0, 0.0]]])
    return TetMesh(pts, np.hstack([f, np.full((len(f), 1), len(v))]))


@pytest.fixture(scope="module")
def sphere():
    return coned_ball(3, radius=10.0)


@pytest.fixture(scope="module")
def potato():
    return coned_ball(3, radius=12.0, bumpy=True)


# --------------------------------------------------------------------- LBO basis
def test_sphere_eigenvalues_are_l_l_plus_1_over_r_squared(sphere):
    lam = lbo_basis(sphere, n=16).eigenvalues
    assert abs(lam[0]) < 1e-10
    r2 = 100.0
    groups = {1: lam[1:4], 2: lam[4:9], 3: lam[9:16]}
    for degree, g in groups.items():
        np.testing.assert_allclose(g, degree * (degree + 1) / r2, rtol=0.02)
    # multiplicities 1, 3, 5: equal within a group, a clear gap between groups
    np.testing.assert_allclose(lam[1:4], lam[1], rtol=1e-8)
    np.testing.assert_allclose(lam[4:9], lam[4], rtol=1e-8)
    assert lam[4] > 2.5 * lam[3] and lam[9] > 1.8 * lam[8]


def test_basis_is_m_orthonormal_smooth_first_and_solves_the_eigenproblem(potato):
    b = lbo_basis(potato, n=20)
    verts, lap, mass = surface_operator(potato)
    np.testing.assert_array_equal(b.vertices, potato.surface_vertices)
    assert b.vectors.shape == (len(verts), 20) and b.eigenvalues.shape == (20,)
    np.testing.assert_allclose(b.mass, mass.diagonal())
    np.testing.assert_allclose(b.mass.sum(), potato.surface_area, rtol=1e-3)
    gram = b.vectors.T @ (b.mass[:, None] * b.vectors)
    np.testing.assert_allclose(gram, np.eye(20), atol=1e-8)
    rayleigh = np.einsum("ij,ij->j", b.vectors, lap @ b.vectors)
    np.testing.assert_allclose(rayleigh, b.eigenvalues, rtol=1e-8, atol=1e-12)
    assert np.all(np.diff(rayleigh) > 0)  # distinct on an irregular surface, smoothest first
    residual = lap @ b.vectors - (b.mass[:, None] * b.vectors) * b.eigenvalues
    assert np.abs(residual).max() < 1e-8 * np.abs(lap @ b.vectors).max()
    # the first vector is the constant 1 / sqrt(area)
    np.testing.assert_allclose(b.vectors[:, 0], 1 / np.sqrt(b.mass.sum()), rtol=1e-8)


@pytest.mark.parametrize("level, bumpy, n", [(2, True, 12), (3, False, 16), (3, False, 20)])
def test_eigenvalues_match_a_dense_generalised_solve(level, bumpy, n):
    # (3, False, 16): a plain eigsh(k=16) misses one copy of the 4-fold eigenvalue near 12/R^2
    mesh = coned_ball(level, radius=5.0, bumpy=bumpy)
    b = lbo_basis(mesh, n=n)
    _, lap, mass = surface_operator(mesh)
    dense = scipy.linalg.eigh(lap.toarray(), mass.toarray(), eigvals_only=True, subset_by_index=[0, n - 1])
    np.testing.assert_allclose(b.eigenvalues, dense, rtol=1e-9, atol=1e-12)


def test_basis_is_deterministic_with_fixed_signs(potato):
    a, b = lbo_basis(potato, n=10), lbo_basis(potato, n=10)
    np.testing.assert_array_equal(a.vectors, b.vectors)
    np.testing.assert_array_equal(a.eigenvalues, b.eigenvalues)
    cols = np.arange(10)
    assert np.all(a.vectors[np.abs(a.vectors).argmax(0), cols] > 0)
    assert not a.vectors.flags.writeable


def test_basis_size_is_validated(sphere):
    with pytest.raises(MeshError, match=r"1 <= n <= 640"):
        lbo_basis(sphere, n=641)
    with pytest.raises(MeshError, match="n=0"):
        lbo_basis(sphere, n=0)


# ------------------------------------------------------------------- LBO fields
def test_random_weights_are_uniform_and_reproducible():
    w = random_lbo_weights(np.random.default_rng(5), 20)
    assert w.shape == (20, 3) and np.all(np.abs(w) < 1)
    np.testing.assert_array_equal(w, np.random.default_rng(5).uniform(-1, 1, (20, 3)))
    big = random_lbo_weights(np.random.default_rng(0), 100000)
    np.testing.assert_allclose(big.var(axis=0), 1 / 3, rtol=0.02)


def test_lbo_field_is_alpha_b_w_on_the_surface_and_zero_inside(sphere):
    b = lbo_basis(sphere, n=8)
    w = random_lbo_weights(np.random.default_rng(1), 8)
    f = lbo_field(b, w, 2.5, sphere.n_vertices)
    assert f.shape == (sphere.n_vertices, 3)
    np.testing.assert_allclose(f[b.vertices], 2.5 * b.vectors @ w, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(f[sphere.interior_vertices], 0.0)
    np.testing.assert_allclose(lbo_field(b, w, 5.0, sphere.n_vertices), 2 * f, rtol=1e-14)
    with pytest.raises(ConfigError, match=r"\(8, 3\)"):
        lbo_field(b, w[:5], 1.0, sphere.n_vertices)


def test_field_scale_is_the_rms_nodal_force_per_unit_alpha(potato):
    b = lbo_basis(potato, n=20)
    rng = np.random.default_rng(2)
    ms = [np.mean(np.sum(lbo_field(b, random_lbo_weights(rng, 20), 1.0, potato.n_vertices)[b.vertices] ** 2, 1))
          for _ in range(3000)]
    np.testing.assert_allclose(np.sqrt(np.mean(ms)), field_scale(b), rtol=0.03)
    # M-orthonormal columns: sum_i m_i B_ik^2 = 1, so the scale is ~ sqrt(n / area)
    np.testing.assert_allclose(field_scale(b), np.sqrt(20 / potato.surface_area), rtol=0.3)


# --------------------------------------------------------------------- LSC fields
def bipyramid():
    """Two tets sharing face (0, 1, 2); apexes 3 and 4. Surface degrees: 4, 4, 4, 3, 3."""
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1], [0.3, 0.3, -1]], float)
    return TetMesh(pts, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))


def test_one_and_two_smoothing_steps_by_hand():
    mesh = bipyramid()
    lap = surface_graph_laplacian(mesh)
    f = np.zeros((5, 3))
    f[3] = [1.0, 0, 0]
    # (L f)_3 = 0 - 1 = -1; (L f)_i = 1/4 for i = 0, 1, 2 (vertex 3 is one of 4 neighbours);
    # (L f)_4 = 0 (its neighbours 0, 1, 2 carry nothing). f + 0.1 L f:
    one = smooth(f, lap, iterations=1, rate=0.1)
    np.testing.assert_allclose(one[:, 0], [0.025, 0.025, 0.025, 0.9, 0.0], atol=1e-15)
    # step 2 at vertex 4: 0 + 0.1 * (mean(0.025, 0.025, 0.025) - 0) = 0.0025;
    # at vertex 3: 0.9 + 0.1 * (0.025 - 0.9) = 0.8125
    two = smooth(f, lap, iterations=2, rate=0.1)
    np.testing.assert_allclose(two[[3, 4], 0], [0.8125, 0.0025], atol=1e-15)
    assert np.all(two[:, 1:] == 0)


def test_smoothing_preserves_the_degree_weighted_total_and_bounds(sphere):
    lap = surface_graph_laplacian(sphere)
    deg = np.diff((lap != 0).astype(int).tocsr().indptr) - 1  # neighbours (row minus diagonal)
    deg[deg < 0] = 0
    rng = np.random.default_rng(4)
    f = np.zeros((sphere.n_vertices, 3))
    f[rng.choice(sphere.surface_vertices, 3, replace=False)] = rng.normal(size=(3, 3))
    g = smooth(f, lap, iterations=20, rate=0.1)
    np.testing.assert_allclose(deg @ g, deg @ f, rtol=1e-12)
    assert np.abs(g).max() <= np.abs(f).max()
    assert np.linalg.norm(g) < np.linalg.norm(f)
    np.testing.assert_array_equal(g[sphere.interior_vertices], 0.0)


def test_support_spreads_one_ring_per_iteration(sphere):
    lap = surface_graph_laplacian(sphere)
    adj = (lap != 0).astype(float)
    hops = shortest_path(adj, unweighted=True, indices=[17])[0]
    f = np.zeros((sphere.n_vertices, 3))
    f[17, 2] = 1.0
    for k in (1, 2, 5):
        g = smooth(f, lap, iterations=k, rate=0.1)
        np.testing.assert_array_equal(np.flatnonzero(g[:, 2] != 0), np.flatnonzero(hops <= k))


def test_lsc_field_draws_loads_away_from_fixed_vertices(sphere):
    fixed = sphere.surface_vertices[:600]  # leaves 42 loadable surface vertices
    raw = lsc_field(sphere, np.random.default_rng(8), n_forces=3, iterations=0, magnitude=2.0, exclude=fixed)
    loaded = np.flatnonzero(np.linalg.norm(raw, axis=1) > 0)
    assert len(loaded) == 3 and not np.isin(loaded, fixed).any()
    np.testing.assert_allclose(np.linalg.norm(raw[loaded], axis=1), 2.0)
    again = lsc_field(sphere, np.random.default_rng(8), n_forces=3, iterations=0, magnitude=2.0, exclude=fixed)
    np.testing.assert_array_equal(raw, again)
    smoothed = lsc_field(sphere, np.random.default_rng(8), n_forces=3, iterations=20, magnitude=2.0, exclude=fixed)
    np.testing.assert_allclose(smoothed, smooth(raw, surface_graph_laplacian(sphere), 20, 0.1), rtol=1e-13)
    with pytest.raises(ConfigError, match="1 <= n_forces <= 42"):
        lsc_field(sphere, np.random.default_rng(0), n_forces=43, exclude=fixed)


def test_lsc_field_matches_reference_norm(sphere):
    b = lbo_basis(sphere, n=20)
    ref = lbo_field(b, random_lbo_weights(np.random.default_rng(0), 20), 3.0, sphere.n_vertices)
    f = lsc_field(sphere, np.random.default_rng(1), reference=ref)
    np.testing.assert_allclose(np.linalg.norm(f), np.linalg.norm(ref), rtol=1e-12)


def test_blend_endpoints_and_midpoint():
    rng = np.random.default_rng(0)
    a, c = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    np.testing.assert_array_equal(blend(a, c, 1.0), a)
    np.testing.assert_array_equal(blend(a, c, 0.0), c)
    np.testing.assert_allclose(blend(a, c, 0.3), 0.3 * a + 0.7 * c)
    with pytest.raises(ConfigError, match="beta"):
        blend(a, c, 1.5)
    with pytest.raises(ConfigError, match="same shape"):
        blend(a, c[:5], 0.5)


@pytest.mark.skipif(not hasattr(tcmesh, "phantom"), reason="tissuecast.mesh.phantom not available yet")
def test_phantom_basis_via_public_api():
    import tissuecast as tc

    mesh = tc.phantom()
    b = tc.lbo_basis(mesh, n=20)
    assert b.vectors.shape == (len(mesh.surface_vertices), 20)
    np.testing.assert_allclose(b.vectors.T @ (b.mass[:, None] * b.vectors), np.eye(20), atol=1e-8)
    assert abs(b.eigenvalues[0]) < 1e-10 and np.all(np.diff(b.eigenvalues) > 0)
    # smoothest non-constant mode of a ~70 mm long body: half a wave along it, ~ (pi / 70)^2
    assert 0.3 * (np.pi / 70) ** 2 < b.eigenvalues[1] < 3 * (np.pi / 70) ** 2
