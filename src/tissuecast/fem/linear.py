"""Pluggable sparse direct solvers for the symmetric stiffness systems of the Newton solver.

Every backend works on one fixed sparsity pattern (that of an
:class:`~tissuecast.fem.assembly.Assembler`): the symbolic analysis (fill-reducing ordering)
is done once, each :meth:`factorize` call only redoes the numeric factorisation.
:meth:`LinearSolver.spawn` gives another solver of the same pattern with a numeric factor of
its own that shares the symbolic analysis where the backend allows (several solves in flight
at once, each with its own factorised tangent).

Backends:

* ``"cholmod"`` -- supernodal Cholesky of SuiteSparse through ``sksparse.cholmod`` with a
  nested-dissection ordering (the fastest here; figures in ``docs/solver.md``).
* ``"pardiso"`` -- Intel MKL PARDISO through ``pypardiso`` when it is installed
  (symmetric indefinite mode, so it never needs a fallback).
* ``"superlu"`` -- SciPy's SuperLU, always available, the slowest.
* ``"p-multigrid"`` -- not a factorisation but a two-level multigrid cycle
  (:mod:`.preconditioners`), an approximate inverse (``exact = False``) whose cost grows
  like the mesh; ``"auto"`` picks it for quadratic meshes of at least
  ``solver.multigrid_dofs`` free dofs.

A stiffness that is not positive definite (possible far from equilibrium, under
compression) raises :class:`NotPositiveDefinite` from the Cholesky backend; the Newton
solver then factorises a shifted matrix ``K + beta D`` (D = diag K), which keeps its step a
descent direction of the potential energy (see :mod:`tissuecast.fem.solver`).
"""

from __future__ import annotations

import importlib.util
import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from ..errors import SolverSetupError
from .assembly import Assembler
from .linear_base import LinearSolver, NotPositiveDefinite

__all__ = ["NotPositiveDefinite", "LinearSolver", "make_linear_solver", "available_backends", "one_blas_thread"]

log = logging.getLogger(__name__)


class CholmodSolver(LinearSolver):
    """Supernodal Cholesky (CHOLMOD); symbolic analysis once, numeric refactorisation in place.

    Args:
        assembler: supplies the pattern.
        ordering: CHOLMOD's fill-reducing ordering.
        symbolic: an analysed (not factorised) ``cholmod.Factor`` of the same pattern to start
            from instead of analysing again (see :meth:`spawn`).
    """

    name = "cholmod"

    def __init__(self, assembler: Assembler, ordering: str = "nesdis", symbolic=None) -> None:
        super().__init__(assembler)
        from sksparse import cholmod

        self._cholmod = cholmod
        if symbolic is None:
            pattern = assembler.lower_csc(np.ones(assembler.nnz))
            symbolic = cholmod.analyze(pattern, mode="supernodal", ordering_method=ordering)
        self._symbolic = symbolic  # never factorised: what spawn() copies
        self._factor = symbolic.copy()
        self._ready = False

    def spawn(self) -> "CholmodSolver":
        """A solver with its own numeric factor and a copy of this one's symbolic analysis."""
        return CholmodSolver(self.assembler, symbolic=self._symbolic)

    def factorize(self, data: np.ndarray) -> None:
        self._ready = False
        try:
            self._factor.cholesky_inplace(self.assembler.lower_csc(data))
        except self._cholmod.CholmodNotPositiveDefiniteError as exc:
            raise NotPositiveDefinite(str(exc)) from None
        self._ready = True

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._factor(b)


class PardisoSolver(LinearSolver):
    """MKL PARDISO via ``pypardiso`` (real symmetric indefinite, upper triangle)."""

    name = "pardiso"

    def __init__(self, assembler: Assembler) -> None:
        super().__init__(assembler)
        import pypardiso

        self._solver = pypardiso.PyPardisoSolver(mtype=-2)
        self._solver.set_phase(12)
        self._matrix = None

    def factorize(self, data: np.ndarray) -> None:
        a = self.assembler
        up = sp.csr_matrix((data[a._upper], a.upper_indices, a.upper_indptr), shape=(self.n, self.n))
        self._solver.factorize(up)
        self._matrix = up

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._solver.solve(self._matrix, np.asarray(b, dtype=np.float64))


class SuperLUSolver(LinearSolver):
    """SciPy SuperLU on the full matrix (always available, slowest)."""

    name = "superlu"

    def __init__(self, assembler: Assembler) -> None:
        super().__init__(assembler)
        self._lu = None

    def factorize(self, data: np.ndarray) -> None:
        mat = self.assembler.matrix(data).tocsc()
        try:
            self._lu = spl.splu(mat, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        except RuntimeError as exc:  # exactly singular
            raise NotPositiveDefinite(str(exc)) from None

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(np.asarray(b, dtype=np.float64))


_BACKENDS = {"cholmod": ("sksparse", CholmodSolver), "pardiso": ("pypardiso", PardisoSolver), "superlu": ("scipy", SuperLUSolver)}


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
    """Names of the backends importable here, fastest first."""
    return [name for name, (module, _) in _BACKENDS.items() if importlib.util.find_spec(module) is not None]


def make_linear_solver(name: str, assembler: Assembler, config=None) -> LinearSolver:
    """Build a backend by name.

    ``"auto"`` picks the two-level multigrid cycle (:class:`.preconditioners.PMultigrid`) for
    quadratic elements with at least ``config.multigrid_dofs`` free dofs (0: never), else the
    fastest direct backend available.

    Args:
        name: ``"auto"``, a direct backend (:func:`available_backends`) or ``"p-multigrid"``.
        assembler: supplies the pattern.
        config: a :class:`~tissuecast.config.SolverConfig` (defaults if None) for the
            multigrid settings.

    Raises:
        SolverSetupError: unknown name, or the named backend's package is not installed.
    """
    if config is None:
        from ..config import SolverConfig

        config = SolverConfig()
    if name == "auto":
        big = config.multigrid_dofs and assembler.n_free >= config.multigrid_dofs
        name = "p-multigrid" if assembler.order == 2 and big else available_backends()[0]
    if name == "p-multigrid":
        from .preconditioners import PMultigrid

        log.debug("linear solver: p-multigrid (%d free dofs)", assembler.n_free)
        return PMultigrid(assembler, degree=config.multigrid_smoothing)
    if name not in _BACKENDS:
        raise SolverSetupError(f"unknown linear solver {name!r}; choose one of 'auto', 'p-multigrid', "
                               f"{', '.join(map(repr, _BACKENDS))}")
    module, cls = _BACKENDS[name]
    if importlib.util.find_spec(module) is None:
        raise SolverSetupError(
            f"linear solver {name!r} needs the Python package {module!r}, which is not installed; "
            f"install it or use linear_solver='auto' (available here: {available_backends()})"
        )
    log.debug("linear solver: %s", name)
    return cls(assembler)
