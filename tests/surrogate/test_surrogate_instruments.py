"""Auxiliary model inputs (tissuecast.surrogate.auxiliary): a tracked instrument's pose through the
head, the networks, the compiled predictor, torch and ONNX, the trust layer, model folders, and the
markers-only fallback when the instrument is absent."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.instruments import InstrumentPose
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.auxiliary import AuxiliaryInputs, AuxiliaryValues, InstrumentInput

from _instrument_synthetic import INPUTS, SPLITS, instrument_data, instrument_model
from _surrogate_synthetic import COMPILED_ATOL, MARKERS


def _offset_max(u, truth) -> float:
    return float(np.linalg.norm(u - truth, axis=2).max(axis=1).mean())


def test_the_instrument_input_halves_the_error_the_markers_leave():
    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"]
    d = m.marker_displacements(U[te])
    with_instrument = _offset_max(m.predict(d, auxiliary=A[te]), U[te])
    markers_only = _offset_max(m.predict(d), U[te])
    assert with_instrument < 0.5 * markers_only, (with_instrument, markers_only)
    assert m.auxiliary.names[:3] == ("retractor.tip_x", "retractor.tip_y", "retractor.tip_z")
    assert m.auxiliary.units == ("mm", "mm", "mm", "1", "1", "1", "mm", "1")


def test_an_absent_instrument_is_the_fallback_and_the_input_forms_agree():
    m = instrument_model()
    _, U, poses, A = instrument_data()
    te = SPLITS["test"][:12]
    d = m.marker_displacements(U[te])
    fallback = m.fallback_.predict(d)
    np.testing.assert_array_equal(m.predict(d), fallback)  # None: every instrument absent
    np.testing.assert_array_equal(m.predict(d, auxiliary={"retractor": None}), fallback)
    mixed = A[te].copy()
    mixed[::2] = np.nan  # every second sample: tracking lost
    u = m.predict(d, auxiliary=mixed)  # a batch split in two: float32's last bits as BLAS sums them
    np.testing.assert_allclose(u[::2], fallback[::2], rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(u[1::2], m.network_.predict(d[1::2], auxiliary=A[te][1::2]), rtol=0, atol=COMPILED_ATOL)
    by_pose = m.predict(d, auxiliary={"retractor": [poses[i] for i in te]})
    np.testing.assert_array_equal(by_pose, m.predict(d, auxiliary=A[te]))
    one = m.predict(d[3], auxiliary={"retractor": poses[te[3]]})
    np.testing.assert_allclose(one, by_pose[3], rtol=0, atol=COMPILED_ATOL)  # single-sample path (gemv)
    away = m.predict(d[:2], auxiliary={"retractor": InstrumentPose.away()})
    np.testing.assert_array_equal(away, m.network_.predict(d[:2], auxiliary=np.zeros((2, 8))))
    assert np.abs(away - fallback[:2]).max() > 0.01  # away from the tissue is not "not tracked"


def test_a_frame_is_checked_once_by_the_composed_model(monkeypatch):
    """The model (its network beside the markers-only fallback; trusted, each with its layer)
    checks the input at its entry and passes it down checked: one marker check, one auxiliary
    check, one gate inspection per call of predict and of predict_trusted."""
    from tissuecast.surrogate import auxiliary, field_predictor, gate

    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"][:3]
    d = m.marker_displacements(U[te])
    calls = {"markers": 0, "auxiliary": 0, "gate": 0}
    counted = {"markers": (field_predictor, "marker_batch"), "auxiliary": (auxiliary.AuxiliaryInputs, "batch"),
               "gate": (gate.InputGate, "_inspect")}
    for key, (owner, name) in counted.items():
        original = getattr(owner, name)
        monkeypatch.setattr(owner, name, lambda *args, _f=original, _k=key, **kw: calls.__setitem__(_k, calls[_k] + 1)
                            or _f(*args, **kw))
    mixed = A[te].copy()
    mixed[1] = np.nan  # one sample's instrument lost: both the network and the fallback predict
    shift = 0.0
    for call in (m.predict, m.predict_trusted):
        for x, a in ((d, mixed), (d[0], A[te[0]])):
            for k in calls:
                calls[k] = 0
            shift += 0.01  # not an input the gate let through before
            call(x + shift, auxiliary=a)
            assert calls == {"markers": 1, "auxiliary": 1, "gate": 1}, call.__name__


def test_the_compiled_predictor_is_the_float64_reference_to_float32_and_torch_and_onnx_agree(tmp_path):
    torch = pytest.importorskip("torch")
    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"][:20]
    d = m.marker_displacements(U[te])
    net = m.network_
    x = np.hstack([d.reshape(len(d), -1), A[te]])
    w = np.mean([k.predict_weights(x) for k in net.members], axis=0) + net.head.predict(x)
    reference = net.basis.inverse_transform(w).reshape(len(d), -1, 3)
    u = m.predict(d, auxiliary=A[te])
    np.testing.assert_allclose(u, reference, rtol=0, atol=COMPILED_ATOL)
    with torch.no_grad():
        t = m.torch_module()(torch.as_tensor(d, dtype=torch.float32), torch.as_tensor(A[te], dtype=torch.float32))
    np.testing.assert_allclose(t.numpy(), u, atol=2e-4)
    ort = pytest.importorskip("onnxruntime")
    for fallback, feeds in ((False, {"markers": d, "auxiliary": A[te]}), (True, {"markers": d})):
        path = tmp_path / f"m{int(fallback)}.onnx"
        m.export_onnx(path, fallback=fallback)
        out = ort.InferenceSession(str(path)).run(None, {k: v.astype(np.float32) for k, v in feeds.items()})[0]
        np.testing.assert_allclose(out, u if not fallback else m.predict(d), atol=2e-4)


def test_a_model_folder_keeps_the_inputs_the_fallback_and_both_trust_layers(tmp_path):
    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"][:10]
    d = m.marker_displacements(U[te])
    m.save(tmp_path / "model")
    back = DeformationModel.load(tmp_path / "model")
    assert back.auxiliary == m.auxiliary and back.auxiliary.instruments[0].device == "RetractorToReference"
    np.testing.assert_array_equal(back.predict(d, auxiliary=A[te]), m.predict(d, auxiliary=A[te]))
    np.testing.assert_array_equal(back.predict(d), m.predict(d))
    a, b = back.predict_trusted(d, auxiliary=A[te]), m.predict_trusted(d, auxiliary=A[te])
    np.testing.assert_allclose(a.error_bound, b.error_bound, rtol=1e-6)  # conformal scores stored as float32
    assert [x.raised for x in a.alarms] == [x.raised for x in b.alarms]
    np.testing.assert_allclose(back.predict_trusted(d).error_bound, m.predict_trusted(d).error_bound, rtol=1e-6)
    assert back.fallback_.auxiliary.width == 0 and "fallback" in back.describe()
    assert back.get_state().fallback_trust.n_auxiliary == 0


def test_bounds_cover_and_the_alarm_sees_the_instrument():
    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"]
    d = m.marker_displacements(U[te])
    tp = m.predict_trusted(d, auxiliary=A[te])
    assert np.mean(np.linalg.norm(tp.displacement - U[te], axis=2) <= tp.error_bound) >= 0.8
    assert np.mean([a.raised for a in tp.alarms]) <= 0.1
    # the same markers with the instrument 60 mm off to the side: far from every training input
    far = A[te].copy()
    far[:, 0] += 60.0 * (far[:, 7] > 0)
    alarms = m.predict_trusted(d, auxiliary=far).alarms
    touching = A[te, 7] > 0
    assert np.mean([a.raised for a, t in zip(alarms, touching) if t]) >= 0.9
    assert m.trusted_.layer.n_auxiliary == 8 and m.fallback_trusted_.layer.n_auxiliary == 0


def test_the_alarm_apart_from_the_field_is_the_same_alarm():
    """predict_trusted(alarm=False) then alarms(): the same field, bounds and alarms as one call,
    each sample routed as before (the instrument lost on a third: the fallback's layer)."""
    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"]
    d = m.marker_displacements(U[te])
    aux = A[te].copy()
    aux[:, 0] += 60.0 * (aux[:, 7] > 0)  # far from training where in contact: alarms
    aux[::3] = np.nan  # tracking lost: the markers-only fallback
    full = m.predict_trusted(d, auxiliary=aux)
    assert 0 < np.mean([a.raised for a in full.alarms]) < 1
    apart = m.predict_trusted(d, auxiliary=aux, alarm=False)
    assert apart.alarms is None
    np.testing.assert_array_equal(apart.displacement, full.displacement)
    np.testing.assert_array_equal(apart.error_bound, full.error_bound)
    np.testing.assert_equal([vars(a) for a in m.alarms(d, auxiliary=aux)], [vars(a) for a in full.alarms])
    for k in (0, 1):  # one input of each route
        whole, one = (m.predict_trusted(d[k], auxiliary=aux[k], alarm=a) for a in (True, False))
        assert one.alarms is None and one.displacement.shape == full.displacement.shape[1:]
        np.testing.assert_array_equal(one.error_bound, whole.error_bound)
        np.testing.assert_equal(vars(m.alarms(d[k], auxiliary=aux[k])), vars(whole.alarms))


def test_the_fallback_is_the_markers_only_model_of_the_same_samples():
    mesh, U, _, A = instrument_data()
    m = instrument_model()
    plain = DeformationModel(epochs=150, patience=0, batch_size=64, n_components=16, hidden=(64, 32))
    plain.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
              calibration_idx=SPLITS["calibration"])
    d = m.marker_displacements(U[SPLITS["test"][:7]])
    np.testing.assert_array_equal(plain.predict(d), m.predict(d))
    np.testing.assert_array_equal(plain.predict_trusted(d).error_bound, m.predict_trusted(d).error_bound)


