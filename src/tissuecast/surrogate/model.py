"""DeformationModel: marker displacements -> whole-body displacement field (PCA + MLP).

Scikit-learn style: the hyper-parameters come from a :class:`~tissuecast.config.SurrogateConfig`
given to ``__init__``; ``fit`` learns the state (attributes ending in ``_``) and returns
``self``; predicting with an unfitted model raises :class:`~tissuecast.errors.ModelError`.

Marker displacements are ordered like the markers, vertex-major: ``(d0x, d0y, d0z, d1x, ...)``
in mm. A displacement field is (n, 3) mm at every mesh vertex (0-based ids).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..config import Config, SurrogateConfig, config_to_dict, with_overrides
from ..errors import ModelError
from .component_choice import choose_by_validation, components_to_train, ridge_components
from .data import FitSplits, dataset_arrays, fit_splits
from .fastpath import CompiledSurrogate
from .head import fit_head, truncated_head
from .inputs import marker_batch
from .mlp import train_mlp
from .pca import PCABasis, PCACurve, fit_pca
from .quadratic import QuadraticRegression
from .ridge import RidgeBaseline, fit_ridge, marker_columns
from .trust import TrustedPrediction, fit_trust
from .weights import MLPWeights

__all__ = ["DeformationModel"]

log = logging.getLogger(__name__)


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


def _check_fit_inputs(displacements, markers, mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(U (N, n, 3), markers (n_d,) int64)`` checked against the mesh's n vertices."""
    U = np.asarray(displacements)
    if U.ndim != 3 or U.shape[2] != 3:
        raise ModelError(f"displacements must be (N, n, 3) mm, got shape {U.shape}")
    if U.shape[1] != mesh.n_vertices:
        raise ModelError(f"displacements have {U.shape[1]} vertices but the mesh has {mesh.n_vertices}")
    mk = np.asarray(markers, dtype=np.int64).ravel()
    if mk.size == 0 or mk.min() < 0 or mk.max() >= mesh.n_vertices or np.unique(mk).size != mk.size:
        raise ModelError(f"markers must be distinct 0-based vertex ids in [0, {mesh.n_vertices}), got {mk.tolist()}")
    return U, mk


def _flat_fields(U: np.ndarray, splits: FitSplits) -> tuple[np.ndarray, np.ndarray]:
    """Training and validation fields as float64 rows (N_t, 3 n), (N_v, 3 n) mm, checked finite."""
    Ut = U[splits.train].reshape(len(splits.train), -1).astype(np.float64)
    Uv = U[splits.valid].reshape(len(splits.valid), -1).astype(np.float64)
    if not (np.isfinite(Ut).all() and np.isfinite(Uv).all()):
        raise ModelError("training/validation displacements contain NaN or inf; select samples with status 'done'")
    return Ut, Uv


#: Member k of an ensemble trains with seed ``surrogate.seed + ENSEMBLE_SEED_STRIDE * k``: far
#: enough apart that runs with neighbouring seeds share no member.
ENSEMBLE_SEED_STRIDE = 1000


