"""The evaluation report: an HTML page with PNG figures, CSV/JSON results and VTU files.

``write_report(folder, model, dataset, evaluation)`` writes::

    index.html            tables next to the paper's figures, plots, renders (opens offline)
    evaluation.json       every number of the page
    trust.json            error-bound coverage and alarm rates (calibrated models)
    samples.csv           per-sample Offset_mean / Offset_max of the MLP, rigid registration,
                          ridge and the PCA floor; peak displacement and non-rigid part
    *.png                 figures and 3D renders
    vtu/*.vtu             benchmark / predicted displacement and vertex error per rendered sample
"""

from __future__ import annotations

import csv
import html
import json
import logging
from pathlib import Path

import numpy as np

from ..config import EvaluateConfig
from . import figures
from .evaluation import METHOD_LABELS
from .render import render_comparison, write_vtu
from ..scenario.describe import scenario_lines

__all__ = ["write_report", "paper_table", "format_evaluation"]

log = logging.getLogger(__name__)

CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}
th{background:#eee}td:first-child,th:first-child{text-align:left}img{max-width:100%}
.good{color:#060}.bad{color:#a00}small{color:#666}"""


def _fmt(v, digits=3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{v:.{digits}f}"


def _table(head: list[str], rows: list[list]) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c if isinstance(c, str) else _fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


#: Columns of the headline tables: the learned model, then what it is compared with.
COLUMNS = ("mlp", "rigid", "ridge", "pca_floor")


def model_description(summary: dict) -> str:
    """'quadratic head (q = 15) + MLP [128, 64]' (x M for an ensemble) from an evaluation's model summary."""
    net = f"MLP {summary.get('hidden')}" + (f" x {summary['ensemble']}" if summary.get("ensemble", 1) > 1 else "")
    q = ((summary.get("pca") or {}).get("head") or {}).get("dims")
    return net if q is None else f"quadratic head (q = {q}) + {net}"


def paper_table(evaluation) -> list[list]:
    """Rows ``[quantity, MLP, rigid, ridge, PCA floor, paper]`` comparing the learned model with
    rigid registration from the markers, the paper's ridge baseline, the PCA floor and the
    paper's figures; then the size of the deformations (peak and non-rigid part)."""
    rows = []
    t1 = evaluation.sets.get("test1")
    dash = ["–"] * len(COLUMNS)
    if t1 is not None:
        s = [t1.summary(m) for m in COLUMNS]
        rows += [
            ["test-1 mean Offset_max (mm)", *[x.offset_max for x in s], "0.533 (architecture table) / 0.837 (n_d table)"],
            ["test-1 mean Offset_mean (mm)", *[x.offset_mean for x in s], "0.146 – 0.287"],
            ["test-1 share with Offset_max < 1 mm (%)", *[100 * x.share_below for x in s], "98"],
            ["test-1 worst Offset_max (mm)", *[x.worst_offset_max for x in s], "–"],
            ["test-1 gain over rigid registration (mean Offset_max ratio)", t1.gain_over_rigid, *dash[1:], "–"],
        ]
        dfm = t1.deformation()
        rows += [
            ["test-1 peak displacement, median / p90 (mm)", f"{dfm['max_displacement_median']:.2f} / "
             f"{dfm['max_displacement_p90']:.2f}", *dash[1:], "~30 (largest)"],
            ["test-1 non-rigid part, median / p90 (mm; median share of peak)",
             f"{dfm['nonrigid_median']:.2f} / {dfm['nonrigid_p90']:.2f} ({100 * dfm['nonrigid_share_median']:.0f} %)",
             *dash[1:], "–"],
        ]
    if evaluation.by_beta:
        for what, attr, paper in (("Offset_max", "offset_max", "0.889 – 1.181"), ("Offset_mean", "offset_mean", "0.350 – 0.453")):
            cells = []
            for m in COLUMNS:
                v = [getattr(b.summary(m), attr) for _, b in evaluation.by_beta]
                cells.append(f"{min(v):.3f} – {max(v):.3f}")
            rows.append([f"test-2 mean {what}, range over beta (mm)", *cells, paper])
    ps = evaluation.predict_seconds
    if ps:
        rows.append(["prediction time, one case (µs, p50 / p99)", f"{ps['p50'] * 1e6:.0f} / {ps['p99'] * 1e6:.0f}",
                     *dash[1:], "< 500000"])
    ms = evaluation.model_summary
    tr = ms.get("training") or {}
    if tr:
        rows.append(["training time (s; PCA choice + head + MLP)", tr.get("seconds", float("nan")), *dash[1:],
                     "1022 (MLP only)"])
    rows.append(["model", model_description(ms), *dash[1:], "MLP [128, 64] (their Fig. 5)"])
    rule = str((ms.get("pca") or {}).get("rule", "")).split(" (")[0]
    rows.append([f"PCA components n_w{' (' + rule + ' rule)' if rule else ''}", ms["n_components"], *dash[1:], "27"])
    return rows


def _summary_rows(evaluation) -> list[list]:
    rows = []
    items = list(evaluation.sets.items()) + [(f"test-2 β={b:g}", r) for b, r in evaluation.by_beta]
    for name, r in items:
        for m in COLUMNS:
            s = r.summary(m)
            rows.append([f"{name} {METHOD_LABELS[m]}", s.count, s.offset_mean, s.offset_max,
                         s.offset_max_percentiles[50.0], s.offset_max_percentiles[95.0], s.worst_offset_max,
                         100 * s.share_below])
    return rows


def _deformation_rows(evaluation) -> list[list]:
    rows = []
    items = list(evaluation.sets.items()) + [(f"test-2 β={b:g}", r) for b, r in evaluation.by_beta]
    for name, r in items:
        d = r.deformation()
        rows.append([name, r.indices.size, d["max_displacement_median"], d["max_displacement_p90"],
                     d["nonrigid_median"], d["nonrigid_p90"], 100 * d["nonrigid_share_median"],
                     r.rigid.offset_max, r.mlp.offset_max, r.gain_over_rigid])
    return rows


def _render_samples(folder: Path, model, dataset, evaluation, count: int) -> list[tuple[str, str, str]]:
    """Render and export up to ``count`` samples: test-1 median and worst, test-2 worst, ..."""
    picks = []
    for name, pick in (("test1", "median"), ("test1", "worst"), ("test2", "worst"), ("test2", "median"), ("valid", "worst")):
        r = evaluation.sets.get(name)
        if r is None or not r.indices.size:
            continue
        k = int(np.argmax(r.mlp_max)) if pick == "worst" else int(np.argsort(r.mlp_max)[r.indices.size // 2])
        label = f"{name} {pick} (sample {int(r.indices[k])}" + (f", β={r.beta[k]:g})" if np.isfinite(r.beta[k]) else ")")
        picks.append((label, int(r.indices[k]), f"{name}_{pick}"))
    out = []
    (folder / "vtu").mkdir(exist_ok=True)
    for label, idx, stem in picks[:count]:
        bench = np.asarray(dataset.displacements[idx], dtype=np.float64)
        pred = model.predict(model.marker_displacements(bench))
        err = np.linalg.norm(pred - bench, axis=1)
        data = {"benchmark_displacement": bench, "predicted_displacement": pred, "vertex_error": err,
                "ridge_displacement": model.predict_ridge(model.marker_displacements(bench))}
        if model.ensemble_size > 1:
            data["uncertainty"] = model.predict_with_uncertainty(model.marker_displacements(bench))[1]
        write_vtu(folder / "vtu" / f"{stem}.vtu", model.mesh, data)
        png = folder / f"render_{stem}.png"
        try:
            render_comparison(png, model.mesh, bench, pred, label, markers=model.markers)
        except Exception as exc:  # noqa: BLE001 - a missing OpenGL stack must not lose the report; logged, shown on the page
            log.warning("3D render of %s failed (%s); the VTU file is still written", label, exc)
            png = None
        out.append((label, png.name if png else "", f"vtu/{stem}.vtu"))
    return out


def _number(v: str):
    try:
        return float(v)
    except ValueError:
        return v


def _read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def _write_tables(folder: Path, evaluation) -> None:
    """``evaluation.json`` (every number of the page) and ``samples.csv`` (per-sample figures)."""
    (folder / "evaluation.json").write_text(json.dumps(evaluation.as_dict(), indent=2, default=float), encoding="utf-8")
    rows = evaluation.samples_table()
    if rows:
        with (folder / "samples.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
            w.writeheader()
            w.writerows(rows)


def _table_sections(title: str, model, dataset, evaluation) -> list[str]:
    """The page's title and tables: the paper's figures, the non-rigid part, per set, uncertainty."""
    ms = evaluation.model_summary
    parts = [f"<h1>{html.escape(title)}</h1>"]
    parts.append(f"<p>Model: {html.escape(repr(model))}<br>Data set: {html.escape(repr(dataset))}<br>"
                 f"Units: mm. Vertex ids 0-based; markers {ms['markers']}.</p>")
    parts.append("<h2>Scenario</h2>")
    parts.append("<p>How the training data's tissue is held and loaded (the model predicts within this "
                 "scenario only).</p>")
    parts.append(_table(["", "what"], [[html.escape(c) for c in row] for row in scenario_lines(ms.get("scenario"))]))
    parts.append("<h2>Measured versus the baselines and the paper</h2>")
    parts.append(_table(["quantity", *(METHOD_LABELS[m] for m in COLUMNS), "paper"], paper_table(evaluation)))
    parts.append("<p><small>Rigid registration: the best rotation and translation of the markers' reference "
                 "positions onto their tracked positions (Kabsch), applied to the whole mesh — what a navigation "
                 "system does with fiducials alone. PCA floor: the true field projected on the model's PCA basis, "
                 "the best any prediction of this model can do. Non-rigid part: the largest vertex residual after the "
                 "best rigid fit of the whole true field. Paper: Liu et al. 2020, H&amp;N tumour mesh, Abaqus data set; "
                 "here: this data set (see the data-set summary). Times measured on this machine.</small></p>")
    parts.append("<h2>How much of the deformation is not rigid</h2>")
    parts.append(_table(["set", "samples", "peak displacement median", "peak p90", "non-rigid part median",
                         "non-rigid p90", "non-rigid share of peak, median (%)", "rigid mean Offset_max",
                         "MLP mean Offset_max", "gain over rigid"], _deformation_rows(evaluation)))
    parts.append("<h2>Per set</h2>")
    parts.append(_table(["set", "samples", "mean Offset_mean", "mean Offset_max", "median Offset_max", "p95 Offset_max",
                         "worst Offset_max", "% Offset_max < 1 mm"], _summary_rows(evaluation)))
    unc = {k: v.as_dict().get("uncertainty") for k, v in evaluation.sets.items()}
    if any(unc.values()):
        parts.append("<h2>Uncertainty (ensemble spread)</h2>")
        parts.append(_table(["set", "mean per-sample Spearman(σ, vertex error)", "Spearman(max σ, Offset_max) over samples"],
                            [[k, u["vertex_spearman_mean"], u["sample_spearman_sigma_max_vs_offset_max"]]
                             for k, u in unc.items() if u]))
    return parts


def _figures(folder: Path, model, evaluation, studies_folder) -> list[tuple[str, Path]]:
    """Plot the figures the evaluation, the model and any studies have data for: ``[(caption, png)]``."""
    figs = [("Offsets per set (boxplots)", figures.boxplots(evaluation, folder / "boxplots.png"))]
    if evaluation.by_beta:
        figs.append(("Test-2 error versus β", figures.beta_curve(evaluation, folder / "beta.png")))
    vcurve = (getattr(model, "pca_choice_", None) or {}).get("validation_curve")
    if vcurve:
        figs.append(("Choice of n_w: validation error of the trained model and the PCA floor versus n_w",
                     figures.pca_validation_curve(vcurve, model.n_components, folder / "pca_validation.png")))
    if getattr(model, "pca_curve_", None) is not None:
        figs.append(("PCA reconstruction error versus n_w (cross-validated on the training set)",
                     figures.pca_curve(model.pca_curve_, folder / "pca.png")))
    members = (evaluation.model_summary.get("training") or {}).get("members") or []
    if members and members[0].get("valid_history"):
        figs.append(("Training: validation loss", figures.training_curves(members, folder / "training.png")))
    sf = Path(studies_folder) if studies_folder else folder
    if (sf / "study_markers.csv").is_file():
        figs.append(("Study: number of markers",
                     figures.marker_count_curve(_read_csv(sf / "study_markers.csv"), folder / "markers.png")))
    if (sf / "study_architecture.csv").is_file():
        figs.append(("Study: hidden layers",
                     figures.architecture_grid(_read_csv(sf / "study_architecture.csv"), folder / "architecture.png")))
    return figs


def _render_section(folder: Path, model, dataset, evaluation, renders: int) -> list[str]:
    parts = ["<h2>3D renders</h2><p>Undeformed, benchmark (FEM) and predicted surfaces; the prediction is coloured by "
             "vertex error; red dots are the fiducial markers. VTU files open in ParaView or 3D Slicer.</p>"]
    for label, png, vtu in _render_samples(folder, model, dataset, evaluation, renders):
        img = f"<img src='{png}' alt='{html.escape(label)}'>" if png else "<p>(render unavailable: no OpenGL)</p>"
        parts.append(f"<h3>{html.escape(label)}</h3>{img}<p><a href='{vtu}'>{vtu}</a></p>")
    return parts


def write_report(folder, model, dataset, evaluation, *, renders: int = EvaluateConfig.renders, studies_folder=None,
                 title="tissuecast report") -> Path:
    """Write the report folder and return the path of ``index.html``.

    Args:
        folder: output folder (created).
        model: the fitted DeformationModel.
        dataset: the data set it was evaluated on.
        evaluation: from :func:`tissuecast.evaluate.evaluation.evaluate_model`.
        renders: number of samples rendered in 3D (and exported as VTU).
        studies_folder: folder holding ``study_markers.csv`` / ``study_architecture.csv``
            (default: ``folder``); found studies are plotted.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _write_tables(folder, evaluation)
    parts = _table_sections(title, model, dataset, evaluation)
    for cap, p in _figures(folder, model, evaluation, studies_folder):
        parts.append(f"<h2>{html.escape(cap)}</h2><img src='{p.name}' alt='{html.escape(cap)}'>")
    if getattr(model, "has_trust", False):
        from .trust_report import trust_section

        parts.append(trust_section(model, dataset, folder))
    if renders:
        parts += _render_section(folder, model, dataset, evaluation, renders)
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>")
    index = folder / "index.html"
    index.write_text(page, encoding="utf-8")
    return index


def format_evaluation(evaluation) -> str:
    """Plain-text table of the headline figures (for terminals and logs)."""
    heads = ("MLP", "rigid", "ridge", "PCA floor")
    lines = [f"{what}: {text}" for what, text in scenario_lines(evaluation.model_summary.get("scenario"))]
    lines.append(f"{'quantity':62s} " + " ".join(f"{h:>15s}" for h in heads) + "   paper")
    for q, *cells, p in paper_table(evaluation):
        text = [c if isinstance(c, str) else _fmt(c) for c in cells]
        if all(t == "–" for t in text[1:]):  # a figure of the model alone: one wide cell
            lines.append(f"{q:62s} {text[0]:>15s}" + " " * 48 + f"   {p}")
        else:
            lines.append(f"{q:62s} " + " ".join(f"{t:>15s}" for t in text) + f"   {p}")
    if evaluation.by_beta:
        lines.append("test-2 mean Offset_max per beta, MLP (rigid, ridge): " + ", ".join(
            f"β={b:g}: {r.mlp.offset_max:.3f} ({r.rigid.offset_max:.3f}, {r.ridge.offset_max:.3f})"
            for b, r in evaluation.by_beta))
    return "\n".join(lines)
