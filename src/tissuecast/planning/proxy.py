"""A cheap stand-in for training the MLP: how well a marker set determines the field.

:class:`QuadraticProxy` regresses the PCA weights of the training fields on the marker
displacements (:func:`tissuecast.surrogate.quadratic.fit_quadratic`: ridge on linear and
quadratic features) and scores a marker set by the validation mean Offset_max of the fields
it predicts. Training fields select, validation fields score; nothing else is read.
Lengths in mm.
"""

from __future__ import annotations

import numpy as np

from ..errors import MarkerError
from ..surrogate.pca import PCABasis
from ..surrogate.quadratic import QUADRATIC_DIMS, fit_quadratic
from ..surrogate.ridge import marker_columns

__all__ = ["QuadraticProxy"]


class QuadraticProxy:
    """Validation error of a marker set under a quadratic ridge regression.

    Args:
        basis: PCA basis of the training fields (K components; more than the MLP will use,
            so that the score is not limited by truncation).
        train: (N_t, n, 3) or (N_t, 3 n) training fields, mm.
        valid: (N_v, n, 3) or (N_v, 3 n) validation fields, mm.
        quadratic_dims: principal directions of the marker input whose products are features.
    """

    def __init__(self, basis: PCABasis, train, valid, *, quadratic_dims: int = QUADRATIC_DIMS):
        self.basis = basis
        self.train = np.asarray(train, dtype=np.float64).reshape(len(train), -1)
        self.valid = np.asarray(valid, dtype=np.float64).reshape(len(valid), -1)
        if self.train.shape[1] != basis.n_features or self.valid.shape[1] != basis.n_features:
            raise MarkerError("training/validation fields do not match the PCA basis")
        self.targets = basis.transform(self.train)  # (N_t, K)
        self.quadratic_dims = int(quadratic_dims)

    def predict(self, markers) -> np.ndarray:
        """Predicted validation fields (N_v, 3 n) mm from the markers' displacements."""
        cols = marker_columns(markers)
        reg = fit_quadratic(self.train[:, cols], self.targets, quadratic_dims=self.quadratic_dims)
        return self.basis.inverse_transform(reg.predict(self.valid[:, cols]))

    def errors(self, markers) -> np.ndarray:
        """(N_v,) validation Offset_max per sample, mm."""
        e = (self.predict(markers) - self.valid).reshape(len(self.valid), -1, 3)
        return np.sqrt((e**2).sum(axis=2)).max(axis=1)

    def __call__(self, markers) -> float:
        """Validation mean Offset_max (mm) of this marker set."""
        return float(self.errors(markers).mean())
