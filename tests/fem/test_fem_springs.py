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


def _held_box():
    """A P2 box (10 x 10 x 20 mm) attached at its base, springs on every node of its top face."""
    from tissuecast.fem import Problem

    mesh = box_grid(2, 2, 4, (10.0, 10.0, 20.0))
    base = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.0))
    top = np.flatnonzero(np.isclose(mesh.points10[:, 2], 20.0))
    springs = NodalSprings(top, np.tile(0.02 * np.eye(3), (len(top), 1, 1)))
    return mesh, Problem(mesh, NeoHookean(), base, order=2, springs=springs), base


def test_tangent_with_springs_matches_finite_differences():
    from tissuecast.fem import Solver

    mesh, problem, _ = _held_box()
    asm = Solver(problem).assembler
    rng = np.random.default_rng(3)
    u = 0.3 * rng.normal(size=(len(problem.nodes), 3))
    _, data, jmin = asm.tangent(u)
    assert jmin > 0
    d = np.zeros(u.shape)
    d.ravel()[asm.free_dofs] = rng.normal(size=len(asm.free_dofs))  # the held dofs stay put
    h = 1e-6
    slope = (asm.internal_force(u + h * d)[0] - asm.internal_force(u - h * d)[0]) / (2 * h)
    kd = asm.matrix(data) @ d.ravel()[asm.free_dofs]
    np.testing.assert_allclose(kd, slope[asm.free_dofs], rtol=0, atol=1e-7 * np.abs(slope).max())


def test_reactions_of_attachment_and_springs_balance_loads_and_gravity():
    """Sum of the base's reactions and the springs' forces balances the applied loads and the
    body loads (gravity), to the solver's tolerance; the springs carry a real share."""
    from tissuecast.fem import Solver
    from tissuecast.scenario.gravity import body_loads

    mesh, problem, base = _held_box()
    forces = np.zeros((mesh.n_vertices, 3))
    side = np.flatnonzero(np.isclose(mesh.points[:, 0], 10.0) & (mesh.points[:, 2] > 5.0))
    forces[side] = [0.0, 2e-3, 0.0]
    gravity = body_loads(mesh, 2, 1e-9 * 9810.0 * np.array([0.3, 0.0, -1.0]))
    gravity[problem.constrained_nodes[0]] = 0.0  # loads on held nodes go straight into the supports
    res = Solver(problem).solve(forces, body_loads=gravity)
    assert res.converged and res.max_displacement > 0.5
    applied = forces.sum(axis=0) + gravity.sum(axis=0)
    springs = problem.springs
    spring_force = np.einsum("sij,sj->i", springs.stiffness, res.nodal_displacement[springs.nodes])
    total_reaction = res.nodal_reaction.sum(axis=0)  # constrained nodes: internal minus applied forces
    np.testing.assert_allclose(total_reaction - spring_force + applied, 0.0, atol=1e-3 * np.abs(applied).max())
    assert np.abs(spring_force).max() > 0.1 * np.abs(applied).max()
