"""Out-of-distribution scores of a marker input, from what is observable during surgery.

Two scores per input d (n_d, 3) mm:

- **distance** from the training inputs: the mean Euclidean distance to the ``k`` nearest
  training inputs after whitening (the training inputs' principal axes scaled to unit
  variance, axes with less than a small share of the largest variance floored). Large for
  deformations the simulations never produced (loads beyond the trained magnitude, other
  force patterns).
- **consistency** of the markers with each other: each marker's displacement is predicted
  from the other markers' by a quadratic ridge regression fitted on the training inputs
  (:mod:`tissuecast.surrogate.quadratic`: where the field the others imply puts that
  marker); the score is the Mahalanobis distance of the vector of all markers' residuals
  under its validation mean and covariance. Large for a swapped marker, a tracking
  glitch, a marker that moved in the tissue.

The two scores, each divided by its median on validation samples, are combined by their
maximum; the alarm threshold is the split-conformal ``1 - alpha`` quantile of that combined
score on a calibration split, so a clean input (exchangeable with the calibration samples)
raises an alarm with probability at most alpha (:class:`OODScores`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ModelError
from .conformal import conformal_quantile
from .quadratic import fit_quadratic

__all__ = ["InputDistance", "MarkerConsistency", "OODScores", "fit_input_distance", "fit_marker_consistency",
           "calibrate_ood", "SCORE_NAMES"]

SCORE_NAMES = ("distance", "consistency")

# Whitening floors each axis's variance at this share of the largest, so that directions
# the training inputs never vary along (to round-off) do not dominate the distance.
_VARIANCE_FLOOR = 1e-4
#: Neighbours averaged by the distance score.
NEIGHBOURS = 5
# Round-off floors: the residuals' mean variance (mm^2; all-zero residuals of a rigid set-up),
# a marker's residual scale as a share of the largest, and a score's median (a dimensionless
# score that is 0 on every validation input), so that nothing is divided by 0.
_TINY_VARIANCE = 1e-18
_SCALE_FLOOR_REL = 1e-9
_TINY_SCORE = 1e-12


@dataclass(frozen=True, eq=False)
class InputDistance:
    """Whitened k-nearest-neighbour distance to the training inputs.

    Attributes:
        mean: (3 n_d,) training input mean, mm.
        whitening: (3 n_d, 3 n_d) map of centred inputs to whitened coordinates, 1/mm.
        reference: (N_t, 3 n_d) whitened training inputs.
        neighbours: k.
    """

    mean: np.ndarray
    whitening: np.ndarray
    reference: np.ndarray
    neighbours: int = NEIGHBOURS

    def __post_init__(self):
        object.__setattr__(self, "_tree", cKDTree(self.reference))

    def __call__(self, X) -> np.ndarray:
        """(B,) scores of inputs (B, 3 n_d) mm (dimensionless)."""
        Z = (np.asarray(X, dtype=np.float64) - self.mean) @ self.whitening
        k = min(self.neighbours, len(self.reference))
        dist, _ = self._tree.query(Z, k=k)
        return dist.reshape(len(Z), -1).mean(axis=1)


def fit_input_distance(X, neighbours: int = NEIGHBOURS) -> InputDistance:
    """Fit on training inputs (N_t, 3 n_d) mm."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or len(X) < 2:
        raise ModelError(f"need (N, 3 n_d) training inputs with N >= 2, got {X.shape}")
    mean = X.mean(axis=0)
    _, s, vt = np.linalg.svd(X - mean, full_matrices=False)
    var = s**2 / (len(X) - 1)
    var = np.maximum(var, _VARIANCE_FLOOR * var.max())
    W = vt.T / np.sqrt(var)
    if W.shape[1] < X.shape[1]:  # fewer samples than dimensions
        W = np.hstack([W, np.zeros((X.shape[1], X.shape[1] - W.shape[1]))])
    return InputDistance(mean, W, (X - mean) @ W, int(neighbours))


@dataclass(frozen=True, eq=False)
class MarkerConsistency:
    """Leave-one-marker-out predictions of each marker's displacement.

    The score of an input is the Mahalanobis distance of its residual vector (every
    marker's predicted minus observed displacement, 3 n_d numbers) under the residuals'
    mean and covariance on validation samples: residuals of different markers are
    correlated (a marker is an input to the others' predictions), which the distance uses.

    Attributes:
        regressions: n_d maps from the other markers' (3 n_d - 3) displacements to this
            marker's (3,), mm.
        scale: (n_d,) root-mean-square residual distance of each marker on validation samples, mm.
        mean: (3 n_d,) mean validation residual vector, mm.
        precision: (3 n_d, 3 n_d) inverse of the (shrunk) validation residual covariance, 1/mm^2.
    """

    regressions: tuple
    scale: np.ndarray
    mean: np.ndarray
    precision: np.ndarray

    def residual_vectors(self, X) -> np.ndarray:
        """(B, 3 n_d) predicted minus observed displacement of every marker, mm."""
        X = np.asarray(X, dtype=np.float64)
        out = np.empty_like(X)
        for j, reg in enumerate(self.regressions):
            cols = np.s_[3 * j:3 * j + 3]
            out[:, cols] = reg.predict(np.delete(X, cols, axis=1)) - X[:, cols]
        return out

    def residuals(self, X) -> np.ndarray:
        """(B, n_d) distance (mm) of each marker from where the other markers put it."""
        R = self.residual_vectors(X)
        return np.linalg.norm(R.reshape(len(R), -1, 3), axis=2)

    def __call__(self, X) -> np.ndarray:
        """(B,) Mahalanobis distance of the residual vectors (dimensionless)."""
        return _mahalanobis(self.residual_vectors(X) - self.mean, self.precision)


