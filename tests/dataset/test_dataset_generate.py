"""Data-set generation with the real FEM solver: exact resume after kill -9, Dask equality,
failure recording, magnitude calibration (small P1 box mesh, so the file runs in seconds)."""

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
from tissuecast.dataset import InitialGuess, SampleStatus, open_dataset, simulate

from dataset_helpers import assert_same_store, done_count, small_config, write_config

N_LBO, N_TEST2, N_BASIS = 120, 9, 16


def _config(folder):
    # calibrated to a 4 mm target on 2 pilot samples; 120 + 9 samples of ~0.05 s each; the
    # first 16 samples (solved from zero) build the reduced-model predictor of the others
    cfg = small_config(folder, n_samples=N_LBO, n_test2=N_TEST2, alpha=0.0, calibration_samples=2)
    return with_overrides(cfg, dataset={"predictor_samples": N_BASIS})




@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run with local worker processes."""
    folder = tmp_path_factory.mktemp("gen")
    cfg = with_overrides(_config(folder), forces={"target_max_displacement": 4.0})
    path = folder / "reference.zarr"
    summary = simulate(cfg, path, progress=False)
    return cfg, path, summary


def test_reference_run_is_complete_and_calibrated(reference):
    cfg, path, summary = reference
    ds = open_dataset(path)
    assert summary["totals"]["pending"] == 0
    assert summary["totals"]["done"] >= 0.9 * ds.n_samples
    cal = ds.calibration
    assert cal["converged"] and cal["pilots"] == [0, 1]
    # the rule: the 0.9 quantile of the pilots' max displacement is the target (within RTOL)
    from tissuecast.dataset.calibrate import RTOL

    pilot_max = ds.max_displacement[:2].astype(np.float64)
    assert np.quantile(pilot_max, 0.9) == pytest.approx(4.0, rel=RTOL + 1e-3)
    assert np.all(ds.alpha[ds.status > 0] == cal["alpha"])
    # the whole data set lands near the target: median within a factor 2, most samples converge
    st = summary["max_displacement"]
    assert 2.0 < st["median"] < 8.0
    assert ds.increments[ds.status == SampleStatus.DONE].min() >= 1




@pytest.mark.parametrize("kill_at", [8, 60], ids=["while-building-the-predictor", "after-it"])
def test_resume_after_kill_is_bit_identical(reference, tmp_path, kill_at):
    cfg, ref_path, _ = reference
    cfg_file = write_config(cfg, tmp_path / "cfg.toml")
    store = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "tissuecast.cli.main", "-q", "simulate", str(cfg_file), "--store", str(store),
           "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while done_count(store) < kill_at and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-500:]}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = done_count(store)
    assert kill_at <= done < N_LBO + N_TEST2, done
    assert open_dataset(store).summary()["totals"]["pending"] > 0  # readable after kill -9
    # workers notice that their parent is gone and exit by themselves
    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert_same_store(store, ref_path)


@pytest.mark.parametrize("how", ["SIGTERM", "Ctrl+C"])
def test_a_stopped_run_exits_cleanly_and_resumes_bit_identically(reference, tmp_path, how):
    """SIGTERM (kill, timeout) to the run, or SIGINT to its whole process group (Ctrl+C in a
    terminal): the run stops its workers and exits with 143 / 130, without tracebacks or leaked
    semaphores, and the same command completes the store bit for bit."""
    cfg, ref_path, _ = reference
    cfg_file = write_config(cfg, tmp_path / "cfg.toml")
    store = tmp_path / "stopped.zarr"
    cmd = [sys.executable, "-m", "tissuecast.cli.main", "-q", "simulate", str(cfg_file), "--store", str(store),
           "--no-progress"]
    # as from a terminal: SIGINT at its default (a shell without job control starts background
    # jobs, and so a test run started with `&`, with SIGINT ignored, which children inherit)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while done_count(store) < 30 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before it could be stopped: {proc.stderr.read()[-500:]}"
    if how == "SIGTERM":
        os.kill(proc.pid, signal.SIGTERM)
    else:
        os.killpg(proc.pid, signal.SIGINT)
    stderr = proc.communicate(timeout=60)[1]
    assert proc.returncode == (143 if how == "SIGTERM" else 130), stderr
    assert "leaked" not in stderr and "Traceback" not in stderr, stderr
    assert ("terminated (SIGTERM)" if how == "SIGTERM" else "interrupted") in stderr
    assert 30 <= done_count(store) < N_LBO + N_TEST2
    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert "leaked" not in rerun.stderr
    assert_same_store(store, ref_path)


def test_predictor_starts_later_samples_near_their_solution(reference):
    cfg, path, _ = reference
    ds = open_dataset(path)
    done = ds.status == SampleStatus.DONE
    model = ds.summary()["predictor"]["model"]
    assert model["snapshots"] == N_BASIS and 1 <= model["modes"] <= N_BASIS and model["fit_error"] <= 0.01
    basis = np.arange(N_LBO + N_TEST2) < N_BASIS
    pilots = np.arange(N_LBO + N_TEST2) < 2
    # the basis samples are solved from zero, the calibration pilots from their previous round
    assert (ds.predicted[basis & ~pilots] == InitialGuess.ZERO).all()
    assert (ds.predicted[pilots] == InitialGuess.PREVIOUS_ROUND).all()
    warm = done & ~basis & (ds.predicted == InitialGuess.REDUCED_MODEL)
    assert warm.sum() >= 0.9 * (~basis).sum()
    # from the prediction the full solver needs fewer iterations than from zero
    assert ds.iterations[warm].mean() < 0.8 * ds.iterations[done & basis].mean()
    # ... and reaches the same equilibrium: re-solve some of them from zero
    from tissuecast.dataset.generate import setup_from_config
    from tissuecast.fem import Solver, build_problem
    from tissuecast.scenario.resolve import base_material

    mesh, _, fixed = setup_from_config(cfg)
    solver = Solver(build_problem(mesh, base_material(cfg), fixed, order=cfg.solver.order), cfg.solver)
    for i in np.flatnonzero(warm)[:5]:
        cold = solver.solve(ds.forces[i].astype(np.float64)).displacement
        peak = np.abs(cold).max()
        assert np.abs(ds.displacements[i] - cold).max() <= 2e-3 * peak


def test_basis_samples_start_from_an_interim_model_of_the_pilots(tmp_path):
    """With >= MIN_INTERIM calibration pilots, the other reduced-model basis samples start from
    an interim model of the pilots' solutions: fewer iterations than from zero, the same
    equilibrium, and guesses that depend on the pilots' snapshots alone (what a resumed run
    has), so a resume solves them the same."""
    import shutil

    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.generate import setup_from_config
    from tissuecast.dataset.reduced_predictor import MIN_INTERIM, _interim_guesses, _pilot_rows, basis_samples
    from tissuecast.dataset.store import StoreWriter
    from tissuecast.dataset.worker import Task
    from tissuecast.fem import Solver, build_problem
    from tissuecast.scenario.resolve import base_material

    cfg = small_config(tmp_path, n_samples=24, n_test2=0, alpha=0.0, calibration_samples=MIN_INTERIM)
    cfg = with_overrides(cfg, dataset={"predictor_samples": 14}, forces={"target_max_displacement": 4.0})
    path = tmp_path / "interim.zarr"
    simulate(cfg, path, progress=False)
    ds = open_dataset(path)
    assert (ds.predicted[:MIN_INTERIM] == InitialGuess.PREVIOUS_ROUND).all()
    interim = np.arange(MIN_INTERIM, 14)
    assert (ds.predicted[interim] == InitialGuess.INTERIM_MODEL).all()
    assert ds.summary()["predictor"]["from_interim_model"]["samples"] == len(interim)
    mesh, _, fixed = setup_from_config(cfg)
    solver = Solver(build_problem(mesh, base_material(cfg), fixed, order=cfg.solver.order), cfg.solver)
    cold = [solver.solve(ds.forces[i].astype(np.float64)) for i in interim]
    assert ds.iterations[interim].sum() < 0.8 * sum(c.iterations for c in cold)
    for i, c in zip(interim, cold):
        assert np.abs(ds.displacements[i] - c.displacement).max() <= 2e-3 * np.abs(c.displacement).max()
    # the guesses use the pilots' snapshots only: the same with the others' rows emptied
    copy = tmp_path / "resumed.zarr"
    shutil.copytree(path, copy)
    root = zarr.open_group(str(copy), mode="r+")
    rows = np.asarray(root["reduced/samples"][...])
    for k in np.flatnonzero(rows >= MIN_INTERIM):
        root["reduced/snapshots"][k] = np.nan
    guesses = []
    for store in (path, copy):
        writer = StoreWriter.open(store)
        recipe = recipe_from_store(writer)
        tasks = [Task(int(i), int(ds.seed[i]), float("nan"), ds.calibration["alpha"]) for i in interim]
        problem = recipe.problem()
        pilot_rows = _pilot_rows(writer, writer.snapshot_rows(basis_samples(writer, cfg), len(problem.nodes)),
                                 writer.snapshot_done())
        assert len(pilot_rows) == MIN_INTERIM
        guesses.append(_interim_guesses(writer, cfg, recipe, problem, tasks, pilot_rows))
    assert len(basis_samples(StoreWriter.open(copy), cfg)) == 14
    for a, b in zip(*guesses):
        assert a.guess_code == b.guess_code == InitialGuess.INTERIM_MODEL
        np.testing.assert_array_equal(a.guess, b.guess)


def test_first_round_pilots_start_warm_from_zero_only_where_that_changes_the_path(reference):
    """The first calibration round's pilots get zero displacements as their guess (one
    increment preconditioned by the shared stiffness at zero) with the krylov strategy and
    its reference preconditioner on the paper's set-up; not otherwise."""
    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.calibrate import warm_zero

    cfg, path, _ = reference
    recipe = recipe_from_store(path)
    scenario = recipe.scenario()
    assert scenario.hangs_on_pins
    zero = warm_zero(cfg.solver, scenario)
    assert zero is not None and zero.shape == (len(recipe.problem().nodes), 3) and not zero.any()
    assert warm_zero(with_overrides(cfg, solver={"strategy": "newton"}).solver, scenario) is None
    assert warm_zero(with_overrides(cfg, solver={"reference_preconditioner": False}).solver, scenario) is None
    # a body held otherwise (here: with gravity too, so not hanging on its pins alone) starts cold
    gravity = with_overrides(cfg, scenario={"gravity": {"enabled": True}})
    from tissuecast.scenario import restore_scenario

    held = restore_scenario(scenario.mesh, gravity, recipe.scenario_arrays, recipe.basis)
    assert not held.hangs_on_pins and warm_zero(gravity.solver, held) is None


