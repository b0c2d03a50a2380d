"""Plan fiducial markers from a simulated data set: which vertices, and how many.

The store holds every vertex's displacement, so markers can be chosen after simulation from
how the tissue actually moves, without simulating again. Selection uses the 'train' split
only (PCA modes, the proxy's regression); choosing how many and assessing use 'valid'
(the proxy's score, and optionally the MLP trained with those markers). Test splits are
never read.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import MarkerError
from ..surrogate.data import dataset_arrays
from ..surrogate.pca import fit_pca
from .candidates import candidate_vertices
from .proxy import QuadraticProxy
from .selection import EXCHANGE_ROUNDS, SHORTLIST, exchange_markers, greedy_markers
from .sentinel import SENTINEL_REACH, attached_range, sentinel_marker

__all__ = ["MarkerPlan", "plan_markers", "validation_error", "MAX_COUNT"]

log = logging.getLogger(__name__)

#: PCA components of the training fields the planner works with.
PLAN_COMPONENTS = 64
#: The largest marker count searched for a target error (as many as the marker-count study's).
MAX_COUNT = 20


@dataclass(eq=False)
class MarkerPlan:
    """Planned markers.

    Attributes:
        markers: (k,) int64 0-based vertex ids, in pick order (the first j are the plan for j markers).
        proxy_errors: (K,) validation mean Offset_max (mm) of the proxy with the first
            j + 1 markers of the greedy path (K >= k when a target was searched).
        path: (K,) int64 the whole greedy path.
        candidates: (c,) int64 candidate ids.
        region: candidate region; min_distance: spacing in mm.
        target_mm: the requested validation error, or None.
        target_reached: whether the chosen count reaches ``target_mm`` (None without target).
        mlp_errors: {n_markers: validation mean Offset_max of the MLP, mm} for counts
            confirmed by training.
        proxy: the :class:`QuadraticProxy` used (scores any marker set).
        proxy_error: the proxy's validation mean Offset_max (mm) of :attr:`markers`.
        exchanged: markers the exchange refinement replaced.
        sentinel: the sentinel's vertex id (the last of :attr:`markers`,
            :mod:`tissuecast.planning.sentinel`), or -1 without one.
        sentinel_least: its least share of the markers' motion in the training samples.
    """

    markers: np.ndarray
    proxy_errors: np.ndarray
    path: np.ndarray
    candidates: np.ndarray
    region: str
    min_distance: float
    target_mm: float | None = None
    target_reached: bool | None = None
    mlp_errors: dict = field(default_factory=dict)
    proxy: QuadraticProxy | None = None
    proxy_error: float = float("nan")
    exchanged: int = 0
    sentinel: int = -1
    sentinel_least: float = 0.0

    @property
    def count(self) -> int:
        return int(self.markers.size)

    def as_dict(self) -> dict:
        return {"markers": self.markers.tolist(), "count": self.count, "path": self.path.tolist(),
                "proxy_valid_offset_max_mm": [float(x) for x in self.proxy_errors],
                "proxy_valid_offset_max_mm_of_markers": float(self.proxy_error), "exchanged": int(self.exchanged),
                "mlp_valid_offset_max_mm": {str(k): float(v) for k, v in sorted(self.mlp_errors.items())},
                "region": self.region, "min_distance_mm": self.min_distance, "n_candidates": int(self.candidates.size),
                "target_mm": self.target_mm, "target_reached": self.target_reached,
                "sentinel": int(self.sentinel), "sentinel_least_share": float(self.sentinel_least)}


def validation_error(arrays, markers, config=None) -> float:
    """Validation mean Offset_max (mm) of an MLP trained on the 'train' split with ``markers``
    (no calibration hold-out, one network)."""
    from ..surrogate import DeformationModel

    m = DeformationModel(config, ensemble=1, calibration="none").fit(
        arrays.displacements, markers, mesh=arrays.mesh, fixed=arrays.fixed,
        train_idx=arrays.train_idx, valid_idx=arrays.valid_idx)
    bench = np.asarray(arrays.displacements[arrays.valid_idx], dtype=np.float64)
    pred = m.predict(bench[:, np.asarray(markers), :])
    return float(np.linalg.norm(pred - bench, axis=2).max(axis=1).mean())


def plan_markers(dataset, count: int | None = None, *, target_mm: float | None = None, max_count: int = MAX_COUNT,
                 region: str = "surface", min_distance: float = 0.0, allowed=None, shortlist: int = SHORTLIST,
                 confirm: bool = False, config=None, exchange_rounds: int = EXCHANGE_ROUNDS, sentinel: bool = False,
                 on_step: Callable[[int, np.ndarray, float], None] | None = None) -> MarkerPlan:
    """Choose markers from a data set's simulated fields.

    Args:
        dataset: a :class:`tissuecast.dataset.Dataset` with converged 'train' and 'valid' samples.
        count: number of markers; or give ``target_mm`` instead.
        target_mm: choose the smallest count whose planned markers reach this validation
            mean Offset_max (mm), searching up to ``max_count``.
        max_count: the largest count searched for ``target_mm``.
        region: candidate vertices, see :data:`tissuecast.planning.candidates.REGIONS`.
        min_distance: markers are farther apart than this (mm).
        allowed: optional user mask (bool (n,) or 0-based ids) of allowed vertices.
        shortlist: candidates scored by the proxy per greedy step (and per position of the exchange).
        exchange_rounds: passes of the exchange refinement over the chosen count's markers
            (:func:`~tissuecast.planning.selection.exchange_markers`); 0 = the greedy path's prefix.
        confirm: train the MLP (validation error) for the chosen count; with ``target_mm``
            the count is then adjusted until the MLP, not only the proxy, decides it.
        config: surrogate settings for ``confirm`` (default: the data set's).
        sentinel: where the data set draws the attached region's extent, the last marker is a
            sentinel just beyond the drawn range (:mod:`~tissuecast.planning.sentinel`): of the
            ``count`` planned markers the one whose place the sentinel takes at the least cost to
            the proxy, the others then refined around it; with ``target_mm`` the sentinel comes on
            top of the markers that reach it. Without a drawn extent, or where no vertex
            qualifies (logged), there is none.
        on_step: progress callback (number of markers, markers so far, proxy score).

    Returns:
        A :class:`MarkerPlan`.

    Raises:
        MarkerError: neither or both of count and target_mm, bad candidates, too few of them.
    """
    _check_request(count, target_mm)
    if config is None:
        config = dataset.config
    arrays = dataset_arrays(dataset)
    planner = _planner(arrays, region, allowed, shortlist, min_distance, on_step)
    watch = attached_range(dataset) if sentinel and (count is None or count >= 2) else None
    n_path = count if count is not None else min(max_count, planner.candidates.size)
    if target_mm is None:
        path, scores = planner.path(n_path)
        markers, err, changed = planner.exchange(path, float(scores[-1]), exchange_rounds)
        plan = MarkerPlan(markers, scores, path, planner.candidates, region, float(min_distance), proxy=planner.proxy,
                          proxy_error=err, exchanged=changed)
        if watch is not None:
            plan = _around_sentinel(plan, planner, arrays, watch, exchange_rounds)
        if confirm:
            plan.mlp_errors[plan.count] = validation_error(arrays, plan.markers, config)
        return plan
    path, scores = planner.path(n_path, stop_at=target_mm)
    n = len(path)
    mlp: dict = {}
    if confirm:
        path, scores, n, mlp = _confirmed_count(planner, arrays, config, path, scores, n_path, target_mm)
    markers, err, changed = planner.exchange(path[:n], float(scores[n - 1]), exchange_rounds)
    if confirm and changed:  # the network decides between the greedy prefix and its exchange
        refined = validation_error(arrays, markers, config)
        if refined < mlp[n]:
            mlp[n] = refined
        else:
            markers, err, changed = path[:n], float(scores[n - 1]), 0
    reached = bool((mlp[n] if confirm else err) <= target_mm)
    plan = MarkerPlan(markers, scores, path, planner.candidates, region, float(min_distance), float(target_mm), reached,
                      mlp, planner.proxy, err, changed)
    return plan if watch is None else _with_sentinel(plan, planner, arrays, watch)


def _around_sentinel(plan: MarkerPlan, planner: "_Planner", arrays, watch, rounds: int) -> MarkerPlan:
    """``plan`` with one of its markers made the sentinel: each marker in turn is left out, the
    sentinel for the others found (:func:`~.sentinel.sentinel_marker`), and the set with the
    lowest proxy score refined by exchanges that keep the sentinel; the sentinel last. Where
    none qualifies (logged), ``plan``."""
    distance, margin_max = watch
    best = None
    for pos in range(plan.count):
        others = np.delete(plan.markers, pos)
        v, least = sentinel_marker(arrays.displacements, arrays.train_idx, others, planner.candidates, distance,
                                   margin_max, points=planner.points, min_distance=planner.min_distance)
        if v >= 0:
            trial = np.r_[v, others]
            score = float(planner.proxy(trial))
            if best is None or score < best[0]:
                best = (score, trial, least)
    if best is None:
        _warn_no_sentinel(margin_max, planner.min_distance)
        return plan
    score, trial, _ = best
    markers, err, changed = planner.exchange(trial, score, rounds, keep=1)
    v = int(markers[0])
    # its least share among the markers it ends with
    _, least = sentinel_marker(arrays.displacements, arrays.train_idx, markers[1:], [v], distance, margin_max)
    _log_sentinel(v, least, distance, margin_max)
    return MarkerPlan(np.append(markers[1:], v), plan.proxy_errors, plan.path, planner.candidates, plan.region,
                      plan.min_distance, proxy=planner.proxy, proxy_error=err, exchanged=plan.exchanged + changed,
                      sentinel=v, sentinel_least=least)


def _warn_no_sentinel(margin_max: float, min_distance: float) -> None:
    log.warning("no sentinel marker: no candidate vertex lies %g-%g mm beyond the attached region's nominal edge "
                "and %g mm from the other markers; an attachment beyond the drawn range goes unseen by the alarm",
                margin_max, margin_max + SENTINEL_REACH, min_distance)


def _log_sentinel(v: int, least: float, distance, margin_max: float) -> None:
    log.info("sentinel marker: vertex %d, %.1f mm beyond the attached region's nominal edge (the drawn range ends at "
             "%g mm); it took at least %.0f %% of the markers' motion in every training sample", v, distance[v],
             margin_max, 100 * least)


def _with_sentinel(plan: MarkerPlan, planner: "_Planner", arrays, watch) -> MarkerPlan:
    """``plan`` with the sentinel appended to its markers (unchanged where none qualifies, logged)."""
    distance, margin_max = watch
    v, least = sentinel_marker(arrays.displacements, arrays.train_idx, plan.markers, planner.candidates, distance,
                               margin_max, points=planner.points, min_distance=planner.min_distance)
    if v < 0:
        _warn_no_sentinel(margin_max, planner.min_distance)
        return plan
    markers = np.append(plan.markers, v)
    _log_sentinel(v, least, distance, margin_max)
    plan.markers, plan.sentinel, plan.sentinel_least = markers, v, least
    plan.proxy_error = float(planner.proxy(markers))
    return plan


def _check_request(count: int | None, target_mm: float | None) -> None:
    if (count is None) == (target_mm is None):
        raise MarkerError("give either a marker count or a target error (target_mm), not both or neither")
    if count is not None and count < 1:
        raise MarkerError(f"the number of markers must be >= 1, got {count}")
    if target_mm is not None and not target_mm > 0:
        raise MarkerError(f"the target error must be a positive number of mm, got {target_mm}")


@dataclass(eq=False)
class _Planner:
    """What every greedy path of one plan shares: the proxy, the PCA modes, the candidates."""

    proxy: QuadraticProxy
    modes: np.ndarray
    candidates: np.ndarray
    points: np.ndarray
    shortlist: int
    min_distance: float
    on_step: Callable | None

    def path(self, count: int, **options) -> tuple[np.ndarray, np.ndarray]:
        """The greedy path to ``count`` markers and its proxy scores (see :func:`greedy_markers`)."""
        return greedy_markers(self.proxy, self.modes, self.candidates, count, shortlist=self.shortlist, points=self.points,
                              min_distance=self.min_distance, on_step=self.on_step, **options)

    def exchange(self, markers: np.ndarray, score: float, rounds: int, keep: int = 0) -> tuple[np.ndarray, float, int]:
        """``markers`` refined by exchanges, the first ``keep`` kept (see :func:`exchange_markers`):
        (ids, proxy score, replaced count)."""
        if rounds < 1 or not np.isfinite(score):
            return markers, score, 0
        out, best, _ = exchange_markers(self.proxy, self.modes, self.candidates, markers, shortlist=self.shortlist,
                                        points=self.points, min_distance=self.min_distance, rounds=rounds, keep=keep)
        if not best < score:
            return markers, score, 0
        return out, best, int(np.sum(out != np.asarray(markers)))


def _planner(arrays, region: str, allowed, shortlist: int, min_distance: float, on_step) -> _Planner:
    """PCA of the training fields (:data:`PLAN_COMPONENTS`), the proxy scored on 'valid', the candidates."""
    U = arrays.displacements
    train = np.asarray(U[arrays.train_idx], dtype=np.float64).reshape(len(arrays.train_idx), -1)
    valid = np.asarray(U[arrays.valid_idx], dtype=np.float64)
    basis = fit_pca(train, min(PLAN_COMPONENTS, len(train) - 1, train.shape[1]))
    proxy = QuadraticProxy(basis, train, valid)
    modes = basis.components * basis.singular_values[:, None]
    cand = candidate_vertices(arrays.mesh, region=region, allowed=allowed, exclude=arrays.fixed)
    return _Planner(proxy, modes, cand, arrays.mesh.points, shortlist, min_distance, on_step)


def _confirmed_count(planner: _Planner, arrays, config, path, scores, n_path: int, target_mm: float):
    """The count the trained MLP (not only the proxy) needs to reach ``target_mm``, from the proxy's.

    Returns:
        ``(path, scores, count, {count: MLP validation mean Offset_max, mm})``; the path grows
        (up to ``n_path``) when the MLP needs more markers than the proxy.
    """
    n = len(path)
    mlp = {n: validation_error(arrays, path[:n], config)}
    while mlp[n] > target_mm and n < n_path:  # the MLP needs more markers than the proxy
        n += 1
        if n > len(path):
            path, more = planner.path(n, start=path)
            scores = np.r_[scores, more[len(scores):]]
        mlp[n] = validation_error(arrays, path[:n], config)
    while n > 1 and mlp[n] <= target_mm:  # ... or fewer
        if n - 1 not in mlp:
            mlp[n - 1] = validation_error(arrays, path[:n - 1], config)
        if mlp[n - 1] > target_mm:
            break
        n -= 1
    return path, scores, n, mlp
