"""Error bounds in the POLYDATA replies and the out-of-distribution alarm as OpenIGTLink STATUS."""

import itertools
import numpy as np
import pytest

from tissuecast.serve import IGTLClient, IGTLServer
from tissuecast.serve.protocol import ProtocolError, pyigtl
from tissuecast.serve.status import (ALARM_NAME, STATUS_DEVICE, AlarmBits, StatusCode, StatusMessage, decode_status,
                                     pack_status, register_status_message)

from _trust_synthetic import SPLITS, trust_data, trust_model


@pytest.fixture(scope="module")
def model():
    return trust_model()


def _positions(model, k=0):
    _, U, _ = trust_data()
    return model.reference_marker_positions + U[SPLITS["test"][k]][model.markers]


def test_status_packs_and_decodes():
    raw = pack_status(StatusCode.UNKNOWN_ERROR, int(AlarmBits.INCONSISTENT_MARKERS), ALARM_NAME, "marker 2 off", 12.5)
    header = pyigtl.MessageBase.parse_header(raw[:58])
    assert header["message_type"] == "STATUS" and header["device_name"] == STATUS_DEVICE
    m = StatusMessage()
    m.unpack(header, raw[58:])  # pyigtl's own unpacking (CRC, header fields)
    assert (m.code, m.subcode, m.error_name, m.status_message) == (2, 2, "OutOfDistribution", "marker 2 off")
    assert len(raw) - 58 == 30 + len("marker 2 off") + 1
    d = decode_status(raw[58:])
    assert d.code == 2 and d.status_message == "marker 2 off"
    with pytest.raises(ProtocolError, match="at least 30 bytes"):
        decode_status(b"\0" * 12)


def test_surface_carries_error_bounds(model):
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        positions = _positions(model, 3).astype(np.float32).astype(np.float64)  # what the POINT message carries
        reply = client.predict(positions)
        expected = model.predict_trusted(positions - model.reference_marker_positions)
        sv = model.mesh.surface_vertices
        np.testing.assert_allclose(reply.polydata.point_data["error_bound_mm"], expected.error_bound[sv], rtol=1e-5)
        assert srv.stats["replies"] == 1  # a clean prediction sends no STATUS


def test_alarm_status_reaches_a_pyigtl_client_and_serving_goes_on(model):
    register_status_message()
    with IGTLServer(model, "127.0.0.1", 0) as srv:
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", srv.address[1])
        try:
            positions = _positions(model, 5)
            slipped = positions.copy()  # one marker 3 mm off: within the input gate's limits, caught by the alarm
            slipped[0] += [3.0, 0.0, 0.0]
            assert not model.check_input(slipped - model.reference_marker_positions).refused
            client.send_message(pyigtl.PointMessage(slipped.astype(np.float32), device_name="Markers"))
            status = client.wait_for_message(STATUS_DEVICE, timeout=10)
            assert isinstance(status, StatusMessage)
            assert status.code == StatusCode.UNKNOWN_ERROR and status.error_name == ALARM_NAME
            assert status.subcode & AlarmBits.INCONSISTENT_MARKERS
            assert "markers disagree" in status.status_message
            client.send_message(pyigtl.PointMessage(positions.astype(np.float32), device_name="Markers"))
            cleared = client.wait_for_message(STATUS_DEVICE, timeout=10)
            assert cleared.code == StatusCode.OK and cleared.subcode == 0
            client.send_message(pyigtl.PointMessage(positions.astype(np.float32), device_name="Markers"))
            assert client.wait_for_message(STATUS_DEVICE, timeout=0.5) is None  # still clean: no STATUS
        finally:
            client.stop()
    assert srv.stats["replies"] == 5  # three surfaces, one alarm, one all-clear


def test_our_client_reads_the_status_after_the_surface(model):
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        far = model.reference_marker_positions + 3.0 * trust_data()[1][SPLITS["test"][0]][model.markers]
        surface = client.predict(far)
        assert surface.header.message_type == "POLYDATA"
        status = client.receive()
        assert status.header.message_type == "STATUS" and status.status.subcode & AlarmBits.FAR_FROM_TRAINING
        assert "far from every simulated deformation" in status.text


def test_a_marker_standing_still_sends_its_own_alarm_bit(model):
    least = model.trusted_.layer.ood.stillness.least
    j = int(np.argmax(least))  # the marker every simulation moved most, relative to the others
    assert least[j] > 0.05
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        held = _positions(model, 4)
        held[j] = model.reference_marker_positions[j]  # tracked where it was before surgery: it did not move
        assert not model.check_input(held - model.reference_marker_positions).refused
        client.predict(held)
        status = client.receive()
        assert status.header.message_type == "STATUS" and status.status.subcode & AlarmBits.STILL_MARKER
        assert f"marker {j} did not move" in status.text


def test_two_exchanged_markers_send_their_own_alarm_bit_naming_them(model):
    """On this small body the input gate refuses every exchange (its markers' distances barely
    change in the simulations); with the gate off, the alarm names the exchanged pair."""
    ref = model.reference_marker_positions
    positions = _positions(model, 4)
    i, j = min(itertools.combinations(range(len(ref)), 2), key=lambda p: np.linalg.norm(ref[p[0]] - ref[p[1]]))
    positions[[i, j]] = positions[[j, i]]  # the tracker's labels of the two nearest markers exchanged
    assert model.check_input(positions - ref).refused
    with model.gate_suspended(), IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        client.predict(positions)
        status = client.receive()
        assert status.header.message_type == "STATUS" and status.status.subcode & AlarmBits.SWAPPED_MARKERS
        assert f"markers {i} and {j} look exchanged" in status.text


def test_the_mesh_goes_out_before_the_alarm_is_computed_and_both_are_as_before(model):
    """A session sends the surface (with its bounds) as soon as the field is predicted and only
    then computes the alarm, which reads the markers alone: the same mesh and the same alarm as
    one prediction with both."""
    from tissuecast.serve import SurfacePredictor
    from tissuecast.serve.session import ClientSession

    predictor = SurfacePredictor(model)
    far = model.reference_marker_positions + 3.0 * trust_data()[1][SPLITS["test"][0]][model.markers]
    far = far.astype(np.float32).astype(np.float64)  # as a POINT message carries them
    whole = predictor.predict(far, 1.0)
    assert whole.alarm.raised and whole.alarm_inputs is None
    mesh = bytes(predictor.surface_message(whole))
    later = predictor.predict(far, 1.0, alarm=False)
    assert later.alarm is None and later.alarm_inputs is not None
    np.testing.assert_array_equal(later.error_bound, whole.error_bound)
    np.testing.assert_equal(vars(predictor.with_alarm(later).alarm), vars(whole.alarm))
    assert predictor.with_alarm(whole) is whole  # nothing pending

    sent = []
    session = ClientSession(predictor, lambda data: sent.append((bytes(data), session.last.alarm)))
    session.feed(pyigtl.PointMessage(far, device_name="Markers", timestamp=1.0).pack())
    (surface, alarm_then), (status, alarm_after) = sent
    assert surface == mesh and alarm_then is None  # the mesh left before the alarm existed
    assert decode_status(status[58:]).subcode & AlarmBits.FAR_FROM_TRAINING and alarm_after.raised
    np.testing.assert_equal(vars(session.last.alarm), vars(whole.alarm))
