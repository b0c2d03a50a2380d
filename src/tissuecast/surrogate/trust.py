"""Trust in a prediction: per-vertex error bounds with guaranteed coverage and an
out-of-distribution alarm (the :class:`TrustLayer`, what ``trust.npz`` stores).

The layer is fitted in two steps (:mod:`.trust_fit`), for any field predictor:

- from **train** and **valid** samples (:func:`.trust_fit.fit_trust_layer`): a second predictor
  (quadratic ridge regression from the markers to 64 PCA weights, :mod:`.quadratic`; for a
  model with a quadratic head, :mod:`.head`, the head itself, so that the disagreement is the
  networks' correction of it), the input distance and the leave-one-marker-out consistency
  regressions (:mod:`.ood`), all on train; on valid, the learned error model, a linear
  regression of the log of each sample's Offset_max on log features of the input alone (the
  largest and mean disagreement between the predictor and the second predictor, how far the
  predicted field misses the markers it was given, the input distance, the peak marker
  displacement, and a regression of the error on the input learnt from out-of-fold errors on
  the training samples), the mean and covariance of the consistency residuals, and the medians
  that put the alarm's scores on one scale;
- **calibration** (:meth:`TrustLayer.calibrate`) from any (input, prediction, truth) triples
  the predictor was not trained on: the split-conformal scores of the bounds
  (:mod:`.conformal`) and of the alarm. Today these are samples held out from the training
  split (``surrogate.calibration = "split"``) or out-of-fold scores of the training split
  (``"cross-validation"``, :mod:`.cross_calibration`); a layer calibrated on nothing has infinite bounds
  and an alarm that never fires.

For a model with a quadratic head the normaliser is g alone (``flat``): the per-vertex conformal
quantiles then carry where a sample's errors are large, which measured better than the
networks' correction of the head did. Otherwise the normaliser of vertex i of a sample is
``g * (LAMBDA + h_i / max h) / (LAMBDA + 1)``: g the
error model's predicted Offset_max (ranks samples), h_i the disagreement of the two
predictors at the vertex (ranks vertices within a sample). Bounds are the normaliser times
the per-vertex conformal quantile. :class:`~.trusted.TrustedPredictor` wraps a predictor and
its layer.

For a predictor with auxiliary inputs (instrument poses, measured parameters: :mod:`.auxiliary`)
every part reads the input x = [d, a] (the second predictor, the input distance, the consistency
regressions, the input error regression; the markers' miss and peak read d), so the bounds and
the alarm see the instrument too; the methods take the auxiliary values as ``auxiliary=``.
"""

from __future__ import annotations

import logging
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..errors import ModelError
from .calibration_scores import CalibrationScores
from .conformal import VertexConformal, normalised_errors
from .ood import InputDistance, MarkerConsistency, MarkerStillness, MarkerSwap, OODScores
from .pca import PCABasis
from .quadratic import QuadraticRegression

__all__ = ["TrustLayer", "Alarm", "TrustedPrediction", "CalibrationScores", "FEATURE_NAMES", "FILE", "PREDICT_CHUNK"]

log = logging.getLogger(__name__)

FILE = "trust.npz"
FEATURE_NAMES = ("log_disagreement_max", "log_disagreement_mean", "log_marker_miss", "log_distance", "log_peak_marker")
#: Share of the flat part in the vertex normaliser: 0 would trust the disagreement map alone
#: (vertices where the two predictors happen to agree get tiny bounds), large values give
#: one bound scale for the whole sample.
LAMBDA = 0.25
#: Floor (mm) inside the logarithms of the error-model features.
LOG_FLOOR = 1e-6
#: Samples predicted or assessed at once while fitting and calibrating (bounds the memory to
#: chunk x n x 3 floats).
PREDICT_CHUNK = 256


