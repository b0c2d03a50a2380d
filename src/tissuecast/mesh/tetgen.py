"""TetGen ``.node`` / ``.ele`` / ``.face`` files (the format the paper's authors use).

Format (https://wias-berlin.de/software/tetgen/fformats.html); ``#`` starts a comment.

- ``.node``: header ``<#points> 3 <#attributes> <0|1 boundary marker>``, then one line per
  point ``<id> <x> <y> <z> [attributes...] [marker]``. Ids may start at 0 or 1 (TetGen's
  ``-z`` switch); the reader follows the first id in the file.
- ``.ele``: header ``<#tets> <4|10> <#attributes>``, then ``<id> <n1> ... <n4|n10>
  [attributes...]``. Quadratic (10-node) tets are reduced to their 4 corner nodes (TetGen
  writes corners first). Region attributes are returned per tet and otherwise unused.
- ``.face``: header ``<#faces> <0|1 boundary marker>``, then ``<id> <n1> <n2> <n3> [marker]``.

The writer emits 1-based ids (TetGen's default) and a ``.face`` file with the outer surface.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import MeshFormatError

__all__ = ["read_tetgen", "read_tetgen_surface", "write_tetgen"]


def _table(path: Path) -> tuple[list[str], np.ndarray]:
    """Header fields and the numeric rows (ragged rows are an error) of a TetGen file."""
    if not path.is_file():
        raise MeshFormatError(f"TetGen file '{path}' does not exist (a TetGen mesh needs both .node and .ele)")
    lines = []
    for raw in path.read_text(encoding="utf-8", errors="replace").splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            lines.append(line.split())
    if not lines:
        raise MeshFormatError(f"TetGen file '{path}' is empty")
    header, rows = lines[0], lines[1:]
    try:
        count = int(header[0])
    except ValueError as exc:
        shown = " ".join(header)
        shown = ascii(shown[:40] + ("..." if len(shown) > 40 else ""))
        raise MeshFormatError(f"TetGen file '{path}': bad header line {shown}; the file is corrupt or not a TetGen file") from exc
    rows = rows[:count]
    if len(rows) < count or len({len(r) for r in rows}) > 1:
        raise MeshFormatError(
            f"TetGen file '{path}': header announces {count} rows but the file has {len(rows)} "
            "rows of consistent length; the file is truncated or malformed"
        )
    try:
        table = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise MeshFormatError(f"TetGen file '{path}' holds non-numeric values: {exc}") from exc
    return header, table.reshape(count, -1)


def _read_nodes(path: Path) -> tuple[np.ndarray, np.ndarray]:
    header, t = _table(path)
    if len(header) > 1 and header[1] != "3":
        raise MeshFormatError(f"TetGen file '{path}' has dimension {header[1]}; only 3D meshes are supported")
    if t.shape[1] < 4:
        raise MeshFormatError(f"TetGen file '{path}': point lines need an id and x y z")
    return t[:, 0].astype(np.int64), t[:, 1:4]


def _to_rows(ids: np.ndarray, refs: np.ndarray, path: Path) -> np.ndarray:
    """Map TetGen point ids (0- or 1-based, as in the .node file) to 0-based row numbers."""
    if np.array_equal(ids, np.arange(ids[0], ids[0] + len(ids))):
        rows = refs - ids[0]
    else:
        order = np.argsort(ids)
        pos = np.clip(np.searchsorted(ids[order], refs), 0, len(ids) - 1)
        rows = np.where(ids[order][pos] == refs, order[pos], -1)
    bad = (rows < 0) | (rows >= len(ids))
    if bad.any():
        raise MeshFormatError(
            f"TetGen file '{path}' refers to point id {int(refs[bad][0])}, which the .node file "
            f"does not define (its ids run from {int(ids.min())} to {int(ids.max())})"
        )
    return rows


def read_tetgen(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``base.node`` and ``base.ele`` (``path`` may name either, or ``base``).

    Returns:
        points (n, 3) float in the file's unit, tets (m, 4) int 0-based rows of ``points``,
        attributes (m, a) float region attributes of each tet (a may be 0).
    """
    base = Path(path).with_suffix("") if Path(path).suffix.lower() in (".node", ".ele", ".face") else Path(path)
    ids, points = _read_nodes(base.with_suffix(".node"))
    ele = base.with_suffix(".ele")
    header, t = _table(ele)
    per = int(header[1]) if len(header) > 1 else 4
    if per not in (4, 10):
        raise MeshFormatError(f"TetGen file '{ele}' has {per} nodes per tetrahedron; 4 or 10 expected")
    n_attr = int(header[2]) if len(header) > 2 else 0
    if t.shape[1] < 1 + per + n_attr:
        raise MeshFormatError(f"TetGen file '{ele}': lines are shorter than the header announces")
    tets = _to_rows(ids, t[:, 1:5].astype(np.int64), ele)
    return points, tets, t[:, 1 + per:1 + per + n_attr]


def read_tetgen_surface(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``base.node`` and ``base.face`` as a triangulated surface.

    Returns:
        points (n, 3) float in the file's unit, triangles (k, 3) int 0-based.
    """
    base = Path(path).with_suffix("")
    ids, points = _read_nodes(base.with_suffix(".node"))
    face = base.with_suffix(".face")
    _, t = _table(face)
    if t.shape[1] < 4:
        raise MeshFormatError(f"TetGen file '{face}': face lines need an id and three point ids")
    return points, _to_rows(ids, t[:, 1:4].astype(np.int64), face)


def write_tetgen(path: str | Path, points: np.ndarray, tets: np.ndarray | None, surface: np.ndarray) -> list[Path]:
    """Write ``base.node``, ``base.ele`` (unless ``tets`` is None) and ``base.face``, 1-based ids.

    Args:
        path: any of ``base.node``, ``base.ele``, ``base.face``.
        points: (n, 3) float, mm.
        tets: (m, 4) int, 0-based, or None to write only the surface (.node + .face).
        surface: (k, 3) int, 0-based outer-surface triangles (boundary marker 1).

    Returns:
        The paths written.
    """
    base = Path(path).with_suffix("")
    n, k = len(points), len(surface)
    out = [base.with_suffix(".node")]
    with open(out[0], "w", encoding="utf-8") as fh:
        fh.write(f"# written by tissuecast; units mm; ids 1-based\n{n} 3 0 0\n")
        np.savetxt(fh, np.c_[np.arange(1, n + 1), points], fmt=["%d"] + ["%.17g"] * 3)
    if tets is not None:
        out.append(base.with_suffix(".ele"))
        with open(out[-1], "w", encoding="utf-8") as fh:
            fh.write(f"{len(tets)} 4 0\n")
            np.savetxt(fh, np.c_[np.arange(1, len(tets) + 1), np.asarray(tets) + 1], fmt="%d")
    out.append(base.with_suffix(".face"))
    with open(out[-1], "w", encoding="utf-8") as fh:
        fh.write(f"{k} 1\n")
        np.savetxt(fh, np.c_[np.arange(1, k + 1), np.asarray(surface) + 1, np.ones(k, dtype=np.int64)], fmt="%d")
    return out
