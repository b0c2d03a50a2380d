"""SubModelSet (one sub-model per dropped marker): routing, persistence, serving with a marker missing."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from serve_support import box_mesh

from tissuecast.errors import ModelError
from tissuecast.serve import IGTLClient, IGTLServer
from tissuecast.serve.synthetic import synthetic_fields
from tissuecast.surrogate.robust import SubModelSet, load_model_folder

pytestmark = pytest.mark.timeout(180)


@functools.lru_cache(maxsize=None)
def model_set() -> SubModelSet:
    mesh = box_mesh()
    fields = synthetic_fields(mesh, 60, seed=3)
    return SubModelSet.fit(fields, [0, 63, 7, 60], mesh=mesh, epochs=8, hidden=(16, 16), n_components=6)


def test_routing_matches_the_individual_models():
    s = model_set()
    rng = np.random.default_rng(0)
    d = rng.normal(0.0, 2.0, (5, 4, 3))
    np.testing.assert_array_equal(s.predict(d), s.full.predict(d))
    for i in range(4):
        np.testing.assert_allclose(s.predict(d, missing=[i]), s.subs[i].predict(np.delete(d, i, axis=1)))
    # per-sample masks route each sample to its own model; the missing marker's value is ignored
    mask = np.zeros((5, 4), dtype=bool)
    mask[1, 2] = mask[3, 0] = True
    d_nan = d.copy()
    d_nan[1, 2] = 1e6
    got = s.predict(d_nan, missing=mask)
    np.testing.assert_allclose(got[1], s.subs[2].predict(np.delete(d[1], 2, axis=0)))
    np.testing.assert_allclose(got[3], s.subs[0].predict(np.delete(d[3], 0, axis=0)))
    np.testing.assert_allclose(got[0], s.full.predict(d[0]))
    with pytest.raises(ModelError, match="at most one"):
        s.predict(d, missing=[0, 1])
    with pytest.raises(ModelError, match="indices"):
        s.predict(d, missing=[4])


def test_save_load_round_trip(tmp_path):
    s = model_set()
    s.save(tmp_path / "set")
    loaded = load_model_folder(tmp_path / "set")
    assert isinstance(loaded, SubModelSet)
    d = np.random.default_rng(1).normal(0.0, 2.0, (3, 4, 3))
    for missing in (None, [1]):
        np.testing.assert_allclose(loaded.predict(d, missing=missing), s.predict(d, missing=missing), rtol=1e-6, atol=1e-9)
    (tmp_path / "set" / "submodels.json").write_text('{"format": "other"}')
    with pytest.raises(ModelError, match="unknown format"):
        SubModelSet.load(tmp_path / "set")


def test_server_predicts_with_an_untracked_marker():
    s = model_set()
    with IGTLServer(s, "127.0.0.1", 0) as server, IGTLClient(*server.address) as client:
        positions = (s.reference_marker_positions + 1.5).astype(np.float32).astype(np.float64)
        positions[3] = np.nan
        reply = client.predict(positions)
        u = s.subs[3].predict(np.delete(positions - s.reference_marker_positions, 3, axis=0))
        expected = (s.mesh.points + u)[s.mesh.surface_vertices]
        np.testing.assert_allclose(reply.polydata.points, expected, atol=1e-4)
        positions[1] = np.nan  # two untracked markers: an error reply, the connection stays usable
        client.send_positions(positions)
        assert "at most one untracked marker" in client.receive().text


def test_a_sub_model_set_serves_the_rigid_baseline_from_its_markers():
    """Rigid registration learns nothing: any predictor's markers and mesh give it."""
    from tissuecast.registration import rigid_registration_field
    from tissuecast.serve import SurfacePredictor

    s = model_set()
    predictor = SurfacePredictor(s, method="rigid")
    assert predictor.supports_missing and not predictor.has_uncertainty and not predictor.has_bounds
    positions = s.reference_marker_positions + np.array([1.0, -0.5, 2.0])
    positions[3] = np.nan  # untracked: left out of the fit
    got = predictor.predict(positions, 0.0).displacement
    d = positions - s.reference_marker_positions
    np.testing.assert_allclose(got, rigid_registration_field(s.mesh.points, s.markers[:3], d[None, :3])[0], atol=1e-12)
    np.testing.assert_allclose(got, np.broadcast_to([1.0, -0.5, 2.0], got.shape), atol=1e-9)  # a pure translation
