"""Data sets of a clinical scenario with the real FEM solver (small P1 box, so the file runs in
seconds): attached face + springs + gravity change + indentation + traction LBO fields. The
store records the scenario and each sample's draws, resumes bit-identically after kill -9,
equals a Dask run, keeps the reduced-model predictor working with the indentation, records
failing samples after their retries; a model trained on it knows its scenario."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr

from tissuecast.config import with_overrides
from tissuecast.dataset import InitialGuess, open_dataset, simulate
from tissuecast.scenario import scenario_from_config, scenario_rng

from dataset_helpers import assert_same_store, done_count, small_config, write_config

N_LBO, N_TEST2, N_BASIS = 72, 4, 8

SCENARIO = {"name": "embedded", "pins": False,
            "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
            "springs": {"rule": "surface"}, "gravity": {"enabled": True},
            "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5]}}


def _config(folder, **dataset):
    # the box's bottom face attached, springs on the rest, traction LBO fields calibrated to
    # 4 mm on 2 pilots; the first 8 samples (solved from zero) build the reduced model
    ds = {"n_samples": N_LBO, "n_test2": N_TEST2, "alpha": 0.0, "calibration_samples": 2, "predictor_samples": N_BASIS}
    ds.update(dataset)
    cfg = small_config(folder, **ds)
    return with_overrides(cfg, forces={"loading": "traction", "target_max_displacement": 4.0}, scenario=SCENARIO)




@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run with local worker processes."""
    folder = tmp_path_factory.mktemp("scenario")
    cfg = _config(folder)
    path = folder / "reference.zarr"
    return cfg, path, simulate(cfg, path, progress=False)


def test_the_store_records_the_scenario_and_each_samples_draws(reference):
    cfg, path, summary = reference
    ds = open_dataset(path)
    assert summary["totals"] == {"pending": 0, "done": N_LBO + N_TEST2, "failed": 0}
    mesh, _, _, sc = scenario_from_config(cfg)
    assert ds.scenario == summary["scenario"] and ds.scenario["name"] == "embedded"
    assert ds.scenario["attached_vertices"] == len(sc.attached) > 0 and ds.scenario["pins"] == 0
    assert ds.scenario["springs"]["nodes"] == len(sc.springs)
    np.testing.assert_array_equal(ds.fixed, sc.supported)  # the attached face, no pins
    root = zarr.open_group(str(path), mode="r")
    np.testing.assert_array_equal(root["scenario/attached"][:], sc.attached)
    np.testing.assert_array_equal(root["scenario/spring_stiffness"][:], sc.springs.stiffness)
    # each sample's stored draws are those its seed makes (scenario_rng), test-2 samples included
    draws = ds.draws
    assert set(draws) == {"gravity_direction", "indent_centre", "indent_depth", "indent_slide", "indent_displacement"}
    for i in (0, 17, N_LBO + 1):
        d = sc.draw(scenario_rng(int(ds.seed[i])))
        np.testing.assert_array_equal(draws["gravity_direction"][i], d.gravity_direction)
        assert draws["indent_centre"][i] == d.indentation.centre
        np.testing.assert_array_equal(draws["indent_displacement"][i], d.indentation.displacement)
        # the patch moved as prescribed
        u = ds.displacements[i].astype(np.float64)
        patch = d.indentation.vertices
        np.testing.assert_allclose(u[patch], np.tile(d.indentation.displacement, (len(patch), 1)),
                                   atol=1e-5)
        assert not u[ds.fixed].any()  # the attached face does not move
    depth = draws["indent_depth"]
    assert ((0.5 <= depth) & (depth <= 1.5)).all() and len(np.unique(draws["indent_centre"])) > 10


