"""Out-of-distribution scores of a marker input, from what is observable during surgery.

Five scores per input d (n_d, 3) mm (for a model with auxiliary inputs a, :mod:`.auxiliary`,
the input is x = [d, a]: the distance is taken over all of it, and every marker is predicted
from the other markers and a, so an instrument pose that disagrees with the markers shows):

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
- **fault** of one marker: the same residuals tested for a bias on a single marker (the
  generalised likelihood ratio of parity-space fault detection). A bias b (3,) on marker j
  changes the residual vector by ``F_j b`` (``F_j`` (3 n_d, 3): -1 on marker j's own
  residual, the sensitivities of the other markers' predictions to it, taken at the
  training mean); the statistic of marker j is the Mahalanobis length of the best-fitting
  ``F_j b``, ``sqrt(r' L F_j (F_j' L F_j)^-1 F_j' L r)`` (L the precision), and the score is
  its maximum over the markers. It looks along 3 directions instead of 3 n_d, so one
  displaced marker among many stands out of the scatter sooner; its argmax names the marker.

- **stillness** of one marker: each marker's displacement as a share of the markers' root-mean-
  square displacement, against the smallest share any training input gave it; the score is the
  largest ratio of that least share to the input's share, over the markers (a marker that some
  simulation held still has a least share of 0 and never scores). Large for a marker that
  stands still while every simulation moved it: the tissue held there (attached farther than
  simulated, a marker planned beyond the attached region's drawn range watches for it:
  :mod:`tissuecast.planning.sentinel`), or a marker lost from the tissue and tracked on a fixed
  frame. The whitened distance and the markers' regressions read one still marker among many
  as a modest change; this score reads it as what it is.
- **swap** of two markers: each pair of markers is exchanged in turn (marker i placed where j
  was tracked and j where i was) and each exchanged input scored by the markers' consistency;
  the score is the input's consistency score over the smallest of theirs, and its argmin names
  the pair. Above 1, exchanging two markers makes the markers agree better: mislabelled or
  swapped markers. The consistency and distance scores see a swap as disagreement or distance
  only where it is larger than what the simulations' range allows; on a store with the
  parameters drawn (wide ranges) many swaps pass them, and this score compares the input with
  its own exchanged versions instead.

The scores the alarm uses (distance, consistency and stillness; the fault score too where
asked, else it only names the suspect marker), each divided by its median on validation
samples, are combined by their maximum; the alarm threshold is the split-conformal ``1 - alpha`` quantile
of that combined score on a calibration split, so a clean input (exchangeable with the
calibration samples) raises that alarm with probability at most alpha (:class:`OODScores`).
The swap score raises the alarm by itself above :data:`SWAP_RATIO`, a fixed level, and adds its
own false-alarm rate (measured, not bounded by alpha); it is off wherever the conformal alarm is
(too few calibration samples for the rate asked). On clean
input it stays near its median (a few tenths: any exchange makes the markers agree worse),
and a score scaled by that median would move with every change of the consistency score
(a slipped marker raises the input's own score, not the exchanged ones' less), which it must
not be read as.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError, require
from .conformal import conformal_quantile
from .quadratic import fit_quadratic

__all__ = ["InputDistance", "MarkerConsistency", "MarkerStillness", "MarkerSwap", "OODScores", "fit_input_distance",
           "fit_marker_consistency", "fit_marker_stillness", "scale_ood", "calibrate_ood", "SCORE_NAMES", "SWAP_RATIO"]

SCORE_NAMES = ("distance", "consistency", "fault", "stillness", "swap")
#: Swap score above which two markers count as exchanged: exchanged back, the markers'
#: consistency score falls at least this many times.
SWAP_RATIO = 2.0

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
#: Markers' root-mean-square displacement (mm) below which an input has no stillness score (0):
#: nothing moved, so no marker stands out by standing still.
STILL_RMS_MM = 1e-6
# Exchanged inputs scored at once by the swap score.
_SWAP_CHUNK = 4096
# Distances held at once by the input distance (a (chunk, N_t) array: 16 MB of float64).
_DISTANCE_ELEMENTS = 2**21
# Inputs up to this batch size have their distance remembered (the last call's, :class:`InputDistance`).
_REMEMBERED_BATCH = 16
# A marker's share below this counts as this (a still marker's score is finite: 1e12 times its least share).
_TINY_SHARE = 1e-12


@dataclass(frozen=True, eq=False)
class InputDistance:
    """Whitened k-nearest-neighbour distance to the training inputs.

    The neighbours are found by brute force (in the 30-40 dimensions of 10 markers and an
    instrument a k-d tree visits most of its nodes anyway, and one matrix product is faster):
    the squared distances to every reference as ``|r|^2 - 2 z.r + |z|^2``, in chunks of inputs
    (``_DISTANCE_ELEMENTS`` distances at once), the k smallest picked and their distances
    recomputed exactly. The last small batch's scores are remembered (its bytes): a served frame
    asks for them more than once (the expert gate, the bounds, the alarm sent after the field).

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
        ref = np.ascontiguousarray(self.reference, dtype=np.float64)
        object.__setattr__(self, "_ref", ref)
        object.__setattr__(self, "_ref_t", np.ascontiguousarray(ref.T))
        object.__setattr__(self, "_ref_sq", np.einsum("ij,ij->i", ref, ref))
        object.__setattr__(self, "_last", None)  # (input's shape and bytes, its scores) of the last small batch

    def __call__(self, X) -> np.ndarray:
        """(B,) scores of inputs (B, 3 n_d) mm (dimensionless)."""
        X = np.asarray(X, dtype=np.float64)
        key = (X.shape, X.tobytes()) if len(X) <= _REMEMBERED_BATCH else None
        last = self._last
        if key is not None and last is not None and last[0] == key:
            return last[1].copy()
        out = self._scores(X)
        if key is not None:
            object.__setattr__(self, "_last", (key, out.copy()))
        return out

    def _scores(self, X: np.ndarray) -> np.ndarray:
        Z = (X - self.mean) @ self.whitening
        k = min(self.neighbours, len(self._ref))
        out = np.empty(len(Z))
        chunk = max(1, _DISTANCE_ELEMENTS // len(self._ref))
        for s in range(0, len(Z), chunk):
            z = Z[s:s + chunk]
            sq = self._ref_sq - 2.0 * (z @ self._ref_t)  # (b, N_t): squared distances less |z|^2
            near = np.argpartition(sq, k - 1, axis=1)[:, :k] if k < sq.shape[1] else np.broadcast_to(
                np.arange(k), sq.shape)
            diff = z[:, None, :] - self._ref[near]
            out[s:s + chunk] = np.sqrt(np.einsum("bkd,bkd->bk", diff, diff)).mean(axis=1)
        return out

    def torch_module(self):
        """The score as a torch module (float32): inputs (B, 3 n_d [+ n_a]) mm -> (B,) scores, the
        neighbours found as :meth:`__call__` finds them (all references at once, then their
        distances recomputed); exportable to ONNX (TopK, Gather)."""
        torch = require("torch", "learn", "the torch/ONNX input distance")
        k = min(self.neighbours, len(self._ref))
        arrays = {"mean": self.mean, "whitening": self.whitening, "reference": self._ref, "reference_sq": self._ref_sq}

        class Distance(torch.nn.Module):
            def __init__(self):
                super().__init__()
                for name, v in arrays.items():
                    self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(v), dtype=torch.float32))

            def forward(self, x):
                z = (x - self.mean) @ self.whitening
                sq = self.reference_sq - 2.0 * (z @ self.reference.T)
                near = torch.topk(sq, k, dim=1, largest=False).indices
                diff = z.unsqueeze(1) - self.reference[near]
                return torch.sqrt((diff * diff).sum(dim=2)).mean(dim=1)

        return Distance().eval()


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
    :meth:`faults` tests the same residuals for a bias on one marker (module docstring).

    Attributes:
        regressions: n_d maps from the other markers' (3 n_d - 3) displacements (and the n_a
            auxiliary inputs after them) to this marker's (3,), mm.
        scale: (n_d,) root-mean-square residual distance of each marker on validation samples, mm.
        mean: (3 n_d,) mean validation residual vector, mm.
        precision: (3 n_d, 3 n_d) inverse of the (shrunk) validation residual covariance, 1/mm^2.
        sensitivity: (n_d, 3 n_d, 3) change of the residual vector per mm of bias on each
            marker (dimensionless; ``F_j``), or None (trust files written before it: no
            fault score).
    """

    regressions: tuple
    scale: np.ndarray
    mean: np.ndarray
    precision: np.ndarray
    sensitivity: np.ndarray | None = None

    def __post_init__(self):
        n_in = len(self.regressions[0].mean) + 3 if self.regressions else 0  # 3 n_d + n_a
        object.__setattr__(self, "_others", np.array([np.delete(np.arange(n_in), np.s_[3 * j:3 * j + 3])
                                                      for j in range(len(self.regressions))], dtype=np.int64))
        object.__setattr__(self, "_stacked", _stack_regressions(self.regressions))
        if self.sensitivity is not None:  # per marker: L F_j (3 n_d, 3) and (F_j' L F_j)^-1 (3, 3)
            LF = np.einsum("pq,jqa->jpa", self.precision, self.sensitivity)
            gram = np.einsum("jpa,jpb->jab", self.sensitivity, LF)
            # L F_j side by side, (3 n_d, 3 n_d): r' L F_j for every j in one product
            object.__setattr__(self, "_fault_maps", (np.ascontiguousarray(LF.transpose(1, 0, 2).reshape(LF.shape[1], -1)),
                                                     np.linalg.inv(gram)))

    def residual_vectors(self, X) -> np.ndarray:
        """(B, 3 n_d) predicted minus observed displacement of every marker, mm, from inputs
        X (B, 3 n_d + n_a)."""
        X = np.asarray(X, dtype=np.float64)
        n_d, B = len(self.regressions), len(X)
        # every marker's regression at once (QuadraticRegression.predict, stacked and folded:
        # markers as the batch of the products)
        linear, offset, quadratic = self._stacked
        q = quadratic.shape[1]
        L = X[:, self._others].transpose(1, 0, 2) @ linear  # (n_d, B, q + 3): projections, linear part
        L += offset[:, None, :]
        P = L[..., :q]
        y = L[..., q:] + np.einsum("jbka,jba->jbk", (P @ quadratic).reshape(n_d, B, 3, q), P)  # (n_d, B, 3)
        return (y.transpose(1, 0, 2) - X[:, :3 * n_d].reshape(B, n_d, 3)).reshape(B, -1)

    def residuals(self, X) -> np.ndarray:
        """(B, n_d) distance (mm) of each marker from where the other markers put it."""
        return self.evaluate(X)[0]

    def __call__(self, X) -> np.ndarray:
        """(B,) Mahalanobis distance of the residual vectors (dimensionless)."""
        return _mahalanobis(self.residual_vectors(X) - self.mean, self.precision)

    def faults(self, X) -> np.ndarray | None:
        """(B, n_d) single-marker fault statistic of each marker (dimensionless), or None
        without :attr:`sensitivity`."""
        return self.evaluate(X)[2]

    def evaluate(self, X) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """:meth:`residuals`, the score (``__call__``) and :meth:`faults` of inputs (B, 3 n_d)
        mm, from one evaluation of the regressions."""
        R = self.residual_vectors(X)
        dist = np.linalg.norm(R.reshape(len(R), -1, 3), axis=2)
        R -= self.mean
        faults = None
        if self.sensitivity is not None:
            LF, inv_gram = self._fault_maps
            v = (R @ LF).reshape(len(R), -1, 3)  # F_j' L r, (B, n_d, 3)
            faults = np.sqrt(np.maximum((np.einsum("bja,jac->bjc", v, inv_gram) * v).sum(axis=2), 0.0))
        return dist, _mahalanobis(R, self.precision), faults


def _stack_regressions(regressions) -> tuple:
    """The markers' regressions as stacked arrays with their standardisation folded in:
    ``(linear (n_d, d, q + 3), offset (n_d, q + 3), quadratic (n_d, q, 3 q))``. For marker j's
    inputs x (d,), ``x @ linear[j] + offset[j]`` is ``[p, c_0 + z @ c_1]`` (p the projections on
    its q directions, z the standardised inputs) and output k's products' term is
    ``sum_a p_a (p @ quadratic[j])[k q + a]`` (each coefficient of p_a p_b, a < b, split evenly
    between (a, b) and (b, a)). They are of one size: each is fitted on the same inputs less one marker's 3 columns
    (:func:`fit_marker_consistency`)."""
    d, q = len(regressions[0].mean), len(regressions[0].directions)
    a, b = np.triu_indices(q)
    linear, offset, quadratic = [], [], []
    for r in regressions:
        scaled = np.hstack([r.directions.T, r.coef[1:1 + d]]) / r.scale[:, None]  # (d, q + 3) on raw inputs
        linear.append(scaled)
        offset.append(np.concatenate([np.zeros(q), r.coef[0]]) - r.mean @ scaled)
        m = np.zeros((q, q, 3))
        c = r.coef[1 + d:]  # (Q, 3), the products p_a p_b in triu order
        np.add.at(m, (a, b), np.where((a == b)[:, None], c, c / 2.0))
        np.add.at(m, (b[a != b], a[a != b]), c[a != b] / 2.0)
        quadratic.append(m.transpose(1, 2, 0).reshape(q, 3 * q))  # row b, columns (output, a)
    return np.stack(linear), np.stack(offset), np.stack(quadratic)


def _mahalanobis(R: np.ndarray, precision: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(((R @ precision) * R).sum(axis=1), 0.0))


def fit_marker_consistency(X_train, X_valid, n_auxiliary: int = 0) -> MarkerConsistency | None:
    """Fit on training inputs (N_t, 3 n_d + n_a) (mm, then the n_a auxiliary inputs), residual
    statistics on validation inputs; None for n_d < 2.

    The covariance is shrunk towards its mean variance with weight ``p / (p + N_v)``
    (p = 3 n_d), so that it stays invertible with few validation samples.
    """
    X_train = np.asarray(X_train, dtype=np.float64)
    X_valid = np.asarray(X_valid, dtype=np.float64)
    n_d = (X_train.shape[1] - n_auxiliary) // 3
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
    # F_j by central differences at the training mean (exact for the quadratic regressions),
    # moving one marker coordinate at a time
    center = X_train.mean(axis=0)
    unit = np.eye(p, X_train.shape[1])
    steps = np.concatenate([center + unit, center - unit])
    diff = draft.residual_vectors(steps)
    sensitivity = ((diff[:p] - diff[p:]) / 2.0).reshape(n_d, 3, p).transpose(0, 2, 1)
    return MarkerConsistency(tuple(regs), np.maximum(scale, _SCALE_FLOOR_REL * max(float(scale.max()), 1e-300)), mean,
                             np.linalg.inv(cov), sensitivity)


@dataclass(frozen=True, eq=False)
class MarkerStillness:
    """The least share of the markers' motion each marker took in any training input.

    Attributes:
        least: (n_d,) smallest ``|d_j| / rms_k |d_k|`` over the training inputs (dimensionless;
            0 for a marker some simulation held still).
    """

    least: np.ndarray

    def shares(self, X) -> np.ndarray:
        """(B, n_d) each marker's displacement over the markers' root-mean-square displacement
        of inputs (B, 3 n_d + n_a) mm (the auxiliary inputs after the markers are not read);
        NaN where the markers did not move (:data:`STILL_RMS_MM`)."""
        X = np.asarray(X, dtype=np.float64)
        n = np.linalg.norm(X[:, :3 * len(self.least)].reshape(len(X), -1, 3), axis=2)
        rms = np.sqrt((n**2).mean(axis=1, keepdims=True))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(rms > STILL_RMS_MM, n / rms, np.nan)

    def ratios(self, X) -> np.ndarray:
        """(B, n_d) each marker's least share over its share in inputs (B, 3 n_d + n_a) mm: above
        1, the marker moved less, relative to the others, than in any training input (0 where
        nothing moved)."""
        return self.evaluate(X)[1]

    def evaluate(self, X) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`shares` and :meth:`ratios` of inputs (B, 3 n_d + n_a) mm, from one evaluation."""
        s = self.shares(X)
        r = self.least / np.maximum(s, _TINY_SHARE)
        return s, np.where(np.isnan(s), 0.0, r)

    def __call__(self, X) -> np.ndarray:
        """(B,) the largest ratio over the markers (dimensionless)."""
        return self.ratios(X).max(axis=1)


