"""`tissuecast markers plan`, training with planned markers, and `predict` with error bounds
and alarms, in-process on a small real store (fast stand-in solver)."""

import csv
import json

import numpy as np
import pytest

from tissuecast.cli.main import main

from _surrogate_synthetic import simulate_box_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from tissuecast.dataset import open_dataset

    folder = tmp_path_factory.mktemp("plan")
    cfg_path, cfg = simulate_box_store(folder)
    return folder, cfg_path, open_dataset(cfg.dataset.store)


def test_plan_count_writes_files_and_respects_spacing(store, capsys):
    folder, _, ds = store
    prefix = folder / "pm"
    assert main(["markers", "plan", str(ds.path), "--count", "3", "--region", "any", "--min-distance", "6",
                 "--out", str(prefix)]) == 0
    out = capsys.readouterr().out
    doc = json.loads((folder / "pm.json").read_text())
    ids = doc["plan"]["markers"]
    assert len(ids) == 3 and doc["ids_are_0_based"] and f"ids = {ids}" in out
    assert len(doc["plan"]["proxy_valid_offset_max_mm"]) == 3 and not set(ids) & set(ds.fixed.tolist())
    assert doc["plan"]["sentinel"] == -1 and "sentinel" not in out  # the store draws no attached extent
    p = ds.mesh.points[ids]
    assert np.linalg.norm(p[:, None] - p[None], axis=2)[np.triu_indices(3, 1)].min() > 6.0
    rows = list(csv.DictReader((folder / "pm.csv").open()))
    assert [int(r["vertex_id_0based"]) for r in rows] == ids
    assert (folder / "pm.vtu").is_file()
    from tissuecast.slicer.markups import read_markups  # the planned markers, ready for Slicer

    lists = {m.name: m for m in read_markups(folder / "pm.mrk.json")}
    np.testing.assert_allclose(lists["FiducialMarkers"].positions, ds.mesh.points[ids], atol=1e-9)
    assert list(lists["FiducialMarkers"].labels) == ["M0", "M1", "M2"]


def test_plan_target_allowed_mask_and_errors(store, capsys, tmp_path):
    _, _, ds = store
    assert main(["markers", "plan", str(ds.path), "--target-mm", "1000", "--out", str(tmp_path / "t")]) == 0
    out = capsys.readouterr().out
    assert "target 1000 mm reached with 1 markers" in out
    assert f"min spacing {ds.config.markers.min_distance:g} mm" in out  # the store's config, as a run plans
    allowed = sorted(int(i) for i in ds.mesh.surface_vertices[::7])
    (tmp_path / "allowed.txt").write_text(", ".join(map(str, allowed)))
    assert main(["markers", "plan", str(ds.path), "--count", "2", "--allowed", str(tmp_path / "allowed.txt"),
                 "--out", str(tmp_path / "a")]) == 0
    capsys.readouterr()
    assert set(json.loads((tmp_path / "a.json").read_text())["plan"]["markers"]) <= set(allowed)
    (tmp_path / "bad.txt").write_text("3 x 5")
    assert main(["markers", "plan", str(ds.path), "--count", "2", "--allowed", str(tmp_path / "bad.txt")]) == 2
    assert "must hold 0-based vertex ids" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["markers", "plan", str(ds.path)])  # neither --count nor --target-mm


def test_train_with_planned_markers_then_predict_with_bounds_and_alarm(store, capsys, tmp_path):
    from tissuecast.config import load_config, with_overrides, config_to_toml

    folder, cfg_path, ds = store
    assert main(["markers", "plan", str(ds.path), "--count", "4", "--region", "any", "--out", str(tmp_path / "p")]) == 0
    ids = json.loads((tmp_path / "p.json").read_text())["plan"]["markers"]
    cfg = with_overrides(load_config(cfg_path), markers={"ids": ids}, surrogate={"ensemble": 1})
    (tmp_path / "planned.toml").write_text(config_to_toml(cfg))
    assert main(["train", str(tmp_path / "planned.toml"), "--out", str(tmp_path / "model"), "--no-onnx"]) == 0
    meta = json.loads((tmp_path / "model" / "model.json").read_text())
    assert meta["markers"] == ids and meta["files"]["trust"] == "trust.npz"
    capsys.readouterr()
    test = ds.select("test1")[:2]
    d = np.asarray(ds.displacements[test], dtype=np.float64)[:, ids, :]
    swapped = d[1].copy()
    ref = ds.mesh.points[ids]
    swapped[[0, 2]] = (ref[[2, 0]] + d[1][[2, 0]]) - ref[[0, 2]]
    (tmp_path / "swap.json").write_text(json.dumps({"displacements": [d[0].tolist(), swapped.tolist()]}))
    # swapped markers: refused by the input gate (markers at distances the body cannot take), exit 2
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "swap.json")]) == 2
    assert "sample 1: marker input refused: marker" in capsys.readouterr().err
    slipped = d[1].copy()  # one marker 1.5 mm off: within the gate's limits (0.5 mm simulated), the alarm's job
    slipped[0] += [1.5, 0.0, 0.0]
    from tissuecast.surrogate import DeformationModel

    assert not DeformationModel.load(tmp_path / "model").check_input(slipped).refused
    (tmp_path / "in.json").write_text(json.dumps({"displacements": [d[0].tolist(), slipped.tolist()]}))
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--out",
                 str(tmp_path / "out.csv"), "--coverage", "0.9", "--false-alarm", "0.2"]) == 0
    out = capsys.readouterr().out  # 12 calibration samples: enough for 90 % bounds and a 20 % false-alarm rate
    assert "error bound (90 %)" in out and "sample 1: ALARM: markers disagree" in out and "note:" not in out
    assert "sample 0: ALARM" not in out
    rows = list(csv.DictReader((tmp_path / "out.csv").open()))
    assert "error_bound_mm" in rows[0] and float(rows[0]["error_bound_mm"]) > 0
    assert {r["sample"]: r["alarm_raised"] for r in rows} == {"0": "0", "1": "1"}  # each sample's alarm in the file
    # the same frames in JSON and VTU: the alarm and the bounds' coverage travel with the field
    args = ["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--coverage", "0.9",
            "--false-alarm", "0.2", "--out"]
    assert main([*args, str(tmp_path / "out.json")]) == 0
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc["frame"] == "LPS" and doc["error_bound_coverage"] == 0.9
    assert [a["raised"] for a in doc["alarms"]] == [False, True] and "markers disagree" in doc["alarms"][1]["text"]
    assert main([*args, str(tmp_path / "out.vtu")]) == 0
    import meshio

    for b, raised in ((0, 0.0), (1, 1.0)):
        vtu = meshio.read(tmp_path / f"out_{b:03d}.vtu")
        assert set(vtu.point_data["alarm_raised"]) == {raised} and "error_bound_mm" in vtu.point_data
    capsys.readouterr()
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json")]) == 0
    out = capsys.readouterr().out  # defaults 0.01 / 0.9: 12 samples cannot set a 1 % alarm threshold
    assert "note: the alarm is off" in out and "ALARM" not in out
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--coverage", "0.99"]) == 0
    assert "note: the bounds are infinite" in capsys.readouterr().out
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "in.json"), "--coverage", "1.5"]) == 2
    assert "coverage" in capsys.readouterr().err


