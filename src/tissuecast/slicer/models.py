"""Meshes and fields as model files 3D Slicer opens in the right frame (.vtk, .vtp, .vtu).

Slicer reads the coordinate system of a model file from the file itself
(``vtkMRMLModelStorageNode``): the header line of a legacy ``.vtk`` file (``... SPACE=LPS``)
or a string array ``SPACE`` in the field data of an XML ``.vtu``/``.vtp`` file; without it
Slicer assumes LPS and warns. Coordinates here are LPS (tissuecast's frame), so a model
overlays the scan it was made from without a manual transform.

- ``.vtk``: the tetrahedral mesh (VTK_TETRA cells), optionally deformed, with point data
  (e.g. ``displacement_mm``), legacy format 4.2 with ``SPACE=LPS`` in the header: read by
  Slicer in its frame, by VTK/pyvista and by meshio.
- ``.vtu``: the same as VTK XML, without the ``SPACE`` array unless ``space_array`` (meshio
  cannot read a file that has it; Slicer takes LPS without it, with a warning).
- ``.vtp``: the outer surface (triangles), optionally deformed, with the point data of the
  surface vertices, and ``SPACE = "LPS"`` (meshio does not read .vtp files at all), written
  with VTK (extra ``viz``).

``.vtk``/``.vtu`` files go through :func:`tissuecast.mesh.write_mesh`, the one writer of
volume meshes. docs/files.md tabulates which tool reads which file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import MeshFormatError, require
from ..mesh.tetmesh import TetMesh
from ..mesh.vtk_space import quiet_vtk

__all__ = ["MODEL_SUFFIXES", "SlicerModel", "write_model", "read_model", "read_model_as_slicer", "read_model_space"]

#: model file endings 3D Slicer opens and this module writes
MODEL_SUFFIXES = (".vtk", ".vtp", ".vtu")
_SPACE = "SPACE"
_VTK_TRIANGLE, _VTK_TETRA = 5, 10


def _vtk():
    require("vtkmodules", "viz", "Writing 3D Slicer model files")
    from vtkmodules import vtkCommonCore, vtkCommonDataModel, vtkIOLegacy, vtkIOXML
    from vtkmodules.util import numpy_support

    return vtkCommonCore, vtkCommonDataModel, vtkIOLegacy, vtkIOXML, numpy_support


def _dataset(points: np.ndarray, cells: np.ndarray, cell_type: int, point_data: dict, polydata: bool):
    core, model, _, _, ns = _vtk()
    data = model.vtkPolyData() if polydata else model.vtkUnstructuredGrid()
    vtk_points = core.vtkPoints()
    vtk_points.SetData(ns.numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    data.SetPoints(vtk_points)
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    offsets = np.arange(0, cells.size + 1, cells.shape[1], dtype=np.int64)
    array = model.vtkCellArray()
    array.SetData(ns.numpy_to_vtkIdTypeArray(offsets, deep=True), ns.numpy_to_vtkIdTypeArray(cells.ravel(), deep=True))
    if polydata:
        data.SetPolys(array)
    else:
        data.SetCells(cell_type, array)
    for name, values in point_data.items():
        arr = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
        arr.SetName(name)
        data.GetPointData().AddArray(arr)
    return data


def write_model(
    path: str | Path,
    mesh: TetMesh,
    *,
    displacement: np.ndarray | None = None,
    point_data: dict | None = None,
    space_array: bool = False,
) -> Path:
    """Write a mesh (or its outer surface) as a 3D Slicer model file in LPS.

    Args:
        path: ``.vtu`` or ``.vtk`` (tetrahedra) or ``.vtp`` (outer surface triangles).
        mesh: the mesh, LPS mm.
        displacement: (n, 3) float, mm: write the deformed mesh and add it as point data
            ``displacement_mm``.
        point_data: name -> (n,) or (n, k) array per mesh vertex (mm where lengths).
        space_array: ``.vtu``: add the ``SPACE`` string array Slicer reads (meshio then
            cannot read the file; see :func:`tissuecast.mesh.write_mesh`).

    Returns:
        The file written.
    """
    from ..mesh.io import write_tetrahedra

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MODEL_SUFFIXES:
        raise MeshFormatError(f"a 3D Slicer model file ends in {', '.join(MODEL_SUFFIXES)}, got '{path.name}'")
    data = dict(point_data or {})
    points = np.asarray(mesh.points, dtype=np.float64)
    if displacement is not None:
        u = np.asarray(displacement, dtype=np.float64)
        if u.shape != points.shape:
            raise MeshFormatError(f"displacement must have shape {points.shape}, got {u.shape}")
        points = points + u
        data["displacement_mm"] = u
    for name, values in data.items():
        if len(values) != mesh.n_vertices:
            raise MeshFormatError(f"point data {name!r} has {len(values)} rows for {mesh.n_vertices} vertices")
    if suffix != ".vtp":
        return write_tetrahedra(path, points, mesh.tets, data, space_array=space_array)[0]
    if space_array:
        raise MeshFormatError("space_array applies to .vtu files; a .vtp model always states SPACE=LPS")
    core, _, _, xml, _ = _vtk()
    ids = mesh.surface_vertices
    local = np.searchsorted(ids, mesh.surface_triangles)
    dataset = _dataset(points[ids], local, _VTK_TRIANGLE, {k: np.asarray(v)[ids] for k, v in data.items()}, True)
    space = core.vtkStringArray()
    space.SetName(_SPACE)
    space.InsertNextValue("LPS")
    dataset.GetFieldData().AddArray(space)
    writer = xml.vtkXMLPolyDataWriter()
    writer.SetDataModeToBinary()
    writer.SetInputData(dataset)
    writer.SetFileName(str(path))
    if not writer.Write():
        raise MeshFormatError(f"VTK could not write '{path}'")
    return path


@dataclass(frozen=True, eq=False)
class SlicerModel:
    """A model file as 3D Slicer loads it (:func:`read_model_as_slicer`).

    Attributes:
        points: (n, 3) float, LPS mm (converted when the file states RAS).
        cell_types: (c,) int VTK cell type of every cell (5 triangle, 10 tetrahedron).
        connectivity: (k,) int and ``offsets`` (c + 1,) int: the cells' vertex ids, VTK style.
        point_data: name -> (n,) or (n, k) array, as stored (no frame change).
        stated_space: ``"LPS"``/``"RAS"`` as the file states it, or None: Slicer then takes
            LPS (its default for a file opened on its own) and logs a warning.
    """

    points: np.ndarray
    cell_types: np.ndarray
    connectivity: np.ndarray
    offsets: np.ndarray
    point_data: dict
    stated_space: str | None

    @property
    def tets(self) -> np.ndarray:
        """(m, 4) int64 the tetrahedra (other cells dropped)."""
        starts = self.offsets[:-1][self.cell_types == _VTK_TETRA]
        return self.connectivity[starts[:, None] + np.arange(4)].astype(np.int64).reshape(-1, 4)


def _space_in_text(text: str | None) -> str | None:
    text = text or ""
    return "RAS" if "SPACE=RAS" in text else "LPS" if "SPACE=LPS" in text else None


def _read_vtk_dataset(path: Path):
    """The dataset of a model file and the frame it states, the way ``vtkMRMLModelStorageNode`` reads it."""
    _, _, legacy, xml, _ = _vtk()
    suffix = path.suffix.lower()
    if suffix == ".vtk":
        poly, grid = legacy.vtkPolyDataReader(), legacy.vtkUnstructuredGridReader()
        poly.SetFileName(str(path))
        grid.SetFileName(str(path))
        reader = poly if poly.IsFilePolyData() else grid if grid.IsFileUnstructuredGrid() else None
        if reader is None:
            raise MeshFormatError(f"'{path}' holds neither polydata nor an unstructured grid (3D Slicer would refuse it)")
        reader.ReadAllScalarsOn()
        reader.ReadAllVectorsOn()
        reader.ReadAllFieldsOn()
        reader.Update()
        return reader.GetOutput(), _space_in_text(poly.GetHeader())
    if suffix not in (".vtp", ".vtu"):
        raise MeshFormatError(f"a 3D Slicer model file ends in {', '.join(MODEL_SUFFIXES)}, got '{path.name}'")
    reader = xml.vtkXMLPolyDataReader() if suffix == ".vtp" else xml.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    data = reader.GetOutput()
    array = data.GetFieldData().GetAbstractArray(_SPACE) if data is not None else None
    value = array.GetValue(0) if array is not None and array.GetNumberOfValues() else ""
    return data, "RAS" if "RAS" in value else "LPS" if "LPS" in value else None


def read_model_as_slicer(path: str | Path) -> SlicerModel:
    """Read a ``.vtk``/``.vtp``/``.vtu`` model the way 3D Slicer does, with VTK's output silenced.

    Mirrors ``vtkMRMLModelStorageNode::ReadDataInternal``: a legacy ``.vtk`` file is polydata
    or an unstructured grid, its frame the ``SPACE=`` text of the header line; an XML file's
    frame is the ``SPACE`` string array of its field data; no statement means LPS.

    Raises:
        MeshFormatError: the file is missing, corrupt or holds no points.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshFormatError(f"model file '{path}' does not exist")
    ns = _vtk()[4]
    with quiet_vtk():
        data, space = _read_vtk_dataset(path)
    if data is None or data.GetNumberOfPoints() == 0:
        raise MeshFormatError(f"VTK read no points from '{path}': the file is empty, corrupt or truncated")
    points = ns.vtk_to_numpy(data.GetPoints().GetData()).astype(np.float64)
    if space == "RAS":
        points = points * np.array([-1.0, -1.0, 1.0])
    polygons = data.IsA("vtkPolyData")  # a surface (.vtk polydata, .vtp), else an unstructured grid
    cells = data.GetPolys() if polygons else data.GetCells()
    offsets = ns.vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64)
    connectivity = ns.vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)
    if polygons:
        types = np.full(len(offsets) - 1, _VTK_TRIANGLE, dtype=np.int64)
    else:
        types = np.array([data.GetCellType(i) for i in range(data.GetNumberOfCells())], dtype=np.int64)
    pd = data.GetPointData()
    point_data = {pd.GetArrayName(i): ns.vtk_to_numpy(pd.GetArray(i)) for i in range(pd.GetNumberOfArrays())}
    return SlicerModel(points, types, connectivity, offsets, point_data, space)


def read_model_space(path: str | Path) -> str | None:
    """The coordinate system a model file states (``"LPS"``/``"RAS"``) where 3D Slicer reads it; None if none."""
    return read_model_as_slicer(path).stated_space


def read_model(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points (LPS mm, converted from a stated RAS) and tetrahedra of a ``.vtu``/``.vtk`` model, read with VTK.

    Returns:
        ``(points (n, 3) float, tets (m, 4) int)``; cells other than tetrahedra are dropped.
    """
    model = read_model_as_slicer(path)
    return model.points, model.tets
