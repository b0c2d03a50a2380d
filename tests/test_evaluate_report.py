"""Evaluation of a model on a data set and the HTML report (synthetic in-memory data set)."""

import csv
import json

import numpy as np
import pytest

from tissuecast.errors import ModelError
from tissuecast.evaluate.evaluation import evaluate_model, spearman_rows
from tissuecast.surrogate import DeformationModel

from _surrogate_synthetic import FakeDataset, box_mesh


@pytest.fixture(scope="module")
def ds():
    return FakeDataset()


@pytest.fixture(scope="module")
def model(ds):
    return DeformationModel.from_dataset(ds, epochs=150, patience=0, n_components=8, ensemble=2, learning_rate=3e-3, batch_size=64)


@pytest.fixture(scope="module")
def evaluation(model, ds):
    return evaluate_model(model, ds, splits=("train", "valid", "test1", "test2"))


def test_from_dataset_uses_converged_splits(model, ds):
    tr = model.training_
    assert tr["n_train"] == 239 and tr["n_valid"] == 30  # sample 5 (train) failed and is left out
    np.testing.assert_array_equal(model.markers, ds.markers)
    np.testing.assert_array_equal(model.fixed, ds.fixed)


def test_evaluation_matches_direct_metrics(evaluation, model, ds):
    t1 = evaluation.sets["test1"]
    idx = ds.select("test1")
    np.testing.assert_array_equal(t1.indices, idx)
    bench = ds.displacements[idx].astype(np.float64)
    pred = model.predict(model.marker_displacements(bench))
    e = np.linalg.norm(pred - bench, axis=2)
    np.testing.assert_allclose(t1.mlp_max, e.max(axis=1))
    np.testing.assert_allclose(t1.mlp_mean, e.mean(axis=1))
    assert t1.mlp.offset_max < t1.ridge.offset_max
    assert 5 not in evaluation.sets["train"].indices
    betas = [b for b, _ in evaluation.by_beta]
    assert betas == pytest.approx(np.linspace(0, 1, 11))
    assert sum(r.indices.size for _, r in evaluation.by_beta) == evaluation.sets["test2"].indices.size
    assert evaluation.predict_seconds["p50"] > 0
    assert t1.sigma_spearman.shape == t1.indices.shape and np.all(np.abs(t1.sigma_spearman) <= 1 + 1e-12)


def test_spearman_rows_known_values():
    a = np.array([[1.0, 2, 3, 4], [1, 2, 3, 4], [1, 5, 2, 2]])
    b = np.array([[10.0, 20, 30, 40], [4, 3, 2, 1], [1, 5, 2, 2]])
    np.testing.assert_allclose(spearman_rows(a, b), [1.0, -1.0, 1.0])


def test_evaluation_refuses_other_mesh(model, ds):
    other = FakeDataset()
    other.mesh = box_mesh(nx=4, ny=5, nz=8, h=6.0)
    with pytest.raises(ModelError, match="mesh"):
        evaluate_model(model, other)


def test_report_is_written(tmp_path, model, ds, evaluation):
    from tissuecast.evaluate.report import write_report

    index = write_report(tmp_path / "rep", model, ds, evaluation, renders=1)
    page = index.read_text()
    assert "Measured versus the paper" in page and "0.889 – 1.181" in page
    for png in ("boxplots.png", "beta.png", "training.png"):
        assert (tmp_path / "rep" / png).stat().st_size > 1000 and png in page
    data = json.loads((tmp_path / "rep" / "evaluation.json").read_text())
    assert data["sets"]["test1"]["mlp"]["offset_max"] == pytest.approx(evaluation.sets["test1"].mlp.offset_max)
    with (tmp_path / "rep" / "samples.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == sum(r.indices.size for r in evaluation.sets.values())
    import meshio

    vtu = meshio.read(tmp_path / "rep" / "vtu" / "test1_median.vtu")
    err = vtu.point_data["vertex_error"]
    np.testing.assert_allclose(err, np.linalg.norm(vtu.point_data["predicted_displacement"] - vtu.point_data["benchmark_displacement"], axis=1))
    t1 = np.sort(evaluation.sets["test1"].mlp_max)
    assert np.max(err) == pytest.approx(t1[t1.size // 2], rel=1e-6)  # the rendered "median" sample


def test_architecture_study_rows(ds, tmp_path):
    from tissuecast.config import Config, with_overrides
    from tissuecast.evaluate import figures, studies

    cfg = with_overrides(Config(), surrogate={"epochs": 15, "patience": 0, "n_components": 8})
    rows = studies.architecture_study(ds, cfg, widths=(8, 16), repeats=1)
    assert [(r["n1"], r["n2"]) for r in rows] == [(8, 8), (8, 16), (16, 8), (16, 16)]
    assert all(r["seconds"] > 0 and r["mlp_offset_max"] > 0 and r["epochs_run"] == 15 for r in rows)
    # the ridge baseline does not depend on the network
    assert len({round(r["ridge_offset_max"], 9) for r in rows}) == 1
    path = studies.write_rows(tmp_path / "study_architecture.csv", rows)
    assert len(path.read_text().splitlines()) == 5
    assert figures.architecture_grid(rows, tmp_path / "a.png").stat().st_size > 1000


def test_study_markers_are_nested_prefixes(ds):
    from tissuecast.config import Config, with_overrides
    from tissuecast.evaluate.studies import study_markers

    cfg = with_overrides(Config(), markers={"start": 0, "min_distance": 12.0})
    m6, d6 = study_markers(ds.mesh, 6, cfg)
    m3, d3 = study_markers(ds.mesh, 3, cfg)
    assert len(set(m6.tolist())) == 6
    if d3 == d6:
        np.testing.assert_array_equal(m6[:3], m3)
