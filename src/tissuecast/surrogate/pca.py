"""PCA of displacement fields and the paper's rule for the number of components n_w.

A displacement field of n vertices is flattened vertex-major to p = 3 n numbers
``(u0x, u0y, u0z, u1x, ...)`` in mm. The basis is fitted on training fields only, mean-centred,
by a float64 thin SVD; components are orthonormal rows, so the weights ``w`` are in mm.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.linalg import eigh

from ..errors import ModelError

__all__ = ["PCABasis", "PCACurve", "fit_pca", "choose_n_components"]

#: When fewer than rank / GRAM_RANK_RATIO components of a wide matrix are wanted, the leading
#: eigenvectors of its (N, N) Gram matrix are computed instead of a full thin SVD.
GRAM_RANK_RATIO = 4
# Singular values below this share of the largest are round-off (a fold's Gram matrix is rank-deficient).
_RANK_RTOL = 1e-12

log = logging.getLogger(__name__)


def _as_matrix(X, name: str = "displacements") -> np.ndarray:
    """(N, n, 3) or (N, p) -> (N, p) float64, validated."""
    A = np.asarray(X, dtype=np.float64)
    if A.ndim == 3 and A.shape[2] == 3:
        A = A.reshape(A.shape[0], -1)
    if A.ndim != 2 or A.shape[0] < 2 or A.shape[1] % 3:
        raise ModelError(f"{name} must be (N, n, 3) or (N, 3 n) with N >= 2 samples, got shape {np.shape(X)}")
    if not np.isfinite(A).all():
        raise ModelError(f"{name} contain NaN or inf; drop failed samples (status != 'done') first")
    return A


@dataclass(frozen=True, eq=False)
class PCABasis:
    """A mean-centred PCA basis of flattened displacement fields.

    Attributes:
        mean: (p,) float64 mean training field, mm (p = 3 n, vertex-major).
        components: (n_w, p) float64 orthonormal principal directions, largest variance first.
        singular_values: (n_w,) float64 singular values of the centred training matrix, mm.
        n_samples: number of training fields it was fitted on.
    """

    mean: np.ndarray
    components: np.ndarray
    singular_values: np.ndarray
    n_samples: int

    @property
    def n_components(self) -> int:
        return int(self.components.shape[0])

    @property
    def n_features(self) -> int:
        return int(self.components.shape[1])

    @property
    def explained_variance(self) -> np.ndarray:
        """(n_w,) variance (mm^2) along each component."""
        return self.singular_values**2 / max(self.n_samples - 1, 1)

    def truncated(self, n_components: int) -> "PCABasis":
        """The first ``n_components`` components of this basis."""
        if not 1 <= n_components <= self.n_components:
            raise ModelError(f"n_components must be in [1, {self.n_components}], got {n_components}")
        k = int(n_components)
        return PCABasis(self.mean, self.components[:k].copy(), self.singular_values[:k].copy(), self.n_samples)

    def transform(self, X) -> np.ndarray:
        """Weights of fields: (N, n, 3) or (N, p) mm -> (N, n_w) mm."""
        A = np.asarray(X, dtype=np.float64).reshape(np.shape(X)[0], -1)
        if A.shape[1] != self.n_features:
            raise ModelError(f"fields have {A.shape[1]} values each, the basis expects {self.n_features}")
        return (A - self.mean) @ self.components.T

    def inverse_transform(self, W) -> np.ndarray:
        """Fields from weights: (N, n_w) mm -> (N, p) mm."""
        W = np.asarray(W, dtype=np.float64)
        return W @ self.components + self.mean


def fit_pca(X, n_components: int | None = None) -> PCABasis:
    """Fit a mean-centred PCA (thin SVD; Gram-matrix eigen-decomposition for a few components).

    Args:
        X: (N, n, 3) or (N, 3 n) training displacements, mm.
        n_components: components to keep; None keeps all min(N, 3 n).

    Returns:
        The :class:`PCABasis`.
    """
    A = _as_matrix(X)
    mean = A.mean(axis=0)
    Ac = A - mean
    r = min(A.shape)
    k = r if n_components is None else int(n_components)
    if not 1 <= k <= r:
        raise ModelError(f"n_components must be in [1, {r}] for {A.shape[0]} samples, got {n_components}")
    if GRAM_RANK_RATIO * k < r and A.shape[0] <= A.shape[1]:
        # a few leading components of a wide matrix: eigen-decomposition of the (N, N) Gram
        # matrix, leading part only, is several times faster than a full thin SVD
        lam, U = eigh(Ac @ Ac.T, subset_by_index=[A.shape[0] - k, A.shape[0] - 1])
        lam, U = lam[::-1], U[:, ::-1]
        s = np.sqrt(np.maximum(lam, 0.0))
        vt = (U.T @ Ac) / np.where(s > 0, s, 1.0)[:, None]
        vt /= np.linalg.norm(vt, axis=1, keepdims=True)  # re-normalise (rounding)
        return PCABasis(mean=mean, components=np.ascontiguousarray(vt), singular_values=s, n_samples=A.shape[0])
    _, s, vt = np.linalg.svd(Ac, full_matrices=False)
    return PCABasis(mean=mean, components=np.ascontiguousarray(vt[:k]), singular_values=s[:k].copy(), n_samples=A.shape[0])


@dataclass(frozen=True, eq=False)
class PCACurve:
    """Cross-validated PCA reconstruction error versus the number of components.

    Attributes:
        n_components: (K,) int, 1..K.
        max_error: (K,) mm, fold average of the largest vertex error over each held-out fold
            (the quantity the rule thresholds; the authors' ``avgMaxMax``).
        mean_max_error: (K,) mm, average over held-out samples of the per-sample largest vertex error.
        mean_error: (K,) mm, average vertex error over all held-out samples.
        chosen: the selected n_w.
        threshold: the rule's threshold (mm).
        folds: number of folds.
    """

    n_components: np.ndarray
    max_error: np.ndarray
    mean_max_error: np.ndarray
    mean_error: np.ndarray
    chosen: int
    threshold: float
    folds: int

    def as_dict(self) -> dict:
        return {
            "n_components": self.n_components.tolist(),
            "max_error": self.max_error.tolist(),
            "mean_max_error": self.mean_max_error.tolist(),
            "mean_error": self.mean_error.tolist(),
            "chosen": int(self.chosen),
            "threshold": float(self.threshold),
            "folds": int(self.folds),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "PCACurve":
        return cls(
            n_components=np.asarray(d["n_components"], dtype=np.int64),
            max_error=np.asarray(d["max_error"], dtype=np.float64),
            mean_max_error=np.asarray(d["mean_max_error"], dtype=np.float64),
            mean_error=np.asarray(d["mean_error"], dtype=np.float64),
            chosen=int(d["chosen"]),
            threshold=float(d["threshold"]),
            folds=int(d["folds"]),
        )


def choose_n_components(
    X, max_error: float = 1.0, folds: int = 5, *, max_components: int = 200, seed: int = 0, full_curve: bool = False
) -> tuple[int, PCACurve]:
    """The paper's rule: smallest n_w whose k-fold PCA reconstruction keeps the largest vertex error < ``max_error``.

    The samples are shuffled (``seed``) and cut into ``folds`` parts; for each part a PCA is
    fitted on the others and the held-out fields are projected and reconstructed with
    1..K components. The criterion, as in the authors' script, is the fold average of the
    largest vertex error (Euclidean, mm) over the held-out fields.

    Args:
        X: (N, n, 3) or (N, 3 n) training displacements, mm.
        max_error: threshold in mm (paper: 1 mm).
        folds: number of folds (paper: 5), 2 <= folds <= N.
        max_components: largest n_w tried (capped by the fold training size and 3 n).
        seed: shuffling seed.
        full_curve: compute the curve up to K instead of stopping past the choice.

    Returns:
        ``(n_w, curve)``; the curve runs to max(2 n_w, n_w + 10) components (or K; at least
        64 when that many are tried). If no
        n_w up to K meets the threshold, n_w = K and a warning is logged.
    """
    A = _as_matrix(X)
    N, p = A.shape
    if not 2 <= folds <= N:
        raise ModelError(f"folds must be in [2, {N}] for {N} samples, got {folds}")
    if not max_error > 0:
        raise ModelError(f"max_error must be positive (mm), got {max_error}")
    order = np.random.default_rng(seed).permutation(N)
    parts = np.array_split(order, folds)
    K = int(min(max_components, p, N - max(len(q) for q in parts)))
    if K < 1:
        raise ModelError(f"too few samples ({N}) for {folds}-fold PCA cross-validation")
    G = A @ A.T  # (N, N) uncentred Gram matrix, shared by all folds
    k_try = min(K, 64)  # few components first: the leading eigenpairs are the expensive part
    while True:
        res = _curve(A, G, order, parts, k_try, max_error, full_curve)
        if k_try >= K or (res[0] and not full_curve):
            break
        k_try = min(K, 3 * k_try)
    chosen, max_err, sample_max, mean_err = res
    if not chosen:
        chosen = len(max_err)
        log.warning(
            "no n_w <= %d keeps the cross-validated max vertex error below %.3g mm (best %.3g mm); using n_w = %d",
            len(max_err), max_error, min(max_err), chosen,
        )
    curve = PCACurve(
        n_components=np.arange(1, len(max_err) + 1),
        max_error=np.asarray(max_err),
        mean_max_error=np.asarray(sample_max),
        mean_error=np.asarray(mean_err),
        chosen=chosen,
        threshold=float(max_error),
        folds=int(folds),
    )
    return chosen, curve


def _curve(A, G, order, parts, K, max_error, full_curve):
    """Cross-validated error curve for 1..K components -> (chosen or 0, max, sample-max, mean lists)."""
    fits = []
    for held in parts:
        train = np.setdiff1d(order, held, assume_unique=True)
        mean = A[train].mean(axis=0)
        Gt = G[np.ix_(train, train)]
        r = Gt.mean(axis=1)
        Gc = Gt - r[:, None] - r[None, :] + r.mean()  # Gram matrix of the centred fold
        k_fold = min(K, len(train))
        lam, U = eigh(Gc, subset_by_index=[len(train) - k_fold, len(train) - 1])
        lam, U = lam[::-1], U[:, ::-1]
        sv = np.sqrt(np.maximum(lam, 0.0))
        keep = sv > _RANK_RTOL * max(sv[0], 1e-300)
        comps = (U[:, keep].T @ (A[train] - mean)) / sv[keep][:, None]
        comps /= np.linalg.norm(comps, axis=1, keepdims=True)
        resid = A[held] - mean  # (m, p): reconstruction error with 0 components
        fits.append((resid, resid @ comps.T, comps))
    K = min(K, min(len(f[2]) for f in fits))
    N = A.shape[0]
    folds = len(parts)
    max_err, sample_max, mean_err = [], [], []
    chosen = 0
    stop = K
    for k in range(K):
        fold_worst, s_max, s_mean = 0.0, 0.0, 0.0
        for resid, coeff, comps in fits:
            resid -= np.outer(coeff[:, k], comps[k])
            r3 = resid.reshape(len(resid), -1, 3)
            e = np.sqrt(np.einsum("mij,mij->mi", r3, r3))  # (m, n) vertex errors, mm
            emax = e.max(axis=1)
            fold_worst += emax.max()
            s_max += emax.sum()
            s_mean += e.mean(axis=1).sum()
        max_err.append(fold_worst / folds)
        sample_max.append(s_max / N)
        mean_err.append(s_mean / N)
        if not chosen and max_err[-1] < max_error:
            chosen = k + 1
            stop = K if full_curve else min(K, max(2 * chosen, chosen + 10))  # keep some of the curve past the choice
        if k + 1 >= stop:
            break
    return chosen, max_err, sample_max, mean_err
