"""The simulator's sensitivities at stored samples: how a sample's whole field moves when its
LBO load weights, or its drawn material and support parameters, move.

At a solved sample (displacement u of the mesh's nodes, loads f(w) = sum_k w_k f_k linear in
the 3 n_b LBO weights w), equilibrium r(u) = f(w) gives

    du/dw_k = K(u)^-1 f_k,

with K the tangent stiffness at u, the held dofs (supports, the instrument's prescribed
patch, an attached margin's vertices) eliminated; along a parameter p (E, the springs,
Poisson's ratio) the load is minus the internal forces' derivative in p at u. One
factorisation per sample, by the solver's own direct backend on its fixed pattern (the held
dofs' couplings zeroed, as the Newton solver holds them), and a triangular solve per
direction: a small share of the sample's own Newton solve. The surrogate trains on these
directions beside the fields (``surrogate.sensitivity_weight``,
:mod:`tissuecast.surrogate.mlp`): each sample then says not only where the markers and the
field are but how they move together along every direction of the simulated family.

Units: mm of displacement per prior standard deviation of the weight (drawn U(-1, 1),
standard deviation :data:`WEIGHT_SD`) or of the parameter (on its log scale for the factors).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse.linalg import splu

from ..errors import ConfigError, ConvergenceError
from ..fem.linear import NotPositiveDefinite
from ..forces.fields import lbo_field
from ..scenario.parameters import LOG_SCALE, law_sd
from ..scenario.sample_inputs import ScenarioDraw

__all__ = ["WEIGHT_SD", "CONTINUOUS_PARAMETERS", "PARAMETER_STEP", "Sensitivities", "parameter_directions",
           "equilibrium_response", "unit_loads", "dataset_sensitivities"]

log = logging.getLogger(__name__)

#: Standard deviation of an LBO weight (drawn U(-1, 1)).
WEIGHT_SD = 3.0 ** -0.5
#: The continuous uncertain parameters a field can be differentiated in, and whether on a log
#: scale (the factors) or as they are (Poisson's ratio).
CONTINUOUS_PARAMETERS = tuple((name, name in LOG_SCALE) for name in ("youngs_modulus", "spring_normal",
                                                                    "spring_tangential", "poisson_ratio"))
#: Finite-difference step of the internal forces in a parameter, in prior standard deviations.
PARAMETER_STEP = 1e-4
#: A progress line at most this often, s.
LOG_SECONDS = 20.0


@dataclass(frozen=True, eq=False)
class Sensitivities:
    """Some samples' field sensitivities.

    Attributes:
        indices: (M,) int64 sample indices, 0-based.
        values: (M, k, n, 3) float32 mm per direction (NaN: the sample has none).
    """

    indices: np.ndarray
    values: np.ndarray

    def rows(self, idx) -> np.ndarray:
        """(len(idx), k, n, 3) float32: the sensitivities of samples ``idx`` (NaN for one not held)."""
        idx = np.asarray(idx, dtype=np.int64)
        pos = np.searchsorted(self.indices, idx)
        pos = np.minimum(pos, len(self.indices) - 1)
        found = self.indices[pos] == idx if len(self.indices) else np.zeros(len(idx), dtype=bool)
        out = np.full((len(idx),) + self.values.shape[1:], np.nan, dtype=np.float32)
        out[found] = self.values[pos[found]]
        return out


def unit_loads(scenario, alpha: float) -> np.ndarray:
    """(3 n_b, n_nodes, 3) N: the surface loads of each unit LBO weight at force magnitude
    ``alpha`` (N) (the same for every sample: a draw changes the body loads, not these)."""
    surface = scenario.surface_forces
    nb, n = surface.basis.n_vectors, scenario.mesh.n_vertices
    out = []
    for k in range(3 * nb):
        w = np.zeros((nb, 3))
        w.flat[k] = 1.0
        out.append(scenario.sample_loads(ScenarioDraw(), lbo_field(surface.basis, w, alpha, n))[0])
    return np.array(out)


def equilibrium_response(solver, inputs, u: np.ndarray, forces: np.ndarray, tangent=None) -> np.ndarray:
    """(3 n_nodes, k) mm: the displacement's first-order response to k load changes at the
    equilibrium ``u``.

    Args:
        solver: the sample's solver (its parameters applied: ``with_parameters``).
        inputs: the sample's :class:`~tissuecast.scenario.SampleInputs` (its held dofs).
        u: (n_nodes, 3) mm, the equilibrium.
        forces: (k, 3 n_nodes) N, the load changes (rows at held dofs are ignored).
        tangent: ``solver.assembler.tangent(u)`` when the caller has it already (e.g. for the
            internal forces), else None.

    Raises:
        ConvergenceError: ``u`` inverts an element (no tangent there).
    """
    asm = solver.assembler
    _, data, jmin = asm.tangent(u) if tangent is None else tangent
    if not jmin > 0.0:
        raise ConvergenceError("the state inverts an element: no tangent stiffness there")
    free = np.asarray(solver.free_dofs)
    nodes, _ = solver.problem.solve_constraints((inputs.prescribed_ids, inputs.prescribed_values))
    held = asm.free_position[(3 * np.asarray(nodes, dtype=np.int64)[:, None] + np.arange(3)).ravel()]
    if len(held):
        data = data.copy()  # the caller's tangent stays as it was
        data[asm.coupling_entries(held)] = 0.0  # held dofs decoupled, their diagonal kept
    rhs = np.ascontiguousarray(np.asarray(forces, dtype=np.float64)[:, free].T)
    rhs[held] = 0.0
    du = np.zeros((u.size, forces.shape[0]))
    du[free] = _tangent_solve(solver, data, rhs)
    return du


def _tangent_solve(solver, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(n_free, k): K^-1 rhs for the assembled tangent ``data`` on the solver's pattern, by the
    solver's own direct backend (its symbolic analysis reused; CHOLMOD where installed); SciPy's
    LU when the backend is not a factorisation or the tangent is not positive definite."""
    factor = solver.borrow_factor()
    try:
        if factor.exact:
            try:
                factor.factorize(data)
            except NotPositiveDefinite:
                pass
            else:
                return np.asarray(factor.solve(rhs)).reshape(rhs.shape)
    finally:
        solver.give_back_factor(factor)
    return splu(solver.assembler.matrix(data).tocsc()).solve(rhs)


