"""A nominal expert beside a model, routed by a gate (tissuecast.surrogate.experts), on synthetic fields."""

import copy
import dataclasses
import functools

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.experts import GATE_FEATURES, ExpertGate, RouteCalibration, gate_features, out_of_fold_routes

from _surrogate_synthetic import COMPILED_ATOL, MARKERS, nonlinear_fields
from _trust_synthetic import SPLITS, trust_data


#: The expert's family: |third latent| below this (the whole family spans [-1, 1]).
NOMINAL_BAND = 0.3


def _small_model(U: np.ndarray) -> DeformationModel:
    """A small calibrated network on fields U (1100, n, 3) split as the trust tests' first 1100:
    too small for the whole family, so that a narrower family suits it better."""
    m = DeformationModel(epochs=60, patience=0, batch_size=32, learning_rate=3e-3, n_components=8, hidden=(12,),
                         head="none", seed=1)
    return m.fit(U, MARKERS, mesh=trust_data()[0], fixed=[0, 1, 2], train_idx=SPLITS["train"],
                 valid_idx=SPLITS["valid"], calibration_idx=SPLITS["calibration"])


@functools.lru_cache(maxsize=None)
def uncertain_model() -> DeformationModel:
    """Trained on the whole family (every latent drawn in [-1, 1])."""
    return _small_model(trust_data()[1][:1100])


@functools.lru_cache(maxsize=None)
def expert_model() -> DeformationModel:
    """Trained on a narrower family of as many samples (the third latent within
    +-NOMINAL_BAND, as a nominal parameter): the better one there, the worse elsewhere."""
    theta = np.random.default_rng(11).uniform(-1, 1, (1100, 3)) * [1.0, 1.0, NOMINAL_BAND]
    return _small_model(nonlinear_fields(trust_data()[0], theta))


@functools.lru_cache(maxsize=None)
def gated() -> DeformationModel:
    _, U, _ = trust_data()
    return uncertain_model().with_nominal_expert(expert_model(), U[SPLITS["valid"]])


def test_route_calibration_covers_each_route_at_its_level():
    """Errors of known distributions on each route: uniform on [0, 0.5] x bound on one route,
    [0, 2] x bound on the other; the per-route quantiles give each route its coverage."""
    rng = np.random.default_rng(5)
    B, n = 400, 30
    bound = rng.uniform(0.5, 3.0, (B, n))
    bound[:, 0] = 0.0  # a held vertex: no bound to scale, the model's own is kept
    route = np.arange(B) % 2 == 0
    errors = rng.uniform(0, 1, (B, n)) * np.where(route[:, None], 0.5, 2.0) * bound
    # each route reads its own model's errors (the other model's, 100 mm off, must not count)
    calib = RouteCalibration.fit(route, errors + 100.0 * ~route[:, None], errors + 100.0 * route[:, None], bound)
    assert calib.summary() == {"expert_samples": 200, "model_samples": 200}
    fresh_bound = rng.uniform(0.5, 3.0, (2000, n))
    fresh_route = rng.uniform(size=2000) < 0.3
    fresh = rng.uniform(0, 1, (2000, n)) * np.where(fresh_route[:, None], 0.5, 2.0) * fresh_bound
    for level in (0.8, 0.9):
        b = calib.bounds(fresh_route, fresh_bound, level)
        for r in (fresh_route, ~fresh_route):
            assert abs(np.mean(fresh[r][:, 1:] <= b[r][:, 1:]) - level) < 0.03
    b = calib.bounds(fresh_route, fresh_bound, 0.9)
    np.testing.assert_allclose(b[fresh_route, 1:] / fresh_bound[fresh_route, 1:], 0.45, atol=0.05)  # 0.9 x 0.5
    assert (calib.bounds(route, bound, 0.9)[:, 0] == 0.0).all()  # the held vertex: no error, no bound
    assert np.isnan(calib.bounds(route, bound, 0.999)).all()  # 200 samples a route cannot say 99.9 %
    back = RouteCalibration.from_arrays(calib.arrays())
    np.testing.assert_allclose(back.bounds(fresh_route, fresh_bound, 0.9), b, rtol=1e-6)
    with pytest.raises(ModelError, match="damaged"):
        RouteCalibration.from_arrays({"expert": np.zeros((3, 4)), "model": np.zeros((3, 5))})