def test_fallback_epochs_train_the_fallback_alone_for_fewer_epochs():
    """``fallback_epochs``: the fallback is the markers-only model trained that many epochs, the
    model with its instrument the same as with the default (0: ``epochs`` for both)."""
    mesh, U, _, A = instrument_data()
    kw = dict(patience=0, batch_size=64, n_components=16, hidden=(64, 32))
    split = dict(mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
                 calibration_idx=SPLITS["calibration"])
    m = DeformationModel(epochs=150, fallback_epochs=40, **kw).fit(U, MARKERS, auxiliary=AuxiliaryValues(INPUTS, A),
                                                                   **split)
    plain = DeformationModel(epochs=40, **kw).fit(U, MARKERS, **split)
    te = SPLITS["test"][:7]
    d = m.marker_displacements(U[te])
    np.testing.assert_array_equal(plain.predict(d), m.predict(d))
    np.testing.assert_array_equal(m.predict(d, auxiliary=A[te]), instrument_model().predict(d, auxiliary=A[te]))
    assert [r["epochs_run"] for r in m.training_["fallback"]["members"]] == [40]
    assert [r["epochs_run"] for r in m.training_["members"]] == [150]


def test_auxiliary_inputs_are_checked():
    m = instrument_model()
    _, U, _, A = instrument_data()
    d = m.marker_displacements(U[:3])
    with pytest.raises(ModelError, match=r"shape \(8,\) or \(3, 8\)"):
        m.predict(d, auxiliary=np.zeros((3, 5)))
    with pytest.raises(ModelError, match="unknown auxiliary inputs"):
        m.predict(d, auxiliary={"spatula": None})
    partial = A[:3].copy()
    partial[0, 2] = np.nan
    with pytest.raises(ModelError, match="give all 8 pose inputs or none"):
        m.predict(d, auxiliary=partial)
    with pytest.raises(ModelError, match="cannot predict with an instrument absent"):
        m.network_.predict(d)
    with pytest.raises(ModelError, match="finite for the samples fitted on"):
        bad = A.copy()
        bad[0] = np.nan
        DeformationModel(epochs=2).fit(U, MARKERS, mesh=instrument_data()[0], auxiliary=AuxiliaryValues(INPUTS, bad))
    with pytest.raises(ModelError, match=r"must be \(N, 8\)"):
        AuxiliaryValues(INPUTS, A[:, :3])
    with pytest.raises(ModelError, match="not recorded per sample"):
        AuxiliaryInputs(parameters=("region_youngs_modulus",))
    spec = AuxiliaryInputs((InstrumentInput("retractor"),), ("youngs_modulus",))
    with pytest.raises(ModelError, match=r"needs the measured parameters \['youngs_modulus'\]"):
        spec.batch({"retractor": None}, 2)
    a = spec.batch({"retractor": None, "youngs_modulus": [1.5, 0.7]}, 2)
    assert np.isnan(a[:, :8]).all() and a[:, 8].tolist() == [1.5, 0.7] and spec.absent(a).all()


