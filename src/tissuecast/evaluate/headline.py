"""The report's first screen: how good, against what, how sure, with numbers written for people.

:func:`headline_rows` gives the headline table (one test set: the learned model next to rigid
registration from the same markers and the paper's ridge baseline; Offset_max and
Offset_mean over all vertices, TRE and the share of the displacement corrected at the
targets), :func:`trust_rows` the calibrated error bounds' coverage and the alarm's rate, and
:func:`verdict` one sentence that says it all. The ``fmt_*`` helpers write numbers as a
reader expects them: ``"0.29 mm"``, ``"100 %"``, ``"5.9×"``, ``"—"`` where there is no number.
"""

from __future__ import annotations

import html
import math

__all__ = ["DASH", "fmt_mm", "fmt_share", "fmt_ratio", "fmt_time", "fmt_alarm", "set_title", "headline_set",
           "headline_rows", "trust_rows", "verdict", "html_table", "beta_table", "HEADLINE_METHODS"]

#: Written where a figure does not exist (a model without bounds, a baseline that cannot predict).
DASH = "—"
#: The methods of the headline table: the learned model, then what it is compared with.
HEADLINE_METHODS = ("mlp", "rigid", "ridge")
#: Test sets in order of preference for the headline (test-1 is the training distribution's).
_SETS = ("test1", "test2", "valid")


def _bad(v) -> bool:
    return v is None or (isinstance(v, float) and not math.isfinite(v))


def fmt_mm(v, unit: bool = True) -> str:
    """A length in mm: 2 decimals below 10 mm (3 below 0.01 mm, "< 0.001" below that), 1 below
    100, none above."""
    if _bad(v):
        return DASH
    a = abs(v)
    if 0 < a < 0.0005:
        text = "< 0.001"
    else:
        text = f"{v:.3f}" if a < 0.01 else f"{v:.2f}" if a < 10 else f"{v:.1f}" if a < 100 else f"{v:.0f}"
    return f"{text} mm" if unit else text


def fmt_share(v) -> str:
    """A share 0..1 as a percentage: whole numbers when they are exact to 0.05 %, else 1 decimal."""
    if _bad(v):
        return DASH
    p = 100.0 * v
    return f"{round(p):.0f} %" if abs(p - round(p)) < 0.05 else f"{p:.1f} %"


#: The alarm's reasons: the figures' key (:func:`.trust_report.bound_figures`, the share of
#: samples raising the alarm for it) -> (the :class:`~tissuecast.surrogate.trust.Alarm` property,
#: its short name in tables).
ALARM_REASONS = {"alarm_far_rate": ("far_from_training", "far"),
                 "alarm_disagree_rate": ("inconsistent_markers", "disagree"),
                 "alarm_still_rate": ("still_marker_alarm", "still marker"),
                 "alarm_swap_rate": ("swapped_markers_alarm", "swapped markers")}


def fmt_alarm(row: dict) -> str:
    """A row's alarm rate (``alarm_rate``) with the reasons that raised it, most frequent first
    (``alarm_far_rate``, ...; rows written before them: the rate alone)."""
    rate = fmt_share(row.get("alarm_rate"))
    reasons = sorted(((row.get(k) or 0.0, w) for k, (_, w) in ALARM_REASONS.items()), reverse=True)
    named = [w for v, w in reasons if v > 0]
    return f"{rate} ({', '.join(named)})" if named else rate


def fmt_ratio(v) -> str:
    """A ratio: ``"5.9×"``, ``"12×"``; ``"> 1000×"`` above a thousand."""
    if _bad(v):
        return DASH
    return f"{v:.2g}×" if abs(v) < 10 else f"{v:.0f}×" if abs(v) <= 1000 else "> 1000×"


def set_title(name: str) -> str:
    """A set's name for people: 'test1' -> 'test-1', 'test2 beta=0.5' -> 'test-2 β=0.5', 'valid' -> 'validation'."""
    out = name.replace("test1", "test-1").replace("test2", "test-2").replace("beta=", "β=")
    return {"valid": "validation", "train": "training"}.get(out, out)


