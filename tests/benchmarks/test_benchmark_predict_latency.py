"""benchmarks/predict_latency.py: every path it times runs on the model it is given, and a model
that reads a tracked instrument is given its poses (or refused with the fix)."""

from __future__ import annotations

import numpy as np
import pytest

from bench_helpers import load_benchmark


def test_the_paper_size_model_is_timed_on_every_path(capsys):
    mod = load_benchmark("predict_latency")
    assert mod.main(["--repeats", "60", "--batch", "16"]) == 0
    out = capsys.readouterr().out
    for path in ("numpy  model.predict", "numpy  model.predict_ridge", "numpy  predict_from_positions"):
        assert path in out
    assert "samples/s" in out


def test_inputs_of_a_markers_only_model_and_of_one_with_an_instrument():
    from _instrument_synthetic import instrument_model

    mod = load_benchmark("predict_latency")
    plain = mod.paper_size_model()
    inputs = mod.model_inputs(plain, np.random.default_rng(0), count=3)
    assert len(inputs) == 3 and all(d.shape == (3 * plain.n_markers,) and a is None for d, a in inputs)
    assert plain.predict(inputs[0][0]).shape == (plain.n_vertices, 3)  # every input passes the gate
    # the synthetic instrument model records no training store: its poses cannot be read
    with pytest.raises(SystemExit, match="retractor.*training store"):
        mod.model_inputs(instrument_model(), np.random.default_rng(0))
