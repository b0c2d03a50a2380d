"""``tissuecast mesh from-image``: a tetrahedral mesh of one label of a segmented scan, sized for
the simulation (an edge length, a vertex budget or a surface tolerance), with its fidelity to
the voxels and the expected cost of a paper-size run on it."""

from __future__ import annotations

import logging

from ..evaluate import json_output
from ..config import MeshConfig
from ..errors import ConfigError
from ..mesh.labelmap import LABEL_MAP_SUFFIXES

log = logging.getLogger(__name__)

def add_parser(msub) -> None:
    """The ``from-image`` action of ``tissuecast mesh``."""
    d = MeshConfig()
    img = msub.add_parser(
        "from-image", help="tetrahedral mesh of one label of a segmented scan (label map or Slicer segmentation)",
        description="Reads " + " ".join(LABEL_MAP_SUFFIXES) + " (NIfTI with nibabel, NRRD and Slicer .seg.nrrd with "
        "slicerio), meshes one label by marching cubes, Taubin smoothing and gmsh, and reports the mesh quality, how "
        "closely it follows the voxels and what a paper-size run on it would cost. Size it by edge length (--size), "
        "by a vertex budget (--max-vertices: gaps and protrusions narrower than the elements are closed) or by a "
        "surface tolerance (--tolerance). Coordinates stay in the scan's physical frame, LPS mm: a .vtk output says "
        "SPACE=LPS in its header and a .vtp in its SPACE array, where 3D Slicer reads them; a .vtu states nothing "
        "unless --space-array (Slicer takes LPS; meshio cannot read the array).")
    img.add_argument("scan", help="label map (.nii, .nii.gz, .nrrd) or 3D Slicer segmentation (.seg.nrrd)")
    img.add_argument("output", help="output mesh (.vtu, .vtk, .vtp surface, or any mesh format)")
    img.add_argument("--label", type=int, help="voxel value to mesh (default: the only non-zero value)")
    img.add_argument("--segment", help="segment name or ID of a .seg.nrrd segmentation")
    size = img.add_mutually_exclusive_group()
    size.add_argument("--size", type=float, metavar="MM",
                      help=f"target tetrahedron edge length in mm (default {d.surface_mesh_size:g})")
    size.add_argument("--max-vertices", type=int, metavar="N",
                      help="at most N vertices: the edge length is searched (a few meshing attempts)")
    img.add_argument("--tolerance", type=float, metavar="MM",
                     help="95 %% of the mesh surface within MM of the label's voxel boundary: alone, the coarsest mesh "
                          "that meets it is searched; with --max-vertices, it is checked")
    img.add_argument("--keep-largest", action="store_true", help="keep the largest piece instead of refusing several")
    img.add_argument("--fill-cavities", action="store_true", help="fill internal cavities instead of refusing them")
    img.add_argument("--smoothing", type=int, default=d.smoothing_iterations, metavar="N",
                     help=f"Taubin smoothing passes (default {d.smoothing_iterations}; 0 = raw marching cubes)")
    img.add_argument("--space-array", action="store_true",
                     help=".vtu output: add the SPACE=LPS string array 3D Slicer reads (meshio cannot read such files)")
    img.add_argument("--json", action="store_true", help="print the figures as JSON")
    img.set_defaults(func=run_from_image)


def _mesh(piece, args):
    """(mesh, sizing dict) as the options ask."""
    from ..mesh.from_image import mesh_label_map
    from ..mesh.sizing import mesh_label_map_to_budget, mesh_label_map_to_tolerance

    if args.tolerance is not None and args.size is not None:
        raise ConfigError("--size and --tolerance exclude each other: the tolerance search chooses the size")
    if args.max_vertices is not None or args.tolerance is not None:
        if args.max_vertices is not None:
            sized = mesh_label_map_to_budget(piece, args.max_vertices, smoothing_iterations=args.smoothing)
        else:
            sized = mesh_label_map_to_tolerance(piece, args.tolerance, smoothing_iterations=args.smoothing)
        return sized.mesh, {"size_mm": sized.size, "max_vertices": args.max_vertices, "tolerance_mm": args.tolerance,
                            "attempts": [{"size_mm": s, "vertices": n} for s, n in sized.attempts]}
    size = MeshConfig.surface_mesh_size if args.size is None else args.size
    mesh = mesh_label_map(piece, size, smoothing_iterations=args.smoothing)
    return mesh, {"size_mm": size, "max_vertices": None, "tolerance_mm": None, "attempts": []}


