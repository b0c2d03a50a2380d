"""meshio's readers called quietly: one clear error, no library output, no ``sys.exit``.

``meshio.read`` prints to stderr and calls ``sys.exit`` when a file cannot be read, and its
readers print warnings of their own; its VTU reader refuses any string array, such as the
``SPACE`` array 3D Slicer writes into the field data of a ``.vtu`` file to state its
coordinate system. :func:`read_with_meshio` calls the format's reader directly with Python's
stdout and stderr captured (what meshio printed is logged at debug level), reads a ``.vtu``
file's string arrays as if absent, and turns any failure into one
:class:`~tissuecast.errors.MeshFormatError` naming the file, its format and the cause.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import tempfile
from pathlib import Path

import numpy as np

from ..errors import MeshFormatError

__all__ = ["FORMAT_NAMES", "read_with_meshio", "strip_string_arrays"]

log = logging.getLogger(__name__)

#: meshio format name -> what the file is, in messages
FORMAT_NAMES = {
    "vtu": "a VTK XML unstructured grid (.vtu)", "vtk": "a legacy VTK file (.vtk)", "gmsh": "a gmsh mesh (.msh)",
    "abaqus": "an Abaqus/CalculiX input deck (.inp)", "medit": "a Medit mesh (.mesh)", "xdmf": "an XDMF file (.xdmf)",
    "stl": "an STL surface (.stl)", "obj": "a Wavefront OBJ surface (.obj)", "ply": "a PLY surface (.ply)",
    "off": "an OFF surface (.off)",
}
#: longest cause quoted from the library's exception
_CAUSE_CHARS = 160
# VTK XML string arrays (self-closing, or with inline content); only searched before <AppendedData
_STRING_ARRAY = re.compile(rb'<(?:Data)?Array\b[^>]*\btype="String"[^>]*?(?:/>|>.*?</(?:Data)?Array>)', re.DOTALL)


def _cause(exc: BaseException) -> str:
    """One line saying why a library failed, at most :data:`_CAUSE_CHARS` characters."""
    if isinstance(exc, UnicodeDecodeError):
        text = "binary data where text was expected"
    elif isinstance(exc, SystemExit):
        text = "the reader gave up"
    else:
        text = " ".join(str(exc).split())
    if len(text) > _CAUSE_CHARS:
        text = text[: _CAUSE_CHARS - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _quiet_call(reader, path: Path):
    """``reader(path)`` with Python's stdout/stderr captured and logged at debug level."""
    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink), np.errstate(over="ignore"):
            return reader(str(path))  # errstate: meshio's STL sniffing multiplies a uint32
    finally:
        if sink.getvalue().strip():
            log.debug("meshio on '%s': %s", path, " ".join(sink.getvalue().split()))


def strip_string_arrays(data: bytes) -> bytes | None:
    """A VTK XML file's bytes without its string arrays (e.g. 3D Slicer's ``SPACE``); None if it has none.

    Only the XML part before ``<AppendedData`` is edited: the appended block is addressed by
    offsets from its own start, so the other arrays stay where their offsets say.
    """
    cut = data.find(b"<AppendedData")
    head, tail = (data, b"") if cut < 0 else (data[:cut], data[cut:])
    stripped, count = _STRING_ARRAY.subn(b"", head)
    return stripped + tail if count else None


def _read_without_strings(path: Path, reader):
    """A .vtu file read after dropping its string arrays (None when it has none)."""
    stripped = strip_string_arrays(path.read_bytes())
    if stripped is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / path.name
        copy.write_bytes(stripped)
        return _quiet_call(reader, copy)


def read_with_meshio(path: Path, fmt: str, tolerant: bool = True):
    """Read ``path`` with meshio's reader of format ``fmt`` (a :data:`FORMAT_NAMES` key).

    Returns:
        The ``meshio.Mesh``.

    Raises:
        MeshFormatError: the file is empty, or the reader failed in any way (the message
            names the file, the format and the cause, on one line).
    """
    import meshio

    what = FORMAT_NAMES.get(fmt, f"a {fmt} file")
    if path.stat().st_size == 0:
        raise MeshFormatError(f"mesh file '{path}' is empty (0 bytes); expected {what}")
    reader = meshio._helpers.reader_map[fmt]
    try:
        return _quiet_call(reader, path)
    except (Exception, SystemExit) as exc:  # meshio raises many kinds (ReadError, ValueError...) and may exit
        first = exc
    retry = None
    try:
        if fmt == "vtu" and "String" in str(first):
            retry = _read_without_strings(path, reader)
        elif tolerant and fmt == "abaqus" and "Element type not available" in str(first):
            retry = _read_inp_tolerant(path)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - reported below with the first cause
        log.debug("second attempt on '%s' failed too: %s", path, _cause(exc))
    if retry is not None:
        return retry
    raise MeshFormatError(f"could not read '{path}' as {what}: the file is corrupt, truncated or of another "
                          f"format ({_cause(first)})") from first


def _read_inp_tolerant(path: Path):
    """Abaqus/CalculiX deck whose *ELEMENT blocks meshio does not know (e.g. gmsh's CPS6
    second-order triangles): drop those blocks (logged) and read the rest; None if none."""
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
        return read_with_meshio(filtered, "abaqus", tolerant=False)
