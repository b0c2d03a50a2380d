"""The input gate (surrogate/gate.py): absurd marker input refused in the API, `predict` and `serve`."""

import itertools
import json

import numpy as np
import pytest

from tissuecast.errors import InputRejected, ModelError
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.network_predictor import NetworkPredictor
from tissuecast.surrogate.gate import DISPLACEMENT_FACTOR, STRAIN_MARGIN, TOLERANCE_MM, InputGate
from tissuecast.surrogate.state import gate_of

from _surrogate_synthetic import MARKERS
from _trust_synthetic import SPLITS, trust_data, trust_model


@pytest.fixture(scope="module")
def model():
    return trust_model()


def _clean(k=0):
    _, U, _ = trust_data()
    return U[SPLITS["test"][k]][MARKERS].astype(np.float64)


def _stretched(model, d, j, k, factor=3.0):
    """d with marker j moved along the line from marker k so that their distance is ``factor`` x the reference's."""
    ref = model.reference_marker_positions
    out = d.copy()
    out[j] = ref[k] + d[k] + factor * (ref[j] - ref[k]) - ref[j]
    return out


def _closest_pair(model):
    ref = model.reference_marker_positions
    return min(itertools.combinations(range(len(ref)), 2), key=lambda p: np.linalg.norm(ref[p[0]] - ref[p[1]]))


# ---------------------------------------------------------------------------------------------- the gate alone
def test_gate_limits_are_the_documented_ones():
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 20.0, 0]])
    gate = InputGate(np.array([4, 5, 6]), ref, np.array([1.0, 2.0, 3.0]), np.array([[0.99, 1.01], [0.9, 1.2], [1.0, 1.0]]))
    # displacement: DISPLACEMENT_FACTOR x the largest simulated one + TOLERANCE_MM, per marker
    limit = DISPLACEMENT_FACTOR * 2.0 + TOLERANCE_MM
    inside, outside = np.zeros((3, 3)), np.zeros((3, 3))
    inside[1, 2] = limit - 1e-6
    outside[1, 2] = limit + 1e-6
    assert not gate.inspect(inside.reshape(1, -1))[0].refused
    v = gate.inspect(outside.reshape(1, -1))[0]
    assert (v.refused, v.reason, v.marker, v.vertex) == (True, "displacement", 1, 5)
    assert "marker 1 (input index 1, vertex 5)" in v.message
    # stretch of pair (0, 1): [0.99 - w, 1.01 + w] x 10 mm -/+ TOLERANCE_MM, w = 0.02 + STRAIN_MARGIN
    hi = 10.0 * (1.01 + 0.02 + STRAIN_MARGIN) + TOLERANCE_MM
    big = np.array([[1e3, 1e3, 1e3]])
    gate = InputGate(np.array([4, 5, 6]), ref, big.ravel(), np.array([[0.99, 1.01], [0.9, 1.2], [1.0, 1.0]]))
    for x, refused in ((hi - 1e-6, False), (hi + 1e-6, True)):
        d = np.zeros((3, 3))
        d[1, 0] = x - 10.0
        d[2] = [0.0, 0.0, 0.0]
        assert gate.inspect(d.reshape(1, -1))[0].refused is refused


def test_gate_from_inputs_takes_the_range_of_the_samples():
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    X = np.zeros((3, 2, 3))
    X[0, 1, 0] = 1.0  # distance 11
    X[1, 0, 1] = -2.0  # marker 0 moved 2 mm sideways: distance sqrt(104)
    X[2, 1, 0] = -0.5  # distance 9.5
    gate = InputGate.from_inputs([7, 8], ref, X)
    np.testing.assert_allclose(gate.max_displacement, [2.0, 1.0])
    np.testing.assert_allclose(gate.stretch, [[0.95, 1.1]])


