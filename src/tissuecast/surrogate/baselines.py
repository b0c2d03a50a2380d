"""The baselines every learned prediction is reported next to, as field predictors.

- :class:`RigidRegistrationPredictor`: what navigation systems do with tracked fiducials
  today, the best rigid motion (Kabsch) of the markers' reference positions onto their
  displaced ones, applied to the whole mesh (:mod:`tissuecast.registration`). Nothing is
  learned: it needs only the mesh and the markers.
- :class:`RidgePredictor`: the paper's ridge regression of the PCA weights on the marker
  displacements (:mod:`.ridge`), as one affine map of the marker displacements to the field.

Both implement :class:`~.field_predictor.FieldPredictor`.
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .component_choice import ridge_components
from .field_predictor import FieldPredictor, check_vertex_ids
from .pca import PCABasis
from .ridge import fit_ridge

__all__ = ["RigidRegistrationPredictor", "RidgePredictor"]


class RigidRegistrationPredictor(FieldPredictor):
    """Rigid registration from the markers (Kabsch) as a displacement field.

    Missing markers are left out of the fit (>= 3 tracked markers, not on one line, must
    remain; else :class:`~tissuecast.errors.RegistrationError` at prediction).

    Args:
        mesh: the :class:`~tissuecast.mesh.TetMesh` (n vertices, mm).
        markers: (n_d,) 0-based marker vertex ids.
    """

    name = "rigid"
    supports_missing_markers = True

    def __init__(self, mesh, markers):
        self.mesh = mesh
        self.markers = check_vertex_ids(markers, mesh.n_vertices)

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None) -> np.ndarray:
        from ..registration import rigid_registration_field

        d = d.reshape(d.shape[0], -1, 3)
        points = self.mesh.points
        if missing is None:
            return rigid_registration_field(points, self.markers, d)
        return np.stack([rigid_registration_field(points, self.markers[~m], di[~m]) for di, m in zip(d, missing)])

    def __repr__(self) -> str:
        return f"RigidRegistrationPredictor(n_vertices={self.n_vertices}, markers={self.markers.tolist()})"


class RidgePredictor(FieldPredictor):
    """The paper's ridge baseline on a PCA basis: ``u = d @ R + r0``, an affine map of the
    marker displacements d (3 n_d,) mm (:mod:`.ridge` derives it).

    Args:
        mesh: the :class:`~tissuecast.mesh.TetMesh` (n vertices, mm).
        markers: (n_d,) 0-based marker vertex ids.
        basis: the PCA basis it regresses on (all its components are used).
        ratio: the ridge ratio a2 / a1 >= 0 (``surrogate.ridge_ratio``).
    """

    name = "ridge"

    def __init__(self, mesh, markers, basis: PCABasis, ratio: float):
        self.mesh = mesh
        self.markers = check_vertex_ids(markers, mesh.n_vertices)
        if basis.n_features != 3 * mesh.n_vertices:
            raise ModelError(f"the PCA basis describes {basis.n_features // 3} vertices, the mesh has {mesh.n_vertices}")
        self.basis = basis
        self.regression = fit_ridge(basis, self.markers, ratio)
        proj = self.regression.matrix.T @ basis.components  # (3 n_d, 3 n)
        self.map = (proj, basis.mean - self.regression.marker_mean @ proj)

    @classmethod
    def fit(cls, mesh, markers, basis: PCABasis, ratio: float, valid_inputs: np.ndarray,
            valid_fields: np.ndarray) -> "RidgePredictor":
        """The baseline on the first k components of ``basis``, k the number at which it has its
        lowest validation mean Offset_max (:func:`.component_choice.ridge_components`).

        Args:
            valid_inputs: (M, 3 n_d) validation marker displacements, mm.
            valid_fields: (M, 3 n) validation fields, mm.
        """
        k = ridge_components(basis, check_vertex_ids(markers, mesh.n_vertices), ratio, valid_inputs, valid_fields)
        return cls(mesh, markers, basis.truncated(k), ratio)

    @property
    def n_components(self) -> int:
        return self.basis.n_components

    def predict(self, marker_displacements, *, missing=None, auxiliary=None) -> np.ndarray:
        """As :meth:`FieldPredictor.predict`; the ridge baseline needs every marker (and reads
        no auxiliary inputs: ``auxiliary`` is ignored)."""
        if missing is not None:
            raise ModelError("the ridge baseline cannot predict with missing markers; use method='mlp' or 'rigid'")
        return super().predict(marker_displacements)

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None) -> np.ndarray:
        R, r0 = self.map
        return (d @ R + r0).reshape(d.shape[0], -1, 3)

    def describe(self) -> dict:
        return {**super().describe(), "n_components": self.n_components, "ratio": self.regression.ratio}

    def __repr__(self) -> str:
        return (f"RidgePredictor(n_vertices={self.n_vertices}, markers={self.markers.tolist()}, "
                f"n_components={self.n_components})")
