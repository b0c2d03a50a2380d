"""The evaluation report: an HTML page that reads at a glance, with its data and files beside it.

``write_report(folder, model, dataset, evaluation)`` writes::

    index.html            the page (opens offline, from the folder, in any browser)
    viewer.js             the interactive 3D view (hand-written WebGL, no third-party code)
    viewer_data.js        its data: surface, markers, targets, true and predicted displacements
    evaluation.json       every number of the page
    trust.json            error-bound coverage and alarm rates (calibrated models)
    samples.csv           per-sample Offset_mean / Offset_max and TRE of the MLP, rigid
                          registration, ridge and the PCA floor; peak displacement, non-rigid part
    *.png                 figures and static 3D renders
    vtu/*.vtu             benchmark / predicted displacement and vertex error per rendered sample

The page's first screen answers "how good, against what, how sure": one sentence, the
headline table (the learned model next to rigid registration from the same markers and the
paper's ridge baseline: Offset_max, Offset_mean, TRE at the targets, the share of their
displacement corrected) and the error bounds' coverage with the alarm's rate. Below it the
deformation in 3D, then every detail folded away (``<details>``).
"""

from __future__ import annotations

import csv
import html
import logging
from pathlib import Path

import numpy as np

from ..config import EvaluateConfig
from . import figures
from . import json_output
from .evaluation import METHOD_LABELS, auxiliary_values, method_fields
from .headline import HEADLINE_METHODS, beta_table, headline_rows, headline_set, html_table, set_title, trust_rows, verdict
from .render import render_comparison, write_vtu
from .tables import (COLUMNS, DEFORMATION_HEAD, SET_HEAD, deformation_rows, expert_line, format_evaluation,
                     model_description, paper_table, set_rows)
from .mismatch_report import mismatch_section
from .trust_report import trust_evaluation, uncertainty_section
from .viewer import pick_samples, write_viewer
from ..scenario.describe import scenario_lines

__all__ = ["write_report", "paper_table", "format_evaluation"]

log = logging.getLogger(__name__)

CSS = """body{font-family:system-ui,sans-serif;max-width:1180px;margin:1.2em auto;padding:0 1em;color:#1d232a;line-height:1.4}
h1{font-size:1.5em;margin:.2em 0}h2{font-size:1.2em;margin:.9em 0 .4em}h3{font-size:1.05em}
.tc-sub{color:#56606b;margin:0 0 .6em}.tc-verdict{font-size:1.08em;background:#f3f6f9;border-left:4px solid #2a6fb0;
padding:.6em .9em;margin:.6em 0}
table{border-collapse:collapse;margin:.5em 0 1em}td,th{border-bottom:1px solid #d5dbe1;padding:4px 10px;text-align:right}
th{background:#eef1f4;font-weight:600}td:first-child,th:first-child{text-align:left}
.tc-wide{overflow-x:auto;max-width:100%}table.tc-headline td:not(:first-child){white-space:nowrap}
table.tc-sure td:last-child,table.tc-sure th:last-child{text-align:left;white-space:normal}
table.tc-headline td:nth-child(2),table.tc-headline th:nth-child(2){background:#e8f1fb;font-weight:600}
img{max-width:100%}details{border-top:1px solid #d5dbe1;padding:.3em 0}summary{cursor:pointer}
summary h2{display:inline;font-size:1.1em}small,.tc-note{color:#56606b}
.tc-controls{display:flex;flex-wrap:wrap;gap:.4em 1.2em;font-size:.92em;margin:.3em 0}
.tc-panels{display:grid;grid-template-columns:1fr 1fr;gap:0;font-size:.9em}
.tc-title{font-weight:600}.tc-bar{display:flex;align-items:center;gap:.4em}
.tc-ramp{display:inline-block;width:160px;height:10px;border:1px solid #999}
.tc-canvas{width:100%;height:440px;display:block;border:1px solid #d5dbe1;touch-action:none;cursor:grab}"""


def _header(title: str, model, dataset, evaluation) -> str:
    ms = evaluation.model_summary
    targets = evaluation.targets
    facts = [model_description(ms), f"{len(ms['markers'])} markers (vertices {ms['markers']})",
             f"data set: {dataset.path or type(dataset).__name__} ({dataset.n_samples} samples)"]
    if targets is not None:
        facts.append(f"targets: {targets.description}")
    routed = expert_line(ms)
    if routed:
        facts.append(routed)
    return (f"<h1>{html.escape(title)}</h1><p class='tc-sub'>{html.escape(' · '.join(str(f) for f in facts))}. "
            "Units: mm; frame LPS; vertex ids 0-based. Every figure below is measured on this data set's finite-element "
            "simulations with exact (noise-free) marker displacements: it says how well the model learned its "
            "simulator, not how far it is from a patient.</p>")


