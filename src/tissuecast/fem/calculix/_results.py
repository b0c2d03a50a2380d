"""Readers of CalculiX result files: displacements (``.dat``, ``.frd``) and progress (``.sta``,
standard output). Node k of a file is row k - 1 of the arrays returned (0-based vertex k - 1).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import MeshFormatError

__all__ = ["StaSummary", "read_sta", "read_displacements", "residual_history"]

_FLOAT = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
_DAT_HEADER = re.compile(r"^\s*displacements \(vx,vy,vz\) for set (\S+) and time\s+(\S+)", re.I)
_STA_ROW = re.compile(r"^\s*(\d+)\s+(\d+)\s+(\d+)(U?)\s+(\d+)\s+(\S+)\s+(\S+)\s+(\S+)\s*$")


@dataclass(frozen=True)
class StaSummary:
    """Progress of a CalculiX step read from its ``.sta`` file.

    Attributes:
        increments: converged increments.
        iterations: Newton iterations of all attempts (each one a factorisation in ccx).
        cutbacks: failed attempts (increment reattempted with a smaller size).
        load_fraction: total time of the last converged increment (step period 1 = full load).
    """

    increments: int = 0
    iterations: int = 0
    cutbacks: int = 0
    load_fraction: float = 0.0


def read_sta(path) -> StaSummary:
    """Parse a ``.sta`` file (missing or empty file: nothing done yet)."""
    path = Path(path)
    if not path.exists():
        return StaSummary()
    inc, its, cut, frac = 0, 0, 0, 0.0
    for line in path.read_text(errors="replace").splitlines():
        m = _STA_ROW.match(line)
        if not m:
            continue
        its += int(m.group(5))
        if m.group(4):
            cut += 1
        else:
            inc += 1
            frac = float(m.group(6))
    return StaSummary(inc, its, cut, frac)


def residual_history(log_text: str) -> tuple[float, ...]:
    """Largest residual force component (N) after every iteration, from ccx's standard output."""
    return tuple(float(m) for m in re.findall(r"largest residual force=\s*(\S+)", log_text))


def _dat_blocks(text: str):
    """Yield (set name, time, ids (k,), values (k, 3)) for each displacement block of a .dat file."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = _DAT_HEADER.match(lines[i])
        i += 1
        if not m:
            continue
        ids, vals = [], []
        while i < len(lines) and not lines[i].strip():
            i += 1
        while i < len(lines) and lines[i].strip():
            parts = lines[i].split(maxsplit=1)
            if not parts[0].isdigit():
                break
            nums = _FLOAT.findall(parts[1]) if len(parts) > 1 else []
            if len(nums) != 3:
                raise MeshFormatError(f"unreadable displacement line in .dat file: {lines[i]!r}")
            ids.append(int(parts[0]))
            vals.append([float(x) for x in nums])
            i += 1
        yield m.group(1), float(m.group(2)), np.array(ids, np.int64), np.array(vals).reshape(-1, 3)


def _frd_blocks(text: str):
    """Yield (time, ids (k,), values (k, 3)) for each DISP block of a .frd file.

    Node records are fixed width: ``' -1'``, the node id (I5 short or I10 long format),
    then E12.5 fields that may run together (``-1.23456E+00-2.34567E+00``).
    """
    lines = text.splitlines()
    t = 0.0
    i = 0
    while i < len(lines):
        line = lines[i]
        i += 1
        if line.startswith("  100C"):
            t = float(line[12:24])
            continue
        if not line.startswith(" -4  DISP"):
            continue
        ids, vals = [], []
        while i < len(lines) and not lines[i].startswith(" -3"):
            rec = lines[i].rstrip("\r\n")
            i += 1
            if not rec.startswith(" -1"):
                continue
            body = rec[3:]
            width = len(body) % 12  # 5 (short) or 10 (long) characters of node id
            if width not in (5, 10) or len(body) < width + 36:
                raise MeshFormatError(f"unreadable node record in .frd file: {rec!r}")
            ids.append(int(body[:width]))
            vals.append([float(body[width + 12 * k : width + 12 * (k + 1)]) for k in range(3)])
        yield t, np.array(ids, np.int64), np.array(vals).reshape(-1, 3)


def read_displacements(path, n_nodes: int, *, return_time: bool = False):
    """Displacements of nodes 1..n_nodes from the last result block of a ccx ``.dat`` or ``.frd``.

    Args:
        path: ``.dat`` (``*NODE PRINT`` output, 7 digits) or ``.frd`` (``*NODE FILE``, 6 digits).
        n_nodes: how many nodes to return: the mesh's vertex count for vertex displacements,
            ``len(mesh.points10)`` for every quadratic node (``.frd`` only).
        return_time: also return the step time of the block (the load fraction).

    Returns:
        (n_nodes, 3) float, mm: row i is node i + 1 (0-based vertex i); with ``return_time``,
        a pair (displacements, time).

    Raises:
        FileNotFoundError: no such file.
        MeshFormatError: no displacement block, unreadable lines, or nodes missing.
    """
    path = Path(path)
    text = path.read_text(errors="replace")
    blocks = list(_frd_blocks(text)) if path.suffix.lower() == ".frd" else [b[1:] for b in _dat_blocks(text)]
    if not blocks:
        raise MeshFormatError(f"{path} holds no displacement results; request U with *NODE PRINT / *NODE FILE")
    t, ids, vals = blocks[-1]
    u = np.full((n_nodes, 3), np.nan)
    keep = (ids >= 1) & (ids <= n_nodes)
    u[ids[keep] - 1] = vals[keep]
    missing = np.flatnonzero(np.isnan(u[:, 0]))
    if missing.size:
        raise MeshFormatError(
            f"{path} has no displacement for {missing.size} of nodes 1..{n_nodes} (first: node {missing[0] + 1}); "
            "was the deck written for this mesh?"
        )
    return (u, t) if return_time else u