def test_calibration_pilots_start_from_their_previous_round(reference):
    cfg, path, _ = reference
    ds = open_dataset(path)
    rounds = ds.calibration["rounds"]
    assert len(rounds) >= 2
    from tissuecast.dataset.generate import setup_from_config
    from tissuecast.fem import Solver, build_problem
    from tissuecast.scenario.resolve import base_material

    mesh, _, fixed = setup_from_config(cfg)
    solver = Solver(build_problem(mesh, base_material(cfg), fixed, order=cfg.solver.order), cfg.solver)
    for i in (0, 1):  # the last round's pilots are samples 0 and 1, at the same equilibrium as from zero
        assert ds.predicted[i] == InitialGuess.PREVIOUS_ROUND
        cold = solver.solve(ds.forces[i].astype(np.float64))
        assert np.abs(ds.displacements[i] - cold.displacement).max() <= 2e-3 * np.abs(cold.displacement).max()
        assert ds.iterations[i] < cold.iterations


def test_interrupted_before_the_calibration_record_calibrates_again_identically(reference, tmp_path, monkeypatch):
    cfg, ref_path, _ = reference
    from tissuecast.dataset.store import StoreWriter

    store = tmp_path / "cut.zarr"
    real = StoreWriter.set_calibration

    def killed(self, record):
        raise KeyboardInterrupt  # the pilots are written, the calibration record is not

    monkeypatch.setattr(StoreWriter, "set_calibration", killed)
    with pytest.raises(KeyboardInterrupt):
        simulate(cfg, store, progress=False)
    ds = open_dataset(store)
    assert ds.calibration is None and (ds.status[:2] == 1).all() and (ds.status[2:] == 0).all()
    monkeypatch.setattr(StoreWriter, "set_calibration", real)
    simulate(cfg, store, progress=False)
    assert_same_store(store, ref_path)


