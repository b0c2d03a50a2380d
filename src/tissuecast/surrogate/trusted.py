"""A field predictor wrapped with its trust layer: calibrated error bounds and the alarm.

In the manner of scikit-learn's ``CalibratedClassifierCV``, :class:`TrustedPredictor` holds a
fitted :class:`~.field_predictor.FieldPredictor` and the :class:`~.trust.TrustLayer` calibrated
for it; it predicts as the wrapped predictor does and adds :meth:`TrustedPredictor.predict_trusted`.
Any predictor can be wrapped: the learned model (whose PCA basis and quadratic head the layer
reuses), a baseline, or a sub-model set.
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .field_predictor import FieldPredictor
from .pca import PCABasis
from .quadratic import QuadraticRegression
from .trust import PREDICT_CHUNK, TrustedPrediction, TrustLayer
from .trust_fit import fit_trust

__all__ = ["TrustedPredictor"]


class TrustedPredictor(FieldPredictor):
    """A predictor and its calibrated trust layer.

    Args:
        predictor: the fitted predictor.
        layer: its :class:`TrustLayer` (same markers), fitted on samples the predictor was not
            trained on.

    Raises:
        ModelError: the layer was fitted for other markers.
    """

    has_trust = True

    def __init__(self, predictor: FieldPredictor, layer: TrustLayer):
        if not np.array_equal(np.asarray(layer.markers), predictor.markers):
            raise ModelError(f"the trust layer is for markers {np.asarray(layer.markers).tolist()}, the predictor uses "
                             f"{predictor.markers.tolist()}; calibrate the layer for this predictor")
        if layer.n_auxiliary != predictor.auxiliary.width:
            raise ModelError(f"the trust layer reads {layer.n_auxiliary} auxiliary inputs, the predictor "
                             f"{predictor.auxiliary.width}; calibrate the layer for this predictor")
        self.predictor = predictor
        self.layer = layer

    @classmethod
    def fit(cls, predictor: FieldPredictor, displacements, *, train_idx, valid_idx, calibration_idx, coverage: float,
            false_alarm: float, fault_score: bool = False, basis: PCABasis | None = None,
            head: QuadraticRegression | None = None, chunk: int = PREDICT_CHUNK, auxiliary=None) -> "TrustedPredictor":
        """Fit and calibrate the layer of a fitted ``predictor`` (:func:`.trust_fit.fit_trust`;
        arguments as there) and wrap it."""
        layer = fit_trust(predictor, displacements, train_idx=train_idx, valid_idx=valid_idx,
                          calibration_idx=calibration_idx, coverage=coverage, false_alarm=false_alarm,
                          fault_score=fault_score, basis=basis, head=head, chunk=chunk, auxiliary=auxiliary)
        return cls(predictor, layer)

    def calibrate(self, marker_displacements, displacements, truths, *, auxiliary=None) -> "TrustedPredictor":
        """The same predictor with its layer recalibrated on (input (m, n_d, 3), prediction
        (m, n, 3), truth (m, n, 3)) triples, mm, that the predictor was not fitted on
        (:meth:`TrustLayer.calibrate`; ``auxiliary`` (m, n_a) for a predictor with auxiliary inputs)."""
        return TrustedPredictor(self.predictor, self.layer.calibrate(marker_displacements, displacements, truths,
                                                                     auxiliary=auxiliary))

    # ------------------------------------------------------------------ the wrapped predictor
    @property
    def name(self) -> str:
        return self.predictor.name

    @property
    def mesh(self):
        return self.predictor.mesh

    @property
    def markers(self) -> np.ndarray:
        return self.predictor.markers

    @property
    def supports_missing_markers(self) -> bool:
        return self.predictor.supports_missing_markers

    @property
    def has_uncertainty(self) -> bool:
        return self.predictor.has_uncertainty

    @property
    def auxiliary(self):
        return self.predictor.auxiliary

    def predict(self, marker_displacements, *, missing=None, auxiliary=None) -> np.ndarray:
        return self.predictor.predict(marker_displacements, missing=missing, auxiliary=auxiliary)

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None, a: np.ndarray | None = None) -> np.ndarray:
        return self.predictor.predict_checked(d, missing, a)

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        return self.predictor.predict_with_uncertainty(marker_displacements, missing=missing, auxiliary=auxiliary)

    # ------------------------------------------------------------------ bounds and alarm
    @property
    def coverage(self) -> float:
        """Default nominal coverage of the bounds."""
        return self.layer.coverage

    @property
    def n_calibration(self) -> int:
        """Samples the bounds were calibrated on (0: infinite bounds)."""
        return self.layer.conformal.n_calibration

    def trusted_checked(self, d: np.ndarray, a: np.ndarray | None, *, coverage: float | None = None,
                        false_alarm: float | None = None, alarm: bool = True) -> TrustedPrediction:
        """:meth:`FieldPredictor.trusted_checked`: the layer's bounds and alarm of the predictor's
        field (its second predictor decoded in the same pass where it shares the basis)."""
        layer = self.layer
        x = layer.inputs(d, a, len(d))
        u, second = self.predictor.predict_and_decode(d, a, layer.basis, layer.second.predict(x))
        if alarm:
            bounds, alarms = layer.assess(x, u, coverage=coverage, false_alarm=false_alarm, second=second)
        else:
            bounds, alarms = layer.bounds(x, u, coverage=coverage, second=second), None
        return TrustedPrediction(u, bounds, coverage or self.layer.coverage, alarms)

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None):
        """The out-of-distribution alarm of inputs as for :meth:`predict_trusted` (the same
        alarm it gives): one :class:`~tissuecast.surrogate.trust.Alarm` or a list of B."""
        d, _, single = self.marker_batch(marker_displacements)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        alarms = self.layer.alarms(self.layer.inputs(d, a, len(d)), false_alarm=false_alarm)
        return alarms[0] if single else alarms

    def input_distance(self, marker_displacements, *, auxiliary=None) -> np.ndarray:
        """(B,) the alarm's distance score (:attr:`~.trust.Alarm.distance`) of inputs as for
        :meth:`predict_trusted`: how far they lie from the inputs the predictor was trained on,
        without the field, its bounds or the alarm's other scores."""
        d, _, _ = self.marker_batch(marker_displacements)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        return self.layer.ood.distance(self.layer.inputs(d, a, len(d)))

    def describe(self) -> dict:
        return {**self.predictor.describe(), "has_trust": True, "trust": self.layer.summary()}

    def __repr__(self) -> str:
        return f"TrustedPredictor({self.predictor!r}, {self.n_calibration} calibration samples)"