def test_calibration_and_deformation_of_the_scenario(reference):
    _, path, _ = reference
    ds = open_dataset(path)
    cal = ds.calibration
    assert cal["converged"] and cal["pilots"] == [0, 1]
    from tissuecast.dataset.calibrate import RTOL

    assert np.quantile(ds.max_displacement[:2].astype(np.float64), 0.9) == pytest.approx(4.0, rel=RTOL + 1e-3)
    # held by its surroundings the box strains: the best rigid fit leaves most of the peak
    share = ds.summary(deformation=True)["nonrigid_share"]
    assert share["median"] > 0.5


def test_the_predictor_starts_samples_with_an_indentation_near_their_solution(reference):
    _, path, _ = reference
    ds = open_dataset(path)
    later = np.arange(N_BASIS, ds.n_samples)
    assert ds.summary()["predictor"]["model"]["snapshots"] == N_BASIS
    # every later sample (each with its own indentation) started from the reduced model's
    # prediction, and converged in fewer Newton iterations than the samples solved from zero
    assert (ds.predicted[later] == InitialGuess.REDUCED_MODEL).all()
    cold = ds.predicted == InitialGuess.ZERO
    assert cold.sum() > 0
    assert ds.iterations[later].mean() < ds.iterations[cold].mean()




def test_resume_after_kill_is_bit_identical(reference, tmp_path):
    cfg, ref_path, _ = reference
    cfg_file = write_config(cfg, tmp_path / "cfg.toml")
    store = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "tissuecast.cli.main", "-q", "simulate", str(cfg_file), "--store", str(store),
           "--no-progress"]
    # the rerun's parent process runs its BLAS on one thread (this process: as many as it has);
    # the parent's solves (the calibration's first alpha) must not depend on it
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 120
    while done_count(store) < N_BASIS + 4 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-500:]}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert N_BASIS + 4 <= done_count(store) < N_LBO + N_TEST2
    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert rerun.returncode == 0, rerun.stderr
    assert_same_store(store, ref_path)


