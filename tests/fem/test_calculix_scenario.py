"""Scenario pieces of the CalculiX deck (springs to ground, gravity, material regions), checked by
running ccx against closed forms and against the consistent loads tissuecast computes.

Tests that run ``ccx`` are marked ``calculix`` and skipped when it is not installed (CI has it).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq
from mesh_factories import box_mesh
from test_calculix import uniaxial_closed_form

from tissuecast.errors import SolverSetupError
from tissuecast.fem import calculix as cx
from tissuecast.fem.material import NeoHookean
from tissuecast.fem.springs import NodalSprings
from tissuecast.mesh.surface import lumped_areas, surface_nodes, triangle_areas
from tissuecast.scenario import body_loads, surface_springs

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="ccx (apt-get install calculix-ccx) not installed")
MAT = NeoHookean(0.021, 0.45)


def _nodes(mesh, order):
    return mesh.points10 if order == 2 else mesh.points


def _rollers(mesh, order, planes):
    """Prescribed vertex values: 0 in direction ``axis`` on each plane ``(axis, coordinate)``, NaN elsewhere."""
    p = mesh.points
    value = np.full((mesh.n_vertices, 3), np.nan)
    for axis, at in planes:
        value[np.isclose(p[:, axis], at), axis] = 0.0
    keep = ~np.isnan(value).all(axis=1)
    return np.flatnonzero(keep), value[keep]


def confined_stress(material: NeoHookean, stretch: float) -> float:
    """Nominal axial stress (MPa) of the NEO HOOKE solid in uniaxial strain F = diag(1, 1, stretch)."""
    return (material.mu * stretch ** (-2.0 / 3.0) * 2.0 * (stretch**2 - 1.0) / (3.0 * stretch)
            + material.kappa * (stretch - 1.0))


def confined_stretch(material: NeoHookean, nominal_stress: float) -> float:
    return brentq(lambda s: confined_stress(material, s) - nominal_stress, 0.2, 5.0, xtol=1e-15)


def _face_loads(mesh, order, axis, at, traction):
    """Consistent nodal loads (n_nodes, 3) of a uniform traction (3,) MPa on the face ``x_axis = at``."""
    tri = mesh.surface_triangles
    tri = tri[np.isclose(mesh.points[tri][:, :, axis], at).all(axis=1)]
    area, _ = triangle_areas(mesh.points, tri)
    nodes = surface_nodes(mesh, tri, order)
    share = np.full(3, 1.0 / 3.0) if order == 1 else np.r_[np.zeros(3), np.full(3, 1.0 / 3.0)]
    out = np.zeros((len(_nodes(mesh, order)), 3))
    np.add.at(out, nodes.ravel(), (area[:, None] * share[None, :]).ravel()[:, None] * np.asarray(traction)[None, :])
    return out


# ---------------------------------------------------------------------------- deck text
def test_deck_scenario_lines():
    iso = NodalSprings([0, 3], np.stack([0.5 * np.eye(3), 0.5 * np.eye(3)]))
    deck = cx.DeckScenario(springs=iso, density=1e-9, acceleration=[0.0, 0.0, -2.0],
                           materials=[(0.03, 0.4, np.arange(3)), (0.02, 0.45, np.arange(3, 6))])
    lines = deck.spring_lines(7, repr) + deck.material_lines(MAT, 6, repr) + deck.step_lines(repr)
    text = "\n".join(lines)
    # isotropic springs of equal stiffness share one element set per dof: 3 sets, ids 7..12
    assert text.count("*ELEMENT, TYPE=SPRING1") == 3 and "ORIENTATION" not in text
    assert "*ELEMENT, TYPE=SPRING1, ELSET=SP7\n7, 1\n10, 4\n*SPRING, ELSET=SP7\n1\n0.5" in text
    assert text.count("*SOLID SECTION") == 2 and "*ELSET, ELSET=TISSUE2\n4, 5, 6" in text
    assert text.count("*DENSITY\n1e-09") == 2
    assert lines[-2:] == ["*DLOAD", "TISSUE, GRAV, 2.0, 0.0, 0.0, -1.0"]
    aniso = NodalSprings([4], np.diag([0.0, 0.2, 0.6])[None])  # no stiffness along x: two springs
    text = "\n".join(cx.DeckScenario(springs=aniso).spring_lines(1, repr))
    assert text.count("SPRING1") == 2 and "*ORIENTATION, NAME=OR5, SYSTEM=RECTANGULAR\n0.0, 0.0, 1.0, 0.0, 1.0, 0.0" in text
    assert "*SPRING, ELSET=SP1, ORIENTATION=OR5\n1\n0.6" in text and "*SPRING, ELSET=SP2, ORIENTATION=OR5\n2\n0.2" in text
    with pytest.raises(SolverSetupError, match="exactly one material"):
        cx.DeckScenario(materials=[(0.03, 0.4, np.arange(4))]).material_lines(MAT, 6, repr)
    with pytest.raises(SolverSetupError, match="positive density"):
        cx.DeckScenario(acceleration=[0.0, 0.0, -1.0])


# ------------------------------------------------------------------------------ springs
@pytest.mark.calculix
@needs_ccx
def test_ccx_springs_follow_their_orientation_exactly(tmp_path):
    """Random anisotropic nodal springs, loads f_a = K_a u0: the exact answer is the rigid
    translation u0 (no strain), which ccx reproduces only if every SPRING1 acts along its
    node's principal direction and the loads stay global (10 mm: linear under NLGEOM)."""
    mesh = box_mesh(2, 2, 2)
    rng = np.random.default_rng(0)
    q = np.linalg.qr(rng.normal(size=(mesh.n_vertices, 3, 3)))[0]
    lam = rng.uniform(0.005, 0.05, size=(mesh.n_vertices, 3))
    k = np.einsum("aij,aj,akj->aik", q, lam, q)
    k[:3] = 0.02 * np.eye(3)  # and three isotropic ones
    springs = NodalSprings(np.arange(mesh.n_vertices), k)
    u0 = np.array([6.0, -4.0, 8.0])
    path = cx.write_inp(tmp_path / "o.inp", mesh, MAT, [], -springs.forces(np.tile(u0, (mesh.n_vertices, 1))), order=1,
                        scenario=cx.DeckScenario(springs=springs))
    u = cx.read_displacements(cx.run_ccx(path).dat, mesh.n_vertices)
    np.testing.assert_allclose(u, np.tile(u0, (mesh.n_vertices, 1)), atol=2e-6 * 10.0)