def _headline(evaluation, trust: dict | None, model) -> str:
    """The first screen: the verdict, how good against what, how sure."""
    name = headline_set(evaluation)
    parts = [f"<p class='tc-verdict'>{html.escape(verdict(evaluation, trust if trust is not None else {}))}</p>"]
    if name is not None:
        parts.append(f"<h2>How good, against what ({html.escape(set_title(name))}, "
                     f"{evaluation.sets[name].indices.size} samples)</h2>")
        head = ["", *(METHOD_LABELS[m] for m in HEADLINE_METHODS)]
        parts.append(html_table(head, headline_rows(evaluation)).replace("<table>", "<table class='tc-headline'>", 1))
    parts.append("<h2>How sure</h2>")
    parts.append(html_table(["", "value", "what it means"], trust_rows(trust, model.has_uncertainty))
                 .replace("<table>", "<table class='tc-sure'>", 1))
    parts.append("<p class='tc-note'>Rigid registration: the best rotation and translation of the markers onto their "
                 "tracked positions, applied to the whole mesh (what a navigation system does with fiducials alone). "
                 "Offset_max: a sample's largest error over every mesh vertex (the worst vertex, interior ones "
                 "included); Offset_mean: its mean over the vertices. "
                 "TRE: error at the targets, points inside the tissue; share corrected: 1 − TRE / the targets' true "
                 "displacement, per sample (negative: worse than not correcting at all). Test-2: samples under other "
                 "kinds of force fields than the training's (β from 0, unlike them, to 1, like them). The alarm's "
                 "reasons: far (inputs unlike every simulated one), disagree (markers inconsistent with each "
                 "other), still marker (a marker that did not move where every simulation moved it), swapped "
                 "markers (two markers that look exchanged).</p>")
    return "".join(parts)


def _render_samples(folder: Path, model, dataset, evaluation, count: int) -> list[tuple[str, str, str]]:
    """Render and export up to ``count`` samples (:func:`~.viewer.pick_samples`)."""
    out = []
    (folder / "vtu").mkdir(exist_ok=True)
    aux = auxiliary_values(model, dataset)
    for label, idx, stem in pick_samples(evaluation, count):
        bench = np.asarray(dataset.displacements[idx], dtype=np.float64)
        d = model.marker_displacements(bench)
        a = None if aux is None else aux[idx]
        fields = method_fields(model, d[None], ("mlp", "ridge"), auxiliary=None if a is None else a[None])
        pred = fields["mlp"][0]
        data = {"benchmark_displacement": bench, "predicted_displacement": pred,
                "vertex_error": np.linalg.norm(pred - bench, axis=1), "ridge_displacement": fields["ridge"][0]}
        if model.has_uncertainty:
            data["uncertainty"] = model.predict_with_uncertainty(d, auxiliary=a)[1]
        write_vtu(folder / "vtu" / f"{stem}.vtu", model.mesh, data)
        png = folder / f"render_{stem}.png"
        try:
            render_comparison(png, model.mesh, bench, pred, label, markers=model.markers)
        except Exception as exc:  # noqa: BLE001 - a missing OpenGL stack must not lose the report; logged, shown on the page
            log.warning("3D render of %s failed (%s); the VTU file is still written", label, exc)
            png = None
        out.append((label, png.name if png else "", f"vtu/{stem}.vtu"))
    return out


