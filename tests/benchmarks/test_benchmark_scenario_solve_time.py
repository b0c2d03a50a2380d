"""benchmarks/scenario_solve_time.py runs end to end on two small configs (a coarse box, the
paper's pins against a provisional embedded scenario) and reports both data sets' figures and
their ratio (figures themselves are not asserted: timings belong to idle machines)."""

from __future__ import annotations

from bench_helpers import load_benchmark
from mesh_factories import box_mesh

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
