"""Fitting a :class:`~.trust.TrustLayer` for any field predictor.

:func:`fit_trust_layer` fits what the bounds and the alarm need from the training and
validation samples (the layer's module docstring lists the parts); the result is not calibrated
yet. :meth:`TrustLayer.calibrate <.trust.TrustLayer.calibrate>` then takes (input, prediction,
truth) triples the predictor was not fitted on; :func:`fit_trust` does both with held-out
calibration samples (split conformal).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import ModelError
from .conformal import VertexConformal, min_calibration_samples
from .data import CALIBRATION_SEED_OFFSET, MIN_SAMPLES
from .field_predictor import FieldPredictor
from .ood import (SCORE_NAMES, MarkerSwap, OODScores, fit_input_distance, fit_marker_consistency, fit_marker_stillness,
                  scale_ood)
from .pca import PCABasis, fit_pca
from .quadratic import QuadraticRegression, fit_quadratic
from .ridge import marker_columns
from .trust import FEATURE_NAMES, PREDICT_CHUNK, TrustLayer, floored_log

__all__ = ["fit_trust_layer", "fit_trust", "held_out_predictions", "SECOND_COMPONENTS", "ERROR_FOLDS",
           "ERROR_INPUT_DIMS", "warn_if_too_few", "fit_error_model"]

# the trust layer's messages keep the logger name they had before fitting moved here (log filters)
log = logging.getLogger("tissuecast.surrogate.trust")

#: PCA components of the second predictor (its truncation error must stay below the network's).
SECOND_COMPONENTS = 64
# Ridge penalty of the error model (its features are O(1) logarithms).
_ERROR_MODEL_RIDGE = 1e-3
#: Folds of the out-of-fold errors behind the input error regression, and its quadratic sizes tried.
ERROR_FOLDS = 5
ERROR_INPUT_DIMS = (0, 6)
_ERROR_INPUT_RIDGE = 1e-3


def held_out_predictions(predictor: FieldPredictor, displacements, idx, chunk: int = PREDICT_CHUNK, auxiliary=None):
    """The predictor's fields for samples ``idx`` from their own marker displacements (and
    auxiliary inputs).

    Args:
        predictor: any :class:`FieldPredictor` on the fields' mesh.
        displacements: (N, n, 3) fields, mm.
        idx: (m,) sample indices.
        chunk: samples predicted at once.
        auxiliary: (N, n_a) every sample's auxiliary inputs (:mod:`.auxiliary`), for a
            predictor that reads some; None without.

    Returns:
        ``(inputs (m, 3 n_d + n_a), predictions (m, n, 3) mm, truths (m, n, 3) mm)``, float64:
        the inputs are the marker displacements (mm) followed by the auxiliary inputs.
    """
    inputs, predictions, truths = [], [], []
    for s in range(0, len(idx), chunk):
        rows = np.asarray(idx[s:s + chunk])
        bench = np.asarray(displacements[rows], dtype=np.float64)
        d = bench[:, predictor.markers, :].reshape(len(bench), -1)
        a = None if auxiliary is None else np.asarray(auxiliary, dtype=np.float64)[rows]
        predictions.append(predictor.predict(d.reshape(len(bench), -1, 3), auxiliary=a))
        inputs.append(d if a is None else np.hstack([d, a]))
        truths.append(bench)
    return np.vstack(inputs), np.concatenate(predictions), np.concatenate(truths)


def _assessed_samples(predictor: FieldPredictor, draft: TrustLayer, U, idx: np.ndarray,
                      chunk: int, auxiliary=None) -> tuple[np.ndarray, ...]:
    """The predictor's fields of samples ``idx`` assessed by ``draft``, ``chunk`` samples at a time.

    Returns:
        ``(features (B, F), vertex errors (B, n) mm, inputs (B, 3 n_d + n_a))``.
    """
    feats, errs, inputs = [], [], []
    for s in range(0, len(idx), chunk):
        d, u, bench = held_out_predictions(predictor, U, idx[s:s + chunk], chunk, auxiliary)
        feats.append(draft.features(d, u)[0])
        errs.append(np.linalg.norm(u - bench, axis=2))
        inputs.append(d)
    return np.vstack(feats), np.vstack(errs), np.vstack(inputs)


def fit_error_model(features: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Ridge regression of log Offset_max on [1, features]: (1 + F,) coefficients (intercept not penalised),
    from features (B, F) and vertex errors (B, n) mm."""
    F = np.hstack([np.ones((len(features), 1)), features])
    G = F.T @ F + _ERROR_MODEL_RIDGE * len(F) * np.diag(np.r_[0.0, np.ones(features.shape[1])])
    return np.linalg.solve(G, F.T @ floored_log(errors.max(axis=1)))