def test_the_quick_check_of_fully_tracked_input_agrees_with_the_full_one():
    """Inputs with every marker tracked are first checked in a few products; the verdict is the
    one of the full check (which a batch with a refused input takes for all of its inputs)."""
    rng = np.random.default_rng(3)
    ref = rng.uniform(-30, 30, size=(6, 3))
    stretch = np.sort(rng.uniform(0.95, 1.05, size=(15, 2)), axis=1)
    gate = InputGate(np.arange(6), ref, rng.uniform(1, 4, size=6), stretch)
    d = rng.normal(scale=rng.choice([0.5, 3.0, 6.0], size=(400, 1, 1)), size=(400, 6, 3)).reshape(400, 18)
    d[7, 4] = np.nan
    d[8, 1] = np.inf
    quick = [gate.inspect(x[None])[0] for x in d]
    full = gate.inspect(d)
    assert [v.refused for v in quick] == [v.refused for v in full]
    assert [v.reason for v in quick] == [v.reason for v in full]
    assert 50 < sum(v.refused for v in quick) < 350  # both kinds of input were drawn
    assert {v.reason for v in quick} == {"", "non-finite", "displacement", "stretch"}
    passed = np.flatnonzero([not v.refused for v in full])
    assert all(not v.refused for v in gate.inspect(d[passed], np.zeros((len(passed), 6), dtype=bool)))  # no marker missing


def test_missing_markers_are_not_checked():
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 20.0, 0]])
    gate = InputGate(np.arange(3), ref, np.ones(3), np.array([[1.0, 1.0]] * 3))
    d = np.zeros((1, 9))
    d[0, 3:6] = np.nan
    assert gate.inspect(d)[0].reason == "non-finite"
    assert not gate.inspect(d, np.array([[False, True, False]]))[0].refused


def test_the_input_let_through_last_passes_at_once_and_nothing_else_does(monkeypatch):
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 20.0, 0]])
    gate = InputGate(np.arange(3), ref, np.ones(3), np.array([[1.0, 1.0]] * 3))
    calls = []
    inspect = InputGate._inspect
    monkeypatch.setattr(InputGate, "_inspect", lambda self, d, missing, key: calls.append(1) or inspect(self, d, missing, key))
    ok = np.zeros((1, 9))
    gate.enforce(ok)
    gate.enforce(ok.copy())  # the same values: not inspected again (the parts of a composed model share the gate)
    assert len(calls) == 1
    mask = np.array([[False, True, False]])
    gate.enforce(ok, mask)  # another mask: inspected
    gate.enforce(ok, mask.copy())
    assert len(calls) == 2
    bad = ok.copy()
    bad[0, 3] = 50.0  # marker 1 displaced 50 mm, more than 3 x 1 mm + 2 mm
    for _ in range(2):  # refused every time: only passed input is remembered
        with pytest.raises(InputRejected, match="marker 1"):
            gate.enforce(bad)
    assert len(calls) == 4
    gate.enforce(ok, mask)  # the last passed input still passes at once
    gate.enforce(ok)  # the one before it is checked again
    assert len(calls) == 5
    # an input a server inspected (and let through) passes the model's enforce at once; a mask
    # with no marker missing is the same input as none
    other = ok + 0.25
    assert not gate.inspect(other, np.zeros((1, 3), dtype=bool))[0].refused
    gate.enforce(other.copy())
    assert len(calls) == 6
    assert gate.inspect(bad)[0].refused  # a refused inspection forgets nothing and remembers nothing
    gate.enforce(other)
    assert len(calls) == 7
    # an untracked marker's coordinates do not count: NaN from the tracker, 0 filled in by a model
    tracked = np.array([[False, True, False]])
    given = other.copy()
    given[0, 3:6] = np.nan
    assert not gate.inspect(given, tracked)[0].refused
    filled = other.copy()
    filled[0, 3:6] = 0.0
    gate.enforce(filled, tracked)
    assert len(calls) == 8


# ---------------------------------------------------------------------------------------------- the API
def test_valid_inputs_pass_and_predict_as_without_the_gate(model):
    _, U, _ = trust_data()
    d = U[:, MARKERS].astype(np.float64)  # every sample: train, valid, calibration, test
    assert not any(v.refused for v in model.check_input(d))
    net = model.network_
    ungated = NetworkPredictor(net.mesh, net.markers, net.basis, net.members, net.head)
    assert ungated.input_gate is None
    np.testing.assert_array_equal(model.predict(d[SPLITS["test"]]), ungated.predict(d[SPLITS["test"]]))


