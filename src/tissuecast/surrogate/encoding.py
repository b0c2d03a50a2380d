"""The network's input layout: standardised marker displacements and marker-present channels.

For n_d markers with displacements d (3 n_d,) mm, vertex-major ``(d0x, d0y, d0z, d1x, ...)``,
the network reads ``z = (d - x_mean) / x_std`` (standardised per component with the training
set's statistics). A network trained with marker masking (``surrogate.marker_dropout > 0``)
reads 4 n_d values instead::

    [z_0 p_0 (3 values), ..., z_(n_d-1) p_(n_d-1) (3 values), p_0, ..., p_(n_d-1)]

with p_j = 1 when marker j is tracked and 0 when it is not: an untracked marker's
standardised displacement is 0, the training mean of its displacement.

Training (:mod:`.mlp`, torch), the float64 reference forward pass
(:class:`.weights.MLPWeights`) and the torch/ONNX network (:mod:`.network`) build this input
with :func:`masked_input`; the compiled predictor (:mod:`.fastpath`) folds the same layout
into its first layer with :func:`fold_first_layer` and :func:`untracked_at_mean`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["input_width", "masked_input", "fold_first_layer", "untracked_at_mean"]


def input_width(n_markers: int, masked: bool) -> int:
    """Number of network inputs for ``n_markers`` markers: 3 n_d, or 4 n_d with masking."""
    return 3 * n_markers + (n_markers if masked else 0)


def masked_input(standardised, present, xp=np):
    """The masked network input.

    Args:
        standardised: (B, 3 n_d) standardised marker displacements z (numpy array or torch
            tensor); an untracked marker's entries may hold any finite value.
        present: (B, n_d) 1.0 for a tracked marker, 0.0 for an untracked one (same kind
            of array as ``standardised``).
        xp: the array module of both arrays: ``numpy`` or ``torch``.

    Returns:
        (B, 4 n_d): ``z * p`` per marker coordinate, then ``p``.
    """
    n_markers = present.shape[1]
    tracked = (standardised.reshape(-1, n_markers, 3) * present[:, :, None]).reshape(-1, 3 * n_markers)
    return xp.concatenate([tracked, present], axis=1)


def fold_first_layer(weight: np.ndarray, bias: np.ndarray, x_mean: np.ndarray, x_std: np.ndarray,
                     masked: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A first layer ``weight @ input + bias`` rewritten to act on raw displacements d (mm).

    Args:
        weight: (h, 3 n_d [+ n_d]) float64 first-layer weights over the network input.
        bias: (h,) float64.
        x_mean, x_std: (3 n_d,) float64 standardisation, mm.
        masked: whether the input has the n_d present channels.

    Returns:
        ``(W (h, 3 n_d), b (h,), present_columns (h, n_d) or None)``: with every marker
        tracked the layer is ``W @ d + b``; with markers missing it is
        ``W @ d' + b - present_columns @ missing`` where ``d'`` is ``d`` with the untracked
        markers at their mean displacement (:func:`untracked_at_mean`).
    """
    nd3 = x_mean.size
    W = weight[:, :nd3] / x_std
    b = bias - W @ x_mean
    if not masked:
        return W, b, None
    present_columns = weight[:, nd3:]
    return W, b + present_columns.sum(axis=1), present_columns  # all markers present


def untracked_at_mean(d: np.ndarray, missing: np.ndarray, x_mean: np.ndarray) -> np.ndarray:
    """Displacements (B, 3 n_d) mm with the untracked markers (``missing`` (B, n_d) bool) at
    their training mean ``x_mean`` (3 n_d,): a standardised value of 0, as in the masked input."""
    return np.where(np.repeat(missing, 3, axis=1), x_mean, d)
