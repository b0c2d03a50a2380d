"""Choosing marker vertices from how the tissue moves: pivoted QR on PCA modes, and greedy
forward selection on a validation score.

Every vertex carries 3 measurements (a tracked marker gives x, y and z together), so the
QR pivoting works on *blocks* of 3 columns: with ``A`` (K, 3 n) the PCA modes scaled by their
singular values, each step picks the candidate vertex whose 3 columns keep the largest
residual (Frobenius norm) after projecting out the span of the columns already picked.
That residual is the variance of the vertex's displacement left unexplained, under a Gaussian
model of the training fields, by the markers chosen so far: pivoted QR (Businger-Golub, as in
Manohar et al. 2018's sparse sensor placement, with vertex blocks instead of single entries).
Greedy forward selection then refines: among the QR's shortlist at each step, it adds the
vertex that most lowers a score (a cheap proxy of the validation error, see
:mod:`tissuecast.planning.proxy`); an exchange pass then revisits each chosen marker and
replaces it when a shortlisted vertex scores lower with the others kept.

Lengths in mm; vertex ids 0-based.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..errors import MarkerError

__all__ = ["qr_markers", "qr_residuals", "greedy_markers", "exchange_markers", "SHORTLIST", "EXCHANGE_ROUNDS"]

# Residual columns shorter than this share of the largest mode norm add no new direction.
_RANK_RTOL = 1e-10
#: Candidates (best by the block QR) the proxy scores per greedy step: each costs one proxy
#: fit, and the QR's order already puts good markers near the top.
SHORTLIST = 24
#: Passes of the exchange refinement over a plan's markers (:func:`exchange_markers`).
EXCHANGE_ROUNDS = 2
# An exchange is taken when it lowers the score by more than this share.
EXCHANGE_RTOL = 1e-4


class _BlockQR:
    """Residual norms of vertex blocks of ``A`` (K, n, 3) as picked blocks are projected out."""

    def __init__(self, A: np.ndarray, candidates: np.ndarray):
        self.A = A[:, candidates, :]  # (K, k, 3)
        self.candidates = candidates
        self.score = (self.A**2).sum(axis=(0, 2))  # (k,) squared residual norms
        self.Q = np.zeros((A.shape[0], 0))
        self.tol = _RANK_RTOL * max(float(np.sqrt(self.score.max(initial=0.0))), 1e-300)

    def add(self, block: np.ndarray) -> None:
        """Project the (K, 3) columns of a picked vertex out of every candidate's residual."""
        r = block - self.Q @ (self.Q.T @ block)
        q, s, _ = np.linalg.svd(r, full_matrices=False)
        q = q[:, s > self.tol]
        if q.shape[1] == 0:
            return
        proj = np.einsum("kj,kvc->jvc", q, self.A)
        self.score = np.maximum(self.score - (proj**2).sum(axis=(0, 2)), 0.0)
        self.Q = np.hstack([self.Q, q])


def _eligible(points: np.ndarray | None, candidates: np.ndarray, chosen: list[int], min_distance: float) -> np.ndarray:
    ok = ~np.isin(candidates, chosen)
    if min_distance > 0 and chosen:
        d = np.linalg.norm(points[candidates, None, :] - points[None, chosen, :], axis=2).min(axis=1)
        ok &= d > min_distance
    return ok


def _check(count: int, candidates: np.ndarray, min_distance: float, points) -> None:
    if count < 1:
        raise MarkerError(f"the number of markers must be >= 1, got {count}")
    if count > candidates.size:
        raise MarkerError(f"{count} markers requested but only {candidates.size} candidate vertices; "
                          "lower --count or widen the candidates")
    if min_distance > 0 and points is None:
        raise MarkerError("a minimum marker spacing needs the vertex positions (points)")


