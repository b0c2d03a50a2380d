"""How far the error bounds and the out-of-distribution alarm can be trusted, on a data set.

For a predictor with a trust layer (a :class:`~tissuecast.surrogate.trusted.TrustedPredictor`,
``DeformationModel.trusted_``; :mod:`tissuecast.surrogate.trust`) and each test set
(test-1, test-2 and each test-2 beta): the empirical coverage of the per-vertex bounds at
90 % and 95 % nominal (share of (sample, vertex) pairs whose error is within the bound),
their sharpness (median bound, mm), how well the bounds rank the errors (Spearman: per
sample, the largest bound against Offset_max; per vertex within each sample, averaged), the
share of samples raising the alarm, and the reliability diagram on test-1. The inputs are
the benchmark (FEM) marker displacements, as in :mod:`.evaluation`.

In the report these are the uncertainty story (:func:`uncertainty_section`): the bounds are
calibrated lengths with a coverage, so they are what the page states; the ensemble's spread
(how much its networks disagree) only ranks errors and is shown as a detail of it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from ..surrogate.conformal import reliability_curve, reliability_levels
from .evaluation import spearman_rows
from . import json_output
from .headline import ALARM_REASONS, DASH, beta_table, fmt_alarm, fmt_mm, fmt_share, html_table, set_title

__all__ = ["bound_figures", "trust_evaluation", "reliability_figure", "uncertainty_section", "LEVELS"]

#: Nominal coverages reported.
LEVELS = (0.9, 0.95)


def bound_figures(trusted, bench: np.ndarray, levels=LEVELS, auxiliary=None) -> dict:
    """Coverage, sharpness, ranking and alarms of the bounds of a predictor with ``has_trust``
    on fields ``bench`` (B, n, 3) mm (``auxiliary`` (B, n_a): their auxiliary inputs, for a
    predictor that reads some); ``alarms`` (B,) bool: which samples raised the alarm, and the
    shares raising it for each reason: ``alarm_far_rate`` (far from training),
    ``alarm_disagree_rate`` (markers disagree), ``alarm_still_rate`` (a marker stood still),
    ``alarm_swap_rate`` (two markers look exchanged)."""
    bench = np.asarray(bench, dtype=np.float64)
    d = trusted.marker_displacements(bench)
    row: dict = {"count": int(len(bench))}
    for c in levels:
        tp = trusted.predict_trusted(d, coverage=c, auxiliary=auxiliary)
        e = np.linalg.norm(tp.displacement - bench, axis=2)
        row[f"coverage_{c:g}"] = float(np.mean(e <= tp.error_bound))
        row[f"median_bound_{c:g}"] = float(np.median(tp.error_bound))
        if c == levels[0]:
            row["offset_max"] = float(e.max(axis=1).mean())
            row["sample_spearman"] = (float(spearmanr(tp.error_bound.max(axis=1), e.max(axis=1))[0]) if len(e) > 2
                                      else float("nan"))
            row["vertex_spearman"] = float(spearman_rows(tp.error_bound, e).mean())
            row["alarms"] = np.array([a.raised for a in tp.alarms], dtype=bool)
            row["alarm_rate"] = float(np.mean(row["alarms"]))
            for key, (reason, _) in ALARM_REASONS.items():
                row[key] = float(np.mean([a.raised and getattr(a, reason) for a in tp.alarms]))
            row["alarm_on"] = bool(np.isfinite(tp.alarms[0].distance_threshold))  # off: too few calibration samples
    return row


def trust_evaluation(trusted, dataset, *, field_predictor=None) -> dict:
    """Figures of the bounds and alarm of a :class:`TrustedPredictor` on the data set's test-1 and
    test-2 samples.

    ``field_predictor``: what predicts the evaluated field and its bounds (default ``trusted``
    itself); e.g. a model with a nominal expert (:class:`~tissuecast.surrogate.DeformationModel`),
    whose routed field has bounds calibrated per route: its reliability curve is then read from
    its own bounds at each level.

    Returns:
        ``{"sets": {name: bound_figures row}, "reliability": {"nominal": [...], "empirical": [...]}}``
        (reliability on test-1; empty sets are skipped).
    """
    from .evaluation import auxiliary_values

    U = dataset.displacements
    beta = np.asarray(dataset.beta, dtype=np.float64)
    field_predictor = trusted if field_predictor is None else field_predictor
    aux = auxiliary_values(trusted, dataset)
    rows = (lambda idx: None) if aux is None else (lambda idx: aux[idx])  # noqa: E731
    sets: dict = {}
    for split in ("test1", "test2"):
        idx = np.asarray(dataset.select(split, status="done"), dtype=np.int64)
        if idx.size == 0:
            continue
        sets[split] = bound_figures(field_predictor, U[idx], auxiliary=rows(idx))
        sets[split].pop("alarms", None)
        if split == "test2":
            for b in np.unique(beta[idx][np.isfinite(beta[idx])]):
                sub = idx[beta[idx] == b]
                sets[f"test2 beta={b:g}"] = bound_figures(field_predictor, U[sub], auxiliary=rows(sub))
                sets[f"test2 beta={b:g}"].pop("alarms", None)
    out: dict = {"sets": sets, "reliability": {}}
    idx = np.asarray(dataset.select("test1", status="done"), dtype=np.int64)
    if idx.size:
        bench = np.asarray(U[idx], dtype=np.float64)
        d = trusted.marker_displacements(bench)
        if field_predictor is trusted:
            u = trusted.predict(d, auxiliary=rows(idx))
            sigma = trusted.layer.normaliser(d.reshape(len(d), -1), u, auxiliary=rows(idx))
            lv, emp = reliability_curve(trusted.layer.conformal, np.linalg.norm(u - bench, axis=2), sigma)
        else:  # the field predictor's own bounds at each level
            lv = reliability_levels()
            emp = np.empty(len(lv))
            for i, level in enumerate(lv):
                t = field_predictor.predict_trusted(d, coverage=float(level), auxiliary=rows(idx), alarm=False)
                emp[i] = float(np.mean(np.linalg.norm(t.displacement - bench, axis=2) <= t.error_bound))
        out["reliability"] = {"nominal": lv.tolist(), "empirical": emp.tolist()}
    return out


def reliability_figure(result: dict, path: Path) -> Path:
    """Nominal versus empirical coverage of the bounds on test-1 (the reliability diagram)."""
    from .figures import pyplot, save_figure

    plt = pyplot()
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
    return save_figure(fig, path)


def _bounds_table(result: dict) -> str:
    head = ["set", "samples", "mean Offset_max", "covered at 90 %", "median bound 90 %", "covered at 95 %",
            "median bound 95 %", "Spearman (largest bound, Offset_max)", "per-vertex Spearman", "alarms"]
    rows = [[set_title(name), str(r["count"]), fmt_mm(r["offset_max"]), fmt_share(r["coverage_0.9"]),
             fmt_mm(r["median_bound_0.9"]), fmt_share(r["coverage_0.95"]), fmt_mm(r["median_bound_0.95"]),
             _fmt_rho(r["sample_spearman"]), _fmt_rho(r["vertex_spearman"]),
             fmt_alarm(r) if r.get("alarm_on", True) else "off"]
            for name, r in result["sets"].items()]
    return beta_table(head, rows)


def _fmt_rho(v) -> str:
    return DASH if v is None or v != v else f"{v:.2f}"


def _spread_html(evaluation) -> str:
    """The ensemble's spread as a detail of the uncertainty story (empty without an ensemble)."""
    rows = []
    for name, r in evaluation.sets.items():
        u = r.as_dict().get("uncertainty")
        if u:
            rows.append([set_title(name), _fmt_rho(u["vertex_spearman_mean"]),
                         _fmt_rho(u["sample_spearman_sigma_max_vs_offset_max"])])
    if not rows:
        return ""
    return ("<details><summary>The ensemble's spread (a detail)</summary><p>How much the networks of the ensemble "
            "disagree (σ per vertex) ranks where the model errs, but it is not a length the error stays under: it "
            "carries no coverage, so the calibrated bounds above are the figures to act on.</p>"
            + html_table(["set", "per-sample Spearman (σ, vertex error), mean", "Spearman (largest σ, Offset_max)"], rows)
            + "</details>")


