"""Springs to ground in the assembly: their CSR positions, forces, energy and tangent."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.fem.assembly import Assembler
from tissuecast.fem.material import NeoHookean
from tissuecast.fem.springs import NodalSprings, SpringAssembly


@pytest.mark.parametrize("order", [1, 2])
def test_spring_assembly_adds_each_nodes_block_and_matches_its_forces(order):
    mesh = box_grid(2, 2, 3, (3.0, 3.0, 3.0))
    nodes = mesh.points if order == 1 else mesh.points10
    conn = mesh.tets if order == 1 else mesh.tets10
    free = np.ones((len(nodes), 3), dtype=bool)
    free[[0, 1, 4]] = False  # some springs sit on constrained nodes: they only reach the reactions
    asm = Assembler(nodes, conn, order, NeoHookean(), free.ravel())
    rng = np.random.default_rng(0)
    ids = np.sort(rng.choice(len(nodes), size=len(nodes) // 2, replace=False))
    ids = np.union1d(ids, [0, 1])
    a = rng.normal(size=(len(ids), 3, 3))
    springs = NodalSprings(ids, np.einsum("sij,skj->sik", a, a) * 0.01)
    sa = SpringAssembly(springs, asm)
    k = asm.matrix(sa.add_tangent(np.zeros(asm.nnz))).toarray()
    dense = np.zeros((asm.n_dofs, asm.n_dofs))
    for node, block in zip(ids, springs.stiffness):
        dense[3 * node : 3 * node + 3, 3 * node : 3 * node + 3] = block
    np.testing.assert_array_equal(k, dense[np.ix_(asm.free_dofs, asm.free_dofs)])
    u = rng.normal(size=(len(nodes), 3))
    np.testing.assert_allclose(sa.forces(u), dense @ u.ravel(), rtol=1e-13, atol=1e-16)
    assert sa.energy(u) == pytest.approx(0.5 * u.ravel() @ dense @ u.ravel(), rel=1e-13)
    # forces are the energy's gradient (central differences)
    d = rng.normal(size=u.shape)
    h = 1e-6
    slope = (sa.energy(u + h * d) - sa.energy(u - h * d)) / (2 * h)
    assert slope == pytest.approx(sa.forces(u) @ d.ravel(), rel=1e-8)
