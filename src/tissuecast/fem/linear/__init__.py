"""Linear solvers for the stiffness systems of the Newton solver: the registry of backends.

Every backend (a :class:`LinearSolver`, :mod:`.base`) factorises matrices of one fixed
sparsity pattern, that of an :class:`~tissuecast.fem.assembly.Assembler`, and solves with
the last factorisation; :meth:`LinearSolver.spawn` gives another numeric factor of the same
pattern. ``solver.linear_solver`` names one of :data:`BACKENDS`:

* ``"cholmod"``, ``"pardiso"``, ``"superlu"`` -- sparse direct factorisations
  (:mod:`.direct`), exact inverses;
* ``"p-multigrid"`` -- not a factorisation but a two-level multigrid cycle (:mod:`.multigrid`),
  an approximate inverse (``exact = False``) whose cost grows like the mesh, which the
  Newton solver uses as the preconditioner of conjugate gradients;
* ``"auto"`` -- the multigrid cycle for quadratic meshes of at least
  ``solver.multigrid_dofs`` free dofs, else the fastest direct backend installed.

A stiffness that is not positive definite (possible far from equilibrium, under
compression) raises :class:`NotPositiveDefinite`; the Newton solver then factorises a
shifted matrix ``K + tau D`` (D = diag K), which keeps its step a descent direction of the
potential energy (see :mod:`tissuecast.fem.directions`).
"""

from __future__ import annotations

import importlib.util
import logging
from dataclasses import dataclass
from typing import Callable

from ...errors import SolverSetupError
from ..assembly import Assembler
from .base import LinearSolver, NotPositiveDefinite
from .direct import CholmodSolver, PardisoSolver, SuperLUSolver
from .multigrid import PMultigrid

__all__ = ["NotPositiveDefinite", "LinearSolver", "Backend", "BACKENDS", "make_linear_solver", "available_backends",
           "one_blas_thread"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Backend:
    """One linear-solver backend of the registry.

    Attributes:
        name: its ``solver.linear_solver`` value.
        package: the Python package it needs (checked before it is built).
        direct: True for a factorisation (an exact inverse), False for a preconditioner.
        build: ``(assembler, solver config) -> LinearSolver``.
    """

    name: str
    package: str
    direct: bool
    build: Callable[[Assembler, object], LinearSolver]


#: Every backend by name; the direct ones fastest first (``"auto"`` takes the first installed).
BACKENDS = {b.name: b for b in (
    Backend("cholmod", "sksparse", True, lambda assembler, config: CholmodSolver(assembler)),
    Backend("pardiso", "pypardiso", True, lambda assembler, config: PardisoSolver(assembler)),
    Backend("superlu", "scipy", True, lambda assembler, config: SuperLUSolver(assembler)),
    Backend("p-multigrid", "scipy", False,
            lambda assembler, config: PMultigrid(assembler, degree=config.multigrid_smoothing)),
)}


def one_blas_thread():
    """A context manager limiting every BLAS/OpenMP library the solver uses to one thread.

    The backends' triangular solves run faster on one thread than on several, and a factor
    built on one thread has the same last bits on every machine (a multi-threaded BLAS sums
    in another order). The libraries are loaded first (SciPy's BLAS, and CHOLMOD's system
    BLAS when ``sksparse`` is installed), since a limit only reaches libraries already loaded.
    Used as ``with one_blas_thread(): ...``; the previous limits come back on exit. Without
    ``threadpoolctl`` (extra ``data``) it limits nothing.
    """
    import contextlib

    import scipy.linalg  # noqa: F401  (load every BLAS the solver uses before limiting them)

    try:
        import sksparse.cholmod  # noqa: F401  (CHOLMOD links the system's BLAS; extra "fast")
    except ImportError:
        pass
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - depends on the environment
        return contextlib.nullcontext()
    return threadpool_limits(limits=1)


def available_backends() -> list[str]:
    """Names of the direct backends importable here, fastest first."""
    return [b.name for b in BACKENDS.values() if b.direct and importlib.util.find_spec(b.package) is not None]


def make_linear_solver(name: str, assembler: Assembler, config=None) -> LinearSolver:
    """Build a backend of :data:`BACKENDS` by name.

    ``"auto"`` picks the two-level multigrid cycle (:class:`.multigrid.PMultigrid`) for
    quadratic elements with at least ``config.multigrid_dofs`` free dofs (0: never), else the
    fastest direct backend available.

    Args:
        name: ``"auto"`` or a name of :data:`BACKENDS` (``"p-multigrid"`` or a direct backend,
            :func:`available_backends`).
        assembler: supplies the pattern.
        config: a :class:`~tissuecast.config.SolverConfig` (defaults if None) for the
            multigrid settings.

    Raises:
        SolverSetupError: unknown name, or the named backend's package is not installed.
    """
    if config is None:
        from ...config import SolverConfig

        config = SolverConfig()
    if name == "auto":
        big = config.multigrid_dofs and assembler.n_free >= config.multigrid_dofs
        name = "p-multigrid" if assembler.order == 2 and big else available_backends()[0]
    backend = BACKENDS.get(name)
    if backend is None:
        raise SolverSetupError(f"unknown linear solver {name!r}; choose one of 'auto', "
                               f"{', '.join(map(repr, BACKENDS))}")
    if importlib.util.find_spec(backend.package) is None:
        raise SolverSetupError(
            f"linear solver {name!r} needs the Python package {backend.package!r}, which is not installed; "
            f"install it or use linear_solver='auto' (available here: {available_backends()})"
        )
    log.debug("linear solver: %s (%d free dofs)", name, assembler.n_free)
    return backend.build(assembler, config)
