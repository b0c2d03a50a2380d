"""Trust in a prediction: per-vertex error bounds with guaranteed coverage and an
out-of-distribution alarm, calibrated on samples held out from training.

A :class:`TrustLayer` is fitted after the network, from three disjoint splits:

- **train** (the network's own): a second predictor (quadratic ridge regression from the
  markers to 64 PCA weights, :mod:`.quadratic`; for a model with a quadratic head,
  :mod:`.head`, the head itself, so that the disagreement is the networks' correction of it),
  the input distance and the leave-one-marker-out consistency regressions (:mod:`.ood`);
- **valid**: the learned error model, a linear regression of the log of each sample's
  Offset_max on log features of the input alone (the largest and mean disagreement between
  the network and the second predictor, how far the network's field misses the markers it
  was given, the input distance, the peak marker displacement, and a regression of the error
  on the input learnt from out-of-fold errors on the training samples), the mean and covariance of
  the consistency residuals, and the medians that put the three alarm scores on one scale;
- **calibration** (held out from the training split, see ``surrogate.calibration_share``):
  the split-conformal scores of the bounds (:mod:`.conformal`) and of the alarm.

For a model with a quadratic head the normaliser is g alone (``flat``): the per-vertex conformal
quantiles then carry where a sample's errors are large, which measured better than the
networks' correction of the head did. Otherwise the normaliser of vertex i of a sample is
``g * (LAMBDA + h_i / max h) / (LAMBDA + 1)``: g the
error model's predicted Offset_max (ranks samples), h_i the disagreement of the two
predictors at the vertex (ranks vertices within a sample). Bounds are the normaliser times
the per-vertex conformal quantile.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import ModelError
from .conformal import VertexConformal, fit_vertex_conformal, min_calibration_samples
from .ood import (SCORE_NAMES, InputDistance, MarkerConsistency, OODScores, calibrate_ood, fit_input_distance,
                  fit_marker_consistency)
from .pca import PCABasis, fit_pca
from .quadratic import QuadraticRegression, fit_quadratic
from .ridge import marker_columns

__all__ = ["TrustLayer", "Alarm", "TrustedPrediction", "fit_trust", "split_calibration", "FEATURE_NAMES", "FILE", "MIN_SAMPLES"]

log = logging.getLogger(__name__)

FILE = "trust.npz"
FEATURE_NAMES = ("log_disagreement_max", "log_disagreement_mean", "log_marker_miss", "log_distance", "log_peak_marker")
#: Share of the flat part in the vertex normaliser: 0 would trust the disagreement map alone
#: (vertices where the two predictors happen to agree get tiny bounds), large values give
#: one bound scale for the whole sample.
LAMBDA = 0.25
# Floors (mm) inside the logarithms of the error-model features.
_LOG_FLOOR = 1e-6
# Ridge penalty of the error model (its features are O(1) logarithms).
_ERROR_MODEL_RIDGE = 1e-3
#: PCA components of the second predictor (its truncation error must stay below the network's).
SECOND_COMPONENTS = 64
#: Samples predicted at once while fitting (bounds the memory to chunk x n x 3 floats).
PREDICT_CHUNK = 256
#: The calibration hold-out is drawn with ``surrogate.seed`` plus this (a prime), so that it does
#: not repeat the draw of the validation split made with the same seed.
CALIBRATION_SEED_OFFSET = 7919


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

    @property
    def far_from_training(self) -> bool:
        return bool(self.distance > self.distance_threshold)

    @property
    def inconsistent_markers(self) -> bool:
        """The markers disagree: as a whole (consistency) or one of them (fault)."""
        return bool(self.consistency > self.consistency_threshold or self.fault > self.fault_threshold)

    @property
    def text(self) -> str:
        """One line for the surgeon's display."""
        if not self.raised:
            return "prediction within the simulated range"
        parts = []
        if self.inconsistent_markers:
            score = (f"one-marker score {self.fault:.1f} > {self.fault_threshold:.1f}" if self.fault > self.fault_threshold
                     else f"score {self.consistency:.1f} > {self.consistency_threshold:.1f}")
            parts.append(f"markers disagree ({score}; most: marker {self.marker}, {self.marker_residual:.1f} mm from where "
                         "the other markers place it): a swapped, slipped or mistracked marker?")
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
        alarms: one :class:`Alarm` (single input) or a list of B.
    """

    displacement: np.ndarray
    error_bound: np.ndarray
    coverage: float
    alarms: object = field(default=None)


def _log(x) -> np.ndarray:
    return np.log(np.maximum(np.asarray(x, dtype=np.float64), _LOG_FLOOR))


@dataclass(frozen=True, eq=False)
class TrustLayer:
    """Everything the bounds and alarms need (saved as ``trust.npz`` in the model folder).

    Attributes:
        markers: (n_d,) 0-based marker ids.
        basis: the second predictor's PCA basis (K components).
        second: quadratic map from marker displacements (3 n_d,) mm to its K weights.
        error_model: (1 + len(FEATURE_NAMES),) coefficients of log Offset_max.
        conformal: calibrated per-vertex conformal scores.
        ood: input distance, marker consistency and their calibration scores.
        coverage: default nominal coverage of the bounds.
        false_alarm: default false-alarm rate of the alarm.
        error_input: regression of the log Offset_max on the marker input (the error model's
            last feature), or None (trust files written before it).
        flat: the normaliser is the error model's g alone (models with a quadratic head).
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

    # ---------------------------------------------------------------- normaliser
    def _parts(self, d: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> (features (B, F), disagreement h (B, n) mm, distance scores (B,))."""
        B = len(d)
        second = self.basis.inverse_transform(self.second.predict(d)).reshape(B, -1, 3)
        h = np.linalg.norm(u - second, axis=2)
        miss = np.linalg.norm(u[:, self.markers, :] - d.reshape(B, -1, 3), axis=2).max(axis=1)
        dist = self.ood.distance(d)
        peak = np.linalg.norm(d.reshape(B, -1, 3), axis=2).max(axis=1)
        cols = [_log(h.max(axis=1)), _log(h.mean(axis=1)), _log(miss), _log(dist), np.log1p(peak)]
        if self.error_input is not None:
            cols.append(self.error_input.predict(d)[:, 0])
        return np.stack(cols, axis=1), h, dist

    def _sigma(self, feats: np.ndarray, h: np.ndarray) -> np.ndarray:
        g = np.exp(np.hstack([np.ones((len(feats), 1)), feats]) @ self.error_model)
        if self.flat:
            return np.repeat(g[:, None], h.shape[1], axis=1)
        shape = (LAMBDA + h / np.maximum(h.max(axis=1, keepdims=True), _LOG_FLOOR)) / (LAMBDA + 1.0)
        return g[:, None] * shape

    def normaliser(self, marker_displacements, displacement) -> np.ndarray:
        """(B, n) normaliser sigma (mm) of predictions (B, n, 3) mm from inputs (B, 3 n_d) mm."""
        d = np.asarray(marker_displacements, dtype=np.float64).reshape(len(displacement), -1)
        feats, h, _ = self._parts(d, np.asarray(displacement, dtype=np.float64))
        return self._sigma(feats, h)

    # ---------------------------------------------------------------- bounds and alarms
    def assess(self, marker_displacements, displacement, *, coverage: float | None = None,
               false_alarm: float | None = None) -> tuple[np.ndarray, list[Alarm]]:
        """Error bounds and alarms of a batch of predictions.

        Args:
            marker_displacements: (B, 3 n_d) or (B, n_d, 3) mm, the inputs.
            displacement: (B, n, 3) mm, the network's predictions for them.
            coverage: nominal coverage (default: :attr:`coverage`).
            false_alarm: false-alarm rate (default: :attr:`false_alarm`).

        Returns:
            ``(bounds (B, n) mm, alarms: B Alarm)``.
        """
        u = np.asarray(displacement, dtype=np.float64)
        d = np.asarray(marker_displacements, dtype=np.float64).reshape(len(u), -1)
        feats, h, dist = self._parts(d, u)
        bounds = self.conformal.bounds(self._sigma(feats, h), self.coverage if coverage is None else coverage)
        thr = self.ood.thresholds(self.false_alarm if false_alarm is None else false_alarm)
        cons = self.ood.consistency
        faults = None
        if cons is not None:
            res, c_score, faults = cons.evaluate(d)
            worst = (res / cons.scale if faults is None else faults).argmax(axis=1)
        else:
            res, c_score, worst = None, np.full(len(d), np.nan), np.full(len(d), -1)
        f_score = faults.max(axis=1) if faults is not None else np.full(len(d), np.nan)
        alarms = []
        for b in range(len(d)):
            raised = bool(dist[b] > thr[0] or c_score[b] > thr[1] or f_score[b] > thr[2])
            alarms.append(Alarm(raised, float(dist[b]), float(thr[0]), float(c_score[b]), float(thr[1]),
                                int(worst[b]), float(res[b, worst[b]]) if res is not None else float("nan"),
                                float(f_score[b]), float(thr[2])))
        return bounds, alarms

    def alarm_scores(self, marker_displacements) -> np.ndarray:
        """(B, 3) [distance, consistency, fault] scores of inputs (B, 3 n_d) or (B, n_d, 3) mm (NaN where absent)."""
        d = np.asarray(marker_displacements, dtype=np.float64)
        return self.ood.scores(d.reshape(len(d), -1))

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
                                 bool(a["ood.use_fault"]) if "ood.use_fault" in a else False),
                   coverage=float(a["coverage"]), false_alarm=float(a["false_alarm"]),
                   error_input=QuadraticRegression.from_arrays(a, "error_input.") if "error_input.coef" in a else None,
                   flat=bool(a["flat"]) if "flat" in a else False)

    def save(self, folder) -> str:
        """Write ``trust.npz`` into a model folder; returns the file name."""
        from pathlib import Path

        np.savez(Path(folder) / FILE, **self.arrays())
        return FILE

    @classmethod
    def load(cls, path) -> "TrustLayer":
        """Read ``trust.npz`` (``allow_pickle=False``)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                return cls.from_arrays({k: z[k] for k in z.files})
        except (KeyError, ValueError, OSError) as exc:
            raise ModelError(f"trust file {str(path)!r} is unreadable or incomplete: {exc}; re-train the model") from exc

    def summary(self) -> dict:
        """Small JSON-able description (for model.json)."""
        return {"file": FILE, "n_calibration": self.conformal.n_calibration, "coverage": self.coverage,
                "false_alarm": self.false_alarm, "second_predictor_components": self.basis.n_components,
                "error_model_features": list(FEATURE_NAMES) + (["input_error_prediction"] if self.error_input else []),
                "error_model": self.error_model.tolist(),
                "consistency": self.ood.consistency is not None,
                "fault_score": self.ood.consistency is not None and self.ood.consistency.sensitivity is not None,
                "fault_score_in_alarm": self.ood.use_fault,
                "flat_normaliser": self.flat}


def _check_splits(sets: list[np.ndarray]) -> None:
    if len(np.unique(np.concatenate(sets))) != sum(len(s) for s in sets):
        raise ModelError("training, validation and calibration samples must be disjoint")
    if len(sets[1]) < MIN_SAMPLES or len(sets[2]) < MIN_SAMPLES:
        raise ModelError(f"the trust layer needs >= {MIN_SAMPLES} validation and calibration samples each, got "
                         f"{len(sets[1])} and {len(sets[2])}; raise surrogate.calibration_share or use a larger data set")


def _assessed_samples(model, draft: TrustLayer, U, idx: np.ndarray, chunk: int) -> tuple[np.ndarray, ...]:
    """The model's predictions of samples ``idx`` assessed by ``draft``, ``chunk`` samples at a time.

    Returns:
        ``(features (B, F), disagreement h (B, n) mm, vertex errors (B, n) mm, inputs (B, 3 n_d) mm)``.
    """
    mk = model.markers
    feats, hs, errs, inputs = [], [], [], []
    for s in range(0, len(idx), chunk):
        bench = np.asarray(U[idx[s:s + chunk]], dtype=np.float64)
        d = bench[:, mk, :].reshape(len(bench), -1)
        u = model.predict(d.reshape(len(bench), -1, 3))
        f, h, _ = draft._parts(d, u)
        feats.append(f)
        hs.append(h)
        errs.append(np.linalg.norm(u - bench, axis=2))
        inputs.append(d)
    return np.vstack(feats), np.vstack(hs), np.vstack(errs), np.vstack(inputs)


def _error_model(features: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Ridge regression of log Offset_max on [1, features]: (1 + F,) coefficients (intercept not penalised)."""
    F = np.hstack([np.ones((len(features), 1)), features])
    G = F.T @ F + _ERROR_MODEL_RIDGE * len(F) * np.diag(np.r_[0.0, np.ones(features.shape[1])])
    return np.linalg.solve(G, F.T @ _log(errors.max(axis=1)))


def _warn_if_too_few(m: int, coverage: float, false_alarm: float) -> None:
    for what, level in (("error bounds at coverage", coverage), ("alarm at false-alarm rate", 1.0 - false_alarm)):
        if m < min_calibration_samples(level):
            log.warning("%d calibration samples are too few for finite %s %g (needs %d): raise "
                        "surrogate.calibration_share or use a larger data set", m, what,
                        coverage if "bounds" in what else false_alarm, min_calibration_samples(level))


def fit_trust(model, displacements, *, train_idx, valid_idx, calibration_idx, coverage: float, false_alarm: float,
              fault_score: bool = False, chunk: int = PREDICT_CHUNK) -> TrustLayer:
    """Fit the trust layer of a fitted :class:`~tissuecast.surrogate.DeformationModel`.

    Args:
        model: the fitted model (its network must not have seen ``valid_idx`` or
            ``calibration_idx`` samples in training).
        displacements: (N, n, 3) fields, mm.
        train_idx, valid_idx, calibration_idx: disjoint sample indices.
        coverage: default nominal coverage of the bounds (``surrogate.coverage``).
        false_alarm: default false-alarm rate (``surrogate.false_alarm_rate``).
        fault_score: the alarm also uses the single-marker fault score
            (``surrogate.alarm_fault_score``; it names the suspect marker either way).
        chunk: samples predicted at once.

    Raises:
        ModelError: overlapping splits or too few validation/calibration samples.
    """
    sets = [np.asarray(i, dtype=np.int64) for i in (train_idx, valid_idx, calibration_idx)]
    _check_splits(sets)
    U = displacements
    mk = model.markers
    cols = marker_columns(mk)
    Ut = np.asarray(U[sets[0]], dtype=np.float64).reshape(len(sets[0]), -1)
    flat = getattr(model, "head_", None) is not None
    if flat:  # the networks' correction of their head (ranks samples; within a sample the conformal quantiles do)
        basis, second = model.pca_, model.head_
    else:
        basis = fit_pca(Ut, min(SECOND_COMPONENTS, len(Ut) - 1, Ut.shape[1]))
        second = fit_quadratic(Ut[:, cols], basis.transform(Ut))
    Xt = Ut[:, cols]
    distance = fit_input_distance(Xt)
    Xv = np.asarray(U[sets[1]], dtype=np.float64).reshape(len(sets[1]), -1)[:, cols]
    consistency = fit_marker_consistency(Xt, Xv)
    ood0 = OODScores(distance, consistency, np.ones(len(SCORE_NAMES)), np.zeros(0))
    draft = TrustLayer(mk, basis, second, np.zeros(1 + len(FEATURE_NAMES)), VertexConformal(np.ones((1, 1))), ood0,
                       coverage, false_alarm, flat=flat)
    fv, _, ev, dv = _assessed_samples(model, draft, U, sets[1], chunk)
    error_input = _input_error_regression(model, Ut, Xt, dv, ev)
    if error_input is not None:
        fv = np.hstack([fv, error_input.predict(dv)])
    beta = _error_model(fv, ev)
    draft = TrustLayer(mk, basis, second, beta, draft.conformal, ood0, coverage, false_alarm, error_input, flat)
    fc, hc, ec, dc = _assessed_samples(model, draft, U, sets[2], chunk)
    conformal = fit_vertex_conformal(ec, draft._sigma(fc, hc))
    ood = calibrate_ood(distance, consistency, dv, dc, fault_score)
    _warn_if_too_few(len(sets[2]), coverage, false_alarm)
    return TrustLayer(mk, basis, second, beta, conformal, ood, coverage, false_alarm, error_input, flat)


#: Folds of the out-of-fold errors behind the input error regression, and its quadratic sizes tried.
ERROR_FOLDS = 5
ERROR_INPUT_DIMS = (0, 6)
_ERROR_INPUT_RIDGE = 1e-3


def _input_error_regression(model, Ut: np.ndarray, Xt: np.ndarray, Xv: np.ndarray,
                            ev: np.ndarray) -> QuadraticRegression | None:
    """A regression of the log per-sample Offset_max on the marker input, learnt from out-of-fold
    errors on the training samples (a quadratic regression in the model's PCA basis, refitted on
    :data:`ERROR_FOLDS` folds: errors like the model's on samples it did not fit), so that the
    error model sees what the input says about the error from many more samples than 'valid'.

    Its size (linear or quadratic features) is the one that ranks the model's validation
    errors best; the error model weighs it with the other features. None with too few samples.
    """
    n = len(Ut)
    if n < 2 * ERROR_FOLDS:
        return None
    basis = model.pca_
    W = basis.transform(Ut)
    head = getattr(model, "head_", None)
    q = len(head.directions) if head is not None else min(12, Xt.shape[1])
    fold = np.random.default_rng(CALIBRATION_SEED_OFFSET).permutation(n) % ERROR_FOLDS
    oof = np.zeros(n)
    for f in range(ERROR_FOLDS):
        fit, held = fold != f, fold == f
        reg = fit_quadratic(Xt[fit], W[fit], quadratic_dims=q)
        e = (basis.inverse_transform(reg.predict(Xt[held])) - Ut[held]).reshape(int(held.sum()), -1, 3)
        oof[held] = np.sqrt((e**2).sum(axis=2)).max(axis=1)
    target = _log(ev.max(axis=1))
    best, best_rho, rhos = None, -np.inf, {}
    for qe in ERROR_INPUT_DIMS:
        reg = fit_quadratic(Xt, _log(oof)[:, None], quadratic_dims=qe, ridge=_ERROR_INPUT_RIDGE)
        rhos[qe] = rho = _spearman(reg.predict(Xv)[:, 0], target)
        if rho > best_rho:
            best, best_rho = reg, rho
    log.info("input error regression from out-of-fold errors: validation Spearman %s (q: rho)",
             ", ".join(f"{q}: {r:.3f}" for q, r in rhos.items()))
    return best


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation (no ties expected in continuous errors)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(a) > 2 else -1.0


#: Fewest calibration (and validation) samples a trust layer is fitted from.
MIN_SAMPLES = 8


def split_calibration(train_idx, share: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Hold out a seeded ``share`` of the training indices for calibration.

    Returns:
        ``(train (k,) int64, calibration (m,) int64)``, both sorted; calibration is empty
        when ``share`` is 0 or would hold fewer than :data:`MIN_SAMPLES` samples.
    """
    idx = np.asarray(train_idx, dtype=np.int64)
    m = int(round(share * len(idx)))
    if share <= 0 or m < MIN_SAMPLES or len(idx) - m < 2:
        return np.sort(idx), np.zeros(0, dtype=np.int64)
    perm = np.random.default_rng(seed + CALIBRATION_SEED_OFFSET).permutation(idx)
    return np.sort(perm[m:]), np.sort(perm[:m])
