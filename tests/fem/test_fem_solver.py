"""Newton solver behaviour: input validation, reactions, failure reporting, strategies, warm starts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.config import SolverConfig
from tissuecast.errors import ConvergenceError, SolverSetupError
from tissuecast.fem import NeoHookean, Problem, SolveResult, Solver, solve
from tissuecast.fem.newton import IncrementFailed, SolveRun
from tissuecast.fem.solver import _drive

MAT = NeoHookean(0.021, 0.45)


@pytest.fixture(scope="module")
def beam():
    """4 x 1 x 1 mm beam (8 x 2 x 2 cells) clamped at x = 0 with a tip load in -z (N)."""
    mesh = box_grid(8, 2, 2, size=(0.5, 0.5, 0.5))
    x = mesh.points[:, 0]
    fixed = np.flatnonzero(x < 1e-9)
    f = np.zeros((mesh.n_vertices, 3))
    tip = np.flatnonzero(x > 4 - 1e-9)
    f[tip, 2] = -2e-4 / len(tip)
    f[tip, 1] = 5e-5 / len(tip)
    return mesh, fixed, f


@pytest.mark.parametrize("order", [1, 2])
def test_reactions_balance_applied_forces(beam, order):
    mesh, fixed, f = beam
    cfg = dataclasses.replace(SolverConfig(), force_tolerance=1e-9, displacement_tolerance=1e-9)
    res = solve(Problem(mesh, MAT, fixed, order=order), f, cfg)
    assert isinstance(res, SolveResult) and res.converged and res.load_fraction == 1.0
    assert res.max_displacement > 0.5  # large deflection: the test is nonlinear
    total = res.nodal_reaction.sum(axis=0) + f.sum(axis=0)
    assert np.abs(total).max() <= 1e-8 * np.abs(f.sum(axis=0)).max()
    free = np.setdiff1d(np.arange(mesh.n_vertices), fixed)
    assert np.all(res.reaction[free] == 0.0)
    # moment balance about the origin in the deformed configuration
    x = res.nodal_displacement + Problem(mesh, MAT, fixed, order=order).nodes
    fnodal = np.zeros_like(x)
    fnodal[: mesh.n_vertices] = f
    moment = np.cross(x, res.nodal_reaction + fnodal).sum(axis=0)
    assert np.abs(moment).max() <= 1e-7 * np.abs(np.cross(x[: mesh.n_vertices], f).sum(axis=0)).max()


def test_result_record_is_complete(beam):
    mesh, fixed, f = beam
    res = Solver(Problem(mesh, MAT, fixed, order=2)).solve(f)
    assert res.displacement.shape == (mesh.n_vertices, 3)
    assert res.nodal_displacement.shape == (mesh.n_vertices + len(mesh.edges), 3)
    np.testing.assert_array_equal(res.nodal_displacement[: mesh.n_vertices], res.displacement)
    assert res.iterations >= res.increments >= 1 and res.factorizations >= 1 and res.solves >= res.iterations
    assert len(res.residual_history) == res.iterations and res.seconds > 0
    assert np.all(res.displacement[fixed] == 0.0)


def test_strategies_agree_and_quasi_newton_saves_factorisations(beam):
    mesh, fixed, f = beam
    prob = Problem(mesh, MAT, fixed, order=2)
    tight = dataclasses.replace(SolverConfig(), force_tolerance=1e-6, displacement_tolerance=1e-6)
    newton = Solver(prob, dataclasses.replace(tight, strategy="newton")).solve(f)
    quasi = Solver(prob, dataclasses.replace(tight, strategy="quasi-newton")).solve(f)
    straight = Solver(prob, dataclasses.replace(tight, rotation_aware=False)).solve(f)
    scale = newton.max_displacement
    assert np.abs(quasi.displacement - newton.displacement).max() <= 1e-5 * scale
    assert np.abs(straight.displacement - newton.displacement).max() <= 1e-5 * scale
    assert quasi.factorizations < newton.factorizations


def test_krylov_strategy_agrees_and_saves_factorisations(beam):
    """Conjugate gradients preconditioned by an older factorisation reach the same solution
    with fewer factorisations; each Newton iteration takes between 1 and krylov_iterations
    preconditioned solves unless it refactorised."""
    mesh, fixed, f = beam
    prob = Problem(mesh, MAT, fixed, order=2)
    tight = dataclasses.replace(SolverConfig(), force_tolerance=1e-6, displacement_tolerance=1e-6)
    newton = Solver(prob, dataclasses.replace(tight, strategy="newton")).solve(f)
    krylov = Solver(prob, dataclasses.replace(tight, strategy="krylov")).solve(f)
    assert krylov.converged
    assert np.abs(krylov.displacement - newton.displacement).max() <= 1e-5 * newton.max_displacement
    assert krylov.factorizations < newton.factorizations
    assert krylov.solves > krylov.iterations  # several CG steps per reused factorisation
    # one CG step allowed: every Newton iteration refactorises unless one step is enough
    one = Solver(prob, dataclasses.replace(tight, strategy="krylov", krylov_iterations=1)).solve(f)
    assert np.abs(one.displacement - newton.displacement).max() <= 1e-5 * newton.max_displacement
    assert one.factorizations > krylov.factorizations


def test_krylov_direction_solves_the_current_tangent():
    """SolveRun.krylov_direction: with the tangent at u itself factorised, one CG step is exact; with an older
    factorisation CG converges to K(u)^-1 r within krylov_tolerance."""
    from mesh_factories import box_grid as grid

    mesh = grid(3, 2, 2, size=(1.0, 1.0, 1.0))
    prob = Problem(mesh, MAT, np.flatnonzero(mesh.points[:, 0] < 1e-9), order=2)  # clamped face
    solver = Solver(prob, SolverConfig(strategy="krylov", krylov_tolerance=1e-8, krylov_iterations=200,
                                       krylov_recycle=0))
    run = SolveRun(solver, np.zeros(solver.assembler.n_dofs))
    rng = np.random.default_rng(1)
    u = 0.005 * rng.normal(size=(len(prob.nodes), 3))  # small enough that K(u) is positive definite
    u[prob.constrained_nodes[0]] = 0.0
    r = rng.normal(size=solver.assembler.n_free)
    _, data, _ = solver.assembler.tangent(u)
    exact = -np.linalg.solve(solver.assembler.matrix(data).toarray(), r)
    run.factorize(u.ravel())
    d, rest = _drive(run.krylov_direction(u.ravel(), r))
    assert rest is None and run.counts.krylov_steps == 1
    np.testing.assert_allclose(d, exact, rtol=1e-8, atol=1e-12 * np.abs(exact).max())
    run.factorize(np.zeros_like(u).ravel())  # an older (reference) tangent as preconditioner
    d, rest = _drive(run.krylov_direction(u.ravel(), r))
    assert rest is None and run.counts.krylov_steps > 2
    assert np.abs(d - exact).max() <= 1e-6 * np.abs(exact).max()


def test_recycled_krylov_is_exact_and_needs_fewer_steps():
    """Deflated CG (krylov_recycle): each direction still solves its own tangent to the
    tolerance, and the directions recycled from earlier tangents (plus the rotations about
    the pins) save conjugate-gradient steps on a sequence of tangents along a load path."""
    from mesh_factories import box_grid as grid

    mesh = grid(4, 3, 3, size=(2.0, 1.5, 1.5))
    pins = np.argsort(np.linalg.norm(mesh.points - mesh.points.mean(axis=0), axis=1))[:3]
    prob = Problem(mesh, MAT, pins, order=2)
    rng = np.random.default_rng(3)
    states = []
    u = np.zeros((len(prob.nodes), 3))
    for _ in range(4):  # small smooth displacements (a swing and a stretch): positive-definite tangents
        u = u + 0.01 * (prob.nodes - prob.nodes.mean(axis=0)) @ rng.normal(size=(3, 3))
        u[prob.constrained_nodes[0]] = 0.0
        states.append(u.copy())
    rhs = [rng.normal(size=3 * len(prob.nodes))[Solver(prob).assembler.free_dofs] for _ in states]
    steps = {}
    for cap in (0, 20):
        solver = Solver(prob, SolverConfig(strategy="krylov", krylov_tolerance=1e-6, krylov_iterations=500,
                                           krylov_recycle=cap))
        run = SolveRun(solver, np.zeros(solver.assembler.n_dofs))
        run.factorize(np.zeros(solver.assembler.n_dofs))  # the reference stiffness as preconditioner
        for state, r in zip(states, rhs):
            _, data, _ = solver.assembler.tangent(state)
            k = solver.assembler.matrix(data)
            exact = -np.linalg.solve(k.toarray(), r)
            d, rest = _drive(run.krylov_direction(state.ravel(), r))
            assert rest is None
            assert np.linalg.norm(k @ d + r) <= 1e-6 * np.linalg.norm(r) * (1 + 1e-9)
            assert np.abs(d - exact).max() <= 1e-4 * np.abs(exact).max()
        steps[cap] = run.counts.krylov_steps
        if cap:
            assert run.recycled is not None and 0 < run.recycled.shape[1] <= cap
    assert steps[20] < steps[0]


def test_default_tolerances_are_accurate(beam):
    mesh, fixed, f = beam
    prob = Problem(mesh, MAT, fixed, order=2)
    ref = Solver(prob, dataclasses.replace(SolverConfig(), force_tolerance=1e-9, displacement_tolerance=1e-9)).solve(f)
    res = Solver(prob).solve(f)
    assert np.abs(res.displacement - ref.displacement).max() <= 2e-3 * ref.max_displacement


def test_initial_guess_at_the_solution_needs_no_work(beam):
    mesh, fixed, f = beam
    solver = Solver(Problem(mesh, MAT, fixed, order=2))
    first = solver.solve(f)
    again = solver.solve(f, initial_guess=first.nodal_displacement)
    assert again.iterations <= 1 and again.factorizations <= 1
    assert np.abs(again.displacement - first.displacement).max() <= 1e-2 * first.max_displacement
    near = solver.solve(f, initial_guess=first.displacement * 1.02)  # vertices only
    assert near.iterations < first.iterations
    assert np.abs(near.displacement - first.displacement).max() <= 1e-2 * first.max_displacement


def test_batch_gathers_the_solves_and_matches_single_solves(beam):
    """solve_batch: the samples that start from guesses share the reference factorisation,
    whose solves are gathered into multi-column ones; each result equals its single solve to
    far below the convergence tolerance, a repeated batch gives the same bits, and a failing
    sample is returned as its ConvergenceError without losing the others."""
    mesh, fixed, f = beam
    cfg = dataclasses.replace(SolverConfig(), min_increment=1e-3, max_increments=40)
    solver = Solver(Problem(mesh, MAT, fixed, order=2), cfg)
    twist = f.copy()
    twist[:, 1] *= -3.0
    fields = [f, 0.7 * f, twist, f, 1e4 * f]
    first = solver.solve(f)
    guesses = [first.nodal_displacement * 1.03, first.displacement * 0.6, first.nodal_displacement, None, None]
    single = [solver.solve(x, initial_guess=g) for x, g in zip(fields[:4], guesses[:4])]
    widths = []
    reference = solver.reference_factor()
    plain = reference.solve

    def counting(b):
        widths.append(1 if b.ndim == 1 else b.shape[1])
        return plain(b)

    reference.solve = counting
    try:
        out = solver.solve_batch(fields, guesses)
    finally:
        reference.solve = plain
    assert isinstance(out[4], ConvergenceError) and out[4].load_fraction < 1.0
    for a, b in zip(out[:4], single):
        assert isinstance(a, SolveResult) and a.converged
        # round-off of the gathered solves, carried through the Newton iterations: far below
        # the convergence tolerance (1e-2 of the displacement)
        assert np.abs(a.displacement - b.displacement).max() <= 1e-6 * b.max_displacement
        # a residual within round-off of the tolerance may take one iteration more or less
        assert abs(a.iterations - b.iterations) <= 1
    assert max(widths) == 3  # the three guessed samples' first solves, together
    assert len(widths) < sum(widths)  # fewer solves than right-hand sides
    again = solver.solve_batch(fields[:4], guesses[:4])
    for a, b in zip(again, out[:4]):
        np.testing.assert_array_equal(a.nodal_displacement, b.nodal_displacement)
    with pytest.raises(SolverSetupError, match="one per field"):
        solver.solve_batch(fields, guesses[:2])
    with pytest.raises(SolverSetupError):
        solver.solve_batch([f, f[:3]])
    with pytest.raises(SolverSetupError, match="initial_guess must be a finite"):
        solver.solve_batch([f, f], [None, first.displacement[:3]])


def test_impossible_load_raises_convergence_error_with_load_fraction(beam):
    mesh, fixed, f = beam
    cfg = dataclasses.replace(SolverConfig(), min_increment=1e-3, max_increments=40)
    with pytest.raises(ConvergenceError) as info:
        solve(Problem(mesh, MAT, fixed, order=1), f * 1e4, cfg)
    err = info.value
    assert 0.0 <= err.load_fraction < 1.0
    assert err.result is not None and not err.result.converged
    assert err.result.load_fraction == err.load_fraction
    assert "load fraction" in str(err)


def test_prescribed_displacement_and_reaction(beam):
    mesh, fixed, _ = beam
    tip = np.flatnonzero(mesh.points[:, 0] > 4 - 1e-9)
    pres = {int(v): (0.0, 0.0, -0.8) for v in tip}
    res = solve(Problem(mesh, MAT, fixed, order=2, prescribed=pres), np.zeros((mesh.n_vertices, 3)))
    np.testing.assert_allclose(res.displacement[tip], np.tile([0.0, 0.0, -0.8], (len(tip), 1)), atol=1e-14)
    # the supports pull the tip down and the clamp holds it: reactions balance
    assert res.reaction[tip, 2].sum() < 0
    assert abs(res.nodal_reaction[:, 2].sum()) <= 1e-3 * abs(res.reaction[tip, 2].sum())


# ------------------------------------------------------------------ validation errors
def test_setup_errors(beam):
    mesh, fixed, f = beam
    line = np.flatnonzero((np.abs(mesh.points[:, 1]) < 1e-9) & (np.abs(mesh.points[:, 2]) < 1e-9))[:4]
    with pytest.raises(SolverSetupError, match="one line"):
        Problem(mesh, MAT, line)
    with pytest.raises(SolverSetupError, match="at least 3"):
        Problem(mesh, MAT, fixed[:2])
    with pytest.raises(SolverSetupError, match="outside"):
        Problem(mesh, MAT, [0, 1, mesh.n_vertices])
    with pytest.raises(SolverSetupError, match="repeats"):
        Problem(mesh, MAT, [0, 0, 1, 2])
    with pytest.raises(SolverSetupError, match="order"):
        Problem(mesh, MAT, fixed, order=3)
    with pytest.raises(SolverSetupError, match="both fixed and prescribed"):
        Problem(mesh, MAT, fixed, prescribed={int(fixed[0]): (0, 0, 1)})
    with pytest.raises(SolverSetupError, match="shape"):
        Problem(mesh, MAT, fixed, prescribed=([5, 6], np.zeros((3, 3))))
    with pytest.raises(SolverSetupError, match="linear solver"):
        Solver(Problem(mesh, MAT, fixed, order=1), dataclasses.replace(SolverConfig(), linear_solver="nope"))


def test_force_errors(beam):
    mesh, fixed, f = beam
    solver = Solver(Problem(mesh, MAT, fixed, order=1))
    with pytest.raises(SolverSetupError, match="shape"):
        solver.solve(f[:-1])
    with pytest.raises(SolverSetupError, match="shape"):
        solver.solve(f.ravel())
    bad = f.copy()
    bad[-1, 0] = np.nan
    with pytest.raises(SolverSetupError, match="not finite"):
        solver.solve(bad)
    on_fixed = f.copy()
    on_fixed[fixed[1]] = (0.0, 1e-5, 0.0)
    with pytest.raises(SolverSetupError, match=f"constrained .*{fixed[1]}"):
        solver.solve(on_fixed)
    with pytest.raises(SolverSetupError, match="initial_guess"):
        solver.solve(f, initial_guess=np.zeros((3, 3)))


def test_zero_forces_give_zero_displacement(beam):
    mesh, fixed, f = beam
    res = solve(Problem(mesh, MAT, fixed, order=2), np.zeros_like(f))
    assert res.converged and np.all(res.displacement == 0.0)


def test_rotation_aware_path_follows_the_arc_of_a_rigid_rotation():
    from tissuecast.fem.linesearch import rotation_matrix, step_path

    rng = np.random.default_rng(0)
    nodes = rng.standard_normal((30, 3)) * 10.0
    u = np.zeros(90)
    cnodes = np.array([0, 1, 2])
    cdofs = (3 * cnodes[:, None] + np.arange(3)).ravel()
    free = np.setdiff1d(np.arange(90), cdofs)
    c = nodes[cnodes].mean(axis=0)
    omega = np.array([0.1, -0.4, 0.3])
    d = np.cross(omega, nodes - c).ravel()[free]  # an infinitesimal rotation about c
    path = step_path(nodes, u, d, free, cnodes, cdofs, rotation_aware=True)
    moved = path(1.0).reshape(-1, 3)
    exact = (nodes - c) @ rotation_matrix(omega).T + c - nodes
    np.testing.assert_allclose(moved[3:], exact[3:], atol=1e-12)
    np.testing.assert_allclose(path.rotation, rotation_matrix(omega), atol=1e-14)
    assert np.all(moved[:3] == 0.0)  # constrained nodes stay put
    # distances between free nodes are preserved (no spurious stretching), unlike the straight line
    straight = step_path(nodes, u, d, free, cnodes, cdofs, rotation_aware=False)(1.0).reshape(-1, 3)
    dist = lambda x: np.linalg.norm(x[3:, None] - x[None, 3:], axis=-1)  # noqa: E731
    np.testing.assert_allclose(dist(nodes + moved), dist(nodes), atol=1e-10)
    assert np.abs(dist(nodes + straight) - dist(nodes)).max() > 1.0


def test_line_search_lengthens_a_newton_step_that_is_too_short():
    """On Pi(x) = 1/2 x.A x - f.x a direction of 0.4 x the true step is stretched 2.5x (the secant of
    the slopes is exact for a quadratic); the exact Newton step is kept as it is."""
    from tissuecast.fem.linesearch import line_search

    rng = np.random.default_rng(3)
    q = rng.normal(size=(6, 6))
    a = q @ q.T + 6 * np.eye(6)
    fext = rng.normal(size=6)

    class Quadratic:
        def energy_and_force(self, u):
            x = u.ravel()
            return 0.5 * x @ a @ x, a @ x, 1.0

    def straight(d):
        def path(s):
            return s * d

        path.rotation = np.eye(3)
        return path

    free = np.arange(6)
    exact = np.linalg.solve(a, fext)
    r0 = -fext
    s, x, pi, _, r, _ = line_search(Quadratic(), straight(0.4 * exact), free, 0.4 * exact, 0.0, r0, fext)
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(x, exact, rtol=1e-12)
    assert np.abs(r).max() < 1e-12
    s, x, *_ = line_search(Quadratic(), straight(exact), free, exact, 0.0, r0, fext)
    assert s == 1.0
    np.testing.assert_allclose(x, exact, rtol=1e-12)


def test_build_problem_takes_the_material_and_order_and_refuses_a_config(beam):
    from tissuecast.config import Config
    from tissuecast.fem import NeoHookean, build_problem

    mesh, fixed, _ = beam
    problem = build_problem(mesh, NeoHookean(0.03, 0.4), fixed, order=1)
    assert problem.order == 1 and problem.material.youngs_modulus == 0.03 and problem.material.poisson_ratio == 0.4
    np.testing.assert_array_equal(problem.fixed, fixed)
    assert build_problem(mesh, NeoHookean(0.03, 0.4), fixed).order == 2
    with pytest.raises(SolverSetupError, match="at least 3"):
        build_problem(mesh, NeoHookean(), fixed[:2])
    with pytest.raises(SolverSetupError, match=r"takes the material as a NeoHookean \(MPa\), got Config; from a run "
                                               r"config: NeoHookean\(cfg.material.youngs_modulus"):
        build_problem(mesh, Config(), fixed)


def test_convergence_test_by_hand():
    """converged(): both criteria, the residual alone far below its tolerance, and the
    correction scaled by rho / (1 - rho) while the corrections contract slowly."""
    from tissuecast.fem.convergence import converged, correction_estimate, reference_force

    assert correction_estimate(1.0, None) == 1.0
    assert correction_estimate(0.5, 1.0) == 0.5  # rho 0.5: rho / (1 - rho) = 1
    assert correction_estimate(0.9, 1.0) == pytest.approx(0.9 * 9.0)  # rho 0.9: 9x
    assert correction_estimate(0.99, 1.0) == 0.99  # not contracting: the raw correction
    tol = dict(force_tolerance=5e-3, displacement_tolerance=1e-2)
    assert converged(rmax=4e-3, q=1.0, cmax=0.05, estimate=0.05, dmax=10.0, umax=10.0, **tol)
    assert not converged(rmax=6e-3, q=1.0, cmax=0.05, estimate=0.05, dmax=10.0, umax=10.0, **tol)  # residual
    assert not converged(rmax=4e-3, q=1.0, cmax=0.05, estimate=0.2, dmax=10.0, umax=10.0, **tol)  # correction
    assert converged(rmax=4e-6, q=1.0, cmax=5.0, estimate=5.0, dmax=10.0, umax=10.0, **tol)  # residual alone
    assert converged(rmax=4e-3, q=1.0, cmax=1e-12, estimate=1.0, dmax=0.0, umax=10.0, **tol)  # round-off
    fext = np.array([0.0, 3.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # 5 N on node 0
    fint = np.array([0.0, 3.0, 4.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0])  # 1 N reaction on node 2
    assert reference_force(fint, fext, np.array([2])) == pytest.approx(3.0)  # mean of 5 and 1


def test_time_limit_stops_a_solve_and_returns_its_factor(beam):
    from tissuecast.errors import SolveTimeout

    mesh, fixed, f = beam
    solver = Solver(Problem(mesh, MAT, fixed, order=2), SolverConfig(strategy="newton"))
    with pytest.raises(SolveTimeout, match="past its time limit of 0.0 s") as err:
        solver.solve(f, time_limit=0.0)
    assert isinstance(err.value, ConvergenceError) and err.value.limit == 0.0
    assert err.value.seconds > err.value.limit  # it stopped because it ran past the limit, and says how far
    assert len(solver._idle_factors) == 1  # the stopped run gave its numeric factor back
    res = solver.solve(f, time_limit=600.0)  # a generous limit changes nothing
    np.testing.assert_array_equal(res.displacement, solver.solve(f).displacement)


def test_iteration_limit_stops_a_solve_at_the_same_point_on_any_machine(beam):
    """iteration_limit: a solve that needs n iterations converges with the limit n, bitwise as
    without one, and is stopped with n - 1 (IterationLimit, a ConvergenceError, its factor
    given back); factorization_limit likewise with its factorisations; a limit that is not a
    whole number is refused."""
    from tissuecast.errors import IterationLimit, SolverSetupError

    mesh, fixed, f = beam
    solver = Solver(Problem(mesh, MAT, fixed, order=2), SolverConfig(strategy="newton"))
    free = solver.solve(f)
    assert free.iterations > 2
    at = solver.solve(f, iteration_limit=free.iterations)
    np.testing.assert_array_equal(at.nodal_displacement, free.nodal_displacement)
    with pytest.raises(IterationLimit, match=f"its limit of {free.iterations - 1} spent") as err:
        solver.solve(f, iteration_limit=free.iterations - 1)
    assert isinstance(err.value, ConvergenceError) and err.value.iterations == free.iterations - 1
    assert err.value.limit == free.iterations - 1
    assert len(solver._idle_factors) == 1  # the stopped run gave its numeric factor back
    assert free.factorizations > 2  # Newton: a factorisation each iteration
    at = solver.solve(f, factorization_limit=free.factorizations)
    np.testing.assert_array_equal(at.nodal_displacement, free.nodal_displacement)
    with pytest.raises(IterationLimit, match=f"its limit of {free.factorizations - 1} factorisations spent") as err:
        solver.solve(f, factorization_limit=free.factorizations - 1)
    assert err.value.limit == free.factorizations - 1 and err.value.iterations < free.iterations
    for bad in (-1, 2.5, "10"):
        for name in ("iteration_limit", "factorization_limit"):
            with pytest.raises(SolverSetupError, match=f"{name} must be a non-negative whole number"):
                solver.solve(f, **{name: bad})


def test_batch_time_limit_stops_each_sample_by_its_share(beam):
    """solve_batch(time_limit=): a sample is stopped once its share of the batch's rounds
    passes the limit (SolveTimeout, the others unaffected by a generous limit)."""
    from tissuecast.errors import SolveTimeout

    mesh, fixed, f = beam
    solver = Solver(Problem(mesh, MAT, fixed, order=2), SolverConfig())
    first = solver.solve(f)
    fields, guesses = [f, 0.8 * f], [first.nodal_displacement * 1.05, first.displacement * 0.7]
    out = solver.solve_batch(fields, guesses, time_limit=0.0)
    for exc in out:
        assert isinstance(exc, SolveTimeout) and exc.limit == 0.0 and exc.seconds > exc.limit
        assert "its share of a batch's time" in str(exc)
    free = solver.solve_batch(fields, guesses)
    limited = solver.solve_batch(fields, guesses, time_limit=600.0)
    for a, b in zip(free, limited):
        np.testing.assert_array_equal(a.nodal_displacement, b.nodal_displacement)


def test_one_blas_thread_limits_every_loaded_blas_and_restores_the_limits():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    import scipy.linalg  # noqa: F401  (the BLAS libraries one_blas_thread loads, loaded before it)

    from tissuecast.fem.linear import available_backends, one_blas_thread

    if "cholmod" in available_backends():
        import sksparse.cholmod  # noqa: F401

    def blas_threads():
        return {p["filepath"]: p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"}

    before = blas_threads()
    with one_blas_thread():
        inside = blas_threads()
    assert inside.keys() == before.keys() and set(inside.values()) == {1}
    assert blas_threads() == before


@pytest.mark.parametrize("strategy", ["krylov", "newton"])
def test_krylov_tries_an_increment_that_failed_twice_with_exact_newton_steps(beam, monkeypatch, strategy):
    """With Krylov directions, the second failed increment in a row is tried again at the same
    load step with a factorisation every iteration (a limit point is not passed by cutting the
    step); the next converged increment goes back to Krylov. Other strategies only cut back."""
    mesh, fixed, f = beam
    prob = Problem(mesh, MAT, fixed, order=1)
    cfg = dataclasses.replace(SolverConfig(), strategy=strategy, initial_increment=0.5)
    reference = Solver(prob, cfg).solve(f)
    original = SolveRun._increment
    calls = []

    def scripted(self, u, u_start, lam, qhist):
        calls.append((lam, self.exact, self.counts.factorizations, self.counts.iterations))
        if len(calls) <= 2:
            raise IncrementFailed("scripted failure")
        return (yield from original(self, u, u_start, lam, qhist))

    monkeypatch.setattr(SolveRun, "_increment", scripted)
    res = Solver(prob, cfg).solve(f)
    assert res.converged and np.abs(res.displacement - reference.displacement).max() <= 0.02 * reference.max_displacement
    (lam0, exact0, *_), (lam1, exact1, *_), (lam2, exact2, fac2, it2), (lam3, exact3, fac3, it3) = calls[:4]
    assert lam0 == 0.5 and lam1 == 0.125 and not exact0 and not exact1
    if strategy == "krylov":
        assert lam2 == lam1 and exact2  # the same step again, exact
        assert fac3 - fac2 == it3 - it2 >= 1  # one factorisation an iteration
        assert not exact3 and lam3 > lam2
        assert res.factorizations < reference.factorizations + (it3 - it2) + 2  # Krylov again after it
    else:
        assert lam2 == 0.125 / 4 and not exact2
