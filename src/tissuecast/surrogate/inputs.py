"""Validation of marker-displacement input: accepted layouts, missing markers, NaN checks."""

from __future__ import annotations

import numpy as np

from ..errors import ModelError

__all__ = ["marker_batch", "missing_mask"]


def marker_batch(marker_displacements, n_d: int, missing=None, masked: bool = False,
                 gate=None, *, check_finite: bool = True) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """Check and reshape marker displacements.

    Args:
        marker_displacements: (3 n_d,), (n_d, 3), (B, n_d, 3) or (B, 3 n_d) float, mm.
        n_d: number of markers of the model.
        missing: untracked markers: indices into the marker list, or bool (n_d,) / (B, n_d).
        masked: whether the model accepts missing markers.
        gate: the model's :class:`~.gate.InputGate`, or None; it refuses implausible tracked
            markers (non-finite ones included) with :class:`~tissuecast.errors.InputRejected`.
        check_finite: refuse NaN/inf in tracked markers (False: leave them to the caller).

    Returns:
        ``(d (B, 3 n_d) float64 with missing entries zeroed, missing (B, n_d) bool or None, single)``.

    Raises:
        ModelError: wrong shape, an empty batch, NaN/inf in tracked markers, missing markers for a model
            trained without masking, or every marker missing.
        InputRejected: the gate refused the input.
    """
    try:
        d = np.asarray(marker_displacements, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"marker displacements must be numeric, got {type(marker_displacements).__name__}") from exc
    s = d.shape
    if s == (3 * n_d,) or s == (n_d, 3):
        d, single = d.reshape(1, 3 * n_d), True
    elif len(s) == 3 and s[1:] == (n_d, 3):
        d, single = d.reshape(s[0], 3 * n_d), False
    elif len(s) == 2 and s[1] == 3 * n_d:
        single = False
    else:
        raise ModelError(
            f"marker displacements must have shape ({3 * n_d},), ({n_d}, 3), (B, {n_d}, 3) or (B, {3 * n_d}) "
            f"for this model's {n_d} markers (mm), got {s}"
        )
    if d.shape[0] == 0:
        raise ModelError(f"no sample to predict: marker displacements of shape {s} hold a batch of 0")
    miss = None
    if missing is not None:
        miss = missing_mask(missing, d.shape[0], n_d)
        if not miss.any():
            miss = None
        elif not masked:
            raise ModelError(
                "this model was trained without marker masking and cannot predict with missing markers; "
                "retrain with surrogate.marker_dropout > 0"
            )
        elif miss.all(axis=1).any():
            raise ModelError("at least one marker must be tracked in every sample")
    if gate is not None:
        gate.enforce(d, miss)
    check = d if miss is None else np.where(np.repeat(miss, 3, axis=1), 0.0, d)
    if check_finite and not np.isfinite(check).all():
        raise ModelError("marker displacements contain NaN or inf; mark untracked markers with missing=[...]")
    if miss is not None:
        d = check
    return d, miss, single


def missing_mask(missing, batch: int, n_d: int) -> np.ndarray:
    """(batch, n_d) bool mask of untracked markers.

    Args:
        missing: indices into the marker list (0-based), or bool (n_d,) / (batch, n_d).
        batch: number of samples B.
        n_d: number of markers of the model.

    Raises:
        ModelError: a bool mask of the wrong shape, or an index outside [0, n_d).
    """
    mask = np.zeros((batch, n_d), dtype=bool)
    mv = np.asarray(missing)
    if mv.dtype == bool:
        if mv.shape not in ((n_d,), (batch, n_d)):
            raise ModelError(f"missing mask must be ({n_d},) or ({batch}, {n_d}) booleans, got {mv.shape}")
        mask[:] = mv
    else:
        ids = mv.astype(np.int64).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= n_d):
            raise ModelError(f"missing marker indices must be in [0, {n_d}) (positions in the marker list), got {ids.tolist()}")
        mask[:, ids] = True
    return mask
