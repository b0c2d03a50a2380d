"""Do the supports hold the body? A linear check before the force calibration.

Dead loads on a body held by a few pinned vertices close together (the compact rule) make it
swing about them until the loads' moment vanishes; a bulky body then strains moderately. A
thin wall (a vessel whose wall is one or two elements thick) or a slender body cannot carry
that moment near the pins: it bends there like a hinge, elements invert, and the nonlinear
solves of the calibration stall for minutes without converging.

:func:`check_supports` sees this before any nonlinear solve: it solves the *linear* problem
(stiffness at zero displacement, linear tetrahedra on the same vertices: one sparse
factorisation of ``3 n`` unknowns) for the first calibration pilots at the calibration's
first, deliberately small force ``alpha0`` (meant to move the body about 1 % of the target;
:func:`.calibrate.initial_alpha`). If that already moves the body beyond the target, the
supports leave a near-mechanism and the data set is refused with the options to use
(measured ratios on several anatomies: ``docs/solver.md``).
"""

from __future__ import annotations

import numpy as np

from ..errors import DatasetError

__all__ = ["linear_peak", "check_supports", "MECHANISM_RATIO"]

#: The supports are refused when the linear response at ``alpha0`` exceeds this multiple of
#: the target displacement (``alpha0`` aims at 1 % of it: a 100-fold excess).
MECHANISM_RATIO = 1.0


def linear_peak(problem, forces: list) -> float:
    """Largest vertex displacement (mm) of the linear-elastic answers to ``forces``.

    Args:
        problem: a :class:`~tissuecast.fem.Problem` (its stiffness at zero displacement is
            used; linear elements keep this cheap).
        forces: list of (n, 3) float nodal force fields on the vertices, N.

    Returns:
        The largest vertex displacement magnitude over all fields, mm (inf when the
        supports leave a rigid-body motion free).
    """
    from ..fem.assembly import Assembler
    from ..fem.linear import NotPositiveDefinite, available_backends, make_linear_solver

    asm = Assembler(problem.nodes, problem.connectivity, problem.order, problem.material, problem.free_mask)
    _, data, _ = asm.tangent(np.zeros((len(problem.nodes), 3)))
    lin = make_linear_solver(available_backends()[0], asm)
    try:
        lin.factorize(data)
    except NotPositiveDefinite:
        return float("inf")
    n = problem.n_vertices
    peak = 0.0
    for f in forces:
        b = np.zeros(asm.n_dofs)
        b[: 3 * n] = np.asarray(f, dtype=np.float64).ravel()
        u = np.zeros(asm.n_dofs)
        u[asm.free_dofs] = lin.solve(b[asm.free_dofs])
        peak = max(peak, float(np.linalg.norm(u.reshape(-1, 3)[:n], axis=1).max()))
    return peak


def check_supports(problem, forces: list, alpha0: float, target: float) -> float:
    """Refuse supports that leave a near-mechanism (see the module notes).

    Args:
        problem: the data set's problem on linear elements (``build_problem(..., order=1)``).
        forces: the first pilots' force fields at ``alpha0``, (n, 3) N each.
        alpha0: the calibration's first force magnitude, N.  target: target displacement, mm.

    Returns:
        The linear peak, mm.

    Raises:
        DatasetError: the linear peak exceeds ``MECHANISM_RATIO`` x ``target``.
    """
    peak = linear_peak(problem, forces)
    if not peak <= MECHANISM_RATIO * target:
        fixed = problem.constrained_nodes[0]
        raise DatasetError(
            f"the fixed vertices {fixed.tolist()} hold the body too loosely for dead loads: the "
            f"calibration's first, deliberately small force (alpha {alpha0:.3g} N, meant to move it about 1 % of the "
            f"{target:g} mm target) already moves it {peak:.3g} mm in linear elasticity, so the body swings and bends "
            "about its pins like a hinge (a thin wall or a slender body held at one spot) and the nonlinear solves "
            "would stall; spread the pins (markers.fixed_rule = \"spread\", or markers.fixed_ids far apart), or hold "
            "it by a surface region instead ([scenario.attached] or [scenario.springs], with scenario.pins = false)")
    return peak
