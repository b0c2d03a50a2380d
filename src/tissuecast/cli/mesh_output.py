"""What the mesh commands print and write about a mesh: its figures, the files in the scan's
frame, and warnings when a mesh is far finer than asked."""

from __future__ import annotations

from pathlib import Path

from ..mesh import TetMesh, write_mesh

__all__ = ["mesh_summary", "write_scan_mesh", "sizing_warnings", "FINER_THAN_ASKED"]

#: a mesh whose mean edge is below this share of the size asked for is "finer than asked"
FINER_THAN_ASKED = 0.7


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


def write_scan_mesh(path, mesh: TetMesh, *, space_array: bool = False) -> list[Path]:
    """Write a mesh in the scan's LPS frame: a .vtp as a 3D Slicer model surface (SPACE=LPS), any
    other format with :func:`~tissuecast.mesh.write_mesh` (.vtk: SPACE=LPS header; .vtu: the
    SPACE array only with ``space_array``)."""
    from ..slicer.models import write_model

    if Path(path).suffix.lower() == ".vtp":
        return [write_model(path, mesh)]
    return write_mesh(path, mesh, space_array=space_array)


def sizing_warnings(mesh: TetMesh, sizing: dict, fidelity=None) -> list[str]:
    """What to tell the user about a mesh against what was asked.

    Args:
        mesh: the mesh made.
        sizing: ``size_mm`` (the edge length asked for or found), ``max_vertices`` and
            ``tolerance_mm`` (None when not asked) and ``attempts`` (empty without a search).
        fidelity: the label-map fidelity, to check a tolerance asked next to a budget.

    Returns:
        Sentences: the mesh is far finer than the size asked (mean edge below
        :data:`FINER_THAN_ASKED` of it), or a budget that misses the tolerance.
    """
    out = []
    edge = mesh.quality.edge_length_mean
    if not sizing["attempts"] and edge < FINER_THAN_ASKED * sizing["size_mm"]:
        out.append(f"the mesh is finer than asked: mean edge {edge:.2f} mm for a size of {sizing['size_mm']:g} mm "
                   f"({mesh.n_vertices} vertices; the surface's detail drove gmsh finer); ask for what the simulation "
                   "can afford with --max-vertices N")
    if fidelity is not None and sizing["max_vertices"] and sizing["tolerance_mm"] is not None \
            and fidelity.surface_p95_mm > sizing["tolerance_mm"]:
        out.append(f"{sizing['max_vertices']} vertices do not meet the tolerance: 95 % of the surface lies within "
                   f"{fidelity.surface_p95_mm:.2f} mm of the label, not {sizing['tolerance_mm']:g} mm; allow more "
                   "vertices or a larger tolerance")
    return out