def test_dask_cluster_gives_theassert_same_store(reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    cfg, ref_path, _ = reference
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        simulate(cfg, tmp_path / "dask.zarr", progress=False, scheduler=cluster.scheduler_address)
    assert_same_store(tmp_path / "dask.zarr", ref_path)


def test_failing_scenario_samples_are_retried_then_recorded(tmp_path):
    # one increment of at most 2 Newton iterations at the full load: the samples cannot converge
    cfg = _config(tmp_path, n_samples=4, n_test2=0, alpha=4.0, predictor="none")
    cfg = with_overrides(cfg, solver={"max_increments": 1, "max_iterations": 2, "retries": 1})
    summary = simulate(cfg, tmp_path / "fail.zarr", progress=False, workers=1)
    ds = open_dataset(tmp_path / "fail.zarr")
    failed = ds.select(status="failed", split=None)
    assert len(failed) > 0 and summary["totals"]["failed"] == len(failed) and set(ds.failures) == set(failed.tolist())
    reason = ds.failures[int(failed[0])]
    assert "attempt 1: ConvergenceError" in reason and "attempt 2: ConvergenceError" in reason
    assert (ds.attempts[failed] == 2).all() and np.isnan(ds.displacements[failed]).all()
    # a failed sample still records its draws
    assert (ds.draws["indent_centre"][failed] >= 0).all()


def test_a_model_knows_its_scenario_and_the_evaluation_states_it(reference, tmp_path):
    from tissuecast.evaluate.evaluation import evaluate_model
    from tissuecast.evaluate.report import format_evaluation, write_report
    from tissuecast.surrogate import DeformationModel

    _, path, _ = reference
    ds = open_dataset(path)
    model = DeformationModel.from_dataset(ds, n_components=4, epochs=20, patience=0)
    assert model.scenario == ds.scenario
    model.save(tmp_path / "m")
    again = DeformationModel.load(tmp_path / "m")
    assert again.scenario == ds.scenario
    evaluation = evaluate_model(again, ds)
    text = format_evaluation(evaluation)
    assert "scenario: embedded" in text
    assert "supports: attached region of" in text and "elastic support on 110 surface vertices" in text
    assert "loads: LBO surface forces; gravity change" in text and "one indentation (patch radius 11 mm" in text
    page = write_report(tmp_path / "report", again, ds, evaluation, renders=0).read_text()
    assert "<h2>Scenario</h2>" in page and "elastic support on 110 surface vertices" in page


def test_a_store_with_markers_of_an_earlier_rule_resumes_with_its_own(reference, tmp_path, caplog):
    """Without pins the markers do not enter the simulation: a store whose markers differ from
    what the config chooses now (an earlier marker rule) is continued, keeping its markers."""
    import logging
    import shutil

    cfg, ref_path, _ = reference
    path = tmp_path / "older.zarr"
    shutil.copytree(ref_path, path)
    root = zarr.open_group(str(path), mode="r+")
    now = np.asarray(root["markers"][...])
    root["markers"][:] = now[::-1]  # as an earlier rule might have ordered them
    with caplog.at_level(logging.INFO, logger="tissuecast.dataset.store"):
        simulate(cfg, path, progress=False)
    assert "the store keeps its own" in caplog.text
    np.testing.assert_array_equal(open_dataset(path).markers, now[::-1])


def test_a_store_without_pins_resumes_under_other_markers_and_trains_with_the_configs(reference, tmp_path):
    """Without pins the [markers] settings change no sample: a store resumes under another
    marker count (with pins it is refused, tests/dataset/test_dataset_store.py) and a model
    trained from that config has the markers the config chooses, not the store's."""
    import shutil

    from tissuecast.app.pipeline import train_from_store
    from tissuecast.markers import markers_from_config

    cfg, ref_path, _ = reference
    path = tmp_path / "copy.zarr"
    shutil.copytree(ref_path, path)
    stored = np.asarray(open_dataset(path).markers)
    other = with_overrides(cfg, markers={"count": len(stored) + 2, "min_distance": 1.0},
                           surrogate={"epochs": 5, "patience": 0, "n_components": 4})
    assert simulate(other, path, progress=False)["run"]["solved"] == 0
    np.testing.assert_array_equal(open_dataset(path).markers, stored)  # the store keeps its own
    model, ds = train_from_store(other, path)
    chosen = markers_from_config(ds.mesh, other.markers, held=ds.scenario_arrays["attached"])
    assert len(chosen) == len(stored) + 2 and not np.isin(chosen, ds.scenario_arrays["attached"]).any()
    np.testing.assert_array_equal(model.markers, chosen)


def test_a_store_with_springs_of_an_earlier_lumping_goes_on_with_its_own(reference, tmp_path, caplog):
    """A store whose springs differ from what its config gives now (P2 springs lumped by
    integral(N_a) dA before HRZ became the default) says so and keeps solving with its own."""
    import logging
    import shutil

    from tissuecast.dataset import recipe_from_store

    cfg, ref_path, _ = reference
    path = tmp_path / "older.zarr"
    shutil.copytree(ref_path, path)
    root = zarr.open_group(str(path), mode="r+")
    older = 0.5 * np.asarray(root["scenario/spring_stiffness"][...])
    root["scenario/spring_stiffness"][:] = older
    with caplog.at_level(logging.WARNING, logger="tissuecast.dataset.store"):
        simulate(cfg, path, progress=False)
    assert "holds springs other than this config gives" in caplog.text
    np.testing.assert_array_equal(recipe_from_store(path).scenario_arrays["spring_stiffness"], older)
    caplog.clear()
    same = tmp_path / "same.zarr"
    shutil.copytree(ref_path, same)
    with caplog.at_level(logging.WARNING, logger="tissuecast.dataset.store"):
        simulate(cfg, same, progress=False)  # its own springs: no warning
    assert "holds springs" not in caplog.text


def test_export_inp_of_a_stored_scenario_sample(reference, tmp_path, capsys):
    """``export-inp STORE --sample K`` writes the deck of that sample with the stored scenario:
    springs, the gravity change and the indentation's prescribed displacements."""
    from tissuecast.cli.main import main

    _, ref_path, _ = reference
    ds = open_dataset(ref_path)
    arrays = ds.scenario_arrays
    assert arrays is not None and len(arrays["attached"]) > 0 and len(arrays["spring_nodes"]) > 0
    deck = tmp_path / "sample5.inp"
    assert main(["export-inp", str(ref_path), str(deck), "--sample", "5"]) == 0
    text = deck.read_text()
    assert "SPRING1" in text and "*DLOAD" in text and "GRAV" in text and "*BOUNDARY" in text
    assert main(["export-inp", str(ref_path), str(deck), "--sample", str(len(ds))]) == 2
    assert f"--sample {len(ds)} is outside" in capsys.readouterr().err


UNCERTAIN = {"youngs_modulus": [0.5, 2.0], "poisson_ratio": [0.40, 0.49], "spring_normal": [0.25, 4.0],
             "spring_tangential": [0.25, 4.0], "density": [0.8, 1.2], "attached_margin": [-3.0, 3.0]}


@pytest.fixture(scope="module")
def uncertain(tmp_path_factory):
    """The scenario with every uncertain parameter drawn per sample."""
    folder = tmp_path_factory.mktemp("uncertain")
    cfg = with_overrides(_config(folder, n_samples=24, n_test2=2, predictor_samples=6),
                         scenario={"uncertain": UNCERTAIN})
    path = folder / "reference.zarr"
    return cfg, path, simulate(cfg, path, progress=False)


def test_a_store_records_each_samples_drawn_parameters_and_solves_with_them(uncertain):
    from tissuecast.scenario.parameters import parameter_rng

    cfg, path, summary = uncertain
    ds = open_dataset(path)
    assert summary["totals"]["failed"] == 0 and ds.scenario["uncertain"]["youngs_modulus"] == [0.5, 2.0]
    params = ds.parameters
    assert set(params) == {"youngs_modulus", "poisson_ratio", "density", "spring_normal", "spring_tangential",
                           "attached_margin"}
    _, _, _, sc = scenario_from_config(cfg)
    for i in (0, 9, 25):
        p = sc.uncertain.draw(parameter_rng(int(ds.seed[i])))
        assert {k: params[k][i] for k in params} == p.record()
        band = sc.uncertain.extra_held(p, sc.attached)
        assert not ds.displacements[i][band].any()  # the drawn attached extent does not move
    assert 0.5 <= params["youngs_modulus"].min() and params["youngs_modulus"].max() <= 2.0
    # a stored sample is the solve with its own parameters, not with the nominal ones
    from tissuecast.fem import Solver

    i = int(np.argmax(np.abs(np.log(params["youngs_modulus"][:24]))))
    x = sc.sample(int(ds.seed[i]), float(ds.alpha[i]))
    solver = Solver(sc.problem(), cfg.solver)
    own = solver.with_parameters(*x.solver_parameters).solve(x.surface, **x.solve_keywords()).displacement
    nominal = solver.solve(x.surface, **x.solve_keywords()).displacement
    stored = ds.displacements[i].astype(np.float64)
    peak = np.abs(stored).max()
    assert np.abs(stored - own).max() < 0.01 * peak < 0.2 * np.abs(stored - nominal).max()


def test_an_uncertain_store_is_the_same_on_dask_and_after_a_kill(uncertain, tmp_path):
    distributed = pytest.importorskip("distributed")
    cfg, ref_path, _ = uncertain
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        simulate(cfg, tmp_path / "dask.zarr", progress=False, scheduler=cluster.scheduler_address)
    assert_same_store(tmp_path / "dask.zarr", ref_path)


def test_dataset_info_prints_each_loads_share(reference, capsys):
    from tissuecast.cli.main import main

    _, path, _ = reference
    assert main(["dataset", "info", str(path), "--load-shares", "2"]) == 0
    out = capsys.readouterr().out
    assert "each load alone" in out and "surface field: peak" in out and "gravity change: peak" in out
    assert "instrument: peak" in out and "% of all loads' peak" in out
