"""OpenIGTLink POLYDATA messages: a pre-packed encoder for replies and a full decoder.

Body layout (OpenIGTLink 2/3 POLYDATA, all big-endian)::

    uint32 x 10   NPOINTS, NVERTICES, SIZE_VERTICES, NLINES, SIZE_LINES, NPOLYGONS,
                  SIZE_POLYGONS, NTRIANGLE_STRIPS, SIZE_TRIANGLE_STRIPS, NATTRIBUTES
    float32       POINTS (NPOINTS x 3)
    uint32        VERTICES, LINES, POLYGONS, TRIANGLE_STRIPS: cells as (count, id0, id1, ...)
    per attribute: uint8 type, uint8 components, uint32 n          (6 bytes each)
    attribute names, each NUL-terminated, plus one padding byte if their total length is odd
    float32       attribute data, one block per attribute

Attribute types: 0 scalars (1..255 components), 1 vectors (3), 2 normals (3), 3 tensors (9),
4 RGBA (4); +0x10 for cell data. pyigtl 0.3.4 packs POLYDATA without attributes and cannot
unpack it; :func:`decode_polydata` fills that gap.

:class:`PolyDataTemplate` packs everything that does not change (header words, cells,
attribute headers and names) once; per reply only the point coordinates and attribute
values are written into the same buffer, and the CRC hashes only those bytes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from .crc import SegmentedCrc
from .protocol import HEADER_SIZE, ProtocolError, pack_header

__all__ = ["ATTRIBUTE_TYPES", "PolyData", "PolyDataTemplate", "decode_polydata"]

_COUNTS = struct.Struct("> 10I")
_ATTRIBUTE_HEADER = struct.Struct("> B B I")
#: attribute kind -> (type code, components); scalars may have other component counts
ATTRIBUTE_TYPES = {"scalars": (0x00, 1), "vectors": (0x01, 3), "normals": (0x02, 3), "tensors": (0x03, 9), "rgba": (0x04, 4)}
_KIND_OF_CODE = {code: kind for kind, (code, _) in ATTRIBUTE_TYPES.items()}


def _cells(triangles: np.ndarray) -> np.ndarray:
    """(k, 3) triangles -> flat (4 k,) uint32 array of (3, i, j, k) records."""
    out = np.empty((len(triangles), 4), dtype=np.uint32)
    out[:, 0] = 3
    out[:, 1:] = triangles
    return out.ravel()


class PolyDataTemplate:
    """A POLYDATA message whose topology is fixed and whose values are refilled per reply.

    Args:
        n_points: number of points.
        triangles: (k, 3) int, 0-based point ids of the polygons (all triangles).
        attributes: ``[(name, kind), ...]`` point-data attributes, kind in
            ``"scalars"`` (1 component) or ``"vectors"`` (3 components); ASCII names.

    Attributes:
        points: (n_points, 3) big-endian float32 view into the message buffer (mm); write
            the coordinates here.
        values: dict name -> (n_points,) or (n_points, 3) big-endian float32 view.
    """

    def __init__(self, n_points: int, triangles: np.ndarray, attributes: list[tuple[str, str]] = ()):
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if len(triangles) and (triangles.min() < 0 or triangles.max() >= n_points):
            raise ValueError(f"triangle ids must lie in [0, {n_points}); got [{triangles.min()}, {triangles.max()}]")
        polygons = _cells(triangles)
        specs = []
        for name, kind in attributes:
            code, ncomp = ATTRIBUTE_TYPES[kind]
            specs.append((name.encode("ascii"), code, ncomp))
        names = b"".join(name + b"\0" for name, _, _ in specs)
        if len(names) % 2:
            names += b"\0"
        counts = (n_points, 0, 0, 0, 0, len(triangles), 4 * polygons.size, 0, 0, len(specs))
        static = bytearray(_COUNTS.pack(*counts))
        points_at = HEADER_SIZE + len(static)
        static += bytes(12 * n_points)
        static += polygons.astype(">u4").tobytes()
        for _, code, ncomp in specs:
            static += _ATTRIBUTE_HEADER.pack(code, ncomp, n_points)
        static += names
        value_at = []
        for _, _, ncomp in specs:
            value_at.append((HEADER_SIZE + len(static), ncomp))
            static += bytes(4 * ncomp * n_points)
        self.buffer = bytearray(bytes(HEADER_SIZE) + static)
        self.body_size = len(static)
        self.points = np.frombuffer(self.buffer, dtype=">f4", count=3 * n_points, offset=points_at).reshape(n_points, 3)
        self.values = {}
        segments = [(points_at - HEADER_SIZE, points_at - HEADER_SIZE + 12 * n_points)]
        for (name, _, _), (at, ncomp) in zip(specs, value_at):
            view = np.frombuffer(self.buffer, dtype=">f4", count=ncomp * n_points, offset=at)
            self.values[name.decode()] = view if ncomp == 1 else view.reshape(n_points, ncomp)
            segments.append((at - HEADER_SIZE, at - HEADER_SIZE + 4 * ncomp * n_points))
        self._crc = SegmentedCrc(memoryview(self.buffer)[HEADER_SIZE:], segments)

    def finish(self, device_name: str, timestamp: float) -> memoryview:
        """Write the header for the current values and return the whole message.

        The returned view aliases the template's buffer: send or copy it before the next
        call refills the values.
        """
        crc = self._crc.compute(memoryview(self.buffer)[HEADER_SIZE:])
        self.buffer[:HEADER_SIZE] = pack_header("POLYDATA", device_name, timestamp, self.body_size, crc)
        return memoryview(self.buffer)


@dataclass(frozen=True)
class PolyData:
    """A decoded POLYDATA message.

    Attributes:
        points: (n, 3) float32, mm.
        vertices, lines, polygons, triangle_strips: lists of int64 arrays of point ids, one
            array per cell.
        point_data, cell_data: dict name -> float32 array, (n,) for single-component
            scalars, else (n, components).
    """

    points: np.ndarray
    vertices: list = field(default_factory=list)
    lines: list = field(default_factory=list)
    polygons: list = field(default_factory=list)
    triangle_strips: list = field(default_factory=list)
    point_data: dict = field(default_factory=dict)
    cell_data: dict = field(default_factory=dict)

    def triangles(self) -> np.ndarray:
        """(k, 3) int64 point ids of the polygons; raises ValueError if one is not a triangle."""
        if any(len(p) != 3 for p in self.polygons):
            raise ValueError("not every polygon is a triangle")
        return np.array(self.polygons, dtype=np.int64).reshape(-1, 3)


def _read_cells(data: np.ndarray, count: int, n_points: int, what: str) -> list:
    if count and data.size and data.size % count == 0:  # fast path: cells of one size
        width = data.size // count
        table = data.reshape(count, width).astype(np.int64)
        if (table[:, 0] == width - 1).all():
            ids = table[:, 1:]
            if ids.size and ids.max() >= n_points:
                raise ProtocolError(f"POLYDATA {what}: point id {ids.max()} >= {n_points} points")
            return list(ids)
    cells, at = [], 0
    for _ in range(count):
        if at >= data.size:
            raise ProtocolError(f"POLYDATA {what}: {count} cells announced, data ends after {len(cells)}")
        size = int(data[at])
        if at + 1 + size > data.size:
            raise ProtocolError(f"POLYDATA {what}: cell {len(cells)} of {size} points runs past its data")
        ids = data[at + 1 : at + 1 + size].astype(np.int64)
        if size and ids.max() >= n_points:
            raise ProtocolError(f"POLYDATA {what}: point id {ids.max()} >= {n_points} points")
        cells.append(ids)
        at += 1 + size
    if at != data.size:
        raise ProtocolError(f"POLYDATA {what}: {data.size - at} values left after {count} cells")
    return cells


def decode_polydata(content) -> PolyData:
    """Decode a POLYDATA message body (content part, without extended header/metadata).

    Raises:
        ProtocolError: any size or index that does not fit the content.
    """
    content = memoryview(content).cast("B")
    if len(content) < _COUNTS.size:
        raise ProtocolError(f"POLYDATA content of {len(content)} bytes is shorter than its 40-byte header")
    counts = _COUNTS.unpack_from(content)
    n_points, n_attributes = counts[0], counts[9]
    at = _COUNTS.size

    def take(n_bytes: int, what: str) -> memoryview:
        nonlocal at
        if n_bytes < 0 or at + n_bytes > len(content):
            raise ProtocolError(f"POLYDATA {what} ({n_bytes} bytes at {at}) runs past the {len(content)}-byte content")
        chunk = content[at : at + n_bytes]
        at += n_bytes
        return chunk

    points = np.frombuffer(take(12 * n_points, "points"), dtype=">f4").astype(np.float32).reshape(n_points, 3)
    cells = []
    for index, what in enumerate(("vertices", "lines", "polygons", "triangle strips")):
        count, size = counts[1 + 2 * index], counts[2 + 2 * index]
        if size % 4:
            raise ProtocolError(f"POLYDATA {what} size {size} is not a multiple of 4")
        data = np.frombuffer(take(size, what), dtype=">u4")
        cells.append(_read_cells(data, count, n_points, what))
    headers = [_ATTRIBUTE_HEADER.unpack(take(6, "attribute header")) for _ in range(n_attributes)]
    names = []
    for _ in range(n_attributes):
        rest = bytes(content[at : at + 256])
        end = rest.find(b"\0")
        if end < 0:
            raise ProtocolError("POLYDATA attribute name is not NUL-terminated within 255 bytes")
        names.append(take(end + 1, "attribute name")[:end].tobytes().decode("ascii", "replace"))
    if sum(len(n) + 1 for n in names) % 2:
        take(1, "attribute name padding")
    point_data, cell_data = {}, {}
    n_cells = sum(len(c) for c in cells)
    for (code, ncomp, n), name in zip(headers, names):
        kind = _KIND_OF_CODE.get(code & 0x0F)
        if kind is None or code & 0xE0:
            raise ProtocolError(f"POLYDATA attribute {name!r} has unknown type {code:#04x}")
        ncomp = ncomp if kind == "scalars" else ATTRIBUTE_TYPES[kind][1]
        target, expected = (cell_data, n_cells) if code & 0x10 else (point_data, n_points)
        if n != expected:
            raise ProtocolError(f"POLYDATA attribute {name!r} has {n} values for {expected} points/cells")
        values = np.frombuffer(take(4 * ncomp * n, f"attribute {name!r}"), dtype=">f4").astype(np.float32)
        target[name] = values if ncomp == 1 else values.reshape(n, ncomp)
    if at != len(content):
        raise ProtocolError(f"POLYDATA content has {len(content) - at} unexplained trailing bytes")
    return PolyData(points, *cells, point_data=point_data, cell_data=cell_data)
