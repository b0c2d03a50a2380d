"""Reading and writing tetrahedral meshes (meshio formats, TetGen, closed surfaces).

=================  =========================================================
extension          handled by
=================  =========================================================
.vtu .vtk          meshio (VTK XML / legacy); point data kept on write
.msh               meshio (gmsh)
.inp               meshio (Abaqus / CalculiX input deck; ids there are 1-based)
.mesh              meshio (Medit)
.xdmf              meshio (XDMF + HDF5)
.node .ele         tissuecast.mesh.tetgen (TetGen; 0- or 1-based, as the file says)
.stl .obj .ply     read: closed surface, tetrahedralised by gmsh at ``mesh_size``;
.off .face         write: the outer surface triangles
=================  =========================================================

Coordinates are LPS (tissuecast's frame, see :mod:`tissuecast.frames`); a .vtk/.vtu file
that states ``SPACE=RAS`` where 3D Slicer writes it (the legacy header line; the ``SPACE``
string array of a .vtu file's field data) is converted to LPS on reading. How tissuecast
states the frame in the files it writes, so that meshio, VTK and 3D Slicer all read them:
docs/files.md.

Reading keeps only tetrahedra (10-node tets are reduced to their 4 corners), drops vertices
that belong to no tetrahedron (logged; the remaining vertices keep their relative order, so
ids are unchanged when unused nodes come last, as with gmsh/Abaqus mid-edge nodes) and
converts coordinates to mm.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import MeshError, MeshFormatError
from .mesher import SURFACE_FORMATS
from .meshio_read import read_with_meshio
from .tetmesh import TetMesh
from .vtk_space import file_space

__all__ = ["read_mesh", "write_mesh", "write_point_set", "UNITS", "VOLUME_FORMATS", "SURFACE_FORMATS", "LEGACY_VTK_HEADER",
           "write_tetrahedra"]

log = logging.getLogger(__name__)

#: length unit -> factor to mm
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: volume-mesh extensions and their meshio format names ("tetgen": our own reader)
VOLUME_FORMATS = {
    ".vtu": "vtu", ".vtk": "vtk", ".msh": "gmsh", ".inp": "abaqus", ".mesh": "medit", ".xdmf": "xdmf",
    ".node": "tetgen", ".ele": "tetgen",
}
#: the header line of the legacy .vtk files tissuecast writes: 3D Slicer reads the frame from it
LEGACY_VTK_HEADER = "tissuecast output. SPACE=LPS"
# a .vtu field-data block with the string array SPACE = "LPS" (characters and a NUL, as VTK writes it)
_SPACE_FIELD_DATA = ('<FieldData>\n<Array type="String" Name="SPACE" NumberOfTuples="1" format="ascii">\n'
                     + " ".join(str(c) for c in b"LPS\0") + "\n</Array>\n</FieldData>\n").encode("ascii")


def _extension(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in VOLUME_FORMATS and ext not in SURFACE_FORMATS:
        raise MeshFormatError(
            f"unknown mesh format {ext or '(no extension)'!r} of '{path}'; supported extensions: "
            + " ".join(sorted(VOLUME_FORMATS)) + " (volume meshes), "
            + " ".join(sorted(SURFACE_FORMATS)) + " (closed surfaces)"
        )
    return ext


def _factor(units: str) -> float:
    if units not in UNITS:
        raise MeshError(f"units must be one of {', '.join(map(repr, UNITS))}, got {units!r}")
    return UNITS[units]


def _check_scale(points: np.ndarray, units: str, path: Path) -> None:
    """Refuse a mesh declared in mm that is smaller than 1 mm across (likely metres)."""
    finite = points[np.isfinite(points).all(axis=1)]
    if units == "mm" and len(finite):
        diag = float(np.linalg.norm(finite.max(0) - finite.min(0)))
        if diag < 1.0:
            raise MeshError(
                f"'{path}' is only {diag:.3g} mm across (bounding-box diagonal) when read as mm; "
                "it looks like it is in metres: pass units='m' (or 'cm'; CLI: --units m; config: [mesh] units = \"m\")"
            )


def _points_from_meshio(m, path: Path) -> np.ndarray:
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or len(points) == 0:
        raise MeshFormatError(f"'{path}' holds no vertices; the file is empty, truncated or of another format")
    return points


def _tets_from_meshio(m, path: Path) -> np.ndarray:
    blocks = [np.asarray(c.data)[:, :4] for c in m.cells if c.type in ("tetra", "tetra4", "tetra10")]
    if not blocks:
        kinds = sorted({c.type for c in m.cells}) or ["none"]
        hint = "; for a closed surface use .stl/.obj/.ply/.off" if "triangle" in kinds else ""
        raise MeshFormatError(f"'{path}' holds no tetrahedra (cell types: {', '.join(kinds)}){hint}")
    return np.vstack(blocks).astype(np.int64)


def _triangles_from_meshio(m, path: Path) -> np.ndarray:
    tris = [np.asarray(c.data) for c in m.cells if c.type == "triangle"]
    quads = [np.asarray(c.data) for c in m.cells if c.type == "quad"]
    tris += [q[:, [0, 1, 2]] for q in quads] + [q[:, [0, 2, 3]] for q in quads]
    if not tris:
        raise MeshFormatError(f"'{path}' holds no triangles; a closed triangulated surface is needed")
    return np.vstack(tris).astype(np.int64)


def _compact(points: np.ndarray, tets: np.ndarray, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices used by no tetrahedron, keeping the others' order."""
    if tets.size and (tets.min() < 0 or tets.max() >= len(points)):
        bad = int(np.flatnonzero((tets < 0).any(1) | (tets >= len(points)).any(1))[0])
        raise MeshError(
            f"'{path}': tetrahedron {bad} = {tets[bad].tolist()} refers to a vertex outside "
            f"0..{len(points) - 1} (the file has {len(points)} vertices)"
        )
    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    if used.all():
        return points, tets
    log.info("'%s': dropped %d vertices that belong to no tetrahedron", path, int((~used).sum()))
    renum = np.cumsum(used) - 1
    return points[used], renum[tets]