class DeformationModel:
    """PCA + MLP surrogate of nonlinear FEM (Liu et al. 2020), with the ridge baseline.

    By default (``surrogate.head = "quadratic"``) a quadratic regression of the PCA weights on
    the marker displacements (:mod:`.head`) predicts first and the networks learn its residual;
    ``head = "none"`` is the paper's network alone.

    Args:
        config: surrogate settings (a :class:`SurrogateConfig`, or a whole :class:`Config`);
            None uses the defaults.
        **overrides: individual ``SurrogateConfig`` fields, validated like a config file
            (e.g. ``hidden=(64, 64), ensemble=5``).
    """

    def __init__(self, config: SurrogateConfig | Config | None = None, **overrides):
        self.config = _surrogate_config(config, overrides)
        self.run_config: dict | None = config_to_dict(config) if isinstance(config, Config) else None
        self.dataset_path: str | None = None
        #: the clinical scenario of the training data (``Dataset.scenario``: supports, loads,
        #: materials; see :mod:`tissuecast.scenario.describe`), or None when not recorded
        self.scenario: dict | None = None

    # ------------------------------------------------------------------ fitted state
    def _fitted(self) -> None:
        if not hasattr(self, "members_"):
            raise ModelError("this DeformationModel is not fitted yet; call fit(...) or DeformationModel.load(folder)")

    @property
    def is_fitted(self) -> bool:
        return hasattr(self, "members_")

    @property
    def mesh(self):
        """The :class:`~tissuecast.mesh.TetMesh` the model predicts on (n vertices)."""
        self._fitted()
        return self.mesh_

    @property
    def markers(self) -> np.ndarray:
        """(n_d,) int64 0-based fiducial marker vertex ids, in input order."""
        self._fitted()
        return self.markers_

    @property
    def fixed(self) -> np.ndarray:
        """(k,) int64 0-based fixed vertex ids of the simulations."""
        self._fitted()
        return self.fixed_

    @property
    def reference_marker_positions(self) -> np.ndarray:
        """(n_d, 3) float64 mm: undeformed marker positions (subtracted from tracked positions)."""
        self._fitted()
        return self.mesh_.points[self.markers_].astype(np.float64)

    @property
    def n_markers(self) -> int:
        return int(self.markers.size)

    @property
    def n_vertices(self) -> int:
        return int(self.mesh.n_vertices)

    @property
    def n_components(self) -> int:
        self._fitted()
        return self.pca_.n_components

    @property
    def ensemble_size(self) -> int:
        self._fitted()
        return len(self.members_)

    @property
    def supports_missing_markers(self) -> bool:
        """Whether the network was trained with marker masking (``marker_dropout > 0``)."""
        self._fitted()
        return bool(self.members_[0].masked)

    # ------------------------------------------------------------------ fitting
    def fit(self, displacements, markers, *, mesh, fixed=(), train_idx=None, valid_idx=None,
            calibration_idx=None) -> "DeformationModel":
        """Fit PCA (training fields only), the ridge baseline and the MLP (ensemble), then the
        trust layer (error bounds and alarm, :mod:`tissuecast.surrogate.trust`) on the
        calibration samples.

        Args:
            displacements: (N, n, 3) float displacement fields, mm (finite for the used samples).
            markers: (n_d,) 0-based marker vertex ids.
            mesh: the :class:`TetMesh` with n vertices.
            fixed: (k,) 0-based fixed vertex ids (metadata for users of the model).
            train_idx: sample indices for training; default: every sample not in valid_idx.
            valid_idx: sample indices for validation (checkpoint/early stopping); default: a
                seeded 10 % of the training indices.
            calibration_idx: sample indices for calibrating the trust layer, never trained
                on; default: a seeded ``surrogate.calibration_share`` of the training indices
                (none when that is 0 or leaves fewer than 8 samples: then no trust layer).

        Returns:
            self.
        """
        t0 = time.perf_counter()
        c = self.config
        U, mk = _check_fit_inputs(displacements, markers, mesh)
        splits = fit_splits(U.shape[0], train_idx, valid_idx, calibration_idx, seed=c.seed,
                            calibration_share=c.calibration_share)
        Ut, Uv = _flat_fields(U, splits)
        n_w, rule, curve = components_to_train(c, Ut)
        t_pca = time.perf_counter()
        basis = fit_pca(Ut, n_w)
        cols = marker_columns(mk)
        Xt, Xv = Ut[:, cols], Uv[:, cols]
        Yt, Yv = basis.transform(Ut), basis.transform(Uv)
        head, head_info = None, {"dims": None}
        if c.head == "quadratic" and c.marker_dropout == 0:
            head, head_info = fit_head(Xt, Yt, Xv, Uv, basis, c.head_dims)
        elif c.head == "quadratic":
            log.info("no quadratic head: it needs every marker, and marker_dropout > 0 trains for missing ones")
        head_t = None if head is None else head.predict(Xt)
        head_v = None if head is None else head.predict(Xv)
        members, summaries = self._train_members(Xt, Yt if head is None else Yt - head_t, Xv,
                                                 Yv if head is None else Yv - head_v)
        choice = {"rule": rule, "n_components": n_w, "head": head_info}
        if not c.n_components and c.pca_rule == "validation":
            n_w, curve_v = choose_by_validation(members, basis, Xv, Uv, head_v)
            basis, members = basis.truncated(n_w), [m.truncated(n_w) for m in members]
            head = truncated_head(head, n_w)
            choice.update(n_components=n_w, trained_components=int(curve_v["n_components"][-1]), validation_curve=curve_v)
        choice["ridge_components"] = ridge_components(basis, mk, c.ridge_ratio, Xv, Uv)
        self.pca_choice_ = choice
        self._set_state(mesh=mesh, markers=mk, fixed=np.asarray(fixed, dtype=np.int64).ravel(), basis=basis,
                        members=members, curve=curve, head=head)
        self.summaries_ = summaries
        self.trust_ = None
        if len(splits.calibration):
            self.trust_ = fit_trust(self, U, train_idx=splits.train, valid_idx=splits.valid,
                                    calibration_idx=splits.calibration, coverage=c.coverage,
                                    false_alarm=c.false_alarm_rate, fault_score=c.alarm_fault_score)
        self.training_ = {
            "n_train": int(len(splits.train)),
            "n_valid": int(len(splits.valid)),
            "n_calibration": int(len(splits.calibration)),
            "n_components": int(n_w),
            "pca_rule": rule,
            "pca_seconds": t_pca - t0,
            "mlp_seconds": float(sum(s.seconds for s in summaries)),
            "seconds": time.perf_counter() - t0,
            "members": [s.as_dict() for s in summaries],
        }
        return self

    def _train_members(self, Xt, Yt, Xv, Yv) -> tuple[list[MLPWeights], list]:
        """The ensemble's networks (member k seeded ``seed + ENSEMBLE_SEED_STRIDE k``) and their training summaries."""
        c = self.config
        members, summaries = [], []
        for k in range(c.ensemble):
            w, s = train_mlp(Xt, Yt, Xv, Yv, c, seed=c.seed + ENSEMBLE_SEED_STRIDE * k)
            members.append(w)
            summaries.append(s)
        return members, summaries

    def _set_state(self, *, mesh, markers, fixed, basis: PCABasis, members: list[MLPWeights], curve: PCACurve | None,
                   head: QuadraticRegression | None = None):
        if members[0].weights[-1].shape[0] != basis.n_components or members[0].n_markers != len(markers):
            raise ModelError("network and PCA basis/markers do not fit together; the model folder is inconsistent")
        if head is not None and (head.coef.shape[1] != basis.n_components or head.mean.size != 3 * len(markers)
                                 or members[0].masked):
            raise ModelError("the quadratic head does not fit the network, PCA basis or markers; "
                             "the model folder is inconsistent")
        self.mesh_ = mesh
        self.markers_ = np.asarray(markers, dtype=np.int64)
        self.fixed_ = np.asarray(fixed, dtype=np.int64)
        self.pca_ = basis
        self.pca_curve_ = curve
        self.members_ = list(members)
        #: the quadratic head (:mod:`.head`) whose residual the networks learn, or None
        self.head_ = head
        k_ridge = int((getattr(self, "pca_choice_", None) or {}).get("ridge_components") or basis.n_components)
        ridge_basis = basis.truncated(min(k_ridge, basis.n_components))
        self.ridge_: RidgeBaseline = fit_ridge(ridge_basis, self.markers_, self.config.ridge_ratio)
        self.compiled_ = CompiledSurrogate(self.members_, basis, head)
        cols = marker_columns(self.markers_)
        # ridge as one affine map of the marker displacements: u = d @ R + r0
        proj = self.ridge_.matrix.T @ ridge_basis.components
        self._ridge_map = (proj, basis.mean - self.ridge_.marker_mean @ proj)
        self._marker_cols = cols

    @classmethod
    def from_dataset(cls, dataset, config: Config | SurrogateConfig | None = None, **overrides) -> "DeformationModel":
        """Fit on a data-set store: the 'train' split (status done) trains, 'valid' validates.

        Args:
            dataset: a :class:`tissuecast.dataset.Dataset` (from ``open_dataset``).
            config: settings; default: the data set's own config. Its ``markers.ids``, when
                given, replace the store's markers (the store holds every vertex's
                displacement, e.g. for markers planned by ``tissuecast markers plan``).
        """
        if config is None:
            config = getattr(dataset, "config", None)
        arrays = dataset_arrays(dataset)
        markers = arrays.markers
        if isinstance(config, Config) and config.markers.ids:
            from ..markers import validate_vertex_ids

            markers = validate_vertex_ids(arrays.mesh, config.markers.ids, "markers.ids", other=arrays.fixed,
                                          other_what="the store's fixed vertices")
        model = cls(config, **overrides)
        path = getattr(dataset, "path", None)
        model.dataset_path = str(Path(path).resolve()) if path is not None else None
        model.scenario = getattr(dataset, "scenario", None)
        return model.fit(
            arrays.displacements, markers, mesh=arrays.mesh, fixed=arrays.fixed,
            train_idx=arrays.train_idx, valid_idx=arrays.valid_idx,
        )

    # ------------------------------------------------------------------ prediction
    def _marker_batch(self, marker_displacements, missing=None) -> tuple[np.ndarray, np.ndarray | None, bool]:
        """Validated input -> ((B, 3 n_d) float64, missing (B, n_d) bool or None, single sample?)."""
        self._fitted()
        return marker_batch(marker_displacements, self.markers_.size, missing, self.members_[0].masked)

    def predict(self, marker_displacements, *, missing=None, method: str = "mlp") -> np.ndarray:
        """Displacement field from marker displacements.

        Args:
            marker_displacements: (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) float, mm.
            missing: optional untracked markers: indices into the marker list, or a bool mask
                (n_d,) / (B, n_d). The MLP needs a model trained with ``marker_dropout > 0``;
                the rigid baseline registers on the tracked markers (>= 3, not collinear).
            method: ``"mlp"`` (the learned model, ensemble mean), ``"rigid"`` (rigid
                registration from the markers: the baseline navigation systems use, and a
                fallback) or ``"ridge"`` (the paper's ridge baseline; no missing markers).

        Returns:
            (n, 3) float64 mm for one sample, (B, n, 3) for a batch.
        """
        if method == "rigid":
            return self.predict_rigid(marker_displacements, missing=missing)
        if method == "ridge":
            if missing is not None:
                raise ModelError("the ridge baseline cannot predict with missing markers; use method='mlp' or 'rigid'")
            return self.predict_ridge(marker_displacements)
        if method != "mlp":
            raise ModelError(f"unknown prediction method {method!r}; use 'mlp', 'rigid' or 'ridge'")
        d, miss, single = self._marker_batch(marker_displacements, missing)
        u = self.compiled_.fields(d, miss).reshape(d.shape[0], -1, 3)
        return u[0] if single else u

    @property
    def has_trust(self) -> bool:
        """Whether error bounds and the alarm are calibrated (``surrogate.calibration_share > 0``)."""
        return getattr(self, "trust_", None) is not None

    def predict_trusted(self, marker_displacements, *, coverage: float | None = None,
                        false_alarm: float | None = None) -> TrustedPrediction:
        """The MLP's field with per-vertex error bounds and the out-of-distribution alarm.

        Args:
            marker_displacements: as for :meth:`predict` (every marker tracked), mm.
            coverage: nominal coverage of the bounds (default ``surrogate.coverage``).
            false_alarm: false-alarm rate of the alarm (default ``surrogate.false_alarm_rate``).

        Returns:
            A :class:`~tissuecast.surrogate.trust.TrustedPrediction`: displacement (n, 3) or
            (B, n, 3) mm, error_bound (n,) or (B, n) mm, and one Alarm or a list of B.

        Raises:
            ModelError: the model has no trust layer (trained with calibration_share = 0).
        """
        if not self.has_trust:
            raise ModelError("this model has no calibrated error bounds or alarm; re-train it with "
                             f"surrogate.calibration_share > 0 (e.g. {SurrogateConfig.calibration_share:g})")
        d, _, single = self._marker_batch(marker_displacements)
        u = self.compiled_.fields(d).reshape(d.shape[0], -1, 3)
        bounds, alarms = self.trust_.assess(d, u, coverage=coverage, false_alarm=false_alarm)
        if single:
            return TrustedPrediction(u[0], bounds[0], coverage or self.trust_.coverage, alarms[0])
        return TrustedPrediction(u, bounds, coverage or self.trust_.coverage, alarms)

    def predict_from_positions(self, positions, *, missing=None, method: str = "mlp") -> np.ndarray:
        """Displacement field from tracked marker positions (n_d, 3) or (B, n_d, 3) mm.

        The positions must be in the model's (mesh) coordinate frame; the reference
        (undeformed) marker positions are subtracted. ``method`` as in :meth:`predict`.
        """
        self._fitted()
        p = np.asarray(positions, dtype=np.float64)
        if p.shape[-2:] != (self.n_markers, 3) or p.ndim not in (2, 3):
            raise ModelError(f"marker positions must be ({self.n_markers}, 3) or (B, {self.n_markers}, 3) mm, got {p.shape}")
        return self.predict(p - self.reference_marker_positions, missing=missing, method=method)

    def predict_ridge(self, marker_displacements) -> np.ndarray:
        """The paper's ridge-regression baseline: (n, 3) or (B, n, 3) mm, same inputs as :meth:`predict`.

        It uses the first ``pca_choice_["ridge_components"]`` components of the model's basis,
        the number at which ridge had its lowest validation error.
        """
        d, _, single = self._marker_batch(marker_displacements)
        R, r0 = self._ridge_map
        u = (d @ R + r0).reshape(d.shape[0], -1, 3)
        return u[0] if single else u

    def predict_rigid(self, marker_displacements, *, missing=None) -> np.ndarray:
        """Rigid-registration baseline: the mesh moved by the best rigid fit (Kabsch) of the
        markers' reference positions to their displaced positions.

        Args:
            marker_displacements: as for :meth:`predict`, mm.
            missing: optional untracked markers (left out of the fit; >= 3 must remain).

        Returns:
            (n, 3) or (B, n, 3) float64 mm.

        Raises:
            RegistrationError: fewer than 3 tracked markers, or tracked markers on one line.
        """
        from ..registration import rigid_registration_field

        self._fitted()
        d, miss, single = marker_batch(marker_displacements, self.markers_.size, missing, masked=True)
        d = d.reshape(d.shape[0], -1, 3)
        points = self.mesh_.points
        if miss is None:
            u = rigid_registration_field(points, self.markers_, d)
        else:
            u = np.stack([rigid_registration_field(points, self.markers_[~m], di[~m]) for di, m in zip(d, miss)])
        return u[0] if single else u

    def predict_with_uncertainty(self, marker_displacements, *, missing=None) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean field and per-vertex uncertainty.

        Returns:
            ``(u, sigma)``: u (n, 3) or (B, n, 3) mm as :meth:`predict`; sigma (n,) or (B, n) mm,
            the root-mean-square over members of each vertex's deviation from the ensemble
            mean (``sqrt(sum_xyz var)``, ddof 0). Needs ``ensemble >= 2``.
        """
        d, miss, single = self._marker_batch(marker_displacements, missing)
        if self.ensemble_size < 2:
            raise ModelError("uncertainty needs an ensemble; fit with surrogate.ensemble >= 2")
        W = self.compiled_.member_weights(d, miss)  # (M, B, n_w)
        C = self.pca_.components
        u = (W.mean(axis=0) @ C + self.pca_.mean).reshape(d.shape[0], -1, 3)
        dev = ((W - W.mean(axis=0)) @ C).reshape(W.shape[0], d.shape[0], -1, 3)
        sigma = np.sqrt((dev**2).sum(axis=3).mean(axis=0))
        return (u[0], sigma[0]) if single else (u, sigma)

    def pca_projection(self, fields) -> np.ndarray:
        """Projection of displacement fields on the model's PCA basis: (n, 3) or (B, n, 3) mm
        -> same shape. No prediction of this model can come closer to a field than this (the
        PCA truncation floor)."""
        self._fitted()
        f = np.asarray(fields, dtype=np.float64)
        flat = f.reshape(-1, self.pca_.n_features)
        return self.pca_.inverse_transform(self.pca_.transform(flat)).reshape(f.shape)

    def marker_displacements(self, fields) -> np.ndarray:
        """Marker displacements (B, n_d, 3) mm picked from full fields (B, n, 3) mm."""
        self._fitted()
        f = np.asarray(fields, dtype=np.float64)
        return f[..., self.markers_, :]

    # ------------------------------------------------------------------ persistence
    def save(self, folder, *, onnx: bool = False) -> None:
        """Write the model folder (see :mod:`tissuecast.surrogate.storage`)."""
        from .storage import save_model

        save_model(self, folder, onnx=onnx)

    @classmethod
    def load(cls, folder) -> "DeformationModel":
        """Read a model folder written by :meth:`save` (no pickle; checks format and schema)."""
        from .storage import load_model

        return load_model(cls, folder)

    def export_onnx(self, path) -> None:
        """Write an ONNX graph: input ``markers`` (B, n_d, 3) float32 mm [+ ``present`` (B, n_d)],
        output ``displacement`` (B, n, 3) float32 mm (PCA reconstruction included)."""
        from .storage import export_onnx

        export_onnx(self, path)

    def torch_module(self):
        """The equivalent torch module (float32), see :func:`tissuecast.surrogate.network.torch_network`."""
        from .network import torch_network

        self._fitted()
        return torch_network(self.members_, self.pca_.components, self.pca_.mean, self.head_)

    def __repr__(self) -> str:
        if not self.is_fitted:
            return f"DeformationModel(hidden={list(self.config.hidden)}, unfitted)"
        return (f"DeformationModel(n_vertices={self.n_vertices}, markers={self.markers_.tolist()}, "
                f"n_components={self.n_components}, hidden={list(self.members_[0].hidden)}, ensemble={self.ensemble_size})")