@pytest.mark.calculix
@needs_ccx
@pytest.mark.parametrize("order, lumping", [(1, "hrz"), (2, "row-sum"), (2, "hrz")])
def test_ccx_block_on_springs_under_traction_moves_by_t_over_k(tmp_path, order, lumping):
    """A block on normal springs (k = 0.002 N/mm^3, on its bottom face, lumped by area) with
    rollers on x = 0 and y = 0, pulled by a uniform traction t on its top face: its bottom
    rises by t / k on the springs' area-weighted mean (equilibrium). Row-sum springs are
    lumped in the shares of a uniform traction's consistent loads, so the block stretches
    uniaxially and every node rises by exactly t / k; P2 HRZ springs (every node sprung)
    dimple the face by ~10 % of t / k (the 2 mm of the closed form)."""
    length, k, t = 10.0, 0.002, 0.004
    mesh = box_mesh(3, 3, 3, (length, length, length))
    bottom = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.0))
    springs = surface_springs(mesh, bottom, order, k, 0.0, lumping)  # normal only: an oriented spring per node
    ids, values = _rollers(mesh, order, [(0, 0.0), (1, 0.0)])
    loads = _face_loads(mesh, order, 2, length, [0.0, 0.0, t])
    path = cx.write_inp(tmp_path / "s.inp", mesh, MAT, [], loads, order=order, prescribed=(ids, values),
                        scenario=cx.DeckScenario(springs=springs), force_tolerance=1e-6, displacement_tolerance=1e-5)
    run = cx.run_ccx(path)
    u = cx.read_displacements(run.frd, len(_nodes(mesh, order)))
    u[: mesh.n_vertices] = cx.read_displacements(run.dat, mesh.n_vertices)
    lam, lateral = uniaxial_closed_form(MAT, t)
    p = _nodes(mesh, order)
    nodes, area, _ = lumped_areas(mesh, mesh.surface_triangles[np.isclose(
        mesh.points[mesh.surface_triangles][:, :, 2], 0.0).all(axis=1)], order, lumping)
    np.testing.assert_array_equal(nodes, springs.nodes)
    assert np.sum(area * u[nodes, 2]) / area.sum() == pytest.approx(t / k, rel=1e-5)  # 2 mm
    expected = np.column_stack([(lateral - 1.0) * p[:, 0], (lateral - 1.0) * p[:, 1], t / k + (lam - 1.0) * p[:, 2]])
    if order == 1 or lumping == "row-sum":
        np.testing.assert_allclose(u, expected, atol=2e-5 * length)
    else:
        dimple = np.abs(u[nodes, 2] - t / k).max() / (t / k)
        assert 0.05 < dimple < 0.15, dimple  # 10.3 % here