def read_mesh(path: str | Path, units: str = "mm", *, mesh_size: float | None = None,
              max_vertices: int | None = None) -> TetMesh:
    """Read a tetrahedral mesh (or a closed surface, which is tetrahedralised).

    Args:
        path: mesh file; see the module docstring for the formats.
        units: length unit of the file, ``"mm"``, ``"cm"`` or ``"m"``; coordinates are
            converted to mm.
        mesh_size: target edge length in mm when tetrahedralising a surface file; default
            ``MeshConfig.surface_mesh_size`` (3 mm). Ignored for volume meshes.
        max_vertices: a surface file is meshed with at most this many vertices, the edge
            length searched (:func:`~tissuecast.mesh.sizing.mesh_to_budget`; ``mesh_size``
            unused); refused for volume meshes, which are read as they are.

    Returns:
        The mesh, coordinates in mm, 0-based ids.

    Raises:
        MeshFormatError: missing file, unknown extension, unreadable file, no tetrahedra.
        MeshError: invalid mesh (see :class:`TetMesh`), a surface that is not closed and
            manifold, or a mesh declared in mm that is smaller than 1 mm (metres?).
    """
    path = Path(path)
    factor = _factor(units)
    ext = _extension(path)
    if not path.is_file():
        raise MeshFormatError(f"mesh file '{path}' does not exist")
    if ext in SURFACE_FORMATS:
        return _read_surface(path, ext, factor, units, mesh_size, max_vertices)
    if max_vertices:
        raise MeshError(f"'{path}' is a volume mesh, read as it is; a vertex budget (max_vertices) applies to "
                        "closed surfaces and label maps, which are meshed")
    if ext in (".node", ".ele"):
        from .tetgen import read_tetgen

        points, tets, attributes = read_tetgen(path)
        if attributes.size:
            log.info("'%s': ignoring %d region attribute(s) per tetrahedron", path, attributes.shape[1])
    else:
        m = read_with_meshio(path, VOLUME_FORMATS[ext])
        points, tets = _points_from_meshio(m, path), _tets_from_meshio(m, path)
        if points.shape[1] != 3:
            raise MeshFormatError(f"'{path}' has {points.shape[1]}-D points; 3-D coordinates are needed")
        if file_space(path) == "RAS":  # a 3D Slicer model saved in RAS: tissuecast works in LPS
            log.info("'%s' states SPACE=RAS; converted to LPS", path)
            points = points * np.array([-1.0, -1.0, 1.0])
    points, tets = _compact(points, tets, path)
    points = points * factor
    _check_scale(points, units, path)
    try:
        return TetMesh(points, tets)
    except MeshError as exc:
        raise type(exc)(f"'{path}': {exc}") from exc


