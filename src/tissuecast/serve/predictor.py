"""Marker positions in, packed POLYDATA replies out: everything per model is precomputed.

The server works with any :class:`~tissuecast.surrogate.field_predictor.FieldPredictor` (a
:class:`~tissuecast.surrogate.DeformationModel`, a sub-model set, a baseline, a trust-wrapped
predictor); what it sends follows the predictor's declared capabilities
(``supports_missing_markers``, ``has_uncertainty``, ``has_trust``). Per request the work is: one
model evaluation, one vectorised write of the deformed coordinates into a pre-packed message
buffer and a CRC over the changed bytes only (see :mod:`tissuecast.serve.crc`).

Replies (OpenIGTLink version-1 headers, timestamp copied from the marker message):

Points go out in the client's frame (:class:`~tissuecast.serve.client_frames.ClientFrames`; the
model's LPS frame by default).

- ``POLYDATA "TissueSurface"``: the deformed outer surface. Points are the mesh's surface
  vertices in ascending id order (``mesh.surface_vertices``), moved by the predicted
  displacement (mm); polygons are ``mesh.surface_triangles`` re-indexed into those points
  (outward normals). With a predictor that has uncertainty (an ensemble) a point-data scalar
  ``"uncertainty_mm"`` holds the per-vertex uncertainty; with a calibrated one (``has_trust``) a
  scalar ``"error_bound_mm"`` holds each vertex's conformal error bound (NaN when a marker is
  untracked).
- ``POLYDATA "TissueField"``: the full field. Points are *all* mesh vertices in id order,
  deformed; polygons are the surface triangles with global vertex ids (interior vertices
  carry no cell); point data ``"displacement_mm"`` (vectors) and, for ensembles,
  ``"uncertainty_mm"`` (scalars).

A model with auxiliary inputs (:mod:`tissuecast.surrogate.auxiliary`) gets them with every
prediction: the tracked instruments' latest poses (:mod:`tissuecast.serve.instruments`; an absent
one makes the model predict from the markers only) and the measured parameters given when the
server starts (they do not change during surgery).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from ..config import SERVE_METHODS, ServeConfig
from ..errors import ConfigError, MarkerError, ModelError
from ..instruments import ReferenceSurface
from ..surrogate.baselines import RigidRegistrationPredictor
from ..surrogate.field_predictor import FieldPredictor
from .client_frames import ClientFrames
from .polydata import PolyDataTemplate

__all__ = ["Prediction", "SurfacePredictor", "served_predictor", "SURFACE_DEVICE", "FIELD_DEVICE", "PredictionError",
           "InputRefused"]

log = logging.getLogger(__name__)

SURFACE_DEVICE = "TissueSurface"
FIELD_DEVICE = "TissueField"
UNCERTAINTY_NAME = "uncertainty_mm"
BOUND_NAME = "error_bound_mm"
DISPLACEMENT_NAME = "displacement_mm"


class PredictionError(MarkerError):
    """Marker positions that cannot be served (wrong count, implausible, model failure)."""


class InputRefused(PredictionError):
    """Marker positions the model's input gate refuses (:mod:`tissuecast.surrogate.gate`).

    Attributes:
        verdict: the gate's :class:`~tissuecast.surrogate.gate.GateVerdict` (reason, marker, vertex).
    """

    def __init__(self, verdict):
        super().__init__(verdict.message)
        self.verdict = verdict


def served_predictor(model: FieldPredictor, method: str = ServeConfig.method) -> FieldPredictor:
    """The predictor that serves ``method``: ``"mlp"`` the model itself, ``"rigid"`` the rigid
    registration of the model's markers on its mesh (learns nothing, so any model has it).

    Raises:
        ModelError: ``model`` is not a FieldPredictor, or rigid registration with < 3 markers.
        ConfigError: an unknown method.
    """
    if not isinstance(model, FieldPredictor):
        raise ModelError(f"serve needs a FieldPredictor (a DeformationModel, SubModelSet or other "
                         f"tissuecast.surrogate predictor), got {type(model).__name__}")
    if method not in SERVE_METHODS:
        raise ConfigError(f"unknown serving method {method!r}; use one of {', '.join(SERVE_METHODS)}")
    if method == "mlp":
        return model
    if model.n_markers < 3:
        raise ModelError(f"rigid registration needs at least 3 markers, this model has {model.n_markers}; "
                         "serve it with method='mlp'")
    return RigidRegistrationPredictor(model.mesh, model.markers)


@dataclass(frozen=True)
class Prediction:
    """One served prediction.

    Attributes:
        timestamp: seconds since 1970, copied from the marker message.
        displacement: (n, 3) float, mm, every mesh vertex.
        uncertainty: (n,) float, mm, or None when the model is not an ensemble.
        error_bound: (n,) float, mm, conformal error bound per vertex, or None.
        alarm: the model's :class:`~tissuecast.surrogate.trust.Alarm`, or None.
        alarm_inputs: ``(marker displacements (n_d, 3) mm, auxiliary inputs)`` the alarm reads,
            where :meth:`SurfacePredictor.predict` left the alarm for later
            (:meth:`SurfacePredictor.with_alarm`); else None.
    """

    timestamp: float
    displacement: np.ndarray
    uncertainty: np.ndarray | None = None
    error_bound: np.ndarray | None = None
    alarm: object | None = None
    alarm_inputs: tuple | None = None


class SurfacePredictor:
    """Wraps a predictor for serving: validates marker positions, predicts, packs replies.

    Args:
        model: a :class:`~tissuecast.surrogate.field_predictor.FieldPredictor`.
        max_marker_offset: largest accepted distance (mm) of a marker from its reference
            position; larger ones are rejected as a likely registration/unit error.
        use_uncertainty: send per-vertex uncertainty when the predictor has it.
        method: ``"mlp"`` (the model) or ``"rigid"`` (the best rigid motion of the markers
            applied to the whole mesh: the navigation systems' baseline, a fallback when the
            learned model is not to be trusted; no uncertainty or bounds are sent), see
            :func:`served_predictor`.
        devices: ``{instrument name: OpenIGTLink device name}`` replacing the devices the model
            recorded for its instruments (``scenario.instruments[k].device``).
        parameters: ``{name: value}`` of the model's measured parameters (their units:
            ``model.auxiliary``), needed when it reads some.

    Raises:
        ConfigError: a device name a marker or registration would take, an unknown instrument,
            or a missing measured parameter.
    """

    def __init__(self, model: FieldPredictor, *, max_marker_offset: float = ServeConfig.max_marker_offset,
                 use_uncertainty: bool = True, method: str = ServeConfig.method, devices: dict | None = None,
                 parameters: dict | None = None):
        self.model = served_predictor(model, method)
        self.method = method
        self.auxiliary = self.model.auxiliary
        self.instrument_devices = _instrument_devices(self.auxiliary, devices or {})
        self.parameters = _measured(self.auxiliary, parameters or {})
        self.reference_surface = ReferenceSurface.of(self.model.mesh) if self.auxiliary.instruments else None
        self.gate = model.input_gate  # the model's, whichever method serves
        mesh = self.model.mesh
        reference = np.asarray(self.model.reference_marker_positions, dtype=np.float64)
        if reference.ndim != 2 or reference.shape[1] != 3 or not np.isfinite(reference).all():
            raise ModelError(f"model.reference_marker_positions must be finite (n_d, 3) mm, got shape {reference.shape}")
        self.reference = reference
        self.n_markers = len(reference)
        self.n_vertices = int(mesh.n_vertices)
        self.max_marker_offset = float(max_marker_offset)
        self.supports_missing = bool(self.model.supports_missing_markers)
        self.has_uncertainty = bool(use_uncertainty and self.model.has_uncertainty)
        self.has_bounds = bool(self.model.has_trust)
        self.points = np.asarray(mesh.points, dtype=np.float64)
        self.surface_ids = np.asarray(mesh.surface_vertices, dtype=np.int64)
        triangles = np.asarray(mesh.surface_triangles, dtype=np.int64)
        local = np.searchsorted(self.surface_ids, triangles)
        extra = [(UNCERTAINTY_NAME, "scalars")] if self.has_uncertainty else []
        extra += [(BOUND_NAME, "scalars")] if self.has_bounds else []
        self.surface = PolyDataTemplate(len(self.surface_ids), local, extra)
        self.field = PolyDataTemplate(self.n_vertices, triangles, [(DISPLACEMENT_NAME, "vectors"), *extra])
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
            InputRefused: the model's input gate refuses the markers (non-finite, displaced far
                beyond the simulations, or at distances the body cannot take).
            PredictionError: wrong count, non-finite values, or a marker too far from its
                reference position.
        """
        positions = np.array(positions, dtype=np.float64)
        if positions.shape != (self.n_markers, 3):
            count = positions.shape[0] if positions.ndim else 0
            raise PredictionError(f"expected {self.n_markers} marker positions (x, y, z in mm), got {count}")
        missing = None
        finite = np.isfinite(positions)
        if self.gate is not None:
            untracked = np.isnan(positions).all(axis=1) if self.supports_missing else None
            verdict = self.gate.inspect((positions - self.reference).reshape(1, -1),
                                        None if untracked is None else untracked[None])[0]
            if verdict.refused:
                raise InputRefused(verdict)
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

    def _evaluate(self, positions: np.ndarray, missing: np.ndarray | None, instruments: dict | None,
                  alarm_now: bool = True) -> tuple:
        """``(displacement, uncertainty, bound, alarm, alarm inputs)`` of checked positions (n_d, 3)
        mm and the instruments' poses (``{name: pose or None}``); the bounds and alarm need every
        marker tracked; ``alarm_now`` False leaves the alarm for :meth:`with_alarm`."""
        d = positions - self.reference
        extra = {} if missing is None else {"missing": missing}
        if self.auxiliary.width:  # as one row (n_a,): the model's parts and the alarm take it as it is
            extra["auxiliary"] = self.auxiliary.batch({**self.parameters, **(instruments or {})}, 1)[0]
        bound, alarm, mean, uncertainty, pending = None, None, None, None, None
        if self.has_bounds and missing is None:
            trusted = self.model.predict_trusted(d, auxiliary=extra.get("auxiliary"), alarm=alarm_now)
            bound = np.asarray(trusted.error_bound, dtype=np.float64).reshape(self.n_vertices)
            alarm, mean = trusted.alarms, trusted.displacement
            pending = None if alarm_now else (d, extra.get("auxiliary"))
        if self.has_uncertainty:
            mean, spread = self.model.predict_with_uncertainty(d, **extra)
            uncertainty = np.asarray(spread, dtype=np.float64).reshape(self.n_vertices)
        elif mean is None:
            mean = self.model.predict_from_positions(positions, **extra)
        return mean, uncertainty, bound, alarm, pending

    def predict(self, positions: np.ndarray, timestamp: float, instruments: dict | None = None, *,
                alarm: bool = True) -> Prediction:
        """Predict the displacement of every vertex from (n_d, 3) marker positions (mm) and the
        tracked instruments' poses (``{name: InstrumentPose or None (lost)}``, model frame;
        an instrument left out is lost). ``alarm`` False leaves the alarm for
        :meth:`with_alarm` (the field and its bounds first: what a server sends before it)."""
        positions, missing = self.check_positions(positions)
        try:
            mean, uncertainty, bound, found, pending = self._evaluate(positions, missing, instruments, alarm)
            displacement = np.asarray(mean, dtype=np.float64).reshape(self.n_vertices, 3)
        except ModelError as exc:  # the model refused this input (e.g. too many untracked markers)
            log.warning("model refused the marker input: %s", exc)
            raise PredictionError(f"model refused the input: {exc}") from exc
        except Exception as exc:  # a model failure must not take the server down
            log.exception("model evaluation failed")
            raise PredictionError(f"model evaluation failed: {type(exc).__name__}: {exc}") from exc
        if not np.isfinite(displacement).all():
            raise PredictionError("the model returned non-finite displacements for these marker positions")
        return Prediction(float(timestamp), displacement, uncertainty, bound, found, pending)

    def with_alarm(self, prediction: Prediction) -> Prediction:
        """``prediction`` with the alarm :meth:`predict` left for later (the same alarm it would
        have given); a prediction without one pending is returned as it is."""
        if prediction.alarm_inputs is None:
            return prediction
        d, auxiliary = prediction.alarm_inputs
        try:
            alarm = self.model.alarms(d, auxiliary=auxiliary)
        except ModelError as exc:  # as predict: the model refused the input
            log.warning("model refused the marker input for the alarm: %s", exc)
            raise PredictionError(f"model refused the input for the alarm: {exc}") from exc
        except Exception as exc:  # a model failure must not take the server down
            log.exception("the alarm's evaluation failed")
            raise PredictionError(f"alarm evaluation failed: {type(exc).__name__}: {exc}") from exc
        return replace(prediction, alarm=alarm, alarm_inputs=None)

    def is_instrument(self, device: str) -> bool:
        """Whether ``device`` is the TRANSFORM device of one of the model's instruments."""
        return device in self.instrument_devices

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


