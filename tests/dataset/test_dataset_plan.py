"""Sample plan (splits, betas, seeds) and the force-magnitude calibration rule (no FEM)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.dataset import SPLIT_CODES, make_plan, sample_seed
from tissuecast.dataset.sample_plan import generation_order
from tissuecast.dataset.calibrate import RTOL, _quantile, calibrate_alpha
from tissuecast.errors import DatasetError


def _plan(**ds):
    return make_plan(with_overrides(Config(), dataset=ds))


def test_paper_split_is_exactly_8_1_1_plus_test2():
    plan = make_plan(Config())
    assert plan.counts() == {"train": 1600, "valid": 200, "test1": 200, "test2": 200}
    assert plan.n_samples == 2200 and plan.n_lbo == 2000
    assert np.all(plan.split[2000:] == SPLIT_CODES["test2"])
    assert np.isnan(plan.beta[:2000]).all()


def test_split_is_a_shuffle_not_a_block():
    plan = _plan(n_samples=1000, n_test2=0)
    train = np.flatnonzero(plan.split == SPLIT_CODES["train"])
    # each tenth of the index range holds about 80 % training samples
    per_block = np.bincount(train // 100, minlength=10)
    assert per_block.min() > 65 and per_block.max() < 95


@pytest.mark.parametrize("n, expected", [(10, (8, 1, 1)), (7, (6, 1, 0)), (1, (1, 0, 0)), (25, (20, 2, 3))])
def test_split_counts_small(n, expected):
    c = _plan(n_samples=n, n_test2=0).counts()
    assert (c["train"], c["valid"], c["test1"]) == expected


def test_test2_betas_equal_counts():
    plan = make_plan(Config())
    betas, counts = np.unique(plan.beta[2000:], return_counts=True)
    np.testing.assert_allclose(betas, np.linspace(0, 1, 11))
    assert counts.max() - counts.min() <= 1 and counts.sum() == 200


def test_generation_order_interleaves_splits_in_proportion():
    plan = make_plan(Config())
    order = generation_order(plan.split, np.arange(plan.n_samples))
    assert np.array_equal(np.sort(order), np.arange(plan.n_samples))
    share = {code: np.mean(plan.split == code) for code in range(4)}
    for m in (1, 10, 57, 300, 1111, 2200):  # every prefix holds each split within one sample
        counts = np.bincount(plan.split[order[:m]], minlength=4)
        for code in range(4):
            assert abs(counts[code] - m * share[code]) <= 1.0, (m, code)
    test2 = order[plan.split[order] == SPLIT_CODES["test2"]]
    assert np.array_equal(test2, np.arange(2000, 2200))  # by index, so the betas cycle
    # the order depends on the set of indices only, not on how they are listed
    rest = order[500:]
    assert np.array_equal(generation_order(plan.split, rest[::-1]), generation_order(plan.split, rest))


def test_plan_is_deterministic_and_seed_dependent():
    a, b, c = _plan(seed=3), _plan(seed=3), _plan(seed=4)
    assert np.array_equal(a.split, b.split) and np.array_equal(a.seed, b.seed)
    assert not np.array_equal(a.split, c.split)
    assert len(np.unique(a.seed)) == a.n_samples


def test_sample_seed_depends_on_index_and_base_only():
    plan = _plan(seed=11, n_samples=50, n_test2=5)
    assert plan.seed[17] == sample_seed(11, 17)
    # a larger data set with the same base seed shares the per-sample seeds of its first samples
    big = _plan(seed=11, n_samples=80, n_test2=5)
    assert np.array_equal(big.seed[:50], plan.seed[:50])
    w1 = np.random.default_rng(plan.seed[17]).uniform(-1, 1, (20, 3))
    w2 = np.random.default_rng(sample_seed(11, 17)).uniform(-1, 1, (20, 3))
    assert np.array_equal(w1, w2)


def test_quantile_matches_numpy_and_handles_failures():
    v = np.array([3.0, 1.0, 7.0, 2.0, 5.0])
    assert _quantile(v, 0.9) == pytest.approx(np.quantile(v, 0.9))
    assert _quantile(np.array([1.0, 2.0, math.inf, 3.0, 4.0]), 0.9) == math.inf
    assert _quantile(np.array([1.0, 2.0, 3.0, 4.0, math.inf]), 0.5) == pytest.approx(3.0)


def _stiffening(alpha, scales):
    # saturating (stiffening) response u = s * a / (1 + a / 40): nonlinear in alpha
    return scales * alpha / (1.0 + alpha / 40.0)


def test_calibration_reaches_target_on_nonlinear_response():
    scales = np.array([0.8, 1.0, 1.1, 1.3, 0.9, 1.2])
    calls = []

    def pilot(a):
        calls.append(a)
        return _stiffening(a, scales)

    rec = calibrate_alpha(pilot, alpha0=0.5, target=30.0, quantile=0.9)
    assert rec["converged"]
    assert np.quantile(_stiffening(rec["alpha"], scales), 0.9) == pytest.approx(30.0, rel=0.02)
    assert len(rec["rounds"]) == len(calls) <= 6


def test_calibration_takes_the_local_exponent_where_the_response_bends():
    """A response that softens sharply near the target (a thin wall, q = 16.5 a (1 + (a/0.19)^4)
    mm): after an overshoot and an undershoot the next round measures the exponent against the
    nearer of the two (the overshoot), not against the first round far below; 4 rounds instead
    of 5, and no second overshoot (whose pilots are the ones that buckle)."""
    scales = np.ones(5)

    def pilot(a):
        return scales * 16.5 * a * (1.0 + (a / 0.19) ** 4)

    rec = calibrate_alpha(pilot, alpha0=0.0907, target=3.0, quantile=0.9)
    assert rec["converged"]
    values = [r["quantile_value"] for r in rec["rounds"]]
    assert len(values) == 4, values
    assert sum(v > 3.0 * 1.02 for v in values) == 1, values


def test_calibration_backs_off_after_failures():
    scales = np.array([1.0, 1.0, 1.2, 0.7])

    def pilot(a):
        u = scales * a**1.3
        return np.where(u > 45.0, np.inf, u)  # the solver fails above 45 mm

    rec = calibrate_alpha(pilot, alpha0=100.0, target=30.0, quantile=0.9)
    assert rec["converged"]
    assert rec["rounds"][0]["quantile_value"] is None  # first trial failed
    assert np.quantile(scales * rec["alpha"] ** 1.3, 0.9) == pytest.approx(30.0, rel=0.02)


def test_calibration_gives_up_with_clear_error_when_everything_fails():
    with pytest.raises(DatasetError, match="every pilot sample failed"):
        calibrate_alpha(lambda a: np.full(3, np.inf), alpha0=1.0, target=30.0, max_rounds=3)


def test_calibration_stops_below_a_failure_limit():
    # the solver fails above alpha = 2 while the target would need alpha = 3: the bracket closes at 2
    def pilot(a):
        u = np.array([9.0, 10.0, 11.0]) * a
        return u if a <= 2.0 else np.full(3, np.inf)

    rec = calibrate_alpha(pilot, alpha0=0.5, target=30.0, quantile=0.9)
    assert not rec["converged"] and rec["limited_by_failures"]
    assert 2.0 / (1.0 + RTOL) <= rec["alpha"] <= 2.0
    assert len(rec["rounds"]) < 10
