"""Write a :class:`tissuecast.fem.Problem`-like set-up as a CalculiX/Abaqus input deck.

Ids in the deck are 1-based: vertex i (0-based) is node i + 1, the mid-edge node of
``mesh.edges[e]`` is node n + e + 1 (row k - 1 of ``mesh.points10`` is node k). Units: mm, N, MPa.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import SolverSetupError
from ._format import id_lines as _id_lines
from ._format import number_text as _num
from ._scenario import NO_ADDITIONS, DeckScenario

__all__ = ["write_inp"]

#: R_n and C_n of ``*CONTROLS, PARAMETERS=FIELD`` when only one of the two is given (the
#: defaults of both CalculiX and Abaqus, and of tissuecast's solver).
DEFAULT_FORCE_TOLERANCE = 0.005
DEFAULT_DISPLACEMENT_TOLERANCE = 0.01


def _as_forces(forces, n: int, n_nodes: int | None = None) -> np.ndarray:
    f = np.asarray(forces, dtype=np.float64)
    if f.shape != (n, 3) and f.shape != (n_nodes, 3):
        raise SolverSetupError(f"forces must have shape ({n}, 3) (N per mesh vertex)"
                               f"{'' if n_nodes is None else f' or ({n_nodes}, 3) (per element node)'}, got {f.shape}")
    if not np.isfinite(f).all():
        raise SolverSetupError(f"forces hold {int((~np.isfinite(f)).sum())} non-finite values; fix the force field")
    return f


def _as_ids(ids, n: int, what: str) -> np.ndarray:
    a = np.asarray(ids).ravel()
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise SolverSetupError(f"{what} must be integer vertex ids (0-based), got dtype {a.dtype}")
    a = a.astype(np.int64)
    if a.size and (a.min() < 0 or a.max() >= n):
        raise SolverSetupError(f"{what} {a[(a < 0) | (a >= n)][:5].tolist()} are outside 0..{n - 1} (ids are 0-based)")
    return a


def _as_prescribed(prescribed, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(ids (p,), values (p, 3) mm, NaN = component left free) from a mapping or a pair."""
    if prescribed is None:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    if isinstance(prescribed, dict):
        ids, values = list(prescribed.keys()), list(prescribed.values())
    else:
        ids, values = prescribed
    ids = _as_ids(ids, n, "prescribed vertices")
    values = np.asarray(values, dtype=np.float64).reshape(len(ids), 3)
    return ids, values


def _constrained_nodes(mesh, order: int, fixed, pre_ids, pre_val):
    """0-based node ids of the fixed nodes and of the prescribed nodes with their values.

    As in :class:`tissuecast.fem.Problem`: for quadratic elements a mid-edge node whose two
    end vertices are both constrained is constrained too (per component), to the mean of
    their values, so the edge stays straight; otherwise it is free.

    Returns:
        ``(fixed nodes (k,), prescribed nodes (p,), values (p, 3) mm with NaN = free)``.
    """
    n = mesh.n_vertices
    value = np.full((n, 3), np.nan)
    value[pre_ids] = pre_val
    is_fixed = np.zeros(n, dtype=bool)
    is_fixed[fixed] = True
    fixed_nodes, pre_nodes, pre_nodal = [fixed], [pre_ids], [pre_val]
    if order == 2:
        e = mesh.edges
        both_fixed = is_fixed[e[:, 0]] & is_fixed[e[:, 1]]
        fixed_nodes.append(n + np.flatnonzero(both_fixed))
        v = np.where(is_fixed[:, None], 0.0, value)
        mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]])  # NaN where an end is free
        k = np.flatnonzero(~both_fixed & ~np.isnan(mid).all(axis=1))
        pre_nodes.append(n + k)
        pre_nodal.append(mid[k])
    return np.concatenate(fixed_nodes), np.concatenate(pre_nodes), np.vstack(pre_nodal)


def _material_constants(material) -> tuple[float, float]:
    try:
        c10, d1 = float(material.c10), float(material.d1)
    except AttributeError:
        raise SolverSetupError(
            f"material must be a neo-Hookean material with .c10 and .d1 (e.g. tissuecast.NeoHookean), got {material!r}"
        ) from None
    if not (c10 > 0 and d1 > 0):
        raise SolverSetupError(f"neo-Hookean constants must be positive, got C10={c10}, D1={d1}")
    return c10, d1


