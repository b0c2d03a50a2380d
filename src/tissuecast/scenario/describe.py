"""A scenario's summary (:meth:`~tissuecast.scenario.Scenario.summary`) in words, for reports.

:func:`paper_summary` is the summary of the paper's set-up (pins and LBO forces), which data
sets and models made before scenarios were recorded mean; :func:`scenario_lines` turns a
summary into ``(what, description)`` rows (supports, loads, materials); :func:`scenario_text`
joins them into one line.
"""

from __future__ import annotations

from .parameters import LOG_SCALE

__all__ = ["paper_summary", "scenario_lines", "scenario_text"]


def paper_summary(n_pins: int) -> dict:
    """The summary of the paper's set-up: ``n_pins`` pinned vertices, LBO forces, nothing else."""
    return {"name": "paper", "pins": int(n_pins), "attached_vertices": 0, "attached_rule": "none", "lbo_forces": True}


def _range(values) -> str:
    lo, hi = (float(v) for v in values)
    return f"{lo:g} mm" if lo == hi else f"{lo:g}-{hi:g} mm"


def _supports(s: dict) -> str:
    parts = []
    if s.get("pins"):
        parts.append(f"{s['pins']} pinned vertices")
    if s.get("attached_vertices"):
        parts.append(f"attached region of {s['attached_vertices']} surface vertices (rule {s.get('attached_rule')})")
    sp = s.get("springs")
    if sp:
        kn, kt = sp["normal_stiffness_N_per_mm3"], sp["tangential_stiffness_N_per_mm3"]
        k = f"k = {kn:g} N/mm^3" if kn == kt else f"k_n = {kn:g}, k_t = {kt:g} N/mm^3"
        parts.append(f"elastic support on {sp['region_vertices']} surface vertices (rule {sp['rule']}, {k})")
    return "; ".join(parts) or "none"


def _loads(s: dict) -> str:
    parts = ["LBO surface forces"] if s.get("lbo_forces", True) else []
    g = s.get("gravity")
    if g:
        parts.append(f"gravity change (surgery within {g['cone_angle_degrees']:g} deg of "
                     f"{[float(v) for v in g['surgery_direction']]}, imaged along {[float(v) for v in g['imaging_direction']]})")
    i = s.get("indentation")
    if i:
        rule = i.get("access_rule", "surface")  # stores made before the access region have none
        where = ("the whole outer surface" if rule == "surface"
                 else f"the access region: {i['access_vertices']} surface vertices, rule {rule}")
        share = f", in {100 * i['probability']:g} % of the samples" if "probability" in i else ""
        parts.append(f"one indentation (patch radius {i['radius_mm']:g} mm, depth {_range(i['depth_mm'])}, "
                     f"slide {_range(i['slide_mm'])}, centres in {where}{share})")
    for inst in s.get("instruments", []):
        parts.append(f"tracked instrument {inst['name']!r} (the {inst['load']}; its pose a model input)")
    return "; ".join(parts) or "none"


#: ``[scenario.uncertain]`` keys in words, and whether the range is a factor.
_UNCERTAIN_WORDS = {"youngs_modulus": ("E", True), "poisson_ratio": ("nu", False),
                    "region_youngs_modulus": ("each region's E", True), "density": ("density", True),
                    "spring_normal": ("springs' normal stiffness", True),
                    "spring_tangential": ("springs' tangential stiffness", True),
                    "attached_margin": ("attached margin", False)}


def _uncertain(u: dict) -> str:
    arcsine = set(u.get("arcsine", ()))
    parts = []
    for key, (words, factor) in _UNCERTAIN_WORDS.items():
        if u.get(key):
            lo, hi = (float(v) for v in u[key])
            span = f"{lo:g} to {hi:g} mm" if key == "attached_margin" else f"x{lo:g}-{hi:g}" if factor else f"{lo:g}-{hi:g}"
            log = key in LOG_SCALE
            law = ("arcsine in log" if log else "arcsine") if key in arcsine else ("log-uniform" if log else "uniform")
            parts.append(f"{words} {span} ({law})")
    text = "drawn per sample: " + ", ".join(parts)
    if u.get("measured"):
        text += f"; measured (model inputs): {', '.join(u['measured'])}"
    if u.get("nominal_share"):
        text += f"; {100 * float(u['nominal_share']):g} % of the samples nominal"
    return text


def scenario_lines(summary: dict | None) -> list[tuple[str, str]]:
    """``[("scenario", name), ("supports", ...), ("loads", ...)]`` and, with material regions,
    ``("materials", ...)``, with uncertain parameters ``("uncertain", ...)`` (their ranges and
    laws); a single ``("scenario", "not recorded")`` row for None."""
    if not summary:
        return [("scenario", "not recorded")]
    rows = [("scenario", str(summary.get("name", "?"))), ("supports", _supports(summary)), ("loads", _loads(summary))]
    mats = summary.get("materials")
    if mats:
        rows.append(("materials", "; ".join(f"{name}: E = {m['youngs_modulus']:.4g} MPa, nu = {m['poisson_ratio']:.3g}"
                                            for name, m in mats.items())))
    if summary.get("uncertain"):
        rows.append(("uncertain", _uncertain(summary["uncertain"])))
    return rows


def scenario_text(summary: dict | None) -> str:
    """:func:`scenario_lines` as one line: ``name: supports ...; loads ...``."""
    rows = dict(scenario_lines(summary))
    if "supports" not in rows:
        return rows["scenario"]
    text = f"{rows['scenario']} - supports: {rows['supports']} - loads: {rows['loads']}"
    return text + (f" - materials: {rows['materials']}" if "materials" in rows else "")
