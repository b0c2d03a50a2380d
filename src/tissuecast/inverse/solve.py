"""The field from the markers through the physics: the loads, and the parameters the operating
room does not know, whose finite-element solution matches the tracked markers.

The surrogate (:mod:`tissuecast.surrogate`) learns the map from marker displacements to the
field from simulations. :class:`MarkerInverse` solves for it instead, one frame at a time, with
the data set's own simulator: it looks for the LBO weights ``W`` ((n_b, 3), the surface load
the scenario draws, at the data set's force magnitude alpha) and the scenario's uncertain
parameters (``[scenario.uncertain]``) whose solution puts the markers where they were tracked,
with the loads that navigation knows (the tracked instrument's indentation, the change of
gravity) given as a :class:`~tissuecast.scenario.ScenarioDraw`.

The estimate is the maximum a posteriori one: marker errors Gaussian with standard deviation
``noise`` (mm, each coordinate), ``W`` with the prior of its draws (independent U(-1, 1):
mean 0, variance 1/3), each continuous parameter with its range's mean and standard deviation
(log-uniform factors in log space). Gauss-Newton steps: the markers' sensitivities from
the tangent stiffness at the current solution (held dofs eliminated; the parameters' through a
finite difference of the internal forces), each full solve started from the last one; a step is
limited to ``STEP_CAP`` prior standard deviations per unknown and halved where the solve fails
or the posterior falls. Where no halving is accepted (markers that respond far from linearly: a
body swinging about its pins), the iteration goes on damped (Levenberg: the prior's precision
times the Gauss-Newton matrix's largest curvature in prior units, times a factor raised tenfold
where a trial is rejected, lowered threefold where one is accepted), in short steps turned
towards the posterior's gradient, rather than giving up. Where the best fit still misses a
marker (by more than ``MISFIT_NOISES`` noise standard deviations), its held set is iterated once
more, damped from the prior mean (another path through the loads), and the better fit kept.

The attached region's margin changes which vertices are held, so the solution jumps where a
vertex joins the region, and a single held vertex next to a marker moves it by millimetres:
the posterior over the margin is rugged. It is searched over every distinct held set its range
gives, each set with its prior probability (the share of the margin's range that gives it: the
nominal extent holds over the whole gap between the rim's inner and outer vertices). The
markers narrow the search first: a marker that did not move (within ``STILL_NOISES`` noise
standard deviations) is held, one that moved is not, which brackets the margin between the
largest surface distance of a still marker and the smallest of a moving one. The likeliest set
a priori is iterated to convergence first, every other one with a few Gauss-Newton steps
started from the best solution so far, then the best ``FINISHED`` to convergence from where
the search left them. The field is, by ``estimate``, the likeliest of them (``"likeliest"``: one
equilibrium of the simulator, the held set the markers favour) or their average weighted by their
posterior ``exp(-objective / 2)`` (``"mean"``: where the markers cannot tell whether a vertex far
from them is held, it takes the middle; a blend of equilibria, smeared at the held region's rim
where the neighbours of the true set take weight). Where the margin is known (measured in
surgery: ``solve(..., attached_margin=...)``), its held set alone is iterated, without the search;
where it is measured with an uncertainty (``attached_margin_sd``), the held sets are searched with
the measurement's normal law as their prior, those it leaves unlikely not at all.
The parameters, W and the misfit are the best set's. The density (a factor on the gravity
change, a small share of the shipped presets' loads: docs/uncertainty.md) and the material
regions' moduli are kept at their nominal values.

This is a measurement of what the markers determine, and a reference predictor: a frame takes
seconds to minutes (tens of full solves with the parameters known, hundreds with them drawn),
not the surrogate's microseconds. ``benchmarks/physics_inverse.py`` measures it against the
surrogate. Ids are 0-based; mm, N, MPa.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, ConvergenceError
from ..dataset.sensitivities import (CONTINUOUS_PARAMETERS, PARAMETER_STEP, WEIGHT_SD, equilibrium_response,
                                     parameter_directions, unit_loads)
from ..scenario.parameters import ParameterDraw, law_cdf
from ..scenario.sample_inputs import SampleInputs, ScenarioDraw

__all__ = ["MarkerInverse", "InverseResult", "NOISE_MM", "MIN_TRACKED", "MISFIT_NOISES", "ESTIMATES", "spread_band"]

#: Default standard deviation of a tracked marker coordinate, mm (a misfit of this size is noise).
NOISE_MM = 0.05
#: Continuous parameters the inverse estimates where the scenario gives them a range, in order;
#: True where the range is log-uniform (a factor).
ESTIMATED = CONTINUOUS_PARAMETERS
#: Finite-difference step of the internal forces in a parameter, in prior standard deviations.
FD_STEP = PARAMETER_STEP
#: Iterations while searching the attached margin, and at most when finishing (damped frames take
#: more than Gauss-Newton's: docs/uncertainty.md). (Two
#: found the same estimates on the preset's test-1 frames but missed the held set of a frame with
#: the region shrunk by 5 mm: docs/uncertainty.md.)
SEARCH_ITERATIONS = 4
MAX_ITERATIONS = 30
#: The largest step of an unknown, in prior standard deviations.
STEP_CAP = 3.0
#: Convergence: the undamped (Gauss-Newton) step's largest component below this many prior
#: standard deviations, or its linearised gain in the objective (a chi-square) below ``GAIN_TOL``.
STEP_TOL = 1e-3
GAIN_TOL = 1e-2
#: Gauss-Newton steps are halved up to ``HALVINGS - 1`` times; where none is accepted, the
#: iteration is damped from then on (Levenberg, in the prior's metric): the damping's start,
#: its factors on a rejected / accepted step, its floor, and the damped trials an iteration may
#: take before it stops.
HALVINGS = 4
DAMPING = 1e-3
DAMPING_UP, DAMPING_DOWN, DAMPING_FLOOR = 10.0, 3.0, 1e-7
TRIALS = 8
#: Poisson's ratio stays within these while iterating.
NU_LIMITS = (0.3, 0.495)
#: Equilibrium iterations and numeric factorisations a full solve may use at most: a trial step
#: into a far, soft corner of the parameters (a body near a limit point) is cut back instead of
#: waited for. Counts of work, not seconds, so that a frame's answer is the same on any machine
#: under any load; two, as a warm solve's iterations cost a preconditioned Krylov solve each and
#: the cautious retry's a factorisation each.
SOLVE_ITERATIONS, SOLVE_FACTORIZATIONS = 200, 40
#: A solve may use this many times the iterations (factorisations) of the frame's longest
#: converged one so far, at least ``SOLVE_FLOOR`` (``FACTORIZATION_FLOOR``) and at most the
#: above: the caps follow the loads.
SOLVE_FACTOR = 5
SOLVE_FLOOR, FACTORIZATION_FLOOR = 40, 8
#: Held sets iterated to convergence after the search.
FINISHED = 4
#: With a measured margin (``solve(attached_margin_sd=...)``), held sets whose prior probability
#: is below this share of the likeliest set's are not searched.
PRIOR_SHARE = 1e-3
#: A marker that moved less than this many noise standard deviations is taken as held.
STILL_NOISES = 4.0
#: Tracked markers a frame needs at least.
MIN_TRACKED = 3
#: A fit whose worst marker misses by more than this many noise standard deviations is flagged:
#: the simulator's loads and parameters do not explain the frame (or the search missed them).
MISFIT_NOISES = 4.0
#: A solve from zero whose field differs anywhere from the warm-started one's by more than this
#: many noise standard deviations is on another branch (another equilibrium of the same loads).
BRANCH_NOISES = 4.0
#: The field a searched frame reports (``MarkerInverse.solve(estimate=...)``; module notes); the
#: first is the default.
ESTIMATES = ("mean", "likeliest")
#: A full solve that stopped or broke down (as the data set's worker counts them).
_SOLVE_FAILURES = (ConvergenceError, ArithmeticError, np.linalg.LinAlgError)


def spread_band(coverage: float) -> float:
    """The factor on :attr:`InverseResult.spread` of the ball that holds ``coverage`` of an
    isotropic 3-D Gaussian error of that spread: ``sqrt(chi2_3(coverage) / 3)`` (1.44 at 0.9)."""
    from scipy.stats import chi2

    if not 0.0 < coverage < 1.0:
        raise ConfigError(f"coverage must lie between 0 and 1, got {coverage!r}")
    return math.sqrt(chi2.ppf(coverage, 3) / 3.0)


@dataclass(frozen=True, eq=False)
class InverseResult:
    """One frame's estimate.

    Attributes:
        field: (n, 3) float64 mm, the displacement at every mesh vertex: the likeliest
            finished held set's, or the posterior mean over them (:attr:`estimate`; module notes).
        weights: (n_b, 3) float64, the LBO weights W of the surface load.
        parameters: the estimated :class:`~tissuecast.scenario.parameters.ParameterDraw`
            (nominal values where the scenario draws nothing).
        marker_misfit: the largest distance between a marker's solved and tracked
            displacement, mm.
        objective: minus twice the log posterior (up to a constant) at the estimate, the held
            set's prior included.
        held_sets: how many of the attached margin's held sets were finished and weighed (1
            where the margin is not drawn or is given).
        solves: full finite-element solves it took.
        seconds: wall-clock time.
        spread: (n,) float64 mm, each vertex's posterior spread ``sqrt(sum_xyz var)`` (as an
            ensemble's ``sigma``): the Laplace approximation within the best held set (what
            the markers' noise leaves open, to first order) plus the finished held sets' fields'
            posterior-weighted mean square distance from ``field``. It does not see what the simulator's family
            leaves out, nor another equilibrium or held set that the search ranked below
            (docs/uncertainty.md measures how often the error exceeds it); NaN where the
            estimate has no tangent.
        complete: False where the frame's time limit cut the search short (the estimate is
            the best reached by then).
        estimate: which field of :data:`ESTIMATES` ``field`` is.
        likeliest_weight: the likeliest finished held set's share of their posterior weight
            (1 where there is one set): how sure the markers are of where the tissue is held.
    """

    field: np.ndarray
    weights: np.ndarray
    parameters: ParameterDraw
    marker_misfit: float
    objective: float
    held_sets: int
    solves: int
    seconds: float
    spread: np.ndarray
    complete: bool = True
    estimate: str = ESTIMATES[0]
    likeliest_weight: float = 1.0

    def within_band(self, truth: np.ndarray, coverage: float = 0.9) -> float:
        """The share of the vertices whose error against ``truth`` (n, 3) mm lies within the
        ``coverage`` band, :func:`spread_band` times :attr:`spread`, up to ``truth``'s rounding
        to float32 (a data set's storage): the vertices the known loads prescribe (held, or moved
        by a tracked instrument) have no spread, and their error is that rounding."""
        truth = np.asarray(truth, dtype=np.float64)
        rounding = np.finfo(np.float32).eps * np.linalg.norm(truth, axis=1)
        error = np.linalg.norm(self.field - truth, axis=1)
        return float(np.mean(error <= spread_band(coverage) * self.spread + rounding))


class MarkerInverse:
    """Fields from tracked markers by solving for the loads and parameters (module notes).

    Args:
        scenario: the data set's resolved :class:`~tissuecast.scenario.Scenario`.
        solver: ``attempt -> Solver`` (``SampleContext.solver``): attempt 0 the data set's
            solver, 1 its first cautious retry (used when a solve from the last one fails).
        markers: (n_d,) int64 marker vertex ids, 0-based.
        alpha: the data set's force magnitude, N.
        noise: standard deviation of a tracked coordinate, mm.
    """

    def __init__(self, scenario, solver, markers, alpha: float, *, noise: float = NOISE_MM):
        self.scenario = scenario
        self._solver = solver
        self.markers = np.asarray(markers, dtype=np.int64)
        self.marker_dofs = (3 * self.markers[:, None] + np.arange(3)).ravel()  # (3 n_d,) node-major
        if not (np.isfinite(alpha) and alpha > 0):
            raise ConfigError(f"the force magnitude alpha must be a positive number of N, got {alpha!r}")
        if not noise > 0:
            raise ConfigError(f"the marker noise must be a positive number of mm, got {noise!r}")
        self.alpha, self.noise = float(alpha), float(noise)
        surface = scenario.surface_forces
        self.n_basis = surface.basis.n_vectors
        self._unit = unit_loads(scenario, self.alpha)  # (3 n_b, n_nodes, 3) N per unit weight
        drawn = parameter_directions(scenario)  # those of ESTIMATED the scenario draws, with their priors
        self._names = [(name, log) for name, log, _, _ in drawn]
        self._mu = np.array([0.0] * (3 * self.n_basis) + [centre for _, _, centre, _ in drawn])
        self._sd = np.array([WEIGHT_SD] * (3 * self.n_basis) + [sd for _, _, _, sd in drawn])
        bounds = scenario.config.uncertain.attached_margin if scenario.uncertain is not None else None
        #: (lo, hi) mm, the attached margin's drawn range, or None where it is not drawn
        self._margin_range = (float(bounds[0]), float(bounds[1])) if bounds else None
        self._margins = self._margin_candidates(scenario.uncertain, self._margin_range)
        self._set_prior = self._held_set_prior(self._margins, self._margin_range,  # aligned with _margins
                                               arcsine="attached_margin" in scenario.config.uncertain.arcsine)

    def flags(self, result: InverseResult) -> bool:
        """Whether ``result``'s worst marker misses by more than :data:`MISFIT_NOISES` noise
        standard deviations (a frame the simulator's family does not explain, or a missed search)."""
        return result.marker_misfit > MISFIT_NOISES * self.noise

    @property
    def estimated(self) -> tuple[str, ...]:
        """The continuous parameters estimated (those the scenario draws, of :data:`ESTIMATED`)."""
        return tuple(name for name, _ in self._names)

    @property
    def n_unknowns(self) -> int:
        """The continuous unknowns of a frame: ``3 n_b`` load weights and the :attr:`estimated`
        parameters (the attached margin, when drawn, is searched over besides)."""
        return int(self._mu.size)

    @property
    def margin_range(self) -> tuple[float, float] | None:
        """(lo, hi) mm, the attached margin's drawn range, or None where the scenario does not
        draw it (then no margin can be given to :meth:`solve`)."""
        return self._margin_range if self._margins.size else None

    @property
    def margins(self) -> np.ndarray:
        """(k,) mm, one attached margin per distinct held set of its range, ascending (empty
        when the margin is not drawn)."""
        return self._margins.copy()

    @classmethod
    def from_dataset(cls, dataset, markers, *, noise: float = NOISE_MM) -> "MarkerInverse":
        """The inverse of a data set's simulator (its scenario, solver and force magnitude: the
        LBO samples' alpha)."""
        from ..dataset.worker import SampleContext

        ctx = SampleContext(dataset.recipe())
        alpha = np.asarray(dataset.alpha, dtype=np.float64)
        lbo = np.isnan(np.asarray(dataset.beta, dtype=np.float64)) & np.isfinite(alpha)
        if not lbo.any():
            raise ConfigError("the data set holds no solved LBO sample to take the force magnitude alpha from")
        return cls(ctx.scenario, ctx.solver, markers, float(np.median(alpha[lbo])), noise=noise)

    @staticmethod
    def _margin_candidates(uncertain, bounds) -> np.ndarray:
        """One margin per distinct held set of the attached margin's range ``bounds`` (lo, hi)
        mm, ascending (empty when the margin is not drawn: ``bounds`` None)."""
        if bounds is None or uncertain.distance is None:
            return np.zeros(0)
        lo, hi = bounds
        d = uncertain.distance[np.isfinite(uncertain.distance)]
        inside = np.unique(d[(d >= lo) & (d <= hi)])
        first = [lo] if not inside.size or inside[0] > lo else []
        return np.concatenate([first, inside])

    @staticmethod
    def _held_set_prior(margins: np.ndarray, bounds, measured: tuple[float, float] | None = None, *,
                        arcsine: bool = False) -> np.ndarray:
        """(k,) ``-2 log P(held set)`` of each candidate margin: the probability of the margins
        that give the set (the nominal extent holds over the whole gap between the rim's inner
        and outer vertices, each vertex beyond it over the gap to the next), under the range's
        law (uniform, or arcsine with ``arcsine``), or with ``measured`` ``(mean, sd)`` mm under
        that normal law truncated to the range."""
        if not margins.size:
            return np.zeros(0)
        lo, hi = bounds
        edges = np.append(margins, hi)
        if measured is None:
            p = np.diff(law_cdf((edges - lo) / (hi - lo), arcsine))
        else:
            from scipy.stats import norm

            mean, sd = measured
            cdf = norm.cdf((edges - mean) / sd)
            p = np.diff(cdf) / max(cdf[-1] - cdf[0], 1e-300)
        return -2.0 * np.log(np.maximum(p, 1e-9 * np.max(p)))  # a set reached only at the range's end

    def known_draw(self, seed: int) -> ScenarioDraw:
        """A simulated sample's known loads: its draws (the instrument's indentation, the
        gravity change) without its uncertain parameters, which the inverse estimates."""
        return dataclasses.replace(self.scenario.draw_for(int(seed)), parameters=None)

    # ------------------------------------------------------------------ solving
    def solve(self, marker_displacements, draw: ScenarioDraw | None = None, *, progress=None,
              time_limit: float | None = None, attached_margin: float | None = None,
              attached_margin_sd: float | None = None, estimate: str | None = None) -> InverseResult:
        """The MAP estimate of one frame.

        Args:
            marker_displacements: (n_d, 3) mm, the tracked markers' displacements; a marker
                that was not tracked is NaN in all three coordinates (left out of the fit; at
                least :data:`MIN_TRACKED` must be tracked).
            draw: the known loads (indentation, gravity change: a simulated sample's
                :meth:`known_draw`, a tracked frame's :meth:`Scenario.frame_draw
                <tissuecast.scenario.Scenario.frame_draw>`); None: none.
            progress: called with a line of text as the search goes on (a frame takes seconds
                to minutes), or None.
            time_limit: wall-clock seconds for the frame, or None (none). Past it no further
                held set is searched or iterated (a solve under way finishes, within its cap:
                :meth:`_Frame.field`): the estimate is the best reached by then and
                ``complete`` is False. The first held set (the likeliest a priori; the only
                one where the margin is not drawn) is iterated to convergence regardless.
                Without a limit the estimate is the same on every machine (every cap inside is
                a count of iterations or factorisations); with one, where it cuts depends on the machine's speed.
            attached_margin: the attached region's margin, mm, where it is known (measured in
                surgery): its held set alone is iterated, no search (seconds, not minutes, a
                frame); None: searched over its range.
            attached_margin_sd: the standard deviation of a measured ``attached_margin``, mm:
                the held sets are searched as without a margin, each with its probability
                under the measurement's normal law (truncated to the drawn range) as its prior
                instead of the range's share; sets below :data:`PRIOR_SHARE` of the likeliest
                are not searched. None: the margin as given, exactly.
            estimate: the field reported where held sets were searched, one of
                :data:`ESTIMATES`: ``"mean"`` (the default; also None) the posterior mean over
                the finished held sets, ``"likeliest"`` the likeliest one's solution (module notes). The
                search, the parameters and the spread's first term are the same either way.

        Raises:
            ConfigError: the displacements do not match the markers, a marker has only some
                coordinates, fewer than :data:`MIN_TRACKED` markers are tracked, or
                ``estimate`` is not one of :data:`ESTIMATES`.
            ConvergenceError: no equilibrium to start the frame from (the known loads with the
                prior's mean parameters) within the solve caps (:data:`SOLVE_ITERATIONS`, :data:`SOLVE_FACTORIZATIONS`).
        """
        t0 = time.perf_counter()
        d = np.asarray(marker_displacements, dtype=np.float64)
        if d.shape != (len(self.markers), 3) or np.isinf(d).any():
            raise ConfigError(f"marker displacements must be finite with shape ({len(self.markers)}, 3), got {d.shape}")
        lost = np.isnan(d)
        if (lost.any(axis=1) & ~lost.all(axis=1)).any():
            j = int(np.flatnonzero(lost.any(axis=1) & ~lost.all(axis=1))[0])
            raise ConfigError(f"marker {j} has only some coordinates; give x, y and z, or NaN for all three (not tracked)")
        if (~lost.all(axis=1)).sum() < MIN_TRACKED:
            raise ConfigError(f"only {int((~lost.all(axis=1)).sum())} markers are tracked; the physics inverse needs at "
                              f"least {MIN_TRACKED}")
        estimate = ESTIMATES[0] if estimate is None else estimate
        if estimate not in ESTIMATES:
            raise ConfigError(f"the estimate must be one of {', '.join(map(repr, ESTIMATES))}, got {estimate!r}")
        if time_limit is not None and not time_limit > 0:
            raise ConfigError(f"the time limit must be a positive number of seconds (or None), got {time_limit!r}")
        deadline = math.inf if time_limit is None else t0 + float(time_limit)
        m = None if attached_margin is None else self._given_margin(attached_margin)
        candidates, prior = self._margins, self._set_prior
        if attached_margin_sd is not None:
            if m is None:
                raise ConfigError("a standard deviation of the attached margin needs the measured margin itself "
                                  "(attached_margin)")
            if not (isinstance(attached_margin_sd, (int, float, np.floating)) and 0 < attached_margin_sd < math.inf):
                raise ConfigError(f"the attached margin's standard deviation must be a positive number of mm, got "
                                  f"{attached_margin_sd!r}")
            prior = self._held_set_prior(candidates, self._margin_range, (m, float(attached_margin_sd)))
            keep = prior <= prior.min() - 2.0 * math.log(PRIOR_SHARE)
            candidates, prior = candidates[keep], prior[keep]
        frame = _Frame(self, d.ravel(), self._known_inputs(draw or ScenarioDraw()), progress, deadline)
        if attached_margin_sd is not None:
            frame.tell(f"attached margin measured {m:+.2f} +- {attached_margin_sd:g} mm: "
                       f"{candidates.size} held sets within reach")
        searched = candidates.size > 0 and (m is None or attached_margin_sd is not None)
        try:
            if searched:
                finished = frame.search_margin(candidates, prior)
            else:  # one held set: the margin given, or none drawn
                m = 0.0 if m is None else m
                finished = [(m, 0.0, *frame.iterate(self._mu, m, None, MAX_ITERATIONS, timed=False))]
                frame.tell("iterated" if attached_margin is None else f"iterated with the attached margin given ({m:+.2f} mm)")
        except _SOLVE_FAILURES as e:  # the first held set's first solve, from zero: the frame has no start
            raise ConvergenceError(f"the physics inverse found no equilibrium to start the frame from (the known loads "
                                   f"with the prior's mean parameters and no LBO load; {e}): the simulator cannot take "
                                   f"this frame's instrument pose or gravity within {SOLVE_ITERATIONS} iterations and "
                                   f"{SOLVE_FACTORIZATIONS} factorisations") from e
        finished = frame.retried([(m, p, *frame.polish(x, m, u)) for m, p, x, u in finished])
        scored, objs = frame.posteriors(finished)
        w = np.exp(-0.5 * (objs - objs.min()))
        n = self.scenario.mesh.n_vertices
        w /= w.sum()
        best = int(np.argmin(objs))
        margin, _, x, u = finished[best]
        field = u[:n].copy() if estimate == "likeliest" else sum(wi * ui[:n] for wi, (_, _, _, ui) in zip(w, finished))
        between = sum(wi * ((ui[:n] - field) ** 2).sum(axis=1) for wi, (_, _, _, ui) in zip(w, finished))
        obj, miss = float(objs[best]), scored[best][1]
        try:
            within = frame.spread(x, margin, u)
        except _SOLVE_FAILURES:  # no tangent at the estimate (an element inverted)
            within = np.full(n, np.nan)
        return InverseResult(field=field, weights=x[: 3 * self.n_basis].reshape(self.n_basis, 3).copy(),
                             parameters=self._draw(x, margin), marker_misfit=miss, objective=obj,
                             held_sets=len(finished), solves=frame.solves, seconds=time.perf_counter() - t0,
                             complete=not frame.cut_short, spread=np.sqrt(within + between), estimate=estimate,
                             likeliest_weight=float(w[best]))

    def _given_margin(self, value) -> float:
        """A known attached margin, mm, checked against the scenario's drawn range."""
        if self.margin_range is None:
            raise ConfigError("the scenario does not draw the attached region's margin ([scenario.uncertain] "
                              "attached_margin): there is no margin to give; leave it out")
        lo, hi = self._margin_range
        if not (isinstance(value, (int, float, np.floating)) and lo <= float(value) <= hi):
            raise ConfigError(f"the attached margin {value!r} mm lies outside the range the simulations drew, "
                              f"[{lo:g}, {hi:g}] mm; give a margin within it (or none, to search it)")
        return float(value)

    def _known_inputs(self, draw: ScenarioDraw) -> SampleInputs:
        sc = self.scenario
        n = sc.mesh.n_vertices
        ids, values = sc.prescribed(draw)
        surface, body = sc.sample_loads(draw, np.zeros((n, 3)))
        return SampleInputs(np.zeros((n, 3)), np.zeros((self.n_basis, 3)), surface,
                            body if draw.body_force is not None else None, ids, values, draw)

    def _draw(self, x: np.ndarray, margin: float) -> ParameterDraw:
        values = {}
        for k, (name, log) in enumerate(self._names):
            v = x[3 * self.n_basis + k]
            values[name] = float(math.exp(v) if log else v)
        return ParameterDraw(attached_margin=float(margin), **values)


class _Frame:
    """The state of one frame's search: its data, known inputs, best point and solve count."""

    def __init__(self, inv: MarkerInverse, d: np.ndarray, known: SampleInputs, progress=None,
                 deadline: float = math.inf):
        self.inv, self.known, self.progress, self.deadline = inv, known, progress, deadline
        self.cut_short = False
        self.rows = np.isfinite(d)  # (3 n_d,) the tracked markers' coordinates
        self.d = np.where(self.rows, d, 0.0)
        self.solves = 0
        self.solve_iterations = SOLVE_ITERATIONS  # a solve's caps (:meth:`field`)
        self.solve_factorizations = SOLVE_FACTORIZATIONS
        self.longest = 0  # iterations of the longest converged solve so far
        self.most_factorizations = 0  # factorisations of a converged solve so far, at most
        self.best_x = inv._mu.copy()
        self.best_u = None
        self.best_obj = math.inf

    def inputs(self, x: np.ndarray, margin: float) -> SampleInputs:
        """The frame's inputs under the parameters of ``x`` and ``margin``."""
        inv = self.inv
        if inv.scenario.uncertain is None:
            return self.known
        return inv.scenario.with_parameters(self.known, inv._draw(x, margin))

    def solver(self, inputs: SampleInputs, attempt: int = 0):
        return self.inv._solver(attempt).with_parameters(*inputs.solver_parameters)

    def field(self, x: np.ndarray, margin: float, guess: np.ndarray | None) -> np.ndarray:
        """(n_nodes, 3) mm: the solution for unknowns ``x`` and margin ``margin``, started from
        ``guess`` (or zero); a failed solve is retried from zero with the cautious solver. Each solve may
        use :attr:`solve_iterations` equilibrium iterations (:data:`SOLVE_FACTOR` times the longest
        converged one so far, within [:data:`SOLVE_FLOOR`, :data:`SOLVE_ITERATIONS`]) and
        :attr:`solve_factorizations` factorisations (likewise)."""
        inv = self.inv
        inputs = self.inputs(x, margin)
        loads = np.tensordot(x[: 3 * inv.n_basis], inv._unit, axes=1)
        kw = inputs.solve_keywords()
        kw.update(iteration_limit=self.solve_iterations, factorization_limit=self.solve_factorizations)
        self.solves += 1
        try:
            return self._counted(self.solver(inputs).solve(loads, guess, **kw))
        except _SOLVE_FAILURES:
            pass
        self.solves += 1
        return self._counted(self.solver(inputs, 1).solve(loads, None, **kw))

    def _counted(self, result) -> np.ndarray:
        """``result``'s displacements (n_nodes, 3) mm; its iterations and factorisations may
        raise the caps."""
        self.longest = max(self.longest, result.iterations)
        self.most_factorizations = max(self.most_factorizations, result.factorizations)
        self.solve_iterations = min(SOLVE_ITERATIONS, max(SOLVE_FLOOR, SOLVE_FACTOR * self.longest))
        self.solve_factorizations = min(SOLVE_FACTORIZATIONS,
                                        max(FACTORIZATION_FLOOR, SOLVE_FACTOR * self.most_factorizations))
        return result.nodal_displacement

    def jacobian(self, x: np.ndarray, margin: float, u: np.ndarray) -> np.ndarray:
        """(3 n_d, n_x) d(marker displacements)/d(unknowns) at the equilibrium ``u`` of ``x``
        (the marker rows of :meth:`sensitivity`)."""
        return self.sensitivity(x, margin, u)[self.inv.marker_dofs]

    def sensitivity(self, x: np.ndarray, margin: float, u: np.ndarray) -> np.ndarray:
        """(3 n_nodes, n_x) d(displacements)/d(unknowns) at the equilibrium ``u`` of ``x``:
        the tangent stiffness K (the held dofs eliminated) solved against the loads' derivative
        (the unit LBO loads) and against minus the internal forces' derivative in each
        parameter (a finite difference of one assembly)."""
        inv = self.inv
        inputs = self.inputs(x, margin)
        solver = self.solver(inputs)
        nw = 3 * inv.n_basis
        forces = np.empty((x.size, u.size))
        forces[:nw] = inv._unit.reshape(nw, -1)
        tangent = solver.assembler.tangent(u) if x.size > nw else None  # its internal forces too
        for k in range(nw, x.size):
            h = FD_STEP * inv._sd[k]
            x2 = x.copy()
            x2[k] += h
            f2, _ = self.solver(self.inputs(x2, margin)).assembler.internal_force(u)
            forces[k] = -(f2 - tangent[0]) / h
        return equilibrium_response(solver, inputs, u, forces, tangent)

    def spread(self, x: np.ndarray, margin: float, u: np.ndarray) -> np.ndarray:
        """(n,) mm^2: each vertex's posterior variance within the held set of ``margin`` at the
        estimate ``(x, u)`` (Laplace): ``trace(S_v C S_v^T)``, with ``S_v`` the vertex's rows of
        :meth:`sensitivity` and ``C = (J^T J / noise^2 + P^-1)^-1`` the Gauss-Newton posterior
        covariance of the unknowns (``J`` the tracked markers' rows, ``P`` the prior's)."""
        inv = self.inv
        S = self.sensitivity(x, margin, u)[: 3 * inv.scenario.mesh.n_vertices]
        J = S[inv.marker_dofs][self.rows]
        cov = np.linalg.inv(J.T @ J / inv.noise**2 + np.diag(inv._sd**-2.0))
        return np.einsum("ij,ij->i", S @ cov, S).reshape(-1, 3).sum(axis=1)

    def objective(self, x: np.ndarray, u: np.ndarray) -> tuple[float, float]:
        """(minus twice the log posterior without the held set's prior, largest marker miss in mm)."""
        inv = self.inv
        r = (self.d - u[inv.markers].ravel())[self.rows]
        z = (x - inv._mu) / inv._sd
        return float(r @ r / inv.noise**2 + z @ z), float(np.linalg.norm(r.reshape(-1, 3), axis=1).max())

    def _clip(self, x: np.ndarray) -> np.ndarray:
        """Poisson's ratio kept physical (the prior alone keeps the factors near their ranges)."""
        for k, (name, _) in enumerate(self.inv._names):
            if name == "poisson_ratio":
                j = 3 * self.inv.n_basis + k
                x[j] = min(max(x[j], NU_LIMITS[0]), NU_LIMITS[1])
        return x

    def iterate(self, x: np.ndarray, margin: float, u: np.ndarray | None, iterations: int, timed: bool = True,
                damped: bool = False):
        """Gauss-Newton from ``x``, damped once it stalls (module notes); returns the last accepted (x, u).
        ``timed``: stop once the frame's time is up (the first held set is iterated to
        convergence regardless: an estimate cut before it converges can be far off). ``damped``:
        damped steps from the start (no Gauss-Newton halvings)."""
        inv = self.inv
        x = x.copy()
        u = self.field(x, margin, u)
        obj, _ = self.objective(x, u)
        damping = DAMPING if damped else 0.0  # Gauss-Newton (halved) until no step is accepted: damped from then on
        for _ in range(iterations):
            if timed and self.out_of_time():
                break
            m0 = u[inv.markers].ravel()[self.rows]
            J = self.jacobian(x, margin, u)[self.rows]
            A = J.T @ J / inv.noise**2 + np.diag(inv._sd**-2.0)
            g = J.T @ (self.d[self.rows] - m0) / inv.noise**2 - (x - inv._mu) / inv._sd**2
            full = np.linalg.solve(A, g)  # the Gauss-Newton step: converged where it is small
            if np.abs(full / inv._sd).max() < STEP_TOL or g @ full < GAIN_TOL:
                break
            scale = np.max(np.diag(A) * inv._sd**2) * inv._sd**-2.0  # the largest curvature, in prior units
            accepted = False
            for trial in range(HALVINGS + TRIALS):
                if damping:
                    step = self._capped(np.linalg.solve(A + damping * np.diag(scale), g))
                else:
                    step = self._capped(full) / 2.0**trial
                x_new = self._clip(x + step)
                try:
                    u_new = self.field(x_new, margin, u)
                except _SOLVE_FAILURES:
                    u_new = None
                if u_new is not None:
                    obj_new, _ = self.objective(x_new, u_new)
                    accepted = obj_new <= obj
                if accepted:
                    damping = damping and max(damping / DAMPING_DOWN, DAMPING_FLOOR)
                    break
                if timed and self.out_of_time():
                    break
                if damping:
                    damping *= DAMPING_UP
                elif trial == HALVINGS - 1:
                    damping = DAMPING
            if not accepted:
                break
            x, u, obj = x_new, u_new, obj_new
        if obj < self.best_obj:
            self.best_obj, self.best_x, self.best_u = obj, x.copy(), u
        return x, u

    def retried(self, finished: list) -> list:
        """``finished`` ``[(margin, prior, x, u)]`` with its best set iterated once more, damped
        from the prior mean, where its worst marker misses by more than :data:`MISFIT_NOISES`
        noise standard deviations (the halved Gauss-Newton steps can end on a branch the solves
        cannot leave); the retry replaces it where it fits better. Not once the frame's time is up."""
        inv = self.inv
        scores, objs = self.posteriors(finished)
        b = int(np.argmin(objs))
        if scores[b][1] <= MISFIT_NOISES * inv.noise or self.out_of_time():
            return finished
        margin, prior, _, _ = finished[b]
        self.tell(f"the best fit misses a marker by {scores[b][1]:.3f} mm: iterated again, damped from the prior mean")
        try:
            x, u = self.iterate(inv._mu, margin, None, MAX_ITERATIONS, damped=True)
        except _SOLVE_FAILURES:
            return finished
        if self.objective(x, u)[0] < scores[b][0]:
            finished = finished.copy()
            finished[b] = (margin, prior, x, u)
        return finished

    def posteriors(self, finished: list) -> tuple[list, np.ndarray]:
        """Of each ``(margin, prior, x, u)`` in ``finished``: its :meth:`objective` (objective,
        worst marker miss), and (k,) its objective plus its held set's prior ``-2 log P``."""
        scored = [self.objective(x, u) for _, _, x, u in finished]
        return scored, np.array([obj + p for (obj, _), (_, p, _, _) in zip(scored, finished)])

    def _capped(self, step: np.ndarray) -> np.ndarray:
        """``step`` scaled down so that no unknown moves by more than :data:`STEP_CAP` prior
        standard deviations."""
        big = np.abs(step / self.inv._sd).max() / STEP_CAP
        return step / big if big > 1.0 else step

    def polish(self, x: np.ndarray, margin: float, u: np.ndarray):
        """``(x, u)`` once more from a solve started at zero: where the loads have more than one
        equilibrium the warm-started solves can follow another branch than a sample's solve
        (which starts near zero). If the field from zero fits better, iterate on from it; if it
        is another branch (:data:`BRANCH_NOISES`) that fits worse at ``x``, take
        :data:`SEARCH_ITERATIONS` steps on it, and where they fit better than ``(x, u)``, go on
        to convergence and keep that (the branch a sample's solve takes can fit the markers far
        better elsewhere). Not once the frame's time is up."""
        if self.out_of_time():
            return x, u
        try:
            fresh = self.field(x, margin, None)
        except _SOLVE_FAILURES:
            return x, u
        here = self.objective(x, u)[0]
        if self.objective(x, fresh)[0] < here - 1e-9:
            return self.iterate(x, margin, fresh, MAX_ITERATIONS)
        if np.linalg.norm(fresh - u, axis=1).max() <= BRANCH_NOISES * self.inv.noise:
            return x, u
        try:  # a few steps on the other branch first: on to convergence only where they already fit better
            x2, u2 = self.iterate(x, margin, fresh, SEARCH_ITERATIONS)
            better = self.objective(x2, u2)[0] < here
            if better:
                x2, u2 = self.iterate(x2, margin, u2, MAX_ITERATIONS)
        except _SOLVE_FAILURES:
            return x, u
        self.tell(f"the solve from zero took another equilibrium; iterated on from it ({'kept' if better else 'not better'})")
        return (x2, u2) if better else (x, u)

    def search_margin(self, candidates: np.ndarray, prior: np.ndarray) -> list:
        """The held sets' search (module notes) over ``candidates`` (k,) mm with their ``prior``
        (k,) ``-2 log P``: ``[(margin, prior, x, u)]`` of the ``FINISHED`` best, each iterated to
        convergence."""
        inv = self.inv
        moved = np.linalg.norm(self.d.reshape(-1, 3), axis=1)
        tracked = self.rows.reshape(-1, 3).all(axis=1)
        dist = inv.scenario.uncertain.distance[inv.markers]
        still = tracked & (moved <= STILL_NOISES * inv.noise)
        moving = tracked & ~still
        lo = float(dist[still].max()) if still.any() else -math.inf
        hi = float(dist[moving].min()) if moving.any() else math.inf
        bracket = np.flatnonzero((candidates >= lo) & (candidates < hi))
        if not bracket.size:  # markers that contradict every held set (noise): search them all
            bracket = np.arange(len(candidates))
        start = int(bracket[np.argmin(prior[bracket])])  # the likeliest set a priori, to convergence first
        x, u = self.iterate(inv._mu, float(candidates[start]), None, MAX_ITERATIONS, timed=False)
        scores = {start: self.objective(x, u)[0] + prior[start]}
        searched = {start: (x, u)}
        self.tell(f"held set 1 of {bracket.size} the markers allow (margin {candidates[start]:+.2f} mm) iterated")
        for j, i in enumerate(sorted(bracket.tolist(), key=lambda i: abs(i - start))[1:], 2):  # outwards from it
            if self.out_of_time():
                self.tell(f"time is up: {j - 1} of {bracket.size} held sets searched")
                break
            try:
                x, u = self.iterate(self.best_x, float(candidates[i]), self.best_u, SEARCH_ITERATIONS)
            except _SOLVE_FAILURES:  # no equilibrium with this held set from the best so far, nor from zero
                self.tell(f"held set {j} of {bracket.size}: no solve converged; left out")
                continue
            scores[i] = self.objective(x, u)[0] + prior[i]
            searched[i] = (x, u)
            self.tell(f"held set {j} of {bracket.size} searched")
        finished = []
        best = sorted(scores, key=scores.get)[:FINISHED]
        for j, i in enumerate(best, 1):  # the best few on to convergence (the first set is already)
            margin = float(candidates[i])
            x, u = searched[i]
            if not (i == start or self.out_of_time()):
                x, u = self.iterate(x, margin, u, MAX_ITERATIONS)
                self.tell(f"best held set {j} of {len(best)} finished (margin {margin:+.2f} mm)")
            finished.append((margin, float(prior[i]), x, u))
        return finished

    def out_of_time(self) -> bool:
        """Whether the frame's time is up (then :attr:`cut_short` is set)."""
        if time.perf_counter() > self.deadline:
            self.cut_short = True
        return self.cut_short

    def tell(self, what: str) -> None:
        """Report the search's progress (with the solves so far), where asked to."""
        if self.progress is not None:
            self.progress(f"{what}; {self.solves} solves so far")
