"""Quantiles of the calibration pilots' maxima, and what their number buys: a stated interval.

:func:`sample_quantile` is the linearly interpolated quantile the force calibration meets
(numpy's default, with failed pilots as +inf); :func:`quantile_interval` the distribution-free
interval of order statistics that holds the true quantile of the data set's maxima with a
stated confidence (the number of pilots below it is binomial): with 24 pilots and the 0.9
quantile, an 80 % interval is [20th, 24th largest], and no 90 % interval has a finite upper end.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["sample_quantile", "quantile_interval", "interval_text"]


def sample_quantile(values: np.ndarray, q: float) -> float:
    """Linearly interpolated quantile (numpy's default) where inf (a failure) may occur."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    pos = q * (len(v) - 1)
    i, j = int(math.floor(pos)), int(math.ceil(pos))
    if not math.isfinite(v[j]):
        return math.inf
    return float(v[i] + (pos - i) * (v[j] - v[i]))


def quantile_interval(values, quantile: float, confidence: float) -> tuple:
    """Distribution-free interval ``(lo, hi)`` (mm) of order statistics of ``values`` (P,) that
    holds the ``quantile`` of the distribution they are drawn from with probability at least
    ``confidence``: ``lo = v_(r)``, ``hi = v_(s)`` (1-based ranks of the sorted values), with
    ``P(B < r) <= (1 - confidence) / 2`` and ``P(B >= s) <= (1 - confidence) / 2`` for ``B`` the
    binomial(P, quantile) number of values below the quantile. A side that P values cannot bound
    at that confidence is None; so is a bound that is a failed pilot (inf)."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    n, tail = len(v), 0.5 * (1.0 - confidence)
    pmf = [math.comb(n, k) * quantile**k * (1.0 - quantile) ** (n - k) for k in range(n + 1)]
    below = np.cumsum(pmf)  # below[k] = P(B <= k)
    lows = [r for r in range(1, n + 1) if below[r - 1] <= tail]  # P(B < r) = P(B <= r - 1)
    highs = [s for s in range(1, n + 1) if 1.0 - below[s - 1] <= tail]  # P(B >= s)
    lo = float(v[max(lows) - 1]) if lows else None
    hi = float(v[min(highs) - 1]) if highs else None
    return (lo if lo is not None and math.isfinite(lo) else None, hi if hi is not None and math.isfinite(hi) else None)


def interval_text(interval: tuple) -> str:
    """``interval`` of :func:`quantile_interval` for a log line."""
    lo, hi = interval
    if lo is None and hi is None:
        return "an interval the pilots are too few to bound"
    if hi is None:
        return f"[{lo:.3g} mm, unbounded] (too few pilots to bound it from above)"
    if lo is None:
        return f"[unbounded, {hi:.3g} mm] (too few pilots to bound it from below)"
    return f"[{lo:.3g}, {hi:.3g}] mm"
