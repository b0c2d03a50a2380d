"""Vectorised assembly: tangent stiffness against finite differences of the residual."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.fem import NeoHookean, Problem
from tissuecast.fem import kernels
from tissuecast.fem.assembly import Assembler
from tissuecast.mesh import TetMesh


def distorted_box(seed=0, n=3):
    base = box_grid(n, n, n, size=(2.0, 2.0, 2.0))
    p = base.points.copy()
    interior = base.interior_vertices
    p[interior] += np.random.default_rng(seed).uniform(-0.35, 0.35, (len(interior), 3))
    return TetMesh(p, base.tets)


def smooth_state(nodes, rng, amplitude):
    x = nodes / nodes.max()
    feats = np.column_stack([x, x**2, np.sin(3 * x)])
    return amplitude * feats @ rng.standard_normal((feats.shape[1], 3))


BACKENDS = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(not kernels.available(), reason="numba missing"))]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("order", [1, 2])
def test_tangent_equals_finite_difference_of_residual(order, backend):
    mesh = distorted_box()
    prob = Problem(mesh, NeoHookean(0.021, 0.45), fixed=[0, 3, 12], order=order)
    asm = Assembler(prob.nodes, prob.connectivity, order, prob.material, prob.free_mask, backend=backend)
    assert asm.backend == backend
    rng = np.random.default_rng(1)
    for _ in range(3):
        u = smooth_state(prob.nodes, rng, 0.4)
        fint, data, jmin = asm.tangent(u)
        assert jmin > 0.2
        k = asm.matrix(data)
        np.testing.assert_allclose((k - k.T).data, 0.0, atol=1e-14 * np.abs(data).max())
        du = np.zeros(asm.n_dofs)
        du[asm.free_dofs] = rng.standard_normal(asm.n_free)
        h = 1e-6
        fp, _ = asm.internal_force(u + h * du.reshape(-1, 3))
        fm, _ = asm.internal_force(u - h * du.reshape(-1, 3))
        fd = ((fp - fm) / (2 * h))[asm.free_dofs]
        kdu = k @ du[asm.free_dofs]
        assert np.abs(fd - kdu).max() <= 1e-6 * np.abs(kdu).max()
        # the internal force is the gradient of the strain energy
        e_p, e_m = asm.energy(u + h * du.reshape(-1, 3)), asm.energy(u - h * du.reshape(-1, 3))
        assert (e_p - e_m) / (2 * h) == pytest.approx(fint @ du, rel=1e-6)
        assert asm.energy_and_force(u)[0] == pytest.approx(asm.energy(u), rel=1e-14)


@pytest.mark.parametrize("order", [1, 2])
def test_projected_tangent_is_positive_definite_and_exact_when_already_pd(order):
    mesh = distorted_box(seed=2)
    prob = Problem(mesh, NeoHookean(0.021, 0.45), fixed=[0, 3, 12], order=order)
    asm = Assembler(prob.nodes, prob.connectivity, order, prob.material, prob.free_mask)
    u0 = np.zeros((len(prob.nodes), 3))
    _, k0, _ = asm.tangent(u0)
    _, k0p, _ = asm.tangent(u0, project=True)
    # PD at rest: unchanged up to the 1e-6 mu floor on the (zero-stiffness) rotation modes
    np.testing.assert_allclose(k0p, k0, atol=1e-5 * np.abs(k0).max())
    # strong compression makes the true tangent indefinite; the projected one stays PD
    u = (np.diag([-0.45, 0.3, 0.3]) @ prob.nodes.T).T
    _, kp, jmin = asm.tangent(u, project=True)
    assert jmin > 0
    eig = np.linalg.eigvalsh(asm.matrix(kp).toarray())
    assert eig.min() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_internal_forces_are_self_equilibrated(backend):
    mesh = distorted_box(seed=3)
    prob = Problem(mesh, NeoHookean(), fixed=[0, 3, 12], order=2)
    asm = Assembler(prob.nodes, prob.connectivity, 2, prob.material, prob.free_mask, backend=backend)
    u = smooth_state(prob.nodes, np.random.default_rng(4), 0.5)
    fint, _ = asm.internal_force(u)
    f = fint.reshape(-1, 3)
    scale = np.abs(f).sum()
    assert np.abs(f.sum(axis=0)).max() <= 1e-12 * scale  # sum of nodal forces
    x = prob.nodes + u
    assert np.abs(np.cross(x, f).sum(axis=0)).max() <= 1e-11 * scale * np.abs(x).max()  # and of moments


@pytest.mark.parametrize("order", [1, 2])
def test_structured_element_stiffness_equals_generic_contraction(order):
    mesh = distorted_box(seed=5, n=2)
    prob = Problem(mesh, NeoHookean(0.021, 0.45), fixed=[0, 1, 3], order=order)
    asm = Assembler(prob.nodes, prob.connectivity, order, prob.material, prob.free_mask)
    u = smooth_state(prob.nodes, np.random.default_rng(6), 0.5)
    f = asm.deformation_gradient(u)
    _, factors, _ = prob.material.stress_and_tangent(f, tangent="factors")
    fast = asm._stiffness_from_factors(f, factors)
    a = prob.material.tangent(f).reshape(f.shape[:2] + (3, 3, 3, 3))
    g, w = asm.geometry.grad, asm.geometry.weight
    generic = np.einsum("mqaJ,mqiJkL,mqbL,mq->maibk", g, a, g, w)
    np.testing.assert_allclose(fast, generic, atol=1e-12 * np.abs(generic).max())


@pytest.mark.parametrize("order", [1, 2])
def test_indefinite_tangent_is_shifted_by_the_smallest_working_tau(order):
    """SolveRun.factorize: an indefinite K (strong compression) is replaced by K + tau diag(K)
    with tau from the ladder 1e-3 x 4^k; the factor then solves that shifted system, and the
    next indefinite K starts the ladder at tau / 2."""
    pytest.importorskip("sksparse")  # a Cholesky backend tells "not positive definite"
    from tissuecast.config import SolverConfig
    from tissuecast.fem import Solver
    from tissuecast.fem.linear import NotPositiveDefinite
    from tissuecast.fem.newton import SolveRun

    mesh = distorted_box(seed=2)
    prob = Problem(mesh, NeoHookean(0.021, 0.45), fixed=[0, 3, 12], order=order)
    solver = Solver(prob, SolverConfig(linear_solver="cholmod"))
    u = (np.diag([-0.45, 0.3, 0.3]) @ prob.nodes.T).T
    _, k, _ = solver.assembler.tangent(u)
    kmat = solver.assembler.matrix(k).toarray()
    assert np.linalg.eigvalsh(kmat).min() < 0
    run = SolveRun(solver, np.zeros(solver.assembler.n_dofs))
    run.factorize(u.ravel())
    tau = run.tau
    assert run.counts.shifted == 1 and run.counts.projected == 0
    ladder = 1e-3 * 4.0 ** np.arange(10)
    assert np.isclose(ladder, tau, rtol=1e-12).any()
    shifted = kmat + tau * np.diag(np.diag(kmat))
    assert np.linalg.eigvalsh(shifted).min() > 0
    if tau > 1e-3:  # the previous rung was not positive definite: tau is the smallest that works
        assert np.linalg.eigvalsh(kmat + tau / 4 * np.diag(np.diag(kmat))).min() < 0
    b = np.random.default_rng(0).normal(size=len(kmat))
    np.testing.assert_allclose(run.linear.solve(b), np.linalg.solve(shifted, b), rtol=1e-8, atol=1e-12)
    assert run.counts.factorizations == 2 + int(round(np.log(tau / 1e-3) / np.log(4.0)))
    with pytest.raises(NotPositiveDefinite):
        run.linear.factorize(k)


@pytest.mark.parametrize("backend", ["cholmod", "superlu"])
def test_spawned_linear_solver_has_its_own_factor_and_the_same_bits(backend):
    """LinearSolver.spawn: a second solver of the same pattern factorises another matrix
    without touching the first one's factor, and (sharing the symbolic analysis) solves
    bit for bit like a solver that analysed the pattern afresh."""
    if backend == "cholmod":
        pytest.importorskip("sksparse")
    from tissuecast.fem.linear import make_linear_solver

    prob = Problem(distorted_box(seed=1), NeoHookean(0.021, 0.45), fixed=[0, 3, 12], order=2)
    asm = Assembler(prob.nodes, prob.connectivity, prob.order, prob.material, prob.free_mask)
    rng = np.random.default_rng(4)
    _, k0, _ = asm.tangent(np.zeros_like(prob.nodes))
    k1 = k0.copy()
    k1[asm.diagonal_index] *= 1.5  # another positive-definite matrix of the same pattern
    first = make_linear_solver(backend, asm)
    other = first.spawn()
    assert type(other) is type(first) and other is not first
    first.factorize(k0)
    other.factorize(k1)
    b = rng.normal(size=asm.n_free)
    for solver, data in ((first, k0), (other, k1)):
        dense = asm.matrix(data).toarray()
        np.testing.assert_allclose(solver.solve(b), np.linalg.solve(dense, b), rtol=1e-8, atol=1e-12)
    fresh = make_linear_solver(backend, asm)
    fresh.factorize(k1)
    np.testing.assert_array_equal(fresh.solve(b), other.solve(b))
