"""The state of a fitted :class:`~.model.DeformationModel`: its parts and the record of how they
were chosen, as plain objects.

``DeformationModel.get_state()`` returns a :class:`ModelState`, ``DeformationModel.from_state``
rebuilds the model from one, and the model folder (:mod:`.storage`) writes and reads them: the
baselines are not stored, they are rebuilt from the network's PCA basis and the markers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import SurrogateConfig
from .experts import ExpertGate, RouteCalibration
from .gate import InputGate
from .mlp import TrainingSummary
from .network_predictor import NetworkPredictor
from .pca import PCACurve
from .trust import TrustLayer

__all__ = ["ModelState", "training_summaries", "gate_of"]


@dataclass(frozen=True, eq=False)
class ModelState:
    """Everything a fitted model is made of.

    Attributes:
        config: the surrogate settings it was fitted with.
        network: the learned predictor (mesh, markers, PCA basis, networks, quadratic head).
        fixed: (k,) int64 0-based fixed vertex ids of the simulations (metadata).
        pca_choice: the rule behind n_w, its curves, the head's size and the ridge
            baseline's number of components (``ridge_components``).
        pca_curve: the paper rule's cross-validated PCA curve, or None.
        trust: the calibrated trust layer, or None (no calibration samples).
        training: the training summary (sample counts, times, per-member summaries), or None.
        run_config: the whole run's configuration as a dict, or None.
        dataset_path: the store it was trained on, or None.
        scenario: the training data's clinical scenario summary, or None.
        metadata: the ``model.json`` it was read from (None for a model fitted in this process).
        fallback: for a network with instrument inputs, its fallback without them
            (:mod:`.fallback`; the same mesh and markers), else None.
        fallback_trust: the fallback's calibrated trust layer, or None.
        gate: the input gate's ranges, or None (derived by :func:`gate_of`).
        expert: the nominal expert's state (:mod:`.experts`: a model of the same mesh, markers and
            inputs trained at the nominal parameters), or None.
        expert_gate: the :class:`~.experts.ExpertGate` routing between this model and the expert.
        expert_routes: the pair's bounds' :class:`~.experts.RouteCalibration`, or None (a pair
            saved before it: the uncertainty-trained model's bounds).
    """

    config: SurrogateConfig
    network: NetworkPredictor
    fixed: np.ndarray
    pca_choice: dict
    pca_curve: PCACurve | None = None
    trust: TrustLayer | None = None
    training: dict | None = None
    run_config: dict | None = None
    dataset_path: str | None = None
    scenario: dict | None = None
    metadata: dict | None = field(default=None, repr=False)
    fallback: NetworkPredictor | None = None
    fallback_trust: TrustLayer | None = None
    gate: InputGate | None = None
    expert: "ModelState | None" = None
    expert_gate: ExpertGate | None = None
    expert_routes: RouteCalibration | None = None

    @property
    def ridge_components(self) -> int:
        """Components of the ridge baseline: its recorded best, else all of the network's."""
        return int(self.pca_choice.get("ridge_components") or self.network.n_components)


def training_summaries(training: dict | None) -> list[TrainingSummary]:
    """The members' :class:`TrainingSummary` objects from a training record (``model.json``)."""
    return [TrainingSummary(**{k: (tuple(map(tuple, v)) if k == "valid_history" else v) for k, v in s.items()})
            for s in (training or {}).get("members", [])]


def gate_of(state: ModelState) -> InputGate:
    """The state's input gate; for a state without one (a folder written before the gate), its
    ranges derived from the trust layer's training inputs (the input distance's whitened
    reference, mapped back to mm) where there is one, else estimated from the PCA basis
    (:meth:`InputGate.from_pca`)."""
    if state.gate is not None:
        return state.gate
    net = state.network
    if state.trust is not None:
        dist = state.trust.ood.distance
        X = dist.reference @ np.linalg.pinv(dist.whitening) + dist.mean
        return InputGate.from_inputs(net.markers, net.reference_marker_positions, X, source="trust-file")
    return InputGate.from_pca(net.markers, net.reference_marker_positions, net.basis)
