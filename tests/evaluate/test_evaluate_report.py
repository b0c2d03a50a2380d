"""Evaluation of a model on a data set and the HTML report (synthetic in-memory data set)."""

import csv
import html
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
    assert evaluation.predict_seconds["p50"] > 0 and evaluation.predict_seconds["gate"] is True  # timed as in surgery
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


def test_tre_at_vertex_targets_equals_the_vertex_errors(model, ds, evaluation):
    from tissuecast.evaluate.targets import point_targets

    ids = np.array([7, 40, 133, 170])
    targets = point_targets(ds.mesh, ds.mesh.points[ids])
    ev = evaluate_model(model, ds, splits=("test1",), targets=targets)
    t1 = ev.sets["test1"]
    bench = ds.displacements[t1.indices].astype(np.float64)
    for method in ("mlp", "rigid", "ridge"):
        pred = model.predict(model.marker_displacements(bench), method=method)
        e = np.linalg.norm(pred - bench, axis=2)[:, ids]
        np.testing.assert_allclose(t1.tre[method][:, 0], e.mean(axis=1), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(t1.tre[method][:, 2], e.max(axis=1), rtol=1e-9, atol=1e-12)
        moved = np.linalg.norm(bench[:, ids], axis=2).mean(axis=1)
        s = t1.target_summary(method)
        assert s.share_corrected_mean == pytest.approx(np.mean(1 - e.mean(axis=1) / moved))
        assert s.share_corrected_worst == pytest.approx(np.min(1 - e.mean(axis=1) / moved))
    # the default targets are interior points away from the supports, and every set reports them
    held = ds.mesh.points[ds.fixed]
    assert evaluation.targets.name == "interior"
    assert not np.all(np.isclose(evaluation.targets.positions[:, None], held[None]), axis=2).any()
    d = evaluation.as_dict()
    assert d["targets"]["count"] == evaluation.targets.count
    assert {"mlp", "rigid", "ridge", "pca_floor"} == set(d["sets"]["test1"]["targets"])
    assert d["by_beta"][0]["targets"]["mlp"]["tre_mean"] >= 0
    row = evaluation.samples_table()[0]
    assert {"mlp_tre_mean", "rigid_tre_p95", "ridge_tre_max", "target_displacement_mean"} <= set(row)


def test_report_is_written(tmp_path, model, ds, evaluation):
    from tissuecast.evaluate.report import write_report

    index = write_report(tmp_path / "rep", model, ds, evaluation, renders=1)
    page = index.read_text()
    # the first screen: the verdict, how good against what, how sure; the details fold away below
    head, _, rest = page.partition("<section id='tc-viewer'")
    assert "class='tc-verdict'" in head and "How good, against what (test-1, 30 samples)" in head
    assert "error at 10 targets (TRE): per-sample mean / p95 / max, averaged over samples" in head
    assert "How sure" in head and "worst sample: Offset_max / worst target error" in head
    worst = evaluation.sets["test1"].target_summary("mlp").worst_tre_max
    from tissuecast.evaluate.headline import fmt_mm

    assert html.escape(f"{fmt_mm(evaluation.sets['test1'].mlp.worst_offset_max, False)} / {fmt_mm(worst)}") in head
    assert "finite-element simulations with exact (noise-free) marker displacements" in head  # not a patient figure
    assert "Offset_max: a sample's largest error over every mesh vertex" in head  # the terms explained
    assert "<h3>test1 median error (sample " in page  # the sample of median error, not of median displacement
    assert page.count("<div class='tc-wide'><table") == page.count("<table")  # no table widens the page
    assert "90 % error bounds: share of vertices covered (test-1)" in head and "<details" not in head
    assert "<td>off</td><td>too few calibration samples" in head  # 30 calibration samples: no finite 1 % alarm
    t1 = evaluation.sets["test1"]
    assert f"{t1.rigid.offset_max:.2f} mm" in head and f"{100 * t1.target_summary('rigid').share_corrected_mean:.1f} %" in head
    assert "Measured against the baselines and the paper" in page and "0.889 – 1.181" in page
    assert "rigid registration" in page and "non-rigid part" in page and "PCA floor" in page
    assert ">nan<" not in page.lower() and "100.000" not in page and "How sure: error bounds and alarm" in rest
    assert "The ensemble's spread (a detail)" in rest  # one uncertainty story: the spread inside it
    q = model.pca_choice_["head"]["dims"]  # the report names the model it measured
    head = "linear head (q = 0)" if q == 0 else f"quadratic head (q = {q})"
    assert q is not None and f"{head} + MLP [" in page and "x 2" in page
    for png in ("boxplots.png", "beta.png", "training.png"):
        assert (tmp_path / "rep" / png).stat().st_size > 1000 and png in page
    def strict(constant):  # what JavaScript's JSON.parse refuses
        raise AssertionError(f"{constant} in a report JSON file")

    for name in ("evaluation.json", "trust.json"):
        if (tmp_path / "rep" / name).is_file():
            json.loads((tmp_path / "rep" / name).read_text(), parse_constant=strict)
    data = json.loads((tmp_path / "rep" / "evaluation.json").read_text())
    assert data["sets"]["test1"]["mlp"]["offset_max"] == pytest.approx(evaluation.sets["test1"].mlp.offset_max)
    assert data["sets"]["test1"]["rigid"]["offset_max"] == pytest.approx(evaluation.sets["test1"].rigid.offset_max)
    assert data["sets"]["test1"]["gain_over_rigid"] == pytest.approx(evaluation.sets["test1"].gain_over_rigid)
    assert data["sets"]["test1"]["targets"]["mlp"]["tre_mean"] == pytest.approx(t1.target_summary("mlp").tre_mean)
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


def test_viewer_data_holds_the_true_and_predicted_surfaces(tmp_path, model, ds, evaluation):
    from tissuecast.evaluate.viewer import write_viewer

    section = write_viewer(tmp_path, model, ds, evaluation)
    assert "<canvas" in section and "viewer_data.js" in section and (tmp_path / "viewer.js").stat().st_size > 5000
    text = (tmp_path / "viewer_data.js").read_text()
    assert text.startswith("window.TISSUECAST_VIEW = ")
    view = json.loads(text[len("window.TISSUECAST_VIEW = "):].rstrip().rstrip(";"))
    surface = np.unique(ds.mesh.surface_triangles)
    points = np.reshape(view["points"], (-1, 3))
    np.testing.assert_allclose(points, ds.mesh.points[surface], atol=5e-4)
    tri = np.reshape(view["triangles"], (-1, 3))
    np.testing.assert_array_equal(surface[tri], ds.mesh.surface_triangles)
    first = view["samples"][0]
    idx = int(first["label"].split("sample ")[1].split(")")[0].split(",")[0])
    bench = ds.displacements[idx].astype(np.float64)
    np.testing.assert_allclose(np.reshape(first["true"], (-1, 3)), bench[surface], atol=5e-4)
    pred = model.predict(model.marker_displacements(bench), method="rigid")
    np.testing.assert_allclose(np.reshape(first["methods"]["rigid"], (-1, 3)), pred[surface], atol=5e-4)
    assert view["methods"] == ["mlp", "rigid", "ridge"] and len(view["samples"]) == 5
    assert len(first["targets"]["mlp"]) == 3 * evaluation.targets.count


def test_how_sure_rows_say_what_is_there():
    from tissuecast.evaluate.headline import trust_rows

    assert trust_rows(None, True)[0][1] == "—" and "calibration_share = 0" in trust_rows(None, True)[0][2]
    assert "ensemble's spread" in trust_rows(None, True)[0][2] and "spread" not in trust_rows(None, False)[0][2]
    row = {"coverage_0.9": 0.894, "median_bound_0.9": 0.12, "alarm_rate": 0.04, "alarm_on": True}
    rows = trust_rows({"sets": {"test1": row, "test2": {**row, "alarm_rate": 0.5, "coverage_0.9": 0.7}}})
    assert [r[1] for r in rows] == ["89.4 %", "4 %", "50 %"] and "median bound 0.12 mm" in rows[0][2]
    assert "bounds cover 70 % there" in rows[2][2]
    rows = trust_rows({"sets": {"test1": {**row, "median_bound_0.9": float("inf"), "alarm_on": False}}})
    assert "infinite" in rows[0][2] and rows[1][1] == "off"


def test_numbers_are_written_for_people():
    from tissuecast.evaluate.headline import fmt_mm, fmt_ratio, fmt_share, fmt_time, set_title

    assert fmt_mm(0.2913) == "0.29 mm" and fmt_mm(0.0042) == "0.004 mm" and fmt_mm(12.345) == "12.3 mm"
    assert fmt_mm(float("nan")) == "—" and fmt_mm(None) == "—" and fmt_mm(1e-9) == "< 0.001 mm"
    assert fmt_share(1.0) == "100 %" and fmt_share(0.2) == "20 %" and fmt_share(0.9655) == "96.5 %"
    assert fmt_share(float("nan")) == "—" and fmt_share(-0.12) == "-12 %"
    assert fmt_ratio(5.87) == "5.9×" and fmt_ratio(12.4) == "12×" and fmt_ratio(2e6) == "> 1000×"
    assert fmt_time(2.3e-5) == "23 µs" and fmt_time(0.0012) == "1.2 ms" and fmt_time(3.14159) == "3.14 s"
    assert set_title("test2 beta=0.5") == "test-2 β=0.5" and set_title("valid") == "validation"


def test_architecture_study_rows(ds, tmp_path):
    from tissuecast.config import Config, with_overrides
    from tissuecast.evaluate import figures, studies

    cfg = with_overrides(Config(), surrogate={"epochs": 15, "patience": 0, "n_components": 8})
    rows = studies.architecture_study(ds, cfg, widths=(8, 16), repeats=1)
    assert [(r["n1"], r["n2"]) for r in rows] == [(8, 8), (8, 16), (16, 8), (16, 16)]
    assert all(r["seconds"] > 0 and r["mlp_offset_max"] > 0 and r["epochs_run"] == 15 for r in rows)
    # TRE at the config's targets (interior by default) beside the offsets, rigid registration's too
    assert all(0 < r["mlp_tre_mean"] < r["rigid_tre_mean"] and r["rigid_share_corrected"] < 1 for r in rows)
    assert len({round(r["rigid_tre_mean"], 12) for r in rows}) == 1
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
    from file_readers import read_everywhere

    from tissuecast.evaluate.report import write_report

    write_report(tmp_path / "rep", model, ds, evaluation, renders=2)
    files = sorted((tmp_path / "rep" / "vtu").glob("*.vtu"))
    assert len(files) == 2
    for path in files:
        seen = read_everywhere(path, model.mesh.points, ("benchmark_displacement", "predicted_displacement",
                                                         "vertex_error", "ridge_displacement"))
        np.testing.assert_allclose(seen["pyvista"].point_data["vertex_error"], seen["meshio"].point_data["vertex_error"])


def test_a_sample_the_gate_refuses_is_evaluated_and_counted(model, ds, tmp_path):
    """A simulated sample outside what the model was trained on (its field 25x a simulated one) is
    refused by the input gate in use, but an evaluation predicts it (the gate suspended) and
    reports the refused share; the gate is on again afterwards."""
    import copy

    from tissuecast.errors import InputRejected

    bent = copy.copy(ds)
    bent.displacements = ds.displacements.copy()
    k = int(ds.select("test1")[0])
    bent.displacements[k] *= 25.0
    d = model.marker_displacements(np.asarray(bent.displacements[k], dtype=np.float64))
    assert model.check_input(d).refused
    ev = evaluate_model(model, bent, splits=("test1",))
    t1 = ev.sets["test1"]
    assert t1.refused.sum() == 1 and t1.refused[list(t1.indices).index(k)]
    assert ev.as_dict()["sets"]["test1"]["gate_refused"] == pytest.approx(1 / t1.indices.size)
    assert np.isfinite(t1.offsets["mlp"]).all()
    with pytest.raises(InputRejected):
        model.predict(d)
    from tissuecast.evaluate.report import write_report

    assert write_report(tmp_path / "rep", model, bent, ev, renders=0).is_file()
    with pytest.raises(InputRejected):
        model.predict(d)


def test_report_json_writes_what_is_not_a_number_as_null():
    from tissuecast.evaluate import json_output

    text = json_output.dumps({"a": float("nan"), "b": [np.float32(1.5), np.inf, -np.inf], "c": np.arange(2),
                              "d": np.bool_(True), "e": {"f": np.float64("nan")}})
    assert json.loads(text) == {"a": None, "b": [1.5, None, None], "c": [0, 1], "d": True, "e": {"f": None}}


def test_the_how_sure_table_says_when_the_bounds_do_not_hold_on_other_force_fields():
    from tissuecast.evaluate.headline import TEST2_COVERAGE_WARNING, trust_rows

    def sets(test2_coverage):
        one = {"coverage_0.9": 0.9, "median_bound_0.9": 0.5, "alarm_rate": 0.01}
        return {"sets": {"test1": one, "test2": {**one, "coverage_0.9": test2_coverage, "alarm_rate": 0.065}}}

    low = trust_rows(sets(0.672))[-1][2]
    assert low.startswith("bounds cover 67.2 % there: the bounds do not hold for force fields unlike the training's")
    assert "93.5 % of those samples raise no alarm" in low
    assert trust_rows(sets(TEST2_COVERAGE_WARNING + 0.05))[-1][2] == "bounds cover 85 % there"
    from tissuecast.evaluate.headline import verdict

    class _Set:  # what the verdict reads of an evaluation's set
        indices, gain_over_rigid = np.arange(30), 5.0

        def summary(self, m):
            return type("S", (), {"offset_max": 0.3 if m == "mlp" else 1.5})()

        def deformation(self):
            return {"max_displacement_median": 16.5, "nonrigid_share_median": 0.1}

        def target_summary(self, m):
            return None

    evaluation = type("E", (), {"sets": {"test1": _Set()}, "model_summary": {"markers": [1, 2, 3, 4, 5]}})()
    assert "(test-2) they cover only 67.2 % and the alarm fires on 6.5 %: there neither is to be trusted" in verdict(
        evaluation, sets(0.672))
    assert "test-2" not in verdict(evaluation, sets(0.85))
    assert "5× better than rigid registration from the same 5 markers" in verdict(evaluation, sets(0.85))
    _Set.gain_over_rigid = 1.0 / 3.0  # a model worse than rigid registration is called worse
    assert "3× worse than rigid registration from the same 5 markers" in verdict(evaluation, sets(0.85))


def test_the_terminal_summary_fits_the_terminal(evaluation):
    """A grid where it fits, else a line per quantity naming each method; never wider than asked."""
    from tissuecast.evaluate.tables import format_evaluation

    wide, narrow = format_evaluation(evaluation, width=1000), format_evaluation(evaluation, width=100)
    assert any(line.startswith("quantity") and line.rstrip().endswith("paper") for line in wide.splitlines())
    assert max(len(line) for line in narrow.splitlines()) <= 100 and "quantity" not in narrow
    t1 = evaluation.sets["test1"]
    from tissuecast.evaluate.headline import fmt_mm

    for text in (wide, narrow):  # the same figures either way
        assert fmt_mm(t1.mlp.offset_max) in text and fmt_mm(t1.rigid.offset_max) in text
    assert f"rigid registration {fmt_mm(t1.rigid.offset_max)}" in narrow and "test-2 mean Offset_max per beta" in narrow


def test_training_plot_draws_the_fallback_dashed_beside_the_model(tmp_path, monkeypatch):
    from tissuecast.evaluate import figures

    drawn = {}

    def keep(fig, path):
        drawn["lines"] = [(ln.get_linestyle(), ln.get_label(), list(ln.get_ydata())) for ln in fig.axes[0].get_lines()]
        drawn["ylabel"] = fig.axes[0].get_ylabel()
        return path

    monkeypatch.setattr(figures, "save_figure", keep)
    member = {"valid_history": [[1, 2.0], [25, 1.0]], "best_epoch": 25, "seconds": 3.0}
    fallback = {"valid_history": [[1, 3.0], [25, 1.5]], "best_epoch": 20, "seconds": 1.0}
    figures.training_curves([member, member], tmp_path / "t.png", [fallback])
    styles = [(s, label.split(" (")[0], y) for s, label, y in drawn["lines"]]
    assert styles == [("-", "member 0", [2.0, 1.0]), ("-", "member 1", [2.0, 1.0]), ("--", "fallback member 0", [3.0, 1.5])]
    assert drawn["ylabel"] == "validation loss (MSE of scaled PCA weights)"


def test_the_model_is_described_by_its_head_and_networks():
    from tissuecast.evaluate.tables import model_description

    base = {"hidden": [256, 256], "ensemble": 1}
    assert model_description({**base, "pca": {"head": {"dims": 12}}}) == "quadratic head (q = 12) + MLP [256, 256]"
    assert model_description({**base, "pca": {"head": {"dims": 0}}}) == "linear head (q = 0) + MLP [256, 256]"
    assert model_description({**base, "ensemble": 3, "pca": {"head": {"dims": None}}, "nominal_expert": {"a": 1}}) == (
        "MLP [256, 256] x 3, with a nominal expert")