def qr_residuals(modes: np.ndarray, candidates: np.ndarray, chosen=()) -> np.ndarray:
    """Squared residual norm of each candidate's block after projecting out ``chosen``.

    Args:
        modes: (K, 3 n) float PCA modes (rows), scaled by their singular values.
        candidates: (k,) int 0-based candidate ids.
        chosen: 0-based ids already picked.

    Returns:
        (k,) float64, mm^2 (times the number of training samples when the modes are scaled
        by singular values).
    """
    A = np.asarray(modes, dtype=np.float64).reshape(len(modes), -1, 3)
    qr = _BlockQR(A, np.asarray(candidates, dtype=np.int64))
    for v in chosen:
        qr.add(A[:, int(v), :])
    return qr.score.copy()


def qr_markers(modes: np.ndarray, candidates, count: int, *, points=None, min_distance: float = 0.0) -> np.ndarray:
    """Markers by block-pivoted QR of the PCA modes.

    Args:
        modes: (K, 3 n) float, PCA modes as rows (vertex-major columns), scaled by their
            singular values (so a mode counts by how much the training fields move along it).
        candidates: (k,) int 0-based vertex ids allowed.
        count: number of markers.
        points: (n, 3) float mm, needed when ``min_distance > 0``.
        min_distance: markers are farther apart than this (mm).

    Returns:
        (count,) int64 0-based ids in pick order. Once the modes are exhausted (about K / 3
        picks) the remaining picks go to the eligible vertex farthest from those chosen.

    Raises:
        MarkerError: too few candidates, or none left at the requested spacing.
    """
    cand = np.asarray(candidates, dtype=np.int64)
    _check(count, cand, min_distance, points)
    pts = None if points is None else np.asarray(points, dtype=np.float64)
    A = np.asarray(modes, dtype=np.float64).reshape(len(modes), -1, 3)
    qr = _BlockQR(A, cand)
    chosen: list[int] = []
    for _ in range(count):
        ok = _eligible(pts, cand, chosen, min_distance)
        if not ok.any():
            raise MarkerError(f"only {len(chosen)} markers fit {min_distance:g} mm apart among the candidates; "
                              "lower the minimum spacing or the count")
        score = np.where(ok, qr.score, -np.inf)
        if score.max() <= qr.tol**2 and chosen and pts is not None:  # modes exhausted: spread out
            far = np.linalg.norm(pts[cand, None, :] - pts[None, chosen, :], axis=2).min(axis=1)
            score = np.where(ok, far, -np.inf)
        v = int(cand[int(np.argmax(score))])
        chosen.append(v)
        qr.add(A[:, v, :])
    return np.asarray(chosen, dtype=np.int64)


