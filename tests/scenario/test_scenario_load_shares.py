"""Each load's share of a sample's peak displacement (scenario preview, dataset info)."""

from __future__ import annotations

import pytest

from tissuecast.config import with_overrides
from tissuecast.scenario import scenario_from_config
from tissuecast.scenario.load_shares import format_load_shares, load_shares

from dataset_helpers import small_config

SCENARIO = {"pins": False, "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
            "springs": {"rule": "surface"}, "gravity": {"enabled": True},
            "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5]}}


def _shares(tmp_path, density: float, **scenario):
    scenario = {**SCENARIO, "gravity": {"enabled": True, "density": density}, **scenario}
    cfg = with_overrides(small_config(tmp_path), forces={"loading": "traction"}, scenario=scenario)
    sc = scenario_from_config(cfg)[3]
    return load_shares(sc, cfg, [11, 12, 13], alpha=1.0)


def test_each_load_alone_and_all_together(tmp_path):
    s = _shares(tmp_path, 1e-9)
    assert set(s) == {"all", "surface field", "gravity change", "instrument"}
    assert s["all"]["share_median"] == 1.0 and s["all"]["samples"] == 3
    for name in ("surface field", "gravity change", "instrument"):
        assert 0.0 < s[name]["share_median"] < 2.0
    # a real-sized gravity change is a small share here; ten times the density moves ten times as much
    assert s["gravity change"]["share_median"] < 0.2
    heavy = _shares(tmp_path, 1e-8)
    assert heavy["gravity change"]["peak_median"] == pytest.approx(10 * s["gravity change"]["peak_median"], rel=0.05)
    # a sample loaded by its surface field alone: that load is all of it
    alone = _shares(tmp_path, 1e-9, indentation={"enabled": False}, gravity={"enabled": False})
    assert set(alone) == {"all", "surface field"} and alone["surface field"]["share_median"] == pytest.approx(1.0)
    lines = format_load_shares(s)
    assert lines[0].startswith("surface field: peak") and "% of all loads' peak" in lines[0]
