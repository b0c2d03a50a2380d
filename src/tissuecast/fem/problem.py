"""The finite-element problem: mesh, material, element order and displacement constraints.

A :class:`Problem` is validated when it is built; the forces of each sample are checked by
:func:`check_forces` when a solve starts. Vertex ids are 0-based (CalculiX/Abaqus decks and
the paper count from 1).

Constraints act on all three components of a vertex: *fixed* vertices do not move,
*prescribed* vertices move by a given displacement (reached in proportion to the load
fraction). For quadratic elements a mid-edge node whose two end vertices are both
constrained is constrained too, to the mean of their displacements (the edge stays
straight, as linear interpolation of the vertex values); a mid-edge node with at most one
constrained end is free, as in a CalculiX deck that constrains corner nodes only.

A problem may also hold nodes by linear springs to ground (an elastic support,
:class:`~.springs.NodalSprings`) and give every element its own material
(:class:`~.material.NeoHookeanField`). Prescribed displacements that change from solve to
solve (an instrument's indentation) are not part of the problem: they are given to each solve
(:meth:`Problem.solve_constraints` turns them into constrained nodes the same way).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..errors import SolverSetupError
from ..mesh.tetmesh import TetMesh
from .material import NeoHookean, NeoHookeanField
from .springs import NodalSprings
from .rigid_motions import free_rigid_motions

__all__ = ["Problem", "check_forces", "build_problem"]


def _vertex_ids(ids, n: int, what: str) -> np.ndarray:
    arr = np.asarray(ids)
    if arr.size == 0:
        return np.zeros(0, dtype=np.int64)
    if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer) or np.all(np.mod(arr, 1) == 0)):
        raise SolverSetupError(f"{what} must be a 1-D list of integer vertex ids, got {np.asarray(ids).tolist()!r}")
    arr = arr.astype(np.int64)
    bad = (arr < 0) | (arr >= n)
    if bad.any():
        raise SolverSetupError(
            f"{what} vertex id {int(arr[bad][0])} is outside 0..{n - 1}; ids are 0-based "
            "(subtract 1 from 1-based Abaqus/CalculiX ids)"
        )
    if len(np.unique(arr)) != len(arr):
        raise SolverSetupError(f"{what} repeats vertex ids: {arr.tolist()}; list each vertex once")
    return arr


def _parse_prescribed(prescribed, n: int) -> tuple[np.ndarray, np.ndarray]:
    if prescribed is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    if isinstance(prescribed, dict):
        ids = list(prescribed.keys())
        vals = [np.asarray(v, dtype=np.float64) for v in prescribed.values()]
        vals = np.array(vals) if vals else np.zeros((0, 3))
    else:
        try:
            ids, vals = prescribed
        except (TypeError, ValueError):
            raise SolverSetupError(
                "prescribed must be a dict {vertex: (3,) displacement in mm} or a pair "
                "(vertex ids (k,), displacements (k, 3) mm)"
            ) from None
        vals = np.asarray(vals, dtype=np.float64)
    ids = _vertex_ids(ids, n, "prescribed")
    if vals.shape != (len(ids), 3):
        raise SolverSetupError(
            f"prescribed displacements must have shape ({len(ids)}, 3) (one (x, y, z) in mm per vertex), got {vals.shape}"
        )
    if not np.all(np.isfinite(vals)):
        raise SolverSetupError("prescribed displacements must be finite numbers of mm")
    return ids, vals


@dataclass(frozen=True, eq=False)
class Problem:
    """A nonlinear elasticity problem on a tetrahedral mesh.

    Args:
        mesh: the tetrahedral mesh (mm).
        material: the neo-Hookean material (MPa).
        fixed: (k,) int, 0-based ids of vertices with all displacement components fixed.
        order: element order, 2 (10-node tets, C3D10; default) or 1 (4-node tets).
        prescribed: optional prescribed vertex displacements (mm): a dict
            ``{vertex: (3,)}`` or a pair ``(ids (k,), displacements (k, 3))``.
        springs: optional linear springs to ground at element nodes (an elastic support),
            N/mm; springs at constrained nodes only reach the reactions.
        materials: optional per-element constants (m elements); ``material`` is then only the
            nominal material (e.g. of reports and decks without regions).
        can_swing: whether the body may swing about its supports as a near-rigid body (a few
            pins), so that the solver's rotation-aware line search and rotation deflation
            apply; None = True exactly when there are no springs. Set False for a body held
            by an attached surface region.

    Raises:
        SolverSetupError: ids out of range or repeated, a vertex both fixed and prescribed,
            or supports that leave rigid-body motion free (without springs: fewer than 3
            constrained vertices, or all of them on one line).
    """

    mesh: TetMesh
    material: NeoHookean = field(default_factory=NeoHookean)
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    order: int = 2
    prescribed: object = None
    springs: NodalSprings | None = None
    materials: NeoHookeanField | None = None
    can_swing: bool | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.mesh, TetMesh):
            raise SolverSetupError(f"mesh must be a TetMesh, got {type(self.mesh).__name__}")
        if not isinstance(self.material, NeoHookean):
            raise SolverSetupError(f"material must be a NeoHookean, got {type(self.material).__name__}")
        if self.order not in (1, 2):
            raise SolverSetupError(f"order must be 1 (4-node tets) or 2 (10-node tets), got {self.order!r}")
        n = self.mesh.n_vertices
        fixed = _vertex_ids(self.fixed, n, "fixed")
        pids, pvals = _parse_prescribed(self.prescribed, n)
        both = np.intersect1d(fixed, pids)
        if both.size:
            raise SolverSetupError(f"vertices {both.tolist()} are both fixed and prescribed; give each one constraint")
        constrained = np.concatenate([fixed, pids])
        self._check_extras()
        object.__setattr__(self, "can_swing", bool(self.springs is None if self.can_swing is None else self.can_swing))
        if self.springs is not None:
            if len(free_rigid_motions(self.nodes, _with_mid_edges(self.mesh, self.order, constrained), self.springs)):
                raise SolverSetupError("the fixed vertices and springs leave a rigid-body motion free; fix more "
                                       "vertices or give the springs tangential stiffness / a wider region")
        elif len(constrained) < 3:
            raise SolverSetupError(
                f"{len(constrained)} constrained vertices cannot stop rigid-body motion; "
                "fix at least 3 vertices that are not on one line"
            )
        if self.springs is None:
            p = self.mesh.points[constrained]
            sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if self.springs is None and sv[1] <= 1e-6 * max(sv[0], 1e-300):
            raise SolverSetupError(
                f"the constrained vertices {constrained.tolist()} lie on one line, so the body can still "
                "rotate about it; fix at least 3 vertices that are not collinear"
            )
        object.__setattr__(self, "fixed", fixed)
        object.__setattr__(self, "prescribed", (pids, pvals) if len(pids) else None)
        object.__setattr__(self, "_pids", pids)
        object.__setattr__(self, "_pvals", pvals)

    def _check_extras(self) -> None:
        if self.springs is not None and not isinstance(self.springs, NodalSprings):
            raise SolverSetupError(f"springs must be NodalSprings, got {type(self.springs).__name__}")
        if self.springs is not None and len(self.springs) and self.springs.nodes.max() >= len(self.nodes):
            raise SolverSetupError(f"spring node {int(self.springs.nodes.max())} is outside the {len(self.nodes)} "
                                   f"element nodes of order {self.order}")
        if self.materials is not None:
            if not isinstance(self.materials, NeoHookeanField):
                raise SolverSetupError(f"materials must be a NeoHookeanField, got {type(self.materials).__name__}")
            if len(self.materials) != self.mesh.n_tets:
                raise SolverSetupError(f"materials give {len(self.materials)} elements constants, the mesh has "
                                       f"{self.mesh.n_tets}")

    @property
    def element_material(self):
        """What the assembler evaluates: ``materials`` if given, else ``material``."""
        return self.materials if self.materials is not None else self.material

    def solve_constraints(self, prescribed) -> tuple[np.ndarray, np.ndarray]:
        """The element nodes a solve's own prescribed vertex displacements constrain.

        Args:
            prescribed: ``{vertex: (3,)}`` or ``(ids (k,), displacements (k, 3) mm)`` of vertices
                that are free in the problem, or None.

        Returns:
            ``(node ids (p,), displacement at full load (p, 3) mm)``: the vertices and, for P2,
            the mid-edge nodes whose two ends are constrained (by the problem or by this solve)
            and at least one of them by this solve, at the mean of their ends' values.

        Raises:
            SolverSetupError: bad ids or values, or a vertex the problem already constrains.
        """
        n = self.mesh.n_vertices
        ids, vals = _parse_prescribed(prescribed, n)
        if not len(ids):
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        clash = np.intersect1d(ids, np.concatenate([self.fixed, self._pids]))
        if clash.size:
            raise SolverSetupError(f"vertices {clash[:5].tolist()} are already fixed or prescribed by the problem; a "
                                   "solve may prescribe free vertices only")
        node_ids, values = [ids], [vals]
        if self.order == 2:
            value = np.full((n, 3), np.nan)
            value[self.fixed] = 0.0
            value[self._pids] = self._pvals
            value[ids] = vals
            mine = np.zeros(n, dtype=bool)
            mine[ids] = True
            e = self.mesh.edges
            k = np.flatnonzero(~np.isnan(value[e[:, 0], 0]) & ~np.isnan(value[e[:, 1], 0]) & mine[e].any(axis=1))
            node_ids.append(n + k)
            values.append(0.5 * (value[e[k, 0]] + value[e[k, 1]]))
        return np.concatenate(node_ids), np.vstack(values)

    @property
    def n_vertices(self) -> int:
        """Number of mesh vertices (rows of forces and displacements)."""
        return self.mesh.n_vertices

    @cached_property
    def nodes(self) -> np.ndarray:
        """(n_nodes, 3) float, mm: element nodes (vertices first, then P2 mid-edge nodes)."""
        return self.mesh.points if self.order == 1 else self.mesh.points10

    @cached_property
    def connectivity(self) -> np.ndarray:
        """(m, 4 or 10) int: element node ids."""
        return self.mesh.tets if self.order == 1 else self.mesh.tets10

    @cached_property
    def constrained_nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(node ids (c,), displacement at full load (c, 3) mm)`` of every constrained node."""
        n = self.mesh.n_vertices
        value = np.full((n, 3), np.nan)
        value[self.fixed] = 0.0
        value[self._pids] = self._pvals
        ids = np.flatnonzero(~np.isnan(value[:, 0]))
        vals = [value[ids]]
        node_ids = [ids]
        if self.order == 2:
            e = self.mesh.edges
            both = ~np.isnan(value[e[:, 0], 0]) & ~np.isnan(value[e[:, 1], 0])
            k = np.flatnonzero(both)
            node_ids.append(n + k)
            vals.append(0.5 * (value[e[k, 0]] + value[e[k, 1]]))
        return np.concatenate(node_ids), np.vstack(vals)

    @cached_property
    def free_mask(self) -> np.ndarray:
        """(3 n_nodes,) bool: True for unknown degrees of freedom."""
        free = np.ones((len(self.nodes), 3), dtype=bool)
        free[self.constrained_nodes[0]] = False
        return free.ravel()