@dataclass(frozen=True)
class Alarm:
    """The out-of-distribution verdict of one prediction.

    Attributes:
        raised: whether any score passed its threshold.
        distance: input-distance score; ``distance_threshold`` its alarm level.
        consistency: marker-consistency score (NaN with one marker); ``consistency_threshold``.
        marker: index (0-based, model marker order) of the marker whose bias best explains
            the markers' disagreement (the largest single-marker fault statistic; in trust
            files written before it, the marker farthest in units of its residual scale from
            where the others put it), -1 without a consistency score.
        marker_residual: that marker's distance from where the other markers put it, mm.
        fault: single-marker fault score (the largest fault statistic; NaN where absent);
            ``fault_threshold``.
        stillness: stillness score (:class:`~.ood.MarkerStillness`: a marker moved less, as a
            share of the markers' motion, than in any simulation; NaN where absent);
            ``stillness_threshold``.
        still_marker: index (0-based, model marker order) of the stillest marker (the largest
            stillness ratio), -1 without a stillness score.
        still_share: that marker's displacement as a share of the markers' root-mean-square
            displacement; ``still_least`` the least share any simulation gave it.
        swap: swap score (:class:`~.ood.MarkerSwap`: how many times better the markers agree
            with two of them exchanged; NaN where absent); ``swap_threshold``.
        swap_first, swap_second: indices (0-based, model marker order) of the pair whose
            exchange makes the markers agree best, -1 without a swap score.
    """

    raised: bool
    distance: float
    distance_threshold: float
    consistency: float
    consistency_threshold: float
    marker: int = -1
    marker_residual: float = float("nan")
    fault: float = float("nan")
    fault_threshold: float = float("inf")
    stillness: float = float("nan")
    stillness_threshold: float = float("inf")
    still_marker: int = -1
    still_share: float = float("nan")
    still_least: float = float("nan")
    swap: float = float("nan")
    swap_threshold: float = float("inf")
    swap_first: int = -1
    swap_second: int = -1

    @property
    def far_from_training(self) -> bool:
        return bool(self.distance > self.distance_threshold)

    @property
    def inconsistent_markers(self) -> bool:
        """The markers disagree: as a whole (consistency) or one of them (fault)."""
        return bool(self.consistency > self.consistency_threshold or self.fault > self.fault_threshold)

    @property
    def still_marker_alarm(self) -> bool:
        """A marker stood still where every simulation moved it (the tissue held there?)."""
        return bool(self.stillness > self.stillness_threshold)

    @property
    def swapped_markers_alarm(self) -> bool:
        """Two markers look exchanged (mislabelled or swapped)."""
        return bool(self.swap > self.swap_threshold)

    @property
    def text(self) -> str:
        """One line for the surgeon's display."""
        if not self.raised:
            return "prediction within the simulated range"
        parts = []
        if self.swapped_markers_alarm:
            parts.append(f"markers {self.swap_first} and {self.swap_second} look exchanged (exchanged back, the markers "
                         f"agree {self.swap:.1f} x better, more than {self.swap_threshold:g} x): check their labels; do not "
                         "trust the predicted shape")
        if self.inconsistent_markers:
            score = (f"one-marker score {self.fault:.1f} > {self.fault_threshold:.1f}" if self.fault > self.fault_threshold
                     else f"score {self.consistency:.1f} > {self.consistency_threshold:.1f}")
            parts.append(f"markers disagree ({score}; most: marker {self.marker}, {self.marker_residual:.1f} mm from where "
                         "the other markers place it): a swapped, slipped or mistracked marker?")
        if self.still_marker_alarm:
            parts.append(f"marker {self.still_marker} did not move ({100 * self.still_share:.0f} % of the markers' mean "
                         f"motion; every simulation moved it at least {100 * self.still_least:.0f} %): is the tissue "
                         "held there (attached farther than simulated) or the marker off the tissue? do not trust the "
                         "predicted shape near it")
        if self.far_from_training:
            parts.append(f"marker input far from every simulated deformation (distance {self.distance:.2f} > "
                         f"{self.distance_threshold:.2f}): do not trust the predicted shape")
        return "; ".join(parts)


