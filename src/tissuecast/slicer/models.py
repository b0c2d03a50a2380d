"""Meshes and fields as model files 3D Slicer opens in the right frame (.vtk, .vtp, .vtu).

Slicer reads the coordinate system of a model file from the file itself: the header line
of a legacy ``.vtk`` file (``... SPACE=LPS``) or a string array ``SPACE`` in the field data
of an XML ``.vtu``/``.vtp`` file; without it Slicer assumes LPS and warns. Every file
written here states ``SPACE=LPS`` (tissuecast's frame) that way, so it overlays the scan it
was made from without a manual transform. Files are written with VTK itself (the library
Slicer reads them with), imported lazily (extra ``viz``).

- ``.vtu`` / ``.vtk``: the tetrahedral mesh (VTK_TETRA cells), optionally deformed, with
  point data (e.g. ``displacement_mm``).
- ``.vtp``: the outer surface (triangles), optionally deformed, with the point data of the
  surface vertices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import MeshFormatError, require
from ..mesh.tetmesh import TetMesh

__all__ = ["MODEL_SUFFIXES", "write_model", "read_model", "read_model_space"]

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
) -> Path:
    """Write a mesh (or its outer surface) as a 3D Slicer model file in LPS.

    Args:
        path: ``.vtu`` or ``.vtk`` (tetrahedra) or ``.vtp`` (outer surface triangles).
        mesh: the mesh, LPS mm.
        displacement: (n, 3) float, mm: write the deformed mesh and add it as point data
            ``displacement_mm``.
        point_data: name -> (n,) or (n, k) array per mesh vertex (mm where lengths).

    Returns:
        The file written.
    """
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
        if len(values) != mesh.n_points:
            raise MeshFormatError(f"point data {name!r} has {len(values)} rows for {mesh.n_points} vertices")
    _, _, legacy, xml, ns = _vtk()
    if suffix == ".vtp":
        ids = mesh.surface_vertices
        local = np.searchsorted(ids, mesh.surface_triangles)
        dataset = _dataset(points[ids], local, _VTK_TRIANGLE, {k: np.asarray(v)[ids] for k, v in data.items()}, True)
    else:
        dataset = _dataset(points, mesh.tets, _VTK_TETRA, data, False)
    if suffix == ".vtk":
        writer = legacy.vtkUnstructuredGridWriter()
        writer.SetHeader(f"tissuecast output. {_SPACE}=LPS")
        writer.SetFileTypeToBinary()
        writer.SetFileVersion(42)  # what Slicer writes: readable by Slicer 4 and 5
    else:
        core = _vtk()[0]
        space = core.vtkStringArray()
        space.SetName(_SPACE)
        space.InsertNextValue("LPS")
        dataset.GetFieldData().AddArray(space)
        writer = xml.vtkXMLPolyDataWriter() if suffix == ".vtp" else xml.vtkXMLUnstructuredGridWriter()
        writer.SetDataModeToBinary()
    writer.SetInputData(dataset)
    writer.SetFileName(str(path))
    if not writer.Write():
        raise MeshFormatError(f"VTK could not write '{path}'")
    return path


def read_model_space(path: str | Path) -> str | None:
    """The coordinate system a model file states (``"LPS"``/``"RAS"``), as 3D Slicer reads it; None if none.

    Mirrors Slicer's ``vtkMRMLModelStorageNode``: the legacy header for ``.vtk``, the
    ``SPACE`` field-data string for ``.vtu``/``.vtp``.
    """
    path = Path(path)
    _, _, legacy, xml, _ = _vtk()
    suffix = path.suffix.lower()
    if suffix == ".vtk":
        reader = legacy.vtkDataReader()
        reader.SetFileName(str(path))
        reader.OpenVTKFile()
        reader.ReadHeader()
        header = reader.GetHeader() or ""
        reader.CloseVTKFile()
        return "RAS" if "SPACE=RAS" in header else "LPS" if "SPACE=LPS" in header else None
    reader = xml.vtkXMLPolyDataReader() if suffix == ".vtp" else xml.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    array = reader.GetOutput().GetFieldData().GetAbstractArray(_SPACE)
    if array is None or array.GetNumberOfValues() < 1:
        return None
    value = array.GetValue(0)
    return "RAS" if "RAS" in value else "LPS" if "LPS" in value else None


def read_model(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points and tetrahedra of a ``.vtu``/``.vtk`` unstructured grid, read with VTK, as stored.

    Returns:
        ``(points (n, 3) float, tets (m, 4) int)``; cells other than tetrahedra are dropped.
    """
    _, _, legacy, xml, ns = _vtk()
    path = Path(path)
    reader = legacy.vtkUnstructuredGridReader() if path.suffix.lower() == ".vtk" else xml.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    if grid is None or grid.GetNumberOfPoints() == 0:
        raise MeshFormatError(f"VTK found no unstructured grid in '{path}'")
    points = ns.vtk_to_numpy(grid.GetPoints().GetData()).astype(np.float64)
    try:
        types = ns.vtk_to_numpy(grid.GetCellTypes())  # VTK >= 9.6
    except TypeError:
        types = ns.vtk_to_numpy(grid.GetCellTypesArray())
    offsets = ns.vtk_to_numpy(grid.GetCells().GetOffsetsArray())
    connectivity = ns.vtk_to_numpy(grid.GetCells().GetConnectivityArray())
    tets = np.array([connectivity[offsets[i]: offsets[i] + 4] for i in np.flatnonzero(types == _VTK_TETRA)], dtype=np.int64)
    return points, tets.reshape(-1, 4)
