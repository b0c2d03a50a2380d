"""The local decoder (global PCA + region-wise components of its residual): its numerics, the
config keys that select it, and a model that decodes with it (fast path, torch, ONNX, model
folder, trust layer)."""

import json

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.errors import ConfigError, ModelError
from tissuecast.surrogate import DeformationModel
from tissuecast.surrogate.decoder import LocalBasis, fit_local_basis, global_part, vertex_regions
from tissuecast.surrogate.pca import fit_pca

from _surrogate_synthetic import COMPILED_ATOL, MARKERS, box_mesh, nonlinear_fields


def _global_and_local_fields(mesh, labels, n, seed=0):
    """(n, 3 n_v) mm: 3 smooth modes that vanish on region 0, plus 2 random local modes on region
    0 alone. The first 100 samples' coefficients are centred and uncorrelated, so that the global
    PCA of 3 components fitted on them is the smooth modes' span and its residual the local one."""
    rng = np.random.default_rng(seed)
    p = 3 * mesh.n_vertices
    smooth = nonlinear_fields(mesh, np.eye(3)).reshape(3, p)
    in0 = np.repeat(labels == 0, 3)
    smooth[:, in0] = 0.0
    local = np.zeros((2, p))
    local[:, in0] = rng.normal(0.0, 0.05, (2, in0.sum()))
    Z = rng.normal(0, 1, (n, 5))
    q, _ = np.linalg.qr(Z[:100] - Z[:100].mean(axis=0))
    Z[:100] = q * np.sqrt(100) * np.array([3.0, 2.5, 2.0, 1.0, 0.7])
    return Z[:, :3] @ smooth + Z[:, 3:] @ local


def test_vertex_regions_cover_the_mesh_and_refuse_impossible_counts():
    mesh = box_mesh()
    labels = vertex_regions(mesh.points, 6)
    assert labels.shape == (mesh.n_vertices,) and set(labels.tolist()) == set(range(6))
    # two regions: the k-center centres are vertex 0 (a corner) and the farthest, the opposite
    # corner; every vertex goes to the nearer one
    P = mesh.points
    far = np.argmax(np.linalg.norm(P - P[0], axis=1))
    nearer_far = np.linalg.norm(P - P[far], axis=1) < np.linalg.norm(P - P[0], axis=1)
    np.testing.assert_array_equal(vertex_regions(P, 2), nearer_far.astype(int))
    assert len(set(vertex_regions(P, mesh.n_vertices).tolist())) == mesh.n_vertices
    for bad in (0, mesh.n_vertices + 1):
        with pytest.raises(ModelError, match="surrogate.decoder_regions"):
            vertex_regions(mesh.points, bad)


def test_local_components_are_local_orthonormal_and_reproduce_local_features():
    mesh = box_mesh()
    labels = vertex_regions(mesh.points, 5)
    U = _global_and_local_fields(mesh, labels, 120)
    pca = fit_pca(U[:100], 3)
    dec = fit_local_basis(U[:100], pca, labels, 4)
    # the residual has 2 directions (on region 0): only those are kept, largest first
    assert dec.n_local == 2 and dec.n_components == 5 and np.all(np.diff(dec.local_singular_values) <= 0)
    outside = ~np.repeat(labels == 0, 3)
    assert np.all(dec.local[:, outside] == 0.0)
    np.testing.assert_allclose(dec.local @ dec.local.T, np.eye(2), atol=1e-12)
    # new fields of the same kind: reproduced to round-off; the global PCA alone misses the local part
    new = U[100:]
    assert np.abs(dec.inverse_transform(dec.transform(new)) - new).max() < 1e-10
    assert np.abs(pca.inverse_transform(pca.transform(new)) - new).max() > 1e-2
    # the coefficients are the least-squares ones (cross-check) and the projection is idempotent
    w_ref = np.linalg.lstsq(dec.components.T, (new - dec.mean).T, rcond=None)[0].T
    np.testing.assert_allclose(dec.transform(new), w_ref, atol=1e-9)
    noisy = new + np.random.default_rng(1).normal(0, 0.1, new.shape)
    once = dec.inverse_transform(dec.transform(noisy))
    np.testing.assert_allclose(dec.inverse_transform(dec.transform(once)), once, atol=1e-9)
    assert global_part(dec) is pca and global_part(pca) is pca


def test_truncation_keeps_global_first_then_local_and_arrays_round_trip():
    mesh = box_mesh()
    labels = vertex_regions(mesh.points, 5)
    U = _global_and_local_fields(mesh, labels, 100)
    dec = fit_local_basis(U, fit_pca(U, 3), labels, 2)
    t2, t4 = dec.truncated(2), dec.truncated(4)
    assert (t2.n_global, t2.n_local, t4.n_global, t4.n_local) == (2, 0, 3, 1)
    np.testing.assert_array_equal(t4.components, dec.components[:4])
    back = LocalBasis.from_arrays(dec.pca, dec.arrays())
    np.testing.assert_array_equal(back.local, dec.local)
    np.testing.assert_array_equal(back.local_singular_values, dec.local_singular_values)
    with pytest.raises(ModelError, match="n_components"):
        dec.truncated(6)
    broken = {**dec.arrays(), "indices": dec.arrays()["indices"] + 3 * mesh.n_vertices}
    with pytest.raises(ModelError, match="corrupt"):
        LocalBasis.from_arrays(dec.pca, broken)
    with pytest.raises(ModelError, match="do not fit"):
        LocalBasis(dec.pca, dec.local[:, :-3], dec.local_singular_values)


