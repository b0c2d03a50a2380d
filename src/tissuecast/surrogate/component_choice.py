"""How many PCA components n_w a surrogate keeps: the configured rule, the validation rule and
the ridge baseline's own n_w.

``surrogate.n_components > 0`` fixes n_w; otherwise ``surrogate.pca_rule`` decides: ``"paper"``
(the smallest n_w whose cross-validated PCA reconstruction error stays below
``pca_max_error``, :func:`tissuecast.surrogate.pca.choose_n_components`) or ``"validation"``
(the network is trained on ``pca_max_components`` components and then cut where its
validation error stops improving, :func:`choose_by_validation`).
"""

from __future__ import annotations

import numpy as np

from ..config import SurrogateConfig
from .pca import PCABasis, PCACurve, choose_n_components
from .ridge import fit_ridge
from .weights import MLPWeights

__all__ = ["components_to_train", "choose_by_validation", "ridge_components", "VALIDATION_TOLERANCE", "FLOOR_SHARE"]


def components_to_train(config: SurrogateConfig, Ut: np.ndarray) -> tuple[int, str, PCACurve | None]:
    """The number of PCA components the network is trained on.

    Args:
        config: the surrogate settings (``n_components``, ``pca_rule`` and its parameters).
        Ut: (N, 3 n) training fields, mm.

    Returns:
        ``(n_w >= 1, a description of the rule, the paper rule's PCACurve or None)``; with the
        validation rule n_w is the number trained on, cut later by :func:`choose_by_validation`.
    """
    c = config
    curve = None
    if c.n_components:
        n_w, rule = min(c.n_components, min(Ut.shape)), "fixed (surrogate.n_components)"
    elif c.pca_rule == "paper":
        n_w, curve = choose_n_components(Ut, c.pca_max_error, min(c.pca_folds, len(Ut)), seed=c.seed)
        rule = f"paper ({c.pca_folds}-fold reconstruction error < {c.pca_max_error:g} mm)"
    else:
        n_w = min(c.pca_max_components, len(Ut) - 1, Ut.shape[1])  # trained on all, truncated later
        rule = "validation (lowest validation mean Offset_max)"
    return max(int(n_w), 1), rule, curve


#: The validation rule keeps the smallest n_w whose validation mean Offset_max is within this
#: share of the best one (components past it change the error by less than its noise) ...
VALIDATION_TOLERANCE = 0.01
#: ... and whose PCA floor is at most this share of that error, so that truncation is not what
#: limits accuracy (errors add about in quadrature: a floor of 0.4 e adds < 9 % to e).
FLOOR_SHARE = 0.4


def choose_by_validation(members: list[MLPWeights], basis: PCABasis, Xv: np.ndarray, Uv: np.ndarray,
                         head_weights: np.ndarray | None = None) -> tuple[int, dict]:
    """The n_w at which the networks' predicted weights are cut, and the curves behind it.

    For every n_w the validation mean Offset_max of the truncated networks (ensemble mean)
    and of the fields' own projection (the PCA floor) are measured; the smallest n_w within
    ``VALIDATION_TOLERANCE`` of the best model error whose floor is at most ``FLOOR_SHARE``
    of the model's error is kept (the best n_w if no floor is that small).

    Args:
        members: networks predicting all ``basis.n_components`` weights.
        basis: the PCA basis they were trained on (K components).
        Xv: (M, 3 n_d) validation marker displacements, mm.
        Uv: (M, 3 n) validation fields, mm.
        head_weights: (M, K) weights of the quadratic head (:mod:`.head`) the networks
            correct, mm; None without a head.

    Returns:
        ``(n_w, {"n_components": 1..K, "model_offset_max": (K,), "floor_offset_max": (K,)})``
        with the validation mean Offset_max (mm) of the truncated model and of the fields'
        own projection (the PCA floor) for every n_w.
    """
    W = np.mean([m.predict_weights(Xv) for m in members], axis=0)  # (M, K) ensemble-mean weights
    if head_weights is not None:
        W = W + head_weights
    true_w = basis.transform(Uv)
    K = basis.n_components
    model, floor = np.empty(K), np.empty(K)
    res_model = Uv - basis.mean  # residual fields with 0 components
    res_floor = res_model.copy()
    for k in range(K):
        ck = basis.components[k]
        res_model -= np.outer(W[:, k], ck)
        res_floor -= np.outer(true_w[:, k], ck)
        model[k] = np.linalg.norm(res_model.reshape(len(Uv), -1, 3), axis=2).max(axis=1).mean()
        floor[k] = np.linalg.norm(res_floor.reshape(len(Uv), -1, 3), axis=2).max(axis=1).mean()
    good = model <= model.min() * (1.0 + VALIDATION_TOLERANCE)
    small_floor = good & (floor <= FLOOR_SHARE * model)
    n_w = int(np.flatnonzero(small_floor if small_floor.any() else model == model.min())[0]) + 1
    return n_w, {"n_components": list(range(1, K + 1)), "model_offset_max": model.tolist(),
                 "floor_offset_max": floor.tolist()}


def ridge_components(basis: PCABasis, markers: np.ndarray, ratio: float, Xv: np.ndarray, Uv: np.ndarray) -> int:
    """The n_w (<= the basis's) at which the ridge baseline has its lowest validation mean
    Offset_max: with few markers, ridge on many components is under-determined and much worse
    than on a few, so the baseline is reported at its best rather than at the MLP's n_w."""
    best, best_k = np.inf, basis.n_components
    for k in range(1, basis.n_components + 1):
        r = fit_ridge(basis.truncated(k), markers, ratio)
        pred = basis.truncated(k).inverse_transform(r.weights(Xv))
        e = np.linalg.norm((pred - Uv).reshape(len(Uv), -1, 3), axis=2).max(axis=1).mean()
        if e < best:
            best, best_k = e, k
    return int(best_k)
