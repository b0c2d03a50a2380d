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
that states ``SPACE=RAS`` as 3D Slicer writes it is converted to LPS on reading. Files with a
``SPACE`` string array (3D Slicer's and tissuecast's models) are read with VTK when meshio
cannot.

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
from .tetmesh import TetMesh

__all__ = ["read_mesh", "write_mesh", "write_point_set", "UNITS", "VOLUME_FORMATS", "SURFACE_FORMATS"]

log = logging.getLogger(__name__)

#: length unit -> factor to mm
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: volume-mesh extensions and their meshio format names ("tetgen": our own reader)
VOLUME_FORMATS = {
    ".vtu": "vtu", ".vtk": "vtk", ".msh": "gmsh", ".inp": "abaqus", ".mesh": "medit", ".xdmf": "xdmf",
    ".node": "tetgen", ".ele": "tetgen",
}
#: closed-surface extensions, tetrahedralised on read
SURFACE_FORMATS = {".stl": "stl", ".obj": "obj", ".ply": "ply", ".off": "off", ".face": "tetgen"}


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
                "it looks like it is in metres: pass units='m' (or 'cm'; CLI: --units m)"
            )


def _meshio_read(path: Path, fmt: str, tolerant: bool = True):
    import meshio

    # meshio.read() prints and calls sys.exit() on some read failures; call the format's
    # reader directly where meshio exposes it.
    reader = getattr(getattr(meshio, "_helpers", None), "reader_map", {}).get(fmt)
    try:
        with np.errstate(over="ignore"):  # meshio's STL sniffing multiplies a uint32
            return reader(str(path)) if reader else meshio.read(path, file_format=fmt)
    except (Exception, SystemExit) as exc:  # meshio raises many kinds (ReadError, ValueError...)
        if tolerant and fmt == "abaqus" and "Element type not available" in str(exc):
            m = _read_inp_tolerant(path)
            if m is not None:
                return m
        if tolerant and fmt in ("vtu", "vtk"):  # e.g. a SPACE string array (3D Slicer models): meshio cannot read it
            m = _read_with_vtk(path)
            if m is not None:
                return m
        why = str(exc).strip() or "the file is corrupt or not in this format"
        raise MeshFormatError(f"could not read '{path}' as {fmt} ({type(exc).__name__}: {why})") from exc


def _read_with_vtk(path: Path):
    """A .vtu/.vtk file meshio refuses, read with VTK if it is installed (None otherwise)."""
    import meshio

    try:
        from ..slicer.models import read_model
    except ImportError:
        return None
    try:
        points, tets = read_model(path)
    except Exception:  # noqa: BLE001 - VTK failed too: report meshio's error
        return None
    return meshio.Mesh(points, [("tetra", tets)])


def _file_space(path: Path, ext: str) -> str:
    """The coordinate system a .vtk/.vtu file states (3D Slicer's SPACE tag); LPS when none."""
    if ext == ".vtk":
        with open(path, "rb") as fh:
            fh.readline()
            header = fh.readline()
        return "RAS" if b"SPACE=RAS" in header else "LPS"
    if ext == ".vtu":
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
        if b'Name="SPACE"' in head:
            try:
                from ..slicer.models import read_model_space
            except ImportError:
                return "LPS"
            return read_model_space(path) or "LPS"
    return "LPS"


def _read_inp_tolerant(path: Path):
    """Abaqus/CalculiX deck whose *ELEMENT blocks meshio does not know (e.g. gmsh's CPS6
    second-order triangles): drop those blocks (logged) and read the rest."""
    import re
    import tempfile

    from meshio.abaqus._abaqus import abaqus_to_meshio_type

    out, dropped, skipping = [], set(), False
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines(keepends=True):
        if line.startswith("*") and not line.startswith("**"):
            skipping = False
            m = re.match(r"\*\s*element\b.*?\btype\s*=\s*([A-Za-z0-9_]+)", line, flags=re.IGNORECASE)
            if m and m.group(1).upper() not in abaqus_to_meshio_type:
                dropped.add(m.group(1).upper())
                skipping = True
        if not skipping:
            out.append(line)
    if not dropped:
        return None
    log.info("'%s': ignoring element blocks of unsupported types %s", path, ", ".join(sorted(dropped)))
    with tempfile.TemporaryDirectory() as tmp:
        filtered = Path(tmp) / path.name
        filtered.write_text("".join(out), encoding="utf-8")
        return _meshio_read(filtered, "abaqus", tolerant=False)


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


