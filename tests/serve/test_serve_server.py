"""The OpenIGTLink server on a loopback port with real DeformationModels (small, synthetic)."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pyigtl
import pytest
from serve_support import small_model

from tissuecast.serve import IGTLClient, IGTLServer, SurfacePredictor
from tissuecast.serve.protocol import ProtocolError
from tissuecast.surrogate import FieldPredictor

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def model():
    return small_model("single")


@pytest.fixture()
def server(model):
    with IGTLServer(model, "127.0.0.1", 0, client_timeout=0.5) as srv:
        yield srv


def motion(model, seed: int, scale: float = 2.0) -> np.ndarray:
    """Marker positions (n_d, 3) mm: reference plus a random offset; float32-exact."""
    rng = np.random.default_rng(seed)
    p = model.reference_marker_positions + rng.normal(0.0, scale, (model.n_markers, 3))
    return p.astype(np.float32).astype(np.float64)


def expected_surface(model, positions):
    mesh = model.mesh
    u = model.predict(positions - model.reference_marker_positions)
    return (mesh.points + u)[mesh.surface_vertices], u


def assert_surface(reply, model, positions):
    points, _ = expected_surface(model, positions)
    assert reply.header.message_type == "POLYDATA" and reply.header.device_name == "TissueSurface"
    np.testing.assert_allclose(reply.polydata.points, points, rtol=0, atol=1e-5 * np.abs(points).max())
    # triangles re-indexed into the surface points are the mesh's outer surface
    sv = model.mesh.surface_vertices
    np.testing.assert_array_equal(sv[reply.polydata.triangles()], model.mesh.surface_triangles)


def test_point_message_returns_predicted_surface_and_field(server, model):
    with IGTLClient(*server.address) as client:
        for seed in range(3):
            positions = motion(model, seed)
            client.send_positions(positions, timestamp=1000.0 + seed)
            reply = client.receive()
            assert_surface(reply, model, positions)
            assert reply.header.timestamp == pytest.approx(1000.0 + seed, abs=1e-6)
        client.request_field()
        field = client.receive()
        _, u = expected_surface(model, positions)
        assert field.header.device_name == "TissueField"
        np.testing.assert_allclose(field.polydata.point_data["displacement_mm"], u, atol=1e-5 * np.abs(u).max())
        np.testing.assert_allclose(field.polydata.points, model.mesh.points + u, atol=1e-4)
        np.testing.assert_array_equal(field.polydata.triangles(), model.mesh.surface_triangles)
    assert server.stats["replies"] == 4


def test_transform_messages_frame_and_each_modes(model):
    for mode in ("frame", "each"):
        with IGTLServer(model, "127.0.0.1", 0, transform_mode=mode) as srv, IGTLClient(*srv.address) as client:
            first, second = motion(model, 10), motion(model, 11)
            client.send_transforms(first)
            assert_surface(client.receive(), model, first)
            if mode == "frame":  # PLUS-style names address the same markers
                for i, xyz in enumerate(second):
                    matrix = np.eye(4)
                    matrix[:3, 3] = xyz
                    client.send(pyigtl.TransformMessage(matrix, device_name=f"Marker{i}ToTracker"))
                assert_surface(client.receive(), model, second)
            # update only marker 0: 'each' predicts at once, 'frame' waits for every marker
            update = first.copy()
            update[0] = second[0]
            client.send_transforms(update[:1])
            if mode == "each":
                assert_surface(client.receive(), model, update)
            client.send_transforms(second)
            replies = 1 if mode == "frame" else model.n_markers
            for _ in range(replies - 1):
                client.receive()
            assert_surface(client.receive(), model, second)


def test_full_field_flag_sends_both_messages(model):
    with IGTLServer(model, "127.0.0.1", 0, full_field=True) as srv, IGTLClient(*srv.address) as client:
        positions = motion(model, 5)
        client.send_positions(positions)
        names = [client.receive().header.device_name for _ in range(2)]
        assert names == ["TissueSurface", "TissueField"]


def test_server_from_a_serve_config_section(model):
    from tissuecast.config import ServeConfig
    from tissuecast.frames import LPS_TO_RAS

    shift = np.eye(4)
    shift[:3, 3] = [5.0, -2.0, 1.0]
    cfg = ServeConfig(full_field=True, client_frame="RAS", tracker_to_client=tuple(shift.ravel()), client_timeout=0.25,
                      max_marker_offset=40.0)
    with IGTLServer.from_config(model, cfg, host="127.0.0.1", port=0) as srv, IGTLClient(*srv.address) as client:
        assert srv.client_timeout == 0.25 and srv.predictor.max_marker_offset == 40.0
        assert srv.frames.client_frame == "RAS" and srv.frames.source == "config"
        positions = motion(model, 4)  # model (LPS) frame -> tracker coordinates of the registration
        ras = positions @ LPS_TO_RAS[:3, :3].T
        client.send_positions(ras - shift[:3, 3], timestamp=5.0)
        surface, field = client.receive(), client.receive()  # full_field: both messages
        assert surface.header.device_name == "TissueSurface" and field.header.device_name == "TissueField"
        expected, _ = expected_surface(model, positions)
        np.testing.assert_allclose(surface.polydata.points, expected @ LPS_TO_RAS[:3, :3].T, atol=1e-4)


def test_ensemble_uncertainty_is_sent_as_point_data():
    ens = small_model("ensemble")
    with IGTLServer(ens, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        positions = motion(ens, 7)
        reply = client.predict(positions)
        u, sigma = ens.predict_with_uncertainty(positions - ens.reference_marker_positions)
        sv = ens.mesh.surface_vertices
        np.testing.assert_allclose(reply.polydata.points, (ens.mesh.points + u)[sv], atol=1e-4)
        got = reply.polydata.point_data["uncertainty_mm"]
        np.testing.assert_allclose(got, sigma[sv], rtol=1e-5, atol=1e-7)
        assert got.max() > 0


def test_missing_marker_as_nan_point_with_masked_model():
    masked = small_model("masked")
    with IGTLServer(masked, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        positions = motion(masked, 8)
        positions[2] = np.nan
        reply = client.predict(positions)
        u = masked.predict(np.nan_to_num(positions - masked.reference_marker_positions), missing=[2])
        sv = masked.mesh.surface_vertices
        np.testing.assert_allclose(reply.polydata.points, (masked.mesh.points + u)[sv], atol=1e-4)


def test_bad_input_gets_error_replies_and_connection_survives(server, model):
    with IGTLClient(*server.address) as client:
        client.send_positions(motion(model, 1)[:2])
        assert "expected 4 marker positions" in client.receive().text
        bad = motion(model, 1)
        bad[1, 0] = np.inf
        client.send_positions(bad)  # refused by the model's input gate: STATUS InputRefused, then the error
        status = client.receive()
        assert status.header.message_type == "STATUS" and status.status.error_name == "InputRefused"
        assert "marker 1 (input index 1" in status.text and "NaN or inf" in client.receive().text
        client.send_positions(motion(model, 1) + 500.0)
        assert client.receive().status.error_name == "InputRefused"
        assert "more than 3 x the largest simulated displacement" in client.receive().text
        client.send(pyigtl.TransformMessage(np.eye(4), device_name="Needle"))
        assert "not a marker" in client.receive().text
        client.send(pyigtl.TransformMessage(np.eye(4), device_name="Marker4"))  # only 0..3 exist
        assert "not a marker" in client.receive().text
        client.send(pyigtl.ImageMessage(np.zeros((2, 2, 2), np.uint8), device_name="US"))
        assert "unsupported message type 'IMAGE'" in client.receive().text
        client.request_field()
        assert "no prediction yet" in client.receive().text
        with pytest.raises(ProtocolError, match="server error"):
            client.predict(motion(model, 1)[:1])
        positions = motion(model, 2)
        assert_surface(client.predict(positions), model, positions)


def test_oversized_body_is_rejected_unread_and_connection_closed(server, model):
    with IGTLClient(*server.address) as client:
        header = pyigtl.StringMessage("x", device_name="D").pack()[:58]
        client.send(header[:42] + (2**62).to_bytes(8, "big") + header[50:])
        reply = client.receive()
        assert reply.is_error and "exceeds the limit" in reply.text
        with pytest.raises(ConnectionError):
            client.receive()
    with IGTLClient(*server.address) as client:  # the server still serves others
        positions = motion(model, 3)
        assert_surface(client.predict(positions), model, positions)


def test_concurrent_clients_and_a_stalled_one(server, model):
    stalled = socket.create_connection(server.address)
    stalled.sendall(pyigtl.PointMessage(motion(model, 0), device_name="M").pack()[:70])  # never finished
    errors = []

    def worker(k: int) -> None:
        try:
            with IGTLClient(*server.address) as client:
                for i in range(25):
                    positions = motion(model, 100 * k + i)
                    assert_surface(client.predict(positions), model, positions)
        except Exception as exc:  # collected and re-raised in the main thread
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors[0]
    assert server.stats["replies"] == 6 * 25
    deadline = time.monotonic() + 10
    while server.stats["timeouts"] == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.stats["timeouts"] == 1  # the stalled client was dropped after client_timeout
    stalled.settimeout(5)
    assert stalled.recv(100) == b""
    stalled.close()


def test_client_that_never_reads_is_dropped(model):
    with IGTLServer(model, "127.0.0.1", 0, max_output_bytes=200_000) as srv:
        greedy = socket.create_connection(srv.address)
        greedy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        message = pyigtl.PointMessage(motion(model, 0), device_name="M").pack()
        greedy.settimeout(5)
        try:
            for _ in range(5000):
                greedy.sendall(message)
                if srv.stats["disconnections"]:
                    break
        except OSError:
            pass  # reset by the server
        deadline = time.monotonic() + 10
        while srv.stats["disconnections"] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert srv.stats["disconnections"] == 1
        greedy.close()
        with IGTLClient(*srv.address) as client:
            positions = motion(model, 4)
            assert_surface(client.predict(positions), model, positions)


def test_predictor_rejects_what_is_not_a_field_predictor():
    class LooksLikeOne:  # duck-typed, but it declares none of the protocol's capabilities
        mesh = small_model("single").mesh
        reference_marker_positions = small_model("single").reference_marker_positions

        def predict_from_positions(self, positions):
            return np.zeros((64, 3))

    with pytest.raises(ValueError, match="serve needs a FieldPredictor .* got LooksLikeOne"):
        SurfacePredictor(LooksLikeOne())


def test_cli_serve_subprocess_round_trip(model, tmp_path):
    folder = tmp_path / "model"
    model.save(folder)
    code = "import sys; from tissuecast.cli.main import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", code, "-q", "serve", str(folder), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("serving") and "127.0.0.1:" in line, line + proc.stderr.read()
        port = int(line.split(" on ")[1].split()[0].rsplit(":", 1)[1])
        banner = [proc.stdout.readline() for _ in range(4)]  # input, frames, output, status
        assert banner[3].startswith("  status: STATUS TissueStatus") and "InputRefused" in banner[3], banner
        with IGTLClient("127.0.0.1", port) as client:
            positions = motion(model, 9)
            assert_surface(client.predict(positions), model, positions)
    finally:
        proc.terminate()
        proc.wait(20)


def test_pyigtl_client_interoperates(server, model):
    """pyigtl's own threaded client: its messages are understood, our STRING replies are readable."""
    client = pyigtl.OpenIGTLinkClient("127.0.0.1", server.address[1])
    try:
        client.send_message(pyigtl.PointMessage(motion(model, 1).astype(np.float32), device_name="Markers"))
        client.send_message(pyigtl.PointMessage(motion(model, 1)[:1].astype(np.float32), device_name="Markers"))
        reply = client.wait_for_message("ERROR", timeout=10)
        assert reply is not None and reply.string.startswith("expected 4 marker positions") and reply.string.endswith("got 1")
    finally:
        client.stop()
    assert server.stats["replies"] == 2  # one POLYDATA (pyigtl cannot decode it and drops it), one ERROR


