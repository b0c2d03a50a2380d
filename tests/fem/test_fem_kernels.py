"""Compiled (numba) element kernels against the numpy reference implementation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_fem_assembly import distorted_box, smooth_state

from tissuecast.errors import DependencyError, SolverSetupError
from tissuecast.fem import NeoHookean, Problem, kernels
from tissuecast.fem.assembly import Assembler

needs_numba = pytest.mark.skipif(not kernels.available(), reason="numba missing")


def pair(prob, rule="default", weights=None):
    out = []
    for backend in ("numpy", "numba"):
        asm = Assembler(prob.nodes, prob.connectivity, prob.order, prob.material, prob.free_mask, rule, backend)
        if weights is not None:  # element weights folded into the quadrature, as the reduced model does
            asm.geometry = dataclasses.replace(asm.geometry, weight=asm.geometry.weight * weights[:, None])
        out.append(asm)
    return out


@needs_numba
@pytest.mark.parametrize("order,rule", [(1, "default"), (2, "default"), (2, "high")])
def test_compiled_kernels_equal_numpy_ones(order, rule):
    prob = Problem(distorted_box(seed=7), NeoHookean(0.021, 0.45), fixed=[0, 3, 12], order=order)
    rng = np.random.default_rng(8)
    weights = rng.uniform(0.0, 3.0, len(prob.connectivity))
    for w in (None, weights):
        ref, fast = pair(prob, rule, w)
        for amplitude in (0.0, 0.3, 0.6):
            u = smooth_state(prob.nodes, rng, amplitude)
            f0, k0, j0 = ref.tangent(u)
            f1, k1, j1 = fast.tangent(u)
            scale_f, scale_k = max(np.abs(f0).max(), 1e-30), np.abs(k0).max()
            assert np.abs(f1 - f0).max() <= 1e-12 * scale_f + 1e-300
            assert np.abs(k1 - k0).max() <= 1e-12 * scale_k
            assert j1 == pytest.approx(j0, rel=1e-13)
            e0, g0, _ = ref.energy_and_force(u)
            e1, g1, jj = fast.energy_and_force(u)
            assert e1 == pytest.approx(e0, rel=1e-12, abs=1e-15 * np.abs(k0).max())
            assert np.abs(g1 - f0).max() <= 1e-12 * scale_f + 1e-300
            assert fast.energy(u) == pytest.approx(e0, rel=1e-12, abs=1e-15 * np.abs(k0).max())
            assert np.abs(fast.internal_force(u)[0] - ref.internal_force(u)[0]).max() <= 1e-12 * scale_f + 1e-300
            assert jj == pytest.approx(j0, rel=1e-13)


@needs_numba
def test_compiled_kernels_flag_inverted_and_invalid_states_like_numpy():
    prob = Problem(distorted_box(seed=9), NeoHookean(), fixed=[0, 3, 12], order=2)
    ref, fast = pair(prob)
    u = -2.5 * (prob.nodes - prob.nodes.mean(axis=0))  # x = -1.5 X: every element inverted
    assert ref.energy(u) == fast.energy(u) == np.inf
    e0, _, j0 = ref.energy_and_force(u)
    e1, _, j1 = fast.energy_and_force(u)
    assert e0 == e1 == np.inf and j1 == pytest.approx(j0) and j1 < 0
    assert fast.tangent(u)[2] == pytest.approx(ref.tangent(u)[2])
    bad = np.zeros_like(u)
    bad[5, 1] = np.nan
    e, _, j = fast.energy_and_force(bad)
    assert np.isnan(j) and not e < np.inf  # never mistaken for a valid state
    assert not fast.energy(bad) < np.inf


def test_backend_choice_and_errors(monkeypatch):
    prob = Problem(distorted_box(), NeoHookean(), fixed=[0, 3, 12], order=1)
    make = lambda b="auto": Assembler(prob.nodes, prob.connectivity, 1, prob.material, prob.free_mask, backend=b)  # noqa: E731
    monkeypatch.setenv("TISSUECAST_KERNELS", "numpy")
    assert make().backend == "numpy"
    monkeypatch.delenv("TISSUECAST_KERNELS")
    assert make().backend == ("numba" if kernels.available() else "numpy")
    with pytest.raises(SolverSetupError, match="'auto', 'numba' or 'numpy'"):
        make("fortran")
    monkeypatch.setattr(kernels, "available", lambda: False)
    with pytest.raises(DependencyError, match=r"tissuecast\[fast\]"):
        make("numba")
    assert make().backend == "numpy"
