"""Ridge regression on linear and quadratic features of standardised inputs.

The features of an input x (d,) are ``[1, z, products of p_a p_b (a <= b)]`` with
``z = (x - mean) / scale`` and ``p`` the first ``quadratic_dims`` principal components of the
training ``z``: linear terms for every input, quadratic terms on a bounded number of
directions, so the cost does not grow with the square of the input size. Large deformations
are rotations to first order and quadratic to second (a rotation by t moves a point by
``t x - t^2 x / 2 + ...``), which linear regression misses.

Used as a fast stand-in for the MLP when planning markers, and to predict each marker from
the others when checking inputs for consistency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError

__all__ = ["QuadraticRegression", "fit_quadratic"]

# Ridge penalty relative to the mean diagonal of the feature Gram matrix: enough to keep the
# normal equations well conditioned, small against the signal of standardised features.
RIDGE_REL = 1e-6
#: Input directions whose pairwise products are features: 12 give 78 quadratic terms and
#: cover nearly all of a 5-marker input's 15 directions.
QUADRATIC_DIMS = 12


@dataclass(frozen=True, eq=False)
class QuadraticRegression:
    """A fitted map x (d,) -> y (m,).

    Attributes:
        mean: (d,) input mean.  scale: (d,) input scale (standard deviation, 1 where 0).
        directions: (q, d) principal directions of the standardised input.
        coef: (1 + d + q (q + 1) / 2, m) regression coefficients.
    """

    mean: np.ndarray
    scale: np.ndarray
    directions: np.ndarray
    coef: np.ndarray

    def __post_init__(self):
        q = len(self.directions)
        object.__setattr__(self, "_pairs", np.triu_indices(q))  # the products p_a p_b, a <= b

    def features(self, X) -> np.ndarray:
        """(B, F) features of inputs (B, d)."""
        Z = (np.asarray(X, dtype=np.float64) - self.mean) / self.scale
        P = Z @ self.directions.T
        a, b = self._pairs
        return np.hstack([np.ones((len(Z), 1)), Z, P[:, a] * P[:, b]])

    def predict(self, X) -> np.ndarray:
        """(B, m) predictions for inputs (B, d)."""
        return self.features(X) @ self.coef

    def arrays(self, prefix: str) -> dict:
        """Name -> array dict for npz storage."""
        return {f"{prefix}mean": self.mean, f"{prefix}scale": self.scale, f"{prefix}directions": self.directions,
                f"{prefix}coef": self.coef}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> "QuadraticRegression":
        return cls(*(np.asarray(arrays[f"{prefix}{k}"], dtype=np.float64) for k in ("mean", "scale", "directions", "coef")))


def fit_quadratic(X, Y, *, quadratic_dims: int = QUADRATIC_DIMS, ridge: float = RIDGE_REL) -> QuadraticRegression:
    """Fit :class:`QuadraticRegression` by ridge least squares.

    Args:
        X: (N, d) inputs.  Y: (N, m) targets.
        quadratic_dims: principal directions of the standardised input whose products are features.
        ridge: penalty relative to the mean diagonal of the Gram matrix.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    if X.ndim != 2 or Y.ndim != 2 or len(X) != len(Y) or len(X) < 2:
        raise ModelError(f"quadratic regression needs (N, d) inputs and (N, m) targets with N >= 2, got {X.shape} and {Y.shape}")
    mean, scale = X.mean(axis=0), X.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    q = min(int(quadratic_dims), X.shape[1])
    _, _, vt = np.linalg.svd((X - mean) / scale, full_matrices=False)
    model = QuadraticRegression(mean, scale, vt[:q].copy(), np.zeros((0, Y.shape[1])))
    F = model.features(X)
    G = F.T @ F
    G[np.diag_indices_from(G)] += ridge * np.trace(G) / len(G)
    coef = np.linalg.solve(G, F.T @ Y)
    return QuadraticRegression(mean, scale, model.directions, coef)
