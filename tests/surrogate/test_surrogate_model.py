"""DeformationModel on a small synthetic nonlinear data set: accuracy, persistence, ONNX, errors."""

import json

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.evaluate import summarize
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.fastpath import CompiledSurrogate

from _surrogate_synthetic import COMPILED_ATOL, MARKERS, box_mesh, nonlinear_fields


@pytest.fixture(scope="module")
def data():
    mesh = box_mesh()
    theta = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    return mesh, nonlinear_fields(mesh, theta).astype(np.float32)


@pytest.fixture(scope="module")
def model(data):
    mesh, U = data
    m = DeformationModel(epochs=300, patience=0, batch_size=64, learning_rate=3e-3, ensemble=2, pca_rule="paper",
                         pca_max_error=0.05)
    return m.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=np.arange(350), valid_idx=np.arange(350, 400))


@pytest.fixture(scope="module")
def masked_model(data):
    mesh, U = data
    m = DeformationModel(epochs=150, patience=0, batch_size=64, learning_rate=3e-3, marker_dropout=0.3, n_components=8)
    return m.fit(U, MARKERS, mesh=mesh, train_idx=np.arange(350), valid_idx=np.arange(350, 400))


def test_mlp_beats_ridge_and_pca_rule_is_used(model, data):
    _, U = data
    test = U[400:]
    d = model.marker_displacements(test)
    mlp = summarize(model.predict(d), test)
    ridge = summarize(model.predict_ridge(d), test)
    assert model.n_components == 8  # the data live in 8 PCA directions; the rule at 0.05 mm finds them
    assert model.pca_curve_.chosen == 8
    assert mlp.offset_max < 0.6 * ridge.offset_max, (mlp, ridge)
    assert mlp.offset_mean < 0.6 * ridge.offset_mean


def test_validation_rule_keeps_the_components_the_data_use(data):
    mesh, U = data
    m = DeformationModel(epochs=300, patience=0, batch_size=64, learning_rate=3e-3, ensemble=2, pca_max_components=30)
    m.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=np.arange(350), valid_idx=np.arange(350, 400))
    choice = m.pca_choice_
    assert choice["rule"].startswith("validation") and choice["trained_components"] == 30
    # the fields live in 8 PCA directions: the floor vanishes there and the model stops improving
    curve = choice["validation_curve"]
    assert m.n_components == 8
    assert curve["floor_offset_max"][7] < 1e-4 < curve["floor_offset_max"][6]
    assert min(curve["model_offset_max"]) >= curve["model_offset_max"][7] / 1.01
    # the truncated model is the one the curve measured (in float64: the compiled predictor's
    # float32 rounding is as large as this model's error)
    valid = U[350:400].astype(np.float64)
    d = m.marker_displacements(valid).reshape(50, -1)
    net = m.network_
    w = np.mean([k.predict_weights(d) for k in net.members], axis=0) + net.head.predict(d)
    u = net.basis.inverse_transform(w).reshape(valid.shape)
    e = np.linalg.norm(u - valid, axis=2).max(axis=1).mean()
    assert e == pytest.approx(curve["model_offset_max"][7], rel=1e-4)
    np.testing.assert_allclose(m.predict(d), u, rtol=0, atol=COMPILED_ATOL)
    assert all(w.weights[-1].shape[0] == 8 for w in m.network_.members)


def test_input_layouts_agree(model, data):
    _, U = data
    d = model.marker_displacements(U[400:404])  # (4, 5, 3)
    batch = model.predict(d)
    assert batch.shape == (4, 270, 3)
    np.testing.assert_allclose(model.predict(d.reshape(4, 15)), batch)
    np.testing.assert_allclose(model.predict(d[1]), batch[1])
    np.testing.assert_allclose(model.predict(d[1].ravel()), batch[1])
    # tracked positions = reference positions + displacements
    pos = model.reference_marker_positions + d[2]
    np.testing.assert_allclose(model.predict_from_positions(pos), batch[2], atol=1e-9)
    np.testing.assert_allclose(model.reference_marker_positions, model.mesh.points[MARKERS])
    # positions take predict's layouts: flat, a batch of flat rows, a batch of (n_d, 3)
    positions = model.reference_marker_positions + d
    np.testing.assert_allclose(model.predict_from_positions(pos.ravel()), batch[2], atol=1e-9)
    np.testing.assert_allclose(model.predict_from_positions(positions.reshape(4, 15)), batch, atol=1e-9)
    np.testing.assert_allclose(model.predict_from_positions(positions), batch, atol=1e-9)
    layouts = r"marker positions must be \(5, 3\), \(15,\), \(B, 5, 3\) or \(B, 15\) mm, got \(4, 14\)"
    with pytest.raises(ModelError, match=layouts):
        model.predict_from_positions(positions.reshape(4, 15)[:, :14])