def fmt_time(seconds) -> str:
    """A duration: µs, ms or s with 2-3 significant digits."""
    if _bad(seconds):
        return DASH
    for scale, unit in ((1e-6, "µs"), (1e-3, "ms")):
        if seconds < 1000 * scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds:.3g} s"


def headline_set(evaluation) -> str | None:
    """The set the headline speaks of: test-1 when evaluated, else test-2, else validation."""
    return next((s for s in _SETS if s in evaluation.sets), None)


def headline_rows(evaluation) -> list[list[str]]:
    """Rows ``[quantity, MLP, rigid registration, ridge]`` of the headline set, formatted."""
    name = headline_set(evaluation)
    if name is None:
        return []
    r = evaluation.sets[name]
    s = {m: r.summary(m) for m in HEADLINE_METHODS}
    rows = [["worst-vertex error, Offset_max (mean over samples)", *(fmt_mm(s[m].offset_max) for m in HEADLINE_METHODS)],
            ["mean vertex error, Offset_mean", *(fmt_mm(s[m].offset_mean) for m in HEADLINE_METHODS)]]
    t = {m: r.target_summary(m) for m in HEADLINE_METHODS}
    if all(t.values()):
        k = evaluation.targets.count if evaluation.targets is not None else "the"
        rows.append([f"error at {k} targets (TRE): per-sample mean / p95 / max, averaged over samples",
                     *(DASH if _bad(t[m].tre_mean) else
                       f"{fmt_mm(t[m].tre_mean, False)} / {fmt_mm(t[m].tre_p95, False)} / {fmt_mm(t[m].tre_max)}"
                       for m in HEADLINE_METHODS)])
        rows.append(["share of the targets' displacement corrected: mean (worst sample)",
                     *(DASH if _bad(t[m].share_corrected_mean) else
                       f"{fmt_share(t[m].share_corrected_mean)} ({fmt_share(t[m].share_corrected_worst)})"
                       for m in HEADLINE_METHODS)])
    rows.append([f"samples with Offset_max < {s['mlp'].threshold:g} mm",
                 *(fmt_share(s[m].share_below) if not _bad(s[m].offset_max) else DASH for m in HEADLINE_METHODS)])
    worst = "worst sample: Offset_max" + (" / worst target error" if all(t.values()) else "")
    rows.append([worst, *(DASH if _bad(s[m].offset_max) else fmt_mm(s[m].worst_offset_max, False) + (
        f" / {fmt_mm(t[m].worst_tre_max)}" if all(t.values()) else " mm") for m in HEADLINE_METHODS)])
    return rows


#: Test-2 coverage of the 90 % bounds below which the report says the bounds do not hold there.
TEST2_COVERAGE_WARNING = 0.8


def _failing_test2(sets: dict) -> dict | None:
    """The trust figures of test-2 (``trust["sets"]``) where its 90 % bounds cover less than
    :data:`TEST2_COVERAGE_WARNING`, else None."""
    t2 = sets.get("test2")
    if t2 is None or _bad(t2["coverage_0.9"]) or t2["coverage_0.9"] >= TEST2_COVERAGE_WARNING:
        return None
    return t2