@pytest.mark.parametrize("case", ["glitch", "nan", "inf", "stretch"])
def test_absurd_inputs_are_refused_naming_the_marker(model, case):
    d = _clean(1)
    j, k = _closest_pair(model)
    if case == "glitch":
        d[2] += [1e9, 0.0, 0.0]
        j, reason = 2, "displacement"
    elif case == "nan":
        d[2, 1] = np.nan
        j, reason = 2, "non-finite"
    elif case == "inf":
        d[2, 0] = np.inf
        j, reason = 2, "non-finite"
    else:
        d = _stretched(model, d, j, k)
        reason = None
    for call in (lambda: model.predict(d), lambda: model.predict(d, method="rigid"), lambda: model.predict(d, method="ridge"),
                 lambda: model.predict_trusted(d),
                 lambda: model.predict_from_positions(model.reference_marker_positions + d),
                 lambda: model.predict(np.stack([_clean(0), d]))):
        with pytest.raises(InputRejected) as info:
            call()
        assert isinstance(info.value, ModelError)
        assert info.value.marker in (j, k) and info.value.vertex == MARKERS[info.value.marker]
        assert reason is None or info.value.reason == reason
        m = info.value.marker
        assert f"marker {m} (input index {m}, vertex {MARKERS[m]})" in str(info.value)
    verdict = model.check_input(d)
    assert verdict.refused and (reason is None or verdict.reason == reason)


def test_positions_and_displacements_mixed_up_are_refused_with_the_fix(model):
    """Positions handed over as displacements (or the reverse) are refused as any absurd input, and
    the message names the mix-up and the call to use, where the other reading is plausible."""
    d = _clean(1)
    p = model.reference_marker_positions + d
    assert not model.check_input(d).refused
    with pytest.raises(InputRejected, match="these look like marker positions, not displacements: use "
                                            "predict_from_positions"):
        model.predict(p)
    with pytest.raises(InputRejected, match="these look like marker displacements given as positions: use predict"):
        model.predict_from_positions(d)
    glitch = d.copy()  # a plain glitch keeps the plain message
    glitch[2] += [1e3, 0.0, 0.0]
    with pytest.raises(InputRejected, match="a tracking glitch, a unit error or a slipped marker"):
        model.predict(glitch)


def test_swapped_markers_are_refused_or_alarmed(model):
    _, U, _ = trust_data()
    ref = model.reference_marker_positions
    d = U[SPLITS["test"][:40]][:, MARKERS].astype(np.float64)
    caught = []
    for a, b in itertools.combinations(range(len(MARKERS)), 2):
        s = d.copy()
        s[:, a], s[:, b] = ref[b] + d[:, b] - ref[a], ref[a] + d[:, a] - ref[b]
        refused = np.array([v.refused for v in model.check_input(s)])
        alarms = model.predict_trusted(s[~refused]).alarms if (~refused).any() else []
        caught.append(refused.sum() + sum(a.raised for a in alarms))
    assert sum(caught) / (len(d) * len(caught)) >= 0.95


def test_gate_is_stored_and_old_folders_derive_it(model, tmp_path):
    model.save(tmp_path / "m")
    loaded = DeformationModel.load(tmp_path / "m")
    np.testing.assert_array_equal(loaded.input_gate.max_displacement, model.input_gate.max_displacement)
    np.testing.assert_array_equal(loaded.input_gate.stretch, model.input_gate.stretch)
    # a folder written before the gate: from the trust layer's training inputs (the train split only)
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    del meta["input_gate"]
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    old = DeformationModel.load(tmp_path / "m")
    assert old.input_gate.source == "trust-file"
    _, U, _ = trust_data()
    exact = InputGate.from_inputs(MARKERS, model.reference_marker_positions, U[SPLITS["train"]][:, MARKERS])
    np.testing.assert_allclose(old.input_gate.max_displacement, exact.max_displacement, rtol=1e-9)
    np.testing.assert_allclose(old.input_gate.stretch, exact.stretch, rtol=1e-9)
    with pytest.raises(InputRejected):
        old.predict(_clean(0) + [[1e9, 0, 0]] + np.zeros((len(MARKERS), 3)))


