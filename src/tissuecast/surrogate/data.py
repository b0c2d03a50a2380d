"""Arrays a surrogate trains on, taken from a data-set store."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError

__all__ = ["TrainingArrays", "dataset_arrays", "split_indices"]


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
    """

    displacements: np.ndarray
    train_idx: np.ndarray
    valid_idx: np.ndarray
    markers: np.ndarray
    fixed: np.ndarray
    mesh: object


def split_indices(dataset, split: str) -> np.ndarray:
    """Indices (k,) int64 of the converged samples of ``split`` ('train', 'valid', 'test1', 'test2')."""
    return np.asarray(dataset.select(split, status="done"), dtype=np.int64)


def dataset_arrays(dataset) -> TrainingArrays:
    """Collect training arrays from a :class:`tissuecast.dataset.Dataset`."""
    train = split_indices(dataset, "train")
    valid = split_indices(dataset, "valid")
    if train.size < 2 or valid.size < 1:
        raise ModelError(
            f"the data set has {train.size} converged training and {valid.size} validation samples; "
            "need at least 2 and 1 (run `tissuecast simulate` to completion first)"
        )
    return TrainingArrays(
        displacements=np.asarray(dataset.displacements),
        train_idx=train,
        valid_idx=valid,
        markers=np.asarray(dataset.markers, dtype=np.int64),
        fixed=np.asarray(dataset.fixed, dtype=np.int64),
        mesh=dataset.mesh,
    )
