"""How much of a sample's displacement each of its loads makes.

A scenario sums its loads per sample: the surface force field (LBO tractions or nodal forces),
the change of gravity, the instrument's indentation. :func:`load_shares` solves sample seeds
with each load alone and with all of them (nonlinear FEM, the scenario's nominal parameters)
and reports each load's peak displacement alone and its share of the peak of all together,
so that a preset shows whether its "clinical" loading is what it claims to be (a gravity
change of real size is often a small share; a surface field calibrated to a peak can dominate
everything). Shares of peaks do not add up to one: loads interact and peak at different
vertices. Lengths in mm.
"""

from __future__ import annotations

import numpy as np

__all__ = ["load_shares", "format_load_shares", "LOADS"]

#: The loads, in the order reported: the surface force field, the gravity change, the instrument.
LOADS = ("surface field", "gravity change", "instrument")


def _alone(inputs) -> dict:
    """``{load: (surface loads (n_nodes, 3) N, solve keywords)}`` of each load the sample has, alone."""
    zero = np.zeros_like(inputs.surface)
    out = {}
    if np.any(inputs.forces):
        out["surface field"] = (inputs.surface, {})
    if inputs.body is not None:
        out["gravity change"] = (zero, {"body_loads": inputs.body})
    if len(inputs.prescribed_ids):
        out["instrument"] = (zero, {"prescribed": (inputs.prescribed_ids, inputs.prescribed_values)})
    return out


def load_shares(scenario, config, seeds, alpha: float) -> dict:
    """Peak displacement of each load alone and of all together over samples ``seeds``.

    Args:
        scenario: the :class:`~.scenario.Scenario`.
        config: the configuration (material, solver).
        seeds: sample seeds (``samples/seed`` of a data set).
        alpha: the surface field's magnitude, N.

    Returns:
        ``{load: {"peak_median": mm, "share_median": 0..1, "samples": k}}`` for each load of
        :data:`LOADS` the samples have, and ``"all"`` (share 1); a solve that does not
        converge leaves its sample out of that load's figures.
    """
    from ..errors import ConvergenceError
    from ..fem import Solver

    solver = Solver(scenario.problem(), config.solver)
    peaks: dict[str, list] = {}
    for seed in seeds:
        inputs = scenario.sample(int(seed), float(alpha), nominal=True)
        cases = {"all": (inputs.surface, inputs.solve_keywords()), **_alone(inputs)}
        result = {}
        for name, (surface, keywords) in cases.items():
            try:
                u = solver.solve(surface, **keywords).displacement
            except ConvergenceError:
                continue
            result[name] = float(np.linalg.norm(u, axis=1).max())
        if "all" not in result:
            continue
        for name, peak in result.items():
            peaks.setdefault(name, []).append((peak, peak / max(result["all"], 1e-300)))
    return {name: {"peak_median": float(np.median([p for p, _ in v])),
                   "share_median": float(np.median([s for _, s in v])), "samples": len(v)}
            for name, v in peaks.items()}


def format_load_shares(shares: dict) -> list[str]:
    """Lines for people: each load's median peak alone and its share of all loads' peak."""
    lines = []
    for name in (*LOADS, "all"):
        if name in shares:
            s = shares[name]
            share = "" if name == "all" else f", {100 * s['share_median']:.0f} % of all loads' peak"
            lines.append(f"{name}: peak {s['peak_median']:.3g} mm (median of {s['samples']} samples){share}")
    return lines
