"""DeformationModel: marker displacements -> whole-body displacement field, the facade users know.

The model is composed of parts that each implement the one predictor protocol
(:class:`~.field_predictor.FieldPredictor`):

- ``network_``: the learned :class:`~.network_predictor.NetworkPredictor` (PCA basis, quadratic
  head, network ensemble), fitted by :func:`~.network_fit.fit_network`;
- ``ridge_`` and ``rigid_``: the baselines (:mod:`.baselines`);
- ``trusted_``: the learned predictor wrapped with its calibrated trust layer
  (:class:`~.trusted.TrustedPredictor`), or None without calibration samples;
- for a model with tracked instruments as inputs (:mod:`.auxiliary`), ``fallback_`` (and
  ``fallback_trusted_``): the learned predictor fitted without the instruments, used for a
  sample whose instrument is absent (:class:`~.fallback.InstrumentFallback`);
- for a model given a nominal expert (:meth:`DeformationModel.with_nominal_expert`),
  ``nominal_expert_``: a model of the same mesh, markers and inputs trained at the nominal
  parameters, and ``expert_gate_``, which routes each sample's field between the two
  (:class:`~.experts.NominalExpertRouter`; the bounds and the alarm stay this model's).

Scikit-learn style: the hyper-parameters come from a :class:`~tissuecast.config.SurrogateConfig`
given to ``__init__``; ``fit`` learns the state (attributes ending in ``_``) and returns
``self``; predicting with an unfitted model raises :class:`~tissuecast.errors.ModelError`.
``get_state()`` / ``from_state()`` give the fitted state as plain objects (:mod:`.state`), which
the model folder stores (:mod:`.storage`).

Marker displacements are ordered like the markers, vertex-major: ``(d0x, d0y, d0z, d1x, ...)``
in mm. A displacement field is (n, 3) mm at every mesh vertex (0-based ids). Auxiliary inputs
(the instruments' poses in the model frame LPS, measured parameters) are given as
``auxiliary=`` (:meth:`DeformationModel.predict`; names and units: ``model.auxiliary``).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config import Config, SurrogateConfig, config_to_dict, with_overrides
from ..errors import ModelError
from .auxiliary import AuxiliaryInputs, AuxiliaryValues
from .baselines import RidgePredictor, RigidRegistrationPredictor
from .cross_calibration import fit_model_trust
from .data import FitSplits, check_fit_inputs, dataset_arrays, fit_splits, flat_fields
from .decoder import global_part
from .experts import (ExpertGate, NominalExpertRouter, RouteCalibration, RoutedNetworks, check_expert, gate_description,
                      gate_features, out_of_fold_routes, routed_networks)
from .fallback import InstrumentFallback
from .field_predictor import FieldPredictor
from .inputs import marker_batch
from .fit_stage import fit_stage
from .network_fit import ENSEMBLE_SEED_STRIDE, fit_network
from .network_predictor import NetworkPredictor
from .ridge import marker_columns
from .gate import GateVerdict, InputGate
from .state import ModelState, gate_of, training_summaries
from .trust import TrustedPrediction
from .trusted import TrustedPredictor

log = logging.getLogger(__name__)

__all__ = ["DeformationModel", "ENSEMBLE_SEED_STRIDE", "METHODS"]

#: The predictors ``predict(..., method=...)`` chooses between.
METHODS = ("mlp", "rigid", "ridge")


def _surrogate_config(config, overrides: dict) -> SurrogateConfig:
    if config is None:
        config = SurrogateConfig()
    elif isinstance(config, Config):
        config = config.surrogate
    elif not isinstance(config, SurrogateConfig):
        raise ModelError(f"config must be a Config or SurrogateConfig, got {type(config).__name__}")
    if overrides:
        config = with_overrides(Config(surrogate=config), surrogate=overrides).surrogate
    return config


def _auxiliary_values(auxiliary: AuxiliaryValues | None, n_samples: int,
                      splits: FitSplits) -> tuple[AuxiliaryInputs, np.ndarray | None]:
    """``(what the inputs are, values (N, n_a) or None)`` of a fit, checked: one row per sample,
    finite on the samples the fit uses."""
    if auxiliary is None or not auxiliary.inputs.width:
        return AuxiliaryInputs(), None
    A = auxiliary.values
    used = np.concatenate([splits.train, splits.valid, splits.calibration])
    if len(A) != n_samples or not np.isfinite(A[used]).all():
        raise ModelError(f"auxiliary values must be ({n_samples}, {A.shape[1]}) and finite for the samples fitted on "
                         "(an instrument away from the tissue is 0, not NaN)")
    return auxiliary.inputs, A


class DeformationModel(FieldPredictor):
    """PCA + MLP surrogate of nonlinear FEM (Liu et al. 2020), with its baselines and trust layer.

    By default (``surrogate.head = "quadratic"``) a quadratic regression of the PCA weights on
    the marker displacements (:mod:`.head`) predicts first and the networks learn its residual;
    ``head = "none"`` is the paper's network alone.

    Args:
        config: surrogate settings (a :class:`SurrogateConfig`, or a whole :class:`Config`);
            None uses the defaults.
        **overrides: individual ``SurrogateConfig`` fields, validated like a config file
            (e.g. ``hidden=(64, 64), ensemble=5``).
    """

    name = "mlp"

    def __init__(self, config: SurrogateConfig | Config | None = None, **overrides):
        self.config = _surrogate_config(config, overrides)
        self.run_config: dict | None = config_to_dict(config) if isinstance(config, Config) else None
        self.dataset_path: str | None = None
        #: the clinical scenario of the training data (``Dataset.scenario``: supports, loads,
        #: materials; see :mod:`tissuecast.scenario.describe`), or None when not recorded
        self.scenario: dict | None = None

    # ------------------------------------------------------------------ fitted state
    def _fitted(self) -> None:
        if not self.is_fitted:
            raise ModelError("this DeformationModel is not fitted yet; call fit(...) or DeformationModel.load(folder)")

    @property
    def is_fitted(self) -> bool:
        return hasattr(self, "network_")

    @property
    def mesh(self):
        """The :class:`~tissuecast.mesh.TetMesh` the model predicts on (n vertices)."""
        self._fitted()
        return self.network_.mesh

    @property
    def markers(self) -> np.ndarray:
        """(n_d,) int64 0-based fiducial marker vertex ids, in input order."""
        self._fitted()
        return self.network_.markers

    @property
    def fixed(self) -> np.ndarray:
        """(k,) int64 0-based fixed vertex ids of the simulations."""
        self._fitted()
        return self.fixed_

    @property
    def n_components(self) -> int:
        self._fitted()
        return self.network_.n_components

    @property
    def ensemble_size(self) -> int:
        self._fitted()
        return self.network_.ensemble_size

    @property
    def supports_missing_markers(self) -> bool:
        """Whether the network was trained with marker masking (``marker_dropout > 0``)."""
        self._fitted()
        return self.network_.supports_missing_markers

    @property
    def has_uncertainty(self) -> bool:
        """Whether the network is an ensemble (``surrogate.ensemble >= 2``): per-vertex spread
        (not with a nominal expert: the routed field has no ensemble of its own)."""
        self._fitted()
        return bool(self._by_method["mlp"].has_uncertainty)

    @property
    def has_nominal_expert(self) -> bool:
        """Whether a nominal expert predicts the samples its gate routes to it (:meth:`with_nominal_expert`)."""
        return self.is_fitted and self.nominal_expert_ is not None

    @property
    def bounds_predictor(self):
        """What predicts the field this model's bounds are measured against, with the bounds: this
        model with a nominal expert (its field is the routed one), else its trusted network
        (:class:`~.trusted.TrustedPredictor`, the samples' instrument poses as auxiliary inputs).
        None without a trust layer."""
        if not self.has_trust:
            return None
        return self if self.has_nominal_expert else self.trusted_

    @property
    def has_trust(self) -> bool:
        """Whether error bounds and the alarm are calibrated (``surrogate.calibration`` not ``"none"``)."""
        return self.is_fitted and self.trusted_ is not None

    @property
    def auxiliary(self) -> AuxiliaryInputs:
        """The auxiliary inputs the model reads besides the markers (:mod:`.auxiliary`: names,
        units; empty for a markers-only model)."""
        return self.network_.auxiliary if self.is_fitted else AuxiliaryInputs()

    def predictor(self, method: str = "mlp") -> FieldPredictor:
        """The part that predicts for ``method``: ``"mlp"`` (the learned model), ``"rigid"`` (rigid
        registration from the markers) or ``"ridge"`` (the paper's ridge baseline)."""
        if method not in METHODS:
            raise ModelError(f"unknown prediction method {method!r}; use 'mlp', 'rigid' or 'ridge'")
        self._fitted()
        return self._by_method[method]

    def get_state(self) -> ModelState:
        """The fitted state as plain objects (:class:`~.state.ModelState`)."""
        self._fitted()
        return ModelState(config=self.config, network=self.network_, fixed=self.fixed_, pca_choice=self.pca_choice_,
                          pca_curve=self.pca_curve_, trust=None if self.trusted_ is None else self.trusted_.layer,
                          training=self.training_, run_config=self.run_config, dataset_path=self.dataset_path,
                          scenario=self.scenario, metadata=self.metadata_, fallback=self.fallback_,
                          fallback_trust=None if self.fallback_trusted_ is None else self.fallback_trusted_.layer,
                          gate=self.gate_, expert=None if self.nominal_expert_ is None else self.nominal_expert_.get_state(),
                          expert_gate=self.expert_gate_, expert_routes=self.expert_routes_)

    @classmethod
    def from_state(cls, state: ModelState) -> "DeformationModel":
        """A fitted model from its state (:meth:`get_state`, or a model folder's)."""
        model = cls(state.config)
        model.run_config, model.dataset_path, model.scenario = state.run_config, state.dataset_path, state.scenario
        model._assemble(state)
        return model

    def _assemble(self, state: ModelState) -> None:
        """Set the fitted parts from ``state``; the baselines are rebuilt from the network's basis."""
        net = state.network
        self.network_: NetworkPredictor = net
        pca = global_part(net.basis)
        k_ridge = min(state.ridge_components, pca.n_components)
        self.ridge_ = RidgePredictor(net.mesh, net.markers, pca.truncated(k_ridge), self.config.ridge_ratio)
        self.rigid_ = RigidRegistrationPredictor(net.mesh, net.markers)
        self.trusted_ = None if state.trust is None else TrustedPredictor(net, state.trust)
        self.fallback_ = state.fallback
        self.fallback_trusted_ = None if state.fallback_trust is None else TrustedPredictor(state.fallback,
                                                                                              state.fallback_trust)
        learned, self._trusted = net, self.trusted_
        if self.fallback_ is not None:
            learned = InstrumentFallback(net, self.fallback_)
            if self.trusted_ is not None and self.fallback_trusted_ is not None:
                self._trusted = InstrumentFallback(self.trusted_, self.fallback_trusted_)
        self.nominal_expert_, self.expert_gate_, self.expert_routes_ = None, state.expert_gate, state.expert_routes
        if state.expert is not None:
            self.nominal_expert_ = DeformationModel.from_state(state.expert)
            self.nominal_expert_._use_gate(None)  # the model's gate judges the input: the expert's ranges are narrower
            if self._trusted is None or not self.nominal_expert_.has_trust:
                raise ModelError("a model with a nominal expert needs both trust layers (trust.npz, and in "
                                 "nominal_expert/; the gate reads both alarms): the folder is incomplete; make the pair "
                                 "again with `tissuecast experts`")
            self._trusted = NominalExpertRouter(learned, self._trusted, self.nominal_expert_._trusted, state.expert_gate,
                                                state.expert_routes)
            learned = self._trusted
        self._by_method = {"mlp": learned, "rigid": self.rigid_, "ridge": self.ridge_}
        self.gate_ = gate_of(state)
        self._use_gate(self.gate_)
        self.fixed_ = np.asarray(state.fixed, dtype=np.int64).ravel()
        self.pca_choice_ = state.pca_choice
        self.pca_curve_ = state.pca_curve
        self.training_ = state.training
        self.summaries_ = training_summaries(state.training)
        self.metadata_ = state.metadata

    # ------------------------------------------------------------------ fitting
    def fit(self, displacements, markers, *, mesh, fixed=(), train_idx=None, valid_idx=None,
            calibration_idx=None, auxiliary: AuxiliaryValues | None = None, sensitivities=None) -> "DeformationModel":
        """Fit PCA (training fields only), the MLP (ensemble) and the ridge baseline, then the
        trust layer (error bounds and alarm, :mod:`tissuecast.surrogate.trust`) on the
        calibration samples. With tracked instruments among the auxiliary inputs, the MLP and
        its trust layer are fitted a second time without them (the fallback, :mod:`.fallback`).

        Args:
            displacements: (N, n, 3) float displacement fields, mm (finite for the used samples).
            markers: (n_d,) 0-based marker vertex ids.
            mesh: the :class:`TetMesh` with n vertices.
            fixed: (k,) 0-based fixed vertex ids (metadata for users of the model).
            train_idx: sample indices for training; default: every sample not in valid_idx.
            valid_idx: sample indices for validation (checkpoint/early stopping); default: a
                seeded 10 % of the training indices.
            calibration_idx: sample indices for calibrating the trust layer, never trained
                on (split conformal on them, whatever ``surrogate.calibration`` says); default:
                by ``surrogate.calibration``: ``"cross-validation"`` trains on every training
                sample and calibrates on out-of-fold predictions (:mod:`.cross_calibration`),
                ``"split"`` holds a seeded ``calibration_share`` of the training indices out
                (none when that is 0 or leaves fewer than 8 samples), ``"none"``: no trust layer.
            auxiliary: every sample's auxiliary inputs (:class:`~.auxiliary.AuxiliaryValues`:
                instrument poses, measured parameters; finite for the used samples), or None
                for a markers-only model.
            sensitivities: the training samples' field sensitivities along their load
                directions (:class:`~tissuecast.dataset.sensitivities.Sensitivities`, mm per
                direction), fitted beside the fields with weight ``sensitivity_weight``
                (:mod:`.mlp`); None: the fields only.

        Returns:
            self.
        """
        t0 = time.perf_counter()
        c = self.config
        U, mk = check_fit_inputs(displacements, markers, mesh)
        splits = fit_splits(U.shape[0], train_idx, valid_idx, calibration_idx, seed=c.seed,
                            calibration_share=c.calibration_share if c.calibration == "split" else 0.0)
        Ut, Uv = flat_fields(U, splits)
        spec, A = _auxiliary_values(auxiliary, U.shape[0], splits)
        explicit = calibration_idx is not None
        if sensitivities is not None and sensitivities.values.shape[2:] != U.shape[1:]:
            raise ModelError(f"sensitivities of fields {sensitivities.values.shape[2:]} do not match the fields {U.shape[1:]}")
        sens = sensitivities if c.sensitivity_weight > 0 else None
        if c.sensitivity_weight > 0 and sensitivities is None:
            log.warning("surrogate.sensitivity_weight = %g but no sensitivities were given: training on the fields only "
                        "(DeformationModel.from_dataset computes them from the data set)", c.sensitivity_weight)
        with fit_stage("model"):
            net, trust, calibration = self._fit_learned(U, Ut, Uv, mk, mesh, splits, spec, A, explicit, sens)
        fallback, fallback_trust = None, None
        if spec.instruments:
            kept = A[:, len(spec.instrument_columns):]
            with fit_stage("markers-only fallback"):
                fallback, fallback_trust, _ = self._fit_learned(U, Ut, Uv, mk, mesh, splits, spec.without_instruments(),
                                                                kept, explicit, sens, epochs=c.fallback_epochs or c.epochs)
        pca = global_part(net.predictor.basis)  # the baselines and the trust layer's second predictor work in it
        ridge = RidgePredictor.fit(mesh, mk, pca, c.ridge_ratio, Uv[:, marker_columns(mk)], Uv)
        training = {
            "n_train": int(len(splits.train)),
            "n_valid": int(len(splits.valid)),
            "n_calibration": int(trust.conformal.n_calibration) if trust is not None else 0,
            "calibration": calibration,
            "n_components": int(net.predictor.n_components),
            "pca_rule": net.choice["rule"],
            "pca_seconds": net.pca_seconds,
            "mlp_seconds": float(sum(s.seconds for s in net.summaries)),
            "seconds": time.perf_counter() - t0,
            "members": [s.as_dict() for s in net.summaries],
            "sensitivities": None if sens is None else {
                "weight": float(c.sensitivity_weight), "directions": int(sens.values.shape[1]),
                "samples": int(np.isfinite(sens.values[:, :, 0, 0]).any(axis=1)[np.isin(sens.indices, splits.train)].sum())},
        }
        choice = {**net.choice, "ridge_components": ridge.n_components}
        if fallback is not None:
            training["fallback"] = {"n_components": int(fallback.predictor.n_components),
                                    "mlp_seconds": float(sum(s.seconds for s in fallback.summaries)),
                                    "members": [s.as_dict() for s in fallback.summaries]}
            choice["fallback"] = {k: v for k, v in fallback.choice.items() if k != "validation_curve"}
        seen = np.concatenate([splits.train, splits.valid, splits.calibration])
        gate = InputGate.from_inputs(mk, mesh.points[mk], U[seen][:, mk])
        self._assemble(ModelState(c, net.predictor, np.asarray(fixed, dtype=np.int64).ravel(), choice, net.curve, trust,
                                  training, self.run_config, self.dataset_path, self.scenario,
                                  fallback=None if fallback is None else fallback.predictor,
                                  fallback_trust=fallback_trust, gate=gate))
        return self

    def _fit_learned(self, U, Ut, Uv, mk, mesh, splits: FitSplits, spec: AuxiliaryInputs, A: np.ndarray | None,
                     explicit: bool, sensitivities=None, epochs: int | None = None):
        """``(NetworkFit, trust layer or None, calibration record)``: the learned predictor reading
        ``spec`` (values A (N, n_a), or None without) and its trust layer
        (:func:`~.cross_calibration.fit_model_trust`; ``explicit``: calibration samples were given),
        trained on ``sensitivities`` too when given, for ``epochs`` (None: the config's)."""
        c = self.config if epochs is None else replace(self.config, epochs=int(epochs))
        A = A if spec.width else None
        rows = (None, None) if A is None else (A[splits.train], A[splits.valid])
        St = None if sensitivities is None else sensitivities.rows(splits.train)
        net = fit_network(Ut, Uv, mk, mesh, c, *rows, auxiliary=spec, St=St)
        del St
        trust, record = fit_model_trust(net.predictor, U, splits, mesh, c, explicit=explicit, auxiliary=A,
                                        sensitivities=sensitivities)
        return net, trust, record

    @classmethod
    def from_dataset(cls, dataset, config: Config | SurrogateConfig | None = None, **overrides) -> "DeformationModel":
        """Fit on a data-set store: the 'train' split (status done) trains, 'valid' validates.

        Args:
            dataset: a :class:`tissuecast.dataset.Dataset` (from ``open_dataset``).
            config: settings; default: the data set's own config. Its ``markers.ids``, when
                given, replace the store's markers (the store holds every vertex's
                displacement, e.g. for markers planned by ``tissuecast markers plan``). Its
                scenario's instruments and measured parameters (the data set's own, for a
                SurrogateConfig) are the model's auxiliary inputs (:mod:`.auxiliary`).
        """
        if config is None:
            config = dataset.config
        source = config if isinstance(config, Config) else dataset.config  # the scenario's inputs
        arrays = dataset_arrays(dataset, None if source is None else AuxiliaryInputs.from_config(source.scenario))
        markers = arrays.markers
        if isinstance(config, Config) and config.markers.ids:
            from ..markers import validate_vertex_ids

            markers = validate_vertex_ids(arrays.mesh, config.markers.ids, "markers.ids", other=arrays.fixed,
                                          other_what="the store's fixed vertices")
        model = cls(config, **overrides)
        model.dataset_path = str(Path(dataset.path).resolve()) if dataset.path is not None else None
        model.scenario = dataset.scenario
        sensitivities = None
        if model.config.sensitivity_weight > 0:
            from ..dataset.sensitivities import dataset_sensitivities

            log.info("the simulator's sensitivities of %d training samples (one tangent factorisation each)",
                     len(arrays.train_idx))
            sensitivities = dataset_sensitivities(dataset, arrays.train_idx)
        return model.fit(
            arrays.displacements, markers, mesh=arrays.mesh, fixed=arrays.fixed,
            train_idx=arrays.train_idx, valid_idx=arrays.valid_idx, auxiliary=arrays.auxiliary,
            sensitivities=sensitivities,
        )

    # ------------------------------------------------------------------ prediction
    def predict(self, marker_displacements, *, missing=None, method: str = "mlp", auxiliary=None) -> np.ndarray:
        """Displacement field from marker displacements (and the auxiliary inputs).

        Args:
            marker_displacements: (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) float, mm.
            missing: optional untracked markers: indices into the marker list, or a bool mask
                (n_d,) / (B, n_d). The MLP needs a model trained with ``marker_dropout > 0``;
                the rigid baseline registers on the tracked markers (>= 3, not collinear).
            method: ``"mlp"`` (the learned model, ensemble mean), ``"rigid"`` (rigid
                registration from the markers: the baseline navigation systems use, and a
                fallback) or ``"ridge"`` (the paper's ridge baseline; no missing markers).
            auxiliary: for a model with auxiliary inputs (``model.auxiliary``: names and
                units), a mapping ``{instrument name: tissuecast.instruments.InstrumentPose (or a
                list of B), parameter name: value (or B values)}`` or an array (n_a,) / (B, n_a)
                in ``model.auxiliary.names`` order. Poses are in the model frame (LPS, mm). An
                instrument left out, None or NaN is absent (tracking lost): the sample is
                predicted by the fallback fitted without instruments. None = every instrument
                absent (a model with measured parameters needs them). Rigid and ridge ignore it; a
                markers-only model refuses it (ModelError) rather than ignore it.

        Returns:
            (n, 3) float64 mm for one sample, (B, n, 3) for a batch.
        """
        self.auxiliary.refuse_unread(auxiliary)
        return self.predictor(method).predict(marker_displacements, missing=missing, auxiliary=auxiliary)

    def _predict_batch(self, d: np.ndarray, missing: np.ndarray | None, a: np.ndarray | None = None) -> np.ndarray:
        return self._by_method["mlp"].predict(d, missing=missing, auxiliary=a)

    def predict_trusted(self, marker_displacements, *, coverage: float | None = None,
                        false_alarm: float | None = None, auxiliary=None, alarm: bool = True) -> TrustedPrediction:
        """The MLP's field with per-vertex error bounds and the out-of-distribution alarm
        (:meth:`FieldPredictor.predict_trusted <.field_predictor.FieldPredictor.predict_trusted>`).

        Args:
            marker_displacements: as for :meth:`predict` (every marker tracked), mm.
            coverage: nominal coverage of the bounds (default ``surrogate.coverage``).
            false_alarm: false-alarm rate of the alarm (default ``surrogate.false_alarm_rate``).
            auxiliary: as for :meth:`predict` (the bounds and the alarm read them too; a sample
                with an absent instrument gets the fallback's).
            alarm: False leaves the alarm out (``alarms`` None): :meth:`alarms` gives the same
                alarm later (a server sends the field first).

        Raises:
            ModelError: the model has no trust layer (trained with calibration = "none", or too few samples).
        """
        self._need_trust()
        self.auxiliary.refuse_unread(auxiliary)
        return self._trusted.predict_trusted(marker_displacements, coverage=coverage, false_alarm=false_alarm,
                                             auxiliary=auxiliary, alarm=alarm)

    def alarms(self, marker_displacements, *, false_alarm: float | None = None, auxiliary=None):
        """The out-of-distribution alarm of :meth:`predict_trusted`, alone: one
        :class:`~tissuecast.surrogate.trust.Alarm` for one input, a list of B for a batch
        (arguments as there).

        Raises:
            ModelError: the model has no trust layer.
        """
        self._need_trust()
        self.auxiliary.refuse_unread(auxiliary)
        return self._trusted.alarms(marker_displacements, false_alarm=false_alarm, auxiliary=auxiliary)

    def _need_trust(self) -> None:
        if not self.has_trust:
            raise ModelError("this model has no calibrated error bounds or alarm; re-train it with surrogate.calibration = "
                             "'cross-validation' (out-of-fold, no samples held out) or 'split' with calibration_share > 0 "
                             f"(e.g. {SurrogateConfig.calibration_share:g})")

    def _use_gate(self, gate) -> None:
        """``gate`` (or None: none) refuses input for the model and every part it predicts with."""
        self.input_gate = gate
        parts = (self.network_, self.ridge_, self.rigid_, self.trusted_, self.fallback_, self.fallback_trusted_,
                 self._trusted, *self._by_method.values())
        for part in parts:
            if part is not None:
                part.input_gate = gate

    @contextmanager
    def gate_suspended(self):
        """A block in which the input gate refuses nothing: for evaluating simulated samples,
        which reports the gate's verdicts (:meth:`check_input`) beside the errors instead of
        stopping at the first refusal. The gate is back on when the block ends."""
        self._fitted()
        self._use_gate(None)
        try:
            yield self
        finally:
            self._use_gate(self.gate_)

    def check_input(self, marker_displacements, *, missing=None) -> GateVerdict | list[GateVerdict]:
        """The input gate's verdict (:mod:`.gate`) without predicting: one :class:`~.gate.GateVerdict`
        for one sample, a list for a batch (same layouts as :meth:`predict`, mm). ``predict`` and
        the other predict methods raise :class:`~tissuecast.errors.InputRejected` where it refuses."""
        self._fitted()
        d, miss, single = marker_batch(marker_displacements, self.n_markers, missing, self.supports_missing_markers,
                                       check_finite=False)
        verdicts = self.gate_.inspect(d, miss)
        return verdicts[0] if single else verdicts

    def predict_from_positions(self, positions, *, missing=None, method: str = "mlp", auxiliary=None) -> np.ndarray:
        """Displacement field from tracked marker positions (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) mm.

        The positions must be in the model's (mesh) coordinate frame; the reference
        (undeformed) marker positions are subtracted. ``method`` and ``auxiliary`` as in :meth:`predict`.
        """
        self.auxiliary.refuse_unread(auxiliary)
        return self.predictor(method).predict_from_positions(positions, missing=missing, auxiliary=auxiliary)

    def predict_ridge(self, marker_displacements) -> np.ndarray:
        """The paper's ridge-regression baseline: (n, 3) or (B, n, 3) mm, same inputs as :meth:`predict`.

        It uses the first ``pca_choice_["ridge_components"]`` components of the model's basis,
        the number at which ridge had its lowest validation error.
        """
        return self.predictor("ridge").predict(marker_displacements)

    def predict_rigid(self, marker_displacements, *, missing=None) -> np.ndarray:
        """Rigid-registration baseline (:class:`~.baselines.RigidRegistrationPredictor`): the mesh
        moved by the best rigid fit (Kabsch) of the markers' reference positions to their
        displaced positions; ``missing`` markers are left out of the fit (>= 3 must remain).

        Raises:
            RegistrationError: fewer than 3 tracked markers, or tracked markers on one line.
        """
        return self.predictor("rigid").predict(marker_displacements, missing=missing)

    def predict_with_uncertainty(self, marker_displacements, *, missing=None,
                                 auxiliary=None) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean field and per-vertex uncertainty
        (:meth:`NetworkPredictor.predict_with_uncertainty <.network_predictor.NetworkPredictor.predict_with_uncertainty>`):
        ``(u (n, 3) or (B, n, 3) mm, sigma (n,) or (B, n) mm)``. Needs ``ensemble >= 2``;
        ``auxiliary`` as in :meth:`predict`."""
        self.auxiliary.refuse_unread(auxiliary)
        return self.predictor("mlp").predict_with_uncertainty(marker_displacements, missing=missing,
                                                              auxiliary=auxiliary)

    def pca_projection(self, fields) -> np.ndarray:
        """Projection of displacement fields on the model's PCA basis: (n, 3) or (B, n, 3) mm
        -> same shape. No prediction of this model can come closer to a field than this (the
        PCA truncation floor)."""
        self._fitted()
        return self.network_.pca_projection(fields)

    def describe(self) -> dict:
        """The learned predictor's description plus the record of the fit (n_w's rule without its
        curves, the training summary)."""
        self._fitted()
        pca = {k: v for k, v in (self.pca_choice_ or {}).items() if k != "validation_curve"}
        out = {**self.network_.describe(), "has_trust": self.has_trust, "pca": pca, "training": self.training_}
        if self.fallback_ is not None:
            out["fallback"] = self.fallback_.describe()
        if self.nominal_expert_ is not None:
            out["nominal_expert"] = self.nominal_expert_.describe()
            out["expert_gate"] = gate_description(self.expert_gate_, self.expert_routes_)
            out["has_uncertainty"] = self.has_uncertainty
        return out

    # ------------------------------------------------------------------ a nominal expert
    def with_nominal_expert(self, expert: "DeformationModel", fields, *, auxiliary=None,
                            drawn=None) -> "DeformationModel":
        """This model with a nominal expert beside it (:mod:`.experts`): a new model whose field
        comes, sample by sample, from ``expert`` where a gate fitted here expects it to be the
        better one, and from this model elsewhere; the alarm stays this model's, the bounds are
        calibrated per route (:class:`.experts.RouteCalibration`) on the fields drawn as this
        model's training data were.

        Args:
            expert: a model trained at the scenario's nominal parameters on the same mesh, with
                this model's markers and auxiliary inputs, calibrated (``has_trust``).
            fields: (B, n, 3) mm simulated fields neither model was trained on, drawn as both
                models' training data were (the validation splits of their stores,
                :func:`tissuecast.app.pipeline.gate_fields`): the gate is fitted on them.
            auxiliary: (B, n_a) their auxiliary inputs (models with some), as for :meth:`predict`.
            drawn: (B,) bool, the fields drawn as this model's training data were (with the
                scenario's parameters drawn; default all): the bounds are calibrated on these, so
                that they hold on each route under the distribution this model's own bounds hold
                under (the nominal store's samples would make the expert's route look easier
                than it is off the nominal parameters; measured in docs/uncertainty.md).

        Raises:
            ModelError: a model without trust, an expert that does not fit (other markers, mesh
                or inputs; an expert with an expert), or samples on which one model is always
                the better one.
        """
        self._fitted()
        expert._fitted()
        self._need_trust()
        if not expert.has_trust:
            raise ModelError("the nominal expert has no calibrated error bounds or alarm (the gate reads its alarm's "
                             "input distance); "
                             "train it with surrogate.calibration = 'split' or 'cross-validation'")
        if expert.has_nominal_expert or self.has_nominal_expert:
            raise ModelError("a model with a nominal expert takes no second one; start from the models it was made of")
        U = np.asarray(fields, dtype=np.float64)
        if U.ndim != 3 or U.shape[1:] != (self.n_vertices, 3):
            raise ModelError(f"fields must be (B, {self.n_vertices}, 3) mm, got {U.shape}")
        keep = np.ones(len(U), dtype=bool) if drawn is None else np.asarray(drawn, dtype=bool)
        if keep.shape != (len(U),):
            raise ModelError(f"drawn must be (B,) = ({len(U)},) bool, got shape {keep.shape}")
        state = self.get_state()
        expert_state = expert.get_state()
        trial = DeformationModel.from_state(expert_state)
        trial._use_gate(None)
        check_expert(self._trusted, trial._trusted)
        d = self.marker_displacements(U).reshape(len(U), -1)
        a = self._trusted.auxiliary_batch(auxiliary, len(U))
        with self.gate_suspended():
            mine = self._trusted.predict_trusted(d, auxiliary=a, alarm=False)
            features = gate_features(trial._trusted, self._trusted, d, a)
        theirs = trial._trusted.predict(d, auxiliary=a)
        e_theirs, e_mine = (np.linalg.norm(u - U, axis=2) for u in (theirs, mine.displacement))
        better = e_theirs.max(axis=1) < e_mine.max(axis=1)
        gate = ExpertGate.fit(features, better)
        routed = out_of_fold_routes(features, better)
        routes = RouteCalibration.fit(routed[keep], e_theirs[keep], e_mine[keep], mine.error_bound[keep])
        return DeformationModel.from_state(replace(state, expert=expert_state, expert_gate=gate, expert_routes=routes))

    # ------------------------------------------------------------------ persistence
    def save(self, folder, *, onnx: bool = False) -> None:
        """Write the model folder (see :mod:`tissuecast.surrogate.storage`)."""
        from .storage import save_model

        save_model(self.get_state(), folder, onnx=onnx)

    @classmethod
    def load(cls, folder) -> "DeformationModel":
        """Read a model folder written by :meth:`save` (no pickle; checks format and schema)."""
        from .storage import load_model

        return cls.from_state(load_model(folder))

    def export_onnx(self, path, *, fallback: bool = False, expert: str | None = None) -> None:
        """Write an ONNX graph: inputs ``markers`` (B, n_d, 3) float32 marker displacements (not
        positions) mm [+ ``auxiliary`` (B, n_a)
        float32 in ``model.auxiliary.units``] [+ ``present`` (B, n_d)], output ``displacement``
        (B, n, 3) float32 mm (PCA reconstruction included). ``fallback``: the graph of the
        fallback without instruments (models with instrument inputs). For a model with a nominal
        expert the graph routes each sample as the model does, both networks and the gate on
        their input distances in it (:class:`~.experts.RoutedNetworks`); ``expert``: one of its
        networks alone instead, ``"uncertain"`` (this model's) or ``"nominal"``. The graph has no
        input gate, bounds or alarm; its ``metadata_props`` describe the inputs (docs/files.md)."""
        from .storage import export_onnx

        export_onnx(self._learned(fallback, expert), path)

    def torch_module(self, *, fallback: bool = False, expert: str | None = None):
        """The equivalent torch module, see :func:`tissuecast.surrogate.network.torch_network`: it
        takes float32 tensors with a batch axis, (B, n_d, 3) marker displacements mm (and the
        inputs :meth:`export_onnx` lists), and checks nothing (no gate, bounds or alarm);
        ``fallback`` and ``expert`` as in :meth:`export_onnx`."""
        return self._learned(fallback, expert).torch_module()

    def _learned(self, fallback: bool, expert: str | None = None) -> NetworkPredictor | RoutedNetworks:
        self._fitted()
        if expert not in (None, "uncertain", "nominal"):
            raise ModelError(f"expert must be 'uncertain' or 'nominal', got {expert!r}")
        if self.nominal_expert_ is None and expert is not None:
            raise ModelError("this model has no nominal expert; export it without expert=")
        if self.nominal_expert_ is not None and expert is None:
            return routed_networks(self.get_state(), fallback)
        if expert == "nominal":
            return self.nominal_expert_._learned(fallback)
        if fallback and self.fallback_ is None:
            raise ModelError("this model has no fallback: it reads no tracked instrument")
        return self.fallback_ if fallback else self.network_

    def __repr__(self) -> str:
        if not self.is_fitted:
            return f"DeformationModel(hidden={list(self.config.hidden)}, unfitted)"
        return (f"DeformationModel(n_vertices={self.n_vertices}, markers={self.markers.tolist()}, "
                f"n_components={self.n_components}, hidden={list(self.network_.hidden)}, ensemble={self.ensemble_size})")
