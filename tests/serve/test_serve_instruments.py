"""Serving a model that reads a tracked instrument: its TRANSFORM in (mapped like the markers), the
prediction with its pose, the markers-only fallback and a STATUS when its messages stop."""

from __future__ import annotations

import numpy as np
import pyigtl
import pytest

from _instrument_synthetic import SPLITS, instrument_data, instrument_model
from tissuecast.errors import ConfigError
from tissuecast.serve import IGTLClient, IGTLServer, SurfacePredictor
from tissuecast.serve.instruments import LOST_NAME, TRACKED_NAME
from tissuecast.serve.status import StatusCode

pytestmark = pytest.mark.timeout(120)


class Clock:
    """A settable server clock (seconds)."""

    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _sample():
    model = instrument_model()
    _, U, poses, _ = instrument_data()
    k = next(int(i) for i in SPLITS["test"] if poses[i].contact)
    markers = (model.reference_marker_positions + U[k][model.markers]).astype(np.float32).astype(np.float64)
    tool = np.eye(4)
    tool[:3, :3] = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]  # the tool's +z pushes along -z
    tool[:3, 3] = poses[k].tip
    return model, markers, tool.astype(np.float32).astype(np.float64), poses[k]


def _replies(client, count: int) -> list:
    return [client.receive() for _ in range(count)]


def _surface(model, u) -> np.ndarray:
    return (model.mesh.points + u)[model.mesh.surface_vertices]


def test_the_instrument_pose_is_used_until_its_messages_stop(tmp_path):
    model, markers, tool, pose = _sample()
    d = markers - model.reference_marker_positions
    with_pose = model.predict(d, auxiliary={"retractor": pose})
    markers_only = model.predict(d)
    clock = Clock()
    with IGTLServer(model, "127.0.0.1", 0, instrument_timeout=0.5) as srv, IGTLClient(*srv.address) as client:
        srv.instruments.clock = clock
        client.send_positions(markers)  # no instrument yet: markers only, and a STATUS saying so
        first = _replies(client, 2)
        assert first[1].status.code == StatusCode.TIME_OUT and first[1].status.error_name == LOST_NAME
        np.testing.assert_allclose(first[0].polydata.points, _surface(model, markers_only), atol=1e-4)
        client.send(pyigtl.TransformMessage(tool, device_name="RetractorToReference"))
        client.send_positions(markers)
        surface, status = _replies(client, 2)
        np.testing.assert_allclose(surface.polydata.points, _surface(model, with_pose), atol=1e-4)
        assert status.status.code == StatusCode.OK and status.status.error_name == TRACKED_NAME
        clock.now += 0.4  # still fresh: same prediction, no STATUS
        client.send_positions(markers)
        again = client.receive()
        np.testing.assert_allclose(again.polydata.points, _surface(model, with_pose), atol=1e-4)
        clock.now += 0.2  # 0.6 s since the TRANSFORM: lost
        client.send_positions(markers)
        surface, status = _replies(client, 2)
        np.testing.assert_allclose(surface.polydata.points, _surface(model, markers_only), atol=1e-4)
        assert status.status.error_name == LOST_NAME and "no TRANSFORM for 0.5 s" in status.text
    assert np.abs(with_pose - markers_only).max() > 0.05


def test_the_instrument_is_mapped_by_the_registration_like_the_markers():
    from scipy.spatial.transform import Rotation

    model, markers, tool, pose = _sample()
    registration = np.eye(4)
    registration[:3, :3] = Rotation.from_euler("xyz", [10.0, -20.0, 35.0], degrees=True).as_matrix()
    registration[:3, 3] = [40.0, -12.0, 7.0]
    to_tracker = np.linalg.inv(registration)
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        client.send(pyigtl.TransformMessage(registration, device_name="TrackerToImage"))
        client.send(pyigtl.TransformMessage(to_tracker @ tool, device_name="RetractorToReference"))
        client.send_positions((to_tracker[:3, :3] @ markers.T).T + to_tracker[:3, 3])
        surface, status = _replies(client, 2)
    expected = model.predict(markers - model.reference_marker_positions, auxiliary={"retractor": pose})
    np.testing.assert_allclose(surface.polydata.points, _surface(model, expected), atol=2e-4)
    assert status.status.error_name == TRACKED_NAME


def test_instrument_devices_and_parameters_are_checked():
    model, markers, tool, _ = _sample()
    with pytest.raises(ConfigError, match="would be read as a marker or a registration"):
        SurfacePredictor(model, devices={"retractor": "Marker2"})
    with pytest.raises(ConfigError, match="would be read as a marker or a registration"):
        SurfacePredictor(model, devices={"retractor": "RetractorToRas"})
    with pytest.raises(ConfigError, match=r"instrument devices given for \['spatula'\]"):
        SurfacePredictor(model, devices={"spatula": "SpatulaToTracker"})
    with pytest.raises(ConfigError, match=r"does not read \['youngs_modulus'\]"):
        SurfacePredictor(model, parameters={"youngs_modulus": 1.0})
    renamed = SurfacePredictor(model, devices={"retractor": "ToolToTracker"})
    assert renamed.instrument_devices == {"ToolToTracker": "retractor"}
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        flat = tool.copy()
        flat[:3, 2] = 0.0  # no push direction: refused, the connection goes on
        client.send(pyigtl.TransformMessage(flat, device_name="RetractorToReference"))
        assert client.receive().text.startswith("TRANSFORM 'RetractorToReference': an instrument pose needs")
        client.send(pyigtl.TransformMessage(tool, device_name="Spatula"))
        assert "or an instrument (RetractorToReference)" in client.receive().text


def test_a_model_reading_a_measured_parameter_needs_it_to_be_served():
    from tissuecast.surrogate import DeformationModel
    from tissuecast.surrogate.auxiliary import AuxiliaryInputs, AuxiliaryValues

    from _surrogate_synthetic import MARKERS

    mesh, U, _, _ = instrument_data()
    spec = AuxiliaryInputs(parameters=("youngs_modulus",))
    m = DeformationModel(epochs=3, n_components=4, hidden=(8,), calibration_share=0.0)
    m.fit(U[:60], MARKERS, mesh=mesh, auxiliary=AuxiliaryValues(spec, np.ones((60, 1))))
    with pytest.raises(ConfigError, match=r"give \['youngs_modulus'\] \(--parameter NAME=VALUE\)"):
        SurfacePredictor(m)
    served = SurfacePredictor(m, parameters={"youngs_modulus": 1.0})
    positions = m.reference_marker_positions
    np.testing.assert_array_equal(served.predict(positions, 0.0).displacement,
                                  m.predict(np.zeros((m.n_markers, 3)), auxiliary={"youngs_modulus": 1.0}))