def test_a_measured_parameter_is_an_input_without_a_fallback():
    """A model reading a measured parameter (no instrument) has no fallback; its E factor changes
    the prediction as the fields' scale does."""
    mesh, U, _, _ = instrument_data()
    rng = np.random.default_rng(3)
    factor = rng.uniform(0.5, 2.0, len(U))
    fields = U / factor[:, None, None]  # a stiffer tissue moves less under the same loads
    spec = AuxiliaryInputs(parameters=("youngs_modulus",))
    m = DeformationModel(epochs=60, patience=0, batch_size=64, n_components=16, hidden=(64, 32), calibration_share=0.0)
    m.fit(fields, MARKERS, mesh=mesh, train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
          auxiliary=AuxiliaryValues(spec, factor[:, None]))
    assert m.fallback_ is None and m.auxiliary.names == ("youngs_modulus",) and m.auxiliary.units == ("factor",)
    te = SPLITS["test"]
    d = m.marker_displacements(fields[te])
    assert np.isfinite(m.predict(d, auxiliary={"youngs_modulus": factor[te]})).all()
    with pytest.raises(ModelError, match="needs the measured parameters"):
        m.predict(d)


def test_cli_predict_reads_the_instrument_pose(tmp_path, capsys):
    import json

    from tissuecast.cli.main import main

    m = instrument_model()
    _, U, poses, A = instrument_data()
    k = next(int(i) for i in SPLITS["test"] if poses[i].contact)
    m.save(tmp_path / "model")
    d = m.marker_displacements(U[[k, k]])
    (tmp_path / "in.json").write_text(json.dumps({"displacements": d.tolist()}))
    pose = {"tip": poses[k].tip.tolist(), "direction": poses[k].direction.tolist()}
    ras = {"frame": "RAS", "retractor": {"tip": [-poses[k].tip[0], -poses[k].tip[1], poses[k].tip[2]],
                                         "direction": [0.0, 0.0, -1.0]}}
    (tmp_path / "tool.json").write_text(json.dumps([{"retractor": pose}, ras]))
    args = ["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--out", str(tmp_path / "u.json")]
    assert main(args + ["--instrument", str(tmp_path / "tool.json")]) == 0
    out = capsys.readouterr().out
    assert f"retractor: in contact, {poses[k].depth:.2f} mm deep" in out
    u = np.array(json.loads((tmp_path / "u.json").read_text())["displacement_mm"])
    expected = m.predict(d, auxiliary={"retractor": poses[k]})
    np.testing.assert_allclose(u, expected, atol=1e-9)  # LPS and RAS files give one pose
    (tmp_path / "none.json").write_text(json.dumps({"retractor": None}))
    assert main(args + ["--instrument", str(tmp_path / "none.json")]) == 0
    assert "retractor: not tracked (markers only)" in capsys.readouterr().out
    np.testing.assert_allclose(np.array(json.loads((tmp_path / "u.json").read_text())["displacement_mm"]), m.predict(d),
                               atol=1e-9)
    (tmp_path / "bad.json").write_text(json.dumps({"spatula": pose}))
    assert main(args + ["--instrument", str(tmp_path / "bad.json")]) == 2
    assert "unknown instruments ['spatula']" in capsys.readouterr().err
    assert main(args + ["--parameter", "youngs_modulus"]) == 2
    assert "write NAME=VALUE" in capsys.readouterr().err


