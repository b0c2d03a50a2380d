"""The one predictor protocol: the model's parts, the baselines and the trust wrapper implement it,
declare their capabilities, and the trust wrapper works around any predictor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.surrogate import (DeformationModel, FieldPredictor, ModelState, NetworkPredictor, RidgePredictor,
                                  RigidRegistrationPredictor, TrustedPredictor)
from tissuecast.surrogate.trust_fit import fit_trust, fit_trust_layer, held_out_predictions

from _surrogate_synthetic import COMPILED_ATOL
from _trust_synthetic import SPLITS, trust_data, trust_model


@pytest.fixture(scope="module")
def model() -> DeformationModel:
    return trust_model()


@pytest.fixture(scope="module")
def test_fields():
    _, U, _ = trust_data()
    return U[SPLITS["test"]]


def test_every_part_is_a_field_predictor_and_declares_what_it_can(model):
    parts = {m: model.predictor(m) for m in ("mlp", "rigid", "ridge")}
    assert isinstance(parts["mlp"], NetworkPredictor) and isinstance(parts["rigid"], RigidRegistrationPredictor)
    assert isinstance(parts["ridge"], RidgePredictor) and isinstance(model.trusted_, TrustedPredictor)
    for name, p in [*parts.items(), ("mlp", model.trusted_), ("mlp", model)]:
        assert isinstance(p, FieldPredictor) and p.name == name
        np.testing.assert_array_equal(p.markers, model.markers)
        assert p.mesh is model.mesh
    # capabilities: declared, and the methods follow them
    assert [parts[m].supports_missing_markers for m in ("mlp", "rigid", "ridge")] == [False, True, False]
    assert [parts[m].has_uncertainty for m in ("mlp", "rigid", "ridge")] == [False, False, False]  # one network
    assert [p.has_trust for p in (*parts.values(), model.trusted_, model)] == [False, False, False, True, True]
    d = np.zeros((2, len(model.markers), 3))
    for p in (parts["rigid"], parts["ridge"], parts["mlp"]):
        with pytest.raises(ModelError, match="no calibrated error bounds"):
            p.predict_trusted(d)
    with pytest.raises(ModelError, match="rigid predictor gives no uncertainty"):
        parts["rigid"].predict_with_uncertainty(d)
    with pytest.raises(ModelError, match="uncertainty needs an ensemble"):
        parts["mlp"].predict_with_uncertainty(d)
    with pytest.raises(ModelError, match="ridge baseline cannot predict with missing markers"):
        parts["ridge"].predict(d, missing=[0])
    assert model.describe()["has_trust"] and model.trusted_.describe()["trust"]["n_calibration"] == 300


def test_the_facade_predicts_through_its_parts(model, test_fields):
    d = model.marker_displacements(test_fields[:30])
    for method in ("mlp", "rigid", "ridge"):
        np.testing.assert_array_equal(model.predict(d, method=method), model.predictor(method).predict(d))
    np.testing.assert_array_equal(model.predict_ridge(d), model.ridge_.predict(d))
    np.testing.assert_array_equal(model.predict_rigid(d), model.rigid_.predict(d))
    tp, wrapped = model.predict_trusted(d), model.trusted_.predict_trusted(d)
    np.testing.assert_array_equal(tp.error_bound, wrapped.error_bound)
    np.testing.assert_allclose(tp.displacement, model.network_.predict(d), rtol=0, atol=COMPILED_ATOL)  # one product of 2 B rows
    with pytest.raises(ModelError, match="unknown prediction method 'affine'"):
        model.predictor("affine")


def test_state_round_trip_rebuilds_the_same_model(model, test_fields):
    state = model.get_state()
    assert isinstance(state, ModelState) and state.network is model.network_ and state.trust is model.trusted_.layer
    again = DeformationModel.from_state(state)
    d = model.marker_displacements(test_fields[:20])
    for method in ("mlp", "rigid", "ridge"):
        np.testing.assert_array_equal(again.predict(d, method=method), model.predict(d, method=method))
    np.testing.assert_array_equal(again.predict_trusted(d).error_bound, model.predict_trusted(d).error_bound)
    assert again.pca_choice_ == model.pca_choice_ and again.ridge_.n_components == model.ridge_.n_components
    # without its trust layer the same parts make a model without bounds
    bare = DeformationModel.from_state(dataclasses.replace(state, trust=None))
    assert not bare.has_trust
    np.testing.assert_array_equal(bare.predict(d), model.predict(d))


def test_the_network_refuses_parts_that_do_not_fit(model):
    net = model.network_
    with pytest.raises(ModelError, match="do not fit together"):
        NetworkPredictor(net.mesh, net.markers[:4], net.basis, net.members)
    with pytest.raises(ModelError, match="do not fit together"):
        NetworkPredictor(net.mesh, net.markers, net.basis.truncated(4), net.members)
    with pytest.raises(ModelError, match="distinct 0-based vertex ids"):
        RigidRegistrationPredictor(net.mesh, [0, 0, 1])


def test_trust_wraps_any_predictor_with_calibrated_coverage(model, test_fields):
    """Split conformal bounds cover at the nominal rate whatever the predictor: here the ridge baseline."""
    _, U, _ = trust_data()
    ridge = model.predictor("ridge")
    trusted = TrustedPredictor.fit(ridge, U, train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
                                   calibration_idx=SPLITS["calibration"], coverage=0.9, false_alarm=0.05)
    assert trusted.name == "ridge" and trusted.has_trust and trusted.n_calibration == 300
    d = trusted.marker_displacements(test_fields)
    tp = trusted.predict_trusted(d)
    e = np.linalg.norm(tp.displacement - test_fields, axis=2)
    np.testing.assert_array_equal(tp.displacement, ridge.predict(d))
    assert abs(np.mean(e <= tp.error_bound) - 0.9) < 0.04
    b95 = trusted.predict_trusted(d, coverage=0.95).error_bound
    assert abs(np.mean(e <= b95) - 0.95) < 0.03 and (b95 >= tp.error_bound).all()


def test_calibration_from_given_pairs_is_the_split_calibration(model):
    """The layer calibrated on (input, prediction, truth) triples is exactly the split-conformal fit,
    uncalibrated it bounds nothing and never alarms, and its checks fire."""
    _, U, _ = trust_data()
    net = model.network_
    kw = dict(train_idx=SPLITS["train"], valid_idx=SPLITS["valid"], coverage=0.9, false_alarm=0.05, basis=net.basis,
              head=net.head)
    draft = fit_trust_layer(net, U, **kw)
    d = net.marker_displacements(U[SPLITS["test"][:5]])
    tp = TrustedPredictor(net, draft).predict_trusted(d)
    assert np.isinf(tp.error_bound).all() and not any(a.raised for a in tp.alarms)
    triples = held_out_predictions(net, U, SPLITS["calibration"])
    layer = draft.calibrate(*triples)
    split = fit_trust(net, U, calibration_idx=SPLITS["calibration"], **kw)
    np.testing.assert_array_equal(layer.conformal.sorted_scores, split.conformal.sorted_scores)
    np.testing.assert_array_equal(layer.ood.calibration, split.ood.calibration)
    again = TrustedPredictor(net, draft).calibrate(*triples)
    np.testing.assert_array_equal(again.predict_trusted(d).error_bound,
                                  TrustedPredictor(net, split).predict_trusted(d).error_bound)
    with pytest.raises(ModelError, match="calibration needs inputs"):
        draft.calibrate(triples[0], triples[1], triples[2][:, :10])
    with pytest.raises(ModelError, match="trust layer is for markers"):
        TrustedPredictor(RigidRegistrationPredictor(net.mesh, net.markers[:4]), layer)


def test_the_network_decodes_its_trust_layer_s_second_predictor_in_the_same_pass(model, test_fields):
    """A trust layer whose second predictor works in the network's basis (the quadratic head of a
    model with one): field and second prediction come from one product, equal to the two separate
    decodes; any other basis (this synthetic model's own layer has one), or another predictor,
    decodes them apart."""
    from tissuecast.surrogate.pca import PCABasis
    from tissuecast.surrogate.quadratic import fit_quadratic

    net, own = model.predictor("mlp"), model.trusted_.layer
    assert not net.decodes_with(own.basis)
    mesh, U, _ = trust_data()
    train = U[SPLITS["train"]].reshape(len(SPLITS["train"]), -1)
    X = model.marker_displacements(U[SPLITS["train"]]).reshape(len(train), -1)
    layer = dataclasses.replace(own, basis=net.basis, second=fit_quadratic(X, net.basis.transform(train)))
    copy = PCABasis(net.basis.mean.copy(), net.basis.components.copy(), net.basis.singular_values, net.basis.n_samples)
    assert net.decodes_with(layer.basis) and net.decodes_with(copy)
    d = model.marker_displacements(test_fields[:7]).reshape(7, -1)
    w2 = layer.second.predict(d)
    u, v = net.predict_and_decode(d, None, layer.basis, w2)
    np.testing.assert_allclose(u, net.predict(d), rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(v.reshape(7, -1), layer.basis.inverse_transform(w2), rtol=0, atol=COMPILED_ATOL)
    # their difference is the weights' difference decoded (float32-relative however small it is)
    w = np.mean([k.predict_weights(d) for k in net.members], axis=0) + (0.0 if net.head is None else net.head.predict(d))
    gap = (w2 - w) @ net.basis.components
    np.testing.assert_allclose((v - u).reshape(7, -1), gap, rtol=0, atol=1e-5 * np.abs(gap).max())
    u1, v1 = net.predict_and_decode(d, None, own.basis, own.second.predict(d))  # apart
    np.testing.assert_array_equal(u1, net.predict(d))
    np.testing.assert_array_equal(v1.reshape(7, -1), own.basis.inverse_transform(own.second.predict(d)))
    # the trusted prediction with the shared pass is the one of the separate decodes
    tp = TrustedPredictor(net, layer).predict_trusted(d)
    bounds, alarms = layer.assess(d, net.predict(d))
    np.testing.assert_allclose(tp.displacement, net.predict(d), rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(tp.error_bound, bounds, rtol=0, atol=COMPILED_ATOL)  # apart: two rounded fields differenced
    np.testing.assert_allclose([a.distance for a in tp.alarms], [a.distance for a in alarms], rtol=1e-12)
