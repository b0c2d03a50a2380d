"""benchmarks/scenario_solve_time.py runs end to end on two small configs (a coarse box, the
paper's pins against a provisional embedded scenario; one config with uncertain parameters
against itself at its nominal ones) and reports both data sets' figures and their ratio
(figures themselves are not asserted: timings belong to idle machines)."""

from __future__ import annotations

import re

from bench_helpers import load_benchmark
from mesh_factories import box_mesh

import numpy as np
import pytest

from tissuecast.dataset import open_dataset
from tissuecast.mesh import write_mesh

COMMON = """
[mesh]
path = "{mesh}"
[markers]
fixed_ids = [37, 66, 46]
ids = [6, 90, 27, 111, 41]
[forces]
target_max_displacement = 5.0
n_basis = 8
[dataset]
store = "{store}"
"""

EMBEDDED = """
[scenario]
name = "embedded"
pins = false
[scenario.attached]
rule = "normal"
direction = [0.0, 0.0, -1.0]
angle = 10.0
[scenario.springs]
rule = "surface"
[scenario.gravity]
enabled = true
[scenario.indentation]
enabled = true
radius = 7.0
depth = [1.0, 2.0]
clearance = 4.0
"""


def test_solve_time_benchmark_runs_both_configs(tmp_path, capsys):
    bench = load_benchmark("scenario_solve_time")
    write_mesh(tmp_path / "box.vtu", box_mesh(3, 3, 6, (20.0, 20.0, 40.0)))
    common = COMMON.format(mesh=tmp_path / "box.vtu", store=tmp_path / "unused.zarr")
    (tmp_path / "paper.toml").write_text('name = "paper-box"\n' + common)
    (tmp_path / "embedded.toml").write_text('name = "embedded-box"\n' + common + EMBEDDED)
    assert bench.main([str(tmp_path / "paper.toml"), str(tmp_path / "embedded.toml"), "--samples", "5",
                       "--predictor-samples", "3", "--keep", str(tmp_path / "stores")]) == 0
    out = capsys.readouterr().out
    assert "5/5" in out and out.count("5/5") == 2 and "ratio embedded / paper per sample" in out
    assert (tmp_path / "stores" / "embedded.zarr").is_dir()


def test_solve_time_benchmark_compares_a_config_with_its_nominal_parameters(tmp_path, capsys, monkeypatch):
    import tempfile

    bench = load_benchmark("scenario_solve_time")
    scratch = tmp_path / "scratch"  # where a run without --keep makes its temporary folder
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    write_mesh(tmp_path / "box.vtu", box_mesh(3, 3, 6, (20.0, 20.0, 40.0)))
    common = COMMON.format(mesh=tmp_path / "box.vtu", store=tmp_path / "unused.zarr")
    uncertain = "[scenario.uncertain]\nyoungs_modulus = [0.5, 2.0]\nattached_margin = [-2.0, 2.0]\n"
    (tmp_path / "embedded.toml").write_text('name = "embedded-box"\n' + common + EMBEDDED + uncertain)
    with pytest.raises(SystemExit):
        bench.main([str(tmp_path / "embedded.toml"), str(tmp_path / "embedded.toml"), "--nominal"])
    with pytest.raises(SystemExit):  # neither a file nor an organ shape
        bench.main([str(tmp_path / "embedded.toml"), "--nominal", "--mesh", str(tmp_path / "no-such.vtu")])
    assert not any(scratch.iterdir())  # refused runs leave no temporary folder behind

    def broken(path, samples, predictor_samples, folder, nominal, mesh):
        (folder / "half-made.zarr").mkdir()  # a store begun, then the run stops
        raise KeyboardInterrupt

    real = bench.time_config
    monkeypatch.setattr(bench, "time_config", broken)
    with pytest.raises(KeyboardInterrupt):
        bench.main([str(tmp_path / "embedded.toml"), "--nominal", "--samples", "4"])
    assert not any(scratch.iterdir())  # nor does a run that stops, without --keep
    monkeypatch.setattr(bench, "time_config", real)
    other = box_mesh(3, 3, 7, (22.0, 22.0, 46.0))  # another mesh than the config's: --mesh puts both runs on it
    write_mesh(tmp_path / "other.vtu", other)
    assert bench.main([str(tmp_path / "embedded.toml"), "--nominal", "--samples", "4", "--predictor-samples", "2",
                       "--keep", str(tmp_path / "stores"), "--mesh", str(tmp_path / "other.vtu")]) == 0
    out = capsys.readouterr().out
    assert out.count("4/4") == 2 and "ratio embedded / embedded (nominal) per sample" in out and "1.2x" in out
    printed = float(re.search(r"per sample: Newton iterations ([0-9.]+)x", out).group(1))
    nominal = open_dataset(tmp_path / "stores" / "embedded-nominal.zarr")
    drawn = open_dataset(tmp_path / "stores" / "embedded.zarr")
    assert nominal.n_vertices == drawn.n_vertices == other.n_vertices != box_mesh(3, 3, 6, (20.0, 20.0, 40.0)).n_vertices
    assert printed == pytest.approx(np.mean(drawn.iterations) / np.mean(nominal.iterations), abs=0.006)
    assert not nominal.parameters  # nothing drawn
    spread = {name: float(np.ptp(values)) for name, values in drawn.parameters.items()}
    assert spread["youngs_modulus"] > 0.0 and spread["attached_margin"] > 0.0 and not spread["poisson_ratio"] > 0.0
