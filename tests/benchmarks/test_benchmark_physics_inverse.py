"""benchmarks/physics_inverse.py: the poses a store recorded are the draws' (what a tracker
reports), and a run as a tracked frame (``--tracked``) puts the inverse far below the model
on samples of its own simulator, and says how much of the field its band holds; ``--known-margin``
on a store that draws no margin is refused; a run names the field it reports."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from tissuecast.dataset import open_dataset
from tissuecast.instruments import recorded_poses
from tissuecast.scenario import scenario_from_config

from bench_helpers import load_benchmark
from dataset_helpers import tracked_retractor_store


def test_the_inverse_as_a_tracked_frame_beats_the_model(tmp_path, capsys):
    mod = load_benchmark("physics_inverse")
    cfg, store, model = tracked_retractor_store(tmp_path)
    ds = open_dataset(store)
    _, _, _, sc = scenario_from_config(cfg)
    touched = 0
    for s in range(ds.n_samples):
        (name, drawn), = sc.draw_for(int(ds.seed[s])).instruments
        pose = recorded_poses(ds.instrument_poses, s)[name]
        assert pose.contact == drawn.contact
        if drawn.contact:
            touched += 1
            np.testing.assert_array_equal(pose.tip, drawn.tip)
            np.testing.assert_allclose(pose.direction, drawn.direction, rtol=0, atol=1e-15)
            assert pose.depth == drawn.depth
    assert 0 < touched < ds.n_samples
    mod.main(["--dataset", str(store), "--model", str(model), "--samples", "2", "--tracked"])
    out = capsys.readouterr().out
    assert "as tracked" in out
    rows = {k: float(v) for k, v in re.findall(r"^\s+(physics inverse|model)\s+([0-9.]+) /", out, flags=re.M)}
    assert rows["physics inverse"] < 0.05 and rows["model"] > 10 * rows["physics inverse"]
    covered = re.search(r"90 % band \(1.44 x its posterior spread\) covers ([0-9.]+) % of the vertices", out)
    assert covered and float(covered.group(1)) > 80.0  # the band holds the error at most vertices (98 % here)
    with pytest.raises(SystemExit):  # the store draws no parameter: nothing to give
        mod.main(["--dataset", str(store), "--model", str(model), "--samples", "1", "--known-margin"])
    assert f"--known-margin: {store} records no drawn attached margin" in capsys.readouterr().err


def test_the_benchmark_says_which_field_a_searched_frame_reports(tmp_path, capsys):
    """On a store that draws the attached margin, the run names the estimate it reports
    (``--estimate``), or that each sample's margin is given (``--known-margin``), and how it is
    measured (``--margin-offset``, ``--margin-sd``)."""
    mod = load_benchmark("physics_inverse")
    _, store, model = tracked_retractor_store(tmp_path, {"attached_margin": [-6.0, 6.0]})
    argv = ["--dataset", str(store), "--model", str(model), "--samples", "1", "--tracked"]
    mod.main(argv + ["--estimate", "likeliest"])
    assert "; the field the likeliest estimate" in capsys.readouterr().out
    mod.main(argv + ["--known-margin"])
    out = capsys.readouterr().out
    assert "; each sample's margin given" in out and "the field the" not in out
    mod.main(argv + ["--known-margin", "--margin-offset", "1", "--margin-sd", "2"])
    assert "; each sample's margin given +1 mm off +- 2 mm; the field the mean estimate" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        mod.main(argv + ["--margin-sd", "2"])
    assert "--margin-offset and --margin-sd describe the measured margin: give --known-margin" in capsys.readouterr().err
    inv = SimpleNamespace(margin_range=(-6.0, 6.0))
    drawn = {"attached_margin": np.array([5.0, -2.0])}
    assert mod.given_margin(inv, drawn, 0, 1.5) == 6.0 and mod.given_margin(inv, drawn, 1, 1.5) == -0.5
