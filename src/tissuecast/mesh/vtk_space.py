"""The coordinate system a VTK file states where 3D Slicer reads it, and VTK read quietly.

3D Slicer (``vtkMRMLModelStorageNode``) reads a model file's frame from the header line of a
legacy ``.vtk`` file (``SPACE=LPS`` / ``SPACE=RAS``) and from the ``SPACE`` string array of
an XML file's field data; a file stating nothing is taken as LPS. :func:`file_space` reads it
the same way: the header line directly, a ``SPACE`` array written as text (tissuecast's
files) by decoding its character codes, any other (3D Slicer's binary arrays) with VTK.
"""

from __future__ import annotations

import logging
import re
from contextlib import contextmanager
from pathlib import Path

from ..errors import require

__all__ = ["file_space", "quiet_vtk", "SPACE_ARRAY"]

log = logging.getLogger(__name__)

#: the field-data array 3D Slicer reads the coordinate system of an XML model file from
SPACE_ARRAY = "SPACE"
_ASCII_SPACE = re.compile(rb'<Array\b[^>]*Name="SPACE"[^>]*format="ascii"[^>]*>([0-9\s]*)</Array>')


@contextmanager
def quiet_vtk():
    """VTK's error and warning output off inside the block (a corrupt file gives one clear error
    from the caller instead of VTK's parser dump); the previous setting is restored."""
    from vtkmodules.vtkCommonCore import vtkObject

    previous = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    try:
        yield
    finally:
        vtkObject.SetGlobalWarningDisplay(previous)


def _system(text: str) -> str | None:
    return "RAS" if "RAS" in text else "LPS" if "LPS" in text else None


def _xml_space_with_vtk(path: Path) -> str | None:
    require("vtkmodules", "viz", "Reading the SPACE array of a VTK XML file")
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLUnstructuredGridReader

    reader = vtkXMLPolyDataReader() if path.suffix.lower() == ".vtp" else vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    with quiet_vtk():
        reader.Update()
    data = reader.GetOutput()
    array = data.GetFieldData().GetAbstractArray(SPACE_ARRAY) if data is not None else None
    return _system(array.GetValue(0)) if array is not None and array.GetNumberOfValues() else None


def file_space(path: str | Path) -> str | None:
    """``"LPS"``/``"RAS"`` as a .vtk/.vtu/.vtp file states it where 3D Slicer looks; None if it states none.

    Without VTK (extra ``viz``), a binary ``SPACE`` array cannot be read: None, with a warning.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".vtk":
        with open(path, "rb") as fh:
            fh.readline()
            header = fh.readline()
        return "RAS" if b"SPACE=RAS" in header else "LPS" if b"SPACE=LPS" in header else None
    if suffix not in (".vtu", ".vtp"):
        return None
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if b'Name="SPACE"' not in head:
        return None
    text = _ASCII_SPACE.search(head)
    if text:
        return _system(bytes(int(c) for c in text.group(1).split()).decode("ascii", "replace"))
    try:
        return _xml_space_with_vtk(path)
    except ImportError as exc:  # DependencyError: VTK is not installed
        log.warning("'%s' states its coordinate system in a SPACE array that needs VTK to read (%s); taken as LPS",
                    path, exc)
        return None
