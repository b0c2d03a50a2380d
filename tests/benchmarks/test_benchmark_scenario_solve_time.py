"""benchmarks/scenario_solve_time.py runs end to end on two small configs (a coarse box, the
paper's pins against a provisional embedded scenario) and reports both data sets' figures and
their ratio (figures themselves are not asserted: timings belong to idle machines)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from mesh_factories import box_mesh

from tissuecast.mesh import write_mesh

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "scenario_solve_time.py"

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
    spec = importlib.util.spec_from_file_location("scenario_solve_time", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    write_mesh(tmp_path / "box.vtu", box_mesh(3, 3, 6, (20.0, 20.0, 40.0)))
    common = COMMON.format(mesh=tmp_path / "box.vtu", store=tmp_path / "unused.zarr")
    (tmp_path / "paper.toml").write_text('name = "paper-box"\n' + common)
    (tmp_path / "embedded.toml").write_text('name = "embedded-box"\n' + common + EMBEDDED)
    assert bench.main([str(tmp_path / "paper.toml"), str(tmp_path / "embedded.toml"), "--samples", "5",
                       "--predictor-samples", "3", "--keep", str(tmp_path / "stores")]) == 0
    out = capsys.readouterr().out
    assert "5/5" in out and out.count("5/5") == 2 and "ratio embedded / paper per sample" in out
    assert (tmp_path / "stores" / "embedded.zarr").is_dir()