def parameter_directions(scenario) -> list[tuple[str, bool, float, float]]:
    """``(name, log, centre, sd)`` of each continuous parameter the scenario draws (of
    :data:`CONTINUOUS_PARAMETERS`): its prior mean and standard deviation on its scale (log for
    the factors), from the config's range and law (uniform, or arcsine where
    ``scenario.uncertain.arcsine`` names it)."""
    c = scenario.config.uncertain
    if scenario.uncertain is None:
        return []
    out = []
    for name, on_log in CONTINUOUS_PARAMETERS:
        bounds = getattr(c, name)
        if bounds:
            lo, hi = (float(v) for v in bounds)
            a, b = (math.log(lo), math.log(hi)) if on_log else (lo, hi)
            out.append((name, on_log, 0.5 * (a + b), law_sd(b - a, name in c.arcsine)))
    return out


def dataset_sensitivities(dataset, indices) -> Sensitivities:
    """The field's derivatives at the stored LBO samples ``indices`` (0-based, ascending after
    unique), per prior standard deviation: along each of the 3 n_b LBO weights, then along
    each continuous parameter the scenario draws (:func:`parameter_directions`, the loads
    held: the internal forces' finite difference). Values (M, 3 n_b + n_p, n, 3) float32 mm;
    NaN for a sample that has none (a test-2 sample's concentrated loads, a failed sample, a
    state without a tangent) and for a parameter direction of a sample drawn at the nominal
    parameters.

    Args:
        dataset: a :class:`~tissuecast.dataset.Dataset` whose solver's nodes are its vertices
            (linear elements: the store keeps only the vertices' displacements).
        indices: (N,) sample indices.

    Raises:
        ConfigError: the data set's elements have nodes the store does not keep.
    """
    from .worker import SampleContext

    idx = np.unique(np.asarray(indices, dtype=np.int64))
    ctx = SampleContext(dataset.recipe())
    sc, base = ctx.scenario, ctx.solver(0)
    n = dataset.n_vertices
    n_nodes = len(base.problem.nodes)
    if n_nodes != n:
        raise ConfigError(f"sensitivities need the solver's nodes to be the store's {n} vertices (linear elements); "
                          f"this data set's elements have {n_nodes} nodes: set "
                          "surrogate.sensitivity_weight = 0 for it")
    nb = sc.surface_forces.basis.n_vectors
    directions = parameter_directions(sc)
    out = np.full((len(idx), 3 * nb + len(directions), n, 3), np.nan, dtype=np.float32)
    alpha, beta = np.asarray(dataset.alpha, dtype=np.float64), np.asarray(dataset.beta, dtype=np.float64)
    done = np.zeros(dataset.n_samples, dtype=bool)
    done[dataset.select(None, status="done")] = True
    params = dataset.parameters
    units: dict[float, np.ndarray] = {}  # per force magnitude
    t0, failed = time.perf_counter(), 0
    last = t0
    log.info("sensitivities of %d samples along %d directions each (one tangent factorisation a sample)", len(idx),
             out.shape[1])
    for k, s in enumerate(idx):
        now = time.perf_counter()
        if k and now - last > LOG_SECONDS:
            last = now
            log.info("%d of %d samples done, ETA %.0f s", k, len(idx), (now - t0) / k * (len(idx) - k))
        if not (done[s] and np.isnan(beta[s]) and np.isfinite(alpha[s])):
            continue
        seed, a = int(dataset.seed[s]), float(alpha[s])
        nominal = not params or all(np.isnan(np.asarray(v, dtype=np.float64)[s]) for v in params.values())
        known = sc.sample(seed, a, nominal=True)
        drawn = None if nominal else sc.draw_for(seed).parameters
        inputs = known if drawn is None else sc.with_parameters(known, drawn)
        solver = base.with_parameters(*inputs.solver_parameters)
        u = np.asarray(dataset.displacements[s], dtype=np.float64)
        if a not in units:
            units[a] = unit_loads(sc, a).reshape(3 * nb, -1)
        forces = [units[a]]
        usable = [True] * (3 * nb)
        tangent = None
        if directions:
            if drawn is not None:
                tangent = solver.assembler.tangent(u)  # its internal forces too
            for name, on_log, _, sd in directions:
                v = None if drawn is None else float(getattr(drawn, name))
                if v is None or not np.isfinite(v):
                    forces.append(np.zeros((1, u.size)))
                    usable.append(False)
                    continue
                h = PARAMETER_STEP * sd
                moved = sc.with_parameters(known, dataclasses.replace(drawn, **{name: v * math.exp(h) if on_log else v + h}))
                f2 = base.with_parameters(*moved.solver_parameters).assembler.internal_force(u)[0]
                forces.append((-(f2 - tangent[0]) / h)[None])
                usable.append(True)
        scale = np.array([WEIGHT_SD] * (3 * nb) + [sd for _, _, _, sd in directions])
        try:
            du = equilibrium_response(solver, inputs, u, np.vstack(forces), tangent)
        except ConvergenceError:
            failed += 1
            continue
        values = (scale[:, None] * du.T).reshape(-1, n, 3)
        values[~np.array(usable)] = np.nan
        out[k] = values
    log.info("sensitivities of %d samples (%d without a tangent) in %.1f s", len(idx), failed, time.perf_counter() - t0)
    return Sensitivities(idx, out)
