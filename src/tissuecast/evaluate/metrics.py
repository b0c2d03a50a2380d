"""Accuracy metrics of predicted displacement fields (the paper's Offset_mean / Offset_max, and TRE).

For one sample with benchmark (FEM) displacements ``u_bench (n, 3)`` and prediction
``u_pred (n, 3)``, the vertex error is ``e_i = ||u_bench_i - u_pred_i||`` (mm). The paper's
metrics are ``Offset_mean = mean_i e_i`` and ``Offset_max = max_i e_i`` over all n vertices
(comparing deformed positions x = X + u is the same thing since X cancels).

The clinic's metrics are read at k targets inside the tissue (:mod:`.targets`): the target
registration error ``TRE_j = ||u_bench(t_j) - u_pred(t_j)||`` per target, summarised per
sample by its mean, 95th percentile and maximum over the targets, and the **share of the
targets' displacement corrected** ``1 - mean_j TRE_j / mean_j ||u_bench(t_j)||`` (1 = every
target where it truly is; 0 = no better than assuming no motion; negative = worse).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import ModelError

__all__ = ["vertex_errors", "offset_mean", "offset_max", "SetSummary", "summarize", "summarize_offsets", "PERCENTILES",
           "target_errors", "share_corrected", "TargetSummary", "summarize_targets"]

PERCENTILES = (50.0, 90.0, 95.0, 99.0)


def _pair(predicted, benchmark) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(predicted, dtype=np.float64)
    b = np.asarray(benchmark, dtype=np.float64)
    if p.shape != b.shape or p.ndim not in (2, 3) or p.shape[-1] != 3:
        raise ModelError(
            f"predicted {p.shape} and benchmark {b.shape} displacements must both be (n, 3) or (B, n, 3) in mm"
        )
    if not (np.isfinite(p).all() and np.isfinite(b).all()):
        raise ModelError("displacement fields contain NaN or inf; remove failed samples before evaluating")
    return p, b


def vertex_errors(predicted, benchmark) -> np.ndarray:
    """Euclidean error per vertex.

    Args:
        predicted: (n, 3) or (B, n, 3) float, mm.
        benchmark: same shape, mm.

    Returns:
        (n,) or (B, n) float64, mm.
    """
    p, b = _pair(predicted, benchmark)
    return np.linalg.norm(p - b, axis=-1)


def offset_mean(predicted, benchmark) -> np.ndarray | float:
    """Mean vertex error per sample: () for one (n, 3) field, (B,) for a batch (mm)."""
    return vertex_errors(predicted, benchmark).mean(axis=-1)


def offset_max(predicted, benchmark) -> np.ndarray | float:
    """Largest vertex error per sample: () for one (n, 3) field, (B,) for a batch (mm)."""
    return vertex_errors(predicted, benchmark).max(axis=-1)


@dataclass(frozen=True)
class SetSummary:
    """Accuracy over a set of samples (all lengths in mm).

    Attributes:
        count: number of samples.
        offset_mean: mean over samples of Offset_mean.
        offset_max: mean over samples of Offset_max (the paper's headline figure).
        offset_mean_percentiles: {percentile: value} of Offset_mean over samples.
        offset_max_percentiles: {percentile: value} of Offset_max over samples.
        worst_offset_max: largest Offset_max in the set.
        share_below: share (0..1) of samples with Offset_max < ``threshold``.
        threshold: the threshold used for ``share_below`` (paper: 1 mm).
    """

    count: int
    offset_mean: float
    offset_max: float
    offset_mean_percentiles: dict
    offset_max_percentiles: dict
    worst_offset_max: float
    share_below: float
    threshold: float

    def as_dict(self) -> dict:
        """Plain JSON-ready dict (percentile keys as strings like ``"p95"``)."""
        d = asdict(self)
        d["offset_mean_percentiles"] = {f"p{k:g}": v for k, v in self.offset_mean_percentiles.items()}
        d["offset_max_percentiles"] = {f"p{k:g}": v for k, v in self.offset_max_percentiles.items()}
        return d


def summarize(predicted, benchmark, *, threshold: float = 1.0, percentiles=PERCENTILES) -> SetSummary:
    """Summarise a batch of predictions against the benchmark.

    Args:
        predicted: (B, n, 3) float, mm (B >= 1).
        benchmark: (B, n, 3) float, mm.
        threshold: Offset_max threshold (mm) for the share of "accurate" samples.
        percentiles: percentiles (0..100) to report.
    """
    p, b = _pair(predicted, benchmark)
    if p.ndim != 3 or p.shape[0] == 0:
        raise ModelError(f"summarize needs a non-empty batch (B, n, 3), got {p.shape}")
    e = np.linalg.norm(p - b, axis=-1)
    return summarize_offsets(e.mean(axis=1), e.max(axis=1), threshold=threshold, percentiles=percentiles)


def summarize_offsets(offset_means, offset_maxes, *, threshold: float = 1.0, percentiles=PERCENTILES) -> SetSummary:
    """Like :func:`summarize`, from per-sample Offset_mean (B,) and Offset_max (B,) in mm."""
    om = np.asarray(offset_means, dtype=np.float64).ravel()
    ox = np.asarray(offset_maxes, dtype=np.float64).ravel()
    if om.size == 0 or om.shape != ox.shape:
        raise ModelError(f"need equally long, non-empty per-sample offsets, got {om.shape} and {ox.shape}")
    return SetSummary(
        count=int(om.size),
        offset_mean=float(om.mean()),
        offset_max=float(ox.mean()),
        offset_mean_percentiles={float(q): float(np.percentile(om, q)) for q in percentiles},
        offset_max_percentiles={float(q): float(np.percentile(ox, q)) for q in percentiles},
        worst_offset_max=float(ox.max()),
        share_below=float(np.mean(ox < threshold)),
        threshold=float(threshold),
    )


def target_errors(predicted, benchmark) -> np.ndarray:
    """Per-sample TRE statistics from target displacements.

    Args:
        predicted: (B, k, 3) float, predicted displacement at the k targets, mm.
        benchmark: (B, k, 3) float, true displacement there, mm.

    Returns:
        (B, 3) float64 [mean, p95, max] of the k target errors per sample, mm.
    """
    e = vertex_errors(predicted, benchmark)
    if e.ndim != 2 or e.shape[1] == 0:
        raise ModelError(f"target displacements must be (B, k, 3) with k >= 1, got {np.shape(predicted)}")
    return np.stack([e.mean(axis=1), np.percentile(e, 95, axis=1), e.max(axis=1)], axis=1)


def share_corrected(tre_mean, displacement_mean) -> np.ndarray:
    """``1 - TRE / |u|`` per sample: (B,) mean TRE and (B,) mean true target displacement, mm -> (B,);
    NaN where the targets did not move."""
    t = np.asarray(tre_mean, dtype=np.float64)
    u = np.asarray(displacement_mean, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(u > 0, 1.0 - t / np.where(u > 0, u, 1.0), np.nan)


@dataclass(frozen=True)
class TargetSummary:
    """Errors at the targets over a set of samples (lengths in mm, shares 0..1).

    Attributes:
        count: number of samples.
        tre_mean, tre_p95, tre_max: per-sample mean / 95th percentile / largest target error,
            averaged over the samples.
        worst_tre_max: largest target error in the set.
        share_corrected_mean: mean over samples of the share of the targets' displacement
            corrected (NaN samples, whose targets did not move, left out).
        share_corrected_worst: its smallest value over the samples.
        target_displacement: mean over samples of the targets' mean true displacement.
    """

    count: int
    tre_mean: float
    tre_p95: float
    tre_max: float
    worst_tre_max: float
    share_corrected_mean: float
    share_corrected_worst: float
    target_displacement: float

    def as_dict(self) -> dict:
        return asdict(self)


def summarize_targets(tre, displacement_mean) -> TargetSummary:
    """Summary of per-sample TRE rows (B, 3) [mean, p95, max] mm and the targets' mean true
    displacement (B,) mm. Samples whose TRE is NaN (a baseline that could not predict) are left out."""
    t = np.asarray(tre, dtype=np.float64).reshape(-1, 3)
    u = np.asarray(displacement_mean, dtype=np.float64).ravel()
    ok = np.isfinite(t).all(axis=1)
    if not ok.any():
        nan = float("nan")
        return TargetSummary(int(len(t)), nan, nan, nan, nan, nan, nan, float(np.mean(u)) if u.size else nan)
    share = share_corrected(t[ok, 0], u[ok])
    has = np.isfinite(share)
    return TargetSummary(
        count=int(len(t)),
        tre_mean=float(t[ok, 0].mean()),
        tre_p95=float(t[ok, 1].mean()),
        tre_max=float(t[ok, 2].mean()),
        worst_tre_max=float(t[ok, 2].max()),
        share_corrected_mean=float(share[has].mean()) if has.any() else float("nan"),
        share_corrected_worst=float(share[has].min()) if has.any() else float("nan"),
        target_displacement=float(u.mean()),
    )
