"""``tissuecast predict MODEL --markers FILE``: displacement field from tracked markers.

Input (mm): CSV with one marker per row (x, y, z; n_d rows per sample) or one sample per row
(3 n_d values), an optional header line; or JSON ``{"displacements": [...]}`` /
``{"positions": [...]}`` / a bare nested list; or 3D Slicer markups (.mrk.json, .fcsv):
marker positions in model marker order, converted from RAS when the file says so (one
point list, or the one named FiducialMarkers; a point without a defined position is an
untracked marker). Empty cells, ``nan`` or ``null`` for all three coordinates of a marker
mark it as not tracked (models trained with marker_dropout > 0).
Output: .vtu (undeformed mesh + displacement point data; one file per sample for batches),
.vtk (deformed mesh) or .vtp (deformed outer surface) as 3D Slicer models in LPS with
``displacement_mm`` point data, .csv (sample, vertex, ux_mm, uy_mm, uz_mm[, uncertainty_mm][,
error_bound_mm][, alarm_raised]) or .json (LPS mm: ``displacement_mm``, ``uncertainty_mm``,
``error_bound_mm``, ``error_bound_coverage``, ``alarms``). Vertex ids are 0-based. Marker input
no simulation could have produced (a marker not a finite number, displaced far beyond its
largest simulated displacement, or markers at distances the body cannot take) is refused with
one error line naming the marker, exit status 2. With a calibrated model (surrogate.calibration
'split', the default, or 'cross-validation') every vertex gets its conformal error bound
(``error_bound_mm`` point data / column: the error is below it with probability
--coverage) and each sample's out-of-distribution alarm is printed.
--targets-out writes where the targets (the model config's [evaluate.targets], or the
points of --targets) are predicted to be: Slicer markups .mrk.json (LPS, one point list per
sample) or CSV.
A model trained with tracked instruments ([[scenario.instruments]]) reads their poses from
--instrument FILE (JSON, model frame LPS mm: {"retractor": {"tip": [x, y, z], "direction":
[dx, dy, dz]}}, or {"transform": 4x4}, {"contact": false}, null; see
tissuecast.cli.predict_inputs); an instrument not given is not tracked and the model predicts
from the markers only. Measured parameters come as --parameter NAME=VALUE.
--physics STORE solves each sample through the data set's simulator instead (the physics
inverse, tissuecast.cli.predict_physics: seconds to minutes a frame, no error bounds; every
instrument's pose needed, --gravity the surgery's gravity direction).
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

from ..evaluate import json_output
from .help_examples import with_examples


#: ``--help``'s examples: (command line, what it does).
EXAMPLES = (
    ("tissuecast predict runs/quick/model --markers displacements.csv --out field.vtu",
     "marker displacements (mm, LPS, one row per sample) -> the field as a VTU for ParaView"),
    ("tissuecast predict runs/quick/model --markers tracked.mrk.json --out field.vtu --targets-out targets.mrk.json",
     "marker positions from 3D Slicer markups; the targets' predicted positions back as markups"),
    ("tissuecast predict runs/embedded/model --markers positions.csv --positions --instrument retractor.json --out f.json",
     "tracked positions and the retractor's pose; JSON with the field, bounds and alarms"),
)


def register(sub) -> None:
    p = sub.add_parser("predict", help="predict the displacement field from marker displacements or positions",
                       description=__doc__.split("\n\n", 1)[1], **with_examples(*EXAMPLES))
    p.add_argument("model", help="model folder")
    p.add_argument("--markers", required=True,
                   help="CSV or JSON file of marker displacements (or positions), mm; "
                        "or Slicer markups .mrk.json/.fcsv (positions)")
    p.add_argument("--positions", action="store_true",
                   help="the file holds tracked marker positions (mm, model frame); reference positions are subtracted")
    p.add_argument("--out", help="output file .vtu, .vtk, .vtp, .csv or .json (default: print a summary only)")
    p.add_argument("--targets-out", metavar="FILE",
                   help="write the targets' predicted positions: Slicer markups .mrk.json (LPS) or .csv")
    p.add_argument("--targets", metavar="FILE",
                   help="target points for --targets-out: CSV (x, y, z or label, x, y, z; LPS mm) or Slicer markups "
                        "(.mrk.json, .fcsv); default the model config's [evaluate.targets]")
    p.add_argument("--uncertainty", action="store_true", help="add the ensemble's per-vertex uncertainty (ensemble >= 2)")
    p.add_argument("--method", choices=("mlp", "rigid", "ridge"), default="mlp",
                   help="mlp: the learned model (default); rigid: rigid registration from the markers (the baseline "
                        "navigation systems use; a fallback); ridge: the paper's ridge baseline")
    p.add_argument("--ridge", action="store_const", const="ridge", dest="method", help="same as --method ridge")
    p.add_argument("--coverage", type=float, metavar="C",
                   help="nominal coverage of the per-vertex error bounds, in (0, 1) (default: the model's surrogate.coverage)")
    p.add_argument("--instrument", metavar="FILE",
                   help="JSON of the tracked instruments' poses (model frame LPS, mm; 'frame': 'RAS' for Slicer's): "
                        "{name: {tip, direction} | {transform} | {contact: false} | null}, or a list with one per sample")
    p.add_argument("--parameter", action="append", metavar="NAME=VALUE",
                   help="a measured parameter of the model (scenario.uncertain.measured): a factor on the nominal value "
                   "for youngs_modulus, spring_* and density (1 = nominal), the ratio itself for poisson_ratio, mm for "
                   "attached_margin; e.g. youngs_modulus=1.3")
    p.add_argument("--false-alarm", type=float, metavar="RATE",
                   help="false-alarm rate of the out-of-distribution alarm, in (0, 1) "
                        "(default: the model's surrogate.false_alarm_rate)")
    p.add_argument("--physics", metavar="STORE",
                   help="solve for the field through the data set's simulator (the store the model was trained on) "
                        "instead of the learned model: the loads and unknown parameters that put the markers where "
                        "they were tracked; seconds to minutes a sample")
    p.add_argument("--gravity", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="with --physics: the direction of gravity in surgery, model frame (LPS); default the "
                        "scenario's planned scenario.gravity.surgery_direction")
    p.add_argument("--noise", type=float, metavar="MM",
                   help="with --physics: standard deviation of a tracked marker coordinate, mm (default 0.05)")
    p.add_argument("--time-limit", type=float, metavar="S",
                   help="with --physics: wall-clock seconds a sample's search may take (default 600; 0: none); past "
                        "it the best estimate reached is written (the first held set always converges); without a limit the "
                        "answer is the same on every machine")
    p.add_argument("--attached-margin", type=float, metavar="MM",
                   help="with --physics: the attached region's margin where it is known (measured in surgery), mm "
                        "along the surface from the planned region, within the drawn range; its held set alone is "
                        "solved, no search (seconds a sample instead of minutes); a margin 1.5 mm off does worse "
                        "than the search: give its uncertainty with --attached-margin-sd (docs/uncertainty.md)")
    p.add_argument("--attached-margin-sd", type=float, metavar="MM",
                   help="with --attached-margin: the measured margin's standard deviation, mm; the held sets within "
                        "reach are searched with the measurement as their prior instead of the one set given (a "
                        "margin known to about a millimetre: docs/uncertainty.md)")
    p.add_argument("--physics-estimate", choices=("mean", "likeliest"),
                   help="with --physics, where the attached margin is searched: the field written, the posterior mean "
                        "over the held sets finished (the default; a blend, the better with tracking noise) or the "
                        "likeliest held set's solution (one equilibrium of the simulator, the better with clean "
                        "markers; docs/uncertainty.md)")
    p.set_defaults(func=run)


def _cell(v: str) -> float:
    v = v.strip()
    return float("nan") if v == "" or v.lower() in ("nan", "null", "none") else float(v)


def read_markups_positions(path: Path, n_d: int) -> np.ndarray:
    """(1, n_d, 3) marker positions (LPS mm, NaN = untracked) from a Slicer .mrk.json/.fcsv file."""
    from ..errors import ModelError
    from ..slicer.markups import read_markups
    from ..markers import MARKERS_LIST

    lists = read_markups(path)
    if len(lists) > 1:
        named = [m for m in lists if m.name == MARKERS_LIST]
        if len(named) != 1:
            raise ModelError(f"{str(path)!r} holds {len(lists)} point lists ({', '.join(repr(m.name) for m in lists)}); "
                             f"keep one, or name the markers' list {MARKERS_LIST!r}")
        lists = named
    positions = lists[0].positions
    if len(positions) != n_d:
        raise ModelError(f"{str(path)!r}: point list {lists[0].name!r} has {len(positions)} points; this model needs its "
                         f"{n_d} markers, in model marker order")
    return positions[None]


def read_marker_file(path: Path, n_d: int) -> tuple[np.ndarray, bool | None]:
    """-> ((B, n_d, 3) float mm with NaN for untracked markers, positions flag from JSON or None)."""
    from ..errors import ModelError
    from ..slicer.markups import MARKUPS_SUFFIXES

    if not path.is_file():
        raise FileNotFoundError(f"marker file {str(path)!r} does not exist")
    if path.name.lower().endswith(MARKUPS_SUFFIXES):
        return read_markups_positions(path, n_d), True
    flag = None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ModelError(f"{str(path)!r} is not valid JSON: {exc}") from exc
        if isinstance(data, dict):
            keys = [k for k in ("displacements", "positions") if k in data]
            if len(keys) != 1:
                raise ModelError(f"{str(path)!r} must hold exactly one of 'displacements' or 'positions'")
            flag = keys[0] == "positions"
            data = data[keys[0]]
        try:
            arr = np.array(data, dtype=np.float64)  # null -> nan
        except (TypeError, ValueError) as exc:
            raise ModelError(f"{str(path)!r}: marker values must be numbers or null ({exc})") from exc
    else:
        rows = []
        with path.open(newline="") as fh:
            for i, row in enumerate(csv.reader(fh)):
                if not row or all(not c.strip() for c in row):
                    continue
                try:
                    rows.append([_cell(c) for c in row])
                except ValueError:
                    if i == 0 and not rows:
                        continue  # header
                    sep = next((f"{name}-separated" for mark, name in ((";", "semicolon"), ("\t", "tab"), (" ", "space"))
                                if len(row) == 1 and mark in row[0].strip()), "")
                    hint = f" (the line looks {sep}: save the CSV with commas between x, y and z)" if sep else ""
                    raise ModelError(f"{str(path)!r} line {i + 1}: non-numeric value in {row}{hint}") from None
        if not rows or len({len(r) for r in rows}) != 1:
            raise ModelError(f"{str(path)!r}: need rows of equal length (3 per marker, or 3 n_d = {3 * n_d} per sample)")
        arr = np.array(rows, dtype=np.float64)
    if arr.size % (3 * n_d):
        raise ModelError(f"{str(path)!r} holds {arr.size} values; this model needs a multiple of 3 n_d = {3 * n_d} "
                         f"(n_d = {n_d} markers, x y z each, mm)")
    return arr.reshape(-1, n_d, 3), flag


def _write(out: Path, model, u: np.ndarray, sigma: np.ndarray | None, bound: np.ndarray | None = None,
           notes: dict | None = None, alarms: list | None = None) -> list[Path]:
    """Write the fields ``u`` (B, n, 3) mm, with ``sigma`` and ``bound`` (B, n) mm where given, to
    ``out`` by its suffix; each sample's alarm (``alarms``, B :class:`~tissuecast.surrogate.trust.Alarm`)
    goes with it (a constant ``alarm_raised`` point array 0/1, an ``alarm`` column, a JSON list);
    ``notes`` (JSON-ready: e.g. the bounds' coverage) go into a JSON output beside them."""
    from ..errors import ModelError

    suf = out.suffix.lower()
    B = u.shape[0]
    raised = None if alarms is None else np.array([a.raised for a in alarms], dtype=np.float64)
    if suf in (".vtu", ".vtk", ".vtp"):
        from ..evaluate.render import write_vtu
        from ..slicer.models import write_model

        files = []
        for b in range(B):
            p = out if B == 1 else out.with_name(f"{out.stem}_{b:03d}{out.suffix}")
            extra = {"uncertainty_mm": sigma[b]} if sigma is not None else {}
            if bound is not None:
                extra["error_bound_mm"] = bound[b]
            if raised is not None:
                extra["alarm_raised"] = np.full(u.shape[1], raised[b])
            if suf == ".vtu":  # undeformed mesh + point data (ParaView's Warp By Vector)
                files.append(write_vtu(p, model.mesh, {"displacement_mm": u[b], **extra}))
            else:  # the deformed mesh (Slicer models)
                files.append(write_model(p, model.mesh, displacement=u[b], point_data=extra or None))
        return files
    if suf == ".csv":
        with out.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["sample", "vertex", "ux_mm", "uy_mm", "uz_mm"] + (["uncertainty_mm"] if sigma is not None else [])
                       + (["error_bound_mm"] if bound is not None else []) + (["alarm_raised"] if raised is not None else []))
            for b in range(B):
                tail = [int(raised[b])] if raised is not None else []
                for i in range(u.shape[1]):
                    w.writerow([b, i, *(f"{x:.6g}" for x in u[b, i])] + ([f"{sigma[b, i]:.6g}"] if sigma is not None else [])
                               + ([f"{bound[b, i]:.6g}"] if bound is not None else []) + tail)
        return [out]
    if suf == ".json":
        doc = {"units": "mm", "frame": "LPS", "vertex_ids": "0-based", "displacement_mm": u.tolist()}
        if sigma is not None:
            doc["uncertainty_mm"] = sigma.tolist()
        if bound is not None:
            doc["error_bound_mm"] = bound.tolist()
        if alarms is not None:
            doc["alarms"] = [{"raised": bool(a.raised), "text": a.text} for a in alarms]
        doc.update(notes or {})
        out.write_text(json_output.dumps(doc), encoding="utf-8")
        return [out]
    raise ModelError(f"unknown output format {out.suffix!r}; use .vtu, .vtk, .vtp, .csv or .json")