def test_out_of_fold_routes_come_from_gates_that_did_not_see_the_sample():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(300, len(GATE_FEATURES)))
    y = X[:, 0] + 0.5 * rng.normal(size=300) > 0
    routes = out_of_fold_routes(X, y, folds=3)
    held = np.arange(300) % 3 == 1
    np.testing.assert_array_equal(routes[held], ExpertGate.fit(X[~held], y[~held]).to_nominal(X[held]))
    assert 0.8 < np.mean(routes == y) < 0.95  # the rule learned, the noise not
    one = np.where(held, y, True)  # fold 1's others all say "the expert": so is fold 1 routed, whatever it holds
    assert out_of_fold_routes(X, one, folds=3)[held].all() and not one[held].all()


def test_gate_fit_recovers_a_logistic_rule_and_round_trips():
    rng = np.random.default_rng(3)
    f = len(GATE_FEATURES)
    X = rng.normal(size=(6000, f)) * rng.uniform(0.5, 3.0, f) + rng.normal(size=f)
    w_true = np.array([1.5, -2.0])
    z = ((X - X.mean(0)) / X.std(0)) @ w_true + 0.3
    y = rng.uniform(size=len(X)) < 1.0 / (1.0 + np.exp(-z))
    gate = ExpertGate.fit(X, y, penalty=1e-6)
    np.testing.assert_allclose(gate.weights, w_true, atol=0.12)
    assert abs(gate.bias - 0.3) < 0.1 and gate.samples == 6000 and abs(gate.nominal_better - y.mean()) < 1e-12
    p = gate.probability(X)
    assert ((p > 0.5) == (z > 0)).mean() > 0.97
    bad = X[:3].copy()
    bad[1, 1] = np.nan
    bad[2, 0] = np.inf if w_true[0] > 0 else -np.inf  # a certain "expert", were it read
    assert not gate.to_nominal(bad)[1:].any()  # a score missing or infinite: the uncertainty-trained model answers
    back = ExpertGate.from_dict(gate.as_dict())
    np.testing.assert_array_equal(back.probability(X), p)
    with pytest.raises(ModelError, match="reads"):
        ExpertGate.from_dict({**gate.as_dict(), "features": ["a"]})
    with pytest.raises(ModelError, match="nothing to route"):
        ExpertGate.fit(X, np.ones(len(X), bool))
    X[0, 0] = np.inf
    with pytest.raises(ModelError, match="not finite"):
        ExpertGate.fit(X, y)