def write_inp(
    path,
    mesh,
    material,
    fixed,
    forces,
    *,
    order: int = 2,
    prescribed=None,
    node_sets: dict | None = None,
    nlgeom: bool = True,
    initial_increment: float = 0.05,
    min_increment: float = 1e-5,
    max_increment: float = 0.25,
    max_increments: int = 1000,
    force_tolerance: float | None = None,
    displacement_tolerance: float | None = None,
    title: str = "tissuecast neo-Hookean problem",
    scenario: DeckScenario = NO_ADDITIONS,
) -> Path:
    """Write the problem as a CalculiX/Abaqus input deck.

    Args:
        path: output ``.inp`` file (the folder must exist).
        mesh: :class:`~tissuecast.mesh.TetMesh` with n vertices (mm).
        material: neo-Hookean material with ``c10`` and ``d1`` (MPa, 1/MPa), e.g.
            :class:`tissuecast.fem.NeoHookean`.
        fixed: (k,) int, 0-based ids of vertices held in all three directions.
        forces: (n, 3) float, N: dead nodal loads on the vertices (corner nodes), or
            (n_nodes, 3) on every element node; zero components are not written.
        order: 2 for quadratic C3D10 elements, 1 for linear C3D4.
        prescribed: optional prescribed vertex displacements (mm), ramped over the step,
            as ``{vertex: (3,)}`` or ``(ids (p,), values (p, 3))``; a NaN component is free.
        node_sets: optional extra node sets ``{NAME: (k,) 0-based vertex ids}`` written as
            ``*NSET`` (e.g. the fiducial markers, to print their displacements).
        nlgeom: geometric nonlinearity (large deformation); the neo-Hookean law always
            switches it on in CalculiX.
        initial_increment, min_increment, max_increment: automatic incrementation, as
            fractions of the total load (the step period is 1).
        max_increments: the step's increment limit (``INC=``).
        force_tolerance, displacement_tolerance: convergence criteria R_n and C_n of
            ``*CONTROLS, PARAMETERS=FIELD`` (residual / average force, correction / increment
            of displacement); None keeps the defaults 0.005 and 0.01 (both programs'; a
            missing one of the two is written with its default).
        title: ``*HEADING`` text.
        scenario: what the scenario adds (:class:`~._scenario.DeckScenario`: springs to
            ground, a gravity load, per-element materials); the default adds nothing (the
            material everywhere, no springs, no gravity: the paper's set-up).

    Returns:
        The path written.

    Raises:
        SolverSetupError: wrong shapes, ids out of range, non-finite forces, forces on fixed
            vertices, or a bad order / material.
    """
    if order not in (1, 2):
        raise SolverSetupError(f"order must be 1 (C3D4) or 2 (C3D10), got {order!r}")
    n = mesh.n_vertices
    _material_constants(material)
    n_nodes = len(mesh.points10) if order == 2 else None
    f, fixed, pre_ids, pre_val = _checked_setup(mesh, fixed, forces, prescribed, n_nodes)
    _check_increments(initial_increment, min_increment, max_increment)
    fixed_nodes, pre_nodes, pre_nodal = _constrained_nodes(mesh, order, fixed, pre_ids, pre_val)
    out = _mesh_lines(mesh, order, title)
    out += _set_lines(n, fixed_nodes, node_sets)
    out += _material_lines(material, scenario, mesh.n_tets)
    out += _step_lines(nlgeom, max_increments, (initial_increment, min_increment, max_increment),
                       force_tolerance, displacement_tolerance)
    out += _load_lines(fixed_nodes, pre_nodes, pre_nodal, f, scenario)
    path = Path(path)
    path.write_text("\n".join(out))
    return path


def _checked_setup(mesh, fixed, forces, prescribed, n_nodes: int | None = None):
    """``(forces (n, 3) or (n_nodes, 3), fixed (k,) sorted, prescribed ids (p,), values (p, 3))``, checked."""
    n = mesh.n_vertices
    f = _as_forces(forces, n, n_nodes)
    fixed = np.unique(_as_ids(fixed, n, "fixed vertices"))
    pre_ids, pre_val = _as_prescribed(prescribed, n)
    both = np.intersect1d(fixed, pre_ids)
    if both.size:
        raise SolverSetupError(f"vertices {both[:5].tolist()} are both fixed and prescribed; give each one constraint")
    loaded_fixed = fixed[np.abs(f[fixed]).sum(axis=1) > 0]
    if loaded_fixed.size:
        raise SolverSetupError(
            f"forces act on fixed vertices {loaded_fixed[:5].tolist()}; set their forces to zero or unfix them"
        )
    return f, fixed, pre_ids, pre_val


def _check_increments(initial_increment: float, min_increment: float, max_increment: float) -> None:
    if not 0 < min_increment <= initial_increment <= 1 or not min_increment <= max_increment <= 1:
        raise SolverSetupError(
            "increments must satisfy 0 < min_increment <= initial_increment <= 1 and min_increment <= max_increment <= 1, "
            f"got {min_increment}, {initial_increment}, {max_increment}"
        )


