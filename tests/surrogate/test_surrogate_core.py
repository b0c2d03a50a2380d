"""PCA, the n_w rule, the ridge baseline and the metrics, on hand-made data."""

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.evaluate import offset_max, offset_mean, summarize, vertex_errors
from tissuecast.surrogate import choose_n_components, fit_pca, fit_ridge, marker_columns


# ------------------------------------------------------------------ metrics
def test_offsets_on_hand_made_fields():
    bench = np.zeros((2, 4, 3))
    pred = np.zeros((2, 4, 3))
    pred[0, 1] = [3.0, 4.0, 0.0]  # error 5 at one vertex
    pred[1] = [1.0, 2.0, 2.0]  # error 3 everywhere
    np.testing.assert_allclose(vertex_errors(pred, bench)[0], [0, 5, 0, 0])
    np.testing.assert_allclose(offset_mean(pred, bench), [1.25, 3.0])
    np.testing.assert_allclose(offset_max(pred, bench), [5.0, 3.0])
    assert offset_max(pred[1], bench[1]) == pytest.approx(3.0)
    s = summarize(pred, bench, threshold=4.0)
    assert s.count == 2 and s.offset_mean == pytest.approx(2.125) and s.offset_max == pytest.approx(4.0)
    assert s.share_below == pytest.approx(0.5) and s.worst_offset_max == pytest.approx(5.0)
    assert s.offset_max_percentiles[50.0] == pytest.approx(4.0)
    assert s.as_dict()["offset_max_percentiles"]["p50"] == pytest.approx(4.0)


def test_metric_inputs_are_checked():
    with pytest.raises(ModelError, match="shape|must both"):
        offset_max(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ModelError, match="NaN"):
        offset_mean(np.full((2, 3), np.nan), np.zeros((2, 3)))


# ------------------------------------------------------------------ PCA
def _low_rank(N=120, n=40, rank=4, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(rank, 3 * n)) * np.linspace(6.0, 2.0, rank)[:, None]
    X = rng.normal(size=(N, rank)) @ basis + rng.normal(size=3 * n) + noise * rng.normal(size=(N, 3 * n))
    return X.reshape(N, n, 3)


def test_pca_full_rank_reconstruction_is_exact():
    X = np.random.default_rng(1).normal(size=(30, 12, 3)) * 5
    b = fit_pca(X)
    assert b.n_components == 30
    np.testing.assert_allclose(b.components @ b.components.T, np.eye(30), atol=1e-12)
    rec = b.inverse_transform(b.transform(X))
    np.testing.assert_allclose(rec, X.reshape(30, -1), atol=1e-10)
    # truncation keeps the leading directions and the variance order
    t = b.truncated(5)
    assert t.n_components == 5 and np.all(np.diff(b.explained_variance) <= 1e-12)


def test_pca_mean_is_training_mean():
    X = _low_rank()
    b = fit_pca(X[:80], 3)
    np.testing.assert_allclose(b.mean, X[:80].reshape(80, -1).mean(axis=0))


def test_n_components_rule_finds_true_rank():
    X = _low_rank(rank=4, noise=1e-3)
    n_w, curve = choose_n_components(X, max_error=0.05, folds=5)
    assert n_w == 4
    assert curve.chosen == 4 and curve.max_error[3] < 0.05 <= curve.max_error[2]
    assert np.all(np.diff(curve.mean_error) <= 1e-9)  # more components never hurt on average
    assert curve.n_components[0] == 1 and len(curve.n_components) >= 14
    assert np.all(curve.mean_max_error <= curve.max_error + 1e-12)


def test_n_components_rule_checks_inputs():
    with pytest.raises(ModelError, match="folds"):
        choose_n_components(_low_rank(N=10), folds=11)
    with pytest.raises(ModelError, match="NaN"):
        X = _low_rank()
        X[3, 2, 1] = np.nan
        choose_n_components(X)


