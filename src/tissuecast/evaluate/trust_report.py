"""How far the error bounds and the out-of-distribution alarm can be trusted, on a data set.

For a model with a trust layer (:mod:`tissuecast.surrogate.trust`) and each test set
(test-1, test-2 and each test-2 beta): the empirical coverage of the per-vertex bounds at
90 % and 95 % nominal (share of (sample, vertex) pairs whose error is within the bound),
their sharpness (median bound, mm), how well the bounds rank the errors (Spearman: per
sample, the largest bound against Offset_max; per vertex within each sample, averaged), the
share of samples raising the alarm, and the reliability diagram on test-1. The inputs are
the benchmark (FEM) marker displacements, as in :mod:`.evaluation`.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from ..surrogate.conformal import reliability_curve
from .evaluation import spearman_rows

__all__ = ["bound_figures", "trust_evaluation", "reliability_figure", "trust_section", "LEVELS"]

#: Nominal coverages reported.
LEVELS = (0.9, 0.95)


def bound_figures(model, bench: np.ndarray, levels=LEVELS) -> dict:
    """Coverage, sharpness, ranking and alarms of the bounds on fields ``bench`` (B, n, 3) mm."""
    bench = np.asarray(bench, dtype=np.float64)
    d = bench[:, model.markers, :]
    row: dict = {"count": int(len(bench))}
    for c in levels:
        tp = model.predict_trusted(d, coverage=c)
        e = np.linalg.norm(tp.displacement - bench, axis=2)
        row[f"coverage_{c:g}"] = float(np.mean(e <= tp.error_bound))
        row[f"median_bound_{c:g}"] = float(np.median(tp.error_bound))
        if c == levels[0]:
            row["offset_max"] = float(e.max(axis=1).mean())
            row["sample_spearman"] = (float(spearmanr(tp.error_bound.max(axis=1), e.max(axis=1))[0]) if len(e) > 2
                                      else float("nan"))
            row["vertex_spearman"] = float(spearman_rows(tp.error_bound, e).mean())
            row["alarm_rate"] = float(np.mean([a.raised for a in tp.alarms]))
    return row


def trust_evaluation(model, dataset) -> dict:
    """Figures of the bounds and alarm on the data set's test-1 and test-2 samples.

    Returns:
        ``{"sets": {name: bound_figures row}, "reliability": {"nominal": [...], "empirical": [...]}}``
        (reliability on test-1; empty sets are skipped).
    """
    U = dataset.displacements
    beta = np.asarray(dataset.beta, dtype=np.float64)
    sets: dict = {}
    for split in ("test1", "test2"):
        idx = np.asarray(dataset.select(split, status="done"), dtype=np.int64)
        if idx.size == 0:
            continue
        sets[split] = bound_figures(model, U[idx])
        if split == "test2":
            for b in np.unique(beta[idx][np.isfinite(beta[idx])]):
                sets[f"test2 beta={b:g}"] = bound_figures(model, U[idx[beta[idx] == b]])
    out: dict = {"sets": sets, "reliability": {}}
    idx = np.asarray(dataset.select("test1", status="done"), dtype=np.int64)
    if idx.size:
        bench = np.asarray(U[idx], dtype=np.float64)
        d = bench[:, model.markers, :]
        u = model.predict(d)
        sigma = model.trust_.normaliser(d.reshape(len(d), -1), u)
        lv, emp = reliability_curve(model.trust_.conformal, np.linalg.norm(u - bench, axis=2), sigma)
        out["reliability"] = {"nominal": lv.tolist(), "empirical": emp.tolist()}
    return out


def reliability_figure(result: dict, path: Path) -> Path:
    """Nominal versus empirical coverage of the bounds on test-1 (the reliability diagram)."""
    from .figures import _plt, _save

    plt = _plt()
    r = result["reliability"]
    fig, ax = plt.subplots(figsize=(4.8, 4.5))
    ax.plot([0.5, 1.0], [0.5, 1.0], "k--", lw=1, label="ideal")
    ax.plot(r["nominal"], r["empirical"], "o-", color="tab:blue", label="test-1")
    ax.set_xlabel("nominal coverage")
    ax.set_ylabel("empirical coverage (vertices within their bound)")
    ax.set_xlim(0.48, 1.0)
    ax.set_ylim(0.48, 1.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def trust_section(model, dataset, folder: Path) -> str:
    """HTML of the report's bounds-and-alarm section; writes ``trust.json`` and ``reliability.png``."""
    result = trust_evaluation(model, dataset)
    folder = Path(folder)
    (folder / "trust.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    head = ["set", "samples", "mean Offset_max", "coverage 90 %", "median bound 90 % (mm)", "coverage 95 %",
            "median bound 95 % (mm)", "Spearman(max bound, Offset_max)", "per-vertex Spearman", "alarms (%)"]
    rows = []
    for name, r in result["sets"].items():
        rows.append([html.escape(name), str(r["count"]), f"{r['offset_max']:.3f}", f"{100 * r['coverage_0.9']:.1f} %",
                     f"{r['median_bound_0.9']:.3f}", f"{100 * r['coverage_0.95']:.1f} %", f"{r['median_bound_0.95']:.3f}",
                     f"{r['sample_spearman']:.3f}", f"{r['vertex_spearman']:.3f}", f"{100 * r['alarm_rate']:.1f}"])
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    t = model.trust_
    parts = ["<h2>Error bounds and out-of-distribution alarm</h2>",
             f"<p>Split-conformal per-vertex bounds calibrated on {t.conformal.n_calibration} samples held out from "
             f"training; alarm threshold for {100 * t.false_alarm:g} % false alarms. Coverage: share of vertices whose "
             "error is within their bound (should match the nominal level on test-1; test-2 is out of distribution).</p>",
             "<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + f"</tr>{body}</table>"]
    if result["reliability"]:
        png = reliability_figure(result, folder / "reliability.png")
        parts.append(f"<h3>Reliability diagram (test-1)</h3><img src='{png.name}' alt='reliability diagram'>")
    return "".join(parts)
