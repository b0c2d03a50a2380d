"""``tissuecast markers plan STORE``: plan fiducial markers from a simulated data set.

Chooses marker vertices from how the tissue moved in the store's simulations ('train'
split selects, 'valid' scores; see :mod:`tissuecast.planning`), either ``--count N`` of them
or the fewest that reach ``--target-mm`` on validation. Writes ``PREFIX.json`` (the plan,
its error curve, 0-based ids), ``PREFIX.csv``, ``PREFIX.vtu`` and ``PREFIX.mrk.json`` (3D Slicer
markups, LPS: the markers ``M0``.. and the store's fixed vertices, like ``tissuecast markers``)
and with ``--png`` a picture. Use the ids for training with
``[markers] ids = [...]`` in the config.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ..evaluate import json_output
from .. import __version__
from ..errors import MarkerError
from ..planning.candidates import REGIONS
from ..planning.plan import MAX_COUNT
from ..planning.selection import EXCHANGE_ROUNDS, SHORTLIST


def register(sub) -> None:
    p = sub.add_parser("markers", help="choose fiducial markers; `markers plan STORE` plans them from a data set",
                       description="tissuecast markers plan STORE: " + __doc__.split("\n\n")[1])
    plans = p.add_subparsers(dest="markers_action", metavar="plan", required=True)
    q = plans.add_parser("plan", help="plan markers from a data-set store", description=__doc__.split("\n\n")[1])
    q.add_argument("store", help="data-set store written by `tissuecast simulate`")
    how = q.add_mutually_exclusive_group(required=True)
    how.add_argument("--count", type=int, help="number of markers")
    how.add_argument("--target-mm", type=float, metavar="MM",
                     help="the fewest markers whose validation mean Offset_max reaches this (mm)")
    q.add_argument("--max-count", type=int, default=MAX_COUNT,
                   help=f"largest count searched with --target-mm (default {MAX_COUNT})")
    q.add_argument("--region", choices=REGIONS, default="surface",
                   help="candidate vertices: surface (optical tracking, default), any (interior fiducials seen by "
                        "ultrasound allowed), interior")
    q.add_argument("--min-distance", type=float, metavar="MM",
                   help="minimum spacing of the markers (mm; default: the store's markers.min_distance, as a run plans)")
    q.add_argument("--allowed", metavar="FILE",
                   help="user mask: a file of allowed 0-based vertex ids (JSON list, or numbers separated by commas/whitespace)")
    q.add_argument("--shortlist", type=int, default=SHORTLIST, help=f"candidates scored per greedy step (default {SHORTLIST})")
    q.add_argument("--exchange-rounds", type=int, default=EXCHANGE_ROUNDS, metavar="N",
                   help=f"passes of the exchange refinement over the chosen markers (default {EXCHANGE_ROUNDS}; 0 = the greedy "
                        "path's first markers, nested across counts)")
    q.add_argument("--confirm", action="store_true",
                   help="train the network with the planned markers and report its validation error (with --target-mm "
                        "the network, not only the proxy, decides the count; ~1 training per count tried)")
    q.add_argument("--no-sentinel", dest="sentinel", action="store_false",
                   help="where the store draws the attached region's extent, do not make the last marker a sentinel "
                        "beyond the drawn range (the alarm's watch for tissue attached farther than simulated)")
    q.add_argument("--out", default="planned_markers", metavar="PREFIX", help="output prefix (default 'planned_markers')")
    q.add_argument("--png", action="store_true", help="also render PREFIX.png (needs pyvista, extra 'viz')")
    q.set_defaults(func=run)


def read_allowed(path: Path) -> np.ndarray:
    """0-based vertex ids from a JSON list or a text/CSV file of integers."""
    if not path.is_file():
        raise FileNotFoundError(f"allowed-vertex file {str(path)!r} does not exist")
    text = path.read_text(encoding="utf-8")
    try:
        values = json.loads(text) if path.suffix.lower() == ".json" else [int(t) for t in text.replace(",", " ").split()]
        ids = np.asarray(values, dtype=np.int64).ravel()
    except (ValueError, TypeError) as exc:
        raise MarkerError(f"{str(path)!r} must hold 0-based vertex ids (integers): {exc}") from exc
    if ids.size == 0:
        raise MarkerError(f"{str(path)!r} holds no vertex ids")
    return ids


def run(args) -> int:
    from ..dataset import open_dataset
    from ..planning import plan_markers

    ds = open_dataset(args.store)
    if args.min_distance is None:
        args.min_distance = ds.config.markers.min_distance
    allowed = read_allowed(Path(args.allowed)) if args.allowed else None

    def progress(k, chosen, score):
        print(f"  {k:2d} markers: proxy validation mean Offset_max {score:.3f} mm (added vertex {int(chosen[-1])})", flush=True)

    print(f"planning markers on {args.store} ({args.region} candidates, min spacing {args.min_distance:g} mm); "
          "ids are 0-based")
    plan = plan_markers(ds, args.count, target_mm=args.target_mm, max_count=args.max_count, region=args.region,
                        min_distance=args.min_distance, allowed=allowed, shortlist=args.shortlist, confirm=args.confirm,
                        exchange_rounds=args.exchange_rounds, sentinel=args.sentinel, on_step=progress)
    if plan.exchanged:
        print(f"  exchange refinement: {plan.exchanged} of {plan.count} markers replaced, proxy validation mean Offset_max "
              f"{plan.proxy_error:.3f} mm")
    for k, v in sorted(plan.mlp_errors.items()):
        print(f"  network with {k} planned markers: validation mean Offset_max {v:.3f} mm")
    if plan.sentinel >= 0:
        print(f"  sentinel: vertex {plan.sentinel}, the last marker, beyond the attached region's drawn range (it took at "
              f"least {100 * plan.sentinel_least:.0f} % of the markers' motion in every training sample; if it stands still "
              "in surgery the alarm says the tissue is attached farther than simulated)")
    if args.target_mm is not None:
        print(f"target {args.target_mm:g} mm {'reached' if plan.target_reached else 'NOT reached'} with {plan.count} markers")
    mesh = ds.mesh
    surface = set(np.asarray(mesh.surface_vertices).tolist())
    prefix = Path(args.out)
    if prefix.parent != Path("."):
        prefix.parent.mkdir(parents=True, exist_ok=True)
    written = [_write_json(prefix, ds, plan, args), _write_csv(prefix, mesh, plan.markers, surface, plan.sentinel)]
    from ..mesh.io import write_point_set

    ids = plan.markers
    written.append(write_point_set(prefix.with_name(prefix.name + ".vtu"), mesh.points[ids],
                                   {"vertex_id": ids.astype(np.int64), "order": np.arange(len(ids), dtype=np.int32)}))
    from ..markers import write_markers_markups
    from .markers_cmd import render_markers_png

    written.append(write_markers_markups(prefix.with_name(prefix.name + ".mrk.json"), mesh, ids, np.asarray(ds.fixed)))
    if args.png:
        written.append(render_markers_png(prefix.with_name(prefix.name + ".png"), mesh, ids, np.asarray(ds.fixed)))
    print(f"planned markers ({plan.count}): {ids.tolist()}")
    print(f"train with them: put `ids = {ids.tolist()}` in the [markers] section of the config")
    for path in written:
        print(f"wrote {path}")
    return 0


def _write_json(prefix: Path, ds, plan, args) -> Path:
    path = prefix.with_name(prefix.name + ".json")
    doc = {"tissuecast_version": __version__, "ids_are_0_based": True, "units": "mm", "dataset": str(ds.path),
           "mesh_fingerprint": ds.mesh.fingerprint(), "method": "QR-shortlisted greedy forward selection, then exchange "
           "refinement, on a quadratic proxy's validation mean Offset_max (train split selects, valid split scores)",
           "plan": plan.as_dict(), "coordinates": ds.mesh.points[plan.markers].tolist(),
           "config_snippet": {"markers": {"ids": plan.markers.tolist()}}}
    path.write_text(json_output.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path


def _write_csv(prefix: Path, mesh, ids, surface, sentinel: int = -1) -> Path:
    """The markers, one row each; the sentinel's role is ``sentinel`` (:mod:`tissuecast.planning.sentinel`)."""
    path = prefix.with_name(prefix.name + ".csv")
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["role", "order", "vertex_id_0based", "x_mm", "y_mm", "z_mm", "on_surface"])
        for k, i in enumerate(ids):
            role = "sentinel" if int(i) == sentinel else "marker"
            w.writerow([role, k, int(i), *(f"{v:.6f}" for v in mesh.points[i]), int(int(i) in surface)])
    return path
