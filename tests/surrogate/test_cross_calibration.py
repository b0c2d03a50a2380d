"""Cross-validated calibration of the trust layer (surrogate/cross_calibration.py): every training
sample trains the model and calibrates its bounds and alarm, out of fold."""

import functools

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.errors import ConfigError, ModelError
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.conformal import fit_vertex_conformal
from tissuecast.surrogate.cross_calibration import calibration_folds, cross_calibration_scores
from tissuecast.surrogate.data import MIN_SAMPLES

from _surrogate_synthetic import MARKERS
from _trust_synthetic import SPLITS, trust_data, trust_model

TRAIN, VALID = np.arange(0, 600), np.arange(600, 800)
SETTINGS = dict(epochs=300, patience=30, batch_size=64, learning_rate=3e-3, n_components=8, hidden=(32,), head="none",
                calibration_folds=5)


@functools.lru_cache(maxsize=None)
def fitted(calibration: str) -> DeformationModel:
    mesh, U, _ = trust_data()
    return DeformationModel(calibration=calibration, **SETTINGS).fit(U, MARKERS, mesh=mesh, train_idx=TRAIN, valid_idx=VALID)


def test_folds_partition_the_training_split_evenly_and_reproducibly():
    f = calibration_folds(103, 5, seed=4)
    assert f.shape == (103,) and set(f.tolist()) == set(range(5))
    assert sorted(np.bincount(f).tolist()) == [20, 20, 21, 21, 21]
    np.testing.assert_array_equal(f, calibration_folds(103, 5, seed=4))
    assert not np.array_equal(f, calibration_folds(103, 5, seed=5))
    with pytest.raises(ModelError, match="calibration_folds"):
        calibration_folds(5 * MIN_SAMPLES - 1, 5, seed=0)


def test_config_keys_are_validated():
    assert Config().surrogate.calibration == "split" and Config().surrogate.calibration_folds == 5
    from tissuecast.app.presets import preset_config

    assert preset_config("paper").surrogate.calibration == preset_config("quick").surrogate.calibration == "cross-validation"
    with pytest.raises(ConfigError, match="surrogate.calibration"):
        with_overrides(Config(), surrogate={"calibration": "jackknife"})
    with pytest.raises(ConfigError, match="surrogate.calibration_folds"):
        with_overrides(Config(), surrogate={"calibration_folds": 1})


def test_the_model_gives_up_no_training_sample():
    cv, none = fitted("cross-validation"), fitted("none")
    assert cv.has_trust and not none.has_trust
    assert cv.training_["n_train"] == none.training_["n_train"] == len(TRAIN)
    _, U, _ = trust_data()
    d = U[SPLITS["test"]][:, MARKERS]
    np.testing.assert_array_equal(cv.predict(d), none.predict(d))  # the same network, bit for bit
    record = cv.training_["calibration"]
    assert record["method"] == "cross-validation" and record["folds"] == 5 and record["n_calibration"] == len(TRAIN)
    assert cv.trusted_.n_calibration == len(TRAIN)
    tp = cv.predict_trusted(d)
    assert np.isfinite(tp.error_bound).all() and np.isfinite(tp.alarms[0].distance_threshold)


def test_each_training_sample_is_scored_once_by_a_model_that_never_saw_it():
    mesh, U, _ = trust_data()
    config = fitted("none").config
    folds = cross_calibration_scores(U, TRAIN, VALID, MARKERS, mesh, config)
    assert folds.scores.n_samples == len(TRAIN) and len(folds.seconds) == 5
    # scored in fold order: the errors are those of fold k's model on fold k's samples
    order = np.concatenate([TRAIN[folds.folds == k] for k in range(5)])
    assert len(set(order.tolist())) == len(TRAIN)
    means = [folds.scores.errors[np.flatnonzero(np.repeat(np.arange(5), np.bincount(folds.folds)) == k)].max(axis=1).mean()
             for k in range(5)]
    np.testing.assert_allclose(means, folds.fold_errors, rtol=1e-12)
    # the input distance of an out-of-fold sample is to the other folds' inputs, never to itself: the
    # final layer, which holds every training input, puts the same inputs closer (one neighbour at 0)
    layer = fitted("cross-validation").trusted_.layer
    in_sample = layer.ood.distance(U[order][:, MARKERS].reshape(len(order), -1))
    assert np.median(folds.scores.alarm[:, 0]) > 1.1 * np.median(in_sample)


def test_split_calibration_is_the_held_out_conformal_quantile():
    model = trust_model()  # calibration_idx given: split conformal on them
    assert model.training_["calibration"]["method"] == "split"
    _, U, _ = trust_data()
    cal = SPLITS["calibration"]
    d = U[cal][:, MARKERS].reshape(len(cal), -1)
    u = model.predict(d.reshape(len(cal), -1, 3))
    layer = model.trusted_.layer
    expected = fit_vertex_conformal(np.linalg.norm(u - U[cal], axis=2), layer.normaliser(d, u))
    np.testing.assert_allclose(layer.conformal.sorted_scores, expected.sorted_scores, rtol=1e-12)
    np.testing.assert_allclose(layer.ood.calibration, np.sort(layer.ood.combined(layer.alarm_scores(d))), rtol=1e-12)


def test_cross_validated_bounds_cover_held_out_samples():
    # trained to convergence (early stopping), so that the fold models are like the model; they
    # train on 4/5 of the samples and err a little more: the bounds are conservative by that much
    model = fitted("cross-validation")
    _, U, _ = trust_data()
    te = SPLITS["test"]
    tp = model.predict_trusted(U[te][:, MARKERS])
    covered = np.mean(np.linalg.norm(tp.displacement - U[te], axis=2) <= tp.error_bound)
    assert 0.87 <= covered <= 0.97
    assert np.mean([a.raised for a in tp.alarms]) <= 0.03