def _with_mid_edges(mesh: TetMesh, order: int, vertices: np.ndarray) -> np.ndarray:
    """The vertices and, for P2, the mid-edge nodes between two of them."""
    vertices = np.asarray(vertices, dtype=np.int64)
    if order == 1 or not vertices.size:
        return vertices
    return np.concatenate([vertices, mesh.n_vertices + np.flatnonzero(np.isin(mesh.edges, vertices).all(axis=1))])


def check_forces(problem: Problem, forces) -> np.ndarray:
    """Validate nodal forces for a problem.

    Args:
        problem: the problem.
        forces: (n, 3) float, N, dead loads on the mesh vertices (for P2 the corner nodes), or
            (n_nodes, 3) on every element node (e.g. consistent loads of a traction or of
            gravity).

    Returns:
        float64 copy of the forces, shaped as given.

    Raises:
        SolverSetupError: wrong shape, non-finite values, or a non-zero force on a fixed or
            prescribed vertex (or, for forces on every node, on any constrained node).
    """
    f = np.asarray(forces, dtype=np.float64) if forces is not None else None
    n, n_nodes = problem.n_vertices, len(problem.nodes)
    if f is None or f.shape not in ((n, 3), (n_nodes, 3)):
        shape = None if f is None else f.shape
        raise SolverSetupError(f"forces must have shape ({n}, 3) (N per mesh vertex) or ({n_nodes}, 3) (N per "
                               f"element node), got {shape}")
    bad = ~np.isfinite(f).all(axis=1)
    if bad.any():
        raise SolverSetupError(
            f"{int(bad.sum())} force rows are not finite (first: vertex {int(np.flatnonzero(bad)[0])}); "
            "replace NaN/inf by numbers of N"
        )
    constrained = np.concatenate([problem.fixed, problem._pids]) if len(f) == n else problem.constrained_nodes[0]
    loaded = constrained[np.any(f[constrained] != 0.0, axis=1)]
    if loaded.size:
        raise SolverSetupError(
            f"forces act on constrained (fixed or prescribed) vertices {loaded.tolist()}; they would go "
            "straight into the supports: set those rows to zero"
        )
    return f.copy()


