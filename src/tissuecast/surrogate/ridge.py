"""The paper's ridge-regression baseline for the PCA weights.

Given marker displacements ``d`` (3 n_d,) mm, the weights minimise

    a1 ||D (P w + mean) - d||^2 + a2 ||w||^2,    r = a2 / a1 (paper: 1e-3),

where P (p, n_w) holds the PCA components as columns and D picks the marker components out
of the flattened field. With P_D = D P and mean_D = D mean the closed form is

    w = (P_D^T P_D + r I)^{-1} P_D^T (d - mean_D),

so the whole field ``mean + P w`` is an affine map of ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import SurrogateConfig
from ..errors import ModelError
from .pca import PCABasis

__all__ = ["RidgeBaseline", "fit_ridge", "marker_columns"]


def marker_columns(markers) -> np.ndarray:
    """Indices (3 n_d,) of the marker components in a vertex-major flattened field."""
    m = np.asarray(markers, dtype=np.int64).ravel()
    return (3 * m[:, None] + np.arange(3)).ravel()


@dataclass(frozen=True, eq=False)
class RidgeBaseline:
    """Fitted ridge map from marker displacements to PCA weights.

    Attributes:
        matrix: (n_w, 3 n_d) float64, ``(P_D^T P_D + r I)^{-1} P_D^T``.
        marker_mean: (3 n_d,) float64 mm, ``mean_D``.
        ratio: r = a2 / a1.
    """

    matrix: np.ndarray
    marker_mean: np.ndarray
    ratio: float

    def weights(self, marker_displacements) -> np.ndarray:
        """PCA weights (B, n_w) mm from marker displacements (B, 3 n_d) mm."""
        d = np.asarray(marker_displacements, dtype=np.float64)
        return (d - self.marker_mean) @ self.matrix.T


def fit_ridge(basis: PCABasis, markers, ratio: float = SurrogateConfig.ridge_ratio) -> RidgeBaseline:
    """Closed-form ridge baseline on a PCA basis.

    Args:
        basis: the fitted PCA basis (n_w components).
        markers: (n_d,) 0-based marker vertex ids.
        ratio: a2 / a1 >= 0 (paper: 1e-3); 0 is plain least squares (needs 3 n_d >= n_w).
    """
    if not ratio >= 0:
        raise ModelError(f"ridge ratio a2/a1 must be >= 0, got {ratio}")
    cols = marker_columns(markers)
    if cols.max(initial=-1) >= basis.n_features or cols.min(initial=0) < 0:
        raise ModelError(f"marker ids {np.asarray(markers).tolist()} are outside the {basis.n_features // 3}-vertex field")
    PD = basis.components[:, cols].T  # (3 n_d, n_w)
    G = PD.T @ PD + ratio * np.eye(basis.n_components)
    try:
        matrix = np.linalg.solve(G, PD.T)  # (n_w, 3 n_d)
    except np.linalg.LinAlgError as exc:
        raise ModelError(
            f"ridge normal matrix is singular (ratio {ratio}, {len(cols)} marker components, "
            f"{basis.n_components} PCA components); use a positive ratio"
        ) from exc
    return RidgeBaseline(matrix=matrix, marker_mean=basis.mean[cols].copy(), ratio=float(ratio))