@pytest.mark.parametrize("section, message", [
    ({"decoder": "graph"}, "surrogate.decoder"),
    ({"decoder_regions": 0}, "surrogate.decoder_regions"),
    ({"decoder_components": 0}, "surrogate.decoder_components"),
])
def test_decoder_keys_are_validated(section, message):
    with pytest.raises(ConfigError, match=message):
        with_overrides(Config(), surrogate=section)
    with pytest.raises(ConfigError, match=message):
        DeformationModel(**section)


# ---------------------------------------------------------------------- a model decoding with it
FAST = dict(epochs=80, patience=0, batch_size=64, learning_rate=3e-3, n_components=4, ensemble=2,
            decoder="local", decoder_regions=6, decoder_components=12, calibration_share=0.4)


@pytest.fixture(scope="module")
def local_model():
    mesh = box_mesh()
    theta = np.random.default_rng(0).uniform(-1, 1, (400, 3))
    U = nonlinear_fields(mesh, theta)
    model = DeformationModel(**FAST).fit(U[:360], MARKERS, mesh=mesh, train_idx=np.arange(300),
                                         valid_idx=np.arange(300, 330))
    return model, U


def test_model_decodes_with_the_local_basis(local_model):
    model, U = local_model
    dec = model.network_.basis
    assert isinstance(dec, LocalBasis) and (dec.n_global, dec.n_local) == (4, 12) and model.n_components == 16
    test = U[360:]
    d = model.marker_displacements(test)
    # the fast path is head + networks decoded by the local basis (the float64 reference, to float32's rounding)
    net = model.network_
    w = np.mean([m.predict_weights(d.reshape(len(d), -1)) for m in net.members], axis=0)
    w += net.head.predict(d.reshape(len(d), -1))
    np.testing.assert_allclose(model.predict(d), dec.inverse_transform(w).reshape(test.shape), rtol=0, atol=COMPILED_ATOL)
    np.testing.assert_allclose(model.predict(d[0]), model.predict(d)[0], rtol=0, atol=COMPILED_ATOL)
    # its floor is the local basis's projection, below the global part's
    floor = np.linalg.norm(model.pca_projection(test) - test, axis=2).max(axis=1).mean()
    floor_global = np.linalg.norm(dec.pca.inverse_transform(dec.pca.transform(test.reshape(40, -1))).reshape(
        test.shape) - test, axis=2).max(axis=1).mean()
    assert floor < 0.8 * floor_global
    # the baselines work in the global part
    assert model.ridge_.basis.n_components <= 4


def test_local_model_torch_and_onnx_match_numpy(local_model, tmp_path):
    torch = pytest.importorskip("torch")
    model, U = local_model
    d = model.marker_displacements(U[360:])
    with torch.no_grad():
        out = model.torch_module()(torch.as_tensor(d, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(out, model.predict(d), atol=2e-5 * np.abs(U).max())
    ort = pytest.importorskip("onnxruntime")
    model.export_onnx(tmp_path / "m.onnx")
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"markers": d.astype(np.float32)})[0]
    np.testing.assert_allclose(got, model.predict(d), atol=2e-5 * np.abs(U).max())


def test_local_model_folder_round_trip_and_a_corrupt_decoder_file(local_model, tmp_path):
    model, U = local_model
    model.save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["decoder"] == {"kind": "local", "global_components": 4, "local_components": 12}
    assert meta["files"]["decoder"] == "decoder.npz" and meta["n_components"] == 16
    loaded = DeformationModel.load(tmp_path / "m")
    d = model.marker_displacements(U[360:])
    np.testing.assert_array_equal(loaded.predict(d), model.predict(d))
    np.testing.assert_array_equal(loaded.predict(d, method="ridge"), model.predict(d, method="ridge"))
    t0, t1 = loaded.predict_trusted(d[:3]), model.predict_trusted(d[:3])
    np.testing.assert_allclose(t0.error_bound, t1.error_bound, rtol=1e-6)  # conformal scores stored as float32
    (tmp_path / "m" / "decoder.npz").write_bytes(b"not an archive")
    with pytest.raises(ModelError, match="decoder.npz"):
        DeformationModel.load(tmp_path / "m")


def test_pca_model_folder_records_its_decoder(tmp_path):
    mesh = box_mesh()
    U = nonlinear_fields(mesh, np.random.default_rng(1).uniform(-1, 1, (120, 3)))
    model = DeformationModel(**{**FAST, "decoder": "pca", "ensemble": 1, "calibration_share": 0.0}).fit(
        U, MARKERS, mesh=mesh, train_idx=np.arange(100), valid_idx=np.arange(100, 120))
    model.save(tmp_path / "p")
    meta = json.loads((tmp_path / "p" / "model.json").read_text())
    assert meta["decoder"]["kind"] == "pca" and "decoder" not in meta["files"]
    assert not (tmp_path / "p" / "decoder.npz").exists()
    assert not isinstance(DeformationModel.load(tmp_path / "p").network_.basis, LocalBasis)


def test_trust_layer_bounds_cover_with_the_local_decoder(local_model):
    model, U = local_model
    test = U[360:]
    tp = model.predict_trusted(model.marker_displacements(test))
    assert np.isfinite(tp.error_bound).all()
    covered = np.linalg.norm(tp.displacement - test, axis=2) <= tp.error_bound
    assert covered.mean() >= 0.8  # nominal 0.9 per vertex, 40 test samples
    # in-distribution inputs rarely raise the alarm
    assert np.mean([a.raised for a in tp.alarms]) <= 0.1
