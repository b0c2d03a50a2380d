"""Files 3D Slicer reads and writes: markups (.mrk.json, .fcsv) and models (.vtk, .vtp, .vtu).

Everything tissuecast writes is in LPS mm (see :mod:`tissuecast.frames`) and says so where
Slicer reads it: the header of a ``.vtk`` model, the ``SPACE`` array of a ``.vtp`` model, the
``coordinateSystem`` of a ``.mrk.json`` list; a ``.vtu`` says so only on request, since meshio
cannot read the array (Slicer then takes LPS, its default; docs/files.md).
"""

from .markups import MARKUPS_SCHEMA_URL, MarkupList, MarkupsError, markups_document, markups_schema, read_markups, write_markups

__all__ = ["MarkupList", "MarkupsError", "MARKUPS_SCHEMA_URL", "markups_schema", "markups_document", "read_markups",
           "write_markups"]
