"""The quadratic head under the networks: exact on quadratic data, chosen on validation, stored,
left out where it cannot work (few samples, missing-marker input)."""

import json

import numpy as np
import pytest

from tissuecast.surrogate import DeformationModel

from _surrogate_synthetic import COMPILED_ATOL, MARKERS, box_mesh

FAST = dict(epochs=150, patience=0, batch_size=64, learning_rate=3e-3, pca_rule="paper", pca_max_error=1e-3)


def quadratic_fields(mesh, n, seed=0):
    """(n, 270, 3) mm fields quadratic in a 3-parameter theta that the markers see linearly."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-1, 1, (n, 3))
    p = mesh.n_vertices * 3
    A = rng.normal(0, 1.0, (3, p))
    B = rng.normal(0, 0.5, (6, p))
    B.reshape(6, -1, 3)[:, MARKERS, :] = 0.0  # markers move linearly in theta
    a, b = np.triu_indices(3)
    U = theta @ A + (theta[:, a] * theta[:, b]) @ B
    return U.reshape(n, -1, 3)


@pytest.fixture(scope="module")
def quadratic_data():
    mesh = box_mesh()
    return mesh, quadratic_fields(mesh, 400)


def _test_error(model, U):
    test = U[350:]
    return np.linalg.norm(model.predict(model.marker_displacements(test)) - test, axis=2).max(axis=1).mean()


def test_head_is_exact_on_fields_quadratic_in_the_markers(quadratic_data):
    mesh, U = quadratic_data
    split = dict(train_idx=np.arange(300), valid_idx=np.arange(300, 350))
    with_head = DeformationModel(**FAST).fit(U, MARKERS, mesh=mesh, **split)
    alone = DeformationModel(head="none", **FAST).fit(U, MARKERS, mesh=mesh, **split)
    info = with_head.pca_choice_["head"]
    # a quadratic in 3 latent directions needs q >= 3; the validation scores say so
    assert info["dims"] >= 3 and info["valid_offset_max"][str(info["dims"])] < 1e-4 < info["valid_offset_max"]["0"]
    peak = np.linalg.norm(U, axis=2).max(axis=1).mean()
    e_head, e_alone = _test_error(with_head, U), _test_error(alone, U)
    assert e_head < 1e-3 * peak, (e_head, peak)  # the networks learnt (nearly) nothing on top
    assert e_alone > 10 * e_head
    assert alone.network_.head is None and alone.pca_choice_["head"] == {"dims": None}


def test_fixed_head_dims_and_round_trip(quadratic_data, tmp_path):
    mesh, U = quadratic_data
    m = DeformationModel(head_dims=2, **FAST).fit(U, MARKERS, mesh=mesh, train_idx=np.arange(300),
                                                   valid_idx=np.arange(300, 350))
    assert m.network_.head.directions.shape == (2, 15) and m.pca_choice_["head"]["dims"] == 2
    m.save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["network"]["head"] == {"kind": "quadratic", "dims": 2} and meta["files"]["head"] == "head.npz"
    loaded = DeformationModel.load(tmp_path / "m")
    d = m.marker_displacements(U[350:])
    np.testing.assert_array_equal(loaded.predict(d), m.predict(d))
    np.testing.assert_array_equal(loaded.network_.head.coef, m.network_.head.coef)


def test_no_head_without_enough_samples_or_with_missing_marker_input(quadratic_data):
    mesh, U = quadratic_data
    # 20 training samples, 5 markers: even the affine head has 16 features (> 20 / 2)
    few = DeformationModel(**FAST).fit(U, MARKERS, mesh=mesh, train_idx=np.arange(20), valid_idx=np.arange(20, 30))
    assert few.network_.head is None and few.pca_choice_["head"]["dims"] is None
    # 40 samples: the affine head (16 features) and no quadratic one (q = 6 gives 37)
    some = DeformationModel(**FAST).fit(U, MARKERS, mesh=mesh, train_idx=np.arange(40), valid_idx=np.arange(40, 50))
    assert some.pca_choice_["head"]["dims"] == 0 and some.network_.head.directions.shape == (0, 15)
    d = some.marker_displacements(U[350:352])
    net = some.network_
    w = np.mean([n.predict_weights(d.reshape(2, -1)) for n in net.members], axis=0) + net.head.predict(d.reshape(2, -1))
    np.testing.assert_allclose(some.predict(d), some.network_.basis.inverse_transform(w).reshape(2, -1, 3), rtol=0,
                               atol=COMPILED_ATOL)
    masked = DeformationModel(marker_dropout=0.3, **FAST).fit(U, MARKERS, mesh=mesh, train_idx=np.arange(300),
                                                              valid_idx=np.arange(300, 350))
    assert masked.network_.head is None and masked.supports_missing_markers


def test_trust_layer_of_a_head_model_has_a_flat_normaliser_and_covers():
    from _trust_synthetic import SPLITS, trust_data

    mesh, U, _ = trust_data()
    two = MARKERS[[0, 4]]  # two markers: the fields are not linear in them, the head is not exact
    m = DeformationModel(epochs=60, patience=0, batch_size=64, learning_rate=3e-3, n_components=8, hidden=(64, 32))
    m.fit(U, two, mesh=mesh, train_idx=SPLITS["train"], valid_idx=SPLITS["valid"], calibration_idx=SPLITS["calibration"])
    assert m.network_.head is not None and m.trusted_.layer.flat and m.trusted_.layer.error_input is not None
    test = U[SPLITS["test"]]
    d = test[:, two, :]
    sigma = m.trusted_.layer.normaliser(d.reshape(len(d), -1), m.predict(d))
    np.testing.assert_allclose(sigma, sigma[:, :1].repeat(sigma.shape[1], axis=1))  # g alone within a sample
    tp = m.predict_trusted(d, coverage=0.9)
    e = np.linalg.norm(tp.displacement - test, axis=2)
    assert abs(np.mean(e <= tp.error_bound) - 0.9) < 0.04
    assert np.ptp(tp.error_bound[0]) > 0  # the vertices' conformal quantiles still shape each sample's bounds
