"""Reading a written mesh or model file back with every tool that reads its kind (meshio,
pyvista, VTK, the way 3D Slicer reads it): shared by the file tests of mesh/ and evaluate/.
Needs meshio, pyvista and VTK (skip the test before calling)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def vtk_read(path: Path):
    """points (n, 3) and point-data names of a file read with VTK's own reader for its kind."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOLegacy import vtkUnstructuredGridReader
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLUnstructuredGridReader

    reader = {".vtu": vtkXMLUnstructuredGridReader, ".vtp": vtkXMLPolyDataReader,
              ".vtk": vtkUnstructuredGridReader}[path.suffix.lower()]()
    reader.SetFileName(str(path))
    if path.suffix.lower() == ".vtk":
        reader.ReadAllScalarsOn()
        reader.ReadAllVectorsOn()
        reader.ReadAllFieldsOn()
    reader.Update()
    data = reader.GetOutput()
    pd = data.GetPointData()
    return vtk_to_numpy(data.GetPoints().GetData()), {pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())}


def read_everywhere(path: Path, points: np.ndarray, point_data: tuple = ()) -> dict:
    """Read ``path`` with every tool that reads its kind; each must give ``points`` (LPS mm) and
    the point data named. Returns what each tool saw (for the .vtu/.vtk/.vtp: the frame Slicer reads)."""
    import meshio
    import pyvista as pv

    path = Path(path)
    suffix = path.suffix.lower()
    seen = {}
    if suffix != ".vtp":  # meshio has no .vtp reader
        m = meshio.read(path)
        np.testing.assert_allclose(m.points, points, atol=1e-6)
        assert set(point_data) <= set(m.point_data), (path, sorted(m.point_data))
        seen["meshio"] = m
    # pyvista.read takes .inp for AVS UCD and reads meshio's XDMF with VTK's XDMF2 reader: both
    # fail; pyvista.read_meshio is its way for them (docs/files.md)
    grid = pv.read_meshio(path) if suffix in (".inp", ".xdmf") else pv.read(path)
    np.testing.assert_allclose(grid.points, points, atol=1e-5)
    assert set(point_data) <= set(grid.point_data.keys()), (path, grid.point_data.keys())
    seen["pyvista"] = grid
    if suffix in (".vtu", ".vtk", ".vtp"):
        from tissuecast.slicer.models import read_model_as_slicer

        vtk_points, names = vtk_read(path)
        np.testing.assert_allclose(vtk_points, points, atol=1e-5)
        assert set(point_data) <= names
        slicer = read_model_as_slicer(path)  # vtkMRMLModelStorageNode's reading: no frame stated = LPS
        assert slicer.stated_space in ("LPS", None) and (slicer.stated_space == "LPS" or suffix == ".vtu")
        np.testing.assert_allclose(slicer.points, points, atol=1e-5)  # so it overlays the scan in Slicer
        seen["slicer"] = slicer
    return seen
