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
    return DeformationModel.from_dataset(ds, epochs=150, patience=0, n_components=8, ensemble=2, learning_rate=3e-3,
                                         batch_size=64)


@pytest.fixture(scope="module")
def evaluation(model, ds):
    return evaluate_model(model, ds, splits=("train", "valid", "test1", "test2"))


def test_from_dataset_uses_converged_splits(model, ds):
    tr = model.training_
    # sample 5 (train) failed and is left out; surrogate.calibration_share (1/8) of 'train' calibrates the bounds
    assert tr["n_train"] + tr["n_calibration"] == 239 and tr["n_calibration"] == 30 and tr["n_valid"] == 30
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


def test_evaluation_reports_rigid_baseline_floor_and_nonrigid_part(evaluation, model, ds):
    from tissuecast.registration import fit_rigid, nonrigid_part

    t1 = evaluation.sets["test1"]
    bench = ds.displacements[t1.indices].astype(np.float64)
    p = ds.mesh.points
    # rigid registration from the markers, computed here sample by sample
    for k in (0, 7):
        ref = p[model.markers]
        fit = fit_rigid(ref, ref + bench[k, model.markers])
        e = np.linalg.norm(fit.apply(p) - (p + bench[k]), axis=1)
        assert t1.offsets["rigid"][k] == pytest.approx([e.mean(), e.max()], rel=1e-9)
    np.testing.assert_allclose(t1.nonrigid, nonrigid_part(p, bench), rtol=1e-12)
    # the PCA floor is the closest point of the model's affine PCA space: per sample, its RMS
    # vertex error is never above the model's
    pred = model.predict(model.marker_displacements(bench))
    floor = model.pca_projection(bench)
    rms = lambda a: np.sqrt(((a - bench) ** 2).sum(axis=(1, 2)))  # noqa: E731
    assert np.all(rms(floor) <= rms(pred) + 1e-9)
    assert t1.gain_over_rigid == pytest.approx(t1.rigid.offset_max / t1.mlp.offset_max)
    assert evaluation.model_summary["pca"]["n_components"] == model.n_components


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
    assert "Measured versus the baselines and the paper" in page and "0.889 – 1.181" in page
    assert "rigid registration" in page and "non-rigid part" in page and "PCA floor" in page
    q = model.pca_choice_["head"]["dims"]  # the report names the model it measured
    assert q is not None and f"quadratic head (q = {q}) + MLP [" in page and "x 2" in page
    for png in ("boxplots.png", "beta.png", "training.png"):
        assert (tmp_path / "rep" / png).stat().st_size > 1000 and png in page
    data = json.loads((tmp_path / "rep" / "evaluation.json").read_text())
    assert data["sets"]["test1"]["mlp"]["offset_max"] == pytest.approx(evaluation.sets["test1"].mlp.offset_max)
    assert data["sets"]["test1"]["rigid"]["offset_max"] == pytest.approx(evaluation.sets["test1"].rigid.offset_max)
    assert data["sets"]["test1"]["gain_over_rigid"] == pytest.approx(evaluation.sets["test1"].gain_over_rigid)
    with (tmp_path / "rep" / "samples.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == sum(r.indices.size for r in evaluation.sets.values())
    import meshio

    vtu = meshio.read(tmp_path / "rep" / "vtu" / "test1_median.vtu")
    err = vtu.point_data["vertex_error"]
    difference = vtu.point_data["predicted_displacement"] - vtu.point_data["benchmark_displacement"]
    np.testing.assert_allclose(err, np.linalg.norm(difference, axis=1))
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


def test_report_vtu_folder_is_read_by_meshio_pyvista_and_vtk(tmp_path, model, ds, evaluation):
    pytest.importorskip("pyvista")
    from test_mesh_file_readers import read_everywhere

    from tissuecast.evaluate.report import write_report

    write_report(tmp_path / "rep", model, ds, evaluation, renders=2)
    files = sorted((tmp_path / "rep" / "vtu").glob("*.vtu"))
    assert len(files) == 2
    for path in files:
        seen = read_everywhere(path, model.mesh.points, ("benchmark_displacement", "predicted_displacement",
                                                         "vertex_error", "ridge_displacement"))
        np.testing.assert_allclose(seen["pyvista"].point_data["vertex_error"], seen["meshio"].point_data["vertex_error"])