def test_a_model_without_trust_has_the_gate_and_old_ones_estimate_it_from_pca():
    mesh, U, _ = trust_data()
    m = DeformationModel(epochs=5, patience=0, n_components=8, hidden=(16,), head="none", calibration="none").fit(
        U[:300], MARKERS, mesh=mesh, train_idx=np.arange(240), valid_idx=np.arange(240, 300))
    assert not m.has_trust
    d = _clean(3)
    d[4] = [np.nan, 0.0, 0.0]
    with pytest.raises(InputRejected, match="marker 4 .*NaN or inf"):
        m.predict(d)
    est = gate_of(type(m.get_state())(**{**m.get_state().__dict__, "gate": None}))
    assert est.source == "pca"
    # the Gaussian estimate's largest displacements are of the training maxima's size, and pass every simulated input
    ratio = est.max_displacement / m.input_gate.max_displacement
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
    assert not any(v.refused for v in est.inspect(U[:, MARKERS].reshape(len(U), -1)))


# ---------------------------------------------------------------------------------------------- predict and serve
@pytest.fixture(scope="module")
def folder(model, tmp_path_factory):
    out = tmp_path_factory.mktemp("gate") / "model"
    model.save(out)
    return out


def _absurd(model, case):
    d = _clean(2)
    if case == "glitch":
        d[2] += [1e9, 0.0, 0.0]
    elif case == "nan":
        d[2] = np.nan
    elif case == "inf":
        d[2, 2] = -np.inf
    elif case == "stretch":
        d = _stretched(model, d, *_closest_pair(model))
    else:  # swapped: markers 0 and 3 exchange tracked positions
        ref = model.reference_marker_positions
        d[[0, 3]] = ref[[3, 0]] + d[[3, 0]] - ref[[0, 3]]
    return d


@pytest.mark.parametrize("case", ["glitch", "nan", "inf", "stretch", "swapped"])
def test_predict_command_refuses_with_one_line_and_status_2(model, folder, tmp_path, capsys, case):
    from tissuecast.cli.main import main

    d = _absurd(model, case)
    path = tmp_path / "m.csv"
    path.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in d))
    status = main(["predict", str(folder), "--markers", str(path), "--out", str(tmp_path / "u.vtu")])
    out, err = capsys.readouterr()
    if case == "swapped" and status == 0:  # passed the gate: then the alarm must fire
        assert "ALARM: markers disagree" in out
        return
    assert status == 2 and not (tmp_path / "u.vtu").exists()
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: marker input refused: marker ")
    assert "(input index" in err and "max displacement" not in out


def test_predict_command_passes_a_clean_input(model, folder, tmp_path, capsys):
    from tissuecast.cli.main import main

    path = tmp_path / "m.csv"
    path.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in _clean(2)))
    assert main(["predict", str(folder), "--markers", str(path)]) == 0
    assert "max displacement" in capsys.readouterr().out


@pytest.mark.parametrize("case", ["glitch", "nan", "inf", "stretch", "swapped"])
def test_serve_sends_status_and_no_mesh_for_refused_markers(model, case):
    from tissuecast.serve.predictor import SurfacePredictor
    from tissuecast.serve.protocol import parse_header, pyigtl
    from tissuecast.serve.session import ClientSession
    from tissuecast.serve.status import ALARM_NAME, REFUSED_NAME, RefusalBits, StatusCode, decode_status

    replies = []
    session = ClientSession(SurfacePredictor(model), lambda b: replies.append(bytes(b)))
    ref = model.reference_marker_positions
    session.feed(pyigtl.PointMessage((ref + _absurd(model, case)).astype(np.float32), device_name="Markers").pack())
    kinds = [parse_header(r[:58]).message_type for r in replies]
    if case == "swapped" and "POLYDATA" in kinds:  # passed the gate: the alarm's STATUS follows the mesh
        assert decode_status(replies[kinds.index("STATUS")][58:]).error_name == ALARM_NAME
        return
    assert kinds == ["STATUS", "STRING"]
    status = decode_status(replies[0][58:])
    assert status.code == StatusCode.UNKNOWN_ERROR and status.error_name == REFUSED_NAME
    assert status.subcode in (RefusalBits.NON_FINITE, RefusalBits.BEYOND_SIMULATED, RefusalBits.IMPOSSIBLE_GEOMETRY)
    assert "marker input refused: marker" in status.status_message and "(input index" in status.status_message
    replies.clear()
    # a clean frame: the mesh, then STATUS OK clears the refusal
    session.feed(pyigtl.PointMessage((ref + _clean(2)).astype(np.float32), device_name="Markers").pack())
    assert [parse_header(r[:58]).message_type for r in replies] == ["POLYDATA", "STATUS"]
    assert decode_status(replies[1][58:]).code == StatusCode.OK