def _mahalanobis(R: np.ndarray, precision: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.einsum("bi,ij,bj->b", R, precision, R), 0.0))


def fit_marker_consistency(X_train, X_valid) -> MarkerConsistency | None:
    """Fit on training inputs (N_t, 3 n_d) mm, residual statistics on validation inputs; None for n_d < 2.

    The covariance is shrunk towards its mean variance with weight ``p / (p + N_v)``
    (p = 3 n_d), so that it stays invertible with few validation samples.
    """
    X_train = np.asarray(X_train, dtype=np.float64)
    X_valid = np.asarray(X_valid, dtype=np.float64)
    n_d = X_train.shape[1] // 3
    if n_d < 2:
        return None
    regs = []
    for j in range(n_d):
        cols = np.s_[3 * j:3 * j + 3]
        regs.append(fit_quadratic(np.delete(X_train, cols, axis=1), X_train[:, cols]))
    p = 3 * n_d
    draft = MarkerConsistency(tuple(regs), np.ones(n_d), np.zeros(p), np.eye(p))
    R = draft.residual_vectors(X_valid)
    mean = R.mean(axis=0)
    cov = np.cov(R, rowvar=False).reshape(p, p) if len(R) > 1 else np.zeros((p, p))
    avg = max(float(np.trace(cov)) / p, _TINY_VARIANCE)
    shrink = p / (p + len(R))
    cov = (1.0 - shrink) * cov + shrink * avg * np.eye(p)
    dist = np.linalg.norm(R.reshape(len(R), -1, 3), axis=2)
    scale = np.sqrt((dist**2).mean(axis=0))
    return MarkerConsistency(tuple(regs), np.maximum(scale, _SCALE_FLOOR_REL * max(float(scale.max()), 1e-300)), mean,
                             np.linalg.inv(cov))


@dataclass(frozen=True, eq=False)
class OODScores:
    """The two scores, combined into one alarm score with a calibrated threshold.

    The alarm score of an input is ``max(distance / scale[0], consistency / scale[1])``
    (scales: the scores' medians on validation samples); its threshold for a false-alarm
    rate alpha is the split-conformal ``1 - alpha`` quantile of the calibration samples'
    alarm scores, so each score's own threshold is that value times its scale.

    Attributes:
        distance: the :class:`InputDistance`.
        consistency: the :class:`MarkerConsistency` (None with one marker).
        scale: (2,) validation medians of the two scores (consistency's 1 when absent).
        calibration: (m,) sorted alarm scores of the calibration samples.
    """

    distance: InputDistance
    consistency: MarkerConsistency | None
    scale: np.ndarray
    calibration: np.ndarray

    def scores(self, X) -> np.ndarray:
        """(B, 2) [distance, consistency] scores of inputs (B, 3 n_d) mm (consistency NaN if absent)."""
        X = np.asarray(X, dtype=np.float64)
        c = self.consistency(X) if self.consistency is not None else np.full(len(X), np.nan)
        return np.stack([self.distance(X), c], axis=1)

    def combined(self, scores) -> np.ndarray:
        """(B,) alarm scores from (B, 2) scores."""
        s = np.asarray(scores, dtype=np.float64) / self.scale
        return np.nanmax(s, axis=1) if self.consistency is not None else s[:, 0]

    def threshold(self, false_alarm: float) -> float:
        """Alarm-score threshold for a false-alarm rate in (0, 1) (inf with too few calibration samples)."""
        if not 0.0 < false_alarm < 1.0:
            raise ModelError(f"the false-alarm rate must be in (0, 1), got {false_alarm}")
        return float(conformal_quantile(self.calibration, 1.0 - false_alarm))

    def thresholds(self, false_alarm: float) -> np.ndarray:
        """(2,) thresholds of the distance and consistency scores (inf for an absent score)."""
        t = self.threshold(false_alarm) * self.scale
        return t if self.consistency is not None else np.array([t[0], np.inf])

    def p_values(self, scores) -> np.ndarray:
        """(B,) conformal p-values ``(1 + #{calibration >= alarm score}) / (m + 1)``."""
        c = self.combined(scores)
        m = len(self.calibration)
        return (1.0 + m - np.searchsorted(self.calibration, c, side="left")) / (m + 1.0)


def calibrate_ood(distance: InputDistance, consistency: MarkerConsistency | None, X_valid, X_calibration) -> OODScores:
    """Scales from validation inputs (B_v, 3 n_d) mm, calibration scores from (B_c, 3 n_d) mm."""
    draft = OODScores(distance, consistency, np.ones(2), np.zeros(0))
    sv = draft.scores(X_valid)
    scale = np.array([np.median(sv[:, 0]), np.median(sv[:, 1]) if consistency is not None else 1.0])
    scale = np.maximum(scale, _TINY_SCORE)
    ood = OODScores(distance, consistency, scale, np.zeros(0))
    return OODScores(distance, consistency, scale, np.sort(ood.combined(ood.scores(X_calibration))))
