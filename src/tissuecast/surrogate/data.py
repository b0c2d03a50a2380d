"""Arrays a surrogate trains on: taken from a data-set store, checked, split into train / valid / calibration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError
from .auxiliary import AuxiliaryInputs, AuxiliaryValues
from .field_predictor import check_vertex_ids

__all__ = ["TrainingArrays", "dataset_arrays", "dataset_auxiliary", "split_indices", "FitSplits", "fit_splits",
           "split_calibration", "check_fit_inputs", "flat_fields", "VALIDATION_EVERY", "MIN_SAMPLES", "CALIBRATION_SEED_OFFSET"]

#: Without given validation samples, one training sample in this many validates (at least one).
VALIDATION_EVERY = 10
#: Fewest calibration (and validation) samples a trust layer is fitted from.
MIN_SAMPLES = 8
#: The calibration hold-out is drawn with ``surrogate.seed`` plus this (a prime), so that it does
#: not repeat the draw of the validation split made with the same seed.
CALIBRATION_SEED_OFFSET = 7919


@dataclass(frozen=True, eq=False)
class TrainingArrays:
    """Everything ``DeformationModel.fit`` needs.

    Attributes:
        displacements: (N, n, 3) float32 mm, all samples of the store.
        train_idx: (N_t,) indices of converged 'train' samples.
        valid_idx: (N_v,) indices of converged 'valid' samples.
        markers: (n_d,) int64 0-based marker ids.
        fixed: (k,) int64 0-based fixed vertex ids.
        mesh: the store's TetMesh.
        auxiliary: every sample's auxiliary inputs (:class:`~.auxiliary.AuxiliaryValues`), or
            None for a markers-only model.
    """

    displacements: np.ndarray
    train_idx: np.ndarray
    valid_idx: np.ndarray
    markers: np.ndarray
    fixed: np.ndarray
    mesh: object
    auxiliary: AuxiliaryValues | None = None


def split_indices(dataset, split: str) -> np.ndarray:
    """Indices (k,) int64 of the converged samples of ``split`` ('train', 'valid', 'test1', 'test2')."""
    return np.asarray(dataset.select(split, status="done"), dtype=np.int64)


def dataset_auxiliary(dataset, inputs: AuxiliaryInputs) -> AuxiliaryValues:
    """Every sample's auxiliary inputs from a data set: the instruments' stored poses
    (``Dataset.instrument_poses``, as :func:`tissuecast.instruments.features_from_arrays` turns
    them into inputs; zeros where away or not solved) and the measured parameters
    (``Dataset.parameters``).

    Raises:
        ModelError: the store records no pose of an instrument, or no value of a parameter.
    """
    from ..instruments import features_from_arrays

    poses, params = dataset.instrument_poses, dataset.parameters
    cols = []
    for inst in inputs.instruments:
        if inst.name not in poses:
            raise ModelError(f"the data set records no pose of instrument {inst.name!r} (it has "
                             f"{sorted(poses) or 'none'}); simulate with [[scenario.instruments]] naming it, or train "
                             "with a config without it")
        p = poses[inst.name]
        cols.append(features_from_arrays(p["tip"], p["direction"], p["depth"], p["contact"] == 1))
    for name in inputs.parameters:
        if name not in params:
            raise ModelError(f"the data set records no value of the measured parameter {name!r} (it draws "
                             f"{sorted(params) or 'none'}); simulate with scenario.uncertain.{name} drawn")
        cols.append(np.asarray(params[name], dtype=np.float64)[:, None])
    values = np.hstack(cols) if cols else np.zeros((dataset.n_samples, 0))
    return AuxiliaryValues(inputs, values)


def dataset_arrays(dataset, inputs: AuxiliaryInputs | None = None) -> TrainingArrays:
    """Collect training arrays from a :class:`tissuecast.dataset.Dataset`, with the auxiliary
    inputs ``inputs`` declares (:func:`dataset_auxiliary`; None or empty: markers only)."""
    train = split_indices(dataset, "train")
    valid = split_indices(dataset, "valid")
    if train.size < 2 or valid.size < 1:
        raise ModelError(
            f"the data set has {train.size} converged training and {valid.size} validation samples; "
            "need at least 2 and 1 (samples still pending: run `tissuecast simulate` to completion; failed ones: "
            "`tissuecast dataset info` lists them; too few planned: raise dataset.n_samples or change dataset.split)"
        )
    return TrainingArrays(
        displacements=np.asarray(dataset.displacements),
        train_idx=train,
        valid_idx=valid,
        markers=np.asarray(dataset.markers, dtype=np.int64),
        fixed=np.asarray(dataset.fixed, dtype=np.int64),
        mesh=dataset.mesh,
        auxiliary=dataset_auxiliary(dataset, inputs) if inputs is not None and inputs.width else None,
    )


@dataclass(frozen=True, eq=False)
class FitSplits:
    """Disjoint sample indices of one fit: train (>= 2), valid (>= 1) and calibration (may be empty), int64."""

    train: np.ndarray
    valid: np.ndarray
    calibration: np.ndarray


def fit_splits(n_samples: int, train_idx=None, valid_idx=None, calibration_idx=None, *, seed: int,
               calibration_share: float) -> FitSplits:
    """The samples :meth:`DeformationModel.fit` trains, validates and calibrates on.

    Args:
        n_samples: N, number of samples given to the fit.
        train_idx: training indices; default: every sample not in ``valid_idx``.
        valid_idx: validation indices; default: a seeded 1 in :data:`VALIDATION_EVERY` of the
            training indices.
        calibration_idx: calibration indices; default: a seeded ``calibration_share`` of the
            training indices (:func:`split_calibration`).
        seed: seed of the default draws.
        calibration_share: share held out for calibration when ``calibration_idx`` is None.

    Raises:
        ModelError: fewer than 2 training or 1 validation samples, or indices outside [0, N).
    """
    rng = np.random.default_rng(seed)
    if train_idx is None:
        exclude = set() if valid_idx is None else set(np.asarray(valid_idx).tolist())
        train_idx = np.array([i for i in range(n_samples) if i not in exclude], dtype=np.int64)
    train_idx = np.asarray(train_idx, dtype=np.int64)
    if valid_idx is None:
        perm = rng.permutation(train_idx)
        n_valid = max(1, len(perm) // VALIDATION_EVERY)
        valid_idx, train_idx = np.sort(perm[:n_valid]), np.sort(perm[n_valid:])
    valid_idx = np.asarray(valid_idx, dtype=np.int64)
    if calibration_idx is None:
        train_idx, calibration_idx = split_calibration(train_idx, calibration_share, seed)
    calibration_idx = np.asarray(calibration_idx, dtype=np.int64)
    if len(train_idx) < 2 or len(valid_idx) < 1:
        raise ModelError(f"need at least 2 training and 1 validation samples, got {len(train_idx)} and {len(valid_idx)}")
    for name, idx in (("train_idx", train_idx), ("valid_idx", valid_idx)):
        if idx.min() < 0 or idx.max() >= n_samples:
            raise ModelError(f"{name} holds indices outside [0, {n_samples})")
    return FitSplits(train_idx, valid_idx, calibration_idx)


def split_calibration(train_idx, share: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Hold out a seeded ``share`` of the training indices for calibration.

    Returns:
        ``(train (k,) int64, calibration (m,) int64)``, both sorted; calibration is empty
        when ``share`` is 0 or would hold fewer than :data:`MIN_SAMPLES` samples.
    """
    idx = np.asarray(train_idx, dtype=np.int64)
    m = int(round(share * len(idx)))
    if share <= 0 or m < MIN_SAMPLES or len(idx) - m < 2:
        return np.sort(idx), np.zeros(0, dtype=np.int64)
    perm = np.random.default_rng(seed + CALIBRATION_SEED_OFFSET).permutation(idx)
    return np.sort(perm[m:]), np.sort(perm[:m])


def check_fit_inputs(displacements, markers, mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(U (N, n, 3), markers (n_d,) int64)`` checked against the mesh's n vertices."""
    U = np.asarray(displacements)
    if U.ndim != 3 or U.shape[2] != 3:
        raise ModelError(f"displacements must be (N, n, 3) mm, got shape {U.shape}")
    if U.shape[1] != mesh.n_vertices:
        raise ModelError(f"displacements have {U.shape[1]} vertices but the mesh has {mesh.n_vertices}")
    return U, check_vertex_ids(markers, mesh.n_vertices)


def flat_fields(U: np.ndarray, splits: FitSplits) -> tuple[np.ndarray, np.ndarray]:
    """Training and validation fields as float64 rows (N_t, 3 n), (N_v, 3 n) mm, checked finite."""
    Ut = U[splits.train].reshape(len(splits.train), -1).astype(np.float64)
    Uv = U[splits.valid].reshape(len(splits.valid), -1).astype(np.float64)
    if not (np.isfinite(Ut).all() and np.isfinite(Uv).all()):
        raise ModelError("training/validation displacements contain NaN or inf; select samples with status 'done'")
    return Ut, Uv
