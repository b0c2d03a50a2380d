"""Out-of-distribution scores on synthetic marker inputs: the single-marker fault score against
the whole-vector consistency score, and its calibrated false-alarm rate."""

import numpy as np

from tissuecast.surrogate.ood import (SWAP_RATIO, MarkerSwap, OODScores, calibrate_ood, fit_input_distance,
                                     fit_marker_consistency, fit_marker_stillness)


def _inputs(n, rng, n_d=20, noise=0.3):
    """(n, 3 n_d) mm: 20 markers moved by a smooth 3-parameter field plus independent tracking-like noise."""
    pos = np.random.default_rng(0).uniform(-30, 30, (n_d, 3))
    theta = rng.uniform(-1, 1, (n, 3))
    field = (theta[:, None, :] * 5.0 + 0.02 * theta[:, [0]][:, :, None] * pos[None] ** 2 / 10
             + 0.1 * np.cross(theta[:, None, :], pos[None]))
    return (field + noise * rng.normal(size=field.shape)).reshape(n, -1)


def test_the_fault_score_finds_one_displaced_marker_that_the_whole_vector_score_misses():
    rng = np.random.default_rng(1)
    Xt, Xv, Xc, Xs = (_inputs(n, rng) for n in (1500, 300, 400, 1000))
    cons = fit_marker_consistency(Xt, Xv)
    ood = calibrate_ood(fit_input_distance(Xt), cons, Xv, Xc, use_fault=True)
    thr = ood.thresholds(0.01)
    clean = ood.scores(Xs)
    assert np.mean((clean / thr).max(axis=1) > 1) <= 0.03  # 1 % nominal (400 calibration inputs), 1000 clean inputs

    n_d = Xs.shape[1] // 3
    k = rng.integers(0, n_d, len(Xs))
    v = rng.normal(size=(len(Xs), 3))
    glitch = Xs.reshape(len(Xs), n_d, 3).copy()
    glitch[np.arange(len(Xs)), k] += 2.0 * v / np.linalg.norm(v, axis=1, keepdims=True)  # ~4 x the residual median
    glitch = glitch.reshape(len(Xs), -1)
    s = ood.scores(glitch)
    by_consistency, by_fault = np.mean(s[:, 1] > thr[1]), np.mean(s[:, 2] > thr[2])
    assert by_fault >= 0.9 and by_consistency < by_fault - 0.5, (by_fault, by_consistency)
    # its argmax names the displaced marker
    named = cons.faults(glitch).argmax(axis=1) == k
    assert np.mean(named[s[:, 2] > thr[2]]) >= 0.95
    # by default the alarm is the distance and consistency scores' alone: the fault score is left out
    default = calibrate_ood(ood.distance, cons, Xv, Xc)
    assert not default.use_fault and np.isinf(default.thresholds(0.01)[2])
    np.testing.assert_array_equal(default.combined(s), np.maximum(s[:, 0] / default.scale[0], s[:, 1] / default.scale[1]))


def test_without_sensitivities_there_is_no_fault_score():
    rng = np.random.default_rng(2)
    Xt, Xv, Xc = (_inputs(n, rng, n_d=4) for n in (400, 100, 100))
    cons = fit_marker_consistency(Xt, Xv)
    old = type(cons)(cons.regressions, cons.scale, cons.mean, cons.precision)  # as read from an older trust file
    assert old.faults(Xc) is None
    ood = calibrate_ood(fit_input_distance(Xt), old, Xv, Xc, use_fault=True)
    assert np.isnan(ood.scores(Xc)[:, 2]).all() and np.isinf(ood.thresholds(0.01)[2]) and ood.scale[2] == 1.0
    # a two-score file's scales get a third 1 and the alarm score is the older one's
    two = type(ood)(ood.distance, old, ood.scale[:2], ood.calibration)
    np.testing.assert_array_equal(two.combined(two.scores(Xc)), ood.combined(ood.scores(Xc)))


