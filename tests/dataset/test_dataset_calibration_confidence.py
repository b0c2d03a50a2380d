"""The calibration's stated confidence (tissuecast.dataset.quantiles) and the thin-shell check
(tissuecast.dataset.mechanism_check.check_thin_body): the interval's coverage on a known
distribution, its order statistics in closed form, and a thin wall refused before anything is solved."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tissuecast.dataset.mechanism_check import THIN_SPHERICITY, check_thin_body, sphericity
from tissuecast.dataset.quantiles import interval_text, quantile_interval, sample_quantile
from tissuecast.errors import DatasetError

from _surrogate_synthetic import box_mesh


def test_the_interval_holds_the_quantile_as_often_as_it_says():
    rng = np.random.default_rng(0)
    truth = -math.log(0.1)  # 0.9 quantile of the unit exponential
    hits, finite = 0, 0
    for _ in range(4000):
        lo, hi = quantile_interval(rng.exponential(size=24), 0.9, 0.8)
        finite += hi is not None
        hits += lo <= truth <= hi
    assert finite == 4000
    # exact coverage of [v_(20), v_(24)] with 24 draws: P(20 <= B <= 23), B ~ binomial(24, 0.9): 0.835
    exact = sum(math.comb(24, k) * 0.9**k * 0.1 ** (24 - k) for k in range(20, 24))
    assert exact >= 0.8
    assert abs(hits / 4000 - exact) < 0.02, (hits / 4000, exact)


def test_the_interval_is_the_order_statistics_in_closed_form():
    v = np.arange(1.0, 25.0)[::-1]  # 24 pilots, unsorted
    assert quantile_interval(v, 0.9, 0.8) == (20.0, 24.0)
    assert quantile_interval(v, 0.9, 0.9)[1] is None  # no 90 % interval has a finite upper end
    assert quantile_interval(np.r_[v[:-1], np.inf], 0.9, 0.8)[1] is None  # a failed pilot bounds nothing
    assert "unbounded" in interval_text((19.0, None))
    assert sample_quantile(np.r_[1.0, 2.0, np.inf], 0.5) == 2.0
    assert sample_quantile(np.r_[1.0, 2.0, np.inf], 0.9) == math.inf


def test_sphericity_of_a_cube_and_a_thin_plate():
    cube = box_mesh(3, 3, 3, h=5.0)
    assert sphericity(cube) == pytest.approx(math.pi ** (1 / 3) * 6 ** (2 / 3) / 6, rel=1e-9)  # 0.806
    plate = box_mesh(30, 30, 1, h=5.0)
    V, A = 150.0 * 150.0 * 5.0, 2 * (150.0 * 150.0 + 2 * 150.0 * 5.0)
    assert sphericity(plate) == pytest.approx(math.pi ** (1 / 3) * (6 * V) ** (2 / 3) / A, rel=1e-9)
    assert sphericity(plate) < THIN_SPHERICITY < sphericity(cube)


class _Scenario:
    def __init__(self, mesh, pinned=(0, 1, 2)):
        self.mesh, self.pinned, self.can_swing = mesh, np.asarray(pinned), True


class _Markers:
    def __init__(self, rule="compact", ids=()):
        self.fixed_rule, self.fixed_ids = rule, list(ids)


def test_a_thin_wall_on_compact_pins_is_refused_and_chosen_pins_are_warned(caplog):
    plate = box_mesh(30, 30, 1, h=5.0)
    with pytest.raises(DatasetError, match="thin shell.*configs/vessel.toml"):
        check_thin_body(_Scenario(plate), _Markers())
    with caplog.at_level("WARNING"):
        assert check_thin_body(_Scenario(plate), _Markers("spread")) < THIN_SPHERICITY
    assert "thin shell" in caplog.text
    cube = box_mesh(3, 3, 3, h=5.0)
    assert check_thin_body(_Scenario(cube), _Markers()) > THIN_SPHERICITY
