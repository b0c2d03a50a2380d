"""The simulator's sensitivities at stored samples (tissuecast.dataset.sensitivities), along
the load weights and the drawn parameters, against central differences of full solves, and
the samples that have none."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from dataset_helpers import small_config

from tissuecast.config import with_overrides
from tissuecast.dataset import open_dataset, simulate
from tissuecast.dataset.sensitivities import (WEIGHT_SD, Sensitivities, _tangent_solve, dataset_sensitivities,
                                             equilibrium_response, parameter_directions)
from tissuecast.dataset.worker import SampleContext
from tissuecast.errors import ConfigError


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sens")
    cfg = with_overrides(small_config(folder, n_samples=6, n_test2=2, workers=1),
                         solver={"force_tolerance": 1e-10})
    path = folder / "s.zarr"
    simulate(cfg, path, progress=False)
    return open_dataset(path)


def test_sensitivities_match_central_differences_of_full_solves(store):
    ds = store
    lbo = ds.select("train")
    S = dataset_sensitivities(ds, lbo)
    ctx = SampleContext(ds.recipe())
    sc, s = ctx.scenario, int(lbo[0])
    assert S.values.shape == (len(lbo), 3 * sc.surface_forces.basis.n_vectors, ds.n_vertices, 3) == (len(lbo), 24, 140, 3)
    assert np.isfinite(S.values).all()
    inputs = sc.sample(int(ds.seed[s]), float(ds.alpha[s]))
    solver = ctx.solver(0)
    h = 1e-2 * WEIGHT_SD
    for k in (0, 7, 20):
        fields = []
        for sign in (1.0, -1.0):
            w = inputs.weights.copy()
            w.flat[k] += sign * h
            moved = sc.inputs_for(int(ds.seed[s]), _field(sc, w, float(ds.alpha[s])), w)
            fields.append(solver.solve(moved.surface, None, **moved.solve_keywords()).displacement)
        fd = (fields[0] - fields[1]) / (2 * h) * WEIGHT_SD
        assert np.linalg.norm(S.values[0, k] - fd) <= 1e-3 * np.linalg.norm(fd), k


def _field(sc, w, alpha):
    from tissuecast.forces.fields import lbo_field

    return lbo_field(sc.surface_forces.basis, w, alpha, sc.mesh.n_vertices)


def test_test2_samples_have_none_and_rows_follow_the_indices(store):
    ds = store
    t2, train = ds.select("test2"), ds.select("train")
    S = dataset_sensitivities(ds, np.concatenate([t2, train[:2]]))
    assert isinstance(S, Sensitivities) and list(S.indices) == sorted(np.concatenate([t2, train[:2]]).tolist())
    rows = S.rows([int(train[1]), int(t2[0]), 10_000])
    assert np.isfinite(rows[0]).all() and np.isnan(rows[1]).all() and np.isnan(rows[2]).all()
    np.testing.assert_array_equal(rows[0], S.values[list(S.indices).index(int(train[1]))])


@pytest.fixture(scope="module")
def uncertain_store(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sens_unc")
    cfg = with_overrides(small_config(folder, n_samples=4, n_test2=1, workers=1), solver={"force_tolerance": 1e-10},
                         scenario={"uncertain": {"youngs_modulus": [0.5, 2.0], "poisson_ratio": [0.40, 0.49]}})
    path = folder / "u.zarr"
    simulate(cfg, path, progress=False)
    return open_dataset(path)


def test_parameter_directions_match_central_differences_of_full_solves(uncertain_store):
    ds = uncertain_store
    s = int(ds.select("train")[0])
    S = dataset_sensitivities(ds, [s])
    ctx = SampleContext(ds.recipe())
    sc = ctx.scenario
    (e_name, e_log, _, e_sd), (nu_name, nu_log, _, nu_sd) = parameter_directions(sc)
    assert (e_name, e_log, nu_name, nu_log) == ("youngs_modulus", True, "poisson_ratio", False)
    assert S.values.shape[1] == 24 + 2 and np.isfinite(S.values).all()
    known = sc.sample(int(ds.seed[s]), float(ds.alpha[s]), nominal=True)
    drawn = sc.draw_for(int(ds.seed[s])).parameters
    for col, name, sd, log in ((24, e_name, e_sd, True), (25, nu_name, nu_sd, False)):
        h = 1e-2 * sd
        fields = []
        for sign in (1.0, -1.0):
            v = getattr(drawn, name)
            moved = sc.with_parameters(known, dataclasses.replace(drawn, **{name: v * np.exp(sign * h) if log else v + sign * h}))
            solver = ctx.solver(0).with_parameters(*moved.solver_parameters)
            fields.append(solver.solve(moved.surface, None, **moved.solve_keywords()).displacement)
        fd = (fields[0] - fields[1]) / (2 * h) * sd
        assert np.linalg.norm(S.values[0, col] - fd) <= 2e-3 * np.linalg.norm(fd), name


def test_a_store_of_quadratic_elements_is_refused_with_the_fix(tmp_path):
    cfg = with_overrides(small_config(tmp_path, n_samples=2, n_test2=0, workers=1), solver={"order": 2})
    simulate(cfg, tmp_path / "p2.zarr", progress=False)
    ds = open_dataset(tmp_path / "p2.zarr")
    with pytest.raises(ConfigError, match="linear elements.*sensitivity_weight = 0"):
        dataset_sensitivities(ds, ds.select("train"))


EMBEDDED_LIKE = {"name": "embedded", "pins": False,
                 "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
                 "springs": {"rule": "surface"},
                 "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5]}}


@pytest.mark.parametrize("backend", ["superlu", "auto"])
def test_the_response_holds_the_indented_dofs_and_solves_the_tangent_system(tmp_path, backend):
    """With held (indented) dofs, on the backend's factorisation: zero there, K du = f elsewhere."""
    cfg = with_overrides(small_config(tmp_path, n_samples=2, n_test2=0, workers=1),
                         forces={"loading": "traction"}, scenario=EMBEDDED_LIKE,
                         solver={"force_tolerance": 1e-10, "linear_solver": backend})
    simulate(cfg, tmp_path / "e.zarr", progress=False)
    ds = open_dataset(tmp_path / "e.zarr")
    s = int(ds.select("train")[0])
    ctx = SampleContext(ds.recipe())
    sc, solver = ctx.scenario, ctx.solver(0)
    inputs = sc.sample(int(ds.seed[s]), float(ds.alpha[s]))
    assert len(inputs.prescribed_ids) > 0
    u = np.asarray(ds.displacements[s], dtype=np.float64)
    forces = np.random.default_rng(1).normal(size=(3, u.size))
    du = equilibrium_response(solver, inputs, u, forces)
    held = (3 * np.asarray(inputs.prescribed_ids)[:, None] + np.arange(3)).ravel()
    assert np.abs(du[held]).max() == 0.0
    free = np.asarray(solver.free_dofs)
    rest = free[~np.isin(free, held)]
    _, data, _ = solver.assembler.tangent(u)
    K = solver.assembler.matrix(data)
    position = np.searchsorted(free, rest)
    residual = (K @ du[free])[position] - forces[:, rest].T
    assert np.linalg.norm(residual) <= 1e-8 * np.linalg.norm(forces[:, rest])
    assert np.linalg.norm(du[rest]) > 0.0
    # a matrix the backend cannot factorise (not positive definite): SciPy's LU solves it
    b = np.random.default_rng(2).normal(size=(len(free), 2))
    x = _tangent_solve(solver, -data, b)
    assert np.linalg.norm(-(K @ x) - b) <= 1e-8 * np.linalg.norm(b)
    S = dataset_sensitivities(ds, [s])
    assert np.isfinite(S.values).all() and np.abs(S.values[0].reshape(S.values.shape[1], -1)[:, held]).max() == 0.0