def build_problem(mesh: TetMesh, material: NeoHookean, fixed, *, order: int = 2, springs: NodalSprings | None = None,
                  materials: NeoHookeanField | None = None, can_swing: bool | None = None) -> Problem:
    """The finite-element problem of a material, supports and element order on ``mesh``.

    A run configuration is translated by its callers (``[material]`` gives
    ``NeoHookean(youngs_modulus, poisson_ratio)``, ``solver.order`` the order; a scenario's
    :meth:`~tissuecast.scenario.Scenario.problem` does both).

    Args:
        mesh: the tetrahedral mesh (mm).
        material: the neo-Hookean constants (MPa) of every element without its own.
        fixed: (k,) int, 0-based ids of the vertices fixed in all components (e.g. from
            :func:`tissuecast.markers.markers_and_fixed`, or a scenario's pins and attached
            region).
        order: element order (1 or 2).
        springs, materials, can_swing: as :class:`Problem` (a scenario's elastic support and
            material regions: :meth:`tissuecast.scenario.Scenario.problem`).

    Raises:
        SolverSetupError: ``material`` is not a :class:`NeoHookean` (e.g. a whole run
            configuration), or as :class:`Problem`.
    """
    if not isinstance(material, NeoHookean):
        raise SolverSetupError(f"build_problem takes the material as a NeoHookean (MPa), got {type(material).__name__}; "
                               "from a run config: NeoHookean(cfg.material.youngs_modulus, cfg.material.poisson_ratio)")
    return Problem(mesh, material, fixed, order=order, springs=springs, materials=materials, can_swing=can_swing)
