"""The supports check before the force calibration: its linear answer, and the refusal of pins
that leave a near-mechanism (a slender bar held at one spot)."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.config import with_overrides
from tissuecast.dataset import simulate
from tissuecast.dataset.mechanism_check import MECHANISM_RATIO, check_supports, linear_peak
from tissuecast.errors import DatasetError
from tissuecast.fem import NeoHookean, Problem, Solver
from tissuecast.mesh import write_mesh
from tissuecast.mesh.shapes import slender_rod

from dataset_helpers import small_config


def test_linear_peak_is_the_small_load_limit_of_the_nonlinear_solve():
    rod = slender_rod(length=40.0, width=4.0, cells_along=10, cells_across=2, bend=0.0)
    fixed = np.flatnonzero(rod.points[:, 2] < 1e-9)
    problem = Problem(rod, NeoHookean(0.021, 0.45), fixed, order=1)
    f = np.zeros((rod.n_points, 3))
    tip = np.flatnonzero(rod.points[:, 2] > 40 - 1e-9)
    f[tip, 0] = 1e-7 / len(tip)  # a tiny tip load: linear regime
    nonlinear = Solver(problem).solve(f).max_displacement
    assert linear_peak(problem, [f, 0.5 * f]) == pytest.approx(nonlinear, rel=1e-3)
    with pytest.raises(DatasetError, match="too loosely"):
        check_supports(problem, [f], 1e-7, target=0.9 * nonlinear / MECHANISM_RATIO)
    assert check_supports(problem, [f], 1e-7, target=1.1 * nonlinear / MECHANISM_RATIO) == pytest.approx(nonlinear, rel=1e-3)


def test_slender_bar_held_by_compact_pins_is_refused_with_the_options(tmp_path):
    path = tmp_path / "bar.vtu"
    write_mesh(path, slender_rod(length=120.0, width=8.0, cells_along=30, cells_across=2))
    cfg = with_overrides(small_config(tmp_path, n_samples=4, n_test2=0, alpha=0.0, workers=1),
                         mesh={"path": str(path)}, markers={"fixed_spacing": 3.0})
    with pytest.raises(DatasetError, match=r"too loosely.*fixed_rule = \"spread\".*\[scenario.attached\]"):
        simulate(cfg, tmp_path / "bar.zarr", progress=False)