@dataclass(frozen=True)
class TrustedPrediction:
    """A prediction with its error bounds and alarm.

    Attributes:
        displacement: (n, 3) or (B, n, 3) float64 mm.
        error_bound: (n,) or (B, n) float64 mm; each vertex's error is below it with
            probability >= ``coverage`` for inputs like the calibration samples.
        coverage: the nominal coverage.
        alarms: one :class:`Alarm` (single input) or a list of B; None where the prediction
            left the alarm out (``predict_trusted(..., alarm=False)``).
    """

    displacement: np.ndarray
    error_bound: np.ndarray
    coverage: float
    alarms: object = field(default=None)

    def first(self) -> "TrustedPrediction":
        """The batch's first sample as a single prediction ((n, 3), (n,), one Alarm or None)."""
        return TrustedPrediction(self.displacement[0], self.error_bound[0], self.coverage,
                                 None if self.alarms is None else self.alarms[0])


def floored_log(x) -> np.ndarray:
    """``log(max(x, LOG_FLOOR))`` as float64 (x in mm)."""
    return np.log(np.maximum(np.asarray(x, dtype=np.float64), LOG_FLOOR))


@dataclass(frozen=True, eq=False)
class TrustLayer:
    """Everything the bounds and alarms need (saved as ``trust.npz`` in the model folder).

    Attributes:
        markers: (n_d,) 0-based marker ids.
        basis: the second predictor's PCA basis (K components).
        second: quadratic map from marker displacements (3 n_d,) mm to its K weights.
        error_model: (1 + len(FEATURE_NAMES),) coefficients of log Offset_max.
        conformal: calibrated per-vertex conformal scores (none before :meth:`calibrate`:
            infinite bounds).
        ood: input distance, marker consistency and their calibration scores (none before
            :meth:`calibrate`: the alarm never fires).
        coverage: default nominal coverage of the bounds.
        false_alarm: default false-alarm rate of the alarm.
        error_input: regression of the log Offset_max on the marker input (the error model's
            last feature), or None (trust files written before it).
        flat: the normaliser is the error model's g alone (models with a quadratic head).
        n_auxiliary: n_a, the auxiliary inputs read after the markers (0: markers only).
        method: how it was calibrated: ``"split"`` (held-out samples) or ``"cross-validation"``
            (out-of-fold predictions of the training split, :mod:`.cross_calibration`).
    """

    markers: np.ndarray
    basis: PCABasis
    second: QuadraticRegression
    error_model: np.ndarray
    conformal: VertexConformal
    ood: OODScores
    coverage: float
    false_alarm: float
    error_input: QuadraticRegression | None = None
    flat: bool = False
    n_auxiliary: int = 0
    method: str = "split"

    def inputs(self, marker_displacements, auxiliary=None, batch: int | None = None) -> np.ndarray:
        """The layer's input x (B, 3 n_d + n_a): marker displacements (B, 3 n_d) or (B, n_d, 3) mm
        and, for a layer with auxiliary inputs, ``auxiliary`` (B, n_a) after them (or already
        part of ``marker_displacements``, (B, 3 n_d + n_a)).

        Raises:
            ModelError: a width other than the layer's.
        """
        d = np.asarray(marker_displacements, dtype=np.float64)
        d = d.reshape(len(d) if batch is None else batch, -1)
        if auxiliary is not None:
            d = np.hstack([d, np.asarray(auxiliary, dtype=np.float64).reshape(len(d), -1)])
        width = 3 * len(self.markers) + self.n_auxiliary
        if d.shape[1] != width:
            raise ModelError(f"the trust layer reads {3 * len(self.markers)} marker displacements"
                             f"{f' and {self.n_auxiliary} auxiliary inputs' if self.n_auxiliary else ''}, got {d.shape[1]} "
                             "values per sample")
        return d

    # ---------------------------------------------------------------- normaliser
    def features(self, d: np.ndarray, u: np.ndarray, second: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the error model reads from inputs x (B, 3 n_d + n_a) (:meth:`inputs`) and
        predictions u (B, n, 3) mm; ``second`` (B, n, 3) mm: the second predictor's fields for
        x where already decoded (:meth:`.field_predictor.FieldPredictor.predict_and_decode`).

        Returns:
            ``(features (B, F), disagreement h (B, n) mm, distance scores (B,))``.
        """
        B = len(d)
        markers = d[:, :3 * len(self.markers)].reshape(B, -1, 3)
        if second is None:
            second = self.basis.inverse_transform(self.second.predict(d))
        second = second.reshape(B, -1, 3)
        h = np.linalg.norm(u - second, axis=2)
        miss = np.linalg.norm(u[:, self.markers, :] - markers, axis=2).max(axis=1)
        dist = self.ood.distance(d)
        peak = np.linalg.norm(markers, axis=2).max(axis=1)
        cols = [floored_log(h.max(axis=1)), floored_log(h.mean(axis=1)), floored_log(miss), floored_log(dist),
                np.log1p(peak)]
        if self.error_input is not None:
            cols.append(self.error_input.predict(d)[:, 0])
        return np.stack(cols, axis=1), h, dist

    def sigma(self, feats: np.ndarray, h: np.ndarray) -> np.ndarray:
        """(B, n) normaliser (mm) from :meth:`features`' features (B, F) and disagreement (B, n) mm."""
        g = np.exp(np.hstack([np.ones((len(feats), 1)), feats]) @ self.error_model)
        if self.flat:
            return np.repeat(g[:, None], h.shape[1], axis=1)
        shape = (LAMBDA + h / np.maximum(h.max(axis=1, keepdims=True), LOG_FLOOR)) / (LAMBDA + 1.0)
        return g[:, None] * shape

    def normaliser(self, marker_displacements, displacement, *, auxiliary=None) -> np.ndarray:
        """(B, n) normaliser sigma (mm) of predictions (B, n, 3) mm from inputs (B, 3 n_d) mm
        (and ``auxiliary`` (B, n_a), :meth:`inputs`)."""
        d = self.inputs(marker_displacements, auxiliary, len(displacement))
        feats, h, _ = self.features(d, np.asarray(displacement, dtype=np.float64))
        return self.sigma(feats, h)

    # ---------------------------------------------------------------- bounds and alarms
    def assess(self, marker_displacements, displacement, *, coverage: float | None = None,
               false_alarm: float | None = None, auxiliary=None, second=None) -> tuple[np.ndarray, list[Alarm]]:
        """Error bounds and alarms of a batch of predictions (:meth:`bounds` and :meth:`alarms`).

        Args:
            marker_displacements: (B, 3 n_d) or (B, n_d, 3) mm, the inputs.
            displacement: (B, n, 3) mm, the network's predictions for them.
            coverage: nominal coverage (default: :attr:`coverage`).
            false_alarm: false-alarm rate (default: :attr:`false_alarm`).
            auxiliary: (B, n_a) the auxiliary inputs of a layer that reads some (:meth:`inputs`).
            second: (B, n, 3) mm, the second predictor's fields where already decoded (:meth:`features`).

        Returns:
            ``(bounds (B, n) mm, alarms: B Alarm)``.
        """
        u = np.asarray(displacement, dtype=np.float64)
        d = self.inputs(marker_displacements, auxiliary, len(u))
        bounds, dist = self._bounds(d, u, coverage, second)
        return bounds, self._alarms(d, false_alarm, dist)

    def bounds(self, marker_displacements, displacement, *, coverage: float | None = None, auxiliary=None,
               second=None) -> np.ndarray:
        """(B, n) mm error bounds of a batch of predictions, without the alarm (arguments as
        :meth:`assess`)."""
        u = np.asarray(displacement, dtype=np.float64)
        return self._bounds(self.inputs(marker_displacements, auxiliary, len(u)), u, coverage, second)[0]

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None) -> list[Alarm]:
        """The alarms (B Alarm) of a batch of inputs (B, 3 n_d) or (B, n_d, 3) mm (and
        ``auxiliary`` (B, n_a), :meth:`inputs`): the alarm reads the inputs only, so it can
        follow the field and its bounds (as :meth:`assess` gives them together)."""
        return self._alarms(self.inputs(marker_displacements, auxiliary), false_alarm, None)

    def _bounds(self, d: np.ndarray, u: np.ndarray, coverage, second) -> tuple[np.ndarray, np.ndarray]:
        """``(bounds (B, n) mm, distance scores (B,))`` of inputs d (B, 3 n_d + n_a) and fields u (B, n, 3)."""
        feats, h, dist = self.features(d, u, second)
        return self.conformal.bounds(self.sigma(feats, h), self.coverage if coverage is None else coverage), dist

    def _alarms(self, d: np.ndarray, false_alarm, dist: np.ndarray | None) -> list[Alarm]:
        """B Alarm of inputs d (B, 3 n_d + n_a); ``dist``: their distance scores where known."""
        dist = self.ood.distance(d) if dist is None else dist
        thr = self.ood.thresholds(self.false_alarm if false_alarm is None else false_alarm)
        cons = self.ood.consistency
        faults = None
        if cons is not None:
            res, c_score, faults = cons.evaluate(d)
            worst = (res / cons.scale if faults is None else faults).argmax(axis=1)
        else:
            res, c_score, worst = None, np.full(len(d), np.nan), np.full(len(d), -1)
        f_score = faults.max(axis=1) if faults is not None else np.full(len(d), np.nan)
        still = self.ood.stillness
        if still is not None:
            shares, ratios = still.evaluate(d)
            stillest = ratios.argmax(axis=1)
            s_score = ratios[np.arange(len(d)), stillest]
        else:
            s_score, stillest = np.full(len(d), np.nan), np.full(len(d), -1)
        if self.ood.has_swap:
            w_score, pair = self.ood.swap.evaluate(d, cons, own=c_score)
            pairs = self.ood.swap.pairs
        else:
            w_score, pair, pairs = np.full(len(d), np.nan), np.full(len(d), -1), None
        alarms = []
        for b in range(len(d)):
            raised = bool(dist[b] > thr[0] or c_score[b] > thr[1] or f_score[b] > thr[2] or s_score[b] > thr[3]
                          or w_score[b] > thr[4])
            j, k = int(stillest[b]), int(pair[b])
            swap_i, swap_j = (int(pairs[k, 0]), int(pairs[k, 1])) if k >= 0 else (-1, -1)
            alarms.append(Alarm(raised, float(dist[b]), float(thr[0]), float(c_score[b]), float(thr[1]),
                                int(worst[b]), float(res[b, worst[b]]) if res is not None else float("nan"),
                                float(f_score[b]), float(thr[2]), float(s_score[b]), float(thr[3]), j,
                                float(shares[b, j]) if j >= 0 else float("nan"),
                                float(still.least[j]) if j >= 0 else float("nan"),
                                float(w_score[b]), float(thr[4]), swap_i, swap_j))
        return alarms

    def alarm_scores(self, marker_displacements, *, auxiliary=None) -> np.ndarray:
        """(B, 5) [distance, consistency, fault, stillness, swap] scores of inputs (B, 3 n_d) or (B, n_d, 3) mm (and
        ``auxiliary`` (B, n_a), :meth:`inputs`; NaN where absent)."""
        return self.ood.scores(self.inputs(marker_displacements, auxiliary))

    # ---------------------------------------------------------------- calibration
    def calibration_scores(self, marker_displacements, displacements, truths, *,
                           chunk: int = PREDICT_CHUNK, auxiliary=None) -> "CalibrationScores":
        """What calibrates a layer, from (input, prediction, truth) triples the predictor of
        *this* layer was not fitted on, as this layer sees them: the error-model features, the
        disagreement map, the vertex errors and the raw alarm scores (:meth:`with_calibration`
        turns them into bounds and a threshold, for this layer or, pooled over the folds of a
        cross-validation, for the layer of the model fitted on every fold).

        Args:
            marker_displacements: (m, 3 n_d) or (m, n_d, 3) mm, the inputs.
            displacements: (m, n, 3) mm, the predictor's fields for them.
            truths: (m, n, 3) mm, the true (simulated) fields.
            chunk: samples assessed at once.
            auxiliary: (m, n_a) the auxiliary inputs of a layer that reads some (:meth:`inputs`).

        Raises:
            ModelError: shapes that do not match, or non-finite errors or normalisers.
        """
        u = np.asarray(displacements, dtype=np.float64)
        truth = np.asarray(truths, dtype=np.float64)
        if u.shape != truth.shape or u.ndim != 3:
            raise ModelError(f"calibration needs inputs (m, {3 * len(self.markers) + self.n_auxiliary}) and predictions "
                             f"and truths (m, n, 3) mm of one shape, got {u.shape} and {truth.shape}")
        d = self.inputs(marker_displacements, auxiliary, len(u))
        feats, hs, errors = [], [], []
        for s in range(0, len(u), chunk):
            f, h, _ = self.features(d[s:s + chunk], u[s:s + chunk])
            feats.append(f)
            hs.append(h)
            errors.append(np.linalg.norm(u[s:s + chunk] - truth[s:s + chunk], axis=2))
        return CalibrationScores(np.vstack(feats), None if self.flat else np.vstack(hs), np.vstack(errors),
                                 self.ood.scores(d))

    def with_calibration(self, scores: "CalibrationScores") -> "TrustLayer":
        """This layer calibrated by ``scores`` (:meth:`calibration_scores`): the per-vertex
        conformal scores ``e / sigma`` (sigma by this layer's error model) and the alarm threshold
        (the alarm scores combined on this layer's scales). Earlier calibration is replaced.

        Raises:
            ModelError: scores for another number of vertices, non-finite errors or normalisers.
        """
        n = self.basis.n_features // 3
        if scores.errors.shape[1] != n:
            raise ModelError(f"calibration scores are for {scores.errors.shape[1]} vertices, this layer predicts {n}")
        h = scores.disagreement if scores.disagreement is not None else np.ones_like(scores.errors)
        vertex = normalised_errors(scores.errors, self.sigma(scores.features, h))
        ood = dataclasses.replace(self.ood, calibration=np.sort(self.ood.combined(scores.alarm)))
        return dataclasses.replace(self, conformal=VertexConformal(np.sort(vertex, axis=0)), ood=ood)

    def calibrate(self, marker_displacements, displacements, truths, *, chunk: int = PREDICT_CHUNK,
                  auxiliary=None) -> "TrustLayer":
        """This layer calibrated on triples its predictor was not fitted on (split conformal):
        :meth:`with_calibration` of :meth:`calibration_scores` (arguments as there). Earlier
        calibration is replaced.

        Raises:
            ModelError: shapes that do not match, or non-finite errors or normalisers.
        """
        return self.with_calibration(self.calibration_scores(marker_displacements, displacements, truths, chunk=chunk,
                                                             auxiliary=auxiliary))

    # ---------------------------------------------------------------- storage
    def arrays(self) -> dict:
        """Name -> array dict for ``trust.npz`` (no pickle)."""
        out = {"markers": self.markers, "basis.mean": self.basis.mean, "basis.components": self.basis.components,
               "basis.singular_values": self.basis.singular_values, "basis.n_samples": np.int64(self.basis.n_samples),
               "error_model": self.error_model, "conformal.sorted_scores": self.conformal.sorted_scores.astype(np.float32),
               "ood.distance.mean": self.ood.distance.mean, "ood.distance.whitening": self.ood.distance.whitening,
               "ood.distance.reference": self.ood.distance.reference,
               "ood.distance.neighbours": np.int64(self.ood.distance.neighbours),
               "ood.scale": self.ood.scale, "ood.calibration": self.ood.calibration,
               "ood.use_fault": np.bool_(self.ood.use_fault), "coverage": np.float64(self.coverage),
               "false_alarm": np.float64(self.false_alarm)}
        out.update(self.second.arrays("second."))
        if self.error_input is not None:
            out.update(self.error_input.arrays("error_input."))
        out["flat"] = np.bool_(self.flat)
        out["n_auxiliary"] = np.int64(self.n_auxiliary)
        out["calibration_method"] = np.str_(self.method)
        cons = self.ood.consistency
        out["ood.consistency.count"] = np.int64(0 if cons is None else len(cons.regressions))
        if cons is not None:
            out["ood.consistency.scale"] = cons.scale
            out["ood.consistency.mean"] = cons.mean
            out["ood.consistency.precision"] = cons.precision
            if cons.sensitivity is not None:
                out["ood.consistency.sensitivity"] = cons.sensitivity
            for j, reg in enumerate(cons.regressions):
                out.update(reg.arrays(f"ood.consistency.{j}."))
        if self.ood.stillness is not None:
            out["ood.stillness.least"] = self.ood.stillness.least
        if self.ood.swap is not None:
            out["ood.swap.reference"] = self.ood.swap.reference
        return out

    @classmethod
    def from_arrays(cls, a) -> "TrustLayer":
        basis = PCABasis(np.asarray(a["basis.mean"]), np.asarray(a["basis.components"]),
                         np.asarray(a["basis.singular_values"]), int(a["basis.n_samples"]))
        dist = InputDistance(np.asarray(a["ood.distance.mean"]), np.asarray(a["ood.distance.whitening"]),
                             np.asarray(a["ood.distance.reference"]), int(a["ood.distance.neighbours"]))
        count = int(a["ood.consistency.count"])
        cons = None
        if count:
            regs = tuple(QuadraticRegression.from_arrays(a, f"ood.consistency.{j}.") for j in range(count))
            sens = a.get("ood.consistency.sensitivity")  # absent in files written before the fault score
            cons = MarkerConsistency(regs, *(np.asarray(a[f"ood.consistency.{k}"], dtype=np.float64)
                                             for k in ("scale", "mean", "precision")),
                                     None if sens is None else np.asarray(sens, dtype=np.float64))
        return cls(markers=np.asarray(a["markers"], dtype=np.int64), basis=basis,
                   second=QuadraticRegression.from_arrays(a, "second."),
                   error_model=np.asarray(a["error_model"], dtype=np.float64),
                   conformal=VertexConformal(np.asarray(a["conformal.sorted_scores"])),
                   ood=OODScores(dist, cons, np.asarray(a["ood.scale"], dtype=np.float64),
                                 np.asarray(a["ood.calibration"], dtype=np.float64),
                                 bool(a["ood.use_fault"]) if "ood.use_fault" in a else False,
                                 # absent in files written before the stillness score
                                 MarkerStillness(np.asarray(a["ood.stillness.least"], dtype=np.float64))
                                 if "ood.stillness.least" in a else None,
                                 # absent in files written before the swap score
                                 MarkerSwap(np.asarray(a["ood.swap.reference"], dtype=np.float64))
                                 if "ood.swap.reference" in a else None),
                   coverage=float(a["coverage"]), false_alarm=float(a["false_alarm"]),
                   error_input=QuadraticRegression.from_arrays(a, "error_input.") if "error_input.coef" in a else None,
                   flat=bool(a["flat"]) if "flat" in a else False,
                   n_auxiliary=int(a["n_auxiliary"]) if "n_auxiliary" in a else 0,
                   method=str(a["calibration_method"]) if "calibration_method" in a else "split")

    def save(self, folder) -> str:
        """Write ``trust.npz`` into a model folder; returns the file name."""
        from pathlib import Path

        np.savez(Path(folder) / FILE, **self.arrays())
        return FILE

    def summary(self) -> dict:
        """Small JSON-able description (for model.json)."""
        return {"file": FILE, "n_calibration": self.conformal.n_calibration, "coverage": self.coverage,
                "false_alarm": self.false_alarm, "second_predictor_components": self.basis.n_components,
                "error_model_features": list(FEATURE_NAMES) + (["input_error_prediction"] if self.error_input else []),
                "error_model": self.error_model.tolist(),
                "consistency": self.ood.consistency is not None,
                "fault_score": self.ood.consistency is not None and self.ood.consistency.sensitivity is not None,
                "fault_score_in_alarm": self.ood.use_fault,
                "stillness_score": self.ood.stillness is not None,
                "swap_score": self.ood.has_swap,
                "flat_normaliser": self.flat, "auxiliary_inputs": self.n_auxiliary,
                "calibration": self.method}
