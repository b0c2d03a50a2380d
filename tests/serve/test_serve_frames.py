"""Serving in the client's frame: 3D Slicer's RAS, and tracker registrations sent as TRANSFORMs
(TrackerToRas, ReferenceToRas, TrackerToImage) or given in the config."""

from __future__ import annotations

import time

import numpy as np
import pyigtl
import pytest
from scipy.spatial.transform import Rotation
from serve_support import small_model

from tissuecast.config import config_from_dict
from tissuecast.errors import ConfigError
from tissuecast.frames import LPS_TO_RAS, apply_transform
from tissuecast.serve import ClientFrames, IGTLClient, IGTLServer

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def model():
    return small_model("single")


def rigid(seed: int) -> np.ndarray:
    """A 4x4 rigid transform (rotation up to ~70 degrees, translation ~100 mm), float32-exact."""
    rng = np.random.default_rng(seed)
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.7, 3)).as_matrix()
    m[:3, 3] = rng.normal(0.0, 100.0, 3)
    return m.astype(np.float32).astype(np.float64)


def expected(model, positions_lps):
    u = model.predict(positions_lps - model.reference_marker_positions)
    return (model.mesh.points + u)[model.mesh.surface_vertices], u


def markers_lps(model, seed=0):
    rng = np.random.default_rng(seed)
    return model.reference_marker_positions + rng.normal(0.0, 1.5, (model.n_markers, 3))


def send_registration(client, name: str, matrix: np.ndarray) -> None:
    client.send(pyigtl.TransformMessage(matrix.astype(np.float32), device_name=name))


def test_slicer_client_in_ras_gets_ras_surface_and_field(model):
    lps = markers_lps(model)
    ras = apply_transform(LPS_TO_RAS, lps).astype(np.float32).astype(np.float64)
    lps = apply_transform(LPS_TO_RAS, ras)  # what the server sees after float32 transport
    with IGTLServer(model, "127.0.0.1", 0, frames=ClientFrames("RAS")) as server, IGTLClient(*server.address) as client:
        reply = client.predict(ras)
        surface, u = expected(model, lps)
        np.testing.assert_allclose(reply.polydata.points, apply_transform(LPS_TO_RAS, surface), atol=1e-4)
        client.request_field()
        field = client.receive().polydata
        np.testing.assert_allclose(field.point_data["displacement_mm"], u * [-1, -1, 1], atol=1e-5)


@pytest.mark.parametrize("name, target", [("TrackerToRas", "RAS"), ("ReferenceToRas", "RAS"), ("TrackerToImage", "LPS")])
def test_registration_transform_maps_tracker_markers_and_answers_in_its_target(model, name, target):
    lps = markers_lps(model, 1)
    to_client = rigid(7)
    model_to_client = LPS_TO_RAS if target == "RAS" else np.eye(4)
    tracker = apply_transform(np.linalg.inv(to_client) @ model_to_client, lps).astype(np.float32).astype(np.float64)
    seen = apply_transform(np.linalg.inv(model_to_client) @ to_client, tracker)  # markers in the model frame
    with IGTLServer(model, "127.0.0.1", 0) as server, IGTLClient(*server.address) as client, \
            IGTLClient(*server.address) as navigation:
        # before any registration the tracker positions are far from the model: refused (the input
        # gate: displaced many times the largest simulated displacement)
        client.send_positions(tracker)
        refusal, error = client.receive(), client.receive()  # STATUS InputRefused, then the error reply
        assert refusal.header.message_type == "STATUS" and "marker input refused" in error.text
        send_registration(navigation, name, to_client)  # e.g. Slicer's registration on its own connection
        deadline = time.monotonic() + 10.0  # a registration has no reply: wait until the server took it
        while server.frames.source != name and time.monotonic() < deadline:
            time.sleep(0.01)
        reply = client.predict(tracker)
        surface, _ = expected(model, seen)
        np.testing.assert_allclose(reply.polydata.points, apply_transform(model_to_client, surface), atol=2e-4)
        assert server.frames.source == name and server.frames.client_frame == target


def test_registration_from_the_config(model):
    cfg = config_from_dict({"serve": {"client_frame": "RAS", "tracker_to_client": rigid(3).ravel().tolist()}})
    frames = ClientFrames(cfg.serve.client_frame, cfg.serve.tracker_to_client)
    lps = markers_lps(model, 2)
    tracker = apply_transform(np.linalg.inv(rigid(3)) @ LPS_TO_RAS, lps)
    np.testing.assert_allclose(frames.to_model(tracker), lps, atol=1e-9)
    with pytest.raises(ConfigError, match="tracker_to_client must be a 4x4 matrix"):
        config_from_dict({"serve": {"tracker_to_client": [1.0, 0.0, 0.0]}})
    with pytest.raises(ConfigError, match="singular"):
        config_from_dict({"serve": {"tracker_to_client": [0.0] * 15 + [1.0]}})
    with pytest.raises(ConfigError, match="client_frame"):
        config_from_dict({"serve": {"client_frame": "XYZ"}})


def test_unusable_registration_is_answered_and_ignored(model):
    with IGTLServer(model, "127.0.0.1", 0) as server, IGTLClient(*server.address) as client:
        singular = np.eye(4)
        singular[2, 2] = 0.0
        send_registration(client, "TrackerToRas", singular)
        reply = client.receive()
        assert reply.is_error and "singular" in reply.text
        assert server.frames.source == "none"
        lps = markers_lps(model, 3).astype(np.float32).astype(np.float64)
        np.testing.assert_allclose(client.predict(lps).polydata.points, expected(model, lps)[0], atol=1e-4)