def run(args) -> int:
    from ..surrogate import DeformationModel

    if args.targets and not args.targets_out:
        from ..errors import ModelError

        raise ModelError("--targets chooses the points --targets-out writes; add --targets-out FILE (.mrk.json or .csv)")
    model = DeformationModel.load(args.model)
    d, flag = read_marker_file(Path(args.markers), model.n_markers)
    positions = args.positions or bool(flag)
    if positions:
        d = d - model.reference_marker_positions
    missing = np.isnan(d).all(axis=2)
    partial = np.isnan(d).any(axis=2) & ~missing
    if partial.any():
        from ..errors import ModelError

        b, j = np.argwhere(partial)[0]
        raise ModelError(f"sample {b}: marker {j} (input index {j}, vertex {int(model.markers[j])}) has only some "
                         "coordinates given; give x, y and z, or leave all three empty")
    if args.physics:
        return _run_physics(args, model, d, missing)
    if any(v is not None for v in (args.gravity, args.noise, args.time_limit, args.attached_margin,
                                   args.attached_margin_sd, args.physics_estimate)):
        from ..errors import ModelError

        raise ModelError("--gravity, --noise, --time-limit, --attached-margin(-sd) and --physics-estimate go with "
                         "--physics (the physics inverse); the learned model reads none of them")
    if not model.predictor(args.method).supports_missing_markers:
        missing[:] = False  # a lost marker: the input gate refuses it, naming the marker
    from .predict_inputs import auxiliary_inputs

    aux = auxiliary_inputs(model, args.instrument, args.parameter, d.shape[0])
    t = time.perf_counter()
    sigma = None
    miss = missing if missing.any() else None
    if args.uncertainty and args.method != "mlp":
        from ..errors import ModelError

        raise ModelError(f"--uncertainty comes from the MLP ensemble; drop it or use --method mlp (not {args.method})")
    if args.uncertainty:
        u, sigma = model.predict_with_uncertainty(d, missing=miss, auxiliary=aux)
    else:
        u = model.predict(d, missing=miss, method=args.method, auxiliary=aux)
    sec = time.perf_counter() - t
    bound, alarms = None, None
    if model.has_trust and args.method == "mlp" and miss is None:
        trusted = model.predict_trusted(d, coverage=args.coverage, false_alarm=args.false_alarm, auxiliary=aux)
        bound, alarms, coverage = trusted.error_bound, trusted.alarms, trusted.coverage
    elif args.coverage is not None or args.false_alarm is not None:
        from ..errors import ModelError

        raise ModelError("--coverage and --false-alarm need a calibrated model (trained with surrogate.calibration "
                         "'cross-validation' or 'split'), --method mlp and every marker tracked")
    for b in range(u.shape[0]):
        mag = np.linalg.norm(u[b], axis=1)
        extra = f", max uncertainty {sigma[b].max():.3f} mm" if sigma is not None else ""
        miss = f", missing markers {np.flatnonzero(missing[b]).tolist()}" if missing[b].any() else ""
        if bound is not None:
            extra += f", error bound ({100 * coverage:g} %) median {np.median(bound[b]):.3f} / max {bound[b].max():.3f} mm"
        print(f"sample {b}: max displacement {mag.max():.3f} mm at vertex {int(mag.argmax())}{extra}{miss}"
              f"{_instrument_note(model, aux, b)}")
        if alarms is not None and alarms[b].raised:
            print(f"sample {b}: ALARM: {alarms[b].text}")
    if bound is not None and not np.isfinite(bound).all():
        print(f"note: the bounds are infinite: {model.trusted_.n_calibration} calibration samples are too few "
              f"for {100 * coverage:g} % coverage; use a lower --coverage or re-train with surrogate.calibration = "
              "'cross-validation'")
    if alarms is not None and not np.isfinite(alarms[0].distance_threshold):
        print("note: the alarm is off: too few calibration samples for this false-alarm rate; use a larger "
              "--false-alarm or re-train with surrogate.calibration = 'cross-validation'")
    print(f"predicted {u.shape[0]} sample(s) (the input read as {model.n_markers} markers each) of {u.shape[1]} vertices "
          f"in {sec * 1e3:.2f} ms")
    notes = {"error_bound_coverage": coverage} if bound is not None else None
    _write_outputs(args, model, u, sigma, bound, args.method, notes, alarms)
    return 0


