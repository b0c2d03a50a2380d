"""Split-conformal error bounds per vertex.

For a calibration set of m samples held out from training, with true vertex errors
``e[s, i]`` (mm) and a normaliser ``sigma[s, i] > 0`` (any positive number computed from the
input alone, large where the model is likely wrong), the nonconformity scores are
``r[s, i] = e[s, i] / sigma[s, i]``. For coverage c and each vertex i, the bound of a new
sample is ``q_i(c) * sigma[i]`` with ``q_i(c)`` the ``ceil((m + 1) c)``-th smallest of the m
calibration scores of vertex i. If the new sample and the calibration samples are
exchangeable (drawn alike), the new error at vertex i is below its bound with probability
at least c (Vovk et al. 2005; Lei et al. 2018), whatever the model and the normaliser; a
good normaliser only makes the bounds tighter where the model is good. With fewer than
``1 / (1 - c) - 1`` calibration samples the bound is infinite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ModelError

__all__ = ["conformal_rank", "conformal_quantile", "min_calibration_samples", "VertexConformal", "fit_vertex_conformal",
           "normalised_errors", "reliability_levels", "reliability_curve"]


def conformal_rank(m: int, coverage: float) -> int:
    """1-based rank ``ceil((m + 1) c)`` of the conformal quantile among m scores (> m: infinite)."""
    if not 0.0 < coverage < 1.0:
        raise ModelError(f"coverage must be in (0, 1), got {coverage}")
    # a tiny slack so that e.g. (m + 1) * 0.9 = 180.00000000000003 gives 180, not 181
    return int(np.ceil((m + 1) * coverage - 1e-9))


def min_calibration_samples(coverage: float) -> int:
    """Fewest calibration samples giving a finite bound at ``coverage`` (9 for 0.9, 19 for 0.95, 99 for 0.99)."""
    m = max(1, int(np.floor(coverage / (1.0 - coverage))) - 1)
    while conformal_rank(m, coverage) > m:
        m += 1
    return m


def conformal_quantile(scores, coverage: float, axis: int = 0) -> np.ndarray:
    """Split-conformal quantile of ``scores`` along ``axis`` (inf when too few scores).

    Args:
        scores: nonconformity scores, m along ``axis``.
        coverage: nominal coverage c in (0, 1).

    Returns:
        The ``ceil((m + 1) c)``-th smallest score along ``axis`` (array without that axis).
    """
    s = np.sort(np.asarray(scores, dtype=np.float64), axis=axis)
    m = s.shape[axis]
    k = conformal_rank(m, coverage)
    if k > m:
        return np.full(np.delete(s.shape, axis), np.inf)
    return np.take(s, k - 1, axis=axis)


@dataclass(frozen=True, eq=False)
class VertexConformal:
    """Calibrated per-vertex conformal bounds.

    Attributes:
        sorted_scores: (m, n) float calibration scores ``e / sigma``, sorted along samples.
    """

    sorted_scores: np.ndarray

    @property
    def n_calibration(self) -> int:
        return int(self.sorted_scores.shape[0])

    def quantiles(self, coverage: float) -> np.ndarray:
        """(n,) per-vertex score quantiles q_i(c) (inf with too few calibration samples)."""
        k = conformal_rank(self.n_calibration, coverage)
        if k > self.n_calibration:
            return np.full(self.sorted_scores.shape[1], np.inf)
        return self.sorted_scores[k - 1].astype(np.float64)

    def bounds(self, sigma, coverage: float) -> np.ndarray:
        """Error bounds (..., n) mm from normalisers ``sigma`` (..., n)."""
        return np.asarray(sigma, dtype=np.float64) * self.quantiles(coverage)


def normalised_errors(errors, sigma) -> np.ndarray:
    """(m, n) nonconformity scores ``e / sigma`` from calibration errors (m, n) mm and normalisers (m, n) > 0.

    Raises:
        ModelError: shapes differ, non-finite values, or a normaliser <= 0.
    """
    e = np.asarray(errors, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    if e.ndim != 2 or e.shape != s.shape:
        raise ModelError(f"calibration errors and normalisers must both be (m, n), got {e.shape} and {s.shape}")
    if not (np.isfinite(e).all() and np.isfinite(s).all()) or (s <= 0).any():
        raise ModelError("calibration errors must be finite and normalisers finite and positive")
    return e / s


def fit_vertex_conformal(errors, sigma) -> VertexConformal:
    """Calibrate from calibration errors (m, n) mm and normalisers (m, n) > 0.

    Raises:
        ModelError: shapes differ, non-finite values, or a normaliser <= 0.
    """
    return VertexConformal(np.sort(normalised_errors(errors, sigma), axis=0))


def reliability_levels() -> np.ndarray:
    """The nominal coverages of a reliability diagram: 0.5, 0.55, ..., 0.95, 0.99."""
    return np.r_[np.arange(0.5, 0.951, 0.05), 0.99]


def reliability_curve(conformal: VertexConformal, errors, sigma, levels=None) -> tuple[np.ndarray, np.ndarray]:
    """Nominal versus empirical coverage on a test set (the reliability diagram).

    Args:
        conformal: the calibrated bounds.
        errors: (B, n) true vertex errors of the test samples, mm.
        sigma: (B, n) their normalisers.
        levels: nominal coverages (default 0.5, 0.55, ..., 0.95, 0.99).

    Returns:
        ``(levels (L,), empirical (L,))``: share of (sample, vertex) pairs within their bound.
    """
    lv = reliability_levels() if levels is None else np.asarray(levels, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    emp = np.array([float(np.mean(e <= conformal.bounds(sigma, c))) for c in lv])
    return lv, emp