# ------------------------------------------------------------------------------ gravity
@pytest.mark.calculix
@needs_ccx
@pytest.mark.parametrize("order", [1, 2])
def test_ccx_grav_equals_the_consistent_body_loads(tmp_path, order):
    """``*DLOAD, GRAV`` and tissuecast's consistent nodal loads (P2: -V/20 corners, V/5 mid-edge)
    give the same deformation of a cantilever (P2: 20 mm), step for step (a dead load in both)."""
    mesh = box_mesh(2, 2, 4, (10.0, 10.0, 40.0))
    fixed = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.0))
    rho, acc = 1e-9, np.array([0.0, 1.0e4, -4.0e4])
    n_nodes = len(_nodes(mesh, order))
    deck = cx.write_inp(tmp_path / "g.inp", mesh, MAT, fixed, np.zeros((mesh.n_vertices, 3)), order=order,
                        scenario=cx.DeckScenario(density=rho, acceleration=acc))
    assert "*DLOAD\nTISSUE, GRAV, " in deck.read_text()
    by_grav = cx.read_displacements(cx.run_ccx(deck).frd, n_nodes)
    loads = body_loads(mesh, order, rho * acc)
    loads[fixed] = 0.0  # those go straight into the support
    deck = cx.write_inp(tmp_path / "c.inp", mesh, MAT, fixed, loads, order=order)
    by_cload = cx.read_displacements(cx.run_ccx(deck).frd, n_nodes)
    assert np.linalg.norm(by_grav, axis=1).max() > (15.0 if order == 2 else 7.0)  # P1 locks: stiffer
    np.testing.assert_allclose(by_grav, by_cload, atol=1e-5)


@pytest.mark.calculix
@needs_ccx
def test_ccx_column_under_its_own_weight_matches_the_closed_form(tmp_path):
    """A confined column (rollers on its sides and base) under 20 g: uniaxial strain with the
    nominal stress growing linearly with depth, P_zz(Z) = -rho g (H - Z), so
    u_z(Z) = integral_0^Z (lambda(P_zz(s)) - 1) ds (9 % strain at the base)."""
    height, rho, g = 40.0, 1e-9, 2.0e5
    mesh = box_mesh(1, 1, 8, (5.0, 5.0, height))
    ids, values = _rollers(mesh, 2, [(0, 0.0), (0, 5.0), (1, 0.0), (1, 5.0), (2, 0.0)])
    deck = cx.write_inp(tmp_path / "col.inp", mesh, MAT, [], np.zeros((mesh.n_vertices, 3)), order=2,
                        prescribed=(ids, values), scenario=cx.DeckScenario(density=rho, acceleration=[0.0, 0.0, -g]),
                        force_tolerance=1e-6, displacement_tolerance=1e-5)
    run = cx.run_ccx(deck)
    u = cx.read_displacements(run.frd, len(mesh.points10))
    z = mesh.points10[:, 2]

    def settle(depth):
        return quad(lambda s: confined_stretch(MAT, -rho * g * (height - s)) - 1.0, 0.0, depth, epsabs=1e-12)[0]

    expected = np.array([settle(v) for v in z])
    assert confined_stretch(MAT, -rho * g * height) < 0.92
    np.testing.assert_allclose(u[:, 2], expected, atol=2e-4 * abs(expected).max())
    np.testing.assert_allclose(u[:, :2], 0.0, atol=1e-6)


# ---------------------------------------------------------------------------- materials
@pytest.mark.calculix
@needs_ccx
def test_ccx_two_material_regions_in_series(tmp_path):
    """Two materials stacked in a confined bar under a nominal compression: each region strains
    by its own closed form (uniaxial strain), the stiffer one 1.7x less (6.2 % against 3.7 %)."""
    length, stress = 10.0, -0.005
    mesh = box_mesh(2, 2, 4, (length, length, 2.0 * length))
    soft, stiff = NeoHookean(0.021, 0.45), NeoHookean(0.063, 0.4)
    upper = mesh.points[mesh.tets].mean(axis=1)[:, 2] > length
    groups = [(soft.youngs_modulus, soft.poisson_ratio, np.flatnonzero(~upper)),
              (stiff.youngs_modulus, stiff.poisson_ratio, np.flatnonzero(upper))]
    ids, values = _rollers(mesh, 2, [(0, 0.0), (0, length), (1, 0.0), (1, length), (2, 0.0)])
    loads = _face_loads(mesh, 2, 2, 2.0 * length, [0.0, 0.0, stress])
    deck = cx.write_inp(tmp_path / "two.inp", mesh, MAT, [], loads, order=2, prescribed=(ids, values),
                        scenario=cx.DeckScenario(materials=groups))
    u = cx.read_displacements(cx.run_ccx(deck).dat, mesh.n_vertices)
    z = mesh.points[:, 2]
    s1, s2 = confined_stretch(soft, stress), confined_stretch(stiff, stress)
    expected = np.where(z <= length, (s1 - 1.0) * z, (s1 - 1.0) * length + (s2 - 1.0) * (z - length))
    assert s1 < 0.95 and (1.0 - s1) > 1.6 * (1.0 - s2)
    np.testing.assert_allclose(u[:, 2], expected, atol=1e-5 * length)
