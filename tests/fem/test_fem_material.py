"""Neo-Hookean (Abaqus/CalculiX NEO HOOKE form): stress and tangent against derivatives and closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.errors import SolverSetupError
from tissuecast.fem import NeoHookean

MAT = NeoHookean(0.021, 0.45)


def random_f(n, seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    f = np.eye(3) + scale * rng.standard_normal((n, 3, 3))
    f[np.linalg.det(f) < 0, :, 0] *= -1.0
    return f


def test_constants_follow_the_abaqus_definitions():
    e, nu = 0.021, 0.45
    assert MAT.c10 == pytest.approx(e / (4 * (1 + nu)))
    assert MAT.d1 == pytest.approx(6 * (1 - 2 * nu) / e)
    assert MAT.mu == pytest.approx(e / (2 * (1 + nu)))
    assert MAT.kappa == pytest.approx(e / (3 * (1 - 2 * nu)))


def test_stress_is_the_derivative_of_the_energy():
    f = random_f(6)
    h = 1e-6
    fd = np.zeros_like(f)
    for i in range(3):
        for j in range(3):
            d = np.zeros((3, 3))
            d[i, j] = h
            fd[:, i, j] = (MAT.energy(f + d) - MAT.energy(f - d)) / (2 * h)
    np.testing.assert_allclose(MAT.stress(f), fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_tangent_is_the_derivative_of_the_stress():
    f = random_f(6, seed=1)
    h = 1e-6
    fd = np.zeros((6, 9, 9))
    for i in range(3):
        for j in range(3):
            d = np.zeros((3, 3))
            d[i, j] = h
            fd[:, :, 3 * i + j] = ((MAT.stress(f + d) - MAT.stress(f - d)) / (2 * h)).reshape(6, 9)
    a = MAT.tangent(f)
    np.testing.assert_allclose(a, fd, rtol=1e-6, atol=1e-8 * np.abs(fd).max())
    np.testing.assert_allclose(a, np.swapaxes(a, -1, -2), atol=1e-15)  # hyperelastic: major symmetry


def test_tangent_matches_torch_autograd():
    torch = pytest.importorskip("torch")
    f = torch.tensor(random_f(1, seed=3)[0], dtype=torch.float64)

    def energy(x):
        j = torch.det(x)
        return MAT.c10 * (j ** (-2.0 / 3.0) * (x * x).sum() - 3.0) + (j - 1.0) ** 2 / MAT.d1

    hess = torch.autograd.functional.hessian(energy, f).reshape(9, 9).numpy()
    np.testing.assert_allclose(MAT.tangent(f.numpy()), hess, rtol=1e-10, atol=1e-14)


def test_small_strain_limit_is_isotropic_linear_elasticity():
    lam = MAT.kappa - 2.0 * MAT.mu / 3.0
    c = np.zeros((3, 3, 3, 3))
    d = np.eye(3)
    c += lam * np.einsum("ij,kl->ijkl", d, d) + MAT.mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))
    a = MAT.tangent(np.eye(3)).reshape(3, 3, 3, 3)
    # at F = I the tangent is C plus nothing else (no initial stress)
    np.testing.assert_allclose(a, c, atol=1e-15)
    np.testing.assert_allclose(MAT.stress(np.eye(3)), 0.0, atol=1e-16)


def test_objectivity_and_inversion_flag():
    f = random_f(4, seed=4)
    q, _ = np.linalg.qr(np.random.default_rng(5).standard_normal((3, 3)))
    q *= np.sign(np.linalg.det(q))
    np.testing.assert_allclose(MAT.stress(q @ f), q @ MAT.stress(f), atol=1e-14)
    np.testing.assert_allclose(MAT.energy(q @ f), MAT.energy(f), rtol=1e-12)
    assert np.isinf(MAT.energy(np.diag([1.0, 1.0, -0.5])))


def test_simple_shear_closed_form():
    # F = I + g e1 e2: J = 1, I1 = 3 + g^2, so P = mu (F - I1/3 F^-T) and the Cauchy stress is
    # sigma = mu (F F^T - I1/3 I): sigma12 = mu g, sigma11 = 2/3 mu g^2, sigma22 = sigma33 = -1/3 mu g^2
    g = 0.7
    f = np.eye(3)
    f[0, 1] = g
    p = MAT.stress(f)
    sigma = p @ f.T
    mu = MAT.mu
    expected = [[2 / 3 * mu * g**2, mu * g, 0], [mu * g, -mu * g**2 / 3, 0], [0, 0, -mu * g**2 / 3]]
    np.testing.assert_allclose(sigma, expected, atol=1e-15)
    assert p[0, 1] == pytest.approx(mu * g)
    assert p[1, 0] == pytest.approx(mu * g * (3 + g**2) / 3)


@pytest.mark.parametrize("kwargs", [{"youngs_modulus": 0.0}, {"youngs_modulus": float("nan")}, {"poisson_ratio": 0.5},
                                    {"poisson_ratio": -1.0}])
def test_bad_parameters_raise(kwargs):
    with pytest.raises(SolverSetupError):
        NeoHookean(**kwargs)
