"""The evaluation's tables, written for people: the paper comparison, per set, the deformations,
and the plain-text summary that ``tissuecast evaluate`` / ``run`` print."""

from __future__ import annotations

import shutil
import textwrap

from .evaluation import METHOD_LABELS
from .headline import DASH, fmt_mm, fmt_ratio, fmt_share, fmt_time, set_title, verdict
from ..scenario.describe import scenario_lines

__all__ = ["COLUMNS", "model_description", "expert_line", "paper_table", "set_rows", "deformation_rows",
           "format_evaluation", "SET_HEAD", "DEFORMATION_HEAD"]

#: Columns of the comparison tables: the learned model, then what it is compared with.
COLUMNS = ("mlp", "rigid", "ridge", "pca_floor")


def model_description(summary: dict) -> str:
    """'quadratic head (q = 15) + MLP [128, 64]' (x M for an ensemble; '+ a nominal expert' for a
    model with one; 'linear head' where the validation chose no quadratic direction, q = 0) from
    an evaluation's model summary."""
    net = f"MLP {summary.get('hidden')}" + (f" x {summary['ensemble']}" if summary.get("ensemble", 1) > 1 else "")
    q = ((summary.get("pca") or {}).get("head") or {}).get("dims")
    head = None if q is None else "linear head (q = 0)" if q == 0 else f"quadratic head (q = {q})"
    text = net if head is None else f"{head} + {net}"
    return text + (", with a nominal expert" if summary.get("nominal_expert") else "")


def expert_line(summary: dict) -> str | None:
    """How a model with a nominal expert routed test-1 (from the evaluation's model summary), or
    None for a model without one."""
    r = summary.get("nominal_expert")
    if not r:
        return None
    return (f"nominal expert: {fmt_share(r['routed_to_nominal'])} of test-1 routed to it by the gate; mean Offset_max "
            f"{fmt_mm(r['routed_offset_max'])} routed, the uncertainty-trained model alone "
            f"{fmt_mm(r['uncertain_offset_max'])}, the expert alone {fmt_mm(r['nominal_offset_max'])}, the better "
            f"of the two on each sample {fmt_mm(r['oracle_offset_max'])}")


def _tre_cells(r) -> list[list[str]]:
    """The TRE and share-corrected rows' cells of a set, per method of :data:`COLUMNS`."""
    t = [r.target_summary(m) for m in COLUMNS]
    if not all(t):
        return []
    tre = [DASH if x.tre_mean != x.tre_mean else f"{fmt_mm(x.tre_mean, False)} / {fmt_mm(x.tre_p95, False)} / "
           f"{fmt_mm(x.tre_max)}" for x in t]
    share = [DASH if x.share_corrected_mean != x.share_corrected_mean else
             f"{fmt_share(x.share_corrected_mean)} ({fmt_share(x.share_corrected_worst)})" for x in t]
    return [tre, share]


