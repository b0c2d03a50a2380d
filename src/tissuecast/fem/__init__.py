"""Nonlinear finite elements: compressible neo-Hookean solid on linear or quadratic tetrahedra.

Public API::

    problem = Problem(mesh, NeoHookean(0.021, 0.45), fixed=[...], order=2)
    problem = build_problem(mesh, NeoHookean(0.021, 0.45), fixed, order=1, springs=...)  # with springs, regions
    result = solve(problem, forces)            # forces (n, 3) N -> result.displacement (n, 3) mm
    solver = Solver(problem, cfg.solver)       # reusable: per-mesh work done once
    result = solver.solve(forces, initial_guess=None)

    # many solves of one problem (data sets): a reduced-order model of earlier solutions
    # predicts the answer, the full solver converges from there
    from tissuecast.fem.reduced import ReducedModel
    model = ReducedModel.fit(problem, snapshots)  # (s, n_nodes, 3) nodal_displacement of solves
    result = solver.solve(forces, initial_guess=model.predict(forces))

Units: mm, N, MPa. Vertex ids are 0-based.
"""

from .material import NeoHookean
from .problem import Problem, build_problem
from .result import SolveResult
from .solver import Solver, solve

__all__ = ["NeoHookean", "Problem", "Solver", "SolveResult", "build_problem", "solve"]
