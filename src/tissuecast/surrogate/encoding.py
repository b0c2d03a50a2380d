"""The network's input layout: standardised marker displacements, auxiliary inputs and
marker-present channels.

For n_d markers with displacements d (3 n_d,) mm, vertex-major ``(d0x, d0y, d0z, d1x, ...)``,
followed by n_a auxiliary inputs a (instrument poses, measured parameters: :mod:`.auxiliary`),
the network reads ``z = (x - x_mean) / x_std`` for ``x = [d, a]`` (3 n_d + n_a values,
standardised per component with the training set's statistics). A network trained with marker
masking (``surrogate.marker_dropout > 0``) reads 4 n_d + n_a values instead::

    [z_0 p_0 (3 values), ..., z_(n_d-1) p_(n_d-1) (3 values), z_a (n_a values), p_0, ..., p_(n_d-1)]

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


def input_width(n_markers: int, masked: bool, n_auxiliary: int = 0) -> int:
    """Number of network inputs for ``n_markers`` markers and ``n_auxiliary`` auxiliary inputs:
    3 n_d + n_a, or 4 n_d + n_a with masking."""
    return 3 * n_markers + n_auxiliary + (n_markers if masked else 0)


def masked_input(standardised, present, xp=np):
    """The masked network input.

    Args:
        standardised: (B, 3 n_d + n_a) standardised inputs z (numpy array or torch tensor):
            the marker displacements, then the auxiliary inputs; an untracked marker's
            entries may hold any finite value.
        present: (B, n_d) 1.0 for a tracked marker, 0.0 for an untracked one (same kind
            of array as ``standardised``).
        xp: the array module of both arrays: ``numpy`` or ``torch``.

    Returns:
        (B, 4 n_d + n_a): ``z * p`` per marker coordinate, the auxiliary inputs, then ``p``.
    """
    n_markers = present.shape[1]
    nd3 = 3 * n_markers
    tracked = (standardised[:, :nd3].reshape(-1, n_markers, 3) * present[:, :, None]).reshape(-1, nd3)
    if standardised.shape[1] == nd3:
        return xp.concatenate([tracked, present], axis=1)
    return xp.concatenate([tracked, standardised[:, nd3:], present], axis=1)


def fold_first_layer(weight: np.ndarray, bias: np.ndarray, x_mean: np.ndarray, x_std: np.ndarray,
                     masked: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A first layer ``weight @ input + bias`` rewritten to act on raw displacements d (mm).

    Args:
        weight: (h, 3 n_d + n_a [+ n_d]) float64 first-layer weights over the network input.
        bias: (h,) float64.
        x_mean, x_std: (3 n_d + n_a,) float64 standardisation (mm for the markers).
        masked: whether the input has the n_d present channels.

    Returns:
        ``(W (h, 3 n_d + n_a), b (h,), present_columns (h, n_d) or None)``: with every marker
        tracked the layer is ``W @ x + b`` (x = [d, a]); with markers missing it is
        ``W @ x' + b - present_columns @ missing`` where ``x'`` is ``x`` with the untracked
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
    """Inputs (B, 3 n_d + n_a) (displacements mm, then auxiliary inputs) with the untracked
    markers (``missing`` (B, n_d) bool) at their training mean ``x_mean`` (3 n_d + n_a,): a
    standardised value of 0, as in the masked input."""
    mask = np.repeat(missing, 3, axis=1)
    if mask.shape[1] < d.shape[1]:
        mask = np.hstack([mask, np.zeros((len(mask), d.shape[1] - mask.shape[1]), dtype=bool)])
    return np.where(mask, x_mean, d)
