"""CalculiX as a second solver backend: same problem in, :class:`~tissuecast.fem.SolveResult` out."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

from ...errors import ConvergenceError, MeshFormatError
from ._deck import write_inp
from ._results import read_displacements
from ._runner import CcxRun, run_ccx

__all__ = ["solve_calculix"]


def solve_calculix(problem, forces, *, workdir=None, threads: int = 1, timeout: float | None = None,
                   executable: str | None = None, **deck_options):
    """Solve a :class:`tissuecast.fem.Problem` with CalculiX instead of the built-in solver.

    Args:
        problem: the problem (``mesh``, ``material``, ``fixed``, ``order``, ``prescribed``).
        forces: (n, 3) float, N: dead nodal loads on the vertices.
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
        inp = write_inp(folder / "tissuecast.inp", mesh, problem.material, problem.fixed, forces, order=order,
                        prescribed=getattr(problem, "prescribed", None), **deck_options)
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
