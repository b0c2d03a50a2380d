"""Training on the simulator's sensitivities (Sobolev training, tissuecast.surrogate.mlp): with
fewer samples than inputs the values leave the map undetermined and the directional
derivatives determine it; the fit path projects field sensitivities on the decoder."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.config import SurrogateConfig
from tissuecast.dataset.sensitivities import Sensitivities
from tissuecast.errors import ModelError
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.mlp import Tangents, train_mlp
from tissuecast.surrogate.network_fit import _tangents
from tissuecast.surrogate.pca import fit_pca

from _surrogate_synthetic import COMPILED_ATOL, MARKERS, box_mesh, nonlinear_fields

pytest.importorskip("torch")


def _linear_problem(n_train: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(9, 5))
    X, Xv, Xt = (rng.normal(size=(m, 9)) for m in (n_train, 16, 200))
    return B, X, Xv, Xt


def _mse(w, Xt, B):
    return float(np.mean((w.predict_weights(Xt) - Xt @ B) ** 2) / np.mean((Xt @ B) ** 2))


def test_derivatives_determine_what_too_few_values_cannot():
    B, X, Xv, Xt = _linear_problem(4)
    base = SurrogateConfig(hidden=(32,), epochs=1500, batch_size=4, patience=0, head="none")
    dX = np.broadcast_to(np.eye(9), (4, 9, 9)).copy()  # every input direction at every sample
    dY = np.broadcast_to(B, (4, 9, 5)).copy()
    plain, _ = train_mlp(X, X @ B, Xv, Xv @ B, base)
    sob, _ = train_mlp(X, X @ B, Xv, Xv @ B, SurrogateConfig(**{**base.__dict__, "sensitivity_weight": 1.0,
                                                                 "sensitivity_directions": 9}),
                       tangents=Tangents(dX, dY))
    e_plain, e_sob = _mse(plain, Xt, B), _mse(sob, Xt, B)
    assert e_plain > 0.5  # 4 samples of a map of 9 inputs: most of it unseen
    assert e_sob < 0.1 * e_plain


def test_tangents_off_or_missing_train_as_without():
    B, X, Xv, _ = _linear_problem(6)
    c = SurrogateConfig(hidden=(8,), epochs=20, batch_size=6, patience=0, head="none")
    dX = np.full((6, 2, 9), np.nan)
    plain, _ = train_mlp(X, X @ B, Xv, Xv @ B, c)
    off, _ = train_mlp(X, X @ B, Xv, Xv @ B, c, tangents=Tangents(np.zeros((6, 2, 9)), np.ones((6, 2, 5))))
    none, _ = train_mlp(X, X @ B, Xv, Xv @ B, SurrogateConfig(**{**c.__dict__, "sensitivity_weight": 1.0}),
                        tangents=Tangents(dX, np.zeros((6, 2, 5))))
    for w in (off, none):  # weight 0, or no sample with finite tangents: bit-identical to values only
        for a, b in zip(plain.weights, w.weights):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ModelError, match="tangents"):
        train_mlp(X, X @ B, Xv, Xv @ B, SurrogateConfig(**{**c.__dict__, "sensitivity_weight": 1.0}),
                  tangents=Tangents(np.zeros((5, 2, 9)), np.zeros((5, 2, 5))))


def test_field_sensitivities_project_on_the_decoder_and_the_markers():
    rng = np.random.default_rng(1)
    n, k = 12, 3
    U = rng.normal(size=(40, 3 * n))
    pca = fit_pca(U, 6)
    markers = np.array([2, 5, 9])
    S = rng.normal(size=(40, k, n, 3))
    Xt = U[:, (3 * markers[:, None] + np.arange(3)).ravel()]
    t = _tangents(S, pca, markers, np.hstack([Xt, np.ones((40, 2))]), None)
    assert t.inputs.shape == (40, k, 11) and t.outputs.shape == (40, k, 6)
    np.testing.assert_allclose(t.inputs[:, :, :9], S[:, :, markers, :].reshape(40, k, 9))
    np.testing.assert_array_equal(t.inputs[:, :, 9:], 0.0)  # the instrument's pose is held
    np.testing.assert_allclose(t.outputs, S.reshape(40, k, -1) @ pca.components.T, atol=1e-12)


# ---------------------------------------------------------------------- a model trained on them
def _fields_and_sensitivities(mesh, theta, h=1e-4):
    """Fields of the synthetic family and their central-difference derivatives along each latent
    parameter: (N, n, 3), (N, 3, n, 3) mm."""
    U = nonlinear_fields(mesh, theta)
    S = np.stack([(nonlinear_fields(mesh, theta + h * e) - nonlinear_fields(mesh, theta - h * e)) / (2 * h)
                  for e in np.eye(3)], axis=1)
    return U, S


@pytest.fixture(scope="module")
def silu_models():
    mesh = box_mesh()
    theta = np.random.default_rng(3).uniform(-1, 1, (240, 3))
    U, S = _fields_and_sensitivities(mesh, theta)
    cfg = dict(epochs=300, patience=0, batch_size=16, n_components=6, hidden=(32, 32), activation="silu",
               calibration_share=0.0, head="none")
    train, valid = np.arange(24), np.arange(24, 40)  # few samples: 24 fields of a 3-parameter family
    plain = DeformationModel(**cfg).fit(U[:40], MARKERS, mesh=mesh, train_idx=train, valid_idx=valid)
    sob = DeformationModel(**cfg, sensitivity_weight=1.0, sensitivity_directions=3).fit(
        U[:40], MARKERS, mesh=mesh, train_idx=train, valid_idx=valid, sensitivities=Sensitivities(train, S[train]))
    return mesh, U, plain, sob


def test_a_model_trained_on_sensitivities_is_more_accurate(silu_models):
    mesh, U, plain, sob = silu_models
    test = U[40:]
    d = plain.marker_displacements(test)
    err = [np.linalg.norm(m.predict(d) - test, axis=2).max(axis=1).mean() for m in (plain, sob)]
    floor = np.linalg.norm(plain.pca_projection(test) - test, axis=2).max(axis=1).mean()
    assert err[1] < 0.7 * err[0] and err[1] > floor


def test_silu_networks_agree_across_numpy_torch_onnx_and_the_folder(silu_models, tmp_path):
    torch = pytest.importorskip("torch")
    _, U, _, model = silu_models
    assert model.network_.members[0].activation == "silu"
    d = model.marker_displacements(U[40:60])
    net = model.network_
    ref = net.basis.inverse_transform(net.members[0].predict_weights(d.reshape(len(d), -1))).reshape(d.shape[0], -1, 3)
    np.testing.assert_allclose(model.predict(d), ref, rtol=0, atol=COMPILED_ATOL)
    with torch.no_grad():
        out = model.torch_module()(torch.as_tensor(d, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(out, ref, atol=2e-5 * np.abs(U).max())
    model.save(tmp_path / "m")
    loaded = DeformationModel.load(tmp_path / "m")
    np.testing.assert_array_equal(loaded.predict(d), model.predict(d))
    ort = pytest.importorskip("onnxruntime")
    model.export_onnx(tmp_path / "m.onnx")
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(sess.run(None, {"markers": d.astype(np.float32)})[0], ref, atol=2e-5 * np.abs(U).max())


def test_settings_that_cannot_train_on_sensitivities_are_refused():
    from tissuecast.config import Config, with_overrides
    from tissuecast.errors import ConfigError

    with pytest.raises(ConfigError, match="marker_dropout = 0"):
        with_overrides(Config(), surrogate={"sensitivity_weight": 1.0, "marker_dropout": 0.1})
    with pytest.raises(ConfigError, match="activation"):
        with_overrides(Config(), surrogate={"activation": "tanh"})


def test_the_fit_records_what_it_trained_on(silu_models):
    _, _, plain, sob = silu_models
    assert plain.training_["sensitivities"] is None
    assert sob.training_["sensitivities"] == {"weight": 1.0, "directions": 3, "samples": 24}


def test_sensitivities_of_other_fields_are_refused(silu_models):
    mesh, U, _, _ = silu_models
    wrong = Sensitivities(np.arange(4), np.zeros((4, 3, mesh.n_vertices - 1, 3), dtype=np.float32))
    with pytest.raises(ModelError, match="do not match the fields"):
        DeformationModel(hidden=(8,), epochs=2, sensitivity_weight=1.0, calibration_share=0.0).fit(
            U[:40], MARKERS, mesh=mesh, train_idx=np.arange(24), valid_idx=np.arange(24, 40), sensitivities=wrong)


def test_train_mlp_refuses_tangents_with_missing_marker_input():
    B, X, Xv, _ = _linear_problem(6)
    c = SurrogateConfig(hidden=(8,), epochs=2, batch_size=6, patience=0, head="none", sensitivity_weight=1.0,
                        marker_dropout=0.2)
    with pytest.raises(ModelError, match="marker_dropout = 0"):
        train_mlp(X, X @ B, Xv, Xv @ B, c, tangents=Tangents(np.zeros((6, 2, 9)), np.zeros((6, 2, 5))))