def read_mesh(path: str | Path, units: str = "mm", *, mesh_size: float | None = None) -> TetMesh:
    """Read a tetrahedral mesh (or a closed surface, which is tetrahedralised).

    Args:
        path: mesh file; see the module docstring for the formats.
        units: length unit of the file, ``"mm"``, ``"cm"`` or ``"m"``; coordinates are
            converted to mm.
        mesh_size: target edge length in mm when tetrahedralising a surface file; default
            ``MeshConfig.surface_mesh_size`` (3 mm). Ignored for volume meshes.

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
        return _read_surface(path, ext, factor, units, mesh_size)
    if ext in (".node", ".ele"):
        from .tetgen import read_tetgen

        points, tets, attributes = read_tetgen(path)
        if attributes.size:
            log.info("'%s': ignoring %d region attribute(s) per tetrahedron", path, attributes.shape[1])
    else:
        m = _meshio_read(path, VOLUME_FORMATS[ext])
        points, tets = np.asarray(m.points, dtype=np.float64), _tets_from_meshio(m, path)
        if points.shape[1] != 3:
            raise MeshFormatError(f"'{path}' has {points.shape[1]}-D points; 3-D coordinates are needed")
        if _file_space(path, ext) == "RAS":  # a 3D Slicer model saved in RAS: tissuecast works in LPS
            log.info("'%s' states SPACE=RAS; converted to LPS", path)
            points = points * np.array([-1.0, -1.0, 1.0])
    points, tets = _compact(points, tets, path)
    points = points * factor
    _check_scale(points, units, path)
    try:
        return TetMesh(points, tets)
    except MeshError as exc:
        raise type(exc)(f"'{path}': {exc}") from exc


def _read_surface(path: Path, ext: str, factor: float, units: str, mesh_size: float | None) -> TetMesh:
    if ext == ".face":
        from .tetgen import read_tetgen_surface

        points, tri = read_tetgen_surface(path)
    else:
        m = _meshio_read(path, SURFACE_FORMATS[ext])
        points, tri = np.asarray(m.points, dtype=np.float64)[:, :3], _triangles_from_meshio(m, path)
    if not np.isfinite(points).all():
        raise MeshError(f"'{path}' has vertices with non-finite coordinates; fix the surface file")
    points = points * factor
    _check_scale(points, units, path)
    if mesh_size is None:
        from ..config import MeshConfig

        mesh_size = MeshConfig().surface_mesh_size
    from .mesher import tetrahedralize_surface

    try:
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


def write_mesh(path: str | Path, mesh: TetMesh, point_data: dict | None = None, cell_data: dict | None = None) -> list[Path]:
    """Write a mesh; the format follows the extension (see the module docstring).

    Args:
        path: output file. ``.node``/``.ele`` write the TetGen trio (1-based ids);
            ``.stl .obj .ply .off .face`` write the outer surface only.
        mesh: the mesh (coordinates in mm; written as mm).
        point_data: name -> (n,) or (n, k) array per vertex, e.g. ``{"displacement": u}``
            (mm) or ``{"error": e}``; kept by .vtu .vtk .msh .xdmf (ParaView, Slicer).
            Pass the deformed mesh (``mesh.deformed(u)``) to write deformed coordinates.
        cell_data: name -> (m,) or (m, k) array per tetrahedron.

    Returns:
        The files written.
    """
    import meshio

    path = Path(path)
    ext = _extension(path)
    pdata = _check_data(point_data, mesh.n_points, "point_data")
    cdata = _check_data(cell_data, mesh.n_tets, "cell_data")
    if ext in (".node", ".ele", ".face"):
        from .tetgen import write_tetgen

        tets = None if ext == ".face" else mesh.tets
        return write_tetgen(path, mesh.points, tets, mesh.surface_triangles)
    if ext in SURFACE_FORMATS:
        verts = mesh.surface_vertices
        renum = np.full(mesh.n_points, -1, dtype=np.int64)
        renum[verts] = np.arange(len(verts))
        tri = renum[mesh.surface_triangles].astype(np.int32)
        meshio.write(path, meshio.Mesh(mesh.points[verts], [("triangle", tri)]), file_format=SURFACE_FORMATS[ext])
        return [path]
    out = meshio.Mesh(
        mesh.points,
        [("tetra", mesh.tets)],
        point_data=pdata,
        cell_data={k: [v] for k, v in cdata.items()},
    )
    kwargs = {"binary": True} if ext == ".vtk" else {}
    meshio.write(path, out, file_format=VOLUME_FORMATS[ext], **kwargs)
    heavy = path.with_suffix(".h5")  # XDMF keeps its arrays in a side file
    return [path, heavy] if ext == ".xdmf" and heavy.is_file() else [path]


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
