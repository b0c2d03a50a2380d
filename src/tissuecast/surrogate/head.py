"""The quadratic head: the part of the marker -> PCA-weight map a regression can carry, so that
the networks learn only what it misses.

The head is a :class:`~tissuecast.surrogate.quadratic.QuadraticRegression` of the training
fields' PCA weights (N_t, K) on the marker displacements (N_t, 3 n_d), mm: an affine term plus
products of the input's first q principal directions (a large deformation is a rotation to
first order and quadratic to second). The networks are then trained on the residual weights,
and a prediction is ``head(d) + mean over members of network(d)``.

q is chosen on the 'valid' split among :data:`HEAD_DIMS` (q <= 3 n_d and features <= half the
training samples, so small data sets get a small head or none), or fixed by
``surrogate.head_dims``. Models trained with ``marker_dropout > 0`` (missing-marker input)
have no head: it needs every marker.
"""

from __future__ import annotations

import numpy as np

from .pca import PCABasis
from .quadratic import QuadraticRegression, fit_quadratic

__all__ = ["HEAD_DIMS", "fit_head", "head_features", "truncated_head"]

#: Quadratic directions q tried on 'valid' when ``surrogate.head_dims`` is 0 (q = 0: affine).
HEAD_DIMS = (0, 6, 12, 18, 24)


def head_features(n_inputs: int, q: int) -> int:
    """Number of regression features of a head with ``n_inputs`` inputs and ``q`` directions."""
    q = min(q, n_inputs)
    return 1 + n_inputs + q * (q + 1) // 2


def _offset_max(basis: PCABasis, W: np.ndarray, Uv: np.ndarray) -> float:
    """Mean Offset_max (mm) of the fields reconstructed from weights W (M, K) against Uv (M, 3 n)."""
    e = (basis.inverse_transform(W) - Uv).reshape(len(Uv), -1, 3)
    return float(np.sqrt((e**2).sum(axis=2)).max(axis=1).mean())


def fit_head(Xt, Yt, Xv, Uv, basis: PCABasis, dims: int = 0) -> tuple[QuadraticRegression | None, dict]:
    """Fit the quadratic head, choosing its size on validation.

    Args:
        Xt: (N_t, 3 n_d) training marker displacements, mm.
        Yt: (N_t, K) training PCA weights, mm.
        Xv: (M, 3 n_d) validation marker displacements, mm.
        Uv: (M, 3 n) validation fields, mm.
        basis: the PCA basis of Yt (K components).
        dims: q; 0 = the best of :data:`HEAD_DIMS` on validation.

    Returns:
        ``(head or None, {"dims": q or None, "valid_offset_max": {q: mm}})``; None when no
        candidate has at most N_t / 2 features.
    """
    d = Xt.shape[1]
    if dims:
        candidates = [min(int(dims), d)]
    else:
        candidates = sorted({min(q, d) for q in HEAD_DIMS if head_features(d, q) <= len(Xt) // 2})
    best, scores = None, {}
    for q in candidates:
        reg = fit_quadratic(Xt, Yt, quadratic_dims=q)
        scores[q] = _offset_max(basis, reg.predict(Xv), Uv)
        if best is None or scores[q] < scores[best[0]]:
            best = (q, reg)
    info = {"dims": None if best is None else best[0], "valid_offset_max": {str(q): s for q, s in scores.items()}}
    return (None if best is None else best[1]), info


def truncated_head(head: QuadraticRegression | None, n_components: int) -> QuadraticRegression | None:
    """The head predicting only the first ``n_components`` PCA weights."""
    if head is None:
        return None
    return QuadraticRegression(head.mean, head.scale, head.directions, head.coef[:, :n_components].copy())