def _read_surface(path: Path, ext: str, factor: float, units: str, mesh_size: float | None,
                  max_vertices: int | None) -> TetMesh:
    if ext == ".face":
        from .tetgen import read_tetgen_surface

        points, tri = read_tetgen_surface(path)
    else:
        m = read_with_meshio(path, SURFACE_FORMATS[ext])
        points, tri = _points_from_meshio(m, path)[:, :3], _triangles_from_meshio(m, path)
    if not np.isfinite(points).all():
        raise MeshError(f"'{path}' has vertices with non-finite coordinates; fix the surface file")
    points = points * factor
    _check_scale(points, units, path)
    if mesh_size is None:
        from ..config import MeshConfig

        mesh_size = MeshConfig().surface_mesh_size
    from .mesher import tetrahedralize_surface

    try:
        if max_vertices:
            from .sizing import mesh_to_budget, surface_volume

            return mesh_to_budget(lambda size: tetrahedralize_surface(points, tri, size), max_vertices,
                                  surface_volume(points, tri)).mesh
        return tetrahedralize_surface(points, tri, mesh_size)
    except MeshError as exc:
        raise MeshError(f"'{path}': {exc}") from exc


def _check_data(data: dict | None, size: int, what: str) -> dict:
    out = {}
    for name, value in (data or {}).items():
        arr = np.asarray(value)
        if arr.ndim not in (1, 2) or arr.shape[0] != size:
            raise MeshError(f"{what} {name!r} must have shape ({size},) or ({size}, k), got {arr.shape}")
        out[str(name)] = arr
    return out


def write_mesh(path: str | Path, mesh: TetMesh, point_data: dict | None = None, cell_data: dict | None = None, *,
               space_array: bool = False) -> list[Path]:
    """Write a mesh; the format follows the extension (see the module docstring).

    Coordinates are written as they are (LPS mm). A ``.vtk`` file (legacy format 4.2, what
    3D Slicer writes) states ``SPACE=LPS`` in its header line, where Slicer reads the frame;
    a ``.vtu`` file states nothing by default (Slicer then takes LPS, its default, with a
    warning), because meshio cannot read a file holding Slicer's ``SPACE`` string array.

    Args:
        path: output file. ``.node``/``.ele`` write the TetGen trio (1-based ids);
            ``.stl .obj .ply .off .face`` write the outer surface only.
        mesh: the mesh (coordinates in mm; written as mm).
        point_data: name -> (n,) or (n, k) array per vertex, e.g. ``{"displacement": u}``
            (mm) or ``{"error": e}``; kept by .vtu .vtk .msh .xdmf (ParaView, Slicer).
            Pass the deformed mesh (``mesh.deformed(u)``) to write deformed coordinates.
        cell_data: name -> (m,) or (m, k) array per tetrahedron.
        space_array: ``.vtu`` only: add the field-data string array ``SPACE = "LPS"`` that
            3D Slicer reads (it then loads the file without a warning; meshio cannot read
            such a file, VTK and pyvista can).

    Returns:
        The files written.
    """
    import meshio

    path = Path(path)
    ext = _extension(path)
    _check_space_array(path, space_array)
    pdata = _check_data(point_data, mesh.n_vertices, "point_data")
    cdata = _check_data(cell_data, mesh.n_tets, "cell_data")
    if ext in (".node", ".ele", ".face"):
        from .tetgen import write_tetgen

        tets = None if ext == ".face" else mesh.tets
        return write_tetgen(path, mesh.points, tets, mesh.surface_triangles)
    if ext in SURFACE_FORMATS:
        verts = mesh.surface_vertices
        renum = np.full(mesh.n_vertices, -1, dtype=np.int64)
        renum[verts] = np.arange(len(verts))
        tri = renum[mesh.surface_triangles].astype(np.int32)
        meshio.write(path, meshio.Mesh(mesh.points[verts], [("triangle", tri)]), file_format=SURFACE_FORMATS[ext])
        return [path]
    return write_tetrahedra(path, mesh.points, mesh.tets, pdata, cdata, space_array=space_array)


