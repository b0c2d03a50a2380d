"""Error bounds and out-of-distribution alarm of a DeformationModel (synthetic nonlinear fields)."""

import json

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.errors import ConfigError, ModelError
from tissuecast.surrogate import DeformationModel

from _surrogate_synthetic import MARKERS, nonlinear_fields
from _trust_synthetic import SPLITS, trust_data, trust_model


def _swap(d, ref, rng, pairs=None):
    """d (B, n_d, 3) with two random markers' tracked positions exchanged in each sample; with
    ``pairs`` (a list), the exchanged (i, j), i < j, are appended to it."""
    out = d.copy()
    for b in range(len(d)):
        i, j = sorted(rng.choice(len(ref), 2, replace=False))
        out[b, i], out[b, j] = ref[j] + d[b, j] - ref[i], ref[i] + d[b, i] - ref[j]
        if pairs is not None:
            pairs.append((int(i), int(j)))
    return out


@pytest.fixture(scope="module")
def model():
    return trust_model()


@pytest.fixture(scope="module")
def test_fields():
    _, U, _ = trust_data()
    return U[SPLITS["test"]]


def test_bounds_cover_at_the_nominal_rate_on_held_out_samples(model, test_fields):
    d = test_fields[:, model.markers, :]
    for c in (0.9, 0.95):
        tp = model.predict_trusted(d, coverage=c)
        e = np.linalg.norm(tp.displacement - test_fields, axis=2)
        assert tp.error_bound.shape == e.shape and tp.coverage == c
        assert abs(np.mean(e <= tp.error_bound) - c) < 0.04, c
    np.testing.assert_allclose(tp.displacement, model.predict(d))
    # bounds are larger where the model is worse: they rank the samples' errors and the vertices' errors
    from scipy.stats import spearmanr

    assert spearmanr(tp.error_bound.max(axis=1), e.max(axis=1))[0] > 0.6
    assert spearmanr(tp.error_bound.ravel(), e.ravel())[0] > 0.4
    single = model.predict_trusted(d[0])
    assert single.displacement.shape == (model.n_vertices, 3) and single.error_bound.shape == (model.n_vertices,)
    assert single.alarms.raised in (True, False)


def _alarm_only(model):
    """The model's network and trust layer without the input gate (which refuses the grossest of
    these faults before the alarm sees them: tests/surrogate/test_gate.py), to measure the alarm itself."""
    from tissuecast.surrogate.network_predictor import NetworkPredictor
    from tissuecast.surrogate.trusted import TrustedPredictor

    net = model.network_
    return TrustedPredictor(NetworkPredictor(net.mesh, net.markers, net.basis, net.members, net.head), model.trusted_.layer)


