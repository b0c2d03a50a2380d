"""Rigid registration from markers (Kabsch) and the non-rigid part of a displacement field."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import tissuecast as tc
from tissuecast.errors import RegistrationError
from tissuecast.registration import fit_rigid, nonrigid_part, rigid_registration_field, rigid_residuals


def _motion(seed):
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=rng).as_matrix()
    return rot, rng.uniform(-20, 20, 3)


@pytest.mark.parametrize("k", [3, 5, 12])
def test_a_rigid_motion_is_recovered_exactly_from_three_or_more_markers(k):
    rng = np.random.default_rng(k)
    x = rng.uniform(-30, 30, (k, 3))
    rot, t = _motion(k)
    fit = fit_rigid(x, x @ rot.T + t)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(fit.translation, t, atol=1e-9)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0, abs=1e-12)


def test_registration_field_moves_the_whole_mesh_rigidly_in_a_batch():
    mesh = tc.phantom()
    p = mesh.points
    markers = np.array([96, 752, 1000, 4, 431])
    motions = [_motion(s) for s in range(4)]
    truth = np.stack([p @ r.T + t - p for r, t in motions])  # (4, n, 3)
    field = rigid_registration_field(p, markers, truth[:, markers])
    assert field.shape == truth.shape
    assert np.abs(field - truth).max() < 1e-9
    single = rigid_registration_field(p, markers, truth[2, markers])
    assert np.abs(single - truth[2]).max() < 1e-9


def test_nonrigid_part_of_a_rigid_motion_is_zero():
    p = tc.phantom().points
    rot, t = _motion(7)
    u = p @ rot.T + t - p
    assert nonrigid_part(p, u) < 1e-9
    assert np.all(nonrigid_part(p, np.stack([u, 2 * np.zeros_like(u)])) < 1e-9)


def test_nonrigid_part_of_a_stretch_is_the_hand_computed_value():
    # the 8 corners of a cube of half-side a, stretched by eps along x: by symmetry the best
    # rigid fit is the identity, so every corner is left |eps a| away from it
    a, eps = 10.0, 0.1
    p = np.array([[sx, sy, sz] for sx in (-a, a) for sy in (-a, a) for sz in (-a, a)])
    u = np.zeros_like(p)
    u[:, 0] = eps * p[:, 0]
    np.testing.assert_allclose(rigid_residuals(p, u), eps * a, rtol=1e-12)
    assert nonrigid_part(p, u) == pytest.approx(1.0, rel=1e-12)
    # the same stretch after a rigid motion has the same non-rigid part
    rot, t = _motion(3)
    moved = (p + u) @ rot.T + t - p
    assert nonrigid_part(p, moved) == pytest.approx(1.0, rel=1e-9)


def test_weights_change_the_fit_and_zero_weight_ignores_a_point():
    rng = np.random.default_rng(1)
    x = rng.uniform(-10, 10, (5, 3))
    rot, t = _motion(2)
    y = x @ rot.T + t
    y[4] += 5.0  # an outlier
    fit = fit_rigid(x, y, weights=[1, 1, 1, 1, 0])
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    assert not np.allclose(fit_rigid(x, y).rotation, rot, atol=1e-6)


@pytest.mark.parametrize("points, message", [
    (np.array([[0.0, 0, 0], [1, 0, 0]]), "at least 3"),
    (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5]]), "lie on one line"),
    (np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), "finite"),
])
def test_degenerate_markers_give_a_clear_error(points, message):
    with pytest.raises(RegistrationError, match=message):
        fit_rigid(points, points)
    assert issubclass(RegistrationError, ValueError)


def test_mismatched_shapes_are_refused():
    x = np.eye(3) * 10
    with pytest.raises(RegistrationError, match="moved positions must be"):
        fit_rigid(x, np.zeros((4, 3)))
    with pytest.raises(RegistrationError, match="weights"):
        fit_rigid(x, x, weights=[1, -1, 1])
    with pytest.raises(RegistrationError, match="marker displacements"):
        rigid_registration_field(tc.phantom().points, [0, 1, 2], np.zeros((4, 3)))