def test_routed_field_bounds_and_alarm():
    model, expert, pair = uncertain_model(), expert_model(), gated()
    _, U, _ = trust_data()
    test = U[SPLITS["test"]]
    d = test[:, MARKERS, :]
    tp = pair.predict_trusted(d)
    mine, theirs = model.predict_trusted(d), expert.predict_trusted(d)
    router = pair.predictor("mlp")
    features = gate_features(router.expert, router.trusted, d.reshape(len(d), -1), None)
    # the gate reads each model's input distance, the one its alarm reports (log, floored)
    np.testing.assert_allclose(np.exp(features), [[t.distance, m.distance] for t, m in zip(theirs.alarms, mine.alarms)],
                               rtol=1e-12)
    to_nominal = pair.expert_gate_.to_nominal(features)
    np.testing.assert_array_equal(router.route(d.reshape(len(d), -1), None), to_nominal)
    assert 0.05 < to_nominal.mean() < 0.95  # the gate uses both
    # the plain field is the routed one (float32 products of other shapes: their last bits differ)
    np.testing.assert_allclose(pair.predict(d), tp.displacement, rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(tp.displacement[to_nominal], theirs.displacement[to_nominal], rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(tp.displacement[~to_nominal], mine.displacement[~to_nominal], rtol=0, atol=COMPILED_ATOL)
    assert [a.raised for a in tp.alarms] == [a.raised for a in mine.alarms]  # the alarm: the model's own
    # the bounds: calibrated per route on the gate's samples, each route covered at its level
    errors = np.linalg.norm(tp.displacement - test, axis=2)
    for route in (to_nominal, ~to_nominal):
        assert 0.82 < np.mean(errors[route] <= tp.error_bound[route]) < 0.97
    assert not np.allclose(tp.error_bound, mine.error_bound)
    routes = pair.expert_routes_.summary()  # the gate's samples, split by their out-of-fold routes
    assert routes["expert_samples"] + routes["model_samples"] == len(SPLITS["valid"]) and routes["expert_samples"] > 20
    for level in (0.8, 0.95):
        at = pair.predict_trusted(d, coverage=level, alarm=False)
        assert at.coverage == level and abs(np.mean(errors <= at.error_bound) - level) < 0.04
    # 0.99 needs 99 samples a route; the expert's route has fewer: its bounds are the model's own there
    assert pair.expert_routes_.expert.n_calibration < 99
    np.testing.assert_array_equal(pair.predict_trusted(d, coverage=0.99, alarm=False).error_bound[to_nominal],
                                  model.predict_trusted(d, coverage=0.99, alarm=False).error_bound[to_nominal])
    one = pair.predict_trusted(d[0], alarm=False)
    np.testing.assert_allclose(one.displacement, tp.displacement[0], rtol=0, atol=COMPILED_ATOL)  # other BLAS sums
    assert one.alarms is None and pair.alarms(d[0]).raised == mine.alarms[0].raised
    np.testing.assert_allclose(one.error_bound, tp.error_bound[0], rtol=1e-5, atol=1e-12)
    assert one.coverage == tp.coverage
    # near the expert's family the pair is as good as the expert, elsewhere as the model, overall better than both
    worst = {k: np.linalg.norm(u - test, axis=2).max(axis=1) for k, u in
             (("mine", mine.displacement), ("theirs", theirs.displacement), ("pair", tp.displacement))}
    near = np.abs(trust_data()[2][SPLITS["test"], 2]) < NOMINAL_BAND
    assert worst["theirs"][near].mean() < 0.9 * worst["mine"][near].mean()  # the expert's advantage, at home
    assert worst["pair"][near].mean() < 1.05 * worst["theirs"][near].mean()
    assert worst["pair"][~near].mean() < 1.05 * worst["mine"][~near].mean() < 0.5 * worst["theirs"][~near].mean()
    assert worst["pair"].mean() < min(worst["mine"].mean(), worst["theirs"].mean())
    assert pair.has_nominal_expert and not model.has_nominal_expert and not pair.has_uncertainty
    assert pair.bounds_predictor is pair and model.bounds_predictor is model.trusted_  # the routed field, or the network's
    assert pair.describe()["expert_gate"]["samples"] == len(SPLITS["valid"])
    with pytest.raises(ModelError, match="no ensemble spread"):
        pair.predict_with_uncertainty(d)


def test_saved_and_loaded(tmp_path):
    pair = gated()
    _, U, _ = trust_data()
    d = U[SPLITS["test"]][:40, MARKERS, :]
    pair.save(tmp_path / "m")
    assert (tmp_path / "m" / "nominal_expert" / "model.json").exists()
    back = DeformationModel.load(tmp_path / "m")
    assert back.has_nominal_expert
    a, b = pair.predict_trusted(d), back.predict_trusted(d)
    np.testing.assert_array_equal(a.displacement, b.displacement)
    np.testing.assert_allclose(a.error_bound, b.error_bound, rtol=1e-6)  # as any trust layer read back
    np.testing.assert_array_equal(back.expert_gate_.weights, pair.expert_gate_.weights)
    # a pair saved before its bounds were calibrated per route: the uncertain model's bounds
    import json

    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["nominal_expert"]["routes"] == "expert_routes.npz"
    del meta["nominal_expert"]["routes"]
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    old = DeformationModel.load(tmp_path / "m")
    assert old.expert_routes_ is None and old.describe()["expert_gate"]["bounds_per_route"] is None
    np.testing.assert_allclose(old.predict_trusted(d).error_bound, uncertain_model().predict_trusted(d).error_bound,
                               rtol=1e-6)


def test_a_model_saved_over_a_pair_folder_keeps_none_of_the_pair(tmp_path):
    folder = tmp_path / "m"
    gated().save(folder)
    (folder / "nominal_expert" / "notes.txt").write_text("the user's")  # not the layout's: kept
    (folder / "README.txt").write_text("the user's")
    uncertain_model().save(folder)
    assert not (folder / "expert_routes.npz").exists()
    assert sorted(p.name for p in (folder / "nominal_expert").iterdir()) == ["notes.txt"]
    assert (folder / "README.txt").exists()
    back = DeformationModel.load(folder)
    assert not back.has_nominal_expert
    d = trust_data()[1][SPLITS["test"]][:10, MARKERS, :]
    np.testing.assert_array_equal(back.predict(d), uncertain_model().predict(d))
    (folder / "nominal_expert" / "notes.txt").unlink()
    gated().save(folder)  # and a pair over a plain model, then a plain one again: no folder left behind
    uncertain_model().save(folder)
    assert not (folder / "nominal_expert").exists()


def _logit(pair, d, a=None):
    """(B,) the gate's logit (float64) of marker displacements d (B, n_d, 3) mm and auxiliary inputs a."""
    router = pair.predictor("mlp")
    f = gate_features(router.expert, router.trusted, d.reshape(len(d), -1), a)
    g = pair.expert_gate_
    return ((f - g.mean) / g.scale) @ g.weights + g.bias


def test_the_routed_graph_routes_and_predicts_as_the_pair(tmp_path):
    """torch and ONNX graphs of a pair: each sample's route and field are the float64 model's
    (but where the gate's logit lies within float32 round-off of 0), both routes taken."""
    torch = pytest.importorskip("torch")
    ort = pytest.importorskip("onnxruntime")
    pair = gated()
    U = trust_data()[1][SPLITS["test"]]
    d = U[:, MARKERS, :]
    want, routes, logit = pair.predict(d), pair.predictor("mlp").route(d.reshape(len(d), -1), None), _logit(pair, d)
    assert 0.1 < routes.mean() < 0.9 and np.array_equal(routes, logit > 0)
    clear = np.abs(logit) > 1e-3
    assert clear.mean() > 0.95
    tol = 1e-5 * np.abs(U).max()
    module = pair.torch_module()
    x = torch.tensor(d, dtype=torch.float32)
    with torch.no_grad():
        np.testing.assert_array_equal(module.to_nominal(x).numpy()[clear], routes[clear])
        np.testing.assert_allclose(module(x).numpy()[clear], want[clear], atol=tol)
        np.testing.assert_allclose(module.nominal_distance(x.reshape(len(d), -1)).numpy(),
                                   pair.predictor("mlp").expert.input_distance(d), rtol=1e-4)
    # the expert's rows are not the uncertain network's: a graph that ignored the gate would fail above
    assert np.abs(want[routes] - uncertain_model().predict(d[routes])).max() > 100 * tol
    pair.save(tmp_path / "m", onnx=True)
    session = ort.InferenceSession(str(tmp_path / "m" / "model.onnx"), providers=["CPUExecutionProvider"])
    (out,) = session.run(["displacement"], {"markers": d.astype(np.float32)})
    np.testing.assert_allclose(out[clear], want[clear], atol=tol)
    (one,) = session.run(None, {"markers": d[:1].astype(np.float32)})  # a batch of one, as served
    np.testing.assert_allclose(one, out[:1], atol=tol)


def test_the_routed_graph_of_a_masked_pair_leaves_untracked_samples_to_the_model(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    mesh, U, _ = trust_data()
    model = DeformationModel(epochs=30, patience=0, batch_size=32, learning_rate=3e-3, n_components=8, hidden=(12,),
                             head="none", seed=1, marker_dropout=0.3)
    model.fit(U[:1100], MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
              calibration_idx=SPLITS["calibration"])
    pair = model.with_nominal_expert(expert_model(), U[SPLITS["valid"]])
    d = U[SPLITS["test"]][:, MARKERS, :]
    routes, clear = pair.predictor("mlp").route(d.reshape(len(d), -1), None), np.abs(_logit(pair, d)) > 1e-3
    pair.export_onnx(tmp_path / "p.onnx")
    session = ort.InferenceSession(str(tmp_path / "p.onnx"), providers=["CPUExecutionProvider"])
    present = np.ones((len(d), len(MARKERS)), np.float32)
    present[::2, 1] = 0  # every second sample has marker 1 untracked: the uncertain model's alone
    (out,) = session.run(None, {"markers": d.astype(np.float32), "present": present})
    missing = present == 0
    want = pair.predict(d, missing=missing)
    tol = 1e-5 * np.abs(U).max()
    np.testing.assert_allclose(out[clear], want[clear], atol=tol)
    np.testing.assert_allclose(out[::2], model.predict(d[::2], missing=[1]), atol=tol)
    assert routes[1::2][clear[1::2]].any()  # the tracked samples take both routes


def test_exports_name_the_network_and_refusals():
    torch = pytest.importorskip("torch")
    pair, model, expert = gated(), uncertain_model(), expert_model()
    x = torch.tensor(trust_data()[1][SPLITS["test"]][:5, MARKERS, :], dtype=torch.float32)
    with torch.no_grad():
        assert torch.equal(pair.torch_module(expert="nominal")(x), expert.torch_module()(x))
        assert torch.equal(pair.torch_module(expert="uncertain")(x), model.torch_module()(x))
    with pytest.raises(ModelError, match="no nominal expert"):
        model.torch_module(expert="nominal")
    with pytest.raises(ModelError, match="no fallback: it reads no tracked instrument"):
        pair.torch_module(fallback=True)  # the routed graph of two fallbacks needs them
    _, U, _ = trust_data()
    valid = U[SPLITS["valid"]]
    with pytest.raises(ModelError, match="takes no second one"):
        pair.with_nominal_expert(expert, valid)
    mesh = trust_data()[0]
    other = DeformationModel(epochs=2, patience=0, n_components=4, hidden=(8,), head="none")
    other.fit(U, MARKERS[:4], mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
              calibration_idx=SPLITS["calibration"])
    with pytest.raises(ModelError, match="same mesh with the model's markers"):
        model.with_nominal_expert(other, valid)
    with pytest.raises(ModelError, match=r"fields must be \(B, 270, 3\)"):
        model.with_nominal_expert(expert, valid[:, :10])
    with pytest.raises(ModelError, match=r"drawn must be \(B,\) = \(200,\) bool"):
        model.with_nominal_expert(expert, valid, drawn=np.ones(10, bool))
    half = model.with_nominal_expert(expert, valid, drawn=np.arange(len(valid)) < 100)  # bounds on the first 100 alone
    assert sum(half.expert_routes_.summary().values()) == 100


def test_served_like_any_model():
    from tissuecast.serve import SurfacePredictor

    pair = copy.copy(gated())  # its own attributes: alarms is patched below
    d = trust_data()[1][SPLITS["test"]][:3, MARKERS, :]
    served = SurfacePredictor(pair)
    calls = []
    alarms = pair.alarms
    pair.alarms = lambda *a, **k: calls.append(1) or alarms(*a, **k)  # counts the alarms computed after the field
    for row in d:
        p = served.predict(pair.reference_marker_positions + row, 0.0)
        want = pair.predict_trusted(row)
        np.testing.assert_allclose(p.displacement, want.displacement, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p.error_bound, want.error_bound, rtol=0, atol=1e-12)
        assert p.alarm.raised == want.alarms.raised
        # as a server predicts: the field and its bounds first (the gate reads the input
        # distances only), the uncertain model's alarm after, once
        first = served.predict(pair.reference_marker_positions + row, 0.0, alarm=False)
        assert first.alarm is None and first.alarm_inputs is not None
        np.testing.assert_allclose(first.displacement, want.displacement, rtol=0, atol=1e-12)
        np.testing.assert_allclose(first.error_bound, want.error_bound, rtol=0, atol=1e-12)
        late = served.with_alarm(first)
        assert late.alarm.raised == want.alarms.raised
        assert late.alarm.distance == pytest.approx(want.alarms.distance, rel=1e-12)
    assert len(calls) == len(d)


def test_untracked_markers_go_to_the_model_row_by_row():
    """A sample with an untracked marker is the model's alone; the others of its batch are routed
    as they would be without it."""
    mesh, U, _ = trust_data()
    kw = dict(epochs=30, patience=0, batch_size=32, learning_rate=3e-3, n_components=8, hidden=(12,), head="none",
              seed=1, marker_dropout=0.3)
    model = DeformationModel(**kw).fit(U[:1100], MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"],
                                       valid_idx=SPLITS["valid"], calibration_idx=SPLITS["calibration"])
    pair = model.with_nominal_expert(expert_model(), U[SPLITS["valid"]])
    d = U[SPLITS["test"]][:6, MARKERS, :]
    missing = np.zeros((6, len(MARKERS)), bool)
    missing[2, 1] = True
    mixed = pair.predict(d, missing=missing)
    np.testing.assert_allclose(np.delete(mixed, 2, axis=0), pair.predict(np.delete(d, 2, axis=0)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(mixed[2], model.predict(d[2], missing=[1]), rtol=0, atol=1e-12)


def test_an_expert_on_another_mesh_is_refused():
    mesh, U, _ = trust_data()
    from tissuecast.mesh import TetMesh

    moved = TetMesh(mesh.points * 1.01, mesh.tets)  # as many vertices, another body
    other = DeformationModel(epochs=2, patience=0, n_components=4, hidden=(8,), head="none")
    other.fit(U, MARKERS, mesh=moved, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
              calibration_idx=SPLITS["calibration"])
    with pytest.raises(ModelError, match="meshes differ"):
        uncertain_model().with_nominal_expert(other, U[SPLITS["valid"]])


def test_a_pair_with_a_tracked_instrument_keeps_the_fallbacks_bounds_when_tracking_is_lost():
    """The route scores are of the model with its instrument: a sample whose instrument is not
    tracked (the markers-only fallback answers) keeps the model's own bounds; tracked ones get
    the routes'."""
    from _instrument_synthetic import MARKERS as IM, SPLITS as IS, instrument_data, instrument_model

    mesh, U, _, A = instrument_data()
    model = instrument_model()
    other = DeformationModel(epochs=60, patience=0, batch_size=64, n_components=8, hidden=(16,), seed=3)
    other.fit(U, IM, mesh=mesh, fixed=[0, 1, 2], train_idx=IS["train"], valid_idx=IS["valid"],
              calibration_idx=IS["calibration"], auxiliary=_auxiliary(A))
    pair = model.with_nominal_expert(other, U[IS["valid"]], auxiliary=A[IS["valid"]])
    test = IS["test"]
    d, a = U[test][:, IM, :], A[test].copy()
    a[::2] = np.nan  # tracking lost on every second sample
    got, own = pair.predict_trusted(d, auxiliary=a), model.predict_trusted(d, auxiliary=a)
    np.testing.assert_array_equal(got.error_bound[::2], own.error_bound[::2])
    assert not np.allclose(got.error_bound[1::2], own.error_bound[1::2])


def test_the_routed_graphs_of_a_pair_with_a_tracked_instrument(tmp_path):
    """model.onnx routes the two networks with the instrument, fallback/model.onnx the two
    fallbacks without it (the frames whose tracking is lost), each as the pair does."""
    ort = pytest.importorskip("onnxruntime")
    from _instrument_synthetic import MARKERS as IM, SPLITS as IS, instrument_data, instrument_model

    mesh, U, _, A = instrument_data()
    other = DeformationModel(epochs=60, patience=0, batch_size=64, n_components=8, hidden=(16,), seed=3)
    other.fit(U, IM, mesh=mesh, fixed=[0, 1, 2], train_idx=IS["train"], valid_idx=IS["valid"],
              calibration_idx=IS["calibration"], auxiliary=_auxiliary(A))
    pair = instrument_model().with_nominal_expert(other, U[IS["valid"]], auxiliary=A[IS["valid"]])
    d, a = U[IS["test"]][:, IM, :], A[IS["test"]]
    lost = np.full_like(a, np.nan)
    # both experts learnt the same fields: the gate is moved so that each route takes about half
    # the samples with and without the instrument
    g = pair.expert_gate_
    middle = np.median(np.concatenate([_logit(pair, d, a), _logit(pair, d, lost)]))
    pair = DeformationModel.from_state(dataclasses.replace(pair.get_state(), expert_gate=dataclasses.replace(
        g, bias=g.bias - middle)))
    pair.save(tmp_path / "m", onnx=True)
    tol = 2e-4 * max(1.0, np.abs(U).max())
    router = pair.predictor("mlp")
    for graph, feeds, aux in (("model.onnx", {"markers": d, "auxiliary": a}, a),
                              ("fallback/model.onnx", {"markers": d}, lost)):
        session = ort.InferenceSession(str(tmp_path / "m" / graph), providers=["CPUExecutionProvider"])
        (out,) = session.run(None, {k: v.astype(np.float32) for k, v in feeds.items()})
        routes, clear = router.route(d.reshape(len(d), -1), aux), np.abs(_logit(pair, d, aux)) > 1e-3
        assert routes.any() and (~routes).any() and clear.mean() > 0.9, graph
        np.testing.assert_allclose(out[clear], pair.predict(d, auxiliary=aux)[clear], atol=tol, err_msg=graph)
        meta = session.get_modelmeta().custom_metadata_map  # the inputs named in the file, units beside them
        assert ("auxiliary" in meta) == (graph == "model.onnx"), graph
    names = pair.auxiliary.names
    assert meta_of(tmp_path / "m" / "model.onnx")["auxiliary"].startswith(f"(B, {len(names)}) float32: {names[0]} [")


def meta_of(path) -> dict:
    import onnx

    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def _auxiliary(A):
    from _instrument_synthetic import INPUTS
    from tissuecast.surrogate.auxiliary import AuxiliaryValues

    return AuxiliaryValues(INPUTS, A)
