"""Marker positions in, packed POLYDATA replies out: everything per model is precomputed.

The server works with any object that has the :class:`ServableModel` interface (a
:class:`tissuecast.surrogate.DeformationModel` does). Per request the work is: one model
evaluation, one vectorised write of the deformed coordinates into a pre-packed message
buffer and a CRC over the changed bytes only (see :mod:`tissuecast.serve.crc`).

Replies (OpenIGTLink version-1 headers, timestamp copied from the marker message):

Points go out in the client's frame (:class:`~tissuecast.serve.frames.ClientFrames`; the
model's LPS frame by default).

- ``POLYDATA "TissueSurface"``: the deformed outer surface. Points are the mesh's surface
  vertices in ascending id order (``mesh.surface_vertices``), moved by the predicted
  displacement (mm); polygons are ``mesh.surface_triangles`` re-indexed into those points
  (outward normals). With an ensemble model a point-data scalar ``"uncertainty_mm"`` holds the
  per-vertex uncertainty; with a calibrated model (``has_trust``) a scalar ``"error_bound_mm"``
  holds each vertex's conformal error bound (NaN when a marker is untracked).
- ``POLYDATA "TissueField"``: the full field. Points are *all* mesh vertices in id order,
  deformed; polygons are the surface triangles with global vertex ids (interior vertices
  carry no cell); point data ``"displacement_mm"`` (vectors) and, for ensembles,
  ``"uncertainty_mm"`` (scalars).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import ServeConfig
from ..errors import MarkerError, ModelError
from .frames import ClientFrames
from .polydata import PolyDataTemplate

__all__ = ["ServableModel", "Prediction", "SurfacePredictor", "SURFACE_DEVICE", "FIELD_DEVICE", "PredictionError"]

log = logging.getLogger(__name__)

SURFACE_DEVICE = "TissueSurface"
FIELD_DEVICE = "TissueField"
UNCERTAINTY_NAME = "uncertainty_mm"
BOUND_NAME = "error_bound_mm"
DISPLACEMENT_NAME = "displacement_mm"


class PredictionError(MarkerError):
    """Marker positions that cannot be served (wrong count, implausible, model failure)."""


@runtime_checkable
class ServableModel(Protocol):
    """What the server needs from a model (a DeformationModel has it).

    Attributes:
        mesh: the :class:`~tissuecast.mesh.TetMesh` the model predicts on (mm).
        reference_marker_positions: (n_d, 3) float, mm, marker positions of the undeformed mesh.

    An optional ``predict_with_uncertainty(marker_displacements (n_d, 3) mm)`` returning
    ``(displacement (n, 3) mm, uncertainty (n,) mm)`` makes the replies carry uncertainty
    (used when the model has no ``ensemble_size`` attribute or it is >= 2). A true
    ``supports_missing_markers`` attribute means both predict methods accept
    ``missing=(n_d,) bool`` for untracked markers.
    """

    mesh: object
    reference_marker_positions: np.ndarray

    def predict_from_positions(self, positions: np.ndarray) -> np.ndarray:
        """(n_d, 3) marker positions (mm) -> (n, 3) vertex displacement (mm)."""


@dataclass(frozen=True)
class Prediction:
    """One served prediction.

    Attributes:
        timestamp: seconds since 1970, copied from the marker message.
        displacement: (n, 3) float, mm, every mesh vertex.
        uncertainty: (n,) float, mm, or None when the model is not an ensemble.
        error_bound: (n,) float, mm, conformal error bound per vertex, or None.
        alarm: the model's :class:`~tissuecast.surrogate.trust.Alarm`, or None.
    """

    timestamp: float
    displacement: np.ndarray
    uncertainty: np.ndarray | None = None
    error_bound: np.ndarray | None = None
    alarm: object | None = None


class SurfacePredictor:
    """Wraps a model for serving: validates marker positions, predicts, packs replies.

    Args:
        model: a :class:`ServableModel`.
        max_marker_offset: largest accepted distance (mm) of a marker from its reference
            position; larger ones are rejected as a likely registration/unit error.
        use_uncertainty: send per-vertex uncertainty when the model provides it.
    """

    def __init__(self, model: ServableModel, *, max_marker_offset: float = ServeConfig.max_marker_offset,
                 use_uncertainty: bool = True):
        mesh = model.mesh
        reference = np.asarray(model.reference_marker_positions, dtype=np.float64)
        if reference.ndim != 2 or reference.shape[1] != 3 or not np.isfinite(reference).all():
            raise ModelError(f"model.reference_marker_positions must be finite (n_d, 3) mm, got shape {reference.shape}")
        self.model = model
        self.reference = reference
        self.n_markers = len(reference)
        self.n_points = int(mesh.n_points)
        self.max_marker_offset = float(max_marker_offset)
        self.supports_missing = bool(getattr(model, "supports_missing_markers", False))
        self.has_uncertainty = bool(
            use_uncertainty
            and callable(getattr(model, "predict_with_uncertainty", None))
            and getattr(model, "ensemble_size", 2) >= 2
        )
        self.points = np.asarray(mesh.points, dtype=np.float64)
        self.surface_ids = np.asarray(mesh.surface_vertices, dtype=np.int64)
        triangles = np.asarray(mesh.surface_triangles, dtype=np.int64)
        local = np.searchsorted(self.surface_ids, triangles)
        self.has_bounds = bool(getattr(model, "has_trust", False) and callable(getattr(model, "predict_trusted", None)))
        extra = [(UNCERTAINTY_NAME, "scalars")] if self.has_uncertainty else []
        extra += [(BOUND_NAME, "scalars")] if self.has_bounds else []
        self.surface = PolyDataTemplate(len(self.surface_ids), local, extra)
        self.field = PolyDataTemplate(self.n_points, triangles, [(DISPLACEMENT_NAME, "vectors"), *extra])
        self.surface_reference = self.points[self.surface_ids]

    def check_positions(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Validate (n_d, 3) marker positions (mm).

        A marker whose coordinates are all NaN counts as *not tracked* when the model
        supports missing markers (``supports_missing_markers``, trained with marker
        dropout); otherwise any NaN or infinity is rejected.

        Returns:
            ``(positions (n_d, 3) mm, missing (n_d,) bool or None)``; missing markers get
            their reference position.

        Raises:
            PredictionError: wrong count, non-finite values, or a marker too far from its
                reference position.
        """
        positions = np.array(positions, dtype=np.float64)
        if positions.shape != (self.n_markers, 3):
            count = positions.shape[0] if positions.ndim else 0
            raise PredictionError(f"expected {self.n_markers} marker positions (x, y, z in mm), got {count}")
        missing = None
        finite = np.isfinite(positions)
        if not finite.all():
            untracked = np.isnan(positions).all(axis=1)
            if not (self.supports_missing and (finite.all(axis=1) | untracked).all() and not untracked.all()):
                what = "; this model cannot predict with untracked markers" if not self.supports_missing else ""
                raise PredictionError(
                    f"marker positions contain NaN or infinite values (markers {np.flatnonzero(~finite.all(axis=1)).tolist()})"
                    f"{what}; mark an untracked marker by all-NaN coordinates with a model trained with marker dropout"
                )
            missing = untracked
            positions[missing] = self.reference[missing]
        offset = np.sqrt(((positions - self.reference) ** 2).sum(axis=1))
        worst = int(np.argmax(offset))
        if offset[worst] > self.max_marker_offset:
            raise PredictionError(
                f"marker {worst} is {offset[worst]:.1f} mm from its reference position (limit "
                f"{self.max_marker_offset:g} mm); send positions in the model's coordinate frame, in mm"
            )
        return positions, missing

    def predict(self, positions: np.ndarray, timestamp: float) -> Prediction:
        """Predict the displacement of every vertex from (n_d, 3) marker positions (mm)."""
        positions, missing = self.check_positions(positions)
        extra = {} if missing is None else {"missing": missing}
        try:
            bound, alarm, mean = None, None, None
            if self.has_bounds and missing is None:  # bounds and alarm need every marker
                trusted = self.model.predict_trusted(positions - self.reference)
                bound, alarm, mean = np.asarray(trusted.error_bound, dtype=np.float64).reshape(self.n_points), \
                    trusted.alarms, trusted.displacement
            if self.has_uncertainty:
                mean, spread = self.model.predict_with_uncertainty(positions - self.reference, **extra)
                uncertainty = np.asarray(spread, dtype=np.float64).reshape(self.n_points)
            else:
                uncertainty = None
                if mean is None:
                    mean = self.model.predict_from_positions(positions, **extra)
            displacement = np.asarray(mean, dtype=np.float64).reshape(self.n_points, 3)
        except ModelError as exc:  # the model refused this input (e.g. too many untracked markers)
            log.warning("model refused the marker input: %s", exc)
            raise PredictionError(f"model refused the input: {exc}") from exc
        except Exception as exc:  # a model failure must not take the server down
            log.exception("model evaluation failed")
            raise PredictionError(f"model evaluation failed: {type(exc).__name__}: {exc}") from exc
        if not np.isfinite(displacement).all():
            raise PredictionError("the model returned non-finite displacements for these marker positions")
        return Prediction(float(timestamp), displacement, uncertainty, bound, alarm)

    def surface_message(self, prediction: Prediction, frames: ClientFrames | None = None) -> memoryview:
        """The packed ``TissueSurface`` POLYDATA message (valid until the next call).

        Args:
            prediction: the prediction (model frame).
            frames: send the points in ``frames.client_frame`` (None: the model frame).
        """
        template = self.surface
        if frames is None or frames.identity_out:
            np.add(self.surface_reference, prediction.displacement[self.surface_ids], out=template.points, casting="unsafe")
        else:
            template.points[:] = frames.points_to_client(self.surface_reference + prediction.displacement[self.surface_ids])
        if prediction.uncertainty is not None and self.has_uncertainty:
            template.values[UNCERTAINTY_NAME][:] = prediction.uncertainty[self.surface_ids]
        if self.has_bounds:
            bound = prediction.error_bound
            template.values[BOUND_NAME][:] = np.nan if bound is None else bound[self.surface_ids]
        return template.finish(SURFACE_DEVICE, prediction.timestamp)

    def field_message(self, prediction: Prediction, frames: ClientFrames | None = None) -> memoryview:
        """The packed ``TissueField`` POLYDATA message (valid until the next call); points and
        ``displacement_mm`` vectors in ``frames.client_frame`` (None: the model frame)."""
        template = self.field
        if frames is None or frames.identity_out:
            np.add(self.points, prediction.displacement, out=template.points, casting="unsafe")
            template.values[DISPLACEMENT_NAME][:] = prediction.displacement
        else:
            template.points[:] = frames.points_to_client(self.points + prediction.displacement)
            template.values[DISPLACEMENT_NAME][:] = frames.vectors_to_client(prediction.displacement)
        if prediction.uncertainty is not None and self.has_uncertainty:
            template.values[UNCERTAINTY_NAME][:] = prediction.uncertainty
        if self.has_bounds:
            template.values[BOUND_NAME][:] = np.nan if prediction.error_bound is None else prediction.error_bound
        return template.finish(FIELD_DEVICE, prediction.timestamp)
