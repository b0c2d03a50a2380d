"""Interoperability with the official OpenIGTLink C++ library (Debian libopenigtlink-dev).

A small client (tests/igtl_client/tissuecast_igtl_client.cxx) is compiled with g++ against the
library, sends a registration TRANSFORM and a POINT message, and unpacks the POLYDATA reply
with the library's own CRC check; the points and triangles must be the Python prediction.
Malformed messages must be answered (STRING ERROR) or, for a stream that can no longer be
trusted, answered and dropped; the out-of-distribution alarm arrives as a STATUS message the
library unpacks.

CI must run this test: with CI set, a missing library or compiler fails instead of skipping.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import numpy as np
import official_client
import pytest
from scipy.spatial.transform import Rotation
from serve_support import small_model

from tissuecast.frames import apply_transform
from tissuecast.serve import IGTLServer

pytestmark = pytest.mark.timeout(120)

@pytest.fixture(scope="module")
def client_binary(tmp_path_factory) -> Path:
    missing = official_client.missing()
    if missing:
        if os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no"):
            pytest.fail(f"CI must run the OpenIGTLink C++ interoperability test: {missing}; "
                        "scripts/install-system-deps.sh installs it")
        pytest.skip(missing)
    return official_client.build(tmp_path_factory.mktemp("igtl"), "-O1")


def _run(binary: Path, address, registration: str, matrix: np.ndarray, markers: np.ndarray) -> list[str]:
    args = [str(binary), address[0], str(address[1]), registration]
    args += [repr(float(v)) for v in matrix.ravel()] + [repr(float(v)) for v in markers.ravel()]
    done = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_cpp_client_point_and_transform_in_polydata_out_and_malformed_messages(client_binary):
    model = small_model("single")
    # tracker frame -> image (model LPS) frame: a rigid registration, exact in float32
    registration = np.eye(4)
    registration[:3, :3] = Rotation.from_euler("xyz", [25.0, -40.0, 60.0], degrees=True).as_matrix()
    registration[:3, 3] = [120.0, -35.0, 80.0]
    registration = registration.astype(np.float32).astype(np.float64)
    rng = np.random.default_rng(5)
    lps = model.reference_marker_positions + rng.normal(0.0, 1.5, (model.n_markers, 3))
    tracker = apply_transform(np.linalg.inv(registration), lps).astype(np.float32).astype(np.float64)
    with IGTLServer(model, "127.0.0.1", 0) as server:
        lines = _run(client_binary, server.address, "TrackerToImage", registration, tracker)

    head = lines[0].split()
    assert head[:3] == ["POLYDATA", "TissueSurface", "1"], lines[0]  # the library's CRC check passed
    mesh = model.mesh
    n_points, n_polygons = int(head[3]), int(head[4])
    assert (n_points, n_polygons) == (len(mesh.surface_vertices), len(mesh.surface_triangles))
    points = np.array([[float(v) for v in line.split()[1:]] for line in lines if line.startswith("P ")])
    triangles = np.array([[int(v) for v in line.split()[1:]] for line in lines if line.startswith("T ")])
    seen = apply_transform(registration, tracker)  # the markers the server predicts from
    u = model.predict(seen - model.reference_marker_positions)
    np.testing.assert_allclose(points, (mesh.points + u)[mesh.surface_vertices], atol=1e-4)
    np.testing.assert_array_equal(mesh.surface_vertices[triangles], mesh.surface_triangles)

    replies = [line for line in lines if line.startswith(("STRING", "CLOSED"))]
    assert replies[0].startswith("STRING ERROR 1 CRC mismatch in POINT message 'Markers'")
    assert replies[1].startswith(f"STRING ERROR 1 expected {model.n_markers} marker positions")
    assert replies[2].startswith("STRING ERROR 1 TRANSFORM device 'Needle' is not a marker")
    assert replies[3].startswith("STRING ERROR 1 unsupported header version 99")
    assert replies[4] == "CLOSED"


def test_cpp_client_reads_the_alarm_status(client_binary):
    """One marker 3 mm off (within the input gate's limits, the alarm's job): the surface reply,
    then a STATUS alarm, both unpacked by the library."""
    from _trust_synthetic import SPLITS, trust_data, trust_model

    from tissuecast.serve.status import ALARM_NAME, STATUS_DEVICE, AlarmBits, StatusCode

    model = trust_model()
    positions = model.reference_marker_positions + trust_data()[1][SPLITS["test"][5]][model.markers]
    positions[0] += [3.0, 0.0, 0.0]
    assert not model.check_input(positions - model.reference_marker_positions).refused
    with IGTLServer(model, "127.0.0.1", 0) as server:
        lines = _run(client_binary, server.address, "TrackerToImage", np.eye(4), positions)
    assert lines[0].startswith("POLYDATA TissueSurface 1 ")
    status = [line.split(" ", 6) for line in lines if line.startswith("STATUS ")]
    assert len(status) == 1, lines
    _, device, crc_ok, code, subcode, name, text = status[0]
    assert (device, crc_ok, int(code), name) == (STATUS_DEVICE, "1", int(StatusCode.UNKNOWN_ERROR), ALARM_NAME)
    assert int(subcode) & AlarmBits.INCONSISTENT_MARKERS and "markers disagree" in text


def test_cpp_client_streams_a_tracked_instrument_and_hears_when_it_is_lost(client_binary):
    """The retractor's TRANSFORM from the official library: the prediction uses its pose; once its
    messages stop for serve.instrument_timeout the server predicts from the markers only and
    says so in a STATUS the library unpacks."""
    from _instrument_synthetic import SPLITS, instrument_data, instrument_model

    from tissuecast.serve.instruments import LOST_NAME, TRACKED_NAME
    from tissuecast.serve.status import STATUS_DEVICE, StatusCode

    model = instrument_model()
    _, U, poses, _ = instrument_data()
    k = next(int(i) for i in SPLITS["test"] if poses[i].contact)
    markers = (model.reference_marker_positions + U[k][model.markers]).astype(np.float32).astype(np.float64)
    tool = np.eye(4)
    tool[:3, 2], tool[:3, 0], tool[:3, 1] = poses[k].direction, [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]
    tool[:3, 3] = poses[k].tip
    tool = tool.astype(np.float32).astype(np.float64)
    with IGTLServer(model, "127.0.0.1", 0, instrument_timeout=0.3) as server:
        args = [str(client_binary), *map(str, server.address), "--instrument", "RetractorToReference", "900"]
        done = subprocess.run(args + [repr(float(v)) for v in tool.ravel()] + [repr(float(v)) for v in markers.ravel()],
                              capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    heads = [i for i, line in enumerate(lines) if line.startswith(("POLYDATA", "STATUS"))]
    kinds = [lines[i].split()[0] for i in heads]
    assert kinds == ["POLYDATA", "STATUS"] * 3, kinds
    d = markers - model.reference_marker_positions
    pose = server.predictor.reference_surface.pose_from_transform(tool)
    expected = [model.predict(d), model.predict(d, auxiliary={"retractor": pose}), model.predict(d)]
    sv = model.mesh.surface_vertices
    for j, u in enumerate(expected):
        start = heads[2 * j]
        assert lines[start].split()[2] == "1"  # the library's CRC check passed
        points = np.array([[float(v) for v in line.split()[1:]] for line in lines[start + 1:heads[2 * j + 1]]
                           if line.startswith("P ")])
        np.testing.assert_allclose(points, (model.mesh.points + u)[sv], atol=1e-4)
    assert np.abs(expected[1] - expected[0]).max() > 0.05  # the pose changed the prediction
    status = [lines[heads[2 * j + 1]].split(" ", 6) for j in range(3)]
    for (_, device, crc_ok, code, _, name, text), (want_code, want_name) in zip(
            status, [(StatusCode.TIME_OUT, LOST_NAME), (StatusCode.OK, TRACKED_NAME), (StatusCode.TIME_OUT, LOST_NAME)]):
        assert (device, crc_ok, int(code), name) == (STATUS_DEVICE, "1", int(want_code), want_name)
        assert "RetractorToReference" in text
    assert "markers only" in status[2][6]


def test_cpp_client_latency_mode_times_every_frame_and_fails_on_a_reply_that_is_not_the_surface(client_binary):
    """The official client's timing mode (benchmarks/igtl_latency.py): TRANSFORM + POINT per frame,
    one time per frame after 20 warm-up frames, each POLYDATA passing the library's CRC check;
    paced, each frame waits the pause after the previous reply (the whole run lasts at least the
    pauses); a reply that is not the surface (a POINT one marker short is answered with a STRING)
    ends it with exit status 3, and a negative pause is refused with the usage (exit status 2)."""
    from _instrument_synthetic import instrument_model

    model = instrument_model()
    tool = np.eye(4)
    tool[:3, 3] = model.mesh.points[model.mesh.surface_vertices[0]]
    markers = model.reference_marker_positions
    frames = 40
    with IGTLServer(model, "127.0.0.1", 0) as server:
        def run(positions, pause_ms=0.0):
            args = [str(client_binary), *map(str, server.address), "--latency", str(frames), "RetractorToReference",
                    str(pause_ms)]
            args += [repr(float(v)) for v in tool.ravel()] + [repr(float(v)) for v in positions.ravel()]
            return subprocess.run(args, capture_output=True, text=True, timeout=60)

        done = run(markers)
        surfaces = server.stats["replies"]
        start = time.perf_counter()
        paced = run(markers, pause_ms=25.0)
        paced_seconds = time.perf_counter() - start
        short = run(markers[:-1])
        negative = run(markers, pause_ms=-1.0)
    for result in (done, paced):
        assert result.returncode == 0, result.stderr
        times = [line.split() for line in result.stdout.splitlines()]
        assert len(times) == frames and all(t[0] == "R" and int(t[1]) > 0 for t in times), result.stdout[:200]
    assert surfaces >= frames + 20  # a surface for every frame, warm-up included
    assert paced_seconds >= (frames + 20 - 1) * 0.025  # sleep_for waits at least the pause
    assert negative.returncode == 2 and "PAUSE_MS" in negative.stderr, (negative.returncode, negative.stderr)
    assert short.returncode == 3 and "no POLYDATA reply" in short.stderr, (short.returncode, short.stderr)
