"""Marker planning: QR pivoting and greedy selection pick the informative vertices of hand-made fields."""

import numpy as np
import pytest
import scipy.linalg

from tissuecast.errors import MarkerError
from tissuecast.planning import QuadraticProxy, candidate_vertices, exchange_markers, greedy_markers, plan_markers, qr_markers
from tissuecast.surrogate.pca import fit_pca

from _surrogate_synthetic import FakeDataset, box_mesh


def _fields(mesh, latents, informative, rng, noise=0.1):
    """Each latent moves one 'informative' vertex by up to 5 mm and every vertex a little along
    random directions (0.05 mm) below the independent noise (0.1 mm): only the informative vertices see it."""
    n = mesh.n_vertices
    N = len(latents)
    U = noise * rng.normal(size=(N, n, 3))
    for j, v in enumerate(informative):
        shape = 0.05 * rng.normal(size=(n, 3))
        shape[v] = [5.0, -3.0, 2.0]
        U += latents[:, j, None, None] * shape
    return U


def test_candidates_follow_region_mask_and_exclusions():
    mesh = box_mesh()
    surf = np.asarray(mesh.surface_vertices)
    np.testing.assert_array_equal(candidate_vertices(mesh, region="surface"), np.sort(surf))
    inner = candidate_vertices(mesh, region="interior")
    assert len(inner) + len(surf) == mesh.n_vertices and not np.isin(inner, surf).any()
    c = candidate_vertices(mesh, region="any", allowed=[5, 7, 9, 11], exclude=[7])
    np.testing.assert_array_equal(c, [5, 9, 11])
    with pytest.raises(MarkerError, match="unknown candidate region"):
        candidate_vertices(mesh, region="skin")
    with pytest.raises(MarkerError, match="outside|0-based"):
        candidate_vertices(mesh, allowed=[mesh.n_vertices])
    with pytest.raises(MarkerError, match="no candidate"):
        candidate_vertices(mesh, region="interior", allowed=surf)


def test_qr_picks_the_informative_vertex_and_matches_scalar_pivoted_qr():
    mesh = box_mesh()
    rng = np.random.default_rng(0)
    U = _fields(mesh, rng.uniform(-1, 1, (400, 1)), [137], rng)
    basis = fit_pca(U.reshape(len(U), -1), 5)
    modes = basis.components * basis.singular_values[:, None]
    cand = np.arange(mesh.n_vertices)
    assert qr_markers(modes, cand, 1)[0] == 137
    # with one column per vertex (x only) the block pivoting is ordinary pivoted QR (PySensors' QR optimizer)
    x_only = modes.reshape(5, -1, 3)[:, :, 0]
    _, _, piv = scipy.linalg.qr(x_only, pivoting=True)
    ours = qr_markers(np.repeat(x_only[:, :, None], 3, axis=2).reshape(5, -1) / np.sqrt(3), cand, 5)
    np.testing.assert_array_equal(ours, piv[:5])


