"""Force-magnitude calibration: choose alpha so the data set's displacements reach the target.

Rule (documented in the store's ``calibration`` attribute):

* Pilot samples: the first ``dataset.calibration_samples`` LBO samples (their weights W come
  from their own seeds, so the pilots are fixed by the configuration).
* Statistic: ``q(alpha)`` = the ``dataset.calibration_quantile`` quantile (default 0.9, linear
  interpolation) of the pilots' per-sample maximum vertex displacement, solved with the full
  nonlinear FEM at force magnitude alpha. A pilot that fails to converge counts as +inf.
* alpha solves ``q(alpha) = forces.target_max_displacement`` to a relative tolerance of
  ``RTOL`` (5 %: the pilots' quantile is itself no closer to the whole data set's, as
  measured in ``docs/scaling.md``): start from a deliberately small dimensional estimate
  (about 1 % of the target: a nearly linear, cheap solve); extrapolate linearly to half the
  target from far below it (the response of a body held by a few pinned vertices softens
  strongly), straight
  to the target from within ``FAR_BELOW`` of it or from above; then iterate
  ``alpha <- alpha (target / q)^(1 / s)`` where the response exponent ``s`` comes from this
  round and the nearest (in log alpha) of the bracket's previous end on its side and its end
  on the other side (secant in log-log, clipped to [0.5, 3]: the local exponent where the
  response bends, as a thin wall's does near its target). Rounds that overshoot (q above
  the target, or failures) bound alpha from above; the next alpha never leaves the bracket
  (geometric bisection when it would); after a failure with no lower bound, alpha / 4.
  If pilots fail before the target is reached, the bracket closes (within ``RTOL``) on the
  largest alpha at which the quantile is still finite: the record says
  ``limited_by_failures`` and the data set stays below the target rather than failing.
* Each pilot is the whole sample (:meth:`tissuecast.scenario.Scenario.sample`: its LBO field
  at alpha and, where the scenario has them, its gravity change and indentation), so the LBO
  magnitude is calibrated with the other loads present. The first trial alpha is the
  dimensional estimate above only where the body hangs on its pins under the LBO nodal forces
  alone (:attr:`~tissuecast.scenario.Scenario.hangs_on_pins`, the paper's set-up); otherwise
  (other supports, other loads, tractions, material regions) it comes from the linear
  response (:func:`linear_alpha`): the pilots' LBO fields alone, solved with the stiffness at
  zero displacement, aimed at ``FIRST_AIM`` of the target. (The dimensional estimate assumes
  a body hanging on pins, and with the other loads present a first round at 1 % of the target
  would measure only them.) Without LBO forces nothing is calibrated (alpha = 0).
* With uncertain parameters (``[scenario.uncertain]``) the pilots are solved at the nominal
  parameters: the loads are as large whatever the tissue's stiffness, so alpha is set for the
  nominal tissue (the record says ``parameters: nominal``), and the samples then deform more or
  less with their drawn parameters. Such pilots are not the samples (those draw their own
  parameters), so they are solved again with the others.
* Confidence: the record also gives the interval of the order statistics of the last
  round's pilot maxima that holds the quantile of the whole data set's maxima (at that alpha)
  with probability at least ``INTERVAL_CONFIDENCE`` (distribution-free: the number of pilots
  below the true quantile is binomial; ``quantile_interval``, None where the pilots are too
  few to bound that side), so what the number of pilots buys is stated.
* If ``dataset.alpha`` > 0 in the config, it is used as is and no pilots are solved.
* From the second round on, each pilot's solve starts from its own solution of the previous
  round (see :func:`calibrate_pilots`); the answers are the same within the solver
  tolerances, and the rounds are deterministic, so a repeated calibration gives the same
  record bit for bit. A round hands out the previous round's slowest pilots first (a round
  lasts at least as long as its slowest pilot; each pilot's solve is its own, so the order
  changes no result unless a time budget, set as a task is handed out, stops a solve).
  Where the body hangs on its pins, the first round's pilots (nearly linear at the small
  first alpha) start from a zero guess, the solver's warm path (one increment with the shared
  reference preconditioner; :func:`warm_zero`). Where the LBO field is the only load and the
  first alpha comes from the linear response (e.g. a vessel held at its ends), each
  first-round pilot starts from its own linear answer at that alpha (``samples/predicted``
  LINEAR_ANSWER), which the first alpha's solves computed already.

So a softer material, a larger tumour or a different mesh resolution all land near the
target: the rule measures the mesh at hand, not a fixed force.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..config import Config, SolverConfig
from ..errors import DatasetError
from .codes import InitialGuess, SampleStatus
from .mechanism_check import MECHANISM_RATIO, check_supports
from .phase_stats import eta_text, work_seconds
from .quantiles import interval_text, quantile_interval
from .quantiles import sample_quantile as _quantile
from .worker import Recipe, SampleContext, Task

if TYPE_CHECKING:
    from ..scenario import Scenario

__all__ = ["calibrate_pilots", "calibrate_alpha", "initial_alpha", "linear_alpha", "warm_zero", "quantile_interval",
           "calibration_outlook", "RTOL", "MAX_ROUNDS", "FIRST_AIM", "FAR_BELOW", "SUPPORT_PILOTS"]

log = logging.getLogger(__name__)

RTOL = 0.05
MAX_ROUNDS = 10
FIRST_AIM = 0.5  # a first extrapolation from far below the target aims at this share of it ...
FAR_BELOW = 0.25  # ... "far below": a quantile under this share of the target
#: Confidence of the stated interval of the quantile (module notes).
INTERVAL_CONFIDENCE = 0.8
#: The response exponent ``s`` of q ~ alpha^s is clipped to this range (a body held by a few
#: pins softens, but not without bound).
EXPONENT_MIN, EXPONENT_MAX = 0.5, 3.0
#: Significant digits of the first alpha of a scenario's calibration (:func:`linear_alpha`).
LINEAR_ALPHA_DIGITS = 6
FAILURE_DIVISOR = 4.0  # after a round with failures and no lower bound, alpha is divided by this
#: Pilots whose linear answers check the pins before the calibration (:mod:`.mechanism_check`).
SUPPORT_PILOTS = 4
#: The calibration's ETA counts on this many rounds (most calibrations take 2-3) ...
EXPECTED_ROUNDS = 3
#: ... and on later rounds' pilots taking this share of the first round's (they start from
#: their previous round's solutions: 0.5-0.75 measured on the phantom and a brain mesh).
LATER_ROUND_SHARE = 0.6


def calibrate_pilots(writer, ex, cfg: Config, recipe: Recipe) -> tuple[dict, list]:
    """Calibrate alpha on the data set's pilot samples (module notes).

    Args:
        writer: the :class:`~.store.StoreWriter` (the pilots' seeds and betas).
        ex: a :class:`~.supervise.Supervisor` of an executor holding ``recipe``.
        cfg: the data set's configuration.  recipe: its :class:`~.worker.Recipe`.

    Returns:
        ``(record, results)``: the calibration record (``dataset.alpha`` when given; alpha 0
        without LBO forces) and the last round's :class:`~.worker.SampleResult` of the pilots
        solved at the calibrated alpha (the samples themselves).

    Raises:
        DatasetError: no LBO sample to calibrate on, pins that leave a near-mechanism, or every
            pilot failed at every trial alpha.
    """
    ds = cfg.dataset
    if ds.alpha > 0:
        return {"rule": "given (dataset.alpha)", "alpha": ds.alpha, "converged": True, "rounds": []}, []
    if not cfg.scenario.lbo_forces:
        return {"rule": "none: the scenario has no LBO forces (scenario.lbo_forces = false)", "alpha": 0.0,
                "converged": True, "rounds": []}, []
    seeds, betas = writer.read("samples/seed"), writer.read("samples/beta")
    pilots = list(range(min(ds.calibration_samples, int(writer.root.attrs["n_lbo"]))))
    if not pilots:
        raise DatasetError("force calibration needs at least one LBO sample; set dataset.n_samples >= 1 or dataset.alpha")
    last: list = []
    rounds: list = []
    scenario = recipe.scenario()
    zero = warm_zero(cfg.solver, scenario)
    nominal = scenario.uncertain is not None  # the loads' size is set at the nominal tissue

    def pilot_max(alpha: float) -> np.ndarray:
        # each pilot starts from its solution of the previous round (if it converged)
        prev = {r.index: r.nodal for r in last if r.status == SampleStatus.DONE and r.nodal is not None}
        # the slowest pilots of the previous round first: a round lasts at least as long as its slowest
        seconds = {r.index: r.seconds for r in last}
        order = sorted(pilots, key=lambda i: -seconds.get(i, 0.0))
        phase = f"calibration round {len(rounds) + 1} (at most {MAX_ROUNDS}), alpha {alpha:.4g} N"
        rounds.append(alpha)

        def start(i: int) -> tuple[np.ndarray | None, int]:
            """Pilot i's guess and its code this round (no guess: from zero, as configured)."""
            if i in prev:
                return prev[i], int(InitialGuess.PREVIOUS_ROUND)
            if linear is not None and len(rounds) == 1:
                return alpha * linear[i], int(InitialGuess.LINEAR_ANSWER)
            if zero is not None:
                return zero, int(InitialGuess.ZERO)
            return None, int(InitialGuess.PREVIOUS_ROUND)  # the code of a task without a guess is unused

        tasks = [Task(i, int(seeds[i]), float(betas[i]), alpha, *start(i), nominal=nominal) for i in order]
        outlook = calibration_outlook(len(rounds), len(pilots), ex.workers)
        last[:] = sorted(ex.run(tasks, phase, unit="pilot", outlook=outlook), key=lambda r: r.index)
        return np.array([r.max_displacement for r in last])

    alpha0, answers = _first_alpha(cfg, recipe, scenario, [(int(seeds[i]), float(betas[i])) for i in pilots])
    linear = None if answers is None else dict(zip(pilots, answers))
    record = calibrate_alpha(pilot_max, alpha0, cfg.forces.target_max_displacement, quantile=ds.calibration_quantile)
    record["pilots"] = pilots
    if nominal:  # the pilots' solves lack their samples' drawn parameters: solved again as samples
        record["parameters"] = "nominal (the samples draw [scenario.uncertain])"
        return record, []
    return record, [r for r in last if r.alpha == record["alpha"]]


def calibration_outlook(round_: int, pilots: int, workers: int):
    """The progress lines' outlook of calibration round ``round_`` (1-based): the calibration's
    ETA as a whole, from the round's ETA and the median worker seconds of its pilots so far,
    taking ``EXPECTED_ROUNDS`` rounds whose later pilots take ``LATER_ROUND_SHARE`` of the
    time (they start from their previous round's solutions)."""

    def outlook(eta: float, median: float | None) -> str:
        later = max(EXPECTED_ROUNDS - round_, 0)
        if median is None or not later:
            return f"; calibration ETA {eta_text(eta)}" + ("" if later else " (if this round is the last)")
        rest = later * work_seconds(pilots, LATER_ROUND_SHARE * median, workers)
        return f"; calibration ETA {eta_text(eta + rest)} (if it takes {EXPECTED_ROUNDS} rounds)"

    return outlook


def _first_alpha(cfg: Config, recipe: Recipe, scenario: "Scenario", pilots: list) -> tuple[float, list | None]:
    """The calibration's first trial alpha (N): the dimensional estimate where the body hangs
    on its pins (the pins checked for a near-mechanism first), else the linear response's;
    and the pilots' linear answers at unit alpha ((n_nodes, 3) mm each) where the LBO field is
    a sample's only load (else None); ``pilots``: their ``(seed, beta)``."""
    target = cfg.forces.target_max_displacement
    if not scenario.hangs_on_pins:
        peaks, answers = linear_answers(recipe, pilots)
        alpha0 = linear_alpha_of(peaks, target)
        return alpha0, (None if scenario.draws_per_sample else answers)
    alpha0 = initial_alpha(scenario.surface_forces.basis, scenario.mesh, scenario.supported,
                           cfg.material.youngs_modulus, target)
    _check_pins(cfg, scenario, pilots[:SUPPORT_PILOTS], alpha0)
    return alpha0, None


def _check_pins(cfg: Config, scenario: "Scenario", pilots: list, alpha0: float) -> None:
    """Refuse pins that leave a near-mechanism (:func:`.mechanism_check.check_supports`), from
    the linear answers of the ``pilots`` ((seed, beta) pairs) at ``alpha0`` on linear elements."""
    from ..fem import build_problem

    forces = [scenario.surface_forces.field(seed, alpha0, beta)[0] for seed, beta in pilots]
    peak = check_supports(build_problem(scenario.mesh, scenario.material, scenario.supported, order=1), forces, alpha0,
                          cfg.forces.target_max_displacement)
    log.info("supports: the first pilots' linear answers at alpha %.3g N peak at %.3g mm (refused above %.3g mm)",
             alpha0, peak, MECHANISM_RATIO * cfg.forces.target_max_displacement)


def warm_zero(solver: SolverConfig, scenario: "Scenario") -> np.ndarray | None:
    """Zero displacements (n_nodes, 3) as the first guess of pilots that hang on their pins
    (:attr:`~tissuecast.scenario.Scenario.hangs_on_pins`: nearly linear at the small first
    alpha), where a guess changes the solver's path (``krylov`` with
    ``reference_preconditioner``: one full increment preconditioned by the shared stiffness at
    zero, no factorisation of its own); else None. A pilot that fails from it goes on with the
    usual attempts from zero (:func:`~.worker.solve_task`); timings in ``docs/scaling.md``.
    """
    if not scenario.hangs_on_pins or solver.strategy != "krylov" or not solver.reference_preconditioner:
        return None
    return np.zeros((scenario.n_nodes, 3))


def initial_alpha(basis, mesh, fixed, youngs_modulus: float, target: float, fraction: float = 0.01) -> float:
    """Dimensional first guess of alpha (N) for about ``fraction`` x ``target`` mm.

    The pinned vertices carry the net force of the field: a net force F on pins in
    elements of size h moves the body by about F / (E h). The RMS net force of a random
    unit-alpha field is ``||B^T 1||`` (W ~ U(-1, 1)), h the mean length of the edges at the
    fixed vertices. The guess is deliberately small (a nearly linear, cheap first round).
    """
    net = float(np.linalg.norm(np.asarray(basis.vectors).sum(axis=0)))  # N per unit alpha
    edges = mesh.edges
    at_pins = np.isin(edges, np.asarray(fixed)).any(axis=1)
    lengths = np.linalg.norm(mesh.points[edges[at_pins, 0]] - mesh.points[edges[at_pins, 1]], axis=1)
    h = float(lengths.mean()) if len(lengths) else float(np.max(mesh.extent)) / 10.0
    if net <= 0.0:  # a basis without net force (should not happen: the constant mode has one)
        net = float(np.linalg.norm(basis.vectors)) / np.sqrt(basis.vectors.shape[0])
    return fraction * target * youngs_modulus * h / net


def linear_alpha(recipe: Recipe, pilots: list, target: float, quantile: float = 0.9, aim: float = FIRST_AIM) -> float:
    """First trial alpha (N) of a scenario's calibration, from the linear response.

    The pilots' LBO fields at unit alpha, applied as the scenario applies them
    (``forces.loading``) but without its other loads, are solved with the stiffness at zero
    displacement (supports, springs, material regions); alpha is set so that the ``quantile``
    of their peak vertex displacements is ``aim * target``, rounded to
    :data:`LINEAR_ALPHA_DIGITS` significant digits: these solves run in the parent process, on
    one BLAS thread as the workers solve (the last bits of a multi-threaded factorisation
    depend on the number of threads), and rounded, the first alpha (and so every later bit of
    the data set) is the same in any process.

    Args:
        recipe: the data set's :class:`~.worker.Recipe`.
        pilots: the pilots' ``(seed, beta)``.
        target: mm.

    Raises:
        DatasetError: the stiffness at zero displacement is singular (supports that leave a
            rigid-body motion free) or the fields do not move the body.
    """
    return linear_alpha_of(linear_answers(recipe, pilots)[0], target, quantile, aim)


def linear_alpha_of(peaks: np.ndarray, target: float, quantile: float = 0.9, aim: float = FIRST_AIM) -> float:
    """alpha (N) putting the ``quantile`` of the linear peaks at unit alpha ``peaks`` (P,) mm/N
    at ``aim * target``, rounded as :func:`linear_alpha` says."""
    q = _quantile(np.array(peaks), quantile)
    if not q > 0.0:
        raise DatasetError("the pilots' LBO fields do not move the body (zero linear response); check the scenario")
    return float(f"{aim * target / q:.{LINEAR_ALPHA_DIGITS}g}")


def linear_answers(recipe: Recipe, pilots: list) -> tuple[np.ndarray, list]:
    """The linear answers of the pilots' LBO fields at unit alpha (:func:`linear_alpha`):
    ``(peaks (P,) mm, answers [(n_nodes, 3) mm at every element node, float64 rounded to
    float32 precision])``; ``pilots``: their ``(seed, beta)``.

    Raises:
        DatasetError: the stiffness at zero displacement is singular.
    """
    from ..fem.linear import one_blas_thread
    from ..scenario import ScenarioDraw

    with one_blas_thread():  # as the workers solve: the same bits in any process of a machine
        ctx = SampleContext(recipe)
        solver = ctx.solver(0)
        reference = solver.reference_factor()
        if reference is None:
            raise DatasetError("the stiffness at zero displacement is not positive definite: the supports leave the "
                               "body free to move; check the scenario's supports")
        free = solver.free_dofs
        n = ctx.mesh.n_vertices
        peaks, answers = [], []
        for seed, beta in pilots:
            f, _ = ctx.scenario.surface_forces.field(seed, 1.0, beta)
            loads = ctx.scenario.loads(ScenarioDraw(), f)
            u = np.zeros(3 * len(loads))
            u[free] = reference.solve(loads.ravel()[free])
            peaks.append(float(np.linalg.norm(u.reshape(-1, 3)[:n], axis=1).max()))
            # rounded to float32 as alpha is to LINEAR_ALPHA_DIGITS: a last safeguard of the bits
            answers.append(u.reshape(-1, 3).astype(np.float32).astype(np.float64))
    return np.array(peaks), answers


def calibrate_alpha(
    pilot_max: Callable[[float], np.ndarray],
    alpha0: float,
    target: float,
    quantile: float = 0.9,
    rtol: float = RTOL,
    max_rounds: int = MAX_ROUNDS,
) -> dict:
    """Find alpha with ``quantile(pilot_max(alpha)) = target`` (see the module notes).

    Args:
        pilot_max: alpha (N) -> (P,) per-pilot maximum displacement (mm; inf = failed).
        alpha0: first trial alpha (N), best below the answer.
        target: target displacement, mm.
        quantile: which quantile of the pilot maxima must reach ``target``.
        rtol: accepted relative deviation of that quantile from ``target``.
        max_rounds: most pilot rounds; the closest round is kept if none is within ``rtol``.

    Returns:
        JSON-able dict: ``alpha``, ``quantile_value``, ``converged``, ``rounds`` (list of
        {alpha, quantile_value, pilot_max}), and the rule's parameters.

    Raises:
        DatasetError: every pilot failed at every trial alpha (the solver cannot run this set-up).
    """
    rounds: list[dict] = []
    lo = hi = None  # (alpha, q) bracket: q(lo) < target < q(hi)
    alpha = float(alpha0)
    best = None
    for _ in range(max_rounds):
        m = np.asarray(pilot_max(alpha), dtype=np.float64)
        q = _quantile(m, quantile)
        rounds.append({"alpha": alpha, "quantile_value": q if math.isfinite(q) else None,
                       "pilot_max": [float(x) if math.isfinite(x) else None for x in m]})
        log.info("calibration round %d: alpha = %.6g N -> q%.0f of pilot max displacement = %.3f mm (target %.3f)",
                 len(rounds), alpha, 100 * quantile, q, target)
        if math.isfinite(q) and (best is None or abs(math.log(q / target)) < abs(math.log(best[1] / target))):
            best = (alpha, q)
        if math.isfinite(q) and abs(q / target - 1.0) <= rtol:
            break
        lo, hi, ref = _bracket(lo, hi, alpha, q, target)
        new = _next_alpha(alpha, q, target, lo, ref)
        if lo is not None and hi is not None:
            if hi[0] <= lo[0] * (1.0 + rtol):
                break  # the bracket is closed: the target lies beyond what the pilots converge at
            if not lo[0] < new < hi[0]:
                new = math.sqrt(lo[0] * hi[0])
        alpha = new
    return _record(rounds, best, target, quantile, rtol)


def _bracket(lo, hi, alpha: float, q: float, target: float):
    """The bracket ``(lo, hi)`` updated with the round ``(alpha, q)``, and the earlier round
    ``ref`` the response exponent is measured against (None: none usable): of the bracket's
    previous end on the same side and its end on the other side, the one nearest ``alpha``
    (in log alpha), so that the exponent is the local one where the response bends."""
    if math.isfinite(q) and q < target:
        prev_lo, lo = lo, (alpha, q)
        candidates = [prev_lo, hi if hi is not None and math.isfinite(hi[1]) else None]
    else:
        prev_hi, hi = hi, (alpha, q)
        usable = prev_hi is not None and math.isfinite(q) and math.isfinite(prev_hi[1])
        candidates = [lo, prev_hi if usable else None]
    candidates = [c for c in candidates if c is not None and c[0] != alpha and 0 < c[1] != q]
    ref = min(candidates, key=lambda c: abs(math.log(c[0] / alpha)), default=None)
    return lo, hi, ref


def _next_alpha(alpha: float, q: float, target: float, lo, ref) -> float:
    """The next trial alpha: after a failure, the geometric mean with the lower bound (or a
    quarter); with two rounds, the power law through them; from one round, linear
    extrapolation (from below ``FAR_BELOW`` of the target only to ``FIRST_AIM`` of it)."""
    if not math.isfinite(q):
        return math.sqrt(lo[0] * alpha) if lo is not None else alpha / FAILURE_DIVISOR
    if ref is not None and ref[0] != alpha and math.isfinite(ref[1]) and 0 < ref[1] != q:
        s = min(max(math.log(q / ref[1]) / math.log(alpha / ref[0]), EXPONENT_MIN), EXPONENT_MAX)
        return alpha * (target / q) ** (1.0 / s)
    aim = FIRST_AIM * target if q < FAR_BELOW * target else target
    return alpha * aim / q


def _record(rounds: list, best, target: float, quantile: float, rtol: float) -> dict:
    """The calibration record (see :func:`calibrate_alpha`) of the closest round ``best``."""
    if best is None:
        raise DatasetError(
            f"force calibration failed: every pilot sample failed to converge at every trial alpha "
            f"(last {rounds[-1]['alpha']:.3g} N); check the material, fixed vertices and solver settings")
    converged = abs(best[1] / target - 1.0) <= rtol
    limited = bool(not converged and any(r["quantile_value"] is None for r in rounds))
    chosen = next(r for r in rounds if r["alpha"] == best[0])
    maxima = [math.inf if m is None else m for m in chosen["pilot_max"]]
    interval = quantile_interval(maxima, quantile, INTERVAL_CONFIDENCE)
    log.info("q%.0f of the %d pilots' maxima at alpha %.6g N: %.3f mm; with %.0f %% confidence the whole data set's "
             "q%.0f lies in %s", 100 * quantile, len(maxima), best[0], best[1], 100 * INTERVAL_CONFIDENCE,
             100 * quantile, interval_text(interval))
    if not converged:
        log.warning("force calibration did not reach %.1f mm (%s); using alpha = %.6g N (q = %.2f mm)", target,
                    "pilot samples fail to converge at larger forces" if limited else f"{len(rounds)} rounds",
                    best[0], best[1])
    return {"rule": f"q{quantile:g} of pilot per-sample max displacement = target (failures count as +inf)",
            "alpha": best[0], "quantile": quantile, "target": target, "quantile_value": best[1], "rtol": rtol,
            "converged": bool(converged), "limited_by_failures": limited, "rounds": rounds,
            "quantile_interval": list(interval), "interval_confidence": INTERVAL_CONFIDENCE}

