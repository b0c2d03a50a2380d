"""The mismatch study's outputs: a terminal table, JSON and CSV, a figure and a report section.

The figure shows, per set, each model's relative error (mean Offset_max over the set's median
peak displacement) next to rigid registration's, sets outside the trained ranges hatched; the
report section (:func:`mismatch_section`) shows the table and the figure when the study's
files are in the report's studies folder (``study_mismatch.json``, ``study_mismatch.png``).
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np

from .headline import DASH, fmt_alarm, fmt_mm, fmt_ratio, fmt_share, html_table
from . import json_output
from .mismatch import PHYSICS, PHYSICS_KNOWN

#: How the physics rows' field was chosen (the study's ``physics_estimate``; studies before it was
#: recorded took the mean), in the report's words.
_ESTIMATE_WORDS = {"likeliest": "the likeliest held set's", "mean": "the posterior mean over the held sets"}

__all__ = ["mismatch_table", "format_mismatch", "write_mismatch", "mismatch_figure", "mismatch_section",
           "MISMATCH_JSON", "MISMATCH_PNG"]

MISMATCH_JSON = "study_mismatch.json"
MISMATCH_PNG = "study_mismatch.png"
_HEAD = ["set", "in range", "model", "peak median", "model Offset_max", "relative", "x nominal", "rigid",
         "ridge", "model vs rigid", "TRE mean", "corrected (rigid)", "90 % bounds cover", "alarm"]


def _range(v) -> str:
    return DASH if v is None else ("yes" if v else "no")


def mismatch_table(rows: list[dict]) -> list[list[str]]:
    """The study's rows as formatted cells (:data:`_HEAD` columns)."""
    out = []
    for r in rows:
        corrected = f"{fmt_share(r.get('mlp_corrected'))} ({fmt_share(r.get('rigid_corrected'))})"
        out.append([r["set"], _range(r["in_range"]), r["model"], fmt_mm(r["peak_median"]), fmt_mm(r["mlp_offset_max"]),
                    fmt_share(r["relative"]), fmt_ratio(r["relative_vs_nominal"]), fmt_mm(r["rigid_offset_max"]),
                    fmt_mm(r["ridge_offset_max"]), fmt_ratio(r["gain_over_rigid"]), fmt_mm(r.get("mlp_tre_mean")),
                    corrected, fmt_share(r.get("coverage_90")), fmt_alarm(r)])
    return out


def format_mismatch(rows: list[dict]) -> str:
    """A plain-text table for the terminal."""
    cells = [_HEAD] + mismatch_table(rows)
    widths = [max(len(row[k]) for row in cells) for k in range(len(_HEAD))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in cells)


def write_mismatch(folder, rows: list[dict], meta: dict) -> tuple[Path, Path]:
    """``study_mismatch.json`` (rows and ``meta``: alpha, samples, models) and ``study_mismatch.csv``."""
    from .studies import write_rows

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / MISMATCH_JSON
    path.write_text(json_output.dumps({"meta": meta, "rows": rows}, indent=1, default=float), encoding="utf-8")
    return path, write_rows(folder / "study_mismatch.csv", [{k: v for k, v in r.items() if k != "what"} for r in rows])


def mismatch_figure(rows: list[dict], path: Path) -> Path:
    """Grouped bars: each model's relative error per set, rigid registration's as a marker."""
    from .figures import pyplot, save_figure

    plt = pyplot()
    sets = list(dict.fromkeys(r["set"] for r in rows))
    models = list(dict.fromkeys(r["model"] for r in rows))
    by = {(r["set"], r["model"]): r for r in rows}
    x = np.arange(len(sets))
    width = 0.8 / max(len(models), 1)
    fig, ax = plt.subplots(figsize=(max(7.0, 0.75 * len(sets) + 2.5), 4.2))
    colours = plt.get_cmap("tab10")
    for k, m in enumerate(models):
        values = [100.0 * by[(s, m)]["relative"] if (s, m) in by else np.nan for s in sets]
        hatch = ["" if by.get((s, m), {}).get("in_range") is not False else "//" for s in sets]
        bars = ax.bar(x + (k - (len(models) - 1) / 2) * width, values, width, label=f"model: {m}", color=colours(k))
        for b, h in zip(bars, hatch):
            b.set_hatch(h)
    rigid = [100.0 * by[(s, models[0])]["rigid_offset_max"] / max(by[(s, models[0])]["peak_median"], 1e-300)
             if (s, models[0]) in by else np.nan for s in sets]
    ax.plot(x, rigid, "k_", markersize=18, markeredgewidth=2, label="rigid registration")
    ax.set_xticks(x, sets, rotation=35, ha="right")
    ax.set_ylabel("mean Offset_max / median peak (%)")
    ax.set_yscale("log")
    ax.set_title("What a mismatch costs (hatched: outside the trained ranges)")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def mismatch_section(studies_folder: Path, folder: Path) -> str | None:
    """The report's folded section of a mismatch study found in ``studies_folder`` (its figure
    copied into the report ``folder``), or None without one."""
    src = Path(studies_folder) / MISMATCH_JSON
    if not src.is_file():
        return None
    data = json.loads(src.read_text(encoding="utf-8"))
    rows = [{k: math.nan if v is None else v for k, v in r.items()} for r in data["rows"]]  # null: not measured
    meta = data.get("meta", {})
    png = mismatch_figure(rows, Path(folder) / MISMATCH_PNG)
    intro = (f"<p>Each model evaluated on test sets simulated with one thing different from its training simulator "
             f"({html.escape(str(meta.get('samples', '')))} samples a set, the same loads: alpha "
             f"{html.escape(str(meta.get('alpha', '')))} N). Relative: mean Offset_max over the set's median peak "
             "displacement; x nominal: that over the model's own on the nominal set; TRE at the evaluation's "
             "targets; corrected: share of the targets' displacement corrected (rigid registration's in brackets). "
             "In range: the uncertain parameters the model was trained with cover the set.</p>")
    if any(r["model"] == PHYSICS for r in rows):
        intro += (f"<p>The <i>physics</i> rows: the physics inverse (<code>predict --physics</code>: the first model's "
                  f"training simulator and markers, the recorded instrument poses) on each set's first "
                  f"{html.escape(str(meta.get('physics_frames', '')))} samples, rigid registration and ridge on the same "
                  "samples; where the attached margin is searched, its field is "
                  + _ESTIMATE_WORDS[meta.get("physics_estimate") or "mean"]
                  + "; its bounds column is the share of vertices within its 90 % band (1.44 x its posterior "
                  "spread, not a calibrated bound), its alarm column the share of frames its misfit warning "
                  "flags.</p>")
    if any(r["model"] == PHYSICS_KNOWN for r in rows):
        intro += ("<p>The <i>physics, margin known</i> rows: the same frames with each one's simulated attached "
                  "margin given (<code>predict --physics --attached-margin</code>: what a measured attachment is "
                  "worth); sets whose margins lie outside the training store's range have none.</p>")
    body = intro + html_table(_HEAD, mismatch_table(rows)) + f"<img src='{png.name}' alt='mismatch study'>"
    return ("<details open><summary><h2>What a mismatch costs</h2></summary>" + body + "</details>")
