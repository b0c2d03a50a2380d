"""Cross-validated calibration of the trust layer: error bounds and the alarm without holding
training samples out (``surrogate.calibration = "cross-validation"``).

The training split is cut into K seeded folds. For each fold k a model is fitted on the other
folds (its PCA basis, quadratic head and networks: :func:`~.network_fit.fit_network`, the same
validation samples) with its own uncalibrated trust layer (:func:`~.trust_fit.fit_trust_layer`:
second predictor, error model, input distance, marker consistency, all from the other folds),
and that layer scores fold k's samples (:meth:`TrustLayer.calibration_scores
<.trust.TrustLayer.calibration_scores>`): each vertex's normalised error ``e / sigma`` and each
input's alarm score. Every training sample is so scored once, by a model that never saw it.
The model users get is fitted on *every* training sample; its layer's error model (the
normaliser's scale) and alarm scales are refitted on the pooled out-of-fold features, errors
and raw alarm scores (:func:`pooled_layer`: one score function for calibration samples and new
inputs), and it is calibrated by them (:meth:`TrustLayer.with_calibration
<.trust.TrustLayer.with_calibration>`).

This is the cross-validation ("CV", MAPIE's ``method="base"`` with ``cv=K``) form of conformal
calibration generalised to the layer's normalised scores: the out-of-fold scores stand in for
those of held-out samples. Its coverage is that of split conformal to the extent that the
model fitted on all folds behaves like the fold models (Barber et al. 2021, "Predictive
inference with the jackknife+", section 5: exact for stable training); the alarm's distance
and consistency scores are computed against the *other* folds' inputs, so a training sample is
never compared with itself. CV+ (the same paper) would guarantee ``1 - 2 alpha`` for an
interval built from the K fold models at every prediction; the K-fold form keeps prediction to
one model. Measured coverage and false alarms: ``docs/trust-and-planning.md``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from ..config import SurrogateConfig
from ..errors import ModelError
from .auxiliary import MARKERS_ONLY, AuxiliaryInputs
from .data import CALIBRATION_SEED_OFFSET, MIN_SAMPLES
from .decoder import global_part
from .head import truncated_head
from .fit_stage import fit_stage
from .network_fit import fit_network
from .field_predictor import FieldPredictor
from .network_predictor import NetworkPredictor
from .pca import PCABasis
from .quadratic import QuadraticRegression
from .trust import PREDICT_CHUNK, CalibrationScores, TrustLayer
from .trust_fit import fit_error_model, fit_trust, fit_trust_layer, held_out_predictions, warn_if_too_few

__all__ = ["FoldCalibration", "calibration_folds", "cross_calibration_scores", "cross_calibrated_layer", "fold_config",
           "pooled_layer", "fit_model_trust", "second_parts"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class FoldCalibration:
    """The pooled out-of-fold scores and the record of the folds.

    Attributes:
        scores: the training samples' :class:`~.trust.CalibrationScores`, fold after fold.
        folds: (N_t,) int64 fold of each training sample (training-split order).
        seconds: (K,) seconds spent on each fold (fit and scoring).
        fold_errors: (K,) mean Offset_max (mm) of each fold model on its held-out fold.
    """

    scores: CalibrationScores
    folds: np.ndarray
    seconds: np.ndarray
    fold_errors: np.ndarray

    def record(self) -> dict:
        """JSON-able summary for the training record."""
        return {"method": "cross-validation", "folds": int(len(self.seconds)), "n_calibration": self.scores.n_samples,
                "fold_seconds": [round(float(s), 3) for s in self.seconds],
                "fold_mean_offset_max_mm": [float(e) for e in self.fold_errors]}


def calibration_folds(n_train: int, folds: int, seed: int) -> np.ndarray:
    """(n_train,) int64 fold of each training sample: a seeded permutation cut into ``folds``
    near-equal parts (seed ``seed + CALIBRATION_SEED_OFFSET``, the split calibration's draw).

    Raises:
        ModelError: fewer than :data:`~.data.MIN_SAMPLES` samples per fold, or fewer than 2 folds.
    """
    if folds < 2 or n_train // folds < MIN_SAMPLES:
        raise ModelError(f"cross-validated calibration with {folds} folds needs >= {MIN_SAMPLES * max(folds, 2)} training "
                         f"samples, got {n_train}; lower surrogate.calibration_folds or use calibration = 'split' / 'none'")
    out = np.empty(n_train, dtype=np.int64)
    out[np.random.default_rng(seed + CALIBRATION_SEED_OFFSET).permutation(n_train)] = np.arange(n_train) % folds
    return out


def fold_config(config: SurrogateConfig) -> SurrogateConfig:
    """The settings of the fold models: the model's, with ``calibration_fold_ensemble`` networks."""
    if config.calibration_fold_ensemble:
        return dataclasses.replace(config, ensemble=config.calibration_fold_ensemble)
    return config


def cross_calibration_scores(U, train_idx, valid_idx, markers, mesh, config: SurrogateConfig, *,
                             chunk: int = PREDICT_CHUNK, auxiliary: np.ndarray | None = None,
                             spec: AuxiliaryInputs = MARKERS_ONLY, sensitivities=None) -> FoldCalibration:
    """The out-of-fold calibration scores of every training sample.

    Args:
        U: (N, n, 3) fields, mm (finite at ``train_idx`` and ``valid_idx``).
        train_idx: (N_t,) training sample indices; cut into ``config.calibration_folds`` folds.
        valid_idx: (N_v,) validation indices, shared by every fold model (checkpoint, n_w,
            head size, the error model, the alarm's scales).
        markers: (n_d,) int64 0-based marker ids.
        mesh: the :class:`TetMesh` with n vertices.
        config: the surrogate settings (the fold models' from :func:`fold_config`).
        chunk: samples predicted at once.
        auxiliary: (N, n_a) every sample's auxiliary inputs (``spec``), or None: the fold
            models read them as the model does.
        spec: what the auxiliary inputs are (:class:`~.auxiliary.AuxiliaryInputs`).
        sensitivities: the training samples' field sensitivities
            (:class:`~tissuecast.dataset.sensitivities.Sensitivities`) the fold models train
            on as the model does, or None.

    Returns:
        A :class:`FoldCalibration`.
    """
    train = np.asarray(train_idx, dtype=np.int64)
    valid = np.asarray(valid_idx, dtype=np.int64)
    c, fc = config, fold_config(config)
    folds = calibration_folds(len(train), c.calibration_folds, c.seed)
    Uv = np.asarray(U[valid], dtype=np.float64).reshape(len(valid), -1)
    parts, seconds, errors = [], [], []
    for k in range(c.calibration_folds):
        t0 = time.perf_counter()
        fit_idx, held = train[folds != k], train[folds == k]
        rows = (None, None) if auxiliary is None else (auxiliary[fit_idx], auxiliary[valid])
        with fit_stage(f"calibration fold {k + 1}/{c.calibration_folds}"):
            net = fit_network(np.asarray(U[fit_idx], dtype=np.float64).reshape(len(fit_idx), -1), Uv, markers, mesh, fc,
                              *rows, auxiliary=spec, St=None if sensitivities is None else sensitivities.rows(fit_idx))
        predictor = net.predictor
        basis, head = second_parts(predictor)
        layer = fit_trust_layer(predictor, U, train_idx=fit_idx, valid_idx=valid, coverage=c.coverage,
                                false_alarm=c.false_alarm_rate, fault_score=c.alarm_fault_score, basis=basis,
                                head=head, chunk=chunk, auxiliary=auxiliary)
        d, u, truth = held_out_predictions(predictor, U, held, chunk, auxiliary)
        parts.append(layer.calibration_scores(d, u, truth, chunk=chunk))
        errors.append(float(np.linalg.norm(u - truth, axis=2).max(axis=1).mean()))
        seconds.append(time.perf_counter() - t0)
        log.info("calibration fold %d/%d: %d samples held out, fold model mean Offset_max %.3f mm (%.1f s)",
                 k + 1, c.calibration_folds, len(held), errors[-1], seconds[-1])
    return FoldCalibration(CalibrationScores.pooled(parts), folds, np.asarray(seconds), np.asarray(errors))


def cross_calibrated_layer(predictor: FieldPredictor, U, train_idx, valid_idx, mesh, config: SurrogateConfig, *,
                           basis: PCABasis | None = None, head: QuadraticRegression | None = None,
                           chunk: int = PREDICT_CHUNK, auxiliary: np.ndarray | None = None,
                           spec: AuxiliaryInputs = MARKERS_ONLY, sensitivities=None) -> tuple[TrustLayer | None, dict]:
    """The trust layer of ``predictor`` (fitted on every ``train_idx`` sample), calibrated on the
    out-of-fold scores of :func:`cross_calibration_scores`.

    Args:
        predictor: the model's fitted learned predictor.
        U, train_idx, valid_idx, mesh, config, chunk, auxiliary, spec, sensitivities: as
            :func:`cross_calibration_scores`.
        basis, head: the predictor's PCA basis and quadratic head (:func:`~.trust_fit.fit_trust_layer`).

    Returns:
        ``(layer, record)``; ``(None, record)`` with a logged warning when the folds or the
        validation split are too small (< :data:`~.data.MIN_SAMPLES` samples each).
    """
    train, valid, k = np.asarray(train_idx), np.asarray(valid_idx), config.calibration_folds
    if len(train) // k < MIN_SAMPLES or len(valid) < MIN_SAMPLES:
        log.warning("no error bounds or alarm: cross-validated calibration needs >= %d samples per fold and >= %d validation "
                    "samples, got %d training samples in %d folds and %d validation samples", MIN_SAMPLES, MIN_SAMPLES,
                    len(train), k, len(valid))
        return None, {"method": "none", "reason": "too few samples for cross-validated calibration"}
    folds = cross_calibration_scores(U, train, valid, predictor.markers, mesh, config, chunk=chunk, auxiliary=auxiliary,
                                     spec=spec, sensitivities=sensitivities)
    draft = fit_trust_layer(predictor, U, train_idx=train, valid_idx=valid, coverage=config.coverage,
                            false_alarm=config.false_alarm_rate, fault_score=config.alarm_fault_score, basis=basis, head=head,
                            chunk=chunk, auxiliary=auxiliary)
    warn_if_too_few(folds.scores.n_samples, config.coverage, config.false_alarm_rate)
    return pooled_layer(draft, folds.scores), folds.record()


def pooled_layer(draft: TrustLayer, scores: CalibrationScores) -> TrustLayer:
    """``draft`` calibrated on the pooled out-of-fold scores, its error model and alarm scales
    refitted on them.

    One score function for the calibration samples and new inputs alike: the fold layers' own
    error models and alarm scales, each fitted on the validation samples only, differ from fit
    to fit by more than the conformal quantiles tolerate (on the demo preset's 25 validation
    samples the bounds covered 82 % of test-1's vertices at 90 %). So the error model (log
    Offset_max on the features) is refitted on every training sample's out-of-fold features and
    errors, and the alarm's scales are the medians of the out-of-fold raw scores. The draft's
    error model is kept where the folds' features differ from its own (an input error
    regression on one side only, with very few samples). The fold models train on (K-1)/K of
    the samples and are a little less accurate than the model: the bounds err on the safe side
    (measured in docs/trust-and-planning.md).

    Args:
        draft: the uncalibrated layer of the model fitted on every fold.
        scores: the pooled out-of-fold scores.
    """
    ood = draft.ood.rescaled(scores.alarm)
    same = scores.features.shape[1] == len(draft.error_model) - 1
    beta = fit_error_model(scores.features, scores.errors) if same else draft.error_model
    return dataclasses.replace(draft, error_model=beta, ood=ood, method="cross-validation").with_calibration(scores)


def second_parts(predictor: NetworkPredictor) -> tuple[PCABasis, QuadraticRegression | None]:
    """The trust layer's second predictor from a network: its global PCA basis (the whole basis
    for ``surrogate.decoder = "pca"``, the global part of a local decoder) and its quadratic head
    on that basis, or None."""
    pca = global_part(predictor.basis)
    return pca, truncated_head(predictor.head, pca.n_components)


def fit_model_trust(predictor: NetworkPredictor, U, splits, mesh, config: SurrogateConfig, *, explicit: bool,
                    auxiliary: np.ndarray | None = None, sensitivities=None) -> tuple[TrustLayer | None, dict]:
    """The trust layer of a model's fitted learned predictor and the record of its calibration:
    split conformal on the held-out ``splits.calibration`` samples (given ones, ``explicit``, or
    ``calibration = "split"``'s share), cross-validated calibration (:func:`cross_calibrated_layer`)
    with ``calibration = "cross-validation"`` and no given samples, or none. ``auxiliary``:
    (N, n_a) every sample's auxiliary inputs for a predictor that reads some (its
    ``auxiliary`` spec), else None. ``sensitivities``: what the fold models of cross-validated
    calibration train on beside the fields (as the model did), or None.

    Returns:
        ``(layer or None, record)``.
    """
    c = config
    basis, head = second_parts(predictor)
    if len(splits.calibration):
        layer = fit_trust(predictor, U, train_idx=splits.train, valid_idx=splits.valid,
                          calibration_idx=splits.calibration, coverage=c.coverage, false_alarm=c.false_alarm_rate,
                          fault_score=c.alarm_fault_score, basis=basis, head=head, auxiliary=auxiliary)
        return layer, {"method": "split", "n_calibration": int(len(splits.calibration))}
    if c.calibration == "cross-validation" and not explicit:
        return cross_calibrated_layer(predictor, U, splits.train, splits.valid, mesh, c, basis=basis, head=head,
                                      auxiliary=auxiliary, spec=predictor.auxiliary, sensitivities=sensitivities)
    return None, {"method": "none"}
