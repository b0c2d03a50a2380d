"""``tissuecast mesh info|convert|phantom``: inspect, convert and export meshes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from ..config import MeshConfig
from ..mesh import TetMesh, phantom, read_mesh, write_mesh
from ..mesh.io import SURFACE_FORMATS, UNITS, VOLUME_FORMATS
from ..mesh.labelmap import LABEL_MAP_SUFFIXES, label_map_format
from ..mesh.source import mesh_from_config

PHANTOM_WORD = "phantom"


def load_mesh_argument(name: str, units: str = "mm", mesh_size: float | None = None, mesh_config=None) -> TetMesh:
    """The mesh a CLI argument names: a mesh, surface or label-map file, or the word ``phantom``.

    A label map is meshed with the options of ``mesh_config`` (a MeshConfig; defaults if None).
    """
    if name == PHANTOM_WORD:
        return phantom()
    if label_map_format(name) is not None:
        mc = mesh_config or MeshConfig()
        if mesh_size:
            mc = dataclasses.replace(mc, surface_mesh_size=mesh_size)
        return mesh_from_config(mc, path=name)
    return read_mesh(name, units=units, mesh_size=mesh_size)


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
    conv.set_defaults(func=run_convert)
    img = msub.add_parser(
        "from-image", help="tetrahedral mesh of one label of a segmented scan (label map or Slicer segmentation)",
        description="Reads " + " ".join(LABEL_MAP_SUFFIXES) + " (NIfTI with nibabel, NRRD and Slicer .seg.nrrd with "
        "slicerio), meshes one label by marching cubes, Taubin smoothing and gmsh, and reports the mesh quality and how "
        "closely it follows the voxels. Coordinates stay in the scan's physical frame, LPS mm: .vtu/.vtk/.vtp outputs "
        "say SPACE=LPS as 3D Slicer does, so the mesh overlays the scan in Slicer.")
    img.add_argument("scan", help="label map (.nii, .nii.gz, .nrrd) or 3D Slicer segmentation (.seg.nrrd)")
    img.add_argument("output", help="output mesh (.vtu, .vtk, .vtp surface, or any mesh format)")
    d = MeshConfig()
    img.add_argument("--label", type=int, help="voxel value to mesh (default: the only non-zero value)")
    img.add_argument("--segment", help="segment name or ID of a .seg.nrrd segmentation")
    img.add_argument("--size", type=float, default=d.surface_mesh_size, metavar="MM",
                     help=f"target tetrahedron edge length in mm (default {d.surface_mesh_size:g})")
    img.add_argument("--keep-largest", action="store_true", help="keep the largest piece instead of refusing several")
    img.add_argument("--fill-cavities", action="store_true", help="fill internal cavities instead of refusing them")
    img.add_argument("--smoothing", type=int, default=d.smoothing_iterations, metavar="N",
                     help=f"Taubin smoothing passes (default {d.smoothing_iterations}; 0 = raw marching cubes)")
    img.add_argument("--json", action="store_true", help="print the figures as JSON")
    img.set_defaults(func=run_from_image)
    ph = msub.add_parser("phantom", help="write the built-in phantom to a file")
    ph.add_argument("output", help="output file (e.g. phantom.vtu, phantom.inp, phantom.node)")
    ph.set_defaults(func=run_phantom)


def mesh_summary(mesh: TetMesh) -> dict:
    """Figures of a mesh as plain numbers (lengths mm, areas mm^2, volumes mm^3)."""
    lo, hi = mesh.bounding_box
    return {
        "vertices": mesh.n_vertices,
        "tetrahedra": mesh.n_tets,
        "reoriented_tetrahedra": mesh.n_flipped,
        "surface_vertices": int(len(mesh.surface_vertices)),
        "interior_vertices": int(len(mesh.interior_vertices)),
        "surface_triangles": int(len(mesh.surface_triangles)),
        "edges": int(len(mesh.edges)),
        "bounding_box_mm": [lo.tolist(), hi.tolist()],
        "extent_mm": mesh.extent.tolist(),
        "volume_mm3": mesh.volume,
        "surface_area_mm2": mesh.surface_area,
        "quality": mesh.quality.as_dict(),
        "fingerprint": mesh.fingerprint(),
    }


def run_info(args) -> int:
    from ..mesh.tags import mesh_file_tags

    mesh = load_mesh_argument(args.file, args.units, args.mesh_size)
    s = mesh_summary(mesh)
    tags = mesh_file_tags(None if args.file == PHANTOM_WORD else args.file)
    s["regions"] = tags.names()  # named regions scenario rules can use (tag = ..., materials.cell_data = ...)
    if args.json:
        print(json.dumps({"file": args.file, **s}, indent=2))
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
    return 0


def run_convert(args) -> int:
    mesh = load_mesh_argument(args.input, args.units, args.mesh_size)
    written = write_mesh(args.output, mesh)
    print(f"read {args.input}: {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra (mm)")
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


def write_scan_mesh(path, mesh: TetMesh) -> list:
    """Write a mesh in the scan's LPS frame: .vtu/.vtk/.vtp as 3D Slicer models (SPACE=LPS), else any format."""
    from pathlib import Path

    from ..slicer.models import MODEL_SUFFIXES, write_model

    if Path(path).suffix.lower() in MODEL_SUFFIXES:
        return [write_model(path, mesh)]
    return write_mesh(path, mesh)


def run_from_image(args) -> int:
    from ..mesh.from_image import label_map_fidelity, label_pieces, mesh_label_map
    from ..mesh.labelmap import LabelMap, read_label_map

    labelmap = read_label_map(args.scan, label=args.label, segment=args.segment)
    mask = label_pieces(labelmap.mask, keep_largest=args.keep_largest, fill_cavities=args.fill_cavities, source=labelmap.source)
    piece = LabelMap(mask, labelmap.ijk_to_lps, labelmap.source)
    mesh = mesh_label_map(piece, args.size, smoothing_iterations=args.smoothing)
    fidelity = label_map_fidelity(mesh, piece)
    written = write_scan_mesh(args.output, mesh)
    spacing = labelmap.spacing
    if args.json:
        print(json.dumps({"scan": args.scan, "label": labelmap.source, "coordinate_system": "LPS",
                          "spacing_mm": spacing.tolist(), "fidelity": fidelity.as_dict(), **mesh_summary(mesh)}, indent=2))
    else:
        print(f"label              {labelmap.source}: {int(labelmap.mask.sum())} voxels of "
              f"{' x '.join(f'{v:.3g}' for v in spacing)} mm"
              + (f" ({int(mask.sum())} meshed)" if mask.sum() != labelmap.mask.sum() else ""))
        print(f"mesh               {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra at size {args.size:g} mm, "
              f"LPS coordinates (the scan's frame)")
        print(f"volume             mesh {fidelity.mesh_volume:.1f} mm^3, voxels {fidelity.label_volume:.1f} mm^3 "
              f"({100 * fidelity.volume_error:+.2f} %)")
        print(f"surface distance   Hausdorff {fidelity.hausdorff_mm:.2f} mm = {fidelity.hausdorff_voxels:.2f} voxel "
              f"(to the label's voxel boundary), mean {fidelity.mean_distance_mm:.2f} mm")
        q = mesh.quality
        print(f"radius ratio       min {q.radius_ratio_min:.3f}  mean {q.radius_ratio_mean:.3f}  (1 = regular tet)")
        print(f"edge length (mm)   min {q.edge_length_min:.3f}  mean {q.edge_length_mean:.3f}  max {q.edge_length_max:.3f}")
        for path in written:
            print(f"wrote {path}")
    return 0