def test_batches_are_chunks_of_the_generation_order_fixed_in_the_store(reference):
    cfg, path, _ = reference

    from tissuecast.dataset.sample_plan import generation_order

    ds = open_dataset(path)
    root = zarr.open_group(str(path), mode="r")
    size = cfg.dataset.batch_size
    assert size > 1 and root.attrs["batches"]["size"] == size
    batch_of = root["samples/batch"][...]
    basis = np.arange(N_LBO + N_TEST2) < N_BASIS
    assert (batch_of[basis] == -1).all()  # solved before the reduced model: alone
    order = generation_order(ds.split, np.flatnonzero(~basis))
    np.testing.assert_array_equal(batch_of[order], np.arange(len(order)) // size)
    assert root.attrs["batches"]["count"] == -(-len(order) // size)


def test_batch_size_may_change_once_the_store_fixed_its_batches(reference, tmp_path):
    """The stored batches decide once fixed: another batch_size continues the store (e.g. one
    made when the default was 8); before that, batch_size is part of the data config."""
    import shutil

    from tissuecast.errors import DatasetError

    cfg, ref_path, _ = reference
    path = tmp_path / "fixed.zarr"
    shutil.copytree(ref_path, path)
    other = with_overrides(cfg, dataset={"batch_size": cfg.dataset.batch_size + 3})
    simulate(other, path, progress=False)  # accepted: nothing pending, the store unchanged
    assert zarr.open_group(str(path), mode="r").attrs["batches"]["size"] == cfg.dataset.batch_size
    assert_same_store(path, ref_path)
    unfixed = tmp_path / "unfixed.zarr"
    shutil.copytree(ref_path, unfixed)
    del zarr.open_group(str(unfixed), mode="r+").attrs["batches"]
    with pytest.raises(DatasetError, match="dataset.batch_size"):
        simulate(other, unfixed, progress=False)


def test_a_partly_written_batch_is_solved_again_in_full(reference, tmp_path):
    """A run stopped between two flushes can leave a batch partly written: the next run
    solves the whole batch again (its done samples too, not written again), so the missing
    samples get the bits of the uninterrupted run."""
    import shutil

    cfg, ref_path, _ = reference
    store = tmp_path / "partial.zarr"
    shutil.copytree(ref_path, store)
    root = zarr.open_group(str(store), mode="r+")
    batch_of = root["samples/batch"][...]
    gone = np.concatenate([np.flatnonzero(batch_of == 2)[1::2], np.flatnonzero(batch_of == batch_of.max())[:1]])
    status = root["samples/status"][...]
    status[gone] = SampleStatus.PENDING
    root["samples/status"][...] = status
    for i in gone:
        root["samples/displacements"][i] = np.nan
    failures = dict(root.attrs["failures"])
    root.attrs["failures"] = {k: v for k, v in failures.items() if int(k) not in set(gone.tolist())}
    summary = simulate(cfg, store, progress=False)
    assert summary["run"]["solved"] == len(gone) and summary["totals"]["pending"] == 0
    assert_same_store(store, ref_path)


def test_batch_size_one_gives_the_same_samples_to_round_off(reference, tmp_path):
    """One sample at a time instead of batches: the same samples, iterations and failures;
    the displacements differ by the round-off of the gathered solves only."""
    cfg, ref_path, _ = reference
    single = tmp_path / "single.zarr"
    simulate(with_overrides(cfg, dataset={"batch_size": 1}), single, progress=False)
    a, b = open_dataset(ref_path), open_dataset(single)
    assert "batches" not in zarr.open_group(str(single), mode="r").attrs
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.predicted, b.predicted)
    done = a.status == SampleStatus.DONE
    assert (a.iterations[done] == b.iterations[done]).mean() >= 0.95
    peak = np.abs(a.displacements[done]).max()
    assert np.abs(a.displacements[done] - b.displacements[done]).max() <= 1e-5 * peak
    np.testing.assert_array_equal(a.forces, b.forces)


def test_samples_failing_in_a_batch_go_on_alone_and_are_recorded(reference, tmp_path):
    """A sample whose try from the prediction fails in its batch is solved alone from zero
    (GUESS_FAILED, the batch's reason kept) and, failing that too, recorded failed after its
    cautious retries with every reason; the other samples of the batch are unaffected."""
    from dataset_helpers import _fingerprint

    cfg, ref_path, _ = reference
    store = tmp_path / "flaky.zarr"
    simulate(cfg, store, progress=False, solver_factory="dataset_helpers:batch_failing_solver_factory")
    ref, ds = open_dataset(ref_path), open_dataset(store)
    batch_of = zarr.open_group(str(store), mode="r")["samples/batch"][...]
    sizes = np.bincount(batch_of[batch_of >= 0])
    batched = np.flatnonzero((batch_of >= 0) & (sizes[np.maximum(batch_of, 0)] > 1))  # a batch of one goes alone
    # the fingerprints of the float64 fields the workers solved (the stored float32 copies can
    # round across a multiple of 4)
    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.worker import SampleContext, Task

    ctx = SampleContext(recipe_from_store(store))
    alpha = float(ds.calibration["alpha"])
    fp = np.array([_fingerprint(ctx.inputs(Task(int(i), int(ds.seed[i]), float(ds.beta[i]), alpha)).forces)
                   for i in batched])
    flaky, doomed = batched[fp % 4 == 0], batched[(fp % 4 == 0) & (fp % 3 == 0)]
    rescued = np.setdiff1d(flaky, doomed)
    assert len(rescued) and len(doomed), "the test needs samples of both kinds"
    for i in rescued:
        assert ds.status[i] == SampleStatus.DONE and ds.predicted[i] == InitialGuess.GUESS_FAILED
        cold = ref.displacements[i]
        assert np.abs(ds.displacements[i] - cold).max() <= 2e-3 * np.abs(cold).max()
    for i in doomed:
        assert ds.status[i] == SampleStatus.FAILED and ds.attempts[i] == cfg.solver.retries + 1
        reason = ds.failures[int(i)]
        assert reason.startswith("attempt 1 from the prediction, in a batch of")
        assert reason.count("made to fail alone too") == cfg.solver.retries + 1, reason
    others = np.setdiff1d(batched, flaky)
    others = others[ref.status[others] == SampleStatus.DONE]
    assert (ds.status[others] == SampleStatus.DONE).all()
    assert (ds.predicted[others] == InitialGuess.REDUCED_MODEL).all()
    peak = np.abs(ref.displacements[others]).max()
    assert np.abs(ds.displacements[others] - ref.displacements[others]).max() <= 1e-5 * peak


def test_no_predictor_solves_every_sample_from_zero(tmp_path):
    cfg = with_overrides(small_config(tmp_path, n_samples=6, n_test2=0, alpha=0.04, workers=1),
                         dataset={"predictor": "none", "predictor_samples": 2})
    simulate(cfg, tmp_path / "cold.zarr", progress=False)
    ds = open_dataset(tmp_path / "cold.zarr")
    assert (ds.status == SampleStatus.DONE).all() and (ds.predicted == InitialGuess.ZERO).all()
    assert ds.summary()["predictor"]["model"] is None


def _start_dask_cluster(folder, workers: int = 2):
    """``dask scheduler`` and ``workers`` x ``dask worker`` started from the command line, bound to
    127.0.0.1 on free ports; returns (scheduler address, the processes)."""
    import json

    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    address_file = folder / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--scheduler-file",
                               str(address_file), *common], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    deadline = time.monotonic() + 60
    while not address_file.exists() and time.monotonic() < deadline and procs[0].poll() is None:
        time.sleep(0.05)
    assert address_file.exists(), "dask scheduler did not start"
    time.sleep(0.1)  # the file is written whole, but give it a moment
    address = json.loads(address_file.read_text())["address"]
    for _ in range(workers):
        procs.append(subprocess.Popen([dask, "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
                                       "--nthreads", "1", *common], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
    return address, procs


def _wait_for_workers(address: str, count: int) -> None:
    import distributed

    with distributed.Client(address, timeout="30s") as client:
        client.wait_for_workers(count, timeout=60)


def test_dask_cluster_gives_the_same_store(reference, tmp_path):
    """A real cluster: scheduler and two workers from the command line, `tissuecast simulate
    --scheduler` as a user runs it; the store equals the local run's bit for bit."""
    pytest.importorskip("distributed")
    cfg, ref_path, _ = reference
    address, procs = _start_dask_cluster(tmp_path)
    try:
        assert address.startswith("tcp://127.0.0.1:")
        _wait_for_workers(address, 2)
        cfg_file = write_config(cfg, tmp_path / "cfg.toml")
        run = subprocess.run([sys.executable, "-m", "tissuecast.cli.main", "simulate", str(cfg_file), "--store",
                              str(tmp_path / "dask.zarr"), "--scheduler", address, "--no-progress"],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        assert f"Dask cluster {address} (2 workers)" in run.stdout
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    assert_same_store(tmp_path / "dask.zarr", ref_path)


def test_non_converging_samples_are_recorded_failed(tmp_path):
    # one increment of at most 3 Newton iterations at the full load: most samples cannot converge
    cfg = small_config(tmp_path, n_samples=8, n_test2=0, alpha=0.08)
    cfg = with_overrides(cfg, solver={"max_increments": 1, "max_iterations": 3, "retries": 1})
    summary = simulate(cfg, tmp_path / "fail.zarr", progress=False, workers=1)
    ds = open_dataset(tmp_path / "fail.zarr")
    failed = ds.select(status="failed", split=None)
    assert len(failed) > 0 and summary["totals"]["failed"] == len(failed)
    assert set(ds.failures) == set(failed.tolist())
    reason = ds.failures[int(failed[0])]
    assert "attempt 1: ConvergenceError" in reason and "attempt 2: ConvergenceError" in reason
    assert (ds.attempts[failed] == 2).all() and (ds.load_fraction[failed] < 1).all()
    assert np.isnan(ds.displacements[failed]).all()
    for split in ("train", "valid", "test1"):
        assert not set(ds.select(split)) & set(failed)


def test_simulate_cli_creates_continues_and_refuses(tmp_path, capsys):
    from tissuecast.cli.main import main

    cfg_file = write_config(small_config(tmp_path, alpha=0.04, workers=1), tmp_path / "c.toml")
    store = tmp_path / "cli.zarr"
    args = ["simulate", str(cfg_file), "--store", str(store), "--samples", "5", "--test2", "2", "--no-progress"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "this run: 7 samples" in out and "train" in out
    ds = open_dataset(store)
    assert len(ds) == 7 and ds.config.dataset.n_samples == 5 and (ds.status == SampleStatus.DONE).all()
    assert main(args) == 0
    assert "this run: 0 samples" in capsys.readouterr().out
    assert main([a if a != "5" else "6" for a in args]) == 2  # --samples 6 on a 5-sample store
    err = capsys.readouterr().err
    assert "dataset.n_samples: 5 in the store, 6 now" in err and "tissuecast simulate STORE" in err
    assert main(["simulate", str(store), "--no-progress"]) == 0  # the store continues with its own config
    assert "this run: 0 samples" in capsys.readouterr().out
    assert main(["config", "show", str(store), "--no-comments"]) == 0
    assert "n_samples = 5" in capsys.readouterr().out


def test_retries_take_a_different_more_cautious_path():
    from tissuecast.config import SolverConfig
    from tissuecast.dataset.worker import retry_solver_config

    base = SolverConfig()
    assert retry_solver_config(base, 0) is base
    r1, r2 = retry_solver_config(base, 1), retry_solver_config(base, 2)
    assert base.strategy == "krylov" and r1.strategy == r2.strategy == "newton"
    assert r1.initial_increment == base.initial_increment / 4 and r2.min_increment == base.min_increment / 16
    assert (r1.max_iterations, r2.max_iterations) == (2 * base.max_iterations, 4 * base.max_iterations)
    assert (r1.max_increments, r2.max_increments) == (2 * base.max_increments, 4 * base.max_increments)


def test_workers_limit_every_blas_to_one_thread():
    """Whatever the environment says (OPENBLAS_NUM_THREADS=2 made a Dask run's store differ
    from a local one), a worker runs every BLAS it loaded on one thread."""
    import subprocess
    import sys

    code = (
        "import threadpoolctl\n"
        "from tissuecast.dataset.executors import single_threaded_blas\n"
        "single_threaded_blas()\n"
        "info = threadpoolctl.threadpool_info()\n"
        "assert info, 'no BLAS found'\n"
        "print(sorted({i['num_threads'] for i in info if i['user_api'] == 'blas'}))\n"
    )
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2", OMP_NUM_THREADS="2")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.strip() == "[1]"


def test_automatic_workers_are_the_usable_cpus_within_the_available_memory(monkeypatch):
    """``dataset.workers = 0``: one worker per CPU the process may use (its affinity mask), no
    more than the available memory holds at ``batch_memory`` GiB each, at least one."""
    from tissuecast.dataset import executors

    monkeypatch.setattr(executors.os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    monkeypatch.setattr(executors, "_available_memory_gib", lambda: 30.0)
    assert executors.default_workers() == 16
    assert executors.default_workers(4.0) == 7
    assert executors.default_workers(64.0) == 1
    monkeypatch.setattr(executors, "_available_memory_gib", lambda: None)  # not Linux: no cap
    assert executors.default_workers(4.0) == 16
    monkeypatch.delattr(executors.os, "sched_getaffinity", raising=False)  # no affinity masks
    monkeypatch.setattr(executors.os, "cpu_count", lambda: 3)
    assert executors.default_workers(4.0) == 3


def test_available_memory_is_read_from_proc_meminfo():
    from tissuecast.dataset import executors

    gib = executors._available_memory_gib()
    if not os.path.exists("/proc/meminfo"):
        assert gib is None
        return
    with open("/proc/meminfo") as f:
        total = next(int(line.split()[1]) for line in f if line.startswith("MemTotal:")) / 2.0**20
    assert 0.0 < gib <= total


def test_workers_take_the_reduced_model_in_place_keeping_processes_and_solvers(reference):
    """``LocalExecutor.update``: the same worker processes solve with the new recipe's reduced
    model (each worker takes it exactly once), with the same bits as a fresh process; in a
    process, a recipe differing only in its predictor keeps the cached solvers."""
    import dataclasses

    from tissuecast.dataset.executors import LocalExecutor
    from tissuecast.dataset.generate import recipe_from_store
    from tissuecast.dataset.worker import Task, context_for, solve_task

    _, path, _ = reference
    full = recipe_from_store(path)
    bare = dataclasses.replace(full, reduced_basis=None, reduced_elements=None, reduced_weights=None)
    assert bare.base_key == full.base_key and bare.key != full.key
    ds = open_dataset(path)
    alpha = float(ds.summary()["calibration"]["alpha"])
    tasks = [Task(i, int(ds.seed[i]), float("nan"), alpha) for i in range(N_BASIS, N_BASIS + 6)]

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):  # as in a worker (executors.single_threaded_blas): the same bits
        ctx = context_for(bare)
        solver = ctx.solver(0)
        assert ctx.reduced is None
        assert context_for(full) is ctx and ctx.solver(0) is solver and ctx.reduced is not None
        here = [solve_task(full, t) for t in tasks]

    with LocalExecutor(bare, 2) as ex:
        before = [r for item in ex.imap_unordered(tasks[:2]) for r in item]
        ex.update(full)
        after = sorted((r for item in ex.imap_unordered(tasks) for r in item), key=lambda r: r.index)
    assert {r.predicted for r in before} == {InitialGuess.ZERO}
    assert {r.predicted for r in after} == {InitialGuess.REDUCED_MODEL}
    for a, b in zip(after, here):
        assert a.index == b.index and a.iterations == b.iterations
        np.testing.assert_array_equal(a.displacement, b.displacement)


def test_batches_are_cut_to_the_memory_their_tangents_need():
    """A batch solves in lockstep and each sample holds its element matrices: on a large mesh
    the requested batch is cut to ``dataset.batch_memory`` (the paper preset's 32 OOM-killed
    a worker on a 58 k-tetrahedron P2 mesh), from the config and mesh alone."""
    from tissuecast.dataset.generate import fitting_batch_size as batch_size

    assert batch_size(32, 4.0, 5066, 2) == 32  # the phantom: 36 MB a sample
    assert batch_size(32, 4.0, 17128, 2) == 32  # ~3500 vertices: 123 MB
    assert batch_size(32, 4.0, 58223, 2) == 10  # ~11 000 vertices: 419 MB a sample
    assert batch_size(32, 4.0, 58223, 1) == 32  # linear tetrahedra: 12 x 12 element matrices
    assert batch_size(32, 0.1, 58223, 2) == 1 and batch_size(1, 100.0, 10, 2) == 1


def test_a_new_store_plans_batches_of_the_size_that_fits(reference, tmp_path):
    cfg, _, _ = reference
    from tissuecast.dataset.generate import setup_from_config

    mesh, _, _ = setup_from_config(cfg)
    order = 10 if cfg.solver.order == 2 else 4
    per_sample = len(mesh.tets) * (3 * order) ** 2 * 8.0
    assert cfg.dataset.batch_size > 2
    small = with_overrides(cfg, dataset={"batch_memory": 2.5 * per_sample / 2.0**30, "n_samples": 30, "n_test2": 0})
    simulate(small, tmp_path / "s.zarr", progress=False)
    assert zarr.open_group(str(tmp_path / "s.zarr"), mode="r").attrs["batches"]["size"] == 2


def test_the_remaining_samples_eta_counts_the_basis_samples_median(caplog):
    """After the reduced model's basis samples: the pending samples at their median worker
    seconds, in whole waves over the workers (101 samples, 2 workers, 1.5 s: 51 waves, 76.5 s)."""
    from types import SimpleNamespace

    from tissuecast.dataset.generate import remaining_outlook

    writer = SimpleNamespace(pending=lambda: list(range(101)))
    ex = SimpleNamespace(phases=[SimpleNamespace(median_seconds=1.5)], workers=2)
    with caplog.at_level("INFO", logger="tissuecast.dataset.generate"):
        remaining_outlook(writer, ex)
    assert "ETA for the 101 remaining samples 76 s" in caplog.text and "(1.50 s of worker time)" in caplog.text
    caplog.clear()
    remaining_outlook(SimpleNamespace(pending=lambda: []), ex)  # nothing left: nothing said
    remaining_outlook(writer, SimpleNamespace(phases=[SimpleNamespace(median_seconds=None)], workers=2))
    assert caplog.text == ""


class _LinearPilots:
    """A stand-in for the calibration's supervisor: records each round's tasks in the order
    they are handed out and answers at once, pilot i's peak being ``(1 + i) * alpha`` mm (a
    linear response), pilot i taking ``1 + i`` s (so the last pilot is the slowest)."""

    workers = 2

    def __init__(self, n_vertices: int):
        self.n, self.rounds = n_vertices, []

    def run(self, tasks, phase, unit="sample", outlook=None):
        from tissuecast.dataset.worker import SampleResult

        tasks = list(tasks)
        self.rounds.append(tasks)
        out = []
        for t in tasks:
            u = np.zeros((self.n, 3), dtype=np.float32)
            u[0, 0] = (1 + t.index) * t.alpha
            out.append(SampleResult(t.index, SampleStatus.DONE, u, u, np.zeros((1, 3)), t.alpha, t.beta, t.seed, 1, 1,
                                    1, 1.0 + t.index, 1.0, 1, nodal=np.full((self.n, 3), 10.0 * t.index + t.alpha)))
        return out


@pytest.mark.parametrize("gravity", [False, True])
def test_first_round_pilots_start_from_their_linear_answer_where_the_field_is_the_only_load(tmp_path, gravity):
    """Without pins (an attached face) the first alpha comes from the pilots' linear answers;
    where the LBO field is a sample's only load, each first-round pilot starts from its own
    linear answer at that alpha (so their q90 is the first aim, half the target), with gravity
    from zero; later rounds hand out the previous round's slowest pilots first, each from its
    own solution of that round."""
    from tissuecast.dataset import recipe_from_store
    from tissuecast.dataset.calibrate import FIRST_AIM, calibrate_pilots
    from tissuecast.dataset.generate import _open_or_create
    from tissuecast.dataset.quantiles import sample_quantile

    cfg = small_config(tmp_path, alpha=0.0, calibration_samples=4)
    cfg = with_overrides(cfg, scenario={"name": "held", "pins": False, "attached": {"rule": "normal",
                                                                                     "direction": [0.0, 0.0, -1.0]},
                                        "gravity": {"enabled": gravity}})
    writer = _open_or_create(cfg, tmp_path / "s.zarr")
    recipe = recipe_from_store(writer)
    n = recipe.scenario().mesh.n_vertices
    ex = _LinearPilots(recipe.scenario().n_nodes)
    record, kept = calibrate_pilots(writer, ex, cfg, recipe)
    first, second = ex.rounds[0], ex.rounds[1]
    assert len(ex.rounds) >= 2 and record["converged"] and len(kept) == 4
    if gravity:
        assert all(t.guess is None for t in first)
    else:
        assert all(t.guess_code == InitialGuess.LINEAR_ANSWER for t in first)
        peaks = [np.linalg.norm(t.guess[:n], axis=1).max() for t in first]
        assert sample_quantile(np.array(peaks), 0.9) == pytest.approx(FIRST_AIM * 10.0, rel=1e-5)
    assert [t.index for t in second] == [3, 2, 1, 0]
    # the record keeps the pilots in index order whatever order they were handed out in
    assert record["rounds"][1]["pilot_max"] == [pytest.approx((1 + i) * second[0].alpha) for i in range(4)]
    for t in second:
        assert t.guess_code == InitialGuess.PREVIOUS_ROUND
        np.testing.assert_array_equal(t.guess, 10.0 * t.index + first[0].alpha)
