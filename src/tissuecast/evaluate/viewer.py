"""The report's interactive 3D view: true and predicted deformation side by side, in the browser.

A small hand-written WebGL viewer (``assets/viewer.js``, no third-party code) is copied into
the report folder with its data (``viewer_data.js``: a script that sets
``window.TISSUECAST_VIEW``, so the page also works from ``file://`` with no server and no
network). The data holds the outer surface (undeformed LPS mm, the surface's own vertex
numbering), the markers and the targets, and for each shown sample the true (FEM) and
predicted displacement of the surface vertices, markers and targets (mm, rounded to 1 µm).
"""

from __future__ import annotations

import html
import json
import shutil
from importlib import resources
from pathlib import Path

import numpy as np

from .evaluation import METHOD_LABELS, PREDICTORS, auxiliary_values, method_fields

__all__ = ["pick_samples", "viewer_payload", "write_viewer", "VIEWER_SAMPLES", "PICKS"]

#: Samples the viewer shows at most (each adds 4 fields of the surface vertices to the page).
VIEWER_SAMPLES = 5
#: Which samples the report shows in 3D, in order: (split, "median" | "worst").
PICKS = (("test1", "median"), ("test1", "worst"), ("test2", "worst"), ("test2", "median"), ("valid", "worst"))
_DECIMALS = 3


def pick_samples(evaluation, count: int) -> list[tuple[str, int, str]]:
    """Up to ``count`` samples to show: ``[(label, sample index, file stem)]`` in :data:`PICKS` order
    (the median and the worst of each set by the MLP's Offset_max)."""
    out = []
    for name, pick in PICKS:
        r = evaluation.sets.get(name)
        if r is None or not r.indices.size:
            continue
        k = int(np.argmax(r.mlp_max)) if pick == "worst" else int(np.argsort(r.mlp_max)[r.indices.size // 2])
        label = (f"{name} {pick} error (sample {int(r.indices[k])}"
                 + (f", β={r.beta[k]:g})" if np.isfinite(r.beta[k]) else ")"))
        out.append((label, int(r.indices[k]), f"{name}_{pick}"))
    return out[:count]


def _flat(a: np.ndarray) -> list:
    return np.round(np.asarray(a, dtype=np.float64), _DECIMALS).ravel().tolist()


def viewer_payload(model, dataset, evaluation, count: int = VIEWER_SAMPLES) -> dict:
    """The viewer's data (plain JSON types): surface, markers, targets and up to ``count`` samples."""
    mesh = model.mesh
    tri = np.asarray(mesh.surface_triangles, dtype=np.int64)
    surface, local = np.unique(tri, return_inverse=True)
    targets = evaluation.targets
    samples = []
    aux = auxiliary_values(model, dataset)
    for label, idx, _ in pick_samples(evaluation, count):
        bench = np.asarray(dataset.displacements[idx], dtype=np.float64)[None]
        fields = method_fields(model, model.marker_displacements(bench), auxiliary=None if aux is None else aux[[idx]])
        fields = {m: f for m, f in fields.items() if f is not None}
        samples.append({
            "label": label,
            "true": _flat(bench[0, surface]),
            "markers": _flat(bench[0, model.markers]),
            "methods": {m: _flat(f[0, surface]) for m, f in fields.items()},
            "targets_true": _flat(targets.displacements(bench)[0]) if targets is not None else [],
            "targets": {m: _flat(targets.displacements(f)[0]) if targets is not None else [] for m, f in fields.items()},
        })
    methods = [m for m in PREDICTORS if samples and m in samples[0]["methods"]]
    return {
        "units": "mm", "frame": "LPS",
        "points": _flat(mesh.points[surface]),
        "triangles": local.reshape(-1).astype(int).tolist(),
        "markers": _flat(mesh.points[model.markers]),
        "targets": _flat(targets.positions) if targets is not None else [],
        "target_labels": list(targets.labels) if targets is not None else [],
        "methods": methods,
        "method_labels": {m: METHOD_LABELS[m] for m in methods},
        "samples": samples,
    }


_CONTROLS = """<div class='tc-controls'>
<label>sample <select data-control='sample'></select></label>
<label>prediction <select data-control='method'></select></label>
<label>displacement <input data-control='scale' type='range' min='0' max='5' step='0.5' value='1'>
<span data-control='scale-value'></span></label>
<label><input data-control='outline' type='checkbox' checked> undeformed outline</label>
<label><input data-control='inside' type='checkbox'> see-through: targets (blue)</label>
</div>"""


def _bar(side: str, stops: str, what: str) -> str:
    return (f"<div class='tc-bar'><span>0</span><span class='tc-ramp' style='background:linear-gradient(to right,{stops})'>"
            f"</span><span data-control='max-{side}'></span> <small>{html.escape(what)}</small></div>")


_VIRIDIS = "#440154,#3e4989,#26828e,#35b779,#b5de2b,#fde725"
_INFERNO = "#000004,#4a0c6b,#a52c60,#ed6925,#f7d13d,#fcffa4"


def write_viewer(folder: Path, model, dataset, evaluation, count: int = VIEWER_SAMPLES) -> str:
    """Write ``viewer.js`` and ``viewer_data.js`` into the report folder; return the section's HTML."""
    folder = Path(folder)
    payload = viewer_payload(model, dataset, evaluation, count)
    if not payload["samples"]:
        return ""
    source = resources.files("tissuecast.evaluate").joinpath("assets").joinpath("viewer.js")
    with resources.as_file(source) as path:
        shutil.copyfile(path, folder / "viewer.js")
    (folder / "viewer_data.js").write_text("window.TISSUECAST_VIEW = " + json.dumps(payload, separators=(",", ":")) + ";\n",
                                           encoding="utf-8")
    panels = (f"<div class='tc-panels'><div><div class='tc-title' data-control='title-left'></div>"
              f"{_bar('left', _VIRIDIS, 'true displacement')}</div>"
              f"<div><div class='tc-title' data-control='title-right'></div>"
              f"{_bar('right', _INFERNO, 'vertex error')}</div></div>")
    return ("<section id='tc-viewer' class='tc-viewer'><h2>The deformation in 3D</h2>"
            "<p class='tc-note'>Left: the true (FEM) deformed surface, coloured by displacement; right: the prediction from "
            "the markers (red), coloured by its error. Drag to rotate, wheel to zoom, double-click to reset; the "
            "displacement slider exaggerates the motion.</p>"
            f"{_CONTROLS}{panels}<canvas class='tc-canvas' role='img' aria-label='3D view: left the true (FEM) "
            "deformed surface coloured by displacement, right the predicted one coloured by its error; the samples "
            "and their figures are in the tables and the static renders'></canvas><p class='tc-message' hidden></p>"
            "<script src='viewer_data.js'></script><script src='viewer.js'></script></section>")
