"""Evaluate a DeformationModel on a data set: MLP and ridge side by side, per split and beta.

All distances in mm, times in seconds. The inputs of every prediction are the benchmark
(FEM) displacements of the model's markers, as in the paper.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import rankdata

from ..errors import ModelError
from .metrics import SetSummary, summarize_offsets

__all__ = ["SetResult", "Evaluation", "evaluate_model", "spearman_rows", "SPLITS"]

SPLITS = ("train", "valid", "test1", "test2")


def spearman_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Spearman rank correlation of each row pair of (B, n) arrays -> (B,)."""
    ra = rankdata(a, axis=1)
    rb = rankdata(b, axis=1)
    ra -= ra.mean(axis=1, keepdims=True)
    rb -= rb.mean(axis=1, keepdims=True)
    den = np.sqrt((ra**2).sum(axis=1) * (rb**2).sum(axis=1))
    return np.where(den > 0, (ra * rb).sum(axis=1) / np.where(den > 0, den, 1.0), 0.0)


@dataclass(eq=False)
class SetResult:
    """Per-sample results on one set of samples.

    Attributes:
        name: 'test1', 'test2', 'test2 beta=0.5', ...
        indices: (k,) sample indices in the data set.
        beta: (k,) LBO share of the force field (NaN for LBO samples).
        mlp_mean, mlp_max: (k,) Offset_mean and Offset_max of the MLP, mm.
        ridge_mean, ridge_max: (k,) the same for the ridge baseline, mm.
        max_displacement: (k,) largest benchmark vertex displacement per sample, mm.
        sigma_spearman: (k,) per-sample Spearman correlation of predicted uncertainty and
            true vertex error (ensembles only, else empty).
        sigma_max: (k,) largest per-vertex uncertainty per sample, mm (ensembles only).
    """

    name: str
    indices: np.ndarray
    beta: np.ndarray
    mlp_mean: np.ndarray
    mlp_max: np.ndarray
    ridge_mean: np.ndarray
    ridge_max: np.ndarray
    max_displacement: np.ndarray
    sigma_spearman: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sigma_max: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def mlp(self) -> SetSummary:
        return summarize_offsets(self.mlp_mean, self.mlp_max)

    @property
    def ridge(self) -> SetSummary:
        return summarize_offsets(self.ridge_mean, self.ridge_max)

    def subset(self, keep: np.ndarray, name: str) -> "SetResult":
        pick = lambda a: a[keep] if a.size else a  # noqa: E731
        return SetResult(name, self.indices[keep], self.beta[keep], self.mlp_mean[keep], self.mlp_max[keep],
                         self.ridge_mean[keep], self.ridge_max[keep], self.max_displacement[keep],
                         pick(self.sigma_spearman), pick(self.sigma_max))

    def as_dict(self) -> dict:
        d = {"name": self.name, "count": int(self.indices.size), "mlp": self.mlp.as_dict(), "ridge": self.ridge.as_dict()}
        if self.sigma_spearman.size:
            d["uncertainty"] = {
                "vertex_spearman_mean": float(self.sigma_spearman.mean()),
                "sample_spearman_sigma_max_vs_offset_max": float(spearman_rows(self.sigma_max[None], self.mlp_max[None])[0])
                if self.indices.size > 1 else float("nan"),
            }
        return d


@dataclass(eq=False)
class Evaluation:
    """Everything the report shows about one model on one data set."""

    sets: dict
    by_beta: list
    predict_seconds: dict
    model_summary: dict

    def as_dict(self) -> dict:
        return {
            "sets": {k: v.as_dict() for k, v in self.sets.items()},
            "by_beta": [{"beta": b, **r.as_dict()} for b, r in self.by_beta],
            "predict_seconds": self.predict_seconds,
            "model": self.model_summary,
        }

    def samples_table(self) -> list[dict]:
        """One row per evaluated sample (for CSV)."""
        rows = []
        for name, r in self.sets.items():
            for i in range(r.indices.size):
                row = {"set": name, "index": int(r.indices[i]), "beta": float(r.beta[i]),
                       "max_displacement": float(r.max_displacement[i]),
                       "mlp_offset_mean": float(r.mlp_mean[i]), "mlp_offset_max": float(r.mlp_max[i]),
                       "ridge_offset_mean": float(r.ridge_mean[i]), "ridge_offset_max": float(r.ridge_max[i])}
                if r.sigma_spearman.size:
                    row["sigma_spearman"] = float(r.sigma_spearman[i])
                    row["sigma_max"] = float(r.sigma_max[i])
                rows.append(row)
        return rows


