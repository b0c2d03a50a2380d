"""Files 3D Slicer reads and writes: markups (.mrk.json, .fcsv) and models (.vtk, .vtp, .vtu).

Everything tissuecast writes is in LPS mm and says so in the file, as Slicer does
(see :mod:`tissuecast.frames`).
"""

from .markups import MARKUPS_SCHEMA_URL, MarkupList, MarkupsError, markups_document, markups_schema, read_markups, write_markups

__all__ = ["MarkupList", "MarkupsError", "MARKUPS_SCHEMA_URL", "markups_schema", "markups_document", "read_markups",
           "write_markups"]