def test_greedy_on_the_proxy_finds_both_informative_vertices_and_respects_spacing():
    mesh = box_mesh()
    rng = np.random.default_rng(1)
    inf = [40, 230]
    lat = rng.uniform(-1, 1, (500, 2))
    U = _fields(mesh, lat, inf, rng)
    train, valid = U[:400], U[400:]
    basis = fit_pca(train.reshape(400, -1), 12)
    proxy = QuadraticProxy(basis, train, valid)
    modes = basis.components * basis.singular_values[:, None]
    cand = np.arange(mesh.n_vertices)
    picked, scores = greedy_markers(proxy, modes, cand, 2, shortlist=10)
    assert sorted(picked.tolist()) == inf
    assert scores[1] < scores[0] and scores[1] < proxy(np.array([0, 1]))  # better than two arbitrary vertices
    # forbid vertex 230's neighbourhood: a 200 mm spacing leaves only one marker possible
    with pytest.raises(MarkerError, match="fit 200 mm apart"):
        greedy_markers(proxy, modes, cand, 2, points=mesh.points, min_distance=200.0)
    far, _ = greedy_markers(proxy, modes, cand, 3, points=mesh.points, min_distance=15.0)
    d = np.linalg.norm(mesh.points[far][:, None] - mesh.points[far][None], axis=2)
    assert d[np.triu_indices(3, 1)].min() > 15.0
    with pytest.raises(MarkerError, match="only 2 candidate"):
        qr_markers(modes, np.array([1, 2]), 3)
    # exchange refinement from two uninformative vertices finds the two informative ones
    swapped, best, n_scores = exchange_markers(proxy, modes, cand, [0, 1], shortlist=10)
    assert sorted(swapped.tolist()) == inf and best == pytest.approx(proxy(swapped)) and best < proxy(np.array([0, 1]))
    assert n_scores > 1
    kept, same, _ = exchange_markers(proxy, modes, cand, inf, shortlist=10)  # nothing beats the informative pair
    assert kept.tolist() == inf and same == pytest.approx(proxy(np.array(inf)))


def test_plan_markers_on_a_data_set_count_and_target():
    ds = FakeDataset(n=200, n_test2=0)
    plan = plan_markers(ds, 4, region="any", shortlist=8)
    assert plan.count == 4 and len(set(plan.markers.tolist())) == 4
    assert not np.isin(plan.markers, ds.fixed).any()
    assert np.all(np.diff(plan.proxy_errors) < 0)  # each greedy step lowers the validation error here
    assert plan.proxy_error <= plan.proxy_errors[-1] and np.isin(plan.markers, ds.fixed).sum() == 0
    assert plan.proxy_error == pytest.approx(plan.proxy(plan.markers))
    target = float(plan.proxy_errors[2]) * 1.0001  # reached with 3 markers, not with 2
    tplan = plan_markers(ds, target_mm=target, region="any", shortlist=8, exchange_rounds=0)
    assert tplan.count == 3 and tplan.target_reached and tplan.exchanged == 0
    np.testing.assert_array_equal(tplan.markers, plan.path[:3])  # without exchanges plans are the path's prefixes
    unreachable = plan_markers(ds, target_mm=1e-9, max_count=3, region="any", shortlist=8)
    assert unreachable.count == 3 and unreachable.target_reached is False
    with pytest.raises(MarkerError, match="either"):
        plan_markers(ds, 3, target_mm=1.0)


def test_the_planned_rule_trains_on_markers_planned_from_the_simulations(tmp_path, monkeypatch):
    """``markers.rule = "planned"``: the run plans ``markers.count`` surface markers at least
    ``markers.min_distance`` apart on the store's train/valid fields and trains with them; the
    plan is saved beside the model; given ids win."""
    import json

    from tissuecast.app import pipeline
    from tissuecast.config import Config, with_overrides

    ds = FakeDataset(n=200, n_test2=0)
    monkeypatch.setattr("tissuecast.dataset.open_dataset", lambda store: ds)
    cfg = with_overrides(Config(), markers={"rule": "planned", "count": 4, "min_distance": 2.0},
                         surrogate={"epochs": 30, "calibration": "none"})
    expected = plan_markers(ds, 4, region="surface", min_distance=2.0)
    assert not np.array_equal(np.sort(expected.markers), np.sort(ds.markers[:4]))  # not the store's own markers
    model, _ = pipeline.train_from_store(cfg, "unused.zarr", model_folder=tmp_path / "model", onnx=False)
    np.testing.assert_array_equal(model.markers, expected.markers)
    saved = json.loads((tmp_path / "model" / pipeline.PLAN_FILE).read_text())
    assert saved["markers"] == expected.markers.tolist() and saved["min_distance_mm"] == 2.0
    points = ds.mesh.points[model.markers]
    assert np.linalg.norm(points[:, None] - points[None], axis=2)[np.triu_indices(4, 1)].min() > 2.0
    given = with_overrides(cfg, markers={"ids": [10, 20, 30]})
    model, _ = pipeline.train_from_store(given, "unused.zarr", model_folder=tmp_path / "given", onnx=False)
    np.testing.assert_array_equal(model.markers, [10, 20, 30])
    assert not (tmp_path / "given" / pipeline.PLAN_FILE).exists()