def greedy_markers(
    score: Callable[[np.ndarray], float],
    modes: np.ndarray,
    candidates,
    count: int,
    *,
    shortlist: int = SHORTLIST,
    points=None,
    min_distance: float = 0.0,
    start=(),
    stop_at: float | None = None,
    on_step: Callable[[int, np.ndarray, float], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy forward selection: each step adds the shortlisted vertex with the lowest score.

    Args:
        score: marker ids (k,) -> error to minimise (e.g. a proxy's validation mean
            Offset_max, mm).
        modes: (K, 3 n) singular-value-scaled PCA modes; the shortlist of each step is the
            ``shortlist`` eligible candidates with the largest QR residual.
        candidates: (k,) int 0-based allowed ids.
        count: final number of markers.
        shortlist: candidates scored per step.
        points: (n, 3) mm, needed when ``min_distance > 0``.
        min_distance: markers are farther apart than this (mm).
        start: ids to start from (kept, in order).
        stop_at: stop early once a step's score is at or below this.
        on_step: called with (number of markers, markers so far, score) after each step.

    Returns:
        ``(markers (count,) int64 in pick order, scores (count,) float64)``: ``scores[j]`` is
        the score of the first j + 1 markers (NaN for given start markers); fewer than
        ``count`` when ``stop_at`` was reached.
    """
    cand = np.asarray(candidates, dtype=np.int64)
    _check(count, cand, min_distance, points)
    if shortlist < 1:
        raise MarkerError(f"the shortlist must hold >= 1 candidate, got {shortlist}")
    pts = None if points is None else np.asarray(points, dtype=np.float64)
    A = np.asarray(modes, dtype=np.float64).reshape(len(modes), -1, 3)
    qr = _BlockQR(A, cand)
    chosen = [int(v) for v in start]
    scores = [np.nan] * len(chosen)
    for v in chosen:
        qr.add(A[:, v, :])
    while len(chosen) < count:
        ok = _eligible(pts, cand, chosen, min_distance)
        if not ok.any():
            raise MarkerError(f"only {len(chosen)} markers fit {min_distance:g} mm apart among the candidates; "
                              "lower the minimum spacing or the count")
        order = np.argsort(-np.where(ok, qr.score, -np.inf), kind="stable")[: min(shortlist, int(ok.sum()))]
        trial = [(score(np.asarray(chosen + [int(cand[i])], dtype=np.int64)), int(cand[i])) for i in order]
        best, v = min(trial, key=lambda t: (t[0], t[1]))
        chosen.append(v)
        scores.append(float(best))
        qr.add(A[:, v, :])
        if on_step:
            on_step(len(chosen), np.asarray(chosen, dtype=np.int64), float(best))
        if stop_at is not None and best <= stop_at:
            break
    return np.asarray(chosen, dtype=np.int64), np.asarray(scores, dtype=np.float64)


def exchange_markers(
    score: Callable[[np.ndarray], float],
    modes: np.ndarray,
    candidates,
    markers,
    *,
    shortlist: int = SHORTLIST,
    points=None,
    min_distance: float = 0.0,
    rounds: int = EXCHANGE_ROUNDS,
    keep: int = 0,
) -> tuple[np.ndarray, float, int]:
    """Exchange refinement of a marker set: each marker in turn is replaced by the shortlisted
    candidate that most lowers the score, if any does (greedy forward selection cannot undo
    an early pick that later ones made redundant).

    Args:
        score: marker ids (k,) -> error to minimise (mm).
        modes: (K, 3 n) singular-value-scaled PCA modes; a position's shortlist is the
            ``shortlist`` eligible candidates with the largest QR residual after projecting
            out the other markers.
        candidates: (c,) int 0-based allowed ids.
        markers: (k,) int the set to refine (e.g. a greedy path's first k).
        shortlist: candidates scored per position.
        points: (n, 3) mm, needed when ``min_distance > 0``.
        min_distance: markers stay farther apart than this (mm).
        rounds: passes over all positions (stops early when a pass changes nothing).
        keep: the first ``keep`` markers are never exchanged.

    Returns:
        ``(markers (k,) int64, score, number of scores computed)``; a replacement keeps its
        position in the list, and only a score lower by a relative 1e-4 is taken.
    """
    cand = np.asarray(candidates, dtype=np.int64)
    pts = None if points is None else np.asarray(points, dtype=np.float64)
    _check(len(markers), cand, min_distance, pts)
    A = np.asarray(modes, dtype=np.float64).reshape(len(modes), -1, 3)
    chosen = [int(v) for v in markers]
    best, n_scores = float(score(np.asarray(chosen, dtype=np.int64))), 1
    for _ in range(rounds):
        changed = False
        for pos in range(keep, len(chosen)):
            others = chosen[:pos] + chosen[pos + 1:]
            qr = _BlockQR(A, cand)
            for v in others:
                qr.add(A[:, v, :])
            ok = _eligible(pts, cand, others, min_distance) & ~np.isin(cand, chosen)
            order = np.argsort(-np.where(ok, qr.score, -np.inf), kind="stable")[: min(shortlist, int(ok.sum()))]
            for i in order:
                trial = chosen[:pos] + [int(cand[i])] + chosen[pos + 1:]
                s = float(score(np.asarray(trial, dtype=np.int64)))
                n_scores += 1
                if s < best * (1.0 - EXCHANGE_RTOL):
                    best, chosen, changed = s, trial, True
        if not changed:
            break
    return np.asarray(chosen, dtype=np.int64), best, n_scores