def test_experts_gives_a_model_a_nominal_expert(store, capsys, tmp_path, monkeypatch):
    """`tissuecast experts`: two models of the store (another seed and width stand in for the
    nominal one), the gate fitted on the valid split; the folder predicts like any model."""
    from tissuecast.config import load_config, with_overrides, config_to_toml
    from tissuecast.surrogate import DeformationModel

    folder, cfg_path, ds = store
    for name, over in (("unc", {"ensemble": 1}), ("nom", {"ensemble": 1, "seed": 5, "hidden": [16]})):
        (tmp_path / f"{name}.toml").write_text(config_to_toml(with_overrides(load_config(cfg_path), surrogate=over)))
        assert main(["train", str(tmp_path / f"{name}.toml"), "--out", str(tmp_path / name), "--no-onnx"]) == 0
    capsys.readouterr()
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "nom"), "--out", str(tmp_path / "pair"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples"] == len(ds.select("valid")) and 0 < out["nominal_better"] < 1
    pair = DeformationModel.load(tmp_path / "pair")
    assert pair.has_nominal_expert and json.loads((tmp_path / "pair" / "model.json").read_text())["nominal_expert"]
    # the printed figures are the saved pair's own on the gate's samples
    valid = np.asarray(ds.displacements[ds.select("valid")], dtype=np.float64)
    with pair.gate_suspended():
        routed = pair.predict(pair.marker_displacements(valid))
    assert out["routed_offset_max"] == pytest.approx(np.linalg.norm(routed - valid, axis=2).max(axis=1).mean(), rel=1e-12)
    assert out["oracle_offset_max"] <= out["routed_offset_max"] and pair.dataset_path == str(ds.path.resolve())
    assert (tmp_path / "pair" / "model.onnx").is_file()  # the routed graph (tests/surrogate/test_surrogate_experts.py)
    d = np.asarray(ds.displacements[ds.select("test1")[:3]], dtype=np.float64)[:, pair.markers, :]
    (tmp_path / "in.json").write_text(json.dumps({"displacements": d.tolist()}))
    assert main(["predict", str(tmp_path / "pair"), "--markers", str(tmp_path / "in.json"), "--out",
                 str(tmp_path / "out.csv")]) == 0
    # an expert on other markers is refused with the fix
    other = with_overrides(load_config(cfg_path), surrogate={"ensemble": 1}, markers={"ids": list(range(10, 15))})
    (tmp_path / "other.toml").write_text(config_to_toml(other))
    assert main(["train", str(tmp_path / "other.toml"), "--out", str(tmp_path / "other"), "--no-onnx"]) == 0
    capsys.readouterr()
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "other"), "--out", str(tmp_path / "bad")]) == 2
    assert "same mesh with the model's markers" in capsys.readouterr().err
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "nom"), "--out", str(tmp_path / "nom")]) == 2
    assert "one of the two models' folders" in capsys.readouterr().err
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "nom"), "--out", str(tmp_path / "bad"),
                 "--nominal-store", str(tmp_path / "nowhere.zarr")]) == 2
    assert "nowhere.zarr" in (err := capsys.readouterr().err) and "is not there" in err and "--nominal-store none" in err
    # 'none': the gate on the uncertain store alone (here both models' store: the same samples)
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "nom"), "--out", str(tmp_path / "alone"),
                 "--nominal-store", "none", "--json", "--no-onnx"]) == 0
    alone = json.loads(capsys.readouterr().out)
    assert alone["nominal_store"] is None and alone["samples"] == out["samples"]
    assert not (tmp_path / "alone" / "model.onnx").exists()
    # a "nominal" store that draws parameters is refused, naming the option (every store made to
    # look as if it drew E)
    from tissuecast.dataset.reader import Dataset

    monkeypatch.setattr(Dataset, "parameters", property(lambda self: {"youngs_modulus": np.ones(self.n_samples)}))
    assert main(["experts", str(tmp_path / "unc"), str(tmp_path / "nom"), "--out", str(tmp_path / "drawn")]) == 2
    assert "draws parameters (youngs_modulus)" in (err := capsys.readouterr().err) and "--nominal-store" in err

