"""A predictor that reads tracked instruments, and its fallback for when their tracking is lost.

A model with instrument inputs (:mod:`.auxiliary`) is fitted twice: the primary predictor reads
the markers, the instruments' poses and the measured parameters; the fallback reads the markers
and the parameters only (trained on the same samples, so it is what a model of a scenario
without tracked instruments would be). :class:`InstrumentFallback` routes each sample: one whose
instrument inputs are given goes to the primary, one with an absent instrument (its inputs NaN:
no TRANSFORM lately, or left out of the call) to the fallback. Both may be trust-wrapped
(:class:`~.trusted.TrustedPredictor`): the bounds and the alarm are then those of the predictor
that made the field.
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .field_predictor import FieldPredictor
from .trust import TrustedPrediction

__all__ = ["InstrumentFallback"]


class InstrumentFallback(FieldPredictor):
    """The primary predictor (with instruments) and its fallback (without), routed per sample.

    Args:
        primary: a predictor whose ``auxiliary`` has instruments.
        fallback: a predictor on the same mesh and markers reading
            ``primary.auxiliary.without_instruments()``.

    Raises:
        ModelError: the two do not fit together.
    """

    def __init__(self, primary: FieldPredictor, fallback: FieldPredictor):
        spec = primary.auxiliary
        if not spec.instruments or fallback.auxiliary != spec.without_instruments():
            raise ModelError("the fallback must read the primary predictor's auxiliary inputs without its instruments")
        if not np.array_equal(primary.markers, fallback.markers) or primary.n_vertices != fallback.n_vertices:
            raise ModelError("the fallback must predict on the primary predictor's mesh from its markers")
        self.primary, self.fallback = primary, fallback
        self._kept = np.arange(len(spec.instrument_columns), spec.width)  # the fallback's columns

    # ------------------------------------------------------------------ the protocol
    @property
    def name(self) -> str:
        return self.primary.name

    @property
    def mesh(self):
        return self.primary.mesh

    @property
    def markers(self) -> np.ndarray:
        return self.primary.markers

    @property
    def auxiliary(self):
        return self.primary.auxiliary

    @property
    def supports_missing_markers(self) -> bool:
        return bool(self.primary.supports_missing_markers and self.fallback.supports_missing_markers)

    @property
    def has_uncertainty(self) -> bool:
        return bool(self.primary.has_uncertainty and self.fallback.has_uncertainty)

    @property
    def has_trust(self) -> bool:
        return bool(self.primary.has_trust and self.fallback.has_trust)

    def routes(self, a: np.ndarray) -> np.ndarray:
        """(B,) bool: True for the samples of inputs ``a`` (B, n_a) that go to the fallback."""
        return self.auxiliary.absent(a)

    def _parts(self, d, missing, a):
        """``[(rows, predictor, d, missing, auxiliary)]`` of the primary and fallback samples."""
        absent = self.routes(a)
        out = []
        for rows, predictor, cols in ((np.flatnonzero(~absent), self.primary, None),
                                      (np.flatnonzero(absent), self.fallback, self._kept)):
            if len(rows):
                aux = a[rows] if cols is None else (a[np.ix_(rows, cols)] if len(cols) else None)
                out.append((rows, predictor, d[rows], None if missing is None else missing[rows], aux))
        return out

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None, a: np.ndarray | None = None) -> np.ndarray:
        u = np.empty((d.shape[0], self.n_vertices, 3))
        for rows, predictor, dr, mr, ar in self._parts(d, missing, a):
            u[rows] = predictor.predict_checked(dr, mr, ar)
        return u

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`FieldPredictor.predict_with_uncertainty`, each sample from the predictor it is routed to."""
        d, miss, single = self.marker_batch(marker_displacements, missing)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        u, sigma = np.empty((d.shape[0], self.n_vertices, 3)), np.empty((d.shape[0], self.n_vertices))
        for rows, predictor, dr, mr, ar in self._parts(d, miss, a):
            u[rows], sigma[rows] = predictor.predict_with_uncertainty(dr, missing=mr, auxiliary=ar)
        return (u[0], sigma[0]) if single else (u, sigma)

    def trusted_checked(self, d: np.ndarray, a: np.ndarray | None, *, coverage: float | None = None,
                        false_alarm: float | None = None, alarm: bool = True) -> TrustedPrediction:
        """:meth:`FieldPredictor.trusted_checked`, each sample's field, bounds and alarm from the
        predictor it is routed to.

        Raises:
            ModelError: the primary or the fallback has no trust layer.
        """
        if not self.has_trust:
            return super().trusted_checked(d, a)
        u, bounds, by_row = np.empty((d.shape[0], self.n_vertices, 3)), np.empty((d.shape[0], self.n_vertices)), {}
        level = None
        for rows, predictor, dr, _, ar in self._parts(d, None, a):
            t = predictor.trusted_checked(dr, ar, coverage=coverage, false_alarm=false_alarm, alarm=alarm)
            u[rows], bounds[rows], level = t.displacement, t.error_bound, t.coverage
            if alarm:
                by_row.update(zip(rows.tolist(), t.alarms))
        alarms = [by_row[b] for b in range(d.shape[0])] if alarm else None
        return TrustedPrediction(u, bounds, level, alarms)

    def input_distance(self, marker_displacements, *, auxiliary=None) -> np.ndarray:
        """As :meth:`.trusted.TrustedPredictor.input_distance`, each sample's from the predictor it is routed to."""
        d, _, _ = self.marker_batch(marker_displacements)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        out = np.empty(d.shape[0])
        for rows, predictor, dr, _, ar in self._parts(d, None, a):
            out[rows] = predictor.input_distance(dr, auxiliary=ar)
        return out

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None):
        """As :meth:`.trusted.TrustedPredictor.alarms`, each sample's alarm from the predictor it is routed to."""
        if not self.has_trust:
            return super().alarms(marker_displacements, false_alarm=false_alarm)
        d, _, single = self.marker_batch(marker_displacements)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        alarms = {}
        for rows, predictor, dr, _, ar in self._parts(d, None, a):
            alarms.update(zip(rows.tolist(), predictor.alarms(dr, false_alarm=false_alarm, auxiliary=ar)))
        return alarms[0] if single else [alarms[b] for b in range(d.shape[0])]

    def describe(self) -> dict:
        return {**self.primary.describe(), "fallback": self.fallback.describe()}

    def __repr__(self) -> str:
        return f"InstrumentFallback({self.primary!r}, fallback={self.fallback!r})"