def _calibration_words(layer) -> str:
    """How the layer was calibrated, for people."""
    m = layer.conformal.n_calibration
    if layer.method == "cross-validation":
        return (f"conformal, calibrated on the out-of-fold predictions of all {m} training samples: each scored by a model "
                "trained on the other folds, the model itself trained on every one of them")
    return f"split-conformal, calibrated on {m} samples held out from training"


def uncertainty_section(trusted, evaluation, result: dict | None, folder: Path) -> str:
    """HTML of the report's "how sure" section: the calibrated error bounds and the alarm, with the
    ensemble's spread as a detail; writes ``trust.json`` and ``reliability.png`` (calibrated models).

    Args:
        trusted: the evaluated model's :class:`TrustedPredictor` (``DeformationModel.trusted_``),
            or None for a model without a trust layer.
        evaluation: its :class:`~.evaluation.Evaluation`.
        result: :func:`trust_evaluation`'s figures, or None for a model without a trust layer.
        folder: the report folder.
    """
    parts = ["<details><summary><h2>How sure: error bounds and alarm</h2></summary>"]
    if result is None:
        parts.append("<p>This model has no calibrated error bounds and no out-of-distribution alarm: it was trained with "
                     "<code>surrogate.calibration = \"none\"</code> (or <code>calibration_share = 0</code>). Re-train "
                     "with <code>calibration = \"cross-validation\"</code> to get both without holding samples out.</p>")
    else:
        Path(folder, "trust.json").write_text(json_output.dumps(result, indent=2), encoding="utf-8")
        t = trusted.layer
        parts.append(f"<p>Every vertex gets an error bound: the error stays below it with the nominal probability "
                     f"({_calibration_words(t)}). "
                     f"Covered: the share of vertices whose error is within their bound; it should match the nominal "
                     f"level on test-1 (test-2's force fields were never trained on). The alarm flags inputs unlike the "
                     f"training data, at {fmt_share(t.false_alarm)} false alarms.</p>")
        parts.append(_bounds_table(result))
        if result["reliability"]:
            png = reliability_figure(result, Path(folder) / "reliability.png")
            parts.append(f"<h3>Reliability diagram (test-1)</h3><img src='{png.name}' alt='reliability diagram'>")
    parts.append(_spread_html(evaluation))
    parts.append("</details>")
    return "".join(parts)
