"""The outcome of one nonlinear solve."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SolveResult", "SolveCounts"]


@dataclass(frozen=True)
class SolveResult:
    """Displacements and convergence record of one solve.

    Attributes:
        displacement: (n, 3) float, mm, at the mesh vertices (corner nodes).
        converged: True when the full load was reached.
        load_fraction: load fraction reached (1.0 when converged).
        increments: accepted load increments.
        iterations: equilibrium iterations over all attempted increments (cut-back ones
            included).
        factorizations: numeric sparse factorisations (the dominant cost).
        residual_history: largest residual force component (N) after every iteration.
        seconds: wall-clock time of the solve.
        nodal_displacement: (n_nodes, 3) float, mm, at every element node (for P2 the
            vertices come first, then the mid-edge nodes in ``mesh.edges`` order).
        nodal_reaction: (n_nodes, 3) float, N, support reactions at constrained nodes
            (zero elsewhere); their sum balances the applied forces.
        cutbacks: increments abandoned and retried with a smaller load step.
        solves: back-substitutions with a factorisation.
    """

    displacement: np.ndarray
    converged: bool
    load_fraction: float
    increments: int
    iterations: int
    factorizations: int
    residual_history: list = field(default_factory=list)
    seconds: float = 0.0
    nodal_displacement: np.ndarray | None = None
    nodal_reaction: np.ndarray | None = None
    cutbacks: int = 0
    solves: int = 0

    @property
    def max_displacement(self) -> float:
        """Largest vertex displacement magnitude, mm."""
        return float(np.linalg.norm(self.displacement, axis=1).max())

    @property
    def reaction(self) -> np.ndarray:
        """(n, 3) float, N: support reactions at the mesh vertices."""
        return self.nodal_reaction[: len(self.displacement)]


@dataclass
class SolveCounts:
    """What one solve did (see :class:`~tissuecast.fem.result.SolveResult`)."""

    iterations: int = 0  # Newton iterations, all increments (cut-back ones included)
    factorizations: int = 0  # numeric factorisations, shifted attempts included
    solves: int = 0  # preconditioner applications (triangular solves)
    shifted: int = 0  # factorisations of a shifted tangent K + tau diag(K)
    projected: int = 0  # factorisations of the projected (positive-definite) stiffness
    krylov_steps: int = 0  # conjugate-gradient steps
    residual_history: list = field(default_factory=list)  # largest residual component (N) per iteration