def _instrument_devices(spec, devices: dict) -> dict[str, str]:
    """``{device: instrument name}`` of a model's instruments, ``devices`` ({name: device}) replacing
    the recorded ones; checked not to be a marker's or a registration's name."""
    import re

    from .client_frames import REGISTRATION_PATTERN

    names = [i.name for i in spec.instruments]
    unknown = sorted(set(devices) - set(names))
    if unknown:
        raise ConfigError(f"instrument devices given for {unknown}; the model reads instruments {names or 'none'}")
    out = {}
    for inst in spec.instruments:
        device = devices.get(inst.name) or inst.device
        if not device or re.fullmatch(r"Marker[0-9]+(To[A-Za-z0-9_]+)?", device) or REGISTRATION_PATTERN.fullmatch(device):
            raise ConfigError(f"instrument {inst.name!r}: device name {device!r} would be read as a marker or a "
                              "registration (Marker<k>, <From>To<Ras|Lps|Image>); name its TRANSFORM otherwise, e.g. "
                              "RetractorTipToRef (scenario.instruments[k].device)")
        out[device] = inst.name
    if len(out) != len(names):
        raise ConfigError(f"instruments {names} need distinct device names, got {sorted(out)}")
    return out


def _measured(spec, parameters: dict) -> dict[str, float]:
    """The measured parameters a model reads, checked: every one given, none unknown."""
    missing = [p for p in spec.parameters if p not in parameters]
    unknown = sorted(set(parameters) - set(spec.parameters))
    if missing or unknown:
        reads = f"the measured parameters {list(spec.parameters)}" if spec.parameters else "no measured parameter"
        raise ConfigError(f"the model reads {reads}: "
                          + (f"give {missing} (--parameter NAME=VALUE)" if missing else f"it does not read {unknown}"))
    return {k: float(v) for k, v in parameters.items()}