def test_the_remaining_checks_fire(tmp_path, capsys):
    import json

    from tissuecast.cli.main import main
    from tissuecast.surrogate.data import dataset_auxiliary
    from tissuecast.surrogate.fallback import InstrumentFallback
    from tissuecast.surrogate.trusted import TrustedPredictor

    m = instrument_model()
    _, U, poses, A = instrument_data()
    d = m.marker_displacements(U[:2])
    spec = AuxiliaryInputs((InstrumentInput("retractor"),), ("youngs_modulus",))
    for given, message in (({"retractor": None, "youngs_modulus": np.nan}, "must be finite"),
                           ({"retractor": None, "youngs_modulus": [1.0, 2.0, 3.0]}, "give one value or 2, got 3"),
                           ({"retractor": [poses[0]], "youngs_modulus": 1.0}, "give one pose or 2, got 1"),
                           ({"retractor": [poses[0], "tip"], "youngs_modulus": 1.0}, "must be tissuecast.instruments"),
                           ("text", "auxiliary inputs must be numbers")):
        with pytest.raises(ModelError, match=message):
            spec.batch(given, 2)
    with pytest.raises(ModelError, match="the trust layer reads 15 marker displacements and 8 auxiliary inputs, got 15"):
        m.trusted_.layer.assess(d, m.predict(d))
    with pytest.raises(ModelError, match="the trust layer reads 8 auxiliary inputs, the predictor 0"):
        TrustedPredictor(m.fallback_, m.trusted_.layer)
    with pytest.raises(ModelError, match="without its instruments"):
        InstrumentFallback(m.network_, m.network_)
    with pytest.raises(ModelError, match="no fallback"):
        DeformationModel(epochs=2).fit(U[:40], MARKERS, mesh=instrument_data()[0]).export_onnx(tmp_path / "x.onnx",
                                                                                               fallback=True)

    class NoPoses:
        instrument_poses, parameters, n_samples = {}, {}, 3

    with pytest.raises(ModelError, match="records no pose of instrument 'retractor'"):
        dataset_auxiliary(NoPoses(), INPUTS)
    with pytest.raises(ModelError, match="no value of the measured parameter 'density'"):
        dataset_auxiliary(NoPoses(), AuxiliaryInputs(parameters=("density",)))
    # the command line's instrument file
    m.save(tmp_path / "model")
    (tmp_path / "in.json").write_text(json.dumps({"displacements": d.tolist()}))
    args = ["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--instrument"]
    for content, message in (({"retractor": [1, 2, 3]}, "give {'tip'"), ({"retractor": {"tip": [0, 0, 0]}}, "got keys"),
                             ({"frame": "XYZ"}, "frame 'XYZ'"), ([{}, {}, {}], "a list of 2"),
                             ({"retractor": {"tip": [0, 0, 0], "direction": [0, 0, 0]}}, "non-zero direction")):
        (tmp_path / "tool.json").write_text(json.dumps(content))
        assert main(args + [str(tmp_path / "tool.json")]) == 2
        assert message in capsys.readouterr().err, message
    plain = DeformationModel(epochs=2, calibration_share=0.0).fit(U[:40], MARKERS, mesh=instrument_data()[0])
    plain.save(tmp_path / "plain")
    assert main(["predict", str(tmp_path / "plain"), "--markers", str(tmp_path / "in.json"), "--instrument",
                 str(tmp_path / "tool.json")]) == 2
    assert "reads the markers only" in capsys.readouterr().err