# ------------------------------------------------------------------ ridge
def test_ridge_matches_stacked_least_squares():
    X = _low_rank(N=200, n=50, rank=12, noise=0.1)
    b = fit_pca(X, 10)
    markers = np.array([3, 17, 41, 8])  # 12 observed values, 10 weights
    r = fit_ridge(b, markers, ratio=1e-3)
    cols = marker_columns(markers)
    d = X[:7].reshape(7, -1)[:, cols]
    w = r.weights(d)
    # independent check: argmin ||P_D w + mean_D - d||^2 + r ||w||^2 as an augmented lstsq
    PD = b.components[:, cols].T
    A = np.vstack([PD, np.sqrt(1e-3) * np.eye(10)])
    for i in range(7):
        rhs = np.concatenate([d[i] - b.mean[cols], np.zeros(10)])
        w_ref = np.linalg.lstsq(A, rhs, rcond=None)[0]
        np.testing.assert_allclose(w[i], w_ref, rtol=1e-8, atol=1e-9)
    # the gradient of the objective vanishes at the solution
    grad = PD.T @ (PD @ w[0] + b.mean[cols] - d[0]) + 1e-3 * w[0]
    assert np.abs(grad).max() < 1e-9


def test_ridge_is_underdetermined_safe_and_checks_ratio():
    b = fit_pca(_low_rank(N=100, rank=20, noise=0.1), 20)
    r = fit_ridge(b, [0, 1], ratio=1e-3)  # 6 observations, 20 weights: ridge still solves
    assert r.matrix.shape == (20, 6) and np.isfinite(r.matrix).all()
    with pytest.raises(ModelError, match="ratio"):
        fit_ridge(b, [0, 1], ratio=-1.0)
    with pytest.raises(ModelError, match="outside"):
        fit_ridge(b, [0, 999])


def test_marker_columns_are_vertex_major():
    np.testing.assert_array_equal(marker_columns([2, 0]), [6, 7, 8, 0, 1, 2])


def test_pca_leading_components_path_matches_full_svd():
    X = _low_rank(N=80, n=100, rank=30, noise=0.05, seed=4)  # wide: 80 x 300
    full = fit_pca(X)
    few = fit_pca(X, 6)  # Gram-matrix eigen path
    np.testing.assert_allclose(few.singular_values, full.singular_values[:6], rtol=1e-10)
    np.testing.assert_allclose(np.abs((few.components * full.components[:6]).sum(axis=1)), 1.0, atol=1e-10)
    np.testing.assert_allclose(few.components @ few.components.T, np.eye(6), atol=1e-12)


# ------------------------------------------------------------------ masked network input
def test_masked_input_layout_in_numpy_and_torch():
    from tissuecast.surrogate.encoding import input_width, masked_input

    z = np.arange(1.0, 13.0).reshape(2, 6)  # 2 samples, 2 markers
    present = np.array([[1.0, 0.0], [0.0, 1.0]])
    expected = np.array([[1, 2, 3, 0, 0, 0, 1, 0], [0, 0, 0, 10, 11, 12, 0, 1]], float)
    np.testing.assert_array_equal(masked_input(z, present), expected)
    torch = pytest.importorskip("torch")
    out = masked_input(torch.as_tensor(z), torch.as_tensor(present), torch)
    np.testing.assert_array_equal(out.numpy(), expected)
    assert input_width(2, True) == 8 and input_width(2, False) == 6


def test_first_layer_folded_over_raw_displacements_equals_the_masked_input():
    from tissuecast.surrogate.encoding import fold_first_layer, masked_input, untracked_at_mean

    rng = np.random.default_rng(4)
    n_d, h, B = 3, 5, 4
    weight, bias = rng.normal(size=(h, 4 * n_d)), rng.normal(size=h)
    x_mean, x_std = rng.normal(size=3 * n_d), rng.uniform(0.5, 2.0, 3 * n_d)
    d = rng.normal(size=(B, 3 * n_d)) * 5
    missing = np.array([[False, True, False], [True, False, False], [False] * 3, [False, False, True]])
    layer = masked_input((d - x_mean) / x_std, (~missing).astype(float)) @ weight.T + bias
    W, b, present_columns = fold_first_layer(weight, bias, x_mean, x_std, masked=True)
    folded = untracked_at_mean(d, missing, x_mean) @ W.T + b - missing.astype(float) @ present_columns.T
    np.testing.assert_allclose(folded, layer, rtol=1e-12, atol=1e-12)
    W, b, none = fold_first_layer(weight[:, :3 * n_d], bias, x_mean, x_std, masked=False)
    np.testing.assert_allclose(d @ W.T + b, (d - x_mean) / x_std @ weight[:, :3 * n_d].T + bias, rtol=1e-12, atol=1e-12)
    assert none is None
