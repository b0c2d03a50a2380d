"""Reduced-order predictor: ECSW weights, Galerkin exactness, and what it saves the full solver."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls

from tissuecast.config import SolverConfig
from tissuecast.errors import SolverSetupError
from tissuecast.fem import NeoHookean, Problem, Solver
from tissuecast.fem.reduced import ReducedModel, ecsw_weights

from mesh_factories import box_grid

MAT = NeoHookean(0.021, 0.45)


def _bar(order):
    """A 40 x 10 x 10 mm bar (P1 or P2) clamped at x = 0, with its end loads."""
    mesh = box_grid(4, 2, 2, size=(10.0, 5.0, 5.0))
    fixed = np.flatnonzero(mesh.points[:, 0] == 0.0)
    end = np.flatnonzero(mesh.points[:, 0] == mesh.points[:, 0].max())
    return Problem(mesh, MAT, fixed, order=order), end


def _forces(problem, end, direction, total):
    f = np.zeros((problem.n_vertices, 3))
    f[end] = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction) * total / len(end)
    return f


def test_ecsw_weights_meet_the_tolerance_sparsely_and_agree_with_nnls():
    rng = np.random.default_rng(0)
    g = np.abs(rng.standard_normal((60, 200))) + 0.3 * rng.standard_normal((60, 200))
    b = g.sum(axis=1)
    x = ecsw_weights(g, b, 1e-2)
    assert (x >= 0).all()
    assert np.linalg.norm(g @ x - b) <= 1e-2 * np.linalg.norm(b)
    assert 0 < (x > 0).sum() < 60  # far fewer than the 200 columns
    # run to the end it is the non-negative least-squares optimum
    exact = ecsw_weights(g, b, 1e-12)
    _, best = nnls(g, b)
    assert np.linalg.norm(g @ exact - b) == pytest.approx(best, abs=1e-8 * np.linalg.norm(b))


@pytest.mark.parametrize("method", ["bfgs", "newton"])
@pytest.mark.parametrize("order", [1, 2])
def test_reduced_solution_is_exact_when_the_basis_holds_the_answer(order, method):
    problem, end = _bar(order)
    solver = Solver(problem, SolverConfig(force_tolerance=1e-9, displacement_tolerance=1e-9))  # tight
    f = _forces(problem, end, [0.0, 0.3, 1.0], 0.02)
    truth = solver.solve(f).nodal_displacement
    assert np.abs(truth).max() > 5.0  # large deformation (mm)
    # the basis holds the answer and the equilibria on the way to it (a straight line from
    # zero to a large rotation would cross an energy barrier: a subspace must hold the path)
    path = [solver.solve(s * f).nodal_displacement for s in (0.25, 0.5, 0.75)]
    free = np.flatnonzero(problem.free_mask)
    basis = np.linalg.qr(np.column_stack([u.ravel()[free] for u in (*path, truth)]))[0]
    m = len(problem.connectivity)
    model = ReducedModel(problem, basis, np.arange(m), np.ones(m))  # every element, weight 1
    guess = model.predict(f, tolerance=1e-10, method=method, bfgs_tolerance=1e-10)
    assert np.abs(guess - truth).max() <= 1e-6 * np.abs(truth).max()


def test_fitted_model_predicts_new_loads_and_saves_newton_iterations():
    problem, end = _bar(2)
    solver = Solver(problem)
    rng = np.random.default_rng(3)
    directions = rng.standard_normal((12, 3)) * [0.3, 1.0, 1.0]
    snaps = [solver.solve(_forces(problem, end, d, 0.015)).nodal_displacement for d in directions]
    model = ReducedModel.fit(problem, np.stack(snaps), tolerance=0.01)
    assert model.n_modes <= 12 and 0 < len(model.elements) < len(problem.connectivity)
    assert model.fit_error <= 0.01
    f = _forces(problem, end, [0.1, 0.6, -0.8], 0.015)
    cold = solver.solve(f)
    guess = model.predict(f)
    peak = np.abs(cold.nodal_displacement).max()
    assert np.abs(guess - cold.nodal_displacement).max() <= 0.05 * peak
    warm = solver.solve(f, initial_guess=guess)
    assert warm.iterations < cold.iterations
    assert np.abs(warm.displacement - cold.displacement).max() <= 2e-3 * peak
    # quasi-Newton (default) and Newton find the same reduced equilibrium
    newton = model.predict(f, method="newton", tolerance=1e-8)
    bfgs = model.predict(f, bfgs_tolerance=1e-8)
    assert np.abs(bfgs - newton).max() <= 1e-4 * peak
    assert np.abs(guess - newton).max() <= 1e-2 * peak  # the default stopping tests


def test_quasi_newton_prediction_falls_back_to_newton(monkeypatch):
    problem, end = _bar(2)
    solver = Solver(problem)
    snaps = [solver.solve(_forces(problem, end, d, 0.01)).nodal_displacement for d in ([0, 1, 0], [0, 0, 1], [1, 1, 1])]
    model = ReducedModel.fit(problem, np.stack(snaps))
    f = _forces(problem, end, [0.2, 0.5, 0.5], 0.01)
    newton = model.predict(f, method="newton")
    monkeypatch.setattr(model, "_bfgs", lambda *args: None)  # e.g. its line search failed
    assert np.array_equal(model.predict(f), newton)
    with pytest.raises(SolverSetupError, match="method must be 'bfgs' or 'newton'"):
        model.predict(f, method="lbfgs")


def test_bad_snapshots_and_prescribed_displacements_are_refused():
    problem, end = _bar(1)
    with pytest.raises(SolverSetupError, match="snapshots must be"):
        ReducedModel.fit(problem, np.zeros((2, 5, 3)))
    with pytest.raises(SolverSetupError, match="all zero"):
        ReducedModel.fit(problem, np.zeros((2, len(problem.nodes), 3)))
    moved = Problem(problem.mesh, MAT, problem.fixed, order=1, prescribed={int(end[0]): [0.0, 0.0, 1.0]})
    free = int(moved.free_mask.sum())
    with pytest.raises(SolverSetupError, match="prescribed"):
        ReducedModel(moved, np.eye(free, 1), np.arange(2), np.ones(2))


def test_best_rotation_recovers_a_rigid_rotation():
    from tissuecast.fem.linesearch import rotation_matrix
    from tissuecast.fem.newton import best_rotation

    problem, _ = _bar(2)
    r = rotation_matrix(np.array([0.3, -0.5, 0.9]))
    x = problem.nodes
    u = (x - x.mean(0)) @ r.T + x.mean(0) + [1.0, 2.0, 3.0] - x
    assert np.allclose(best_rotation(x, u), r, atol=1e-12)


def test_reference_preconditioner_saves_factorisations_from_a_guess():
    problem, end = _bar(2)
    f = _forces(problem, end, [0.2, 0.5, -0.8], 0.015)
    cold = Solver(problem).solve(f)
    guess = cold.nodal_displacement * 0.97  # a guess 3 % off
    plain = Solver(problem, SolverConfig(reference_preconditioner=False)).solve(f, initial_guess=guess)
    ref = Solver(problem).solve(f, initial_guess=guess)
    assert ref.factorizations < plain.factorizations
    peak = np.abs(cold.displacement).max()
    assert np.abs(ref.displacement - cold.displacement).max() <= 2e-3 * peak


def _bar_snapshots(problem, end, n=8):
    solver = Solver(problem)
    rng = np.random.default_rng(5)
    directions = rng.standard_normal((n, 3)) * [0.3, 1.0, 1.0]
    return np.stack([solver.solve(_forces(problem, end, d, 0.01)).nodal_displacement for d in directions])


def test_with_springs_is_the_model_of_the_problem_with_those_springs():
    from tissuecast.fem.springs import NodalSprings

    problem, end = _bar(1)
    model = ReducedModel.fit(problem, _bar_snapshots(problem, end), tolerance=0.01)
    f = _forces(problem, end, [0.1, 0.6, -0.8], 0.01)
    before = model.predict(f)
    k = np.zeros((len(end), 3, 3))
    k[:, [0, 1, 2], [0, 1, 2]] = [0.002, 0.004, 0.004]  # N/mm on the loaded end
    springs = NodalSprings(end, k)
    held = ReducedModel(Problem(problem.mesh, MAT, problem.fixed, order=1, springs=springs),
                        model.basis, model.elements, model.weights)
    view = model.with_springs(springs)
    expected = held.predict(f)
    assert np.abs(view.predict(f) - expected).max() <= 1e-9 * np.abs(expected).max()
    assert np.abs(expected).max() < 0.9 * np.abs(before).max()  # the springs hold the end back
    np.testing.assert_array_equal(model.predict(f), before)  # the model itself is unchanged
    np.testing.assert_array_equal(model.with_springs(None).predict(f), before)  # no springs: as the problem's (none)


def test_a_samples_reduced_guess_scales_loads_and_springs_with_its_modulus_and_holds_its_extra_vertices():
    """A body s times stiffer on springs of c times the nominal stiffness deforms under loads L
    as the nominal body under L / s on springs c / s times the nominal (exact for the
    neo-Hookean energy)."""
    from tissuecast.fem.springs import NodalSprings
    from tissuecast.scenario.parameters import ParameterDraw
    from tissuecast.scenario.sample_inputs import SampleInputs, ScenarioDraw

    problem, end = _bar(1)
    k = np.zeros((len(end), 3, 3))
    k[:, [0, 1, 2], [0, 1, 2]] = 0.003
    nominal_springs = NodalSprings(end, k)
    problem = Problem(problem.mesh, MAT, problem.fixed, order=1, springs=nominal_springs)
    model = ReducedModel.fit(problem, _bar_snapshots(problem, end), tolerance=0.01)
    s, c = 2.5, 0.4
    f = _forces(problem, end, [0.1, 0.6, -0.8], 0.01 * s)
    stiff = Problem(problem.mesh, NeoHookean(0.021 * s, 0.45), problem.fixed, order=1,
                    springs=NodalSprings(end, k * c))
    expected = ReducedModel(stiff, model.basis, model.elements, model.weights).predict(f)

    def inputs(held=()):
        return SampleInputs(f, np.zeros((0, 3)), f, None, np.zeros(0, np.int64), np.zeros((0, 3)), ScenarioDraw(),
                            parameters=ParameterDraw(youngs_modulus=s, spring_normal=c, spring_tangential=c),
                            springs=NodalSprings(end, k * c),
                            extra_held=np.asarray(held, dtype=np.int64))

    guess = inputs().reduced_guess(model)
    assert np.abs(guess - expected).max() <= 1e-8 * np.abs(expected).max()
    naive = model.predict(f / s)  # the loads scaled, the springs not: the body on springs s times the nominal
    assert np.abs(naive - expected).max() > 1e-3 * np.abs(expected).max()
    middle = np.flatnonzero(np.isclose(problem.mesh.points[:, 0], 20.0))
    held = inputs(middle).reduced_guess(model)
    assert np.abs(held[middle]).max() < 0.1 * np.abs(guess[middle]).max()


def test_a_samples_reduced_guess_carries_its_prescribed_displacements():
    """A sample's prescribed vertices (an indentation) are pulled to their values in the guess
    by stiff springs: the guess puts them near the values and the rest of the body follows,
    where the loads-only prediction leaves them where the loads put them."""
    from tissuecast.scenario.sample_inputs import SampleInputs, ScenarioDraw

    problem, end = _bar(1)
    model = ReducedModel.fit(problem, _bar_snapshots(problem, end), tolerance=0.01)
    f = _forces(problem, end, [0.1, 0.6, -0.8], 0.002)
    values = np.tile([0.0, 0.0, -3.0], (len(end), 1))  # the loaded end pushed 3 mm down
    sample = SampleInputs(f, np.zeros((0, 3)), f, None, end.astype(np.int64), values, ScenarioDraw())
    guess = sample.reduced_guess(model)
    free = model.predict(f)
    assert np.abs(guess[end] - values).max() < 0.1 * 3.0, guess[end]
    assert np.abs(free[end] - values).max() > 1.0  # the loads alone do not put the end there
    middle = np.flatnonzero(np.isclose(problem.mesh.points[:, 0], 20.0))
    assert guess[middle, 2].mean() < 0.3 * values[0, 2]  # the body between follows the end down
    # with no prescribed vertex and no drawn parameter: the plain prediction, bit for bit
    plain = SampleInputs(f, np.zeros((0, 3)), f, None, np.zeros(0, np.int64), np.zeros((0, 3)), ScenarioDraw())
    np.testing.assert_array_equal(plain.reduced_guess(model), free)