def write_tetrahedra(path: str | Path, points: np.ndarray, tets: np.ndarray, point_data: dict | None = None,
                     cell_data: dict | None = None, *, space_array: bool = False) -> list[Path]:
    """Write tetrahedra as they are (no checks of the cells, e.g. a deformed mesh) to a volume format.

    Args:
        path: ``.vtu .vtk .msh .inp .mesh .xdmf`` (see :func:`write_mesh` for .vtk/.vtu and ``space_array``).
        points: (n, 3) float, mm.
        tets: (m, 4) int, 0-based.
        point_data, cell_data: as in :func:`write_mesh`.

    Returns:
        The files written (``.xdmf`` adds its ``.h5`` file).
    """
    import meshio

    path = Path(path)
    ext = _extension(path)
    if ext not in VOLUME_FORMATS or ext in (".node", ".ele"):
        raise MeshFormatError(f"write_tetrahedra writes {' '.join(sorted(set(VOLUME_FORMATS) - {'.node', '.ele'}))}, "
                              f"got '{path.name}'; use write_mesh")
    _check_space_array(path, space_array)
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    out = meshio.Mesh(points, [("tetra", tets)], point_data=_check_data(point_data, len(points), "point_data"),
                      cell_data={k: [v] for k, v in _check_data(cell_data, len(tets), "cell_data").items()})
    if ext in (".vtk", ".vtu"):
        _write_vtk_file(path, out, space_array)
        return [path]
    meshio.write(path, out, file_format=VOLUME_FORMATS[ext])
    heavy = path.with_suffix(".h5")  # XDMF keeps its arrays in a side file
    return [path, heavy] if ext == ".xdmf" and heavy.is_file() else [path]


def _check_space_array(path: Path, space_array: bool) -> None:
    if space_array and path.suffix.lower() != ".vtu":
        raise MeshFormatError(f"space_array applies to .vtu files (a .vtk file states SPACE=LPS in its header); "
                              f"got '{path.name}'")


def _write_vtk_file(path: Path, out, space_array: bool) -> None:
    """A meshio mesh as .vtk (legacy 4.2, ``SPACE=LPS`` header) or .vtu (optionally with ``SPACE``)."""
    import meshio

    if path.suffix.lower() == ".vtk":
        meshio.vtk.write(str(path), out, fmt_version="4.2", binary=True)
        version, _, rest = path.read_bytes().split(b"\n", 2)  # line 2 is the free-text header
        path.write_bytes(b"\n".join([version, LEGACY_VTK_HEADER.encode("ascii"), rest]))
        return
    meshio.vtu.write(str(path), out)
    if space_array:
        tag = b"<UnstructuredGrid>\n"
        data = path.read_bytes()
        if tag not in data:  # pragma: no cover - meshio always writes this line
            raise MeshFormatError(f"could not add the SPACE array to '{path}': no <UnstructuredGrid> line")
        path.write_bytes(data.replace(tag, tag + _SPACE_FIELD_DATA, 1))


def write_point_set(path: str | Path, points: np.ndarray, point_data: dict | None = None) -> Path:
    """Write points as VTK vertex cells (.vtu), e.g. fiducial markers and fixed vertices.

    Args:
        path: output ``.vtu`` file.
        points: (p, 3) float, mm.
        point_data: name -> (p,) or (p, k) numeric array, e.g. ``{"role": ...,
            "vertex_id": ...}``.
    """
    import meshio

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    data = _check_data(point_data, len(points), "point_data")
    cells = [("vertex", np.arange(len(points), dtype=np.int64)[:, None])]
    meshio.write(Path(path), meshio.Mesh(points, cells, point_data=data), file_format="vtu")
    return Path(path)