def test_alarm_is_quiet_on_clean_inputs_and_fires_on_each_fault(model, test_fields):
    model = _alarm_only(model)
    rng = np.random.default_rng(3)
    d = test_fields[:, model.markers, :]
    clean = [a.raised for a in model.predict_trusted(d).alarms]
    assert np.mean(clean) <= 0.03  # nominal 1 % false alarms
    # (a) two markers' tracked positions swapped
    pairs = []
    swapped = model.predict_trusted(_swap(d, model.reference_marker_positions, rng, pairs)).alarms
    assert np.mean([a.raised and a.inconsistent_markers for a in swapped]) >= 0.95
    # ... and named as an exchange: exchanged back, the markers agree far better
    assert np.mean([a.raised and a.swapped_markers_alarm for a in swapped]) >= 0.95
    assert np.mean([(a.swap_first, a.swap_second) == p for a, p in zip(swapped, pairs)]) >= 0.95
    first = next(a for a in swapped if a.swapped_markers_alarm)
    assert f"markers {first.swap_first} and {first.swap_second} look exchanged" in first.text
    assert not any(a.swapped_markers_alarm for a in model.predict_trusted(d).alarms)
    # (b) one marker 3 mm off its true position (fields here reach ~10 mm)
    glitch = d.copy()
    v = rng.normal(size=(len(d), 3))
    k = rng.integers(0, len(MARKERS), len(d))
    glitch[np.arange(len(d)), k] += 3.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    alarms = model.predict_trusted(glitch).alarms
    assert np.mean([a.raised for a in alarms]) >= 0.95
    caught = [a for a in alarms if a.inconsistent_markers]
    assert len(caught) > 0.9 * len(d) and "from where the other markers place it" in caught[0].text
    assert np.mean([a.swapped_markers_alarm for a in alarms]) <= 0.05  # a slipped marker is not an exchange
    assert np.mean([a.marker for a in alarms] == k) >= 0.95  # the single-marker fault score names it
    # (c) deformations beyond the simulated range (latents 1.5-2x outside [-1, 1])
    mesh, _, _ = trust_data()
    theta = rng.uniform(1.5, 2.0, (200, 3)) * rng.choice([-1, 1], (200, 3))
    far = nonlinear_fields(mesh, theta)[:, model.markers, :]
    far_alarms = model.predict_trusted(far).alarms
    assert np.mean([a.raised for a in far_alarms]) >= 0.95
    assert "far from every simulated deformation" in next(a.text for a in far_alarms if a.far_from_training)
    # (d) one marker still (the tissue held there, or the marker tracked off the tissue) where every
    # simulation moved it
    least = model.layer.ood.stillness.least
    moving = np.flatnonzero(least > 0.05)
    assert moving.size >= len(MARKERS) // 2
    held = d.copy()
    k = moving[rng.integers(0, moving.size, len(d))]
    held[np.arange(len(d)), k] = 0.0
    held_alarms = model.predict_trusted(held).alarms
    assert np.mean([a.raised and a.still_marker_alarm for a in held_alarms]) >= 0.95
    assert np.mean([a.still_marker for a in held_alarms] == k) >= 0.95
    assert "did not move" in held_alarms[0].text
    assert not any(a.still_marker_alarm for a, c in zip(model.predict_trusted(d).alarms, clean) if not c)
    # a looser false-alarm rate raises more alarms on clean inputs, never fewer
    loose = np.mean([a.raised for a in model.predict_trusted(d, false_alarm=0.2).alarms])
    assert loose >= np.mean(clean) and 0.1 < loose < 0.3