def paper_table(evaluation) -> list[list[str]]:
    """Rows ``[quantity, MLP, rigid, ridge, PCA floor, paper]`` comparing the learned model with
    rigid registration from the markers, the paper's ridge baseline, the PCA floor and the
    paper's figures (Offset_max, Offset_mean, TRE at the targets and the share of their
    displacement corrected); then the size of the deformations, times and the model."""
    rows = []
    t1 = evaluation.sets.get("test1")
    dash = [DASH] * len(COLUMNS)
    if t1 is not None:
        s = [t1.summary(m) for m in COLUMNS]
        rows += [["test-1 mean Offset_max", *(fmt_mm(x.offset_max) for x in s), "0.533 (architecture table) / 0.837 mm"],
                 ["test-1 mean Offset_mean", *(fmt_mm(x.offset_mean) for x in s), "0.146 – 0.287 mm"]]
        tre = _tre_cells(t1)
        if tre:
            k = evaluation.targets.count if evaluation.targets is not None else ""
            rows += [[f"test-1 TRE at the {k} targets: mean / p95 / max", *tre[0], DASH],
                     ["test-1 share of the targets' displacement corrected: mean (worst)", *tre[1], DASH]]
        rows += [["test-1 share with Offset_max < 1 mm", *(fmt_share(x.share_below) for x in s), "98 %"],
                 ["test-1 worst Offset_max", *(fmt_mm(x.worst_offset_max) for x in s), DASH],
                 ["test-1 gain over rigid registration (mean Offset_max ratio)", fmt_ratio(t1.gain_over_rigid), *dash[1:],
                  DASH]]
        dfm = t1.deformation()
        rows += [["test-1 peak displacement, median / p90", f"{fmt_mm(dfm['max_displacement_median'], False)} / "
                  f"{fmt_mm(dfm['max_displacement_p90'])}", *dash[1:], "~30 mm (largest)"],
                 ["test-1 non-rigid part, median / p90 (median share of peak)",
                  f"{fmt_mm(dfm['nonrigid_median'], False)} / {fmt_mm(dfm['nonrigid_p90'])} "
                  f"({fmt_share(dfm['nonrigid_share_median'])})", *dash[1:], DASH]]
    if evaluation.by_beta:
        for what, attr, paper in (("Offset_max", "offset_max", "0.889 – 1.181 mm"), ("Offset_mean", "offset_mean",
                                                                                      "0.350 – 0.453 mm")):
            cells = []
            for m in COLUMNS:
                v = [getattr(b.summary(m), attr) for _, b in evaluation.by_beta]
                cells.append(f"{fmt_mm(min(v), False)} – {fmt_mm(max(v))}")
            rows.append([f"test-2 mean {what}, range over beta", *cells, paper])
    ps = evaluation.predict_seconds
    if ps:
        gate = {True: ", input gate on", False: ", input gate off (it refused the timed inputs)"}.get(ps.get("gate"), "")
        rows.append([f"prediction time, one case (p50 / p99{gate})", f"{fmt_time(ps['p50'])} / {fmt_time(ps['p99'])}",
                     *dash[1:], "< 0.5 s"])
    ms = evaluation.model_summary
    tr = ms.get("training") or {}
    if tr:
        rows.append(["training time (all it fits: PCA, head, networks, fold models, fallback)",
                     fmt_time(tr.get("seconds", float("nan"))), *dash[1:], "1022 s (MLP only)"])
    rows.append(["model", model_description(ms), *dash[1:], "MLP [128, 64] (their Fig. 5)"])
    rule = str((ms.get("pca") or {}).get("rule", "")).split(" (")[0]
    rows.append([f"PCA components n_w{' (' + rule + ' rule)' if rule else ''}", str(ms["n_components"]), *dash[1:], "27"])
    return rows


def _items(evaluation) -> list:
    return [(set_title(k), r) for k, r in evaluation.sets.items()] + [(f"test-2 β={b:g}", r) for b, r in evaluation.by_beta]


def set_rows(evaluation) -> list[list[str]]:
    """One row per set (and per test-2 β): samples; mean Offset_max of every method; mean TRE of
    the MLP, rigid registration and ridge; the MLP's share corrected and share below 1 mm."""
    rows = []
    for name, r in _items(evaluation):
        s = {m: r.summary(m) for m in COLUMNS}
        t = {m: r.target_summary(m) for m in ("mlp", "rigid", "ridge")}
        tre = [fmt_mm(t[m].tre_mean, False) if t[m] else DASH for m in t]
        share = fmt_share(t["mlp"].share_corrected_mean) if t["mlp"] else DASH
        rows.append([name, str(r.indices.size), *(fmt_mm(s[m].offset_max, False) for m in COLUMNS), *tre, share,
                     fmt_share(s["mlp"].share_below)])
    return rows


#: Column heads of :func:`set_rows`.
SET_HEAD = ["set", "samples", *(f"{METHOD_LABELS[m]} Offset_max (mm)" for m in COLUMNS),
            *(f"{METHOD_LABELS[m]} TRE mean (mm)" for m in ("mlp", "rigid", "ridge")), "MLP share corrected",
            "MLP Offset_max < 1 mm"]


def deformation_rows(evaluation) -> list[list[str]]:
    """Per set: peak displacement and non-rigid part (median / p90), rigid and MLP error, gain."""
    rows = []
    for name, r in _items(evaluation):
        d = r.deformation()
        rows.append([name, str(r.indices.size), fmt_mm(d["max_displacement_median"]), fmt_mm(d["max_displacement_p90"]),
                     fmt_mm(d["nonrigid_median"]), fmt_mm(d["nonrigid_p90"]), fmt_share(d["nonrigid_share_median"]),
                     fmt_mm(r.rigid.offset_max), fmt_mm(r.mlp.offset_max), fmt_ratio(r.gain_over_rigid)])
    return rows


