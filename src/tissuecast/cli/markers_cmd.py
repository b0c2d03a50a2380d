"""``tissuecast markers MESH``: choose fiducial markers and fixed vertices, and show them.

Writes ``PREFIX.csv`` and ``PREFIX.json`` (0-based ids, coordinates in mm, role, the
parameters), ``PREFIX.vtu`` (the points as VTK vertices with ``role`` 1 = marker,
2 = fixed, ``vertex_id`` and ``order`` arrays; open it in ParaView/Slicer next to the mesh),
``PREFIX.mrk.json`` (3D Slicer markups: point lists ``FiducialMarkers`` and
``FixedVertices``, LPS mm in the mesh's frame; drag it into Slicer next to the scan) and, with
``--png``, ``PREFIX.png`` (the surface, markers red, fixed vertices blue).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from ..evaluate import json_output
from .. import __version__
from ..config import FIXED_RULES, MarkerConfig, with_overrides
from ..errors import require
from ..markers import write_markers_markups
from ..mesh import TetMesh
from ..mesh.io import UNITS, write_point_set
from .mesh_cmd import PHANTOM_WORD, load_mesh_argument

ROLE_CODES = {"marker": 1, "fixed": 2}


def register(sub) -> None:
    d = MarkerConfig()
    p = sub.add_parser(
        "markers",
        help="choose fiducial markers (revised k-center) and fixed vertices",
        description="Vertex ids are 0-based (the paper's 1-based vertex 97 is 96 here). Lengths in mm. "
        "Options override the [markers] section of --config (defaults: the paper's values). "
        "To plan markers from a simulated data set instead: tissuecast markers plan STORE --count N.",
    )
    p.add_argument("mesh", nargs="?", help=f"mesh file, or '{PHANTOM_WORD}' (default: mesh.path of the config, else the phantom)")
    p.add_argument("--config", metavar="TOML",
                   help="config file or a packaged preset (its [mesh] and [markers] sections, and [scenario]'s pins and "
                        "attached region, are used)")
    p.add_argument("--units", choices=sorted(UNITS), help="length unit of the mesh file (default mm)")
    p.add_argument("--mesh-size", type=float, default=None, metavar="MM", help="edge length when MESH is a surface")
    p.add_argument("--count", type=int, help=f"number of markers n_d (default {d.count})")
    p.add_argument("--start", type=int, help=f"0-based start vertex v0 (default {d.start})")
    p.add_argument("--min-distance", type=float, metavar="MM", help=f"d_min in mm (default {d.min_distance:g})")
    p.add_argument("--ids", type=int, nargs="+", metavar="ID", help="use these 0-based marker ids instead of choosing")
    p.add_argument("--fixed-count", type=int, help=f"number of fixed vertices (default {d.fixed_count})")
    p.add_argument("--fixed-rule", choices=FIXED_RULES,
                   help=f"fixed-vertex placement (default {d.fixed_rule}): compact = a small pinned triangle deep "
                   "inside, the body swings about it; spread = as far apart as possible")
    p.add_argument("--fixed-spacing", type=float, metavar="MM",
                   help=f"smallest distance between compact fixed vertices in mm (default {d.fixed_spacing:g})")
    p.add_argument("--fixed-ids", type=int, nargs="+", metavar="ID", help="use these 0-based fixed vertex ids")
    p.add_argument("--out", default="markers", metavar="PREFIX", help="output prefix (default 'markers')")
    p.add_argument("--png", action="store_true", help="also render PREFIX.png (needs pyvista, extra 'viz')")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..app.configuration import load_run_config

    cfg = load_run_config(args.config)
    given = {"count": args.count, "start": args.start, "min_distance": args.min_distance, "ids": args.ids,
             "fixed_count": args.fixed_count, "fixed_ids": args.fixed_ids, "fixed_rule": args.fixed_rule,
             "fixed_spacing": args.fixed_spacing}
    cfg = with_overrides(cfg, markers={k: v for k, v in given.items() if v is not None})
    mc = cfg.markers
    mesh_name = args.mesh or cfg.mesh.path or PHANTOM_WORD
    if not args.mesh and cfg.mesh.path:
        from ..mesh.source import check_mesh_path

        check_mesh_path(cfg.mesh.path)
    units = args.units or cfg.mesh.units
    mesh = load_mesh_argument(mesh_name, units, args.mesh_size or cfg.mesh.surface_mesh_size, cfg.mesh)
    from ..mesh.tags import mesh_file_tags
    from ..scenario import scenario_markers

    markers, fixed = scenario_markers(mesh, cfg, mesh_file_tags(None if mesh_name == PHANTOM_WORD else mesh_name))
    params = {
        "mesh": mesh_name,
        "units": units,
        "count": len(markers),
        "start": int(markers[0]),
        "min_distance_mm": mc.min_distance,
        "user_given_markers": bool(mc.ids),
        "fixed_count": len(fixed),
        "fixed_depth_fraction": mc.fixed_depth_fraction,
        "fixed_rule": mc.fixed_rule,
        "fixed_spacing_mm": mc.fixed_spacing,
        "user_given_fixed": bool(mc.fixed_ids),
    }
    prefix = Path(args.out)
    if prefix.parent != Path("."):
        prefix.parent.mkdir(parents=True, exist_ok=True)
    surface = set(mesh.surface_vertices.tolist())
    print(f"mesh {mesh_name}: {mesh.n_vertices} vertices; ids and marker numbers are 0-based (vertex ids: add 1 for the "
          "paper / Abaqus; marker k is M<k> in the markups file, Marker<k> over OpenIGTLink)")
    print(f"{'role':7s} {'#':>2s} {'id':>6s} {'x (mm)':>9s} {'y (mm)':>9s} {'z (mm)':>9s}  where")
    for role, k, i, (x, y, z) in _rows(mesh, markers, fixed):
        where = "surface" if i in surface else "interior"
        print(f"{role:7s} {k:2d} {i:6d} {x:9.3f} {y:9.3f} {z:9.3f}  {where}")
    inside = [k for k, i in enumerate(markers) if int(i) not in surface]
    if inside:
        print(f"note: marker(s) {inside} are interior vertices: an optical tracker cannot see them (ultrasound or CT "
              "can); `tissuecast markers plan STORE` chooses surface markers from the simulations (as a run does "
              "where the config plans them), --ids gives your own")
    if mc.rule == "planned" and not mc.ids:
        print("note: markers.rule = 'planned': these are the k-center markers the data set records, not the ones to "
              "track; the model's markers are planned from the simulations when it is trained: track the points of "
              "MODEL/markers.mrk.json (its plan in MODEL/markers_plan.json), or plan them now with "
              "`tissuecast markers plan STORE`")
    written = [_write_csv(prefix, mesh, markers, fixed, surface), _write_json(prefix, mesh, markers, fixed, params)]
    written.append(_write_vtu(prefix, mesh, markers, fixed))
    written.append(write_markers_markups(prefix.with_name(prefix.name + ".mrk.json"), mesh, markers, fixed))
    if args.png:
        written.append(render_markers_png(prefix.with_name(prefix.name + ".png"), mesh, markers, fixed))
    for path in written:
        print(f"wrote {path}")
    return 0


def _rows(mesh: TetMesh, markers: np.ndarray, fixed: np.ndarray):
    for role, ids in (("marker", markers), ("fixed", fixed)):
        for k, i in enumerate(ids):
            yield role, k, int(i), mesh.points[i]


def _write_csv(prefix: Path, mesh, markers, fixed, surface) -> Path:
    path = prefix.with_name(prefix.name + ".csv")
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["role", "order", "vertex_id_0based", "x_mm", "y_mm", "z_mm", "on_surface"])
        for role, k, i, p in _rows(mesh, markers, fixed):
            w.writerow([role, k, i, *(f"{v:.6f}" for v in p), int(i in surface)])
    return path


def _write_json(prefix: Path, mesh, markers, fixed, params) -> Path:
    path = prefix.with_name(prefix.name + ".json")
    doc = {
        "tissuecast_version": __version__,
        "ids_are_0_based": True,
        "units": "mm",
        "mesh_fingerprint": mesh.fingerprint(),
        "parameters": params,
        "markers": {"ids": markers.tolist(), "coordinates": mesh.points[markers].tolist()},
        "fixed": {"ids": fixed.tolist(), "coordinates": mesh.points[fixed].tolist()},
    }
    path.write_text(json_output.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path


def _write_vtu(prefix: Path, mesh, markers, fixed) -> Path:
    ids = np.r_[markers, fixed].astype(np.int64)
    role = np.r_[np.full(len(markers), ROLE_CODES["marker"]), np.full(len(fixed), ROLE_CODES["fixed"])]
    order = np.r_[np.arange(len(markers)), np.arange(len(fixed))]
    data = {"role": role.astype(np.int32), "vertex_id": ids, "order": order.astype(np.int32)}
    return write_point_set(prefix.with_name(prefix.name + ".vtu"), mesh.points[ids], data)


def render_markers_png(path: Path, mesh: TetMesh, markers: np.ndarray, fixed: np.ndarray, size=(1200, 900)) -> Path:
    """Render the semi-transparent surface with markers (red) and fixed vertices (blue).

    Args:
        path: output PNG.
        mesh: the mesh (mm).
        markers: (k,) int 0-based marker ids, labelled M0.. in pick order.
        fixed: (f,) int 0-based fixed vertex ids, labelled F0...
    """
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    pv = require("pyvista", "viz", "Rendering the marker picture")
    pv.OFF_SCREEN = True
    tri = mesh.surface_triangles
    surf = pv.PolyData(mesh.points, np.c_[np.full(len(tri), 3), tri].ravel())
    radius = 0.015 * float(np.linalg.norm(mesh.extent))
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.set_background("white")
    plotter.add_mesh(surf, color="tan", opacity=0.3, show_edges=True, edge_color="gray", line_width=0.5)
    for ids, color, tag in ((markers, "red", "M"), (fixed, "royalblue", "F")):
        for i in ids:
            plotter.add_mesh(pv.Sphere(radius=radius, center=mesh.points[i]), color=color)
        if len(ids):
            labels = [f"{tag}{k} ({int(i)})" for k, i in enumerate(ids)]
            plotter.add_point_labels(mesh.points[ids], labels, font_size=14, text_color=color,
                                     shape_opacity=0.6, always_visible=True, show_points=False)
    plotter.add_legend([("fiducial markers M (0-based id)", "red"), ("fixed vertices F", "royalblue")],
                       bcolor=None, loc="upper left", size=(0.42, 0.1))
    plotter.view_vector((1.0, 0.5, 0.35), viewup=(0.0, 0.0, 1.0))
    plotter.add_axes()
    plotter.screenshot(str(path))
    plotter.close()
    return Path(path)
