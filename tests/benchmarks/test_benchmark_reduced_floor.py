"""benchmarks/reduced_floor.py: a Galerkin model whose basis spans a sample's field gives that field
back from the sample's own inputs (drawn E, Poisson's ratio and springs included); the rows of the
command; bad arguments refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tissuecast.config import with_overrides
from tissuecast.dataset import open_dataset, simulate
from tissuecast.dataset.worker import Task, context_for

from bench_helpers import SPRING_HELD, load_benchmark
from dataset_helpers import small_config

#: Drawn per sample: a reduced model of the nominal material would miss these samples' fields.
DRAWN = {"youngs_modulus": [0.5, 2.0], "poisson_ratio": [0.40, 0.49], "spring_normal": [0.25, 4.0]}


@pytest.fixture(scope="module")
def drawn_store(tmp_path_factory):
    """A small spring-held store (no indentation, no drawn attachment) with E, Poisson's ratio and
    the springs drawn per sample."""
    tmp = tmp_path_factory.mktemp("reduced_floor")
    cfg = with_overrides(small_config(tmp, n_samples=20, n_test2=0, alpha=0.0, calibration_samples=2,
                                      predictor="none", store=str(tmp / "data.zarr")),
                         forces={"loading": "traction", "target_max_displacement": 4.0},
                         scenario={**SPRING_HELD, "uncertain": DRAWN}, solver={"order": 1})
    simulate(cfg, progress=False)
    return cfg.dataset.store


def test_a_basis_spanning_the_field_gives_it_back(drawn_store):
    mod = load_benchmark("reduced_floor")
    ds = open_dataset(drawn_store)
    test = ds.select("test1")
    assert len(test) >= 1
    factors = ds.parameters["youngs_modulus"][test]
    assert np.any(np.abs(factors - 1.0) > 0.1)  # the samples are not the nominal material
    ctx = context_for(ds.recipe())
    problem = ctx.solver(0).problem
    free = np.flatnonzero(problem.free_mask)
    tasks = [Task(int(k), int(ds.seed[k]), float(ds.beta[k]), float(ds.alpha[k])) for k in test]
    samples = {t.index: ctx.inputs(t) for t in tasks}
    truth = {int(k): np.asarray(ds.displacements[k], dtype=np.float64) for k in test}
    m = len(problem.connectivity)
    # the test fields themselves in the basis: the reduced equilibrium is the full one
    basis = mod.training_basis(ds.displacements[np.concatenate([ds.select("train"), test])], free, 1000)
    fields, seconds, failed = mod.reduced_answers(ctx, samples, basis, np.arange(m), np.ones(m), ds.mesh.n_vertices)
    assert failed == [] and len(seconds) == len(tasks)
    peak = max(float(np.linalg.norm(u, axis=1).max()) for u in truth.values())
    err = mod.field_errors(fields, truth)
    assert err["offset_max_mm"] < 0.01 * peak
    # the training fields alone do not span them: the same model is then measurably off
    basis = mod.training_basis(ds.displacements[ds.select("train")[:3]], free, 1000)
    fields, _, _ = mod.reduced_answers(ctx, samples, basis, np.arange(m), np.ones(m), ds.mesh.n_vertices)
    assert mod.field_errors(fields, truth)["offset_max_mm"] > 0.05 * peak


def test_the_rows_of_the_command(drawn_store, tmp_path, capsys):
    mod = load_benchmark("reduced_floor")
    out = tmp_path / "rows.json"
    assert mod.main([drawn_store, "--modes", "2", "8", "9", "--samples", "2", "--no-galerkin", "--ecsw-snapshots", "8",
                     "--ecsw-tolerance", "0.001"]) == 0
    assert "ecsw      9: not fitted, more modes than the 8 fields" in capsys.readouterr().out
    assert mod.main([drawn_store, "--modes", "2", "8", "--samples", "2", "--ecsw-snapshots", "8",
                     "--ecsw-tolerance", "0.001", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "training fields" in text and "median peak" in text and "non-rigid part" in text
    report = json.loads(out.read_text())
    assert 0.0 < report["median_nonrigid_mm"] <= report["median_peak_mm"]
    rows = report["rows"]
    assert [(r["method"], r["modes"]) for r in rows] == [
        ("projection", 2), ("proj held", 2), ("galerkin", 2), ("springs", 2), ("projection", 8), ("proj held", 8),
        ("galerkin", 8), ("springs", 8), ("ecsw", 2), ("ecsw", 8)]
    m = len(open_dataset(drawn_store).recipe().problem().connectivity)
    for r in rows:
        assert r["failed"] == [] and 0.0 <= r["offset_mean_mm"] <= r["offset_max_mm"]
    assert all(r["elements"] == m for r in rows if r["method"] in ("galerkin", "springs"))
    assert all(0 < r["elements"] < m and r["ms_median"] > 0 for r in rows if r["method"] == "ecsw")
    # more of the basis projects closer (nested subspaces: the residual's 2-norm cannot grow)
    proj = [r for r in rows if r["method"] == "projection"]
    assert proj[1]["offset_mean_mm"] < proj[0]["offset_mean_mm"]


def test_bad_arguments_are_refused(drawn_store, capsys):
    mod = load_benchmark("reduced_floor")
    with pytest.raises(SystemExit):
        mod.main([drawn_store, "--modes", "0"])
    assert "--modes and --samples must be positive" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        mod.main([drawn_store, "--ecsw-tolerance", "1.5"])
    assert "--ecsw-tolerance in (0, 1)" in capsys.readouterr().err


def test_the_learned_model_and_baselines_beside_a_tracked_retractors_store(tmp_path, capsys):
    """A store with a tracked retractor's dent and a drawn attachment (held vertices beyond the
    supports, pulled by stiff springs in the reduced model): the model, rigid registration and
    ridge rows from the model's markers and the recorded poses; a basis spanning the fields
    gives them back to round-off through the constrained basis."""
    from tissuecast.surrogate import DeformationModel

    from dataset_helpers import tracked_retractor_store

    _, store, folder = tracked_retractor_store(tmp_path, {"attached_margin": [-6.0, 6.0]})
    mod = load_benchmark("reduced_floor")
    out = tmp_path / "rows.json"
    assert mod.main([str(store), "--modes", "40", "--samples", "3", "--model", str(folder), "--json", str(out)]) == 0
    assert "model" in capsys.readouterr().out
    rows = json.loads(out.read_text())["rows"]
    assert [r["method"] for r in rows] == ["model", "rigid", "ridge", "projection", "proj held", "galerkin", "springs"]
    ds = open_dataset(store)
    test = ds.select("test1")[:3]
    model = DeformationModel.load(folder)
    u = np.asarray(ds.displacements[test], dtype=np.float64)
    rigid = np.linalg.norm(model.predict_rigid(u[:, model.markers]) - u, axis=2).max(axis=1).mean()
    assert rows[1]["offset_max_mm"] == pytest.approx(rigid, rel=1e-9)
    assert rows[0]["ms_median"] > 0 and rows[5]["failed"] == []
    # holding what the sample holds can only cost: the constrained span lies in the span
    assert rows[4]["offset_mean_mm"] >= rows[3]["offset_mean_mm"] - 1e-12
    ctx = context_for(ds.recipe())
    problem = ctx.solver(0).problem
    free = np.flatnonzero(problem.free_mask)
    everything = np.concatenate([ds.select("train"), test])
    assert ds.parameters["attached_margin"][test].std() > 0 and ds.instrument_poses  # held sets and dents differ
    basis = mod.training_basis(ds.displacements[everything], free, 1000)
    m = len(problem.connectivity)
    tasks = [Task(int(k), int(ds.seed[k]), float(ds.beta[k]), float(ds.alpha[k])) for k in test]
    samples = {t.index: ctx.inputs(t) for t in tasks}
    truth = {int(k): u[i] for i, k in enumerate(test)}
    peak = np.linalg.norm(u, axis=2).max()
    fields, _, failed = mod.reduced_answers(ctx, samples, basis, np.arange(m), np.ones(m), ds.mesh.n_vertices)
    assert failed == [] and mod.field_errors(fields, truth)["offset_max_mm"] < 0.002 * peak
    # the data set's guesses' springs (100 mm x E) on the same basis: the held vertices give
    fields, _, _ = mod.reduced_answers(ctx, samples, basis, np.arange(m), np.ones(m), ds.mesh.n_vertices, exact=False)
    assert mod.field_errors(fields, truth)["offset_max_mm"] > 0.02 * peak
    # the held vertices and the patch: the constrained basis vanishes at the held ones and one
    # column moves the patch by the values
    pos = np.full(3 * len(problem.nodes), -1)
    pos[free] = np.arange(len(free))
    dents = 0
    for task in [Task(int(k), int(ds.seed[k]), float(ds.beta[k]), float(ds.alpha[k])) for k in ds.select("test1")]:
        held, values = ctx.inputs(task).held_values
        if not len(held):
            continue
        b = mod.constrained_basis(basis, free, len(problem.nodes), held, values)
        assert np.allclose(b.T @ b, np.eye(b.shape[1]), atol=1e-10)
        rows = pos[(3 * held[:, None] + np.arange(3)).ravel()]
        moving = np.abs(b[rows[rows >= 0]]).max(axis=0) > 1e-9
        dent = len(values) and np.abs(values).max() > 0
        dents += bool(dent)
        assert moving.sum() == (1 if dent else 0)
        if dent:  # that column, scaled, reaches the values (the truth is in the span)
            c, v = b[rows[rows >= 0]][:, moving][:, 0], values.ravel()[rows >= 0]
            assert np.abs(c * (c @ v) / (c @ c) - v).max() < 1e-6 * np.abs(v).max()
    assert dents >= 1