def _second_predictor(Ut: np.ndarray, Xt: np.ndarray, basis: PCABasis | None,
                      head: QuadraticRegression | None) -> tuple[PCABasis, QuadraticRegression, PCABasis]:
    """``(second basis, second regression, basis of the input error regression)``: the given head
    on the given basis, or a quadratic regression of :data:`SECOND_COMPONENTS` of the training
    fields on the inputs ``Xt`` (N_t, 3 n_d + n_a)."""
    if head is not None:  # the networks' correction of their head (ranks samples; within a sample the conformal quantiles do)
        if basis is None:
            raise ModelError("a head as second predictor needs the PCA basis it predicts the weights of")
        return basis, head, basis
    own = fit_pca(Ut, min(SECOND_COMPONENTS, len(Ut) - 1, Ut.shape[1]))
    return own, fit_quadratic(Xt, own.transform(Ut)), own if basis is None else basis


def fit_trust_layer(predictor: FieldPredictor, displacements, *, train_idx, valid_idx, coverage: float,
                    false_alarm: float, fault_score: bool = False, basis: PCABasis | None = None,
                    head: QuadraticRegression | None = None, chunk: int = PREDICT_CHUNK,
                    auxiliary=None) -> TrustLayer:
    """The trust layer of a fitted predictor, not calibrated yet (:meth:`TrustLayer.calibrate`).

    Args:
        predictor: the fitted predictor (it must not have been fitted on ``valid_idx`` samples).
        displacements: (N, n, 3) fields, mm.
        train_idx, valid_idx: disjoint sample indices: the predictor's training samples, and
            >= :data:`~.data.MIN_SAMPLES` validation samples.
        coverage: default nominal coverage of the bounds (``surrogate.coverage``).
        false_alarm: default false-alarm rate (``surrogate.false_alarm_rate``).
        fault_score: the alarm also uses the single-marker fault score
            (``surrogate.alarm_fault_score``; it names the suspect marker either way).
        basis: the predictor's PCA basis, if it has one (the input error regression works in
            it); None: the second predictor's own basis.
        head: the predictor's quadratic head on ``basis``, if it has one: it is then the second
            predictor and the normaliser is flat (module docstring of :mod:`.trust`).
        chunk: samples predicted at once.
        auxiliary: (N, n_a) every sample's auxiliary inputs, for a predictor that reads some
            (:mod:`.auxiliary`): every part of the layer then reads them after the markers.
    """
    sets = [np.asarray(i, dtype=np.int64) for i in (train_idx, valid_idx)]
    U, mk = displacements, predictor.markers
    cols = marker_columns(mk)
    A = None if auxiliary is None else np.asarray(auxiliary, dtype=np.float64)
    n_a = 0 if A is None else A.shape[1]
    Ut = np.asarray(U[sets[0]], dtype=np.float64).reshape(len(sets[0]), -1)
    Xt = Ut[:, cols] if A is None else np.hstack([Ut[:, cols], A[sets[0]]])
    second_basis, second, error_basis = _second_predictor(Ut, Xt, basis, head)
    distance = fit_input_distance(Xt)
    Xv = np.asarray(U[sets[1]], dtype=np.float64).reshape(len(sets[1]), -1)[:, cols]
    Xv = Xv if A is None else np.hstack([Xv, A[sets[1]]])
    consistency = fit_marker_consistency(Xt, Xv, n_a)
    stillness = fit_marker_stillness(Xt, n_a)
    swap = MarkerSwap(predictor.reference_marker_positions) if consistency is not None else None
    ood0 = OODScores(distance, consistency, np.ones(len(SCORE_NAMES)), np.zeros(0), fault_score, stillness, swap)
    empty = VertexConformal(np.zeros((0, U.shape[1])))
    draft = TrustLayer(mk, second_basis, second, np.zeros(1 + len(FEATURE_NAMES)), empty, ood0, coverage, false_alarm,
                       flat=head is not None, n_auxiliary=n_a)
    fv, ev, dv = _assessed_samples(predictor, draft, U, sets[1], chunk, A)
    q = len(head.directions) if head is not None else min(12, Xt.shape[1])
    error_input = _input_error_regression(error_basis, q, Ut, Xt, dv, ev)
    if error_input is not None:
        fv = np.hstack([fv, error_input.predict(dv)])
    return TrustLayer(mk, second_basis, second, fit_error_model(fv, ev), empty,
                      scale_ood(distance, consistency, dv, fault_score, stillness, swap), coverage, false_alarm, error_input,
                      head is not None, n_a)


