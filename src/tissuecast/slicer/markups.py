"""3D Slicer markups: point lists in ``.mrk.json`` (read and write) and legacy ``.fcsv`` (read).

A ``.mrk.json`` file follows Slicer's published markups schema (v1.0.3, shipped in
``tissuecast/slicer/schema`` with 3D Slicer's licence): ``{"@schema": URL, "markups":
[{"type": "Fiducial", "name": ..., "coordinateSystem": "LPS" | "RAS", "coordinateUnits":
"mm", "controlPoints": [{"id", "label", "description", "position": [x, y, z],
"orientation", "selected", "locked", "visibility", "positionStatus"}, ...]}, ...]}``. Slicer
loads every list of such a file as one point-list node, named by ``name``.

In memory a :class:`MarkupList` always holds **LPS** mm (tissuecast's frame): files in RAS
are converted on reading, and the writer converts to the coordinate system asked for (by
negating x and y, so a round trip is exact). A point whose ``positionStatus`` is not
``defined`` (placed nowhere yet, or marked missing) reads as NaN: an untracked marker.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MarkupsError
from ..frames import COORDINATE_SYSTEMS, convert_points

__all__ = [
    "MarkupList",
    "MarkupsError",
    "MARKUPS_SCHEMA_URL",
    "markups_schema",
    "markups_document",
    "write_markups",
    "read_markups",
    "MARKUPS_SUFFIXES",
]

#: the schema URL Slicer writes into ``@schema`` (Slicer accepts any markups-schema-v1.x.y)
MARKUPS_SCHEMA_URL = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/"
    "markups-schema-v1.0.3.json#"
)
#: file name endings read as Slicer markups
MARKUPS_SUFFIXES = (".mrk.json", ".fcsv")
_SCHEMA_FILE = "markups-schema-v1.0.3.json"
# columns of a .fcsv file without a "# columns =" line (Slicer 4.x)
_FCSV_COLUMNS = ["id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc", "associatedNodeID"]
# a point's identity orientation (Slicer's default) as Slicer writes it in each system
_ORIENTATION = {"RAS": (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), "LPS": (-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0)}


@dataclass(frozen=True)
class MarkupList:
    """One named list of points (a Slicer point-list node).

    Attributes:
        name: the list's name (Slicer's node name).
        positions: (n, 3) float, LPS mm; NaN rows for points without a position.
        labels: n point labels (shown next to the points in Slicer).
        descriptions: n point descriptions.
    """

    name: str
    positions: np.ndarray
    labels: tuple[str, ...] = field(default=())
    descriptions: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        positions = np.array(self.positions, dtype=np.float64).reshape(-1, 3)
        n = len(positions)
        labels = tuple(self.labels) or tuple(f"{self.name}-{i + 1}" for i in range(n))
        descriptions = tuple(self.descriptions) or ("",) * n
        if len(labels) != n or len(descriptions) != n:
            raise MarkupsError(f"markup list {self.name!r}: {n} points but {len(labels)} labels and "
                               f"{len(descriptions)} descriptions")
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "descriptions", descriptions)


def markups_schema() -> dict:
    """Slicer's markups JSON schema (v1.0.3) as a dict, read from the packaged copy."""
    from importlib import resources

    return json.loads((resources.files("tissuecast.slicer") / "schema" / _SCHEMA_FILE).read_text(encoding="utf-8"))


def markups_document(lists: list[MarkupList], coordinate_system: str = "LPS") -> dict:
    """The ``.mrk.json`` content (a dict) of point lists, positions in ``coordinate_system``."""
    system = str(coordinate_system).upper()
    if system not in COORDINATE_SYSTEMS:
        raise MarkupsError(f"coordinate_system must be LPS or RAS, got {coordinate_system!r}")
    markups = []
    for markup in lists:
        positions = convert_points(markup.positions, "LPS", system)
        points = []
        for i, (xyz, label, description) in enumerate(zip(positions, markup.labels, markup.descriptions)):
            defined = bool(np.isfinite(xyz).all())
            point = {"id": str(i + 1), "label": label, "description": description, "associatedNodeID": ""}
            if defined:  # the schema wants 3 numbers; a point without position has no "position" key
                point["position"] = [float(v) for v in xyz]
            points.append({
                **point,
                "orientation": list(_ORIENTATION[system]),
                "selected": True,
                "locked": True,
                "visibility": True,
                "positionStatus": "defined" if defined else "undefined",
            })
        markups.append({
            "type": "Fiducial",
            "name": markup.name,
            "coordinateSystem": system,
            "coordinateUnits": "mm",
            "locked": True,
            "fixedNumberOfControlPoints": True,
            "labelFormat": "%N-%d",
            "lastUsedControlPointNumber": len(points),
            "controlPoints": points,
        })
    return {"@schema": MARKUPS_SCHEMA_URL, "markups": markups}