def test_the_stillness_score_finds_a_marker_held_still_that_every_training_input_moved():
    rng = np.random.default_rng(4)
    Xt, Xv, Xc, Xs = (_inputs(n, rng, n_d=8) for n in (1500, 300, 400, 1000))
    Xt[:10, 3:6] = 0.0  # marker 1 held still in a few training inputs
    still = fit_marker_stillness(Xt)
    # the least share, by hand: |d_j| over the markers' root-mean-square displacement
    n = np.linalg.norm(Xt.reshape(len(Xt), -1, 3), axis=2)
    np.testing.assert_allclose(still.least, (n / np.sqrt((n**2).mean(axis=1, keepdims=True))).min(axis=0), rtol=1e-12)
    assert still.least[1] == 0.0 and (np.delete(still.least, 1) > 0.01).all()
    ood = calibrate_ood(fit_input_distance(Xt), fit_marker_consistency(Xt, Xv), Xv, Xc, stillness=still)
    thr = ood.thresholds(0.01)
    assert np.isfinite(thr[3])
    assert np.mean(ood.combined(ood.scores(Xs)) > ood.threshold(0.01)) <= 0.03  # 1 % nominal
    # a marker held still: its ratio is its least share over ~0, far beyond the threshold, and it is named
    held = Xs.reshape(len(Xs), -1, 3).copy()
    k = rng.choice([0, 2, 3, 4, 5, 6, 7], len(Xs))
    held[np.arange(len(Xs)), k] = 0.0
    held = held.reshape(len(Xs), -1)
    s = ood.scores(held)
    assert np.mean(s[:, 3] > thr[3]) == 1.0
    np.testing.assert_array_equal(still.ratios(held).argmax(axis=1), k)
    # a marker that some simulation held never scores, and nothing moving scores 0
    held1 = Xs.reshape(len(Xs), -1, 3).copy()
    held1[:, 1] = 0.0
    assert (still.ratios(held1.reshape(len(Xs), -1))[:, 1] == 0.0).all()
    assert (still(np.zeros((3, Xs.shape[1]))) == 0.0).all()
    # trust files written before the score: no fourth score, the alarm score of three
    old = OODScores(ood.distance, ood.consistency, ood.scale[:3], ood.calibration)
    assert np.isnan(old.scores(Xs)[:, 3]).all() and np.isinf(old.thresholds(0.01)[3])
    np.testing.assert_array_equal(old.combined(old.scores(Xs)[:, :3]), old.combined(old.scores(Xs)))


def test_exchanged_inputs_put_each_marker_of_a_pair_where_the_other_was_tracked():
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 20.0, 0]])
    swap = MarkerSwap(ref)
    np.testing.assert_array_equal(swap.pairs, [[0, 1], [0, 2], [1, 2]])
    d = np.array([[1.0, 2, 3], [4.0, 5, 6], [7.0, 8, 9]])
    x = np.concatenate([d.ravel(), [0.5, -0.5]])[None]  # two auxiliary inputs after the markers
    out = swap.exchanged(x)
    assert out.shape == (1, 3, 11)
    for p, (i, j) in enumerate(swap.pairs):
        e = out[0, p, :9].reshape(3, 3)
        np.testing.assert_allclose(ref + e, (ref + d)[[{i: j, j: i}.get(k, k) for k in range(3)]])  # positions exchanged
        np.testing.assert_array_equal(out[0, p, 9:], [0.5, -0.5])
    np.testing.assert_allclose(swap.exchanged(swap.exchanged(x)[:, 1])[:, 1], x)  # exchanging twice restores


def test_the_swap_score_finds_two_exchanged_markers_and_passes_clean_and_slipped_ones(monkeypatch):
    rng = np.random.default_rng(6)
    n_d = 8
    pos = np.random.default_rng(0).uniform(-30, 30, (n_d, 3))
    Xt, Xv, Xc, Xs = (_inputs(n, rng, n_d=n_d) for n in (1500, 300, 400, 500))
    swap = MarkerSwap(pos)  # the reference positions of _inputs' markers
    cons = fit_marker_consistency(Xt, Xv)
    ood = calibrate_ood(fit_input_distance(Xt), cons, Xv, Xc, swap=swap)
    thr = ood.thresholds(0.01)
    assert thr[4] == SWAP_RATIO and ood.scale[4] == 1.0
    clean = ood.scores(Xs)[:, 4]
    assert np.mean(clean > SWAP_RATIO) <= 0.01 and np.median(clean) < 1.0  # any exchange makes clean markers agree worse
    # two markers exchanged: exchanging them back is the best exchange, and by far
    d = Xs.reshape(len(Xs), n_d, 3)
    pair = rng.integers(0, len(swap.pairs), len(Xs))
    i, j = swap.pairs[pair, 0], swap.pairs[pair, 1]
    rows = np.arange(len(Xs))
    swapped = d.copy()
    swapped[rows, i] = pos[j] + d[rows, j] - pos[i]
    swapped[rows, j] = pos[i] + d[rows, i] - pos[j]
    score, named = swap.evaluate(swapped.reshape(len(Xs), -1), cons)
    assert np.mean(score > SWAP_RATIO) >= 0.95
    assert np.mean(named == pair) >= 0.95
    np.testing.assert_allclose(ood.scores(swapped.reshape(len(Xs), -1))[:, 4], score)
    import tissuecast.surrogate.ood as ood_module

    monkeypatch.setattr(ood_module, "_SWAP_CHUNK", 100)  # a long batch scored in chunks: the same scores
    chunked, named_chunked = swap.evaluate(swapped.reshape(len(Xs), -1), cons)
    np.testing.assert_array_equal(chunked, score)
    np.testing.assert_array_equal(named_chunked, named)
    # one marker slipped 5 mm: the markers disagree, but no exchange explains it
    slipped = d.copy()
    v = rng.normal(size=(len(Xs), 3))
    slipped[rows, rng.integers(0, n_d, len(Xs))] += 5.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    s = ood.scores(slipped.reshape(len(Xs), -1))
    assert np.mean(s[:, 1] > thr[1]) >= 0.9 and np.mean(s[:, 4] > SWAP_RATIO) <= 0.02
    # the swap score is not part of the conformal alarm score, and an uncalibrated alarm is off, swaps too
    np.testing.assert_array_equal(ood.combined(s), OODScores(ood.distance, cons, ood.scale[:4], ood.calibration).combined(s))
    assert np.isinf(OODScores(ood.distance, cons, ood.scale, np.zeros(0), swap=swap).thresholds(0.01)[4])
    # trust files written before the score, and a single marker (no consistency): no swap score
    for old in (OODScores(ood.distance, cons, ood.scale[:4], ood.calibration),
                OODScores(ood.distance, None, ood.scale, ood.calibration, swap=swap)):
        assert not old.has_swap and np.isnan(old.scores(Xs)[:, 4]).all() and np.isinf(old.thresholds(0.01)[4])


