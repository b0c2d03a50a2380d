"""The nonlinear solver against closed forms: patch test, uniaxial stress, simple shear,
small-strain linear elasticity, and the mesh convergence rate of a cantilever."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from mesh_factories import box_grid
from scipy.optimize import brentq

from tissuecast.config import SolverConfig
from tissuecast.fem import NeoHookean, Problem, Solver, solve
from tissuecast.mesh import TetMesh

MAT = NeoHookean(0.021, 0.45)
TIGHT = dataclasses.replace(SolverConfig(), force_tolerance=1e-7, displacement_tolerance=1e-7)


def distorted_box(n=3, side=6.0, seed=0):
    base = box_grid(n, n, n, size=(side / n,) * 3)
    p = base.points.copy()
    inner = base.interior_vertices
    p[inner] += np.random.default_rng(seed).uniform(-0.3, 0.3, (len(inner), 3)) * side / n
    return TetMesh(p, base.tets)


def homogeneous_solve(mesh, grad, order):
    """Prescribe u = (F - I) X on every boundary vertex and solve with no forces."""
    bnd = mesh.surface_vertices
    prescribed = (bnd, mesh.points[bnd] @ grad.T)
    prob = Problem(mesh, MAT, fixed=[], order=order, prescribed=prescribed)
    res = Solver(prob, TIGHT).solve(np.zeros((mesh.n_vertices, 3)))
    return prob, res


def average_stress(prob, res):
    """(1/V) sum_a R_a (x) X_a = volume average of P (exact identity at equilibrium)."""
    return np.einsum("ak,aJ->kJ", res.nodal_reaction, prob.nodes) / prob.mesh.volume


def neo_hookean_p(f):
    j = np.linalg.det(f)
    i1 = np.sum(f * f)
    h = np.linalg.inv(f).T
    return MAT.mu * j ** (-2 / 3) * (f - i1 / 3 * h) + MAT.kappa * j * (j - 1) * h


def uniaxial_closed_form(stretch):
    """Lateral stretch t with P22 = P33 = 0 for F = diag(stretch, t, t), and P11."""

    def p22(t):
        j = stretch * t * t
        i1 = stretch**2 + 2 * t * t
        return MAT.mu * j ** (-2 / 3) * (t - i1 / (3 * t)) + MAT.kappa * j * (j - 1) / t

    t = brentq(p22, 0.3, 1.5, xtol=1e-15)
    j = stretch * t * t
    i1 = stretch**2 + 2 * t * t
    p11 = MAT.mu * j ** (-2 / 3) * (stretch - i1 / (3 * stretch)) + MAT.kappa * j * (j - 1) / stretch
    return t, p11


@pytest.mark.parametrize("order", [1, 2])
def test_patch_test_linear_field_reproduced_on_distorted_mesh(order):
    mesh = distorted_box()
    grad = 1e-3 * np.random.default_rng(1).standard_normal((3, 3))
    prob, res = homogeneous_solve(mesh, grad, order)
    exact = prob.nodes @ grad.T
    assert np.abs(res.nodal_displacement - exact).max() <= 1e-9 * np.abs(exact).max()


@pytest.mark.parametrize("order", [1, 2])
def test_uniaxial_stretch_matches_closed_form(order):
    stretch = 1.4
    t, p11 = uniaxial_closed_form(stretch)
    grad = np.diag([stretch - 1, t - 1, t - 1])
    prob, res = homogeneous_solve(distorted_box(seed=2), grad, order)
    exact = prob.nodes @ grad.T
    assert np.abs(res.nodal_displacement - exact).max() <= 1e-8 * np.abs(exact).max()
    pbar = average_stress(prob, res)
    expected = np.zeros((3, 3))
    expected[0, 0] = p11
    np.testing.assert_allclose(pbar, expected, atol=1e-7 * p11)
    assert t < 1.0  # lateral contraction


@pytest.mark.parametrize("order", [1, 2])
def test_simple_shear_matches_closed_form(order):
    g = 0.5
    grad = np.zeros((3, 3))
    grad[0, 1] = g
    prob, res = homogeneous_solve(distorted_box(seed=3), grad, order)
    pbar = average_stress(prob, res)
    f = np.eye(3) + grad
    mu = MAT.mu
    # J = 1: P12 = mu g, P21 = mu g (3 + g^2) / 3, Cauchy sigma12 = mu g
    assert pbar[0, 1] == pytest.approx(mu * g, rel=1e-7)
    assert pbar[1, 0] == pytest.approx(mu * g * (3 + g * g) / 3, rel=1e-7)
    sigma = pbar @ f.T
    assert sigma[0, 1] == pytest.approx(mu * g, rel=1e-7)
    np.testing.assert_allclose(pbar, neo_hookean_p(f), atol=1e-8 * mu)


def test_small_uniaxial_strain_gives_youngs_modulus_and_poisson_ratio():
    eps = 1e-5
    t, p11 = uniaxial_closed_form(1 + eps)
    assert p11 / eps == pytest.approx(MAT.youngs_modulus, rel=1e-4)
    assert (1 - t) / eps == pytest.approx(MAT.poisson_ratio, rel=1e-4)
    prob, res = homogeneous_solve(distorted_box(seed=4), np.diag([eps, t - 1, t - 1]), 2)
    assert average_stress(prob, res)[0, 0] / eps == pytest.approx(MAT.youngs_modulus, rel=1e-4)


def cantilever(k, order, load):
    """4 x 1 x 1 mm beam, 4k x k x k cells, clamped at x = 0, dead load -z on the x = L vertices."""
    mesh = box_grid(4 * k, k, k, size=(1.0 / k,) * 3)
    x = mesh.points[:, 0]
    fixed = np.flatnonzero(x < 1e-9)
    tip = np.flatnonzero(x > 4 - 1e-9)
    f = np.zeros((mesh.n_vertices, 3))
    f[tip, 2] = -load / len(tip)
    res = solve(Problem(mesh, MAT, fixed, order=order), f, TIGHT)
    mid = np.flatnonzero(np.abs(x - 2.0) < 1e-9)
    return res, -res.displacement[mid, 2].mean()


def test_small_loads_reproduce_linear_elasticity():
    load = 1e-7  # N: deflection ~1e-3 mm
    res_small, w_small = cantilever(1, 2, load)
    res_2x, w_2x = cantilever(1, 2, 2 * load)
    assert w_2x / w_small == pytest.approx(2.0, rel=1e-3)  # linear in the load
    # and equal to the linear FE solution K0^-1 f
    mesh = box_grid(4, 1, 1)
    x = mesh.points[:, 0]
    prob = Problem(mesh, MAT, np.flatnonzero(x < 1e-9), order=2)
    solver = Solver(prob)
    f = np.zeros((mesh.n_vertices, 3))
    tip = np.flatnonzero(x > 4 - 1e-9)
    f[tip, 2] = -load / len(tip)
    asm = solver.assembler
    _, k0, _ = asm.tangent(np.zeros((len(prob.nodes), 3)))
    rhs = np.zeros(asm.n_dofs)
    rhs[: 3 * mesh.n_vertices] = f.ravel()
    solver.linear.factorize(k0)
    lin = np.zeros(asm.n_dofs)
    lin[asm.free_dofs] = solver.linear.solve(rhs[asm.free_dofs])
    lin = lin.reshape(-1, 3)[: mesh.n_vertices]
    assert np.abs(res_small.displacement - lin).max() <= 1e-3 * np.abs(lin).max()


def test_cantilever_mesh_convergence_rate():
    load = 2e-5  # N: mid-span deflection ~0.1 mm on 4 mm (geometrically nonlinear regime, mildly)
    _, w_ref = cantilever(6, 2, load)
    hs, err1, err2 = [], [], []
    for k in (1, 2, 3):
        hs.append(1.0 / k)
        err2.append(abs(cantilever(k, 2, load)[1] - w_ref))
        err1.append(abs(cantilever(k, 1, load)[1] - w_ref))
    rate2 = np.polyfit(np.log(hs), np.log(err2), 1)[0]
    assert rate2 > 1.5, (rate2, err2)
    assert err1[0] > err1[1] > err1[2]  # P1 converges too, but slowly (locking at nu = 0.45)
    assert all(e2 < e1 for e1, e2 in zip(err1, err2))  # P2 beats P1 (P1 locks at nu = 0.45)