def fit_marker_stillness(X_train, n_auxiliary: int = 0) -> MarkerStillness:
    """Fit on training inputs (N_t, 3 n_d + n_a) (mm, then the n_a auxiliary inputs); inputs
    where no marker moved are left out."""
    X = np.asarray(X_train, dtype=np.float64)
    n_d = (X.shape[1] - n_auxiliary) // 3
    s = MarkerStillness(np.zeros(n_d)).shares(X)
    s = s[~np.isnan(s).any(axis=1)]
    return MarkerStillness(s.min(axis=0) if len(s) else np.zeros(n_d))


@dataclass(frozen=True, eq=False)
class MarkerSwap:
    """Whether two markers' tracked positions look exchanged (module notes).

    Attributes:
        reference: (n_d, 3) reference (undeformed) marker positions, mm, in input order.
        pairs: (P, 2) int64 the pairs exchanged, ``(i, j)`` with i < j in ``itertools.combinations``
            order (set from ``reference``; P = n_d (n_d - 1) / 2).
    """

    reference: np.ndarray

    def __post_init__(self):
        n = len(self.reference)
        object.__setattr__(self, "reference", np.asarray(self.reference, dtype=np.float64).reshape(n, 3))
        object.__setattr__(self, "pairs", np.array(list(itertools.combinations(range(n), 2)),
                                                   dtype=np.int64).reshape(-1, 2))

    def exchanged(self, X) -> np.ndarray:
        """(B, P, 3 n_d + n_a) inputs X (B, 3 n_d + n_a) mm (the auxiliary inputs after the
        markers, unchanged) with the P pairs of markers (:attr:`pairs`, ``itertools.combinations``
        order) exchanged in turn: ``d_i' = r_j + d_j - r_i`` and ``d_j' = r_i + d_i - r_j``."""
        X = np.asarray(X, dtype=np.float64)
        B, n_d, P = len(X), len(self.reference), len(self.pairs)
        d = X[:, :3 * n_d].reshape(B, n_d, 3)
        pos = d + self.reference  # tracked positions
        i, j, p = self.pairs[:, 0], self.pairs[:, 1], np.arange(P)
        out = np.repeat(d[:, None], P, axis=1)  # (B, P, n_d, 3)
        out[:, p, i] = pos[:, j] - self.reference[i]
        out[:, p, j] = pos[:, i] - self.reference[j]
        out = out.reshape(B, P, 3 * n_d)
        if X.shape[1] > 3 * n_d:
            out = np.concatenate([out, np.repeat(X[:, None, 3 * n_d:], P, axis=1)], axis=2)
        return out

    def evaluate(self, X, consistency: MarkerConsistency, own=None) -> tuple[np.ndarray, np.ndarray]:
        """``(scores (B,), pair (B,))`` of inputs X (B, 3 n_d + n_a) mm: each input's
        consistency score (``own`` (B,) where already known) over the smallest of its exchanged
        inputs' (dimensionless), and the index into :attr:`pairs` of that exchange (-1 with
        fewer than two markers: score 0)."""
        X = np.asarray(X, dtype=np.float64)
        B, P = len(X), len(self.pairs)
        if P == 0 or B == 0:
            return np.zeros(B), np.full(B, -1, dtype=np.int64)
        c = consistency(X) if own is None else np.asarray(own, dtype=np.float64)
        step = max(1, _SWAP_CHUNK // P)  # inputs exchanged at once (bounds the memory of a long batch)
        ce = np.concatenate([consistency(self.exchanged(X[k:k + step]).reshape(-1, X.shape[1])).reshape(-1, P)
                             for k in range(0, B, step)])
        best = ce.argmin(axis=1)
        return c / np.maximum(ce[np.arange(B), best], _TINY_SCORE), best

    def __call__(self, X, consistency: MarkerConsistency) -> np.ndarray:
        """(B,) the swap scores of inputs (B, 3 n_d + n_a) mm (:meth:`evaluate`)."""
        return self.evaluate(X, consistency)[0]


@dataclass(frozen=True, eq=False)
class OODScores:
    """The scores, combined into one alarm score with a calibrated threshold.

    The alarm score of an input is ``max(distance / scale[0], consistency / scale[1],
    stillness / scale[3])``, and with ``use_fault`` also ``fault / scale[2]`` (scales: the
    scores' medians on validation samples; an absent score is left out); its threshold for a false-alarm rate alpha is the
    split-conformal ``1 - alpha`` quantile of the calibration samples' alarm scores, so each
    score's own threshold is that value times its scale. The swap score is not part of it: its
    threshold is :data:`SWAP_RATIO` (module notes) and its scale 1.

    Attributes:
        distance: the :class:`InputDistance`.
        consistency: the :class:`MarkerConsistency` (None with one marker; then no
            consistency and no fault score).
        scale: (5,) validation medians of the scores (1 for an absent one and for the swap score; trust files
            written before the fault, the stillness or the swap score hold two to four, and get 1s).
        calibration: (m,) sorted alarm scores of the calibration samples (empty: not calibrated,
            every threshold infinite).
        use_fault: the fault score is part of the alarm score (``surrogate.alarm_fault_score``).
        stillness: the :class:`MarkerStillness` (None in trust files written before it: no
            stillness score).
        swap: the :class:`MarkerSwap` (None in trust files written before it, or without a
            consistency score: no swap score).
    """

    distance: InputDistance
    consistency: MarkerConsistency | None
    scale: np.ndarray
    calibration: np.ndarray
    use_fault: bool = False
    stillness: MarkerStillness | None = None
    swap: MarkerSwap | None = None

    def __post_init__(self):
        scale = np.asarray(self.scale, dtype=np.float64)
        object.__setattr__(self, "scale", np.concatenate([scale, np.ones(len(SCORE_NAMES) - len(scale))]))

    @property
    def has_swap(self) -> bool:
        """Whether the swap score is present (it needs the consistency score)."""
        return self.swap is not None and self.consistency is not None

    def scores(self, X) -> np.ndarray:
        """(B, 5) [distance, consistency, fault, stillness, swap] scores of inputs (B, 3 n_d) mm (NaN where absent)."""
        X = np.asarray(X, dtype=np.float64)
        out = np.full((len(X), len(SCORE_NAMES)), np.nan)
        out[:, 0] = self.distance(X)
        if self.consistency is not None:
            _, out[:, 1], faults = self.consistency.evaluate(X)
            if faults is not None:
                out[:, 2] = faults.max(axis=1)
        if self.stillness is not None:
            out[:, 3] = self.stillness(X)
        if self.has_swap:
            out[:, 4] = self.swap.evaluate(X, self.consistency, own=out[:, 1])[0]
        return out

    def combined(self, scores) -> np.ndarray:
        """(B,) alarm scores from (B, 5) scores (absent scores NaN; the (B, 3) or (B, 4) scores of
        trust files written before the stillness or the swap score read them as absent)."""
        s = np.asarray(scores, dtype=np.float64)
        if s.shape[1] < len(SCORE_NAMES):
            s = np.hstack([s, np.full((len(s), len(SCORE_NAMES) - s.shape[1]), np.nan)])
        s = s / self.scale
        used = [True, True, self.use_fault, True, False]
        return np.nanmax(s[:, used], axis=1)

    def threshold(self, false_alarm: float) -> float:
        """Alarm-score threshold for a false-alarm rate in (0, 1) (inf with too few calibration samples)."""
        if not 0.0 < false_alarm < 1.0:
            raise ModelError(f"the false-alarm rate must be in (0, 1), got {false_alarm}")
        return float(conformal_quantile(self.calibration, 1.0 - false_alarm))

    def thresholds(self, false_alarm: float) -> np.ndarray:
        """(5,) thresholds of the distance, consistency, fault, stillness and swap scores (inf
        for a score that is absent or not part of the alarm)."""
        t = self.threshold(false_alarm) * self.scale
        # an alarm that is off (too few calibration samples for the rate) is off for swaps too
        t[4] = SWAP_RATIO if np.isfinite(t[0]) else np.inf
        present = [True, self.consistency is not None,
                   self.use_fault and self.consistency is not None and self.consistency.sensitivity is not None,
                   self.stillness is not None, self.has_swap]
        return np.where(present, t, np.inf)

    def calibrated(self, X_calibration) -> "OODScores":
        """These scores with the alarm threshold calibrated on inputs (B_c, 3 n_d) mm that the
        alarm should pass (exchangeable with clean inputs): their sorted alarm scores."""
        return dataclasses.replace(self, calibration=np.sort(self.combined(self.scores(X_calibration))))

    def rescaled(self, scores) -> "OODScores":
        """These scores (not calibrated) with their scales the medians of (B, 5) raw scores
        (:meth:`scores` of inputs like the clean ones: out-of-fold training inputs)."""
        return dataclasses.replace(self, scale=_medians(scores), calibration=np.zeros(0))

    def p_values(self, scores) -> np.ndarray:
        """(B,) conformal p-values ``(1 + #{calibration >= alarm score}) / (m + 1)``."""
        c = self.combined(scores)
        m = len(self.calibration)
        return (1.0 + m - np.searchsorted(self.calibration, c, side="left")) / (m + 1.0)


def _medians(scores) -> np.ndarray:
    """(5,) the scores' medians over inputs (B, 5) (floored; 1 for an absent score and for the
    swap score, whose threshold is fixed)."""
    sv = np.asarray(scores, dtype=np.float64)
    out = np.where(np.isnan(sv[0]), 1.0, np.maximum(np.median(sv, axis=0), _TINY_SCORE))
    out[4:] = 1.0
    return out


def scale_ood(distance: InputDistance, consistency: MarkerConsistency | None, X_valid,
              use_fault: bool = False, stillness: MarkerStillness | None = None,
              swap: MarkerSwap | None = None) -> OODScores:
    """Uncalibrated scores (no threshold yet: :meth:`OODScores.calibrated` sets it), their scales
    the medians on validation inputs (B_v, 3 n_d) mm; ``use_fault``: the fault score is part of the alarm."""
    draft = OODScores(distance, consistency, np.ones(len(SCORE_NAMES)), np.zeros(0), use_fault, stillness, swap)
    return draft.rescaled(draft.scores(X_valid))


def calibrate_ood(distance: InputDistance, consistency: MarkerConsistency | None, X_valid, X_calibration,
                  use_fault: bool = False, stillness: MarkerStillness | None = None,
                  swap: MarkerSwap | None = None) -> OODScores:
    """Scales from validation inputs (B_v, 3 n_d) mm, calibration scores from (B_c, 3 n_d) mm;
    ``use_fault``: the fault score is part of the alarm."""
    return scale_ood(distance, consistency, X_valid, use_fault, stillness, swap).calibrated(X_calibration)
