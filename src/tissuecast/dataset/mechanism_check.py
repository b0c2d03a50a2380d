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

:func:`check_thin_body` sees a thin shell before anything is solved, from the shape alone:
its sphericity ``pi^(1/3) (6 V)^(2/3) / A`` (1 for a ball; 0.8-0.95 for the phantom, a dome and
brain hemispheres; 0.47 for a 8 x 8 x 120 mm bar; 0.18 for a bent tube of 0.8 mm wall) is below
``THIN_SPHERICITY``. Held by pins alone, such a wall hinges about them and its solves stall
(a thin-walled aorta: pilots of over 1000 Newton iterations) while its linear answers may pass
the check above; a vessel is held by its ends and its surroundings (``configs/vessel.toml``).
With the compact pins of the paper's set-up the data set is refused before the store is made;
with pins the user chose (spread, or given ids) a warning says the same.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..errors import DatasetError

__all__ = ["linear_peak", "check_supports", "check_thin_body", "sphericity", "MECHANISM_RATIO", "THIN_SPHERICITY"]

log = logging.getLogger(__name__)

#: The supports are refused when the linear response at ``alpha0`` exceeds this multiple of
#: the target displacement (``alpha0`` aims at 1 % of it: a 100-fold excess).
MECHANISM_RATIO = 1.0
#: A body whose sphericity is below this is a thin shell (module notes).
THIN_SPHERICITY = 0.3


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


def sphericity(mesh) -> float:
    """``pi^(1/3) (6 V)^(2/3) / A`` of a tetrahedral mesh (V its volume, A its boundary's area):
    1 for a ball, small for a thin wall (about its thickness over its extent)."""
    return float(math.pi ** (1.0 / 3.0) * (6.0 * mesh.volume) ** (2.0 / 3.0) / mesh.surface_area)


def check_thin_body(scenario, markers_config) -> float:
    """Refuse (compact pins, the default) or warn about (pins the user chose) a thin shell held
    by pins alone (see the module notes); returns the sphericity.

    Args:
        scenario: the resolved :class:`~tissuecast.scenario.Scenario`.
        markers_config: the config's :class:`~tissuecast.config.MarkerConfig` (how the pins were chosen).

    Raises:
        DatasetError: a thin shell held by the compact pins alone.
    """
    psi = sphericity(scenario.mesh)
    if psi >= THIN_SPHERICITY or not scenario.can_swing or not len(scenario.pinned):
        return psi
    wall = 2.0 * scenario.mesh.volume / scenario.mesh.surface_area
    text = (f"the body is a thin shell (sphericity {psi:.2f}, below {THIN_SPHERICITY:g}: a wall about {wall:.2g} mm "
            "thick; a solid organ has 0.7-0.95) held by pins alone: pins cannot hold a thin wall, it swings and bends "
            "about them like a hinge and the solves stall. Hold it as a vessel is held, by its ends and its "
            "surroundings: configs/vessel.toml ([scenario] pins = false, [scenario.attached] the vertices of both "
            "open ends by rule \"tag\" or \"ids\", [scenario.springs] rule = \"surface\", [forces] loading = "
            "\"traction\", n_basis = 6, target_max_displacement = 3; docs/scaling.md)")
    if markers_config.fixed_rule == "compact" and not markers_config.fixed_ids:
        raise DatasetError(text)
    log.warning("%s", text)
    return psi
