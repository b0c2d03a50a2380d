"""``tissuecast mesh info|convert|phantom``: inspect, convert and export meshes."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from ..evaluate import json_output
from ..config import MeshConfig
from ..errors import MeshError
from ..mesh import TetMesh, phantom, read_mesh, write_mesh
from ..mesh.io import SURFACE_FORMATS, UNITS, VOLUME_FORMATS
from ..mesh.labelmap import label_map_format
from ..mesh.run_cost import paper_run_estimate
from ..mesh.source import mesh_from_config
from .mesh_image_cmd import add_parser as add_from_image_parser
from .mesh_output import mesh_summary, sizing_warnings

PHANTOM_WORD = "phantom"

log = logging.getLogger(__name__)


def load_mesh_argument(name: str, units: str = "mm", mesh_size: float | None = None, mesh_config=None,
                       max_vertices: int | None = None) -> TetMesh:
    """The mesh a CLI argument names: a mesh, surface or label-map file, or the word ``phantom``.

    A label map is meshed with the options of ``mesh_config`` (a MeshConfig; defaults if None);
    ``max_vertices`` meshes a label map or closed surface within that many vertices.
    """
    if name == PHANTOM_WORD:
        if max_vertices:
            raise MeshError("the built-in phantom is a fixed mesh; a vertex budget applies to closed surfaces and "
                            "label maps, which are meshed")
        return phantom()
    if label_map_format(name) is not None:
        mc = mesh_config or MeshConfig()
        if mesh_size:
            mc = dataclasses.replace(mc, surface_mesh_size=mesh_size)
        if max_vertices:
            mc = dataclasses.replace(mc, max_vertices=max_vertices)
        return mesh_from_config(mc, path=name)
    return read_mesh(name, units=units, mesh_size=mesh_size, max_vertices=max_vertices)


def _add_mesh_options(p, surface: bool = True) -> None:
    p.add_argument("--units", choices=sorted(UNITS), default="mm", help="length unit of the input file (converted to mm)")
    if surface:
        p.add_argument("--mesh-size", type=float, default=None, metavar="MM",
                       help="target edge length (mm) when the input is a closed surface "
                            f"(default {MeshConfig.surface_mesh_size:g})")


def register(sub) -> None:
    formats = " ".join(sorted(VOLUME_FORMATS) + sorted(SURFACE_FORMATS))
    p = sub.add_parser("mesh", help="inspect, convert or export tetrahedral meshes",
                       description=f"Mesh formats (by extension): {formats}. Vertex ids are 0-based.")
    msub = p.add_subparsers(dest="mesh_command", metavar="ACTION", required=True)
    info = msub.add_parser("info", help="counts, bounding box, volume, surface and quality statistics")
    info.add_argument("file", help=f"mesh file, or the word '{PHANTOM_WORD}' for the built-in phantom")
    _add_mesh_options(info)
    info.add_argument("--json", action="store_true", help="print the figures as JSON")
    info.set_defaults(func=run_info)
    conv = msub.add_parser("convert", help="convert between mesh formats (surfaces are tetrahedralised)")
    conv.add_argument("input", help=f"input mesh file, or '{PHANTOM_WORD}'")
    conv.add_argument("output", help="output file; its extension picks the format")
    _add_mesh_options(conv)
    conv.add_argument("--max-vertices", type=int, metavar="N",
                      help="a closed surface or label map is meshed with at most N vertices (the edge length searched; "
                           "--mesh-size unused)")
    conv.add_argument("--space-array", action="store_true",
                      help=".vtu output: add the SPACE=LPS string array 3D Slicer reads (meshio cannot read such files)")
    conv.set_defaults(func=run_convert)
    add_from_image_parser(msub)
    ph = msub.add_parser("phantom", help="write the built-in phantom to a file")
    ph.add_argument("output", help="output file (e.g. phantom.vtu, phantom.inp, phantom.node)")
    ph.set_defaults(func=run_phantom)


def run_info(args) -> int:
    from ..mesh.tags import mesh_file_tags

    mesh = load_mesh_argument(args.file, args.units, args.mesh_size)
    s = mesh_summary(mesh)
    tags = mesh_file_tags(None if args.file == PHANTOM_WORD else args.file)
    s["regions"] = tags.names()  # named regions scenario rules can use (tag = ..., materials.cell_data = ...)
    if args.json:
        print(json_output.dumps({"file": args.file, **s}, indent=2))
        return 0
    q = s["quality"]
    f3 = lambda v: " ".join(f"{x:9.3f}" for x in v)  # noqa: E731
    print(f"mesh               {args.file}" + (" (built-in)" if args.file == PHANTOM_WORD else ""))
    print(f"vertices           {s['vertices']}  ({s['surface_vertices']} on the surface, "
          f"{s['interior_vertices']} interior; ids 0-based)")
    print(f"tetrahedra         {s['tetrahedra']}  ({s['reoriented_tetrahedra']} re-oriented on load)")
    print(f"surface triangles  {s['surface_triangles']}")
    print(f"edges              {s['edges']}")
    print(f"bounding box (mm)  min {f3(s['bounding_box_mm'][0])}")
    print(f"                   max {f3(s['bounding_box_mm'][1])}")
    print(f"extent (mm)        {' x '.join(f'{x:.2f}' for x in s['extent_mm'])}")
    print(f"volume             {s['volume_mm3']:.2f} mm^3")
    print(f"surface area       {s['surface_area_mm2']:.2f} mm^2")
    print(f"radius ratio       min {q['radius_ratio_min']:.3f}  mean {q['radius_ratio_mean']:.3f}  (1 = regular tet)")
    print(f"edge ratio         max {q['edge_ratio_max']:.3f}")
    print(f"edge length (mm)   min {q['edge_length_min']:.3f}  mean {q['edge_length_mean']:.3f}  max {q['edge_length_max']:.3f}")
    print(f"tet volume (mm^3)  min {q['volume_min']:.4g}  max {q['volume_max']:.4g}")
    print(f"fingerprint        {s['fingerprint']}")
    print(f"named regions      {', '.join(s['regions']) or 'none'}  (point data, point/cell sets, cell data)")
    print(f"expected cost      {paper_run_estimate(mesh.n_vertices, s['edges']).text()}")
    return 0


def run_convert(args) -> int:
    mesh = load_mesh_argument(args.input, args.units, args.mesh_size, max_vertices=args.max_vertices)
    written = write_mesh(args.output, mesh, space_array=args.space_array)
    print(f"read {args.input}: {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra (mm)")
    remeshed = Path(args.input).suffix.lower() in SURFACE_FORMATS or label_map_format(args.input) is not None
    if remeshed and not args.max_vertices:
        size = args.mesh_size or MeshConfig.surface_mesh_size
        for text in sizing_warnings(mesh, {"size_mm": size, "max_vertices": None, "tolerance_mm": None,
                                           "attempts": []}):
            log.warning(text)
    print(f"expected cost: {paper_run_estimate(mesh.n_vertices, len(mesh.edges)).text()}")
    for path in written:
        print(f"wrote {path}")
    return 0


def run_phantom(args) -> int:
    mesh = phantom()
    written = write_mesh(args.output, mesh)
    ext = np.round(mesh.extent, 1)
    print(f"phantom: {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra, {ext[0]} x {ext[1]} x {ext[2]} mm")
    for path in written:
        print(f"wrote {path}")
    return 0
