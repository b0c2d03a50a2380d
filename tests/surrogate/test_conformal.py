"""Split-conformal per-vertex bounds on synthetic errors with a known distribution."""

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.surrogate.conformal import (conformal_quantile, conformal_rank, fit_vertex_conformal,
                                            min_calibration_samples, reliability_curve)

Z90, Z95 = 1.6448536269514722, 1.959963984540054  # quantiles of |N(0, 1)| at 0.9 and 0.95


def _errors(rng, m, n):
    """Errors e = sigma |z| with a known, vertex- and sample-dependent scale sigma (mm)."""
    sigma = np.exp(rng.normal(size=(m, 1)) + rng.normal(size=(1, n)))
    return sigma * np.abs(rng.normal(size=(m, n))), sigma


def test_rank_and_quantile_follow_the_finite_sample_rule():
    assert conformal_rank(19, 0.9) == 18  # ceil(20 * 0.9) exactly, despite 20 * 0.9 = 18.000000000000004
    assert conformal_rank(199, 0.95) == 190
    s = np.arange(1.0, 20.0)[::-1]  # 19 scores 19..1
    assert conformal_quantile(s, 0.9) == 18.0
    assert np.isinf(conformal_quantile(s, 0.96))  # ceil(20 * 0.96) = 20 > 19 scores: no finite bound
    with pytest.raises(ModelError, match="coverage"):
        conformal_rank(10, 1.0)
    assert [min_calibration_samples(c) for c in (0.5, 0.9, 0.95, 0.99)] == [1, 9, 19, 99]
    for c in (0.9, 0.95, 0.99):
        m = min_calibration_samples(c)
        assert conformal_rank(m, c) <= m and conformal_rank(m - 1, c) > m - 1


def test_marginal_coverage_is_exactly_rank_over_m_plus_1():
    # exchangeable continuous scores: P(test <= k-th smallest of m) = k / (m + 1)
    rng = np.random.default_rng(0)
    m, reps = 19, 40000
    cal = rng.exponential(size=(reps, m))
    test = rng.exponential(size=reps)
    k = conformal_rank(m, 0.9)
    q = np.sort(cal, axis=1)[:, k - 1]
    cover = np.mean(test <= q)
    assert k / (m + 1) == 0.9
    assert abs(cover - 0.9) < 0.006  # 4 standard errors of 40000 Bernoulli draws


@pytest.mark.parametrize("coverage, z", [(0.9, Z90), (0.95, Z95)])
def test_normalised_bounds_cover_and_recover_the_known_quantile(coverage, z):
    rng = np.random.default_rng(1)
    e_cal, s_cal = _errors(rng, 2000, 30)
    conf = fit_vertex_conformal(e_cal, s_cal)
    q = conf.quantiles(coverage)
    np.testing.assert_allclose(q, z, rtol=0.08)  # the exact normaliser makes every vertex's score |z|
    e_test, s_test = _errors(rng, 3000, 30)
    b = conf.bounds(s_test, coverage)
    assert abs(np.mean(e_test <= b) - coverage) < 0.01
    # per vertex too (each vertex has its own quantile)
    per_vertex = np.mean(e_test <= b, axis=0)
    assert np.all(np.abs(per_vertex - coverage) < 0.03)


def test_reliability_curve_is_diagonal_for_a_calibrated_model_and_flags_an_overconfident_one():
    rng = np.random.default_rng(2)
    e_cal, s_cal = _errors(rng, 1500, 20)
    conf = fit_vertex_conformal(e_cal, s_cal)
    e_test, s_test = _errors(rng, 1500, 20)
    lv, emp = reliability_curve(conf, e_test, s_test)
    assert lv[0] == 0.5 and lv[-1] == 0.99
    np.testing.assert_allclose(emp, lv, atol=0.015)
    _, emp_shifted = reliability_curve(conf, 2.0 * e_test, s_test)  # errors twice as large as calibrated
    assert np.all(emp_shifted < lv - 0.15)


def test_bad_calibration_input_is_refused():
    with pytest.raises(ModelError, match="both be"):
        fit_vertex_conformal(np.ones((3, 4)), np.ones((3, 5)))
    with pytest.raises(ModelError, match="positive"):
        fit_vertex_conformal(np.ones((3, 4)), np.zeros((3, 4)))