def write_markups(path: str | Path, lists: list[MarkupList], coordinate_system: str = "LPS") -> Path:
    """Write point lists as a Slicer ``.mrk.json`` file (positions in ``coordinate_system``)."""
    path = Path(path)
    if not path.name.lower().endswith(".mrk.json"):
        raise MarkupsError(f"a Slicer markups file must end in .mrk.json, got '{path.name}'")
    path.write_text(json.dumps(markups_document(lists, coordinate_system), indent=2) + "\n", encoding="utf-8")
    return path


def read_markups(path: str | Path) -> list[MarkupList]:
    """Read the point lists of a ``.mrk.json`` or ``.fcsv`` file, positions converted to LPS mm.

    Only ``Fiducial`` (point-list) markups are returned; lines, curves, planes... are skipped.

    Raises:
        MarkupsError: missing or malformed file, unknown coordinate system or units, or no
            point list in it.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"markups file '{path}' does not exist")
    name = path.name.lower()
    if name.endswith(".fcsv"):
        lists = [_read_fcsv(path)]
    elif name.endswith(".json"):
        lists = _read_json(path)
    else:
        raise MarkupsError(f"'{path}' is not a Slicer markups file; use " + " or ".join(MARKUPS_SUFFIXES))
    if not lists:
        raise MarkupsError(f"'{path}' holds no point list (markups of type Fiducial)")
    return lists


def _system(value, path: Path) -> str:
    system = {"0": "RAS", "1": "LPS"}.get(str(value).strip(), str(value).strip().upper())
    if system not in COORDINATE_SYSTEMS:
        raise MarkupsError(f"'{path}': unknown coordinate system {value!r}; Slicer writes LPS or RAS")
    return system


def _read_json(path: Path) -> list[MarkupList]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MarkupsError(f"'{path}' is not valid JSON: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("markups"), list):
        raise MarkupsError(f"'{path}' is not a Slicer markups file: no 'markups' list at its top level")
    lists = []
    for index, markup in enumerate(doc["markups"]):
        if not isinstance(markup, dict) or markup.get("type") != "Fiducial":
            continue
        system = _system(markup.get("coordinateSystem", "LPS"), path)
        units = markup.get("coordinateUnits", "mm")
        if units not in ("mm", ["mm", "UCUM", "millimeter"]):
            raise MarkupsError(f"'{path}': markup {index} is in {units!r}; tissuecast reads markups in mm")
        positions, labels, descriptions = [], [], []
        for k, point in enumerate(markup.get("controlPoints", [])):
            status = point.get("positionStatus", "defined")
            xyz = point.get("position", "")
            if status == "defined":
                try:
                    xyz = [float(v) for v in xyz]
                except (TypeError, ValueError):
                    xyz = []
                if len(xyz) != 3:
                    raise MarkupsError(f"'{path}': point {k} of markup {index} has position {point.get('position')!r}; "
                                       "three numbers are needed")
            else:
                xyz = [np.nan] * 3
            positions.append(xyz)
            labels.append(str(point.get("label", "")))
            descriptions.append(str(point.get("description", "")))
        lps = convert_points(np.array(positions, dtype=np.float64).reshape(-1, 3), system, "LPS")
        name = str(markup.get("name", f"{path.name.split('.')[0]}-{index}"))
        lists.append(MarkupList(name, lps, tuple(labels), tuple(descriptions)))
    return lists


def _read_fcsv(path: Path) -> MarkupList:
    system = "RAS"  # .fcsv files older than Slicer 4.11 state none and are RAS
    columns = _FCSV_COLUMNS
    positions, labels, descriptions = [], [], []
    with path.open(newline="", encoding="utf-8") as fh:
        for number, row in enumerate(csv.reader(fh), start=1):
            if not row or not "".join(row).strip():
                continue
            if row[0].startswith("#"):
                key, _, value = ",".join(row).lstrip("#").partition("=")
                if key.strip() == "CoordinateSystem":
                    system = _system(value, path)
                elif key.strip() == "columns":
                    columns = [c.strip() for c in value.split(",")]
                continue
            record = dict(zip(columns, row))
            try:
                xyz = [float(record[c]) for c in ("x", "y", "z")]
            except (KeyError, ValueError):
                raise MarkupsError(f"'{path}' line {number}: no numeric x, y, z in {row}") from None
            positions.append(xyz)
            labels.append(record.get("label", ""))
            descriptions.append(record.get("desc", ""))
    lps = convert_points(np.array(positions, dtype=np.float64).reshape(-1, 3), system, "LPS")
    return MarkupList(path.name[: -len(".fcsv")], lps, tuple(labels), tuple(descriptions))