def _write_outputs(args, model, u, sigma, bound, method: str, notes: dict | None = None, alarms: list | None = None) -> None:
    if args.out:
        for f in _write(Path(args.out), model, u, sigma, bound, notes, alarms):
            print(f"wrote {f}")
    if args.targets_out:
        print(f"wrote {_write_targets(Path(args.targets_out), model, u, args.targets, method)}")


def _run_physics(args, model, d: np.ndarray, missing: np.ndarray) -> int:
    """``--physics``: every sample through the physics inverse (:mod:`.predict_physics`)."""
    from .predict_physics import TIME_LIMIT, check_physics_options, describe, misfit_warning, physics_fields, record

    if args.time_limit is None:
        args.time_limit = TIME_LIMIT
    check_physics_options(args)
    t = time.perf_counter()
    u, results, inverse = physics_fields(args, model, d, missing)
    for b, res in enumerate(results):
        mag = np.linalg.norm(u[b], axis=1)
        lost = f", missing markers {np.flatnonzero(missing[b]).tolist()}" if missing[b].any() else ""
        print(f"sample {b}: max displacement {mag.max():.3f} mm at vertex {int(mag.argmax())} (physics: "
              f"{describe(res, inverse.estimated)}){lost}")
        warning = misfit_warning(res, inverse)
        if warning:
            print(f"sample {b}: {warning}")
    print(f"solved {u.shape[0]} sample(s) of {u.shape[1]} vertices through the physics in {time.perf_counter() - t:.1f} s")
    _write_outputs(args, model, u, np.stack([res.spread for res in results]), None, "physics",
                   {"physics": [record(res, inverse) for res in results]})
    return 0


def _instrument_note(model, aux, b: int) -> str:
    """``", retractor: in contact, 3.1 mm deep"`` ... for sample b of a model with instruments."""
    notes = []
    for inst in model.auxiliary.instruments:
        pose = (aux or {}).get(inst.name)
        pose = pose[b] if isinstance(pose, list) else pose
        if pose is None:
            notes.append(f"{inst.name}: not tracked (markers only)")
        else:
            notes.append(f"{inst.name}: " + (f"in contact, {pose.depth:.2f} mm deep" if pose.contact else "away"))
    return "".join(f", {n}" for n in notes)


def _write_targets(path: Path, model, u: np.ndarray, points: str | None, method: str) -> Path:
    """The targets' predicted positions from the predicted fields u (B, n, 3) mm."""
    from ..evaluate.target_files import write_predicted_targets
    from ..evaluate.targets import model_targets

    targets = model_targets(model, points=points)
    return write_predicted_targets(path, targets, targets.displacements(u), method=method)