def test_the_markers_command_says_a_planned_rule_plans_at_training(tmp_path, capsys):
    from pathlib import Path

    from tissuecast.cli.main import main

    preset = Path(__file__).resolve().parents[2] / "configs" / "embedded.toml"
    assert main(["markers", "phantom", "--config", str(preset), "--out", str(tmp_path / "mk")]) == 0
    assert "markers.rule = 'planned'" in capsys.readouterr().out
    assert main(["markers", "phantom", "--out", str(tmp_path / "paper")]) == 0
    assert "planned" not in capsys.readouterr().out


def _attached(ds, margin):
    """The fake data set drawing an attached region's extent: the nominal edge at z = 10 mm, the
    surface distance z - 10 (mm; inf inside), the margin drawn within ``margin``."""
    from types import SimpleNamespace

    p, surf = ds.mesh.points, np.asarray(ds.mesh.surface_vertices)
    distance = np.full(len(p), np.inf)
    distance[surf] = p[surf, 2] - 10.0
    ds.config = SimpleNamespace(scenario=SimpleNamespace(uncertain=SimpleNamespace(attached_margin=margin)))
    ds.scenario_arrays = {"attached_distance": distance}
    return distance


def _least_shares(U, others, band):
    """Each band vertex's least share of the markers' motion (it included), by loops."""
    out = []
    for v in band:
        shares = []
        for u in U:
            rms = np.sqrt((sum(np.sum(u[k] ** 2) for k in others) + np.sum(u[v] ** 2)) / (len(others) + 1))
            shares.append(np.linalg.norm(u[v]) / rms)
        out.append(min(shares))
    return np.array(out)


def test_a_sentinel_marker_watches_just_beyond_the_attached_regions_drawn_range(caplog):
    from tissuecast.planning.sentinel import SENTINEL_REACH, sentinel_marker

    ds = FakeDataset(n=200, n_test2=0)
    distance = _attached(ds, (-2.0, 2.0))
    p = ds.mesh.points
    plain = plan_markers(ds, 4, min_distance=2.0)
    plan = plan_markers(ds, 4, min_distance=2.0, sentinel=True)
    assert plain.sentinel == -1  # without the flag, or without a drawn extent, no sentinel
    assert plan.count == 4 and plan.sentinel == plan.markers[-1] and plan.as_dict()["sentinel"] == plan.sentinel
    assert 2.0 < distance[plan.sentinel] <= 2.0 + SENTINEL_REACH  # no draw holds it; a region 5 mm larger would
    gaps = np.linalg.norm(p[plan.markers][:, None] - p[plan.markers][None], axis=2)[np.triu_indices(4, 1)]
    assert gaps.min() >= 2.0 and len(set(plan.markers.tolist())) == 4
    assert plan.proxy_error == pytest.approx(plan.proxy(plan.markers))
    # it costs the plan one marker's worth at most: no worse than the plain plan for three
    assert plan.proxy_error <= plan_markers(ds, 3, min_distance=2.0).proxy_error
    # of the band's vertices it is the one whose least share of the markers' motion is largest
    train = ds.select("train")
    U = np.asarray(ds.displacements[train], dtype=np.float64)
    others = plan.markers[:3]
    band = np.asarray(ds.mesh.surface_vertices)
    band = band[(distance[band] > 2.0) & (distance[band] <= 2.0 + SENTINEL_REACH)]
    band = band[np.linalg.norm(p[band][:, None] - p[others][None], axis=2).min(axis=1) >= 2.0]
    least = _least_shares(U, others, band)
    v, share = sentinel_marker(ds.displacements, train, others, plan.candidates, distance, 2.0, points=p,
                               min_distance=2.0)
    assert v == band[np.argmax(least)] and share == pytest.approx(least.max(), rel=1e-9)
    # a simulation that held that vertex still disqualifies it
    ds.displacements[train[0], v] = 0.0
    assert sentinel_marker(ds.displacements, train, others, plan.candidates, distance, 2.0, points=p,
                           min_distance=2.0)[0] not in (v, -1)
    # no vertex within reach of the range: the plain plan, and the log says why
    _attached(ds, (-2.0, 40.0))
    with caplog.at_level("WARNING"):
        none = plan_markers(ds, 4, min_distance=2.0, sentinel=True)
    assert none.sentinel == -1 and "no sentinel marker" in caplog.text
    np.testing.assert_array_equal(none.markers, plan_markers(ds, 4, min_distance=2.0).markers)
    # with a target error the sentinel comes on top of the markers that reach it
    _attached(ds, (-2.0, 2.0))
    ref = plan_markers(ds, target_mm=float(plain.proxy_errors[1]) * 1.0001, min_distance=2.0, exchange_rounds=0)
    target = plan_markers(ds, target_mm=float(plain.proxy_errors[1]) * 1.0001, min_distance=2.0, exchange_rounds=0,
                          sentinel=True)
    assert target.count == ref.count + 1 and target.sentinel == target.markers[-1]
    np.testing.assert_array_equal(target.markers[:-1], ref.markers)


