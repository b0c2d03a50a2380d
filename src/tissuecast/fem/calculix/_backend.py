"""CalculiX as a second solver backend: same problem in, :class:`~tissuecast.fem.SolveResult` out."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from ...errors import ConvergenceError, MeshFormatError, SolverSetupError
from ._deck import _as_prescribed, write_inp
from ._scenario import DeckScenario
from ._results import read_displacements
from ._runner import CcxRun, run_ccx

__all__ = ["solve_calculix"]


def solve_calculix(problem, forces, *, prescribed=None, body_loads=None, workdir=None, threads: int = 1,
                   timeout: float | None = None, executable: str | None = None, **deck_options):
    """Solve a :class:`tissuecast.fem.Problem` with CalculiX instead of the built-in solver.

    The same arguments as :meth:`tissuecast.fem.Solver.solve` (a scenario sample's surface
    loads, per-solve prescribed displacements and body loads) give the same discrete problem:
    the problem's springs become ``SPRING1`` elements, its per-element materials one section
    per (E, nu), the prescribed displacements ``*BOUNDARY`` values ramped over the step and the
    body loads ``*CLOAD`` at every element node (the consistent loads ``*DLOAD, GRAV`` gives).

    Args:
        problem: the problem (``mesh``, ``material``, ``fixed``, ``order``, ``prescribed``,
            ``springs``, ``materials``).
        forces: (n, 3) float, N: dead nodal loads on the vertices, or (n_nodes, 3) on every
            element node.
        prescribed: optional displacements (mm) of vertices the problem leaves free, as
            ``(ids (k,), values (k, 3))`` or ``{vertex: (3,)}`` (an indentation).
        body_loads: optional (n_nodes, 3) float, N: loads on every element node added to
            ``forces`` (e.g. :func:`tissuecast.scenario.body_loads`).
        workdir: folder for the deck and ccx's files (kept); None = a temporary folder
            removed afterwards.
        threads: ccx threads.
        timeout: seconds before ccx is stopped (raises ConvergenceError).
        executable: ccx program (default ``ccx`` on PATH).
        **deck_options: ``initial_increment``, ``min_increment``, ``max_increment``,
            ``max_increments``, ``force_tolerance``, ``displacement_tolerance`` for
            :func:`write_inp`.

    Returns:
        :class:`tissuecast.fem.SolveResult` with ``displacement`` (n, 3) mm at the vertices,
        ``nodal_displacement`` at every node (vertices first, then mid-edge nodes), the
        increments, iterations (= factorisations in ccx), cutbacks, residual history (largest
        residual force component, N, after every iteration) and the wall time in seconds
        (deck writing, ccx and parsing).

    Raises:
        DependencyError: ccx is missing.
        ConvergenceError: ccx stopped early; ``.load_fraction`` is the load reached and
            ``.result`` the last converged state (or None). Pass ``workdir`` to keep ccx's
            log for a look at the failure.
    """
    from .. import SolveResult  # the fem package's result type; imported here to avoid a cycle

    t0 = time.perf_counter()
    mesh = problem.mesh
    n = mesh.n_vertices
    order = int(getattr(problem, "order", 2))
    with tempfile.TemporaryDirectory(prefix="tissuecast-ccx-") as tmp:
        folder = Path(workdir) if workdir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        loads, held = _deck_loads(problem, forces, prescribed, body_loads)
        inp = write_inp(folder / "tissuecast.inp", mesh, problem.material, problem.fixed, loads, order=order,
                        prescribed=held, scenario=DeckScenario.from_problem(problem), **deck_options)
        try:
            run = run_ccx(inp, threads=threads, timeout=timeout, executable=executable)
        except ConvergenceError as exc:
            partial = None
            if exc.result is not None and exc.result.dat.exists():
                try:
                    u = read_displacements(exc.result.dat, n)
                    partial = _result(SolveResult, u, u, exc.result, False, time.perf_counter() - t0)
                except MeshFormatError:
                    partial = None
            raise ConvergenceError(str(exc), exc.load_fraction, partial) from None
        u = read_displacements(run.dat, n)
        nodal = read_displacements(run.frd, len(mesh.points10) if order == 2 else n)
        nodal[:n] = u  # the .dat holds one more digit than the .frd
    return _result(SolveResult, u, nodal, run, True, time.perf_counter() - t0)


def _deck_loads(problem, forces, prescribed, body_loads):
    """``(loads (n, 3) or (n_nodes, 3) N, prescribed (ids (k,), values (k, 3) mm) or None)`` for
    the deck: the forces plus the body loads, the problem's prescribed vertices plus the solve's."""
    loads = np.asarray(forces, dtype=np.float64)
    if body_loads is not None:
        b = np.asarray(body_loads, dtype=np.float64)
        n_nodes = len(problem.mesh.points10) if int(getattr(problem, "order", 2)) == 2 else problem.mesh.n_vertices
        if b.shape != (n_nodes, 3):
            raise SolverSetupError(f"body_loads must have shape ({n_nodes}, 3) (N per element node), got {b.shape}")
        full = b.copy()
        full[: len(loads)] += loads
        loads = full
    parts = [p for p in (getattr(problem, "prescribed", None), prescribed) if p is not None]
    if not parts:
        return loads, None
    ids, values = zip(*(_as_prescribed(p, problem.mesh.n_vertices) for p in parts))
    return loads, (np.concatenate(ids), np.vstack(values))


def _result(cls, u, nodal, run: CcxRun, converged: bool, seconds: float):
    values = dict(
        displacement=u,
        nodal_displacement=nodal,
        converged=converged,
        load_fraction=run.summary.load_fraction if not converged else 1.0,
        increments=run.summary.increments,
        iterations=run.summary.iterations,
        factorizations=run.summary.iterations,
        cutbacks=run.summary.cutbacks,
        residual_history=list(run.residual_history),
        seconds=seconds,
    )
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in values.items() if k in names})