def test_cross_validated_calibration_reads_the_instrument_in_every_fold():
    mesh, U, _, A = instrument_data()
    m = DeformationModel(epochs=60, patience=0, batch_size=64, n_components=16, hidden=(64, 32),
                         calibration="cross-validation", calibration_folds=4)
    m.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
          auxiliary=AuxiliaryValues(INPUTS, A))
    assert m.training_["calibration"]["method"] == "cross-validation"
    assert m.trusted_.layer.method == "cross-validation" and m.trusted_.layer.n_auxiliary == 8
    assert m.fallback_trusted_.layer.n_auxiliary == 0
    te = SPLITS["test"]
    d = m.marker_displacements(U[te])
    tp = m.predict_trusted(d, auxiliary=A[te])
    coverage = np.mean(np.linalg.norm(tp.displacement - U[te], axis=2) <= tp.error_bound)
    assert 0.8 <= coverage <= 0.99, coverage
    # without the pose: the markers-only fallback's own cross-validated bounds
    lost = m.predict_trusted(d, auxiliary={"retractor": None})
    coverage = np.mean(np.linalg.norm(lost.displacement - U[te], axis=2) <= lost.error_bound)
    assert 0.8 <= coverage <= 0.99, coverage
    assert m.fallback_trusted_.layer.method == "cross-validation"


