"""The mismatch study: its sets, their configs, the refined-mesh reference, and a small run of
the whole study (two models, a few sets) through the CLI."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest

from tissuecast.config import with_overrides
from tissuecast.dataset import open_dataset, simulate
from tissuecast.errors import ConfigError
from tissuecast.evaluate.mismatch import chosen_sets, mismatch_sets, set_config
from tissuecast.fem import Solver
from tissuecast.mesh.refine import refine_uniformly
from tissuecast.scenario import scenario_from_config
from tissuecast.scenario.refined import refined_sample

from dataset_helpers import small_config, write_config

SCENARIO = {"name": "embedded", "pins": False,
            "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
            "springs": {"rule": "surface"}, "gravity": {"enabled": True},
            "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5],
                            "tool": "rounded", "tool_radius": 20.0}}
UNCERTAIN = {"youngs_modulus": [0.5, 2.0], "spring_normal": [0.25, 4.0], "spring_tangential": [0.25, 4.0],
             "attached_margin": [-5.0, 5.0]}


def _config(folder, uncertain=True, **dataset):
    ds = {"n_samples": 60, "n_test2": 0, "alpha": 0.0, "calibration_samples": 2, "predictor_samples": 8,
          "split": [6.0, 2.0, 2.0]}
    ds.update(dataset)
    cfg = with_overrides(small_config(folder, **ds), forces={"loading": "traction", "target_max_displacement": 4.0},
                         scenario=SCENARIO, surrogate={"epochs": 60, "patience": 0, "calibration_share": 0.2})
    return with_overrides(cfg, scenario={"uncertain": UNCERTAIN if uncertain else {}})


def test_the_sets_their_ranges_and_their_configs(tmp_path):
    cfg = _config(tmp_path)
    mesh, markers, fixed, _ = scenario_from_config(cfg)
    sets = {s.name: s for s in mismatch_sets(cfg, mesh)}
    assert list(sets)[0] == "nominal" and sets["discretisation"].reference == "refined"
    assert sets["quadratic elements"].reference == "p2"  # linear elements here: their order's share too
    # the refined solves take minutes to tens of minutes: run when named, not by default
    default = [s.name for s in chosen_sets(cfg, mesh)]
    assert "discretisation" not in default and "quadratic elements" in default and default[0] == "nominal"
    assert [s.name for s in chosen_sets(cfg, mesh, ["discretisation"])] == ["nominal", "discretisation"]
    with pytest.raises(ConfigError, match=r"unknown mismatch set\(s\) \['E x3'\]; choose among"):
        chosen_sets(cfg, mesh, ["E x3"])
    quadratic = with_overrides(cfg, solver={"order": 2})
    assert "quadratic elements" not in {s.name for s in mismatch_sets(quadratic, mesh)}  # it would be the data itself
    assert sets["E x0.5"].in_range and sets["E x2"].in_range and not sets["E x4"].in_range
    assert sets["springs x0.25"].in_range and sets["attached +5 mm"].in_range and not sets["attached +10 mm"].in_range
    assert not sets["nu 0.40"].in_range  # the config draws no nu
    assert not sets["gravity 45 deg off"].in_range and not sets["inclusion 3x E"].in_range
    one = set_config(cfg, sets["springs x4"], alpha=1.5, samples=12, markers=markers, fixed=fixed, store=tmp_path / "s")
    u = one.scenario.uncertain
    assert u.spring_normal == (4.0, 4.0) and u.spring_tangential == (4.0, 4.0) and u.youngs_modulus == ()
    assert one.dataset.alpha == 1.5 and one.dataset.split == (0.0, 0.0, 1.0) and one.dataset.n_test2 == 0
    assert one.dataset.seed != cfg.dataset.seed and one.markers.ids == tuple(int(m) for m in markers)
    g = set_config(cfg, sets["gravity 45 deg off"], alpha=1.5, samples=12, markers=markers, fixed=fixed, store="s")
    d0, d1 = np.asarray(cfg.scenario.gravity.surgery_direction), np.asarray(g.scenario.gravity.surgery_direction)
    assert np.degrees(np.arccos(d0 @ d1 / np.linalg.norm(d0) / np.linalg.norm(d1))) == pytest.approx(45.0)
    # a training config's nominal share does not reach the sets: each set's samples all have its values
    shared = with_overrides(cfg, scenario={"uncertain": {"nominal_share": 0.25}})
    for name in ("nominal", "springs x4"):
        assert set_config(shared, sets[name], alpha=1.5, samples=12, markers=markers, fixed=fixed,
                          store="s").scenario.uncertain.nominal_share == 0.0
    inc = set_config(cfg, sets["inclusion 3x E"], alpha=1.5, samples=12, markers=markers, fixed=fixed, store="s")
    assert inc.scenario.materials.regions[-1].youngs_modulus == pytest.approx(3 * cfg.material.youngs_modulus)
    with pytest.raises(Exception, match="outside soft tissue"):
        with_overrides(cfg, material={"youngs_modulus": 30.0})


def test_the_refined_sample_carries_the_same_loads_and_converges(tmp_path):
    cfg = with_overrides(_config(tmp_path, uncertain=False), solver={"order": 2})
    mesh, _, _, sc = scenario_from_config(cfg)
    refined = refine_uniformly(mesh)
    x = sc.sample(3, alpha=1.0)
    fine = refined_sample(sc, cfg, refined, x)
    # the same total traction and body force (held by springs alone: no load lost to a support),
    # the supports refined, the instrument at the same tip
    free = with_overrides(cfg, scenario={"attached": {"rule": "none"}, "indentation": {"enabled": False}})
    free_sc = scenario_from_config(free)[3]
    xf = free_sc.sample(3, alpha=1.0)
    ff = refined_sample(free_sc, free, refined, xf)
    np.testing.assert_allclose(ff.surface.sum(axis=0), xf.surface.sum(axis=0), rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(ff.keywords["body_loads"].sum(axis=0), xf.body.sum(axis=0), rtol=1e-10)
    held = fine.problem.fixed
    assert np.isin(sc.attached, held).all() and len(held) > 2 * len(sc.attached)  # + midpoints between them
    assert np.allclose(refined.mesh.points[held, 2], 0.0)
    ids, values = fine.keywords["prescribed"]
    assert len(ids) >= len(x.prescribed_ids)
    centre = x.draw.indentation.centre
    np.testing.assert_allclose(values[list(ids).index(centre)], x.draw.indentation.displacement, atol=1e-12)
    u_fine = Solver(fine.problem, cfg.solver).solve(fine.surface, **fine.keywords).displacement[: mesh.n_vertices]
    u_p2 = Solver(sc.problem(), cfg.solver).solve(x.surface, **x.solve_keywords()).displacement
    cfg1 = with_overrides(cfg, solver={"order": 1})
    sc1 = scenario_from_config(cfg1)[3]
    x1 = sc1.sample(3, alpha=1.0)
    u_p1 = Solver(sc1.problem(), cfg1.solver).solve(x1.surface, **x1.solve_keywords()).displacement
    far = np.linalg.norm(mesh.points - mesh.points[centre], axis=1) > 12.0  # away from the contact's rim
    err_p2, err_p1 = (np.abs(u - u_fine)[far].max() for u in (u_p2, u_p1))
    assert err_p2 < 0.5 * err_p1


def test_a_small_mismatch_study_through_the_cli(tmp_path, capsys):
    from tissuecast.cli.main import main

    models = {}
    for label, unc in (("nominal", False), ("uncertain", True)):
        (tmp_path / label).mkdir()
        cfg = _config(tmp_path / label, uncertain=unc)
        cfg = with_overrides(cfg, dataset={"store": str(tmp_path / label / "data.zarr")},
                             output=str(tmp_path / label))
        path = write_config(cfg, tmp_path / f"{label}.toml")
        simulate(cfg, progress=False)
        assert main(["-q", "train", str(path), "--out", str(tmp_path / label / "model")]) == 0
        models[label] = tmp_path / label / "model"
    out = tmp_path / "study"
    assert main(["-q", "study", "mismatch", str(tmp_path / "uncertain.toml"), "--model", f"u={models['uncertain']}",
                 "--refined-time-limit", "-5"]) == 2
    assert "--refined-time-limit -5: give seconds > 0, or 0 for no limit" in capsys.readouterr().err
    code = main(["-q", "study", "mismatch", str(tmp_path / "uncertain.toml"), "--out", str(out),
                 "--model", f"nominal={models['nominal']}", "--model", f"uncertain={models['uncertain']}",
                 "--sets", "E x2,attached -5 mm,quadratic elements,discretisation", "--samples", "6",
                 "--refined-samples", "2"])
    assert code == 0
    data = json.loads((out / "study_mismatch.json").read_text())
    rows = {(r["set"], r["model"]): r for r in data["rows"]}
    assert set(rows) == {(s, m) for s in ("nominal", "E x2", "attached -5 mm", "quadratic elements", "discretisation")
                         for m in ("nominal", "uncertain")}
    # the quadratic-elements set: the nominal set's first samples with P2 on the same mesh
    nominal_set = open_dataset(out / "mismatch" / "nominal.zarr")
    first = int(nominal_set.select("test1")[0])
    p2 = np.load(out / "mismatch" / "quadratic_elements" / f"sample_{first:05d}.npy")
    linear = np.linalg.norm(nominal_set.displacements[first], axis=1)
    assert np.linalg.norm(p2, axis=1).mean() > 1.05 * linear.mean()  # linear tetrahedra are the stiffer
    for label in ("nominal", "uncertain"):  # each model's relative error over its own nominal one
        for name in ("E x2", "attached -5 mm"):
            assert rows[(name, label)]["relative_vs_nominal"] == pytest.approx(
                rows[(name, label)]["relative"] / rows[("nominal", label)]["relative"], rel=1e-12)
    assert rows[("E x2", "uncertain")]["relative_vs_nominal"] != rows[("E x2", "nominal")]["relative_vs_nominal"]
    assert rows[("E x2", "nominal")]["in_range"] is True and rows[("E x2", "nominal")]["count"] == 6
    assert (out / "study_mismatch.png").is_file() and (out / "study_mismatch.csv").is_file()
    _a_refined_solve_past_its_limit_is_recorded(tmp_path / "uncertain.toml", out / "mismatch", tmp_path / "timed")
    _the_reference_takes_the_data_sets_path(out / "mismatch" / "nominal.zarr")
    _answers_solved_another_way_are_solved_again(tmp_path / "uncertain.toml", out / "mismatch")
    # the sets are data sets with the set's parameter fixed, the trained alpha, the models' markers
    e2 = open_dataset(out / "mismatch" / "e_x2.zarr")
    assert (e2.parameters["youngs_modulus"] == 2.0).all()
    # the sets' loads are the first model's training loads; with uncertain parameters alpha is
    # calibrated at the nominal parameters, so both training stores have the same
    nominal_alpha = open_dataset(tmp_path / "nominal" / "data.zarr").calibration["alpha"]
    assert e2.calibration["alpha"] == nominal_alpha
    assert open_dataset(tmp_path / "uncertain" / "data.zarr").calibration["alpha"] == pytest.approx(nominal_alpha)
    # the report shows the study when it is in the studies folder
    from tissuecast.evaluate.mismatch_report import mismatch_section

    (tmp_path / "report_folder").mkdir()
    section = mismatch_section(out, tmp_path / "report_folder")
    assert "What a mismatch costs" in section and "E x2" in section


def test_every_default_set_has_its_own_folder():
    from tissuecast.evaluate.mismatch import set_folder_name

    names = ["nominal", "E x0.5", "E x2", "E x4", "nu 0.40", "nu 0.49", "springs x0.25", "springs x4", "attached +5 mm",
             "attached -5 mm", "attached +10 mm", "gravity 45 deg off", "inclusion 3x E", "quadratic elements",
             "discretisation"]
    folders = [set_folder_name(n) for n in names]
    assert len(set(folders)) == len(names), folders
    assert set_folder_name("attached -5 mm") == "attached_minus5_mm" and set_folder_name("E x0.5") == "e_x0p5"


def test_the_alarm_cell_names_what_raised_it():
    from tissuecast.evaluate.headline import ALARM_REASONS
    from tissuecast.evaluate.mismatch_report import mismatch_table
    from tissuecast.surrogate.trust import Alarm

    assert all(isinstance(getattr(Alarm, prop, None), property) for prop, _ in ALARM_REASONS.values())

    row = {"set": "attached +10 mm", "in_range": False, "model": "m", "peak_median": 15.9, "mlp_offset_max": 7.0,
           "relative": 0.44, "relative_vs_nominal": 2.5, "rigid_offset_max": 12.3, "ridge_offset_max": 7.8,
           "gain_over_rigid": 1.8, "alarm_rate": 1.0, "alarm_far_rate": 0.1, "alarm_disagree_rate": 0.0,
           "alarm_still_rate": 1.0}
    assert mismatch_table([row])[0][-1] == "100 % (still marker, far)"
    quiet = {**row, "alarm_rate": 0.0, "alarm_far_rate": 0.0, "alarm_still_rate": 0.0}
    assert mismatch_table([quiet])[0][-1] == "0 %"
    old = {k: v for k, v in row.items() if not k.startswith("alarm_") or k == "alarm_rate"}  # rows written before
    assert mismatch_table([old])[0][-1] == "100 %"


def test_run_with_a_nominal_expert(tmp_path):
    """`surrogate.nominal_expert`: the run simulates the nominal store beside the uncertain one
    (the same alpha, nothing drawn, its own seed, ``nominal_samples`` of them and no test-2),
    trains the expert on the model's markers and saves the pair; the config refuses what the
    expert cannot be built from."""
    from tissuecast.app.configuration import check_config
    from tissuecast.app.pipeline import run_pipeline
    from tissuecast.surrogate import DeformationModel

    cfg = with_overrides(_config(tmp_path, n_test2=3), surrogate={"nominal_expert": True, "nominal_samples": 50,
                                                                  "calibration_share": 0.3}, evaluate={"renders": 0},
                         dataset={"store": str(tmp_path / "data.zarr")}, output=str(tmp_path / "run"))
    (tmp_path / "run" / "model").mkdir(parents=True)
    (tmp_path / "run" / "model" / "model.onnx").write_text("an earlier model's graph")
    result = run_pipeline(cfg, progress=False)
    paths = result["paths"]
    unc, nom = open_dataset(paths.store), open_dataset(paths.nominal_store)
    assert paths.nominal_store.name == "data_nominal.zarr"
    assert nom.calibration["alpha"] == unc.calibration["alpha"] and not nom.parameters
    assert nom.config.dataset.seed != unc.config.dataset.seed and "simulate nominal" in result["seconds"]
    assert (nom.n_samples, len(nom.select("test2")), len(unc.select("test2"))) == (50, 0, 3)
    assert result["nominal_dataset"]["totals"]["done"] == nom.n_samples - result["nominal_dataset"]["totals"]["failed"]
    model = DeformationModel.load(paths.model)
    assert model.has_nominal_expert and np.array_equal(model.nominal_expert_.markers, model.markers)
    assert result["model"].has_nominal_expert
    # the earlier model's graph is replaced by the pair's routed graph
    ort = pytest.importorskip("onnxruntime")
    test = unc.select("test1", status="done")
    U = np.asarray(unc.displacements[test], dtype=np.float64)
    d = model.marker_displacements(U)
    session = ort.InferenceSession(str(paths.model / "model.onnx"), providers=["CPUExecutionProvider"])
    feeds = {"markers": d.astype(np.float32)}
    auxiliary = None
    if model.auxiliary.width:
        from tissuecast.app.pipeline import split_fields

        auxiliary = split_fields(model, unc, "test1")[1]
        feeds["auxiliary"] = auxiliary.astype(np.float32)
    (graph,) = session.run(None, feeds)
    close = np.abs(graph - model.predict(d, auxiliary=auxiliary)).max(axis=(1, 2)) < 1e-4 * np.abs(U).max()
    assert close.mean() > 0.9  # but where the gate's logit lies within float32 round-off of 0
    assert model.expert_gate_.samples == len(unc.select("valid")) + len(nom.select("valid"))  # both families
    assert sum(model.expert_routes_.summary().values()) == len(unc.select("valid"))  # the bounds: the drawn family
    # the evaluation says how test-1 was routed; its routed figure is the pair's own field's
    from tissuecast.evaluate.tables import format_evaluation

    ev = result["evaluation"]
    routed = ev.model_summary["nominal_expert"]
    assert routed["count"] == len(unc.select("test1", status="done")) and 0.0 <= routed["routed_to_nominal"] <= 1.0
    assert routed["routed_offset_max"] == pytest.approx(ev.sets["test1"].summary("mlp").offset_max, rel=1e-9)
    assert routed["oracle_offset_max"] <= min(routed["uncertain_offset_max"], routed["nominal_offset_max"]) + 1e-12
    assert "nominal expert: " in format_evaluation(ev) and "with a nominal expert" in format_evaluation(ev)
    # the models given the wrong way round to `tissuecast experts`: refused, naming the order
    from tissuecast.cli.main import main

    assert main(["experts", str(paths.model / "nominal_expert"), str(paths.model), "--out", str(tmp_path / "x")]) == 2
    with pytest.raises(ConfigError, match="without --skip-simulate"):  # no nominal store to train the expert on
        run_pipeline(with_overrides(cfg, dataset={"store": str(tmp_path / "other.zarr")}), simulate=False)
    for change, words in (({"scenario": {"uncertain": {name: [] for name in UNCERTAIN}}}, "draws no parameter"),
                          ({"scenario": {"uncertain": {"measured": ["youngs_modulus"]}}}, "measured parameters"),
                          ({"surrogate": {"calibration": "none"}}, "needs error bounds"),
                          ({"surrogate": {"nominal_expert": False}}, "set nominal_expert = true or remove")):
        with pytest.raises(ConfigError, match=words):
            check_config(with_overrides(cfg, **change))


@contextlib.contextmanager
def _watched_solver(hook):
    """``tissuecast.fem.Solver`` replaced, inside the block, by one whose ``solve`` calls
    ``hook(solver, solve, kwargs)`` (``solve()``: the real solve) and returns what it returns."""
    import tissuecast.fem

    class Watched(tissuecast.fem.Solver):
        def solve(self, *args, **kwargs):
            return hook(self, lambda: super(Watched, self).solve(*args, **kwargs), kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(tissuecast.fem, "Solver", Watched)
    try:
        yield
    finally:
        mp.undo()


def _a_refined_solve_past_its_limit_is_recorded(config_path, study, folder):
    """The discretisation set under a time limit no refined solve meets: every sample left out
    and recorded; a second run with the same limit solves nothing; without a limit the samples
    are solved again, as the study solved them."""
    from tissuecast.config import load_config
    from tissuecast.evaluate.mismatch import discretisation_set

    cfg = load_config(config_path)
    calls = []

    def counting(solver, solve, kwargs):
        calls.append(kwargs.get("time_limit"))
        return solve()

    with _watched_solver(counting):
        assert discretisation_set(cfg, study / "nominal.zarr", folder, 2, time_limit=1e-9).n_samples == 0
        records = sorted(folder.glob("*.failed.json"))
        assert len(records) == 2 and calls == [1e-9, 1e-9]
        doc = json.loads(records[0].read_text())
        assert doc["timeout"] is True and doc["time_limit"] == 1e-9 and "time limit" in doc["reason"]
        assert discretisation_set(cfg, study / "nominal.zarr", folder, 2, time_limit=1e-9).n_samples == 0
        assert len(calls) == 2  # recorded: not tried again under the same limit
        again = discretisation_set(cfg, study / "nominal.zarr", folder, 2, time_limit=None)
        assert len(calls) == 4 and again.n_samples == 2
    for k, path in enumerate(sorted((study / "discretisation").glob("sample_*.npy"))):
        np.testing.assert_allclose(again.displacements[k], np.load(path), rtol=1e-9, atol=1e-9)


class _AlongTheLoadPath:
    """A data set read as if it had been solved from zero along the load path (``predictor = "none"``)."""

    def __init__(self, ds, **changes):
        self._ds, self.config = ds, with_overrides(ds.config, dataset={"predictor": "none"}, **changes)

    def __getattr__(self, name):
        return getattr(self._ds, name)


def _the_reference_takes_the_data_sets_path(store):
    """A data set solved from a guess: its reference starts from the data set's answer; one solved
    along the load path: the reference too, from zero (the P2 answer of a plain solve from zero)."""
    from tissuecast.errors import ConvergenceError
    from tissuecast.evaluate.mismatch import ReferenceSolver
    from tissuecast.scenario import restore_scenario

    ds = open_dataset(store)
    k = int(ds.select("test1")[0])
    guesses = []

    def recording(solver, solve, kwargs):
        guesses.append(kwargs.get("initial_guess"))
        return solve()

    with _watched_solver(recording):
        assert ds.config.dataset.predictor == "reduced" and not ReferenceSolver(ds, "p2").along_load_path
        ReferenceSolver(ds, "p2").solve(k)
        np.testing.assert_array_equal(guesses[-1], ds.displacements[k])
        along = ReferenceSolver(_AlongTheLoadPath(ds), "p2")
        u = along.solve(k)
    assert along.along_load_path and guesses[-1] is None
    cfg2 = with_overrides(ds.config, solver={"order": 2})
    sc = restore_scenario(ds.mesh, cfg2, ds.scenario_arrays, ds.basis)
    x = sc.sample(int(ds.seed[k]), float(ds.alpha[k]))
    plain = Solver(sc.problem(), cfg2.solver).solve(x.surface, **x.solve_keywords()).displacement[: ds.mesh.n_vertices]
    np.testing.assert_allclose(u, plain, rtol=0, atol=1e-9)
    # a solve that stops is tried again as the data set's samples are (exact Newton steps, smaller
    # increments), from the state it reached; without a state, from zero again
    strategies, starts, reached = [], [], []

    def stops_unless_newton(solver, solve, kwargs):
        strategies.append(solver.config.strategy)
        starts.append(kwargs.get("initial_guess"))
        if solver.config.strategy == "newton":
            return solve()
        if len(strategies) > 1:  # stopped before it reached anything
            raise ConvergenceError("stopped at load fraction 0", 0.0)
        reached.append(solve())  # as if it had stopped there
        raise ConvergenceError("stopped at load fraction 0.9", 0.9, result=reached[0])

    with _watched_solver(stops_unless_newton):
        retried = along.solve(k)
        assert ds.config.solver.strategy != "newton" and strategies == [ds.config.solver.strategy, "newton"]
        assert starts[0] is None and starts[1] is reached[0].nodal_displacement
        np.testing.assert_allclose(retried, plain, rtol=0, atol=1e-3 * np.abs(plain).max())  # the same equilibrium
        again = along.solve(k)  # stopped at once: from zero, with Newton steps
        assert strategies[2:] == [ds.config.solver.strategy, "newton"] and starts[3] is None
        np.testing.assert_allclose(again, plain, rtol=0, atol=0.02 * np.abs(plain).max())
        once = ReferenceSolver(_AlongTheLoadPath(ds, solver={"retries": 0}), "p2")
        with pytest.raises(ConvergenceError, match="load fraction 0"):
            once.solve(k)
        assert strategies[4:] == [ds.config.solver.strategy]


def _answers_solved_another_way_are_solved_again(config_path, study):
    """The quadratic set's folder records how its answers were solved; answers of another path
    (or of a version that did not record it) are moved aside and solved again, never mixed."""
    from tissuecast.config import load_config
    from tissuecast.evaluate.mismatch import REFERENCE_RECORD, discretisation_set

    cfg, folder = load_config(config_path), study / "quadratic_elements"
    record = folder / REFERENCE_RECORD
    assert json.loads(record.read_text()) == {"reference": "p2", "path": "from the data set's answer"}
    first = sorted(folder.glob("sample_*.npy"))[0]
    before = np.load(first)
    calls = []

    def counting(solver, solve, kwargs):
        calls.append(1)
        return solve()

    with _watched_solver(counting):
        again = discretisation_set(cfg, study / "nominal.zarr", folder, 1, reference="p2")
        assert calls == [] and again.n_samples == 1  # the same path: the answers are reused
        record.write_text(json.dumps({"reference": "p2", "path": "load path"}))
        again = discretisation_set(cfg, study / "nominal.zarr", folder, 1, reference="p2")
        assert calls == [1] and (folder / "superseded" / first.name).is_file()
        assert json.loads(record.read_text())["path"] == "from the data set's answer"
        np.testing.assert_allclose(again.displacements[0], before, rtol=0, atol=1e-9)  # solved again, the same way
        record.unlink()  # answers of a version that did not record how they were solved
        discretisation_set(cfg, study / "nominal.zarr", folder, 1, reference="p2")
        assert calls == [1, 1] and record.is_file()


def test_a_folder_keeps_the_answers_of_one_path(tmp_path, caplog):
    from tissuecast.evaluate.mismatch import REFERENCE_RECORD, keep_answers_of_one_path

    np.save(tmp_path / "sample_00001.npy", np.ones((3, 3)))
    (tmp_path / "sample_00002.failed.json").write_text("{}")
    keep_answers_of_one_path(tmp_path, {"path": "load path"})  # unrecorded answers: moved aside
    assert sorted(p.name for p in (tmp_path / "superseded").iterdir()) == ["sample_00001.npy", "sample_00002.failed.json"]
    assert "did not record how" in caplog.text
    np.save(tmp_path / "sample_00001.npy", np.zeros((3, 3)))
    keep_answers_of_one_path(tmp_path, {"path": "load path"})  # the same path: kept
    assert (tmp_path / "sample_00001.npy").is_file()
    keep_answers_of_one_path(tmp_path, {"path": "from the data set's answer"})
    assert not (tmp_path / "sample_00001.npy").exists() and np.load(tmp_path / "superseded" / "sample_00001.npy").sum() == 0
    assert json.loads((tmp_path / REFERENCE_RECORD).read_text()) == {"path": "from the data set's answer"}
    assert '{"path": "load path"}' in caplog.text


def test_the_study_solves_a_few_frames_of_each_set_through_the_physics(tmp_path, capsys):
    """``--physics 2``: each set's first two frames also through the physics inverse (the model's
    training simulator, markers and recorded retractor poses): on the nominal set it recovers the
    fields far below the model, within its band and without a misfit warning, and the row carries
    the baselines of the same frames; the report explains the row."""
    from dataset_helpers import tracked_retractor_store

    from tissuecast.cli.main import main
    from tissuecast.evaluate.mismatch_report import mismatch_section

    cfg, store, model = tracked_retractor_store(tmp_path)
    path = write_config(cfg, tmp_path / "tracked.toml")
    out = tmp_path / "study"
    argv = ["-q", "study", "mismatch", str(path), "--out", str(out), "--model", f"m={model}", "--sets", "E x2",
            "--samples", "4"]
    assert main(argv + ["--physics", "-1"]) == 2
    assert "--physics -1: give a number of frames >= 0" in capsys.readouterr().err
    assert main(argv + ["--model", f"physics={model}", "--physics", "2"]) == 2
    assert "a model is labelled 'physics', the label of the physics rows" in capsys.readouterr().err
    assert main(argv + ["--physics-known-margin"]) == 2
    assert "give a number of physics frames" in capsys.readouterr().err
    assert main(argv + ["--physics", "2", "--physics-known-margin"]) == 2
    assert "does not draw the attached region's margin" in capsys.readouterr().err
    assert main(argv + ["--physics", "2"]) == 0
    data = json.loads((out / "study_mismatch.json").read_text())
    rows = {(r["set"], r["model"]): r for r in data["rows"]}
    assert set(rows) == {(s, m) for s in ("nominal", "E x2") for m in ("m", "physics")} and data["meta"]["physics_frames"] == 2
    phys, learned = rows[("nominal", "physics")], rows[("nominal", "m")]
    assert phys["count"] == 2 and learned["count"] == 4
    assert phys["mlp_offset_max"] < 0.02 * phys["peak_median"] and learned["mlp_offset_max"] > 5 * phys["mlp_offset_max"]
    assert phys["alarm_rate"] == 0.0 and phys["coverage_90"] > 0.5 and phys["incomplete"] == 0
    assert phys["rigid_offset_max"] > 5 * phys["mlp_offset_max"] and phys["mlp_corrected"] > 0.95
    assert rows[("E x2", "physics")]["relative_vs_nominal"] == pytest.approx(
        rows[("E x2", "physics")]["relative"] / phys["relative"])
    header = (out / "study_mismatch.csv").read_text().splitlines()[0].split(",")
    assert "coverage_90" in header and "seconds_median" in header  # keys only the physics rows carry
    (tmp_path / "report").mkdir()
    section = mismatch_section(out, tmp_path / "report")
    assert "The <i>physics</i> rows" in section and "its field is the posterior mean over the held sets" in section
    assert data["meta"]["physics_estimate"] == "mean"


def test_the_study_gives_the_physics_frames_their_attached_margin(tmp_path, caplog, monkeypatch, capsys):
    """``--physics 2 --physics-known-margin`` on a store that draws the attached margin
    (-6..6 mm): a row per set with each frame's simulated margin given, as good as the searched
    row's; the set grown by 10 mm (beyond the range) gets none, said so."""
    import logging

    from dataset_helpers import tracked_retractor_store

    from tissuecast.cli.main import main
    from tissuecast.evaluate.mismatch import PHYSICS, PHYSICS_KNOWN
    from tissuecast.evaluate.mismatch_report import mismatch_section

    from tissuecast.inverse import MarkerInverse

    cfg, store, model = tracked_retractor_store(tmp_path, {"attached_margin": [-6.0, 6.0]})
    path = write_config(cfg, tmp_path / "tracked.toml")
    out = tmp_path / "study"
    given, solve = [], MarkerInverse.solve

    def recording(self, *args, **kwargs):  # what each frame is told about the margin and the estimate
        given.append(kwargs.get("attached_margin"))
        estimates.append(kwargs.get("estimate"))
        return solve(self, *args, **kwargs)

    estimates = []

    monkeypatch.setattr(MarkerInverse, "solve", recording)
    with caplog.at_level(logging.WARNING, logger="tissuecast.evaluate.mismatch"):
        assert main(["-q", "study", "mismatch", str(path), "--out", str(out), "--model", f"m={model}", "--sets",
                     "attached +5 mm,attached +10 mm", "--samples", "3", "--physics", "2", "--physics-known-margin",
                     "--physics-estimate", "likeliest"]) == 0
    data = json.loads((out / "study_mismatch.json").read_text())
    rows = {(r["set"], r["model"]): r for r in data["rows"]}
    assert {k for k in rows if k[1] == PHYSICS_KNOWN} == {("nominal", PHYSICS_KNOWN), ("attached +5 mm", PHYSICS_KNOWN)}
    assert "attached +10 mm: its attached margins (+10 to +10 mm) lie outside" in caplog.text
    # searched rows: no margin (3 sets x 2 frames); known rows: each frame its simulated one (the
    # nominal set's draws none: the nominal extent, 0 mm; the +10 mm set's lies outside: no row)
    assert given.count(None) == 6
    assert sorted(m for m in given if m is not None) == pytest.approx([0.0, 0.0, 5.0, 5.0])
    for name in ("nominal", "attached +5 mm"):
        known, searched = rows[(name, PHYSICS_KNOWN)], rows[(name, PHYSICS)]
        assert known["count"] == 2 and known["alarm_rate"] == 0.0
        assert known["mlp_offset_max"] < 0.05 * known["peak_median"] < known["rigid_offset_max"]
        assert known["mlp_offset_max"] <= 1.05 * searched["mlp_offset_max"] + 1e-3
    assert data["meta"]["physics_known_margin"] is True and data["meta"]["physics_estimate"] == "likeliest"
    assert {e for m, e in zip(given, estimates) if m is None} == {"likeliest"}  # every searched frame
    assert main(["-q", "study", "mismatch", str(path), "--out", str(out), "--model", f"m={model}",
                 "--physics-estimate", "mean"]) == 2
    assert "the estimate chooses the physics rows' field: give a number of physics frames" in capsys.readouterr().err
    (tmp_path / "report").mkdir()
    section = mismatch_section(out, tmp_path / "report")
    assert "The <i>physics, margin known</i> rows" in section and "its field is the likeliest held set's" in section
