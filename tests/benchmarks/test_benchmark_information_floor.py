"""benchmarks/information_floor.py: which parameters a variant measures, and the inputs it
gives a model on a mismatch-study set (a set at nominal values records none of them)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.surrogate.auxiliary import AuxiliaryInputs

from bench_helpers import load_benchmark


def _config():
    attached = {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0}
    return with_overrides(Config(), scenario={"pins": False, "attached": attached, "uncertain": {
        "youngs_modulus": [0.5, 2.0], "poisson_ratio": [0.40, 0.49], "attached_margin": [-5.0, 5.0]}})


def test_variants_name_drawn_parameters_only():
    mod, cfg = load_benchmark("information_floor"), _config()
    assert mod.variant_names("none", cfg) == ()
    assert mod.variant_names("all", cfg) == ("youngs_modulus", "poisson_ratio", "attached_margin")
    assert mod.variant_names("attached_margin+youngs_modulus", cfg) == ("attached_margin", "youngs_modulus")
    with pytest.raises(SystemExit, match="spring_normal"):
        mod.variant_names("spring_normal", cfg)
    assert mod.with_measured(cfg, ("poisson_ratio",)).scenario.uncertain.measured == ("poisson_ratio",)


def test_a_sets_missing_or_nan_parameters_are_their_nominal_values():
    mod, cfg = load_benchmark("information_floor"), _config()
    model = SimpleNamespace(auxiliary=AuxiliaryInputs(parameters=("youngs_modulus", "poisson_ratio", "attached_margin")))
    drawn = SimpleNamespace(n_samples=2, instrument_poses={}, parameters={
        "youngs_modulus": np.array([2.0, 0.5]), "poisson_ratio": np.array([np.nan, 0.41]),
        "attached_margin": np.array([-5.0, 1.0])})
    np.testing.assert_array_equal(mod.set_inputs(model, drawn, cfg),
                                  [[2.0, cfg.material.poisson_ratio, -5.0], [0.5, 0.41, 1.0]])
    nominal = SimpleNamespace(n_samples=3, instrument_poses={}, parameters={})  # a set that draws nothing
    np.testing.assert_array_equal(mod.set_inputs(model, nominal, cfg), [[1.0, cfg.material.poisson_ratio, 0.0]] * 3)
    assert mod.set_inputs(SimpleNamespace(auxiliary=AuxiliaryInputs()), nominal, cfg) is None