def test_the_stacked_consistency_regressions_are_each_marker_s_own_regression():
    """MarkerConsistency.residual_vectors (every marker's regression in one set of products, the
    standardisation folded in) against each QuadraticRegression.predict on the other markers'
    inputs and two auxiliary ones; one input and a batch."""
    rng = np.random.default_rng(8)
    n_d = 6
    Xt, Xv, Xs = (_inputs(n, rng, n_d=n_d) for n in (800, 200, 9))
    aux = lambda n: rng.normal(0.0, 2.0, (n, 2))  # noqa: E731
    Xt, Xv, Xs = (np.hstack([X, aux(len(X))]) for X in (Xt, Xv, Xs))
    cons = fit_marker_consistency(Xt, Xv, n_auxiliary=2)
    for X in (Xs[:1], Xs):
        expected = np.hstack([cons.regressions[j].predict(np.delete(X, np.s_[3 * j:3 * j + 3], axis=1))
                              - X[:, 3 * j:3 * j + 3] for j in range(n_d)])
        np.testing.assert_allclose(cons.residual_vectors(X), expected, rtol=0, atol=1e-11)


def test_the_input_distance_is_the_mean_of_the_k_nearest_as_a_kd_tree_finds_them(monkeypatch):
    """Brute-force neighbours (chunked) against SciPy's k-d tree: 40 dimensions, k below, at
    and above the number of training inputs, a chunk boundary inside the batch."""
    from scipy.spatial import cKDTree

    import tissuecast.surrogate.ood as ood_module

    monkeypatch.setattr(ood_module, "_DISTANCE_ELEMENTS", 7 * 300)  # chunks of 7 inputs
    rng = np.random.default_rng(5)
    X = rng.normal(size=(300, 40)) * rng.uniform(0.1, 5.0, 40)
    queries = np.vstack([rng.normal(size=(20, 40)) * 4.0, X[:3]])  # training inputs themselves too
    for n_train, k in ((300, 5), (5, 5), (3, 5)):  # chunks of 7, 420 and 700 inputs
        dist = fit_input_distance(X[:n_train], neighbours=k)
        tree = cKDTree(dist.reference)
        expected, _ = tree.query((queries - dist.mean) @ dist.whitening, k=min(k, n_train))
        np.testing.assert_allclose(dist(queries), expected.reshape(len(queries), -1).mean(axis=1), rtol=1e-12)
        for row in (4, 20):  # single frames (remembered: asked twice)
            for _ in range(2):
                np.testing.assert_allclose(dist(queries[row:row + 1]), expected[row:row + 1].reshape(1, -1).mean(axis=1),
                                           rtol=1e-12)


def test_the_last_small_batch_s_distances_are_remembered_and_nothing_else(monkeypatch):
    """A served frame asks for its input distance twice (expert gate, bounds): the second call
    reads the first's scores; another input, or a batch too large to remember, is scored again."""
    import tissuecast.surrogate.ood as ood_module

    rng = np.random.default_rng(6)
    dist = fit_input_distance(rng.normal(size=(200, 12)))
    calls = []
    scores = ood_module.InputDistance._scores
    monkeypatch.setattr(ood_module.InputDistance, "_scores", lambda self, X: calls.append(len(X)) or scores(self, X))
    frame = rng.normal(size=(1, 12))
    first = dist(frame)
    first[0] = -1.0  # the caller's copy: what is remembered stays
    again = dist(frame.copy())
    assert calls == [1] and again[0] > 0 and again[0] == dist(frame)[0]
    dist(frame + 1e-9)  # another input
    assert calls == [1, 1]
    big = rng.normal(size=(ood_module._REMEMBERED_BATCH + 1, 12))
    dist(big)
    dist(big)
    assert calls == [1, 1, 17, 17]