def _mesh_lines(mesh, order: int, title: str) -> list[str]:
    """Header, nodes (1-based), elements and the vertex node set NVERT."""
    n = mesh.n_vertices
    if order == 2:
        nodes, elements, etype = mesh.points10, mesh.tets10, "C3D10"
    else:
        nodes, elements, etype = mesh.points, mesh.tets, "C3D4"
    out = [
        "** tissuecast input deck for CalculiX (ccx >= 2.20) and Abaqus/Standard. Units: mm, N, MPa.",
        "** Node and element ids are 1-based: node k is 0-based mesh vertex i = k - 1 (k <= n_vertices);",
        f"** for C3D10, node n_vertices + e + 1 is the midpoint of mesh edge e. n_vertices = {n}.",
        "*HEADING",
        title,
        "*NODE, NSET=NALL",
    ]
    out += [f"{k + 1}, {_num(x)}, {_num(y)}, {_num(z)}" for k, (x, y, z) in enumerate(nodes.tolist())]
    out.append(f"*ELEMENT, TYPE={etype}, ELSET=TISSUE")
    body = np.hstack([np.arange(1, len(elements) + 1)[:, None], elements + 1])
    out += [", ".join(map(str, row)) for row in body.tolist()]
    out += ["*NSET, NSET=NVERT, GENERATE", f"1, {n}, 1"]
    return out


def _set_lines(n: int, fixed_nodes: np.ndarray, node_sets: dict | None) -> list[str]:
    """The fixed node set NFIXED and the user's node sets (checked names and ids)."""
    out = ["*NSET, NSET=NFIXED"] + _id_lines(fixed_nodes + 1) if fixed_nodes.size else []
    for name, ids in (node_sets or {}).items():
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,79}", str(name)):
            raise SolverSetupError(f"node set name {name!r} must be a letter followed by letters, digits or _")
        ids = _as_ids(ids, n, f"node set {name}")
        if ids.size:
            out += [f"*NSET, NSET={name}"] + _id_lines(ids + 1)
    return out


def _material_lines(material, scenario: DeckScenario, n_elements: int) -> list[str]:
    """Material(s) and section(s) (the scenario's per-region materials, or ``material``
    everywhere) and the scenario's springs."""
    return scenario.material_lines(material, n_elements, _num) + scenario.spring_lines(n_elements + 1, _num)


def _step_lines(nlgeom: bool, max_increments: int, increments: tuple,
                force_tolerance: float | None, displacement_tolerance: float | None) -> list[str]:
    """The static step with its incrementation and convergence controls."""
    initial_increment, min_increment, max_increment = increments
    out = [
        f"*STEP, NLGEOM={'YES' if nlgeom else 'NO'}, INC={int(max_increments)}",
        "*STATIC",
        f"{_num(initial_increment)}, 1.0, {_num(min_increment)}, {_num(max_increment)}",
    ]
    if force_tolerance is not None or displacement_tolerance is not None:
        r_n = DEFAULT_FORCE_TOLERANCE if force_tolerance is None else float(force_tolerance)
        c_n = DEFAULT_DISPLACEMENT_TOLERANCE if displacement_tolerance is None else float(displacement_tolerance)
        if not (0 < r_n < 1 and 0 < c_n < 1):
            raise SolverSetupError(f"convergence tolerances must lie in (0, 1), got {r_n}, {c_n}")
        out += ["*CONTROLS, PARAMETERS=FIELD, FIELD=DISPLACEMENT", f"{_num(r_n)}, {_num(c_n)}"]
    return out


def _load_lines(fixed_nodes: np.ndarray, pre_nodes: np.ndarray, pre_nodal: np.ndarray, f: np.ndarray,
                scenario: DeckScenario) -> list[str]:
    """Boundary conditions, nodal loads (non-zero components) and the output requests."""
    out = []
    bc = ["NFIXED, 1, 3"] if fixed_nodes.size else []
    for i, v in zip(pre_nodes.tolist(), pre_nodal.tolist()):
        bc += [f"{i + 1}, {d + 1}, {d + 1}, {_num(x)}" for d, x in enumerate(v) if np.isfinite(x)]
    if bc:
        out += ["*BOUNDARY"] + bc
    nz = np.argwhere(f != 0)
    if nz.size:
        out += ["*CLOAD"] + [f"{i + 1}, {d + 1}, {_num(f[i, d])}" for i, d in nz.tolist()]
    out += scenario.step_lines(_num)
    out += ["*NODE PRINT, NSET=NVERT", "U", "*NODE FILE", "U", "*END STEP", ""]
    return out
