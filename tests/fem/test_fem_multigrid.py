"""The two-level p-multigrid backend: its prolongation, its cycle, and solves with it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse.linalg as spl
from mesh_factories import box_grid

from tissuecast.config import SolverConfig
from tissuecast.errors import SolverSetupError
from tissuecast.fem import NeoHookean, Problem, Solver
from tissuecast.fem.linear import NotPositiveDefinite, make_linear_solver
from tissuecast.fem.linear.multigrid import PMultigrid, vertex_interpolation

MAT = NeoHookean(0.021, 0.45)


@pytest.fixture(scope="module")
def block():
    """6 x 3 x 3 mm block (6 x 3 x 3 cells), clamped at x = 0, P2; its stiffness at zero."""
    mesh = box_grid(6, 3, 3)
    fixed = np.flatnonzero(mesh.points[:, 0] < 1e-9)
    problem = Problem(mesh, MAT, fixed, order=2)
    solver = Solver(problem, SolverConfig(linear_solver="cholmod"))
    _, data, _ = solver.assembler.tangent(np.zeros((len(problem.nodes), 3)))
    return mesh, fixed, problem, solver, data


def test_prolongation_interpolates_linear_fields_exactly(block):
    mesh, fixed, problem, solver, _ = block
    asm = solver.assembler
    p, coarse = vertex_interpolation(asm.connectivity, asm.n_nodes, asm.free_dofs)
    assert p.shape == (asm.n_free, len(coarse)) and np.all(coarse < 3 * mesh.n_vertices)
    # an affine displacement field, zero on the clamped face x = 0, is reproduced at every node
    field = np.column_stack([0.1 * problem.nodes[:, 0], 0.2 * problem.nodes[:, 0], -0.05 * problem.nodes[:, 0]]).ravel()
    np.testing.assert_allclose(p @ field[coarse], field[asm.free_dofs], rtol=0, atol=1e-14)


def test_cycle_is_symmetric_positive_definite_and_preconditions_well(block):
    _, _, _, solver, data = block
    mg = make_linear_solver("p-multigrid", solver.assembler, SolverConfig(multigrid_smoothing=2))
    assert isinstance(mg, PMultigrid) and not mg.exact and mg.coarse_size < solver.assembler.n_free / 5
    mg.factorize(data)
    n = solver.assembler.n_free
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    assert a @ mg.solve(b) == pytest.approx(b @ mg.solve(a), rel=1e-10)  # symmetric
    assert min(v @ mg.solve(v) for v in rng.standard_normal((5, n))) > 0  # positive
    # a two-column solve is the two single solves
    two = mg.solve(np.column_stack([a, b]))
    np.testing.assert_allclose(two[:, 1], mg.solve(b), rtol=1e-12, atol=1e-14)
    # conjugate gradients with the cycle: far fewer steps than with Jacobi
    k = solver.assembler.matrix(data)
    steps = {}
    jacobi = spl.LinearOperator((n, n), lambda v: v / k.diagonal())
    for name, m in (("mg", spl.LinearOperator((n, n), mg.solve)), ("jacobi", jacobi)):
        count = [0]

        def tick(_, count=count):
            count[0] += 1

        x, info = spl.cg(k, b, rtol=1e-8, M=m, maxiter=2000, callback=tick)
        assert info == 0 and np.linalg.norm(k @ x - b) <= 1e-7 * np.linalg.norm(b)
        steps[name] = count[0]
    assert steps["mg"] < steps["jacobi"] / 4, steps


def test_indefinite_matrix_is_refused_like_a_cholesky(block):
    _, _, _, solver, data = block
    mg = PMultigrid(solver.assembler)
    with pytest.raises(NotPositiveDefinite):
        mg.factorize(-data)


def test_newton_with_p_multigrid_reaches_the_direct_answer(block):
    mesh, fixed, problem, _, _ = block
    f = np.zeros((mesh.n_vertices, 3))
    tip = np.flatnonzero(mesh.points[:, 0] > 6 - 1e-9)
    f[tip, 2] = -3e-3 / len(tip)
    direct = Solver(problem, SolverConfig(linear_solver="cholmod")).solve(f)
    assert direct.max_displacement > 1.0  # large deflection
    for strategy in ("krylov", "newton"):
        cfg = dataclasses.replace(SolverConfig(), linear_solver="p-multigrid", strategy=strategy)
        res = Solver(problem, cfg).solve(f)
        diff = np.abs(res.displacement - direct.displacement).max() / direct.max_displacement
        assert diff < 1e-3, (strategy, diff)


def test_auto_picks_p_multigrid_by_size_and_order(block):
    mesh, fixed, problem, solver, _ = block
    n = solver.assembler.n_free
    pick = lambda cfg, asm=solver.assembler: make_linear_solver("auto", asm, cfg).name  # noqa: E731
    assert pick(SolverConfig(multigrid_dofs=n)) == "p-multigrid"
    assert pick(SolverConfig(multigrid_dofs=n + 1)) != "p-multigrid"
    assert pick(SolverConfig(multigrid_dofs=0)) != "p-multigrid"
    p1 = Solver(Problem(mesh, MAT, fixed, order=1), SolverConfig(linear_solver="cholmod")).assembler
    assert pick(SolverConfig(multigrid_dofs=1), p1) != "p-multigrid"
    with pytest.raises(SolverSetupError, match="needs quadratic elements"):
        make_linear_solver("p-multigrid", p1)


def test_the_registry_lists_every_backend_the_config_can_name(block):
    """fem.linear.BACKENDS is the one list: the config's linear_solver choices are it plus
    "auto", each name builds its own class, and an unknown name lists them all."""
    from tissuecast.fem.linear import BACKENDS, available_backends

    choices = {f.name: f for f in dataclasses.fields(SolverConfig)}["linear_solver"].metadata["choices"]
    assert set(choices) == set(BACKENDS) | {"auto"}
    assert [b.name for b in BACKENDS.values() if not b.direct] == ["p-multigrid"]
    assert set(available_backends()) <= {b.name for b in BACKENDS.values() if b.direct} and "superlu" in available_backends()
    asm = block[3].assembler
    for name in ["p-multigrid", *available_backends()]:
        lin = make_linear_solver(name, asm, SolverConfig())
        assert lin.name == name and lin.exact == BACKENDS[name].direct
    assert isinstance(make_linear_solver("p-multigrid", asm), PMultigrid)
    with pytest.raises(SolverSetupError, match="unknown linear solver 'lu'; choose one of 'auto', 'cholmod', 'pardiso', "
                                               "'superlu', 'p-multigrid'"):
        make_linear_solver("lu", asm)
