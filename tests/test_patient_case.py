"""docs/patient-case.md's steps up to the scenario preview, on its example config
(examples/chest_tumour_clinical.toml): the label map from the real chest CT, the mesh the run
makes from it, and the clinical scenario placed where the page says (LPS: posterior +y,
anterior -y)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "examples" / "chest_tumour_clinical.toml"


@pytest.mark.slow
def test_the_patient_case_config_places_its_scenario_on_the_label_map(tmp_path, monkeypatch):
    pytest.importorskip("slicerio")
    monkeypatch.chdir(tmp_path)
    subprocess.run([sys.executable, str(REPO / "examples" / "chest_tumour_label.py"), "walkthrough"], check=True,
                   capture_output=True)
    from tissuecast.app.configuration import load_run_config
    from tissuecast.cli.main import main
    from tissuecast.scenario import scenario_from_config

    assert main(["scenario", "preview", str(CONFIG), "--out", "sc", "--no-png", "--no-deformations", "--examples", "3"]) == 0
    doc = json.loads(Path("sc.json").read_text())
    cfg = load_run_config(CONFIG)
    mesh, _, _, sc = scenario_from_config(cfg)
    assert 500 < mesh.n_vertices < 3000
    points = mesh.points
    surface = np.asarray(mesh.surface_vertices)
    # held on its posterior face (toward the chest wall): the attached vertices lie behind the rest
    attached = np.asarray(doc["attached"])
    assert len(attached) > 10 and np.array_equal(attached, sc.attached)
    assert points[attached, 1].mean() > points[surface, 1].mean() + 10.0
    # the access is the anterior-most surface point (LPS -y) and 3 mm around it
    access = np.asarray(doc["access"])
    front = surface[np.argmin(points[surface, 1])]
    assert front in access and np.linalg.norm(points[access] - points[front], axis=1).max() <= 3.0 + 1e-9
    # supine: gravity posterior in the scan, within 20 degrees of posterior on the table
    assert cfg.scenario.gravity.imaging_direction == (0.0, 1.0, 0.0)
    for example in doc["examples"]:
        g = np.array([example["gravity_x"], example["gravity_y"], example["gravity_z"]])
        assert np.degrees(np.arccos(np.clip(g @ [0.0, 1.0, 0.0], -1, 1))) <= 20.0 + 1e-9
    assert doc["scenario"]["name"] == "chest-tumour-clinical"
    assert [i.device for i in cfg.scenario.instruments] == ["RetractorTipToRef"]
