"""The one protocol every predictor of a displacement field from marker displacements follows.

A :class:`FieldPredictor` maps the displacements of n_d fiducial markers (mm, model marker
order, vertex-major ``(d0x, d0y, d0z, d1x, ...)``) to the displacement of every vertex of its
mesh (mm, 0-based vertex ids). The learned model (:class:`~.network_predictor.NetworkPredictor`:
PCA basis, quadratic head, network ensemble), the baselines (:class:`~.baselines.RidgePredictor`,
:class:`~.baselines.RigidRegistrationPredictor`), the trust wrapper
(:class:`~.trusted.TrustedPredictor`), the sub-model set (:class:`~.robust.SubModelSet`) and the
facade :class:`~.model.DeformationModel` all implement it, so callers (``serve``, ``evaluate``,
the CLI) talk to one interface.

A predictor may read **auxiliary inputs** besides the markers (the tracked instruments' poses,
measured parameters: :mod:`.auxiliary`); it declares them as ``auxiliary`` (an
:class:`~.auxiliary.AuxiliaryInputs`, empty for the baselines and markers-only models), and
``predict(..., auxiliary=...)`` takes their values. A predictor without auxiliary inputs
ignores them.

What a predictor can do beyond :meth:`FieldPredictor.predict` is declared, never probed:

- ``supports_missing_markers``: ``predict(..., missing=...)`` accepts untracked markers;
- ``has_uncertainty``: :meth:`FieldPredictor.predict_with_uncertainty` gives a per-vertex spread;
- ``has_trust``: :meth:`FieldPredictor.predict_trusted` gives calibrated error bounds and the
  out-of-distribution alarm.

A predictor without a capability raises :class:`~tissuecast.errors.ModelError` naming it when
the method is called.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from ..errors import ModelError
from .auxiliary import MARKERS_ONLY, AuxiliaryInputs
from .inputs import marker_batch

__all__ = ["FieldPredictor", "check_vertex_ids"]


def check_vertex_ids(markers, n_vertices: int) -> np.ndarray:
    """(n_d,) int64 marker ids, checked to be distinct 0-based ids in [0, n_vertices).

    Raises:
        ModelError: no markers, an id outside the mesh, or a repeated id.
    """
    mk = np.asarray(markers, dtype=np.int64).ravel()
    if mk.size == 0 or mk.min() < 0 or mk.max() >= n_vertices or np.unique(mk).size != mk.size:
        raise ModelError(f"markers must be distinct 0-based vertex ids in [0, {n_vertices}), got {mk.tolist()}")
    return mk


class FieldPredictor(ABC):
    """Marker displacements (n_d, 3) or (B, n_d, 3) mm -> displacement field (n, 3) or (B, n, 3) mm.

    Subclasses provide ``mesh`` (a :class:`~tissuecast.mesh.TetMesh` with n vertices, mm),
    ``markers`` ((n_d,) int64 0-based vertex ids, in input order), a ``name`` and
    :meth:`_predict_batch`; they override the capability flags and the matching methods they
    support.

    Attributes:
        name: short name of the method (``"mlp"``, ``"ridge"``, ``"rigid"``, ...).
        supports_missing_markers: ``predict(..., missing=...)`` accepts untracked markers.
        has_uncertainty: :meth:`predict_with_uncertainty` is available.
        has_trust: :meth:`predict_trusted` is available.
        auxiliary: the auxiliary inputs it reads (:class:`~.auxiliary.AuxiliaryInputs`; empty:
            markers only). A predictor with some implements ``_predict_batch(d, missing, a)``.
    """

    name: str = "predictor"
    mesh: object
    markers: np.ndarray
    supports_missing_markers: bool = False
    has_uncertainty: bool = False
    has_trust: bool = False
    auxiliary: AuxiliaryInputs = MARKERS_ONLY
    #: the :class:`~.gate.InputGate` that refuses implausible input, or None (predictors built
    #: outside a model; a :class:`~.model.DeformationModel` sets it on itself and its parts)
    input_gate = None

    # ------------------------------------------------------------------ geometry
    @property
    def n_markers(self) -> int:
        return int(np.asarray(self.markers).size)

    @property
    def n_vertices(self) -> int:
        return int(self.mesh.n_vertices)

    @property
    def reference_marker_positions(self) -> np.ndarray:
        """(n_d, 3) float64 mm: undeformed marker positions (subtracted from tracked positions)."""
        return np.asarray(self.mesh.points, dtype=np.float64)[self.markers]

    def marker_displacements(self, fields) -> np.ndarray:
        """Marker displacements (B, n_d, 3) mm picked from full fields (B, n, 3) mm."""
        return np.asarray(fields, dtype=np.float64)[..., self.markers, :]

    # ------------------------------------------------------------------ prediction
    def marker_batch(self, marker_displacements, missing=None) -> tuple[np.ndarray, np.ndarray | None, bool]:
        """Checked input: ``(d (B, 3 n_d) float64, missing (B, n_d) bool or None, single sample?)``.

        Accepts (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) mm (:func:`.inputs.marker_batch`);
        the :attr:`input_gate`, where set, refuses implausible input
        (:class:`~tissuecast.errors.InputRejected`).
        """
        return marker_batch(marker_displacements, self.n_markers, missing, self.supports_missing_markers, self.input_gate)

    def auxiliary_batch(self, given, batch: int) -> np.ndarray | None:
        """Checked auxiliary inputs (B, n_a) float64 (:meth:`.auxiliary.AuxiliaryInputs.batch`),
        or None for a predictor without them (``given`` is then ignored)."""
        return self.auxiliary.batch(given, batch)

    def predict(self, marker_displacements, *, missing=None, auxiliary=None) -> np.ndarray:
        """Displacement field from marker displacements (and the auxiliary inputs).

        Args:
            marker_displacements: (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) float, mm.
            missing: optional untracked markers (predictors with ``supports_missing_markers``):
                indices into the marker list, or a bool mask (n_d,) / (B, n_d).
            auxiliary: the auxiliary inputs of a predictor that reads some (``auxiliary.names``,
                in ``auxiliary.units``): an array (n_a,) or (B, n_a), or a mapping
                ``{instrument name: InstrumentPose or None, parameter name: value}``
                (:meth:`.auxiliary.AuxiliaryInputs.batch`); ignored by predictors without.

        Returns:
            (n, 3) float64 mm for one sample, (B, n, 3) for a batch.
        """
        d, miss, single = self.marker_batch(marker_displacements, missing)
        a = self.auxiliary_batch(auxiliary, d.shape[0])
        u = self._predict_batch(d, miss) if a is None else self._predict_batch(d, miss, a)
        return u[0] if single else u

    def predict_checked(self, d: np.ndarray, missing: np.ndarray | None = None, a: np.ndarray | None = None) -> np.ndarray:
        """Fields (B, n, 3) float64 mm of input a composing predictor has checked already (its
        :meth:`marker_batch` and :meth:`auxiliary_batch`, the input gate's verdict included): d
        (B, 3 n_d) mm, missing (B, n_d) bool or None, a (B, n_a) or None. The parts of a
        composed predictor are called through it, so a frame is checked once, not once per layer."""
        if missing is not None and not missing.any():  # as marker_batch gives it: None
            missing = None
        return self._predict_batch(d, missing) if a is None else self._predict_batch(d, missing, a)

    @abstractmethod
    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None) -> np.ndarray:
        """Fields (B, n, 3) float64 mm from checked displacements d (B, 3 n_d) mm and the
        untracked-marker mask (B, n_d) bool or None (predictors with auxiliary inputs take
        them as a third argument, (B, n_a))."""

    def predict_from_positions(self, positions, *, missing=None, auxiliary=None) -> np.ndarray:
        """As :meth:`predict`, from tracked marker positions in the model's (mesh) frame, mm, in
        :meth:`predict`'s layouts ((3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d)): the reference
        marker positions are subtracted."""
        n = self.n_markers
        p = np.asarray(positions, dtype=np.float64)
        if p.shape == (3 * n,) or (p.ndim == 2 and p.shape[1] == 3 * n and p.shape != (n, 3)):
            p = p.reshape(*p.shape[:-1], n, 3)
        if p.shape[-2:] != (n, 3) or p.ndim not in (2, 3):
            raise ModelError(f"marker positions must be ({n}, 3), ({3 * n},), (B, {n}, 3) or (B, {3 * n}) mm, "
                             f"got {p.shape}")
        return self.predict(p - self.reference_marker_positions, missing=missing, auxiliary=auxiliary)

    def predict_and_decode(self, d: np.ndarray, auxiliary, basis, weights) -> tuple[np.ndarray, np.ndarray]:
        """``(u (B, n, 3), v (B, n, 3))`` mm: the fields of checked input (as
        :meth:`predict_checked`: displacements d (B, 3 n_d) mm, every marker tracked, the
        auxiliary inputs (B, n_a) or None), and ``weights`` (B, K) decoded by ``basis`` (a
        :class:`~.pca.PCABasis` of K components): a trust layer's second predictor beside the
        field. A predictor that decodes with the same basis reads it once for both."""
        u = self.predict_checked(d, None, auxiliary).reshape(len(d), -1, 3)
        return u, basis.inverse_transform(weights).reshape(len(d), -1, 3)

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        """``(u, sigma)``: the field as :meth:`predict` and a per-vertex spread (n,) or (B, n) mm.

        Raises:
            ModelError: this predictor has no uncertainty (``has_uncertainty`` is False).
        """
        raise ModelError(f"the {self.name} predictor gives no uncertainty; use an ensemble model (surrogate.ensemble >= 2)")

    def predict_trusted(self, marker_displacements, *, coverage: float | None = None, false_alarm: float | None = None,
                        auxiliary=None, alarm: bool = True):
        """The field with per-vertex error bounds and the out-of-distribution alarm (checked as
        :meth:`predict` checks, then :meth:`trusted_checked`).

        Args:
            marker_displacements: as for :meth:`predict` (every marker tracked), mm.
            coverage: nominal coverage of the bounds (default: the trust layer's).
            false_alarm: false-alarm rate of the alarm (default: the trust layer's).
            auxiliary: the auxiliary inputs, as for :meth:`predict` (the bounds and the alarm
                read them too).
            alarm: False leaves the alarm out (``alarms`` None): :meth:`alarms` gives it later,
                e.g. after the field has been sent.

        Returns:
            A :class:`~tissuecast.surrogate.trust.TrustedPrediction`: displacement (n, 3) or
            (B, n, 3) mm, error_bound (n,) or (B, n) mm, and one Alarm or a list of B (None
            with ``alarm=False``).

        Raises:
            ModelError: this predictor is not calibrated (``has_trust`` is False).
        """
        if not self.has_trust:
            raise ModelError(self._untrusted())
        d, _, single = self.marker_batch(marker_displacements)
        t = self.trusted_checked(d, self.auxiliary_batch(auxiliary, d.shape[0]), coverage=coverage,
                                 false_alarm=false_alarm, alarm=alarm)
        return t.first() if single else t

    def trusted_checked(self, d: np.ndarray, a: np.ndarray | None, *, coverage: float | None = None,
                        false_alarm: float | None = None, alarm: bool = True):
        """:meth:`predict_trusted` of input a composing predictor has checked already (as
        :meth:`predict_checked`: d (B, 3 n_d) mm, every marker tracked, a (B, n_a) or None): a
        batch :class:`~.trust.TrustedPrediction`.

        Raises:
            ModelError: this predictor is not calibrated (``has_trust`` is False).
        """
        raise ModelError(self._untrusted())

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None):
        """The out-of-distribution alarm :meth:`predict_trusted` gives, alone (one
        :class:`~.trust.Alarm` or a list of B).

        Raises:
            ModelError: this predictor is not calibrated (``has_trust`` is False).
        """
        raise ModelError(self._untrusted())

    def _untrusted(self) -> str:
        return (f"the {self.name} predictor has no calibrated error bounds or alarm; wrap it in a "
                "TrustedPredictor (tissuecast.surrogate.trusted) or train with surrogate.calibration = "
                "'cross-validation' or 'split'")

    def describe(self) -> dict:
        """Small JSON-able description: name, sizes and capabilities."""
        return {"name": self.name, "n_vertices": self.n_vertices, "markers": np.asarray(self.markers).tolist(),
                "supports_missing_markers": bool(self.supports_missing_markers),
                "has_uncertainty": bool(self.has_uncertainty), "has_trust": bool(self.has_trust),
                **({"auxiliary": self.auxiliary.as_dict()} if self.auxiliary.width else {})}
