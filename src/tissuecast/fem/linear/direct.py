"""The sparse direct backends: Cholesky or LDL^T factorisations of the stiffness.

Every backend works on one fixed sparsity pattern (that of an
:class:`~tissuecast.fem.assembly.Assembler`): the symbolic analysis (fill-reducing ordering)
is done once, each :meth:`factorize` call only redoes the numeric factorisation.
:meth:`LinearSolver.spawn` gives another solver of the same pattern with a numeric factor of
its own that shares the symbolic analysis where the backend allows (several solves in flight
at once, each with its own factorised tangent).

* :class:`CholmodSolver` (``"cholmod"``) -- supernodal Cholesky of SuiteSparse through
  ``sksparse.cholmod`` with a nested-dissection ordering (the fastest here; figures in
  ``docs/solver.md``).
* :class:`PardisoSolver` (``"pardiso"``) -- Intel MKL PARDISO through ``pypardiso`` when it is
  installed (symmetric indefinite mode, so it never needs a fallback).
* :class:`SuperLUSolver` (``"superlu"``) -- SciPy's SuperLU, always available, the slowest.

They are chosen by name through the registry, :func:`tissuecast.fem.linear.make_linear_solver`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from ..assembly import Assembler
from .base import LinearSolver, NotPositiveDefinite

__all__ = ["CholmodSolver", "PardisoSolver", "SuperLUSolver"]


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