def trust_rows(trust: dict | None, model_has_ensemble: bool = False) -> list[list[str]]:
    """Rows ``[quantity, value, what it means]`` of the calibrated bounds and the alarm."""
    if not trust or not trust.get("sets"):
        why = ("not calibrated: the model was trained with surrogate.calibration = 'none' or calibration_share = 0"
               + ("; only the ensemble's spread is there, which is not in calibrated mm" if model_has_ensemble else ""))
        return [["90 % error bounds, alarm", DASH, why]]
    sets = trust["sets"]
    name = next(s for s in ("test1", "test2") if s in sets)
    t = sets[name]
    finite = not _bad(t["median_bound_0.9"])
    rows = [[f"90 % error bounds: share of vertices covered ({set_title(name)})", fmt_share(t["coverage_0.9"]),
             f"should be about 90 %; median bound {fmt_mm(t['median_bound_0.9'])}" if finite else
             "the bounds are infinite: too few calibration samples for 90 %"]]
    if not t.get("alarm_on", True):
        rows.append(["out-of-distribution alarm", "off", "too few calibration samples for its false-alarm rate"])
        return rows
    rows.append([f"out-of-distribution alarm: samples raising it ({set_title(name)})", fmt_alarm(t),
                 "in-distribution inputs: should be near the false-alarm rate"])
    if name == "test1" and "test2" in sets:
        t2 = sets["test2"]
        meaning = f"bounds cover {fmt_share(t2['coverage_0.9'])} there"
        if _failing_test2(sets):
            meaning += (f": the bounds do not hold for force fields unlike the training's, and "
                        f"{fmt_share(1.0 - t2['alarm_rate'])} of those samples raise no alarm")
        rows.append(["alarm on test-2 (other force fields)", fmt_alarm(t2), meaning])
    return rows


def verdict(evaluation, trust: dict | None = None) -> str:
    """One sentence: how far off the model is, against rigid registration, at the targets, and
    (``trust``: :func:`~.trust_report.trust_evaluation`'s result, ``{}`` for a model without
    bounds, None to say nothing of them) how sure."""
    name = headline_set(evaluation)
    if name is None:
        return "No test samples were evaluated."
    r = evaluation.sets[name]
    mlp, rigid = r.summary("mlp"), r.summary("rigid")
    d = r.deformation()
    n_markers = len(evaluation.model_summary.get("markers", []))
    text = (f"On {r.indices.size} {set_title(name)} samples (peak displacement median {fmt_mm(d['max_displacement_median'])}, "
            f"{fmt_share(d['nonrigid_share_median'])} of it not rigid), the learned model's worst vertex is "
            f"{fmt_mm(mlp.offset_max)} off on average")
    if not _bad(rigid.offset_max):
        gain = r.gain_over_rigid
        if not _bad(gain) and gain < 1.0:
            text += f", {fmt_ratio(1.0 / gain)} worse than rigid registration from the same {n_markers} markers"
        else:
            text += f", {fmt_ratio(gain)} better than rigid registration from the same {n_markers} markers"
    t_mlp, t_rigid = r.target_summary("mlp"), r.target_summary("rigid")
    if t_mlp is not None:
        text += f"; at the targets it corrects {fmt_share(t_mlp.share_corrected_mean)} of the displacement"
        if t_rigid is not None and not _bad(t_rigid.share_corrected_mean):
            text += f" (rigid registration {fmt_share(t_rigid.share_corrected_mean)})"
    text += "."
    if trust is not None and trust.get("sets"):
        t = trust["sets"].get("test1") or next(iter(trust["sets"].values()))
        alarm = (f"the alarm fires on {fmt_share(t['alarm_rate'])} of these samples" if t.get("alarm_on", True) else
                 "its alarm is off (too few calibration samples)")
        text += f" Its 90 % error bounds cover {fmt_share(t['coverage_0.9'])} of vertices and {alarm}."
        t2 = _failing_test2(trust["sets"])
        if t2 is not None:
            text += (f" Under force fields unlike the training's (test-2) they cover only {fmt_share(t2['coverage_0.9'])}"
                     f" and the alarm fires on {fmt_share(t2['alarm_rate'])}: there neither is to be trusted.")
    elif trust is not None:
        text += " It has no calibrated error bounds or alarm."
    return text


def html_table(head: list[str], rows: list[list[str]]) -> str:
    """An HTML table of text cells (escaped)."""
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def beta_table(head: list[str], rows: list[list[str]]) -> str:
    """:func:`html_table` of the sets, with the per-β rows (a 'β' in the first cell) folded away."""
    main, per_beta = [r for r in rows if "β" not in r[0]], [r for r in rows if "β" in r[0]]
    out = html_table(head, main)
    if per_beta:
        out += f"<details><summary>test-2 per β ({len(per_beta)} rows)</summary>{html_table(head, per_beta)}</details>"
    return out