def test_fast_path_matches_plain_forward(model, data):
    _, U = data
    d = model.marker_displacements(U[400:410]).reshape(10, -1)
    w = np.mean([m.predict_weights(d) for m in model.network_.members], axis=0)
    assert model.network_.head is not None  # the default: the networks correct a quadratic head
    w += model.network_.head.predict(d)  # the plain (unfolded) regression
    ref = model.network_.basis.inverse_transform(w).reshape(10, -1, 3)
    np.testing.assert_allclose(model.predict(d), ref, rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(model.predict(d[3]), ref[3], rtol=0, atol=COMPILED_ATOL)  # the single-sample path
    # the folding itself is exact: compiled in float64 it is the plain forward pass to round-off
    net = model.network_
    twin = CompiledSurrogate(net.members, net.basis, net.head, dtype=np.float64)
    np.testing.assert_allclose(twin.fields(d).reshape(ref.shape), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(twin.field(d[3]).reshape(ref[3].shape), ref[3], rtol=0, atol=1e-9)
    w64 = twin.member_weights(d)
    np.testing.assert_allclose(CompiledSurrogate(net.members, net.basis, net.head).member_weights(d), w64, rtol=0,
                               atol=1e-5 * np.abs(w64).max())


def test_torch_module_matches_numpy(model, data):
    torch = pytest.importorskip("torch")
    _, U = data
    d = model.marker_displacements(U[400:410])
    with torch.no_grad():
        out = model.torch_module()(torch.as_tensor(d, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(out, model.predict(d), atol=2e-5 * np.abs(U).max())


def test_uncertainty_from_ensemble(model, data):
    _, U = data
    d = model.marker_displacements(U[400:420])
    u, sigma = model.predict_with_uncertainty(d)
    np.testing.assert_allclose(u, model.predict(d), rtol=0, atol=COMPILED_ATOL)
    assert sigma.shape == (20, 270) and (sigma >= 0).all() and sigma.max() > 0
    # two members: sigma is half the distance between their fields
    W = model.network_.member_weights(d.reshape(20, -1))
    f = (W @ model.network_.basis.components).reshape(2, 20, 270, 3)
    np.testing.assert_allclose(sigma, 0.5 * np.linalg.norm(f[0] - f[1], axis=-1), atol=1e-9)
    u1, s1 = model.predict_with_uncertainty(d[0])
    assert u1.shape == (270, 3) and s1.shape == (270,)


def test_save_load_round_trip(model, data, tmp_path):
    _, U = data
    model.save(tmp_path / "m")
    loaded = DeformationModel.load(tmp_path / "m")
    d = model.marker_displacements(U[400:])
    np.testing.assert_array_equal(loaded.predict(d), model.predict(d))
    np.testing.assert_array_equal(loaded.predict_ridge(d), model.predict_ridge(d))
    np.testing.assert_array_equal(loaded.markers, MARKERS)
    np.testing.assert_array_equal(loaded.fixed, [0, 1, 2])
    np.testing.assert_array_equal(loaded.mesh.tets, model.mesh.tets)
    # the points to track, as 3D Slicer reads them: the model's markers in its order, LPS
    from tissuecast.slicer.markups import read_markups

    lists = {m.name: m for m in read_markups(tmp_path / "m" / "markers.mrk.json")}
    np.testing.assert_allclose(lists["FiducialMarkers"].positions, model.reference_marker_positions)
    assert lists["FiducialMarkers"].labels == tuple(f"M{k}" for k in range(len(MARKERS)))
    np.testing.assert_allclose(lists["FixedVertices"].positions, model.mesh.points[[0, 1, 2]])
    assert loaded.ensemble_size == 2 and loaded.pca_curve_.chosen == 8
    assert loaded.pca_choice_ == model.pca_choice_ and loaded.pca_choice_["rule"].startswith("paper")
    np.testing.assert_array_equal(loaded.predict(d, method="rigid"), model.predict(d, method="rigid"))
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["units"]["length"] == "mm" and meta["markers"] == MARKERS.tolist()
    assert not list(tmp_path.glob("m/*.pkl")) and not list(tmp_path.glob("m/*.pt"))


def test_rigid_and_ridge_methods_of_predict(model, data):
    from scipy.spatial.transform import Rotation

    from tissuecast.errors import RegistrationError

    mesh, U = data
    d = model.marker_displacements(U[400:403])
    np.testing.assert_array_equal(model.predict(d, method="ridge"), model.predict_ridge(d))
    np.testing.assert_array_equal(model.predict(d, method="rigid"), model.predict_rigid(d))
    # a rigid motion of the markers moves the whole mesh rigidly, exactly
    p = mesh.points
    rot = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix()
    truth = p @ rot.T + [1.0, -2.0, 3.0] - p
    np.testing.assert_allclose(model.predict(truth[MARKERS], method="rigid"), truth, atol=1e-9)
    np.testing.assert_allclose(model.predict_from_positions(p[MARKERS] + truth[MARKERS], method="rigid"), truth, atol=1e-9)
    # an untracked marker is left out of the fit; the other four still determine the motion
    moved = truth[MARKERS].copy()
    moved[1] = np.nan
    np.testing.assert_allclose(model.predict(moved, missing=[1], method="rigid"), truth, atol=1e-9)
    with pytest.raises(RegistrationError, match="at least 3"):
        model.predict(moved, missing=[0, 1, 2], method="rigid")
    with pytest.raises(ModelError, match="unknown prediction method"):
        model.predict(d, method="kabsch")
    with pytest.raises(ModelError, match="missing markers"):
        model.predict(d, missing=[1], method="ridge")
    # a markers-only model refuses instrument poses or parameters rather than ignore them
    for given in ({"youngs_modulus": 1.3}, {"retractor": None}, np.zeros(3)):
        with pytest.raises(ModelError, match="this model reads the markers only; auxiliary inputs"):
            model.predict(d, auxiliary=given)
        with pytest.raises(ModelError, match="this model reads the markers only"):
            model.predict_from_positions(model.reference_marker_positions + d, auxiliary=given)
    np.testing.assert_array_equal(model.predict(d, auxiliary={}), model.predict(d))
    with pytest.raises(ModelError, match="no sample to predict: .* a batch of 0"):
        model.predict(np.zeros((0, len(MARKERS), 3)))


def test_onnx_equals_numpy(model, data, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    _, U = data
    model.export_onnx(tmp_path / "m.onnx")
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    d = model.marker_displacements(U[400:450]).astype(np.float32)
    (out,) = sess.run(["displacement"], {"markers": d})
    assert out.shape == (50, 270, 3)
    np.testing.assert_allclose(out, model.predict(d), atol=1e-5 * max(1.0, np.abs(U).max()))
    (one,) = sess.run(None, {"markers": d[:1]})
    np.testing.assert_allclose(one[0], model.predict(d[0]), atol=1e-5 * max(1.0, np.abs(U).max()))
    # the file alone says what its inputs are: displacements (not positions), mm, LPS, which markers
    meta = sess.get_modelmeta().custom_metadata_map
    assert "displacement from its reference position (not its position), mm" in meta["markers"] and "LPS" in meta["markers"]
    assert json.loads(meta["marker_vertex_ids"]) == model.markers.tolist()
    np.testing.assert_allclose(json.loads(meta["reference_marker_positions_mm"]), model.reference_marker_positions, atol=1e-6)
    assert meta["checks"].startswith("none") and "auxiliary" not in meta and "present" not in meta


def test_missing_markers(masked_model, model, data, tmp_path):
    _, U = data
    test = U[400:]
    d = masked_model.marker_displacements(test)
    full = summarize(masked_model.predict(d), test).offset_mean
    d_nan = d.copy()
    d_nan[:, 2] = np.nan
    missing = masked_model.predict(d_nan, missing=[2])
    assert summarize(missing, test).offset_mean < 3 * full + 0.5
    # the value given for a missing marker is ignored
    np.testing.assert_allclose(masked_model.predict(d * 1.0, missing=[2]), missing)
    mask = np.zeros(5, bool)
    mask[2] = True
    np.testing.assert_allclose(masked_model.predict(d_nan, missing=mask), missing)
    # the masked fast path equals the plain forward pass with present channels
    present = np.ones((len(d), 5))
    present[:, 2] = 0
    w = masked_model.network_.members[0].predict_weights(np.nan_to_num(d_nan).reshape(len(d), -1), present)
    reference = masked_model.network_.basis.inverse_transform(w).reshape(missing.shape)
    np.testing.assert_allclose(missing, reference, rtol=0, atol=COMPILED_ATOL)
    net = masked_model.network_
    twin = CompiledSurrogate(net.members, net.basis, net.head, dtype=np.float64)  # the folding, to round-off
    mask = np.zeros((len(d), 5), bool)
    mask[:, 2] = True
    np.testing.assert_allclose(twin.fields(np.nan_to_num(d_nan).reshape(len(d), -1), mask).reshape(missing.shape),
                               reference, rtol=0, atol=1e-9)
    with pytest.raises(ModelError, match="marker_dropout"):
        model.predict(d[0], missing=[1])
    masked_model.save(tmp_path / "mm")
    np.testing.assert_array_equal(DeformationModel.load(tmp_path / "mm").predict(d_nan, missing=[2]), missing)


def test_onnx_with_missing_markers(masked_model, data, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    _, U = data
    masked_model.export_onnx(tmp_path / "mm.onnx")
    sess = ort.InferenceSession(str(tmp_path / "mm.onnx"), providers=["CPUExecutionProvider"])
    d = masked_model.marker_displacements(U[400:410]).astype(np.float32)
    present = np.ones((10, 5), np.float32)
    present[:, 4] = 0
    (out,) = sess.run(None, {"markers": d, "present": present})
    np.testing.assert_allclose(out, masked_model.predict(d, missing=[4]), atol=1e-5 * np.abs(U).max())


def test_training_is_deterministic(data):
    mesh, U = data
    kw = dict(epochs=20, patience=0, n_components=8, batch_size=64, noise_sigma=0.1, marker_dropout=0.2)
    a = DeformationModel(**kw).fit(U[:200], MARKERS, mesh=mesh, valid_idx=np.arange(150, 200))
    b = DeformationModel(**kw).fit(U[:200], MARKERS, mesh=mesh, valid_idx=np.arange(150, 200))
    for wa, wb in zip(a.network_.members[0].weights, b.network_.members[0].weights):
        np.testing.assert_array_equal(wa, wb)
    c = DeformationModel(seed=1, **kw).fit(U[:200], MARKERS, mesh=mesh, valid_idx=np.arange(150, 200))
    assert not np.array_equal(a.network_.members[0].weights[0], c.network_.members[0].weights[0])


def test_train_mlp_reads_its_settings_from_the_surrogate_config(data):
    from tissuecast.config import SurrogateConfig
    from tissuecast.surrogate.mlp import train_mlp

    mesh, U = data
    X = U[:60][:, MARKERS].reshape(60, -1)
    Y = U[:60, :4, 0]
    cfg = SurrogateConfig(hidden=(8,), epochs=5, patience=0, seed=7, batch_size=16)
    w, s = train_mlp(X[:50], Y[:50], X[50:], Y[50:], cfg)
    w7, _ = train_mlp(X[:50], Y[:50], X[50:], Y[50:], cfg, seed=7)
    w8, _ = train_mlp(X[:50], Y[:50], X[50:], Y[50:], cfg, seed=8)
    assert s.seed == 7 and s.epochs_run == 5 and w.hidden == (8,)
    np.testing.assert_array_equal(w.weights[0], w7.weights[0])
    assert not np.array_equal(w.weights[0], w8.weights[0])
    for bad, match in ((dict(schedule="linear"), "schedule 'linear'"), (dict(output_scaling="each"), "output_scaling 'each'")):
        with pytest.raises(ModelError, match=match):
            train_mlp(X[:50], Y[:50], X[50:], Y[50:], SurrogateConfig(**bad))
    with pytest.raises(ModelError, match="do not match"):
        train_mlp(X[:50], Y[:50], X[50:, :6], Y[50:], cfg)


def test_bad_inputs_raise_model_error(model, data, tmp_path):
    mesh, U = data
    with pytest.raises(ModelError, match="not fitted"):
        DeformationModel().predict(np.zeros(15))
    with pytest.raises(ModelError, match="shape"):
        model.predict(np.zeros(14))
    with pytest.raises(ModelError, match="shape"):
        model.predict(np.zeros((2, 4, 3)))
    with pytest.raises(ModelError, match="NaN"):
        model.predict(np.full(15, np.nan))
    with pytest.raises(ModelError, match="ensemble"):
        DeformationModel(epochs=2, n_components=4).fit(U[:40], MARKERS, mesh=mesh).predict_with_uncertainty(np.zeros(15))
    with pytest.raises(ModelError, match="vertices"):
        DeformationModel().fit(U[:, :100], MARKERS, mesh=mesh)
    with pytest.raises(ModelError, match="markers"):
        DeformationModel().fit(U, [1, 1, 2], mesh=mesh)
    bad = U[:60].copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(ModelError, match="NaN"):
        DeformationModel(epochs=2).fit(bad, MARKERS, mesh=mesh)
    with pytest.raises(ValueError, match="hidden"):
        DeformationModel(hidden=())
    # incompatible or missing model folders
    with pytest.raises(ModelError, match="not a model folder"):
        DeformationModel.load(tmp_path)
    model.save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    meta["schema"] = 99
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="schema 99"):
        DeformationModel.load(tmp_path / "m")
    meta["schema"] = 1
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    (tmp_path / "m" / "pca.npz").unlink()
    with pytest.raises(ModelError, match="missing"):
        DeformationModel.load(tmp_path / "m")


def test_fit_log_lines_name_the_network_and_report_progress(data, caplog, monkeypatch):
    """Every network a fit trains says which it is (the model or its fallback, a calibration fold,
    an ensemble member), and a fit running longer than PROGRESS_SECONDS says how far it is."""
    import logging

    from tissuecast.surrogate import fit_stage, mlp
    from tissuecast.surrogate.auxiliary import AuxiliaryValues

    from _instrument_synthetic import INPUTS, instrument_data

    monkeypatch.setattr(mlp, "PROGRESS_SECONDS", 0.0)
    mesh, U, _, A = instrument_data()
    kw = dict(epochs=3, patience=0, batch_size=64, n_components=4, hidden=(8,), ensemble=2, calibration="cross-validation",
              calibration_folds=2, calibration_fold_ensemble=1)
    with caplog.at_level(logging.INFO, logger="tissuecast.surrogate.mlp"), fit_stage("nominal expert"):
        DeformationModel(**kw).fit(U[:120], MARKERS, mesh=mesh, valid_idx=np.arange(100, 120),
                                   auxiliary=AuxiliaryValues(INPUTS, A[:120]))
    trained = [r.getMessage() for r in caplog.records if r.getMessage().startswith("trained")]
    labels = [m.split("(", 1)[1].split(")", 1)[0] for m in trained]
    assert labels == ["nominal expert, model, member 1/2", "nominal expert, model, member 2/2",
                      "nominal expert, model, calibration fold 1/2", "nominal expert, model, calibration fold 2/2",
                      "nominal expert, markers-only fallback, member 1/2",
                      "nominal expert, markers-only fallback, member 2/2",
                      "nominal expert, markers-only fallback, calibration fold 1/2",
                      "nominal expert, markers-only fallback, calibration fold 2/2"]
    progress = [r.getMessage() for r in caplog.records if ": epoch " in r.getMessage()]
    # every epoch but the last of each of the 8 fits
    assert len(progress) == 8 * 2
    assert progress[0].startswith("training MLP [8] seed 0 (nominal expert, model, member 1/2): epoch 1/3, validation loss")
    assert "left (less if it stops early)" in progress[0]


def test_training_runs_on_the_configured_threads_and_restores_torchs(data, monkeypatch):
    import torch

    from tissuecast.config import SurrogateConfig
    from tissuecast.surrogate import mlp

    mesh, U = data
    X = U[:60][:, MARKERS].reshape(60, -1)
    seen = []
    fit = mlp._fit

    def spy(torch_, *args, **kwargs):
        seen.append(torch_.get_num_threads())
        return fit(torch_, *args, **kwargs)

    monkeypatch.setattr(mlp, "_fit", spy)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        for threads in (1, 2):
            mlp.train_mlp(X[:50], U[:50, :4, 0], X[50:], U[50:60, :4, 0], SurrogateConfig(hidden=(8,), epochs=2, threads=threads))
            assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
    assert seen == [1, 2]
    assert SurrogateConfig().threads == 2