def _set_result(model, U: np.ndarray, idx: np.ndarray, beta: np.ndarray, name: str, chunk: int = 256) -> SetResult:
    parts = {k: [] for k in ("mm", "mx", "rm", "rx", "md", "ss", "sm")}
    unc = model.ensemble_size > 1
    for s in range(0, idx.size, chunk):
        bench = np.asarray(U[idx[s:s + chunk]], dtype=np.float64)
        d = model.marker_displacements(bench)
        if unc:
            pred, sigma = model.predict_with_uncertainty(d)
        else:
            pred = model.predict(d)
        e = np.linalg.norm(pred - bench, axis=2)
        er = np.linalg.norm(model.predict_ridge(d) - bench, axis=2)
        parts["mm"].append(e.mean(axis=1))
        parts["mx"].append(e.max(axis=1))
        parts["rm"].append(er.mean(axis=1))
        parts["rx"].append(er.max(axis=1))
        parts["md"].append(np.linalg.norm(bench, axis=2).max(axis=1))
        if unc:
            parts["ss"].append(spearman_rows(sigma, e))
            parts["sm"].append(sigma.max(axis=1))
    cat = lambda k: np.concatenate(parts[k]) if parts[k] else np.zeros(0)  # noqa: E731
    return SetResult(name, idx, beta, cat("mm"), cat("mx"), cat("rm"), cat("rx"), cat("md"), cat("ss"), cat("sm"))


def _timing(model, U, idx, repeats: int = 2000) -> dict:
    """Single-sample prediction time (s): p50 and p99 over repeated calls."""
    if idx.size == 0:
        return {}
    d = model.marker_displacements(np.asarray(U[idx[: min(64, idx.size)]], dtype=np.float64))
    for x in d[:10]:
        model.predict(x)
    t = np.empty(repeats)
    for i in range(repeats):
        x = d[i % len(d)]
        t0 = time.perf_counter()
        model.predict(x)
        t[i] = time.perf_counter() - t0
    return {"p50": float(np.percentile(t, 50)), "p99": float(np.percentile(t, 99)), "repeats": repeats}


def evaluate_model(model, dataset, splits=("valid", "test1", "test2")) -> Evaluation:
    """Offsets of the MLP and the ridge baseline on the converged samples of each split.

    Args:
        model: a fitted :class:`~tissuecast.surrogate.DeformationModel` on the data set's mesh.
        dataset: a :class:`tissuecast.dataset.Dataset` (or any object with ``displacements``,
            ``beta``, ``mesh`` and ``select(split, status)``).
        splits: which splits to evaluate ('train', 'valid', 'test1', 'test2').
    """
    if model.n_vertices != dataset.mesh.n_points or model.mesh.fingerprint() != dataset.mesh.fingerprint():
        raise ModelError("the model was trained on another mesh than this data set's; evaluate it on its own data set")
    U = dataset.displacements
    beta = np.asarray(dataset.beta, dtype=np.float64)
    sets, by_beta = {}, []
    for name in splits:
        idx = np.asarray(dataset.select(name, status="done"), dtype=np.int64)
        if idx.size == 0:
            continue
        sets[name] = _set_result(model, U, idx, beta[idx], name)
    if "test2" in sets:
        t2 = sets["test2"]
        for b in np.unique(t2.beta[np.isfinite(t2.beta)]):
            by_beta.append((float(b), t2.subset(t2.beta == b, f"test2 beta={b:g}")))
    timing_idx = np.asarray(dataset.select("test1", status="done"), dtype=np.int64)
    summary = {"n_components": model.n_components, "markers": model.markers.tolist(), "ensemble": model.ensemble_size,
               "hidden": list(model.members_[0].hidden), "training": getattr(model, "training_", None)}
    return Evaluation(sets=sets, by_beta=by_beta, predict_seconds=_timing(model, U, timing_idx), model_summary=summary)