def _read_csv(path: Path) -> list[dict]:
    def number(v: str):
        try:
            return float(v)
        except ValueError:
            return v

    with path.open(newline="") as fh:
        return [{k: number(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def _write_tables(folder: Path, evaluation) -> None:
    """``evaluation.json`` (every number of the page) and ``samples.csv`` (per-sample figures)."""
    (folder / "evaluation.json").write_text(json_output.dumps(evaluation.as_dict(), indent=2, default=float), encoding="utf-8")
    rows = evaluation.samples_table()
    if rows:
        with (folder / "samples.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
            w.writeheader()
            w.writerows(rows)


def _fold(title: str, body: str, open_: bool = False, id_: str = "") -> str:
    ident = f" id='{id_}'" if id_ else ""
    return f"<details{ident}{' open' if open_ else ''}><summary><h2>{html.escape(title)}</h2></summary>{body}</details>"


def _detail_sections(evaluation) -> list[str]:
    """Every figure of the evaluation, folded: the paper comparison, per set, the deformations, the scenario."""
    ms = evaluation.model_summary
    paper = html_table(["quantity", *(METHOD_LABELS[m] for m in COLUMNS), "paper"], paper_table(evaluation))
    paper += ("<p><small>PCA floor: the true field projected on the model's PCA basis, the best prediction of this "
              "model in the least-squares sense (not a bound on Offset_max, which it can exceed). Non-rigid part: "
              "the largest vertex residual after the best rigid fit of the whole true field. Paper: Liu et al. 2020, "
              "H&amp;N tumour mesh, Abaqus data set, not comparable with this data set's simulations. Training time: "
              "everything the model's training fits (the calibration's fold models and the markers-only fallback "
              "included, where there are; a nominal expert's training not), against the paper's network alone. "
              "Times measured on this machine. Every number is in "
              "evaluation.json, every sample in samples.csv.</small></p>")
    scenario = ("<p>How the training data's tissue is held and loaded (the model predicts within this scenario only).</p>"
                + html_table(["", "what"], [list(row) for row in scenario_lines(ms.get("scenario"))]))
    return [_fold("Measured against the baselines and the paper", paper),
            _fold("Per set and per β", beta_table(SET_HEAD, set_rows(evaluation))),
            _fold("How much of the deformation is not rigid", beta_table(DEFORMATION_HEAD, deformation_rows(evaluation))),
            _fold("Scenario", scenario)]


def _figures(folder: Path, model, evaluation, studies_folder) -> list[tuple[str, Path]]:
    """Plot the figures the evaluation, the model and any studies have data for: ``[(caption, png)]``."""
    figs = [("Offsets per set (boxplots)", figures.boxplots(evaluation, folder / "boxplots.png"))]
    if evaluation.by_beta:
        figs.append(("Test-2 error versus β", figures.beta_curve(evaluation, folder / "beta.png")))
    vcurve = (model.pca_choice_ or {}).get("validation_curve")
    if vcurve:
        figs.append(("Choice of n_w: validation error of the trained model and the PCA floor versus n_w",
                     figures.pca_validation_curve(vcurve, model.n_components, folder / "pca_validation.png")))
    if model.pca_curve_ is not None:
        figs.append(("PCA reconstruction error versus n_w (cross-validated on the training set)",
                     figures.pca_curve(model.pca_curve_, folder / "pca.png")))
    training = evaluation.model_summary.get("training") or {}
    members = training.get("members") or []
    if members and members[0].get("valid_history"):
        fallback = [m for m in (training.get("fallback") or {}).get("members") or [] if m.get("valid_history")]
        figs.append(("Training: validation loss versus epoch (lower is better; the scale is the networks' own, "
                     "not mm)" + ("; dashed: the markers-only fallback" if fallback else ""),
                     figures.training_curves(members, folder / "training.png", fallback)))
    sf = Path(studies_folder) if studies_folder else folder
    if (sf / "study_markers.csv").is_file():
        figs.append(("Study: number of markers",
                     figures.marker_count_curve(_read_csv(sf / "study_markers.csv"), folder / "markers.png")))
    if (sf / "study_architecture.csv").is_file():
        figs.append(("Study: hidden layers",
                     figures.architecture_grid(_read_csv(sf / "study_architecture.csv"), folder / "architecture.png")))
    return figs


def _render_section(folder: Path, model, dataset, evaluation, renders: int) -> str:
    parts = ["<p>Undeformed, benchmark (FEM) and predicted surfaces; the prediction is coloured by vertex error; red "
             "dots are the fiducial markers. The VTU files open in ParaView or 3D Slicer.</p>"]
    for label, png, vtu in _render_samples(folder, model, dataset, evaluation, renders):
        img = f"<img src='{png}' alt='{html.escape(label)}'>" if png else "<p>(render unavailable: no OpenGL)</p>"
        parts.append(f"<h3>{html.escape(label)}</h3>{img}<p><a href='{vtu}'>{vtu}</a></p>")
    return _fold("Static renders and VTU files", "".join(parts), id_="tc-renders")  # the viewer opens it without WebGL


def write_report(folder, model, dataset, evaluation, *, renders: int = EvaluateConfig.renders, studies_folder=None,
                 title="tissuecast report") -> Path:
    """Write the report folder and return the path of ``index.html``.

    Args:
        folder: output folder (created).
        model: the fitted DeformationModel.
        dataset: the data set it was evaluated on.
        evaluation: from :func:`tissuecast.evaluate.evaluation.evaluate_model`.
        renders: number of samples rendered in 3D as static pictures (and exported as VTU);
            the interactive view shows up to :data:`~.viewer.VIEWER_SAMPLES` in any case.
        studies_folder: folder holding ``study_markers.csv`` / ``study_architecture.csv``
            (default: ``folder``); found studies are plotted.
    """
    with model.gate_suspended():  # the data set's simulated samples: the gate's verdicts are in the evaluation
        return _write_report(Path(folder), model, dataset, evaluation, renders, studies_folder, title)


def _write_report(folder: Path, model, dataset, evaluation, renders: int, studies_folder, title: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    _write_tables(folder, evaluation)
    trust = trust_evaluation(model.trusted_, dataset, field_predictor=model.bounds_predictor) if model.has_trust else None
    parts = [_header(title, model, dataset, evaluation), _headline(evaluation, trust, model),
             write_viewer(folder, model, dataset, evaluation), uncertainty_section(model.trusted_, evaluation, trust, folder)]
    parts += _detail_sections(evaluation)
    figs = "".join(f"<h3>{html.escape(cap)}</h3><img src='{p.name}' alt='{html.escape(cap)}'>"
                   for cap, p in _figures(folder, model, evaluation, studies_folder))
    parts.append(_fold("Figures", figs))
    mismatch = mismatch_section(Path(studies_folder) if studies_folder else folder, folder)
    if mismatch:
        parts.insert(4, mismatch)
    if renders:
        parts.append(_render_section(folder, model, dataset, evaluation, renders))
    body = "".join(parts).replace("<table", "<div class='tc-wide'><table").replace("</table>", "</table></div>")
    page = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<style>{CSS}</style></head><body>{body}</body></html>")
    index = folder / "index.html"
    index.write_text(page, encoding="utf-8")
    return index
