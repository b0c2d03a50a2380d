"""The train / evaluate / predict / study / run commands, in-process, on a small real store.

The store is written by ``tissuecast.dataset.simulate`` with a fast stand-in solver
(``_surrogate_synthetic.smooth_solver_factory``), so the whole data-set layout is real.
"""

import json

import numpy as np
import pytest

from tissuecast.cli.main import main
from tissuecast.errors import ConfigError

from _surrogate_synthetic import simulate_box_store


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    cfg_path, cfg = simulate_box_store(folder)
    return folder, cfg_path, cfg


def test_train_evaluate_predict(run, capsys):
    folder, cfg_path, cfg = run
    assert main(["train", str(cfg_path), "--out", str(folder / "model")]) == 0
    out = capsys.readouterr().out
    assert "PCA components n_w = 6" in out and "quadratic head under the network" in out
    for f in ("model.json", "weights.safetensors", "pca.npz", "mesh.npz", "model.onnx"):
        assert (folder / "model" / f).is_file()
    assert main(["evaluate", str(folder / "model"), "--out", str(folder / "rep"), "--renders", "0"]) == 0
    out = capsys.readouterr().out
    assert "test-1 mean Offset_max" in out and (folder / "rep" / "index.html").is_file()
    assert "rigid" in out and "PCA floor" in out and "non-rigid part" in out
    ev = json.loads((folder / "rep" / "evaluation.json").read_text())
    assert {"valid", "test1", "test2"} <= set(ev["sets"]) and len(ev["by_beta"]) == 3
    # --json: strict JSON (what JSON.parse reads) on stdout, with where the report went
    assert main(["evaluate", str(folder / "model"), "--out", str(folder / "rep_json"), "--renders", "0", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"{c} in --json output"))
    assert printed["report"] == str(folder / "rep_json" / "index.html") and set(printed["sets"]) == set(ev["sets"])
    # a store simulated with other physics: evaluated, with a warning that the figures measure a mismatch
    from tissuecast.config import with_overrides
    from tissuecast.dataset import simulate

    stiff = with_overrides(cfg, material={"youngs_modulus": 2 * cfg.material.youngs_modulus},
                           dataset={"store": str(folder / "stiff.zarr"), "n_samples": 20, "n_test2": 0})
    simulate(stiff, progress=False, solver_factory="_surrogate_synthetic:smooth_solver_factory")
    assert main(["evaluate", str(folder / "model"), "--store", str(folder / "stiff.zarr"), "--out",
                 str(folder / "rep_stiff"), "--renders", "0"]) == 0
    err = capsys.readouterr().err
    assert "was simulated with other physics than the model's training data (material.youngs_modulus differ)" in err
    assert main(["evaluate", str(folder / "model"), "--out", str(folder / "rep"), "--renders", "0"]) == 0
    assert "other physics" not in capsys.readouterr().err  # its own store: no warning
    # errors at the targets beside the offsets: the default interior targets, or listed points
    assert "targets: 10 interior points" in out and "test-1 TRE at the 10 targets: mean / p95 / max" in out
    assert "share of the targets' displacement corrected" in out and ev["targets"]["name"] == "interior"
    from tissuecast.surrogate import DeformationModel as _Model

    mesh = _Model.load(folder / "model").mesh
    centroids = mesh.points[mesh.tets[[0, 5, 9]]].mean(axis=1)
    (folder / "t.csv").write_text("\n".join(f"tip{i},{x},{y},{z}" for i, (x, y, z) in enumerate(centroids)))
    assert main(["evaluate", str(folder / "model"), "--out", str(folder / "rep_t"), "--renders", "0",
                 "--targets", str(folder / "t.csv"), "--json"]) == 0
    ev_t = json.loads(capsys.readouterr().out)
    assert ev_t["targets"]["labels"] == ["tip0", "tip1", "tip2"] and ev_t["targets"]["count"] == 3
    assert ev_t["sets"]["test1"]["targets"]["mlp"]["tre_mean"] != ev["sets"]["test1"]["targets"]["mlp"]["tre_mean"]

    from tissuecast.dataset import open_dataset
    from tissuecast.surrogate import DeformationModel

    model = DeformationModel.load(folder / "model")
    ds = open_dataset(cfg.dataset.store)
    i = int(ds.select("test1")[0])
    d = model.marker_displacements(ds.displacements[i])
    # displacements as CSV (one marker per row, with header) -> CSV field
    csv_in = folder / "markers.csv"
    csv_in.write_text("dx,dy,dz\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in d))
    assert main(["predict", str(folder / "model"), "--markers", str(csv_in), "--out", str(folder / "u.csv")]) == 0
    rows = np.loadtxt(folder / "u.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows[:, 2:5], model.predict(d), atol=1e-5)
    # tracked positions as JSON -> VTU
    js = folder / "pos.json"
    js.write_text(json.dumps({"positions": (model.reference_marker_positions + d).tolist()}))
    assert main(["predict", str(folder / "model"), "--markers", str(js), "--out", str(folder / "u.vtu"), "--uncertainty"]) == 0
    import meshio

    vtu = meshio.read(folder / "u.vtu")
    np.testing.assert_allclose(vtu.point_data["displacement_mm"], model.predict(d), atol=1e-6)
    assert vtu.point_data["uncertainty_mm"].shape == (model.n_vertices,)
    # the rigid-registration baseline from the same file, and its clear refusal of --uncertainty
    assert main(["predict", str(folder / "model"), "--markers", str(csv_in), "--method", "rigid",
                 "--out", str(folder / "r.csv")]) == 0
    rows = np.loadtxt(folder / "r.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows[:, 2:5], model.predict(d, method="rigid"), atol=1e-5)
    assert main(["predict", str(folder / "model"), "--markers", str(csv_in), "--method", "rigid", "--uncertainty"]) == 2
    assert "--uncertainty comes from the MLP" in capsys.readouterr().err
    # wrong number of values is one clear error
    bad = folder / "bad.csv"
    bad.write_text("1,2,3\n4,5,6\n")
    assert main(["predict", str(folder / "model"), "--markers", str(bad)]) == 2
    assert "multiple of 3 n_d = 12" in capsys.readouterr().err
    # a CSV saved with semicolons or spaces (a European spreadsheet) is named as such
    for sep, name in ((";", "semicolon"), (" ", "space")):
        bad.write_text("x;y;z\n" + "\n".join(sep.join(f"{v:.9g}" for v in row) for row in d))
        assert main(["predict", str(folder / "model"), "--markers", str(bad)]) == 2
        assert f"line 2: non-numeric value in ['{sep.join(f'{v:.9g}' for v in d[0])}'] (the line looks {name}-separated: " \
               "save the CSV with commas" in capsys.readouterr().err
    # two samples' markers in one file: the summary says how the rows were read
    csv_in.write_text("\n".join(",".join(f"{v:.9g}" for v in row) for row in np.r_[d, d]))
    assert main(["predict", str(folder / "model"), "--markers", str(csv_in)]) == 0
    assert "predicted 2 sample(s) (the input read as 4 markers each)" in capsys.readouterr().out


def test_study_markers_and_pca(run, capsys):
    folder, cfg_path, _ = run
    assert main(["study", "markers", str(cfg_path), "--counts", "3-5", "--out", str(folder / "st")]) == 0
    lines = (folder / "st" / "study_markers.csv").read_text().splitlines()
    assert lines[0].startswith("n_markers,") and len(lines) == 4
    assert (folder / "st" / "study_markers.png").is_file()
    assert main(["study", "pca", str(cfg_path), "--max-components", "12", "--out", str(folder / "st")]) == 0
    assert len((folder / "st" / "study_pca.csv").read_text().splitlines()) == 13


def test_run_pipeline_skip_simulate(run, capsys):
    folder, cfg_path, cfg = run
    assert main(["run", str(cfg_path), "--skip-simulate"]) == 0
    out = capsys.readouterr().out
    assert "report:" in out
    assert (folder / "run" / "model" / "model.json").is_file()
    assert (folder / "run" / "report" / "index.html").is_file()
    assert list((folder / "run" / "report" / "vtu").glob("*.vtu"))


def test_every_command_takes_a_config_file_or_a_preset_name(tmp_path, monkeypatch, capsys):
    from tissuecast.app.configuration import load_run_config

    monkeypatch.chdir(tmp_path)
    assert load_run_config("embedded").scenario.name == "embedded"
    (tmp_path / "embedded").write_text('name = "mine"\n')  # a file of that name wins
    assert load_run_config("embedded").name == "mine"
    with pytest.raises(ConfigError, match="does not exist and is no packaged preset.*embedded, paper, quick"):
        load_run_config("no-such-preset")
    assert main(["config", "show", "quick", "--no-comments"]) == 0  # not only `run`: every command
    assert 'name = "quick"' in capsys.readouterr().out
    assert main(["config", "show", "quik"]) == 2
    assert "paper, quick" in capsys.readouterr().err
    assert main(["simulte", "quick"]) == 2  # a misspelt command: the one meant
    assert "unknown command 'simulte'; did you mean `tissuecast simulate`?" in capsys.readouterr().err
    assert main(["run", "quick", "--workers", "-1"]) == 2  # refused before anything is made
    assert "workers = -1: give 0 (one per usable CPU)" in capsys.readouterr().err
    assert not (tmp_path / "tissuecast-demo").exists()


def test_every_help_example_parses_and_is_printed_as_written(capsys):
    """A command's --help ends with examples; each is a command line its parser takes."""
    import importlib
    import shlex

    from tissuecast.cli.main import COMMANDS, build_parser

    seen = 0
    for name, module in COMMANDS.items():
        examples = getattr(importlib.import_module(f"tissuecast.cli.{module}"), "EXAMPLES", ())
        for line, _ in examples:
            words = shlex.split(line)
            assert words[:2] == ["tissuecast", name], line
            args = build_parser(name).parse_args(words[1:])
            assert args.command == name and callable(args.func), line
            seen += 1
        if examples:
            with pytest.raises(SystemExit):
                build_parser(name).parse_args([name, "--help"])
            text = capsys.readouterr().out
            tail = text[text.index("\nexamples:\n"):]
            for line, what in examples:
                assert f"\n  {line}\n      {what}\n" in tail + "\n"
    assert seen >= 15