def test_trust_layer_round_trips_through_the_model_folder(model, test_fields, tmp_path):
    model.save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["files"]["trust"] == "trust.npz" and meta["trust"]["n_calibration"] == 300 and meta["trust"]["fault_score"]
    with np.load(tmp_path / "m" / "trust.npz", allow_pickle=False) as z:
        assert "conformal.sorted_scores" in z.files and "error_input.coef" in z.files
        assert z["ood.consistency.sensitivity"].shape == (len(MARKERS), 3 * len(MARKERS), 3)
    # the error model weighs the input error regression (learnt from out-of-fold errors) as a sixth feature
    assert meta["trust"]["error_model_features"][-1] == "input_error_prediction" and len(meta["trust"]["error_model"]) == 7
    back = DeformationModel.load(tmp_path / "m")
    assert back.trusted_.layer.error_input is not None
    d = test_fields[:20, model.markers, :]
    a, b = model.predict_trusted(d), back.predict_trusted(d)
    np.testing.assert_allclose(b.error_bound, a.error_bound, rtol=1e-6)
    assert [x.raised for x in a.alarms] == [x.raised for x in b.alarms]
    np.testing.assert_allclose([x.distance for x in b.alarms], [x.distance for x in a.alarms], rtol=1e-12)
    np.testing.assert_allclose([x.fault for x in b.alarms], [x.fault for x in a.alarms], rtol=1e-12)
    np.testing.assert_array_equal(back.trusted_.layer.ood.stillness.least, model.trusted_.layer.ood.stillness.least)
    np.testing.assert_allclose([x.stillness for x in b.alarms], [x.stillness for x in a.alarms], rtol=1e-12)
    assert meta["trust"]["stillness_score"] and meta["trust"]["swap_score"]
    np.testing.assert_array_equal(back.trusted_.layer.ood.swap.reference, model.reference_marker_positions)
    np.testing.assert_allclose([x.swap for x in b.alarms], [x.swap for x in a.alarms], rtol=1e-12)
    # a trust file written before the swap score loads without it, and its alarms are as before but for it
    with np.load(tmp_path / "m" / "trust.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "ood.swap.reference"}
    np.savez(tmp_path / "m" / "trust.npz", **arrays)
    old = DeformationModel.load(tmp_path / "m")
    assert not old.trusted_.layer.ood.has_swap
    c = old.predict_trusted(d)
    assert all(np.isnan(x.swap) and not x.swapped_markers_alarm for x in c.alarms)
    np.testing.assert_allclose(c.error_bound, a.error_bound, rtol=1e-6)
    np.testing.assert_allclose([x.distance for x in c.alarms], [x.distance for x in a.alarms], rtol=1e-12)
    # an empty, truncated or random-bytes trust file: one ModelError naming it, never a traceback or
    # an offer to unpickle
    whole = (tmp_path / "m" / "trust.npz").read_bytes()
    rng = np.random.default_rng(0)
    for broken in (b"", whole[:100], rng.integers(0, 256, 4000, dtype=np.uint8).tobytes()):
        (tmp_path / "m" / "trust.npz").write_bytes(broken)
        with pytest.raises(ModelError, match=r"trust.npz' is unreadable or incomplete .*the model folder is corrupt") as err:
            DeformationModel.load(tmp_path / "m")
        assert "allow_pickle" not in str(err.value)
    (tmp_path / "m" / "trust.npz").unlink()
    with pytest.raises(ModelError, match="trust.npz"):
        DeformationModel.load(tmp_path / "m")


def test_models_without_calibration_have_no_bounds_and_say_how_to_get_them():
    mesh, U, _ = trust_data()
    m = DeformationModel(epochs=5, patience=0, n_components=4, calibration_share=0.0).fit(
        U[:200], MARKERS, mesh=mesh, train_idx=np.arange(150), valid_idx=np.arange(150, 200))
    assert not m.has_trust and m.training_["n_calibration"] == 0 and m.training_["n_train"] == 150
    with pytest.raises(ModelError, match="calibration_share"):
        m.predict_trusted(U[0, MARKERS])
    # the default share holds out 1/8 of the training samples
    m2 = DeformationModel(epochs=5, patience=0, n_components=4).fit(
        U[:200], MARKERS, mesh=mesh, train_idx=np.arange(160), valid_idx=np.arange(160, 200))
    assert m2.has_trust and m2.training_["n_calibration"] == 20 and m2.training_["n_train"] == 140
    with pytest.raises(ModelError, match="coverage"):
        m2.predict_trusted(U[0, MARKERS], coverage=1.5)
    with pytest.raises(ModelError, match="disjoint"):
        DeformationModel(epochs=5, patience=0, n_components=4).fit(
            U[:200], MARKERS, mesh=mesh, train_idx=np.arange(100), valid_idx=np.arange(100, 150),
            calibration_idx=np.arange(140, 200))


@pytest.mark.parametrize("key, value, match", [("calibration_share", 0.5, "calibration_share"),
                                               ("coverage", 1.0, "coverage"),
                                               ("false_alarm_rate", 0.0, "false_alarm_rate")])
def test_trust_config_keys_are_validated(key, value, match):
    with pytest.raises(ConfigError, match=match):
        with_overrides(Config(), surrogate={key: value})


def test_the_fault_score_joins_the_alarm_when_asked_and_is_stored():
    mesh, U, _ = trust_data()
    m = DeformationModel(epochs=5, patience=0, n_components=4, head="none", alarm_fault_score=True).fit(
        U[:400], MARKERS, mesh=mesh, train_idx=np.arange(250), valid_idx=np.arange(250, 300),
        calibration_idx=np.arange(300, 400))
    assert m.trusted_.layer.ood.use_fault and np.isfinite(m.trusted_.layer.ood.thresholds(0.01)).all()
    assert m.trusted_.layer.summary()["fault_score_in_alarm"]
    back = type(m.trusted_.layer).from_arrays(m.trusted_.layer.arrays())
    assert back.ood.use_fault
    d = U[1100:1150, MARKERS]
    np.testing.assert_array_equal(back.alarm_scores(d), m.trusted_.layer.alarm_scores(d))
    with pytest.raises(ConfigError, match="alarm_fault_score"):
        DeformationModel(alarm_fault_score="yes")