def run_from_image(args) -> int:
    from ..mesh.from_image import label_map_fidelity, label_pieces
    from ..mesh.labelmap import LabelMap, read_label_map
    from ..mesh.run_cost import paper_run_estimate
    from .mesh_output import mesh_summary, sizing_warnings, write_scan_mesh

    labelmap = read_label_map(args.scan, label=args.label, segment=args.segment)
    mask = label_pieces(labelmap.mask, keep_largest=args.keep_largest, fill_cavities=args.fill_cavities, source=labelmap.source)
    piece = LabelMap(mask, labelmap.ijk_to_lps, labelmap.source)
    mesh, sizing = _mesh(piece, args)
    fidelity = label_map_fidelity(mesh, piece)
    written = write_scan_mesh(args.output, mesh, space_array=args.space_array)
    cost = paper_run_estimate(mesh.n_vertices, len(mesh.edges))
    for text in sizing_warnings(mesh, sizing, fidelity):
        log.warning(text)
    if args.json:
        print(json_output.dumps({"scan": args.scan, "label": labelmap.source, "coordinate_system": "LPS",
                                 "spacing_mm": labelmap.spacing.tolist(), "sizing": sizing, "fidelity": fidelity.as_dict(),
                                 "paper_run": {"seconds": cost.seconds, "unknowns": cost.unknowns,
                                               "exponent": cost.exponent, "extrapolated": cost.extrapolated},
                                 **mesh_summary(mesh)}, indent=2))
        return 0
    _print_report(args, labelmap, mask, mesh, sizing, fidelity, cost)
    for path in written:
        print(f"wrote {path}")
    return 0


def _print_report(args, labelmap, mask, mesh, sizing, fidelity, cost) -> None:
    spacing = labelmap.spacing
    print(f"label              {labelmap.source}: {int(labelmap.mask.sum())} voxels of "
          f"{' x '.join(f'{v:.3g}' for v in spacing)} mm"
          + (f" ({int(mask.sum())} meshed)" if mask.sum() != labelmap.mask.sum() else ""))
    how = f"at size {sizing['size_mm']:.3g} mm"
    if sizing["attempts"]:
        asked = (f"budget {sizing['max_vertices']} vertices" if sizing["max_vertices"]
                 else f"tolerance {sizing['tolerance_mm']:g} mm")
        n = len(sizing["attempts"])
        how += f" ({asked}; {n} meshing attempt{'' if n == 1 else 's'})"
    print(f"mesh               {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra {how}, LPS coordinates "
          "(the scan's frame)")
    print(f"volume             mesh {fidelity.mesh_volume:.1f} mm^3, voxels {fidelity.label_volume:.1f} mm^3 "
          f"({100 * fidelity.volume_error:+.2f} %)")
    print(f"surface distance   Hausdorff {fidelity.hausdorff_mm:.2f} mm = {fidelity.hausdorff_voxels:.2f} voxel "
          f"(to the label's voxel boundary), mean {fidelity.mean_distance_mm:.2f} mm")
    print(f"  95th percentile  mesh surface to label {fidelity.surface_p95_mm:.2f} mm = "
          f"{fidelity.surface_p95_voxels:.2f} voxel, label boundary to mesh {fidelity.boundary_p95_mm:.2f} mm = "
          f"{fidelity.boundary_p95_voxels:.2f} voxel")
    q = mesh.quality
    print(f"radius ratio       min {q.radius_ratio_min:.3f}  mean {q.radius_ratio_mean:.3f}  (1 = regular tet)")
    print(f"edge length (mm)   min {q.edge_length_min:.3f}  mean {q.edge_length_mean:.3f}  max {q.edge_length_max:.3f}")
    print(f"expected cost      {cost.text()}")
