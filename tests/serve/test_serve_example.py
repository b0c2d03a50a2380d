"""examples/stream_trajectory.py: stream a trajectory, get a VTU time series that matches the model."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import meshio
import numpy as np
import pytest
from serve_support import small_model

pytestmark = pytest.mark.timeout(120)

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "stream_trajectory.py"


def load_example():
    spec = importlib.util.spec_from_file_location("stream_trajectory", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_stream_trajectory_writes_matching_vtu_series(tmp_path):
    example = load_example()
    model = small_model("single")
    model.save(tmp_path / "model")
    files = example.main(["--model", str(tmp_path / "model"), "--out", str(tmp_path / "out"), "--frames", "6"])
    assert [f.name for f in files] == [f"surface_{i:04d}.vtu" for i in range(6)]
    pvd = (tmp_path / "out" / "surface.pvd").read_text()
    assert pvd.count("<DataSet") == 6 and 'file="surface_0005.vtu"' in pvd
    times, positions = example.read_trajectory(tmp_path / "out" / "trajectory.csv")
    assert positions.shape == (6, model.n_markers, 3)
    mesh = meshio.read(files[4])
    u = model.predict_from_positions(positions[4].astype(np.float32))
    expected = (model.mesh.points + u)[model.mesh.surface_vertices]
    np.testing.assert_allclose(mesh.points, expected, atol=1e-4)
    sv = model.mesh.surface_vertices
    np.testing.assert_array_equal(sv[mesh.cells_dict["triangle"]], model.mesh.surface_triangles)
    assert np.ptp(positions[:, 0, 0]) > 0.1  # the markers actually move


def test_trajectory_csv_round_trip(tmp_path):
    example = load_example()
    reference = np.array([[0.0, 1.0, 2.0], [10.0, 11.0, 12.0]])
    times, positions = example.sample_trajectory(reference, n_frames=4, rate=10.0)
    example.write_trajectory(tmp_path / "t.csv", times, positions)
    t2, p2 = example.read_trajectory(tmp_path / "t.csv")
    np.testing.assert_allclose(t2, times, atol=1e-6)
    np.testing.assert_allclose(p2, positions, atol=1e-6)
    np.testing.assert_allclose(positions[0], reference)  # motion ramps up from rest
