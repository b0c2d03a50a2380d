"""Config: paper defaults, TOML round trip, strict validation naming the key."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from tissuecast.cli.main import main
from tissuecast.config import (
    Config,
    config_from_dict,
    config_to_dict,
    config_to_toml,
    load_config,
    with_overrides,
)
from tissuecast.errors import ConfigError


def test_defaults_are_the_papers_values():
    c = Config()
    assert c.material.youngs_modulus == 0.021 and c.material.poisson_ratio == 0.45  # 21 kPa in MPa
    assert (c.markers.count, c.markers.start, c.markers.min_distance, c.markers.fixed_count) == (5, 96, 10.0, 3)
    assert c.solver.order == 2  # quadratic C3D10
    assert c.forces.n_basis == 20 and c.forces.lsc_points == 3
    assert c.forces.lsc_iterations == 20 and c.forces.lsc_rate == 0.1
    assert c.forces.betas == pytest.approx([0.1 * k for k in range(11)])
    assert c.forces.target_max_displacement == 30.0
    assert c.dataset.n_samples == 2000 and c.dataset.split == (8.0, 1.0, 1.0) and c.dataset.n_test2 == 200
    assert c.surrogate.hidden == (128, 64) and c.surrogate.pca_max_error == 1.0 and c.surrogate.pca_folds == 5
    assert c.surrogate.ridge_ratio == 1e-3 and c.surrogate.learning_rate == 3e-3
    assert c.mesh.units == "mm" and c.mesh.path == ""
    assert c.serve.port == 18944 and c.serve.host == "127.0.0.1"


def test_toml_round_trip_of_defaults_and_changed_values(tmp_path):
    for cfg in (
        Config(),
        with_overrides(Config(), markers={"count": 7, "ids": [1, 2, 3]}, surrogate={"hidden": [64, 32, 16]},
                       material={"poisson_ratio": 0.4}, name="run \"A\""),
    ):
        for comments in (True, False):
            path = tmp_path / "c.toml"
            path.write_text(config_to_toml(cfg, comments=comments))
            assert load_config(path) == cfg
    assert load_config(None) == Config()
    assert config_from_dict(config_to_dict(Config())) == Config()


def test_partial_file_keeps_other_defaults(tmp_path):
    (tmp_path / "p.toml").write_text("[dataset]\nn_samples = 100\n")
    c = load_config(tmp_path / "p.toml")
    assert c.dataset.n_samples == 100 and c.dataset.n_test2 == 200 and c.material == Config().material


@pytest.mark.parametrize(
    "data, key, text",
    [
        ({"markers": {"cout": 5}}, "markers.cout", "unknown config key"),
        ({"colour": "red"}, "colour", "unknown config key"),
        ({"markers": {"count": "five"}}, "markers.count", "must be an integer"),
        ({"markers": {"count": 2.5}}, "markers.count", "must be an integer"),
        ({"material": {"youngs_modulus": "21kPa"}}, "material.youngs_modulus", "must be a number"),
        ({"material": {"youngs_modulus": True}}, "material.youngs_modulus", "must be a number"),
        ({"mesh": {"path": 3}}, "mesh.path", "must be a string"),
        ({"surrogate": {"hidden": 128}}, "surrogate.hidden", "must be a list"),
        ({"surrogate": {"head": "cubic"}}, "surrogate.head", "is not allowed"),
        ({"surrogate": {"head_dims": 61}}, "surrogate.head_dims", "out of range"),
        ({"markers": "five"}, "markers", "must be a table"),
        ({"material": {"poisson_ratio": 0.5}}, "material.poisson_ratio", "out of range"),
        ({"material": {"youngs_modulus": 0.0}}, "material.youngs_modulus", "out of range"),
        ({"markers": {"count": 0}}, "markers.count", "out of range"),
        ({"markers": {"fixed_spacing": 0.0}}, "markers.fixed_spacing", "out of range"),
        ({"markers": {"fixed_rule": "tight"}}, "markers.fixed_rule", "is not allowed"),
        ({"serve": {"port": 70000}}, "serve.port", "out of range"),
        ({"material": {"youngs_modulus": float("nan")}}, "material.youngs_modulus", "must be finite"),
        ({"mesh": {"units": "inch"}}, "mesh.units", "is not allowed"),
        ({"solver": {"order": 3}}, "solver.order", "is not allowed"),
        ({"solver": {"strategy": "cg"}}, "solver.strategy", "is not allowed"),
        ({"solver": {"krylov_tolerance": 0.0}}, "solver.krylov_tolerance", "out of range"),
        ({"solver": {"krylov_iterations": 0}}, "solver.krylov_iterations", "out of range"),
        ({"solver": {"krylov_recycle": -1}}, "solver.krylov_recycle", "out of range"),
        ({"forces": {"betas": [0.5, 1.5]}}, "betas", "must be numbers in [0, 1]"),
        ({"dataset": {"split": [8, 1]}}, "split", "three non-negative numbers"),
        ({"dataset": {"predictor": "pod"}}, "dataset.predictor", "is not allowed"),
        ({"dataset": {"predictor_samples": 1}}, "dataset.predictor_samples", "out of range"),
        ({"dataset": {"predictor_tolerance": 0.0}}, "dataset.predictor_tolerance", "out of range"),
        ({"solver": {"reference_preconditioner": "yes"}}, "solver.reference_preconditioner", "must be"),
        ({"solver": {"linear_solver": "amg"}}, "solver.linear_solver", "is not allowed"),
        ({"solver": {"multigrid_dofs": -1}}, "solver.multigrid_dofs", "out of range"),
        ({"solver": {"multigrid_smoothing": 0}}, "solver.multigrid_smoothing", "out of range"),
        ({"solver": {"multigrid_smoothing": 9}}, "solver.multigrid_smoothing", "out of range"),
        ({"dataset": {"time_budget": -1.0}}, "dataset.time_budget", "out of range"),
        ({"dataset": {"time_budget_min": -0.5}}, "dataset.time_budget_min", "out of range"),
        ({"dataset": {"batch_size": 0}}, "dataset.batch_size", "out of range"),
        ({"dataset": {"batch_size": 257}}, "dataset.batch_size", "out of range"),
        ({"dataset": {"batch_memory": 0.0}}, "dataset.batch_memory", "out of range"),
        ({"scenario": {"springs": {"lumping": "consistent"}}}, "scenario.springs.lumping", "is not allowed"),
    ],
)
def test_bad_values_raise_config_error_naming_the_key(data, key, text):
    with pytest.raises(ConfigError) as err:
        config_from_dict(data)
    msg = str(err.value)
    assert key in msg and text in msg


def test_out_of_range_message_gives_the_allowed_range():
    message = r"material\.poisson_ratio = 0\.5 is out of range; allowed values are in \(-1\.0, 0\.5\)"
    with pytest.raises(ConfigError, match=message):
        config_from_dict({"material": {"poisson_ratio": 0.5}})
    with pytest.raises(ConfigError,
                       match=r"allowed keys in \[markers\]: count, fixed_count, .*min_distance, rule, sentinel, start"):
        config_from_dict({"markers": {"cout": 5}})


#: Sections whose key descriptions are held to one short line (``tissuecast config show`` prints
#: each after its key); add the others here once theirs are short.
SHORT_DOC_SECTIONS = ("mesh", "markers", "material", "surrogate", "evaluate", "serve")


@pytest.mark.parametrize("section", SHORT_DOC_SECTIONS)
def test_key_descriptions_are_one_short_line(section):
    import dataclasses

    from tissuecast.config import Config

    cls = type(getattr(Config(), section))
    for f in dataclasses.fields(cls):
        doc = f.metadata.get("doc", "")
        assert doc, f"{section}.{f.name} has no description"
        assert len(doc) <= 150 and "\n" not in doc, f"{section}.{f.name}: {len(doc)} characters"


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("[markers\ncount = 5\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(tmp_path / "bad.toml")


def test_dataset_keys_are_either_content_or_run_settings():
    """Each [dataset] key is in exactly one group; the store compares the content only."""
    from tissuecast.config import DatasetConfig, DatasetContent, RunSettings
    from tissuecast.dataset import data_config

    content = {f.name for f in dataclasses.fields(DatasetContent)}
    run = {f.name for f in dataclasses.fields(RunSettings)}
    assert not content & run and content | run == {f.name for f in dataclasses.fields(DatasetConfig)}
    cfg = with_overrides(Config(), dataset={"seed": 7, "split": [6, 2, 2], "workers": 3, "store": "x.zarr",
                                            "time_budget": 0.0})
    assert cfg.dataset.content().seed == 7 and cfg.dataset.content().split == (6.0, 2.0, 2.0)
    assert cfg.dataset.run_settings() == RunSettings("x.zarr", 3, "", 0.0, 60.0)
    assert data_config(cfg)["dataset"] == config_to_dict(cfg.dataset.content())
    assert data_config(cfg) == data_config(with_overrides(Config(), dataset={"seed": 7, "split": [6, 2, 2]},
                                                          mesh={"path": "moved.vtu"}))
    assert data_config(cfg) != data_config(with_overrides(cfg, dataset={"batch_size": 4}))


def test_config_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Config().markers.count = 3  # type: ignore[misc]


def test_config_show_cli(tmp_path, capsys):
    assert main(["config", "show"]) == 0
    out = capsys.readouterr().out
    assert "[material]" in out and "youngs_modulus = 0.021" in out
    (tmp_path / "c.toml").write_text("[markers]\ncount = 9\n")
    assert main(["config", "show", str(tmp_path / "c.toml"), "--no-comments"]) == 0
    out = capsys.readouterr().out
    assert "count = 9\n" in out and "#" not in out
    path = tmp_path / "shown.toml"
    path.write_text(out)
    assert load_config(path).markers.count == 9


def test_what_a_path_names_is_checked_at_the_edge_with_one_error_naming_the_key(tmp_path, capsys):
    """config.py checks values; the CLI's loader asks the domain what each path names."""
    from tissuecast.evaluate.targets import targets_from_config
    from tissuecast.mesh import phantom

    bad = tmp_path / "bad.toml"
    bad.write_text('[mesh]\npath = "roi.vtu"\nlabel = 2\n')
    assert load_config(bad).mesh.label == 2  # a value like any other, for the library
    assert main(["config", "show", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: mesh.label and mesh.segment apply only when mesh.path names a label map")
    assert err.count("\n") == 1  # one line
    targets = config_from_dict({"evaluate": {"targets": {"rule": "label", "path": "tumour.vtu"}}}).evaluate.targets
    with pytest.raises(ConfigError, match="evaluate.targets.path = 'tumour.vtu' is not a label map"):
        targets_from_config(targets, phantom())  # and where the targets are made


# ------------------------------------------------------------------------- scenario
EMBEDDED = {"pins": False, "attached": {"rule": "normal", "direction": [0, -1, 0], "angle": 30.0},
            "springs": {"rule": "surface", "tangential_stiffness": 0.001},
            "gravity": {"enabled": True, "cone_angle": 20.0}, "indentation": {"enabled": True},
            "materials": {"cell_data": "region", "regions": [
                {"name": "tumour", "value": 2, "youngs_modulus": 0.063, "youngs_modulus_range": [0.05, 0.08]},
                {"name": "core", "rule": "distance", "point": [1.0, 2.0, 3.0], "distance": 5.0}]}}


def test_scenario_defaults_are_the_papers_and_nested_tables_round_trip(tmp_path):
    sc = Config().scenario
    assert sc.pins and sc.lbo_forces and sc.attached.rule == "none" and sc.springs.rule == "none"
    assert not sc.gravity.enabled and not sc.indentation.enabled and sc.materials.regions == ()
    assert sc.springs.normal_stiffness == pytest.approx(0.021 / 10.0, rel=1e-12)  # E over 10 mm, N/mm^3
    assert sc.gravity.density == 1e-9 and sc.gravity.acceleration == 9810.0
    cfg = with_overrides(Config(), scenario=EMBEDDED)
    assert cfg.scenario.materials.regions[0].youngs_modulus_range == (0.05, 0.08)
    assert cfg.scenario.materials.regions[1].rule == "distance"
    for comments in (True, False):
        text = config_to_toml(cfg, comments=comments)
        assert "[scenario.gravity]" in text and text.count("[[scenario.materials.regions]]") == 2
        path = tmp_path / "s.toml"
        path.write_text(text)
        assert load_config(path) == cfg
        # only what differs from the defaults: the same config, each value marked changed
        changed = config_to_toml(cfg, comments=comments, changed_only=True)
        path.write_text(changed)
        assert load_config(path) == cfg
        assert "[solver]" not in changed and "[scenario.gravity]" in changed and "[scenario.springs]" in changed
        assert changed.count("[[scenario.materials.regions]]") == 2
        assert ("enabled = true  # changed (default false): add the change of gravity" in changed) == comments
    assert config_to_toml(Config(), changed_only=True) == "\n"  # the defaults change nothing
    marked = config_to_toml(cfg)
    assert "cone_angle = 20.0  # changed (default 30.0): each sample's surgery direction" in marked
    assert "acceleration = 9810.0  # |g| in mm/s^2 (9.81 m/s^2 = 9810 mm/s^2)" in marked  # a default: its doc alone
    # a sub-table given in part keeps its other keys (and the other sub-tables)
    more = with_overrides(cfg, scenario={"gravity": {"density": 1.05e-9}})
    assert more.scenario.gravity.density == 1.05e-9 and more.scenario.gravity.cone_angle == 20.0
    assert more.scenario.springs == cfg.scenario.springs


@pytest.mark.parametrize(
    "scenario, key, text",
    [
        ({"attached": {"rule": "back"}}, "scenario.attached.rule", "is not allowed"),
        ({"attached": {"rule": "ids"}}, "scenario.attached.rule", "needs scenario.attached.ids"),
        ({"attached": {"rule": "tag"}}, "scenario.attached.rule", "needs scenario.attached.tag"),
        ({"attached": {"rule": "normal", "direction": [0, 0, 0]}}, "scenario.attached.direction", "not all zero"),
        ({"springs": {"rule": "distance", "point": [1, 2]}}, "scenario.springs.point", "3 numbers"),
        ({"attached": {"ids": [-1]}}, "scenario.attached.ids[0]", "out of range"),
        ({"attached": {"angle": 200.0}}, "scenario.attached.angle", "out of range"),
        ({"springs": {"rule": "surface", "normal_stiffness": 2.1e6}}, "scenario.springs.normal_stiffness", "N/m^3"),
        ({"springs": {"rule": "surface", "tangential_stiffness": 1e-9}}, "scenario.springs.tangential_stiffness",
         "per unit area"),
        ({"springs": {"normal_stiffness": 0.0}}, "scenario.springs.normal_stiffness", "out of range"),
        ({"gravity": {"density": 1000.0}}, "scenario.gravity.density", "1000 kg/m^3 = 1 g/cm^3 = 1e-9 t/mm^3"),
        ({"gravity": {"density": 1.0}}, "scenario.gravity.density", "outside the range of tissues"),
        ({"gravity": {"acceleration": 9.81}}, "scenario.gravity.acceleration", "looks like m/s^2"),
        ({"gravity": {"cone_angle": 120.0}}, "scenario.gravity.cone_angle", "out of range"),
        ({"gravity": {"surgery_direction": [0, 1]}}, "scenario.gravity.surgery_direction", "3 numbers"),
        ({"gravity": {"densty": 1e-9}}, "scenario.gravity.densty", "unknown config key"),
        ({"indentation": {"radius": 0.004}}, "scenario.indentation.radius", "look like metres"),
        ({"indentation": {"depth": [0.002, 0.006]}}, "scenario.indentation.radius", "look like metres"),
        ({"indentation": {"depth": [6.0, 2.0]}}, "scenario.indentation.depth", "min <= max"),
        ({"indentation": {"slide": [1.0]}}, "scenario.indentation.slide", "[min, max]"),
        ({"indentation": {"depth": [0.0, 0.0]}}, "scenario.indentation.depth", "never pushes"),
        ({"materials": {"regions": [{"name": "t"}]}}, "scenario.materials.cell_data", "must name"),
        ({"materials": {"cell_data": "r", "regions": [{"name": "t"}, {"name": "t"}]}}, "scenario.materials.regions",
         "repeat a name"),
        ({"materials": {"cell_data": "r", "regions": [{"name": "t", "modulus": 1.0}]}},
         "scenario.materials.regions[0].modulus", "unknown config key"),
        ({"materials": {"cell_data": "r", "regions": [{"youngs_modulus_range": [0.08, 0.05]}]}},
         "scenario.materials.regions[0].youngs_modulus_range", "min <= max"),
        ({"materials": {"cell_data": "r", "regions": [{"poisson_ratio_range": [0.4, 0.5]}]}},
         "scenario.materials.regions[0].poisson_ratio_range[1]", "out of range"),
        ({"materials": {"regions": {"name": "t"}}}, "scenario.materials.regions", "must be a list"),
        ({"pins": False}, "scenario", "has no support"),
        ({"lbo_forces": False}, "scenario", "has no load"),
    ],
)
def test_bad_scenario_values_raise_config_error_naming_the_key(scenario, key, text):
    with pytest.raises(ConfigError) as err:
        config_from_dict({"scenario": scenario})
    msg = str(err.value)
    assert key in msg and text in msg


def test_spring_stiffness_is_judged_against_the_tissue_modulus():
    """k = E / L: the same k is plausible for a stiff tissue and implausible for a soft one."""
    springs = {"rule": "surface", "normal_stiffness": 1.0, "tangential_stiffness": 1.0}
    stiff = {"material": {"youngs_modulus": 10.0, "check_range": False}, "scenario": {"springs": springs}}
    assert config_from_dict(stiff).scenario.springs.normal_stiffness == 1.0  # 10 MPa over 10 mm
    stiff["material"]["youngs_modulus"] = 0.001
    with pytest.raises(ConfigError, match=r"over 0\.001 mm"):
        config_from_dict(stiff)


@pytest.mark.parametrize("section", ["forces", "scenario"])
def test_forces_and_scenario_key_descriptions_are_one_short_line(section):
    import dataclasses

    from tissuecast.config import Config, MaterialRegionConfig

    def check(obj, name):
        for f in dataclasses.fields(obj):
            doc = f.metadata.get("doc", "")
            assert doc, f"{name}.{f.name} has no description"
            assert len(doc) <= 150 and "\n" not in doc, f"{name}.{f.name}: {len(doc)} characters"
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                check(value, f"{name}.{f.name}")

    check(getattr(Config(), section), section)
    if section == "scenario":
        check(MaterialRegionConfig(), "scenario.materials.regions")


@pytest.mark.parametrize(
    "data, key, text",
    [
        ({"material": {"youngs_modulus": 21.0}}, "material.youngs_modulus = 21.0 MPa", "21 kPa would be 0.021 MPa"),
        ({"material": {"youngs_modulus": 21000.0}}, "material.youngs_modulus = 21000.0 MPa", "21000 Pa would be 0.021 MPa"),
        ({"material": {"youngs_modulus": 2e-5}}, "material.youngs_modulus", "outside soft tissue's range"),
        ({"scenario": {"materials": {"regions": [{"name": "t", "rule": "distance", "youngs_modulus": 63.0}]}}},
         "scenario.materials.regions[0].youngs_modulus = 63.0 MPa", "63 kPa would be 0.063 MPa"),
        ({"scenario": {"materials": {"regions": [{"name": "t", "rule": "distance", "youngs_modulus_range": [0.01, 50.0]}]}}},
         "scenario.materials.regions[0].youngs_modulus_range = 50.0 MPa", "material.check_range = false"),
        ({"forces": {"target_max_displacement": 0.03}}, "forces.target_max_displacement = 0.03 mm", "looks like metres"),
        ({"scenario": {"gravity": {"enabled": True, "density": 1000.0}}}, "scenario.gravity.density", "1e-9 t/mm^3"),
    ],
)
def test_values_that_are_almost_surely_a_unit_slip_are_refused_with_the_fix(data, key, text):
    with pytest.raises(ConfigError) as err:
        config_from_dict(data)
    assert key in str(err.value) and text in str(err.value)


def test_a_stiff_material_is_accepted_when_the_range_check_is_off():
    cfg = config_from_dict({"material": {"youngs_modulus": 21.0, "check_range": False},
                            "scenario": {"materials": {"regions": [{"name": "t", "rule": "distance",
                                                                    "youngs_modulus": 63.0}]}}})
    assert cfg.material.youngs_modulus == 21.0 and cfg.scenario.materials.regions[0].youngs_modulus == 63.0
    assert config_from_dict({"material": {"youngs_modulus": 1e-4}}).material.youngs_modulus == 1e-4  # brain, softest


@pytest.mark.parametrize(
    "targets, key, text",
    [
        ({"rule": "tumour"}, "evaluate.targets.rule", "is not allowed"),
        ({"count": 0}, "evaluate.targets.count", "out of range"),
        ({"depth": -1.0}, "evaluate.targets.depth", "out of range"),
        ({"rule": "tag"}, "evaluate.targets.tag", "needs"),
        ({"rule": "label"}, "evaluate.targets.path", "a label map"),
        ({"rule": "points"}, "evaluate.targets.path", "a CSV or Slicer markups file"),
        ({"rule": "label", "path": "tumour.vtu"}, "evaluate.targets.path", "is not a label map"),
        ({"rule": "points", "path": "targets.txt"}, "evaluate.targets.path", "reads .csv, .mrk.json, .fcsv"),
        ({"rule": "label", "path": "scan.nrrd", "segment": "tumour"}, "evaluate.targets.segment", "use evaluate.targets.label"),
        ({"tag": "tumour"}, "evaluate.targets.tag", "does not apply to evaluate.targets.rule = 'interior'"),
        ({"rule": "points", "path": "t.csv", "label": 2}, "evaluate.targets.label", "does not apply"),
    ],
)
def test_bad_targets_raise_config_error_naming_the_key(targets, key, text):
    from tissuecast.app import check_config

    with pytest.raises(ConfigError) as err:  # values at loading, what a path names at the edge
        check_config(config_from_dict({"evaluate": {"targets": targets}}))
    msg = str(err.value)
    assert key in msg and text in msg


def test_targets_default_and_round_trip(tmp_path):
    t = Config().evaluate.targets
    assert (t.rule, t.count, t.depth) == ("interior", 10, 0.0)
    cfg = with_overrides(Config(), evaluate={"targets": {"rule": "label", "path": "scan.seg.nrrd", "segment": "tumour",
                                                         "count": 25}})
    path = tmp_path / "c.toml"
    path.write_text(config_to_toml(cfg))
    assert load_config(path) == cfg and "[evaluate.targets]" in path.read_text()
    assert all(len(f.metadata["doc"]) <= 150 for f in dataclasses.fields(type(t)))


def test_fallback_epochs_need_a_tracked_instrument():
    from tissuecast.app import check_config

    with pytest.raises(ConfigError, match="surrogate.fallback_epochs = 200 .* declares none"):
        check_config(config_from_dict({"surrogate": {"fallback_epochs": 200}}))
    emb = load_config(Path(__file__).resolve().parents[1] / "configs" / "embedded.toml")
    assert check_config(with_overrides(emb, surrogate={"fallback_epochs": 200})).surrogate.fallback_epochs == 200


def test_a_run_too_small_to_train_validate_and_evaluate_is_refused_before_simulating(tmp_path, capsys):
    from tissuecast.app.configuration import check_run_sizes
    from tissuecast.dataset.sample_plan import split_sizes

    assert split_sizes(4, (8, 1, 1)) == (3, 0, 1) and split_sizes(2000, (8, 1, 1)) == (1600, 200, 200)
    with pytest.raises(ConfigError, match=r"dataset.n_samples = 4 at dataset.split 8:1:1 gives 3 training, 0 validation, "
                                          r"1 test-1 samples; .* raise dataset.n_samples to at least 8 or change"):
        check_run_sizes(with_overrides(Config(), dataset={"n_samples": 4}))
    check_run_sizes(with_overrides(Config(), dataset={"n_samples": 8}))
    assert split_sizes(8, (8, 1, 1)) == (6, 1, 1) and split_sizes(7, (8, 1, 1)) == (6, 1, 0)  # 8 is the least that works
    with pytest.raises(ConfigError, match="change dataset.split$"):  # no size gives a validation sample
        check_run_sizes(with_overrides(Config(), dataset={"n_samples": 100, "split": [1, 0, 1]}))
    expert = with_overrides(load_config(Path(__file__).resolve().parents[1] / "configs" / "embedded.toml"),
                            surrogate={"nominal_samples": 6})
    with pytest.raises(ConfigError, match="surrogate.nominal_samples = 6 at"):
        check_run_sizes(expert)
    cfg = tmp_path / "tiny.toml"  # the command refuses it before anything is simulated
    cfg.write_text(f'[dataset]\nn_samples = 4\nstore = "{(tmp_path / "s.zarr").as_posix()}"\n')
    assert main(["run", str(cfg)]) == 2
    assert "raise dataset.n_samples to at least 8" in capsys.readouterr().err and not (tmp_path / "s.zarr").exists()
