"""benchmarks/discretisation.py with quadratic elements on the store's own mesh as the reference:
the cached answers are the samples' own P2 solutions, and every model is evaluated against both."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tissuecast.config import with_overrides
from tissuecast.dataset import open_dataset, simulate
from tissuecast.fem import Solver
from tissuecast.scenario import restore_scenario
from tissuecast.surrogate import DeformationModel

from bench_helpers import SPRING_HELD, load_benchmark
from dataset_helpers import small_config


def test_quadratic_reference_and_models_against_both(tmp_path, capsys):
    cfg = with_overrides(small_config(tmp_path, n_samples=40, n_test2=0, alpha=0.0, calibration_samples=2,
                                      predictor_samples=8, split=[6.0, 2.0, 2.0],
                                      store=str(tmp_path / "data.zarr")),
                         forces={"loading": "traction", "target_max_displacement": 4.0}, scenario=SPRING_HELD,
                         solver={"order": 1}, surrogate={"epochs": 40, "patience": 0, "calibration": "none"})
    simulate(cfg, progress=False)
    ds = open_dataset(cfg.dataset.store)
    DeformationModel.from_dataset(ds, cfg).save(tmp_path / "model")
    mod = load_benchmark("discretisation")
    assert mod.main([cfg.dataset.store, "--samples", "2", "--reference", "p2", "--cache", str(tmp_path / "c"),
                     "--model", f"linear={tmp_path / 'model'}"]) == 0
    out = capsys.readouterr().out
    assert "against P2 on this mesh, 2 test-1 samples" in out
    assert out.count("mm from the supports and nan mm from the instrument's contact") == 2  # no instrument here
    assert sum(line.startswith("linear") for line in out.splitlines()) == 2  # against the data and the reference
    cached = sorted((tmp_path / "c").glob("sample_*.p2.npy"))
    assert len(cached) == 2 and not list((tmp_path / "c").glob("*.reference.npy"))
    # each sample's printed figures, recomputed from the store's field and the cached P2 answer
    printed = re.findall(r"sample (\d+): peak ([0-9.]+) mm, data's largest error ([0-9.]+) % of it \(([0-9.]+) % after a "
                         r"rigid fit, which turns it by ([0-9.]+) deg\)", out)
    assert len(printed) == 2
    for k, peak, largest, flexible, angle in printed:
        ref = np.load(tmp_path / "c" / f"sample_{int(k):05d}.p2.npy")
        data = np.asarray(ds.displacements[int(k)], dtype=np.float64)
        top = np.linalg.norm(ref, axis=1).max()
        errors, deg = mod._after_rigid(ds.mesh.points, data, ref)
        assert float(peak) == pytest.approx(top, abs=0.006)
        assert float(largest) == pytest.approx(100 * np.linalg.norm(data - ref, axis=1).max() / top, abs=0.06)
        assert float(flexible) == pytest.approx(100 * errors.max() / top, abs=0.06)
        assert float(angle) == pytest.approx(deg, abs=0.006)
        assert float(largest) > 0.1  # P1 is not P2
    # the model against the data and against the reference: its Offset_max on each, recomputed
    rows = {line.split()[1]: float(line.split()[2]) for line in out.splitlines() if line.startswith("linear")}
    model = DeformationModel.load(tmp_path / "model")
    kept = [int(k) for k, *_ in printed]
    for truth, fields in (("data", [np.asarray(ds.displacements[k], dtype=np.float64) for k in kept]),
                          ("reference", [np.load(tmp_path / "c" / f"sample_{k:05d}.p2.npy") for k in kept])):
        offsets = [np.linalg.norm(model.predict(u[model.markers]) - u, axis=1).max() for u in fields]
        assert rows[truth] == pytest.approx(np.mean(offsets), abs=0.006)
    assert rows["reference"] != rows["data"]
    record = json.loads((tmp_path / "c" / "reference.json").read_text())
    assert record == {"path": "from the data set's answer"}  # this store's samples start from a reduced guess
    # the cached answer is the sample's own P2 solution, its loads the store's (the store's LBO
    # basis: a basis computed again may differ in its eigenvectors' signs), solved from zero here
    k = int(cached[0].name.split("_")[1].split(".")[0])
    sc = restore_scenario(ds.mesh, with_overrides(cfg, solver={"order": 2}), ds.scenario_arrays, ds.basis)
    x = sc.sample(int(ds.seed[k]), float(ds.alpha[k]))
    u2 = Solver(sc.problem(), with_overrides(cfg, solver={"order": 2}).solver).solve(x.surface, **x.solve_keywords())
    np.testing.assert_allclose(np.load(cached[0]), u2.displacement, atol=2e-3 * np.abs(u2.displacement).max())
    u1 = np.asarray(ds.displacements[k])
    assert np.abs(u1 - u2.displacement).max() > 1e-3 * np.abs(u2.displacement).max()  # P1 is not P2
    with pytest.raises(SystemExit, match="quadratic already"):
        q = with_overrides(cfg, dataset={"store": str(tmp_path / "q.zarr"), "n_samples": 20}, solver={"order": 2})
        simulate(q, progress=False)
        mod.main([q.dataset.store, "--reference", "p2"])


def test_a_swing_of_the_whole_body_is_taken_out_and_its_angle_measured():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)) * 20.0
    ref = rng.normal(size=(50, 3))
    angle = np.radians(7.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    swung = (points + ref) @ turn.T + np.array([1.0, -2.0, 0.5]) - points  # the reference, turned and moved
    bump = np.zeros_like(ref)
    bump[3] = [0.0, 0.0, 0.4]
    errors, deg = load_benchmark("discretisation")._after_rigid(points, swung + bump, ref)
    assert deg == pytest.approx(7.0, abs=0.05)
    assert errors.max() == pytest.approx(0.4, abs=0.02) and int(np.argmax(errors)) == 3
    assert np.linalg.norm(swung - ref, axis=1).max() > 2.0  # before the fit the swing dominates
