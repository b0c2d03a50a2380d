"""Shape functions, quadrature rules and reference gradients of the P1/P2 tetrahedra."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tissuecast.fem.elements import quadrature, reference_gradients, shape_functions, shape_gradients
from tissuecast.mesh import TET_EDGES

REF_CORNERS = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def reference_nodes(order):
    if order == 1:
        return REF_CORNERS
    mids = 0.5 * (REF_CORNERS[TET_EDGES[:, 0]] + REF_CORNERS[TET_EDGES[:, 1]])
    return np.vstack([REF_CORNERS, mids])


def monomial_integral(a, b, c):
    """Exact integral of xi^a eta^b zeta^c over the reference tetrahedron."""
    return math.factorial(a) * math.factorial(b) * math.factorial(c) / math.factorial(a + b + c + 3)


@pytest.mark.parametrize("order", [1, 2])
def test_shape_functions_are_nodal_and_partition_unity(order):
    nodes = reference_nodes(order)
    np.testing.assert_allclose(shape_functions(order, nodes), np.eye(len(nodes)), atol=1e-14)
    pts = np.random.default_rng(0).dirichlet(np.ones(4), size=20)[:, 1:]
    np.testing.assert_allclose(shape_functions(order, pts).sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(shape_gradients(order, pts).sum(axis=1), 0.0, atol=1e-13)
    # the shape functions reproduce the coordinates (isoparametric, straight edges)
    np.testing.assert_allclose(shape_functions(order, pts) @ nodes, pts, atol=1e-14)


@pytest.mark.parametrize("order", [1, 2])
def test_shape_gradients_match_finite_differences(order):
    pts = np.random.default_rng(1).dirichlet(np.ones(4), size=5)[:, 1:]
    h = 1e-6
    fd = np.stack(
        [(shape_functions(order, pts + h * e) - shape_functions(order, pts - h * e)) / (2 * h) for e in np.eye(3)], axis=-1
    )
    np.testing.assert_allclose(shape_gradients(order, pts), fd, atol=1e-8)


@pytest.mark.parametrize("order,rule", [(1, "default"), (2, "default"), (2, "high")])
def test_quadrature_is_exact_to_its_degree(order, rule):
    qr = quadrature(order, rule)
    assert qr.weights.sum() == pytest.approx(1.0 / 6.0, abs=1e-15)
    for deg in range(qr.degree + 1):
        for a in range(deg + 1):
            for b in range(deg + 1 - a):
                c = deg - a - b
                x = qr.points
                val = np.sum(qr.weights * x[:, 0] ** a * x[:, 1] ** b * x[:, 2] ** c)
                assert val == pytest.approx(monomial_integral(a, b, c), rel=1e-12, abs=1e-15)
    # and not exact one degree higher (the rules are what they claim, not more)
    x = qr.points
    errs = [
        abs(np.sum(qr.weights * x[:, 0] ** a * x[:, 1] ** (qr.degree + 1 - a)) - monomial_integral(a, qr.degree + 1 - a, 0))
        for a in range(qr.degree + 2)
    ]
    assert max(errs) > 1e-8


@pytest.mark.parametrize("order", [1, 2])
def test_reference_gradients_integrate_volume_and_linear_fields(order):
    rng = np.random.default_rng(2)
    corners = rng.standard_normal((4, 3))
    if np.linalg.det(corners[1:] - corners[0]) < 0:
        corners[[1, 2]] = corners[[2, 1]]
    nodes = reference_nodes(order) @ (corners[1:] - corners[0]) + corners[0]
    geo = reference_gradients(nodes, np.arange(len(nodes))[None], order)
    volume = abs(np.linalg.det(corners[1:] - corners[0])) / 6.0
    assert geo.weight.sum() == pytest.approx(volume, rel=1e-13)
    grad_true = rng.standard_normal((3, 3))
    u = nodes @ grad_true.T  # linear field u = G X
    grad = np.einsum("ai,qaJ->qiJ", u, geo.grad[0])
    np.testing.assert_allclose(grad, np.broadcast_to(grad_true, grad.shape), atol=1e-12)