def test_session_handles_byte_by_byte_delivery(model):
    from tissuecast.serve.session import ClientSession

    replies = []
    session = ClientSession(SurfacePredictor(model), lambda data: replies.append(bytes(data)))
    positions = motion(model, 6)
    one = pyigtl.PointMessage(positions.astype(np.float32), device_name="M").pack()
    raw = one * 2
    for i in range(len(raw)):
        session.feed(raw[i : i + 1])
        assert session.partial == ((i + 1) % len(one) != 0)
    assert len(replies) == 2 and replies[0] == replies[1]
    with IGTLServer(model, "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        client.send(replies[0])  # a POLYDATA sent *to* the server is refused politely
        assert "unsupported message type 'POLYDATA'" in client.receive().text


def test_pipelining_client_does_not_starve_others(model):
    """A client that pipelines 400 requests is served in turns of messages_per_turn."""
    with IGTLServer(model, "127.0.0.1", 0, messages_per_turn=4) as srv:
        flood = IGTLClient(*srv.address, timeout=30)
        positions = motion(model, 12)
        flood.send(pyigtl.PointMessage(positions.astype(np.float32), device_name="M").pack() * 400)
        with IGTLClient(*srv.address) as client:
            other = motion(model, 13)
            assert_surface(client.predict(other), model, other)
        for _ in range(400):
            assert_surface(flood.receive(), model, positions)
        flood.close()
        assert srv.stats["replies"] == 401


def test_cli_serve_rejects_bad_options(tmp_path, capsys):
    from tissuecast.cli.main import main

    assert main(["serve", str(tmp_path), "--max-offset", "-1"]) == 2
    assert "serve.max_marker_offset" in capsys.readouterr().err
    assert main(["serve", str(tmp_path), "--port", "-1"]) == 2
    assert "--port -1: give 0 (any free port) or a TCP port 1-65535" in capsys.readouterr().err
    assert main(["serve", str(tmp_path / "missing-model"), "--port", "0"]) == 2
    assert "error:" in capsys.readouterr().err
    small_model("single").save(tmp_path / "model")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        assert main(["serve", str(tmp_path / "model"), "--port", str(busy.getsockname()[1])]) == 2
    assert "cannot listen on 127.0.0.1:" in capsys.readouterr().err


def test_failing_model_gets_error_reply_and_server_survives(model):
    class Flaky(FieldPredictor):
        """Delegates to the real model but fails on every other call."""

        name = "flaky"
        mesh = model.mesh
        markers = model.markers
        calls = 0

        def _predict_batch(self, d, missing):
            Flaky.calls += 1
            if Flaky.calls % 2:
                raise RuntimeError("simulated failure")
            return model.predict(d)

    with IGTLServer(Flaky(), "127.0.0.1", 0) as srv, IGTLClient(*srv.address) as client:
        positions = motion(model, 14)
        client.send_positions(positions)
        assert client.receive().text == "model evaluation failed: RuntimeError: simulated failure"
        assert_surface(client.predict(positions), model, positions)
        assert srv.stats["internal_errors"] == 0


def test_rigid_method_serves_the_markers_rigid_motion(model):
    """serve.method = "rigid": a rigid motion of the markers moves the whole surface rigidly."""
    from scipy.spatial.transform import Rotation

    from tissuecast.config import Config, with_overrides

    rotation = Rotation.from_rotvec([0.05, -0.08, 0.12]).as_matrix()
    shift = np.array([1.5, -2.0, 0.7])
    centre = model.mesh.points.mean(axis=0)
    moved = lambda p: (p - centre) @ rotation.T + centre + shift  # noqa: E731
    positions = moved(model.reference_marker_positions).astype(np.float32).astype(np.float64)
    serve = with_overrides(Config(), serve={"method": "rigid"}).serve
    with IGTLServer.from_config(model, serve, host="127.0.0.1", port=0) as srv, IGTLClient(*srv.address) as client:
        assert srv.predictor.method == "rigid" and not srv.predictor.has_uncertainty
        reply = client.predict(positions)
    expected = moved(model.mesh.points)[model.mesh.surface_vertices]
    np.testing.assert_allclose(reply.polydata.points, expected, rtol=0, atol=1e-3)  # float32 points, markers float32
    learned, _ = expected_surface(model, positions)
    assert np.abs(learned - expected).max() > 1e-2  # the learned model's answer differs: the rigid path was used


def test_rigid_method_errors(model):
    from tissuecast.errors import ConfigError, ModelError

    with pytest.raises(ConfigError, match="unknown serving method 'affine'"):
        SurfacePredictor(model, method="affine")

    class TwoMarkers(FieldPredictor):  # a rigid motion needs 3 markers not on one line
        mesh = model.mesh
        markers = model.markers[:2]

        def _predict_batch(self, d, missing):
            return np.zeros((len(d), model.mesh.n_vertices, 3))

    with pytest.raises(ModelError, match="rigid registration needs at least 3 markers, this model has 2"):
        SurfacePredictor(TwoMarkers(), method="rigid")
    assert SurfacePredictor(TwoMarkers()).method == "mlp"  # the predictor itself serves
