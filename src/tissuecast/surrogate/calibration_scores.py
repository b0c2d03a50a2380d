"""What calibrates a trust layer: per calibration sample, what the layer that scored it saw
(:meth:`TrustLayer.calibration_scores <.trust.TrustLayer.calibration_scores>`), so that scores of
several layers (the folds of a cross-validation, :mod:`.cross_calibration`) can be pooled and
calibrate another layer (:meth:`TrustLayer.with_calibration <.trust.TrustLayer.with_calibration>`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CalibrationScores"]


@dataclass(frozen=True, eq=False)
class CalibrationScores:
    """What calibrates a trust layer, per calibration sample, as the layer that scored them saw it.

    Attributes:
        features: (m, F) error-model features (:meth:`TrustLayer.features <.trust.TrustLayer.features>`).
        disagreement: (m, n) disagreement map h, mm (None for a flat normaliser).
        errors: (m, n) true vertex errors of the predictions, mm.
        alarm: (m, 5) raw alarm scores [distance, consistency, fault, stillness, swap] (NaN where absent).
    """

    features: np.ndarray
    disagreement: np.ndarray | None
    errors: np.ndarray
    alarm: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(len(self.errors))

    @classmethod
    def pooled(cls, parts) -> "CalibrationScores":
        """The scores of several disjoint sets of samples (the folds of a cross-validation) as one."""
        parts = list(parts)
        h = None if parts[0].disagreement is None else np.vstack([p.disagreement for p in parts])
        return cls(np.vstack([p.features for p in parts]), h, np.vstack([p.errors for p in parts]),
                   np.vstack([p.alarm for p in parts]))