def test_the_plan_command_names_the_sentinel_and_can_leave_it_out(tmp_path, monkeypatch, capsys):
    import csv
    import json

    from tissuecast.cli.main import main

    ds = FakeDataset(n=200, n_test2=0)
    _attached(ds, (-2.0, 2.0))
    monkeypatch.setattr("tissuecast.dataset.open_dataset", lambda store: ds)
    assert main(["markers", "plan", "fake.zarr", "--count", "4", "--min-distance", "2", "--out", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    plan = json.loads((tmp_path / "s.json").read_text())["plan"]
    rows = list(csv.DictReader((tmp_path / "s.csv").open()))
    assert plan["sentinel"] == plan["markers"][-1] >= 0 and f"sentinel: vertex {plan['sentinel']}" in out
    assert [r["role"] for r in rows] == ["marker"] * 3 + ["sentinel"]
    assert main(["markers", "plan", "fake.zarr", "--count", "4", "--min-distance", "2", "--no-sentinel",
                 "--out", str(tmp_path / "n")]) == 0
    assert json.loads((tmp_path / "n.json").read_text())["plan"]["sentinel"] == -1
    assert "sentinel" not in capsys.readouterr().out


def test_the_planned_rule_makes_the_last_marker_a_sentinel_unless_told_not_to(tmp_path, monkeypatch):
    import json

    from tissuecast.app import pipeline
    from tissuecast.config import Config, with_overrides

    ds = FakeDataset(n=200, n_test2=0)
    distance = _attached(ds, (-2.0, 2.0))
    monkeypatch.setattr("tissuecast.dataset.open_dataset", lambda store: ds)
    cfg = with_overrides(Config(), markers={"rule": "planned", "count": 4, "min_distance": 2.0},
                         surrogate={"epochs": 5, "calibration": "none"})
    model, _ = pipeline.train_from_store(cfg, "unused.zarr", model_folder=tmp_path / "model", onnx=False)
    saved = json.loads((tmp_path / "model" / pipeline.PLAN_FILE).read_text())
    assert saved["sentinel"] == int(model.markers[-1]) and 2.0 < distance[model.markers[-1]] <= 7.0
    off = with_overrides(cfg, markers={"sentinel": False})
    model, _ = pipeline.train_from_store(off, "unused.zarr", model_folder=tmp_path / "off", onnx=False)
    assert json.loads((tmp_path / "off" / pipeline.PLAN_FILE).read_text())["sentinel"] == -1
    np.testing.assert_array_equal(model.markers, plan_markers(ds, 4, min_distance=2.0).markers)
