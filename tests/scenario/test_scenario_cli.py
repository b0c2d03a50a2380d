"""``tissuecast scenario preview`` and ``tissuecast mesh info``'s list of named regions."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.cli.main import main
from tissuecast.mesh import write_mesh
from tissuecast.scenario.preview import SUPPORT_CODES

# Linear tetrahedra, as in configs/embedded.toml: quadratic spring-held bodies at these loads
# take minutes of Newton iterations (docs/scenarios.md), which the preview's outputs don't need.
EMBEDDED = """
name = "try"
[solver]
order = 1
strategy = "quasi-newton"
[scenario]
name = "embedded"
pins = false
[scenario.attached]
rule = "normal"
direction = [0.0, -1.0, 0.0]
angle = 30.0
[scenario.springs]
rule = "surface"
tangential_stiffness = 0.001
[scenario.gravity]
enabled = true
[scenario.indentation]
enabled = true
[[scenario.materials.regions]]
name = "core"
rule = "distance"
point = [11.0, 19.0, 35.0]
distance = 8.0
youngs_modulus = 0.063
youngs_modulus_range = [0.042, 0.084]
"""


def test_scenario_preview_writes_vtu_json_and_png(tmp_path, capsys):
    meshio = pytest.importorskip("meshio")
    (tmp_path / "e.toml").write_text(EMBEDDED)
    png = pytest.importorskip("pyvista") is not None
    args = ["scenario", "preview", str(tmp_path / "e.toml"), "--out", str(tmp_path / "out" / "e"), "--examples", "4"]
    assert main(args + ([] if png else ["--no-png"])) == 0
    out = capsys.readouterr().out
    assert "attached region" in out and "sample 3: gravity" in out and "material core: E" in out
    doc = json.loads((tmp_path / "out" / "e.json").read_text())
    assert doc["ids_are_0_based"] and len(doc["examples"]) == 4 and doc["pinned"] == []
    assert doc["scenario"]["springs"]["tangential_stiffness_N_per_mm3"] == 0.001
    m = meshio.read(tmp_path / "out" / "e.vtu")
    support = m.point_data["support"]
    np.testing.assert_array_equal(np.flatnonzero(support == SUPPORT_CODES["attached"]), doc["attached"])
    example = m.point_data["indentation_example"]
    for k, ex in enumerate(doc["examples"]):
        assert np.all(example[ex["indent_vertices"]] >= k + 1)
        assert 2.0 <= ex["indent_depth"] <= 6.0
    e = m.cell_data["youngs_modulus"][0]
    assert set(np.round(np.unique(e), 6)) == {0.021, round(float(e.max()), 6)} and 0.042 <= e.max() <= 0.084
    if png:
        data = (tmp_path / "out" / "e.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    (tmp_path / "bad.toml").write_text(EMBEDDED.replace('direction = [0.0, -1.0, 0.0]\nangle = 30.0',
                                                        'direction = [0.0, -1.0, 0.0]\nangle = 0.1'))
    assert main(["scenario", "preview", str(tmp_path / "bad.toml"), "--no-png", "--out", str(tmp_path / "b")]) == 2
    assert "scenario.attached: rule 'normal' selects no surface vertex" in capsys.readouterr().err


def test_mesh_info_lists_the_named_regions(tmp_path, capsys):
    mesh = box_grid(2, 2, 2)
    write_mesh(tmp_path / "t.vtu", mesh, point_data={"base": (mesh.points[:, 2] == 0).astype(np.int32)},
               cell_data={"tissue": np.ones(mesh.n_tets, dtype=np.int32)})
    assert main(["mesh", "info", str(tmp_path / "t.vtu")]) == 0
    assert "named regions      base, tissue" in capsys.readouterr().out
    assert main(["mesh", "info", str(tmp_path / "t.vtu"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["regions"] == ["base", "tissue"]
