"""benchmarks/load_path.py: a store solved along the load path is found on it (its own solver's
path reproduces every answer), a second strategy's path is compared, and bad arguments are refused."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tissuecast.config import with_overrides
from tissuecast.dataset import open_dataset, simulate

from bench_helpers import SPRING_HELD, load_benchmark
from dataset_helpers import small_config


@pytest.fixture(scope="module")
def path_store(tmp_path_factory):
    """A small spring-held store whose samples were solved from zero along the load path, as the
    embedded preset's are (Krylov steps, first increment a tenth, no reduced-order guess)."""
    tmp = tmp_path_factory.mktemp("load_path")
    cfg = with_overrides(small_config(tmp, n_samples=8, n_test2=0, alpha=0.0, calibration_samples=2,
                                      predictor="none", store=str(tmp / "data.zarr")),
                         forces={"loading": "traction", "target_max_displacement": 4.0}, scenario=SPRING_HELD,
                         solver={"order": 1, "strategy": "krylov", "initial_increment": 0.1})
    simulate(cfg, progress=False)
    return cfg.dataset.store


def test_a_store_solved_along_its_load_path_is_on_it(path_store, tmp_path, capsys):
    mod = load_benchmark("load_path")
    out = tmp_path / "report.json"
    assert mod.main([path_store, "--first", "2", "--samples", "4", "--strategies", "krylov", "newton", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    printed = {m.group(1): m.groups()[1:] for m in re.finditer(r"^(krylov|newton)\s+(\d+)\s+(\d+)\s+(\d+)", text, flags=re.M)}
    assert printed["krylov"] == ("4", "0", "0") and printed["newton"] == ("4", "0", "0")  # solved, failed, stored off
    assert "disagree on 0 of 4 samples" in text
    report = json.loads(out.read_text())
    ds = open_dataset(path_store)
    kry = report["strategies"]["krylov"]
    assert kry["solved"] == 4 and kry["failed"] == 0 and kry["off_path"] == 0
    # the store's own path, solved again: the same answers up to the store's float32
    peak = float(np.max(ds.max_displacement[2:6]))
    assert kry["largest_distance_mm"] < 1e-5 * peak + 1e-6
    # exact Newton along the same path reaches the same equilibrium on this gentle body (to its tolerance)
    new = report["strategies"]["newton"]
    assert new["off_path"] == 0 and 0.0 < new["largest_distance_mm"] < 0.01 * peak
    assert report["paths_disagree"]["samples"] == [] and report["paths_disagree"]["of"] == 4


def test_a_store_off_its_path_is_reported(path_store):
    """Stored answers moved by a known field are reported off the path by that distance."""
    mod = load_benchmark("load_path")
    ds = open_dataset(path_store)
    answers = mod.path_answers(ds, [2, 3], ["krylov"], 0.1)
    shifted = {k: u + np.array([0.0, 0.0, 0.5]) for k, u in answers["krylov"]["fields"].items()}
    answers["krylov"]["fields"] = shifted
    report = mod.compare(ds, answers, 0.001)
    r = report["strategies"]["krylov"]
    assert r["off_path"] == 2 and r["largest_distance_mm"] == pytest.approx(0.5, abs=1e-5)
    assert "paths_disagree" not in report


def test_bad_arguments_are_refused(path_store, capsys):
    mod = load_benchmark("load_path")
    with pytest.raises(SystemExit):
        mod.main([path_store, "--increment", "0"])
    assert "--increment must be in (0, 1]" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        mod.main([path_store, "--first", "100"])
    assert "no solved samples" in capsys.readouterr().err