def _check_splits(sets: list[np.ndarray]) -> None:
    if len(np.unique(np.concatenate(sets))) != sum(len(s) for s in sets):
        raise ModelError("training, validation and calibration samples must be disjoint")
    if len(sets[1]) < MIN_SAMPLES or len(sets[2]) < MIN_SAMPLES:
        raise ModelError(f"the trust layer needs >= {MIN_SAMPLES} validation and calibration samples each, got "
                         f"{len(sets[1])} and {len(sets[2])}; raise surrogate.calibration_share or use a larger data set")


def warn_if_too_few(m: int, coverage: float, false_alarm: float) -> None:
    """Log a warning where ``m`` calibration samples give infinite bounds at ``coverage`` or an
    alarm that cannot fire at ``false_alarm``."""
    for what, level in (("error bounds at coverage", coverage), ("alarm at false-alarm rate", 1.0 - false_alarm)):
        if m < min_calibration_samples(level):
            log.warning("%d calibration samples are too few for finite %s %g (needs %d): use surrogate.calibration = "
                        "'cross-validation' (every training sample calibrates), a larger calibration_share or a larger "
                        "data set", m, what,
                        coverage if "bounds" in what else false_alarm, min_calibration_samples(level))


def fit_trust(predictor: FieldPredictor, displacements, *, train_idx, valid_idx, calibration_idx, coverage: float,
              false_alarm: float, fault_score: bool = False, basis: PCABasis | None = None,
              head: QuadraticRegression | None = None, chunk: int = PREDICT_CHUNK, auxiliary=None) -> TrustLayer:
    """:func:`fit_trust_layer`, calibrated on the held-out ``calibration_idx`` samples (split conformal).

    Args:
        calibration_idx: >= :data:`~.data.MIN_SAMPLES` sample indices disjoint from the others,
            never trained on.
        Others: as :func:`fit_trust_layer`.

    Raises:
        ModelError: overlapping splits or too few validation/calibration samples.
    """
    sets = [np.asarray(i, dtype=np.int64) for i in (train_idx, valid_idx, calibration_idx)]
    _check_splits(sets)
    draft = fit_trust_layer(predictor, displacements, train_idx=sets[0], valid_idx=sets[1], coverage=coverage,
                            false_alarm=false_alarm, fault_score=fault_score, basis=basis, head=head, chunk=chunk,
                            auxiliary=auxiliary)
    layer = draft.calibrate(*held_out_predictions(predictor, displacements, sets[2], chunk, auxiliary), chunk=chunk)
    warn_if_too_few(len(sets[2]), coverage, false_alarm)
    return layer


def _input_error_regression(basis: PCABasis, q: int, Ut: np.ndarray, Xt: np.ndarray, Xv: np.ndarray,
                            ev: np.ndarray) -> QuadraticRegression | None:
    """A regression of the log per-sample Offset_max on the marker input, learnt from out-of-fold
    errors on the training samples (a quadratic regression with ``q`` directions in ``basis``,
    refitted on :data:`ERROR_FOLDS` folds: errors like the model's on samples it did not fit), so
    that the error model sees what the input says about the error from many more samples than
    'valid'.

    Its size (linear or quadratic features) is the one that ranks the predictor's validation
    errors ``ev`` (B, n) mm best; the error model weighs it with the other features. None with
    too few samples.
    """
    n = len(Ut)
    if n < 2 * ERROR_FOLDS:
        return None
    W = basis.transform(Ut)
    fold = np.random.default_rng(CALIBRATION_SEED_OFFSET).permutation(n) % ERROR_FOLDS
    oof = np.zeros(n)
    for f in range(ERROR_FOLDS):
        fit, held = fold != f, fold == f
        reg = fit_quadratic(Xt[fit], W[fit], quadratic_dims=q)
        e = (basis.inverse_transform(reg.predict(Xt[held])) - Ut[held]).reshape(int(held.sum()), -1, 3)
        oof[held] = np.sqrt((e**2).sum(axis=2)).max(axis=1)
    target = floored_log(ev.max(axis=1))
    best, best_rho, rhos = None, -np.inf, {}
    for qe in ERROR_INPUT_DIMS:
        reg = fit_quadratic(Xt, floored_log(oof)[:, None], quadratic_dims=qe, ridge=_ERROR_INPUT_RIDGE)
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