DEFORMATION_HEAD = ["set", "samples", "peak displacement median", "peak p90", "non-rigid part median", "non-rigid p90",
                    "non-rigid share of peak, median", "rigid mean Offset_max", "MLP mean Offset_max", "gain over rigid"]


def format_evaluation(evaluation, width: int | None = None) -> str:
    """Plain-text summary for terminals and logs: the verdict, the headline, the paper table.

    The table is a grid (a column per method) where it fits ``width`` characters (default: the
    terminal's width, 200 where there is no terminal), else one line per quantity naming each
    method; long lines are wrapped to ``width``."""
    columns = width or shutil.get_terminal_size(fallback=(200, 24)).columns
    lines = [f"{what}: {text}" for what, text in scenario_lines(evaluation.model_summary.get("scenario"))]
    if evaluation.targets is not None:
        lines.append(f"targets: {evaluation.targets.description}")
    lines.append(textwrap.fill(verdict(evaluation), columns))
    rows = paper_table(evaluation)
    labels = [METHOD_LABELS[m] for m in COLUMNS]
    grid = _grid(rows, labels)
    if max(len(line) for line in grid) <= columns:
        lines += grid
    else:
        for q, *cells, p in rows:
            named = ([cells[0]] if _model_only([q, *cells, p]) else
                     [f"{label} {c}" for label, c in zip(labels, cells) if c != DASH])
            lines += _wrap_items(f"{q}:", named + ([f"paper {p}"] if p != DASH else []), columns)
    routed = expert_line(evaluation.model_summary)
    if routed:
        lines.append(textwrap.fill(routed, columns, subsequent_indent="    "))
    if evaluation.by_beta:
        lines += _wrap_items("test-2 mean Offset_max per beta, MLP (rigid, ridge):", [
            f"β={b:g}: {fmt_mm(r.mlp.offset_max, False)} ({fmt_mm(r.rigid.offset_max, False)}, "
            f"{fmt_mm(r.ridge.offset_max, False)})" for b, r in evaluation.by_beta], columns, sep=", ")
    return "\n".join(lines)


def _wrap_items(head: str, items: list[str], width: int, indent: str = "    ", sep: str = " · ") -> list[str]:
    """``head`` then ``items`` joined by ``sep``, wrapped to ``width`` between items (an item is
    never broken: a value stays with its unit)."""
    lines, line = [], head
    for k, item in enumerate(items):
        piece = (" " if k == 0 else sep) + item
        if len(line) + len(piece) > width and line.strip():
            trailing = k > 0 and sep.strip() in (",", ";")  # a comma ends its line; a bullet starts the next
            lines.append(line + (sep.rstrip() if trailing else ""))
            line = indent + (item if k == 0 or trailing else sep.lstrip() + item)
        else:
            line += piece
    return lines + [line]


def _grid(rows: list[list[str]], labels: list[str]) -> list[str]:
    """The paper table as aligned text: quantity, a column per method (each as wide as its
    widest cell), the paper's figure last; a figure of the model alone spans the method columns."""
    wq = max(len("quantity"), *(len(r[0]) for r in rows))
    widths = [max(len(label), *(len(r[1 + k]) for r in rows if not _model_only(r))) for k, label in enumerate(labels)]
    gap = "   "
    span = sum(widths) + len(gap) * (len(widths) - 1)
    out = [f"{'quantity':{wq}s}{gap}" + gap.join(f"{label:>{w}s}" for label, w in zip(labels, widths)) + f"{gap}paper"]
    for q, *cells, p in rows:
        if _model_only([q, *cells, p]):
            out.append(f"{q:{wq}s}{gap}{cells[0]:<{span}s}{gap}{p}")
        else:
            out.append(f"{q:{wq}s}{gap}" + gap.join(f"{c:>{w}s}" for c, w in zip(cells, widths)) + f"{gap}{p}")
    return out


def _model_only(row: list[str]) -> bool:
    """A row with a figure of the model alone (the other methods' cells empty)."""
    return all(c == DASH for c in row[2:-1])