def test_a_local_decoder_with_the_instrument_round_trips_with_its_fallback(tmp_path):
    mesh, U, _, A = instrument_data()
    m = DeformationModel(epochs=40, patience=0, batch_size=64, n_components=16, hidden=(64, 32), decoder="local",
                         decoder_regions=4, decoder_components=24)
    m.fit(U, MARKERS, mesh=mesh, fixed=[0, 1, 2], train_idx=SPLITS["train"], valid_idx=SPLITS["valid"],
          calibration_idx=SPLITS["calibration"], auxiliary=AuxiliaryValues(INPUTS, A))
    assert m.network_.n_components == 16 + 24 and m.fallback_.n_components == 16 + 24
    m.save(tmp_path / "m")
    assert (tmp_path / "m" / "decoder.npz").is_file() and (tmp_path / "m" / "fallback" / "decoder.npz").is_file()
    back = DeformationModel.load(tmp_path / "m")
    te = SPLITS["test"][:9]
    d = m.marker_displacements(U[te])
    np.testing.assert_array_equal(back.predict(d, auxiliary=A[te]), m.predict(d, auxiliary=A[te]))
    np.testing.assert_array_equal(back.predict(d, auxiliary={"retractor": None}), m.fallback_.predict(d))
    np.testing.assert_allclose(back.predict_trusted(d, auxiliary=A[te]).error_bound,  # scores kept as float32
                               m.predict_trusted(d, auxiliary=A[te]).error_bound, rtol=1e-6)


def test_the_gates_distances_are_the_alarms_with_the_instrument_tracked_or_lost():
    """A nominal expert's gate reads each model's input distance without checking the inputs
    again (tissuecast.surrogate.experts.gate_features): the alarm's own distance, from the
    primary where the instrument is tracked and from the fallback where it is lost."""
    from tissuecast.surrogate.experts import gate_features
    from tissuecast.surrogate.fallback import InstrumentFallback

    m = instrument_model()
    _, U, _, A = instrument_data()
    te = SPLITS["test"]
    d = m.marker_displacements(U[te]).reshape(len(te), -1)
    aux = A[te].copy()
    aux[::3] = np.nan  # tracking lost on a third
    both = InstrumentFallback(m.trusted_, m.fallback_trusted_)
    want = np.array([a.distance for a in m.alarms(d, auxiliary=aux)])
    np.testing.assert_allclose(np.exp(gate_features(both, both, d, aux)), np.stack([want, want], axis=1), rtol=1e-12)
    np.testing.assert_allclose(both.input_distance(d, auxiliary=aux), want, rtol=1e-12)
    assert not np.allclose(want[::3], m.trusted_.input_distance(d[::3], auxiliary=A[te][::3]))  # the fallback's own
