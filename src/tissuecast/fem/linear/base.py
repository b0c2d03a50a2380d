"""The interface of the linear backends (:mod:`.direct`, :mod:`.multigrid`): a solver
that factorises a matrix of one fixed sparsity pattern and solves with it, and the error a
Cholesky backend raises on a matrix that is not positive definite."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..assembly import Assembler

__all__ = ["NotPositiveDefinite", "LinearSolver"]


class NotPositiveDefinite(ArithmeticError):
    """The matrix handed to a Cholesky backend is not positive definite."""


class LinearSolver:
    """Base class: factorise a matrix with a fixed pattern, then solve with it.

    Args:
        assembler: supplies the pattern (``indptr``, ``indices``) and matrix builders.
    """

    name = "base"
    #: ``solve`` returns ``K^-1 b`` to round-off (False: an approximate inverse, a preconditioner).
    exact = True

    def __init__(self, assembler: Assembler) -> None:
        self.assembler = assembler
        self.n = assembler.n_free

    def factorize(self, data: np.ndarray) -> None:
        """Numeric factorisation of the matrix with CSR values ``data`` ((nnz,) float)."""
        raise NotImplementedError

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factorisation: ``b`` (n_free,) or (n_free, k) -> same shape."""
        raise NotImplementedError

    def spawn(self) -> "LinearSolver":
        """A new solver of this backend and pattern, not factorised yet, whose numeric
        factorisations are its own (this base version redoes the symbolic analysis)."""
        return type(self)(self.assembler)
