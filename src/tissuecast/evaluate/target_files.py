"""Target points in files: read (CSV, 3D Slicer markups) and their predicted positions written
(Slicer markups ``.mrk.json`` stating LPS, one point list per sample; or CSV).

CSV in: one point per row, ``x, y, z`` or ``label, x, y, z`` in LPS mm, a header line and
``#`` comment lines allowed. CSV out: ``sample, target, label, x_lps_mm, y_lps_mm, z_lps_mm,
ux_mm, uy_mm, uz_mm`` (the predicted position and displacement of each target).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import ConfigError, ModelError

__all__ = ["read_target_points", "write_predicted_targets", "PREDICTED_TARGETS_LIST", "TARGET_OUTPUT_SUFFIXES"]

#: Name of the point list (Slicer node) of predicted targets; ``-000``, ``-001``... per sample of a batch.
PREDICTED_TARGETS_LIST = "PredictedTargets"
#: Files :func:`write_predicted_targets` writes.
TARGET_OUTPUT_SUFFIXES = (".mrk.json", ".csv")


def read_target_points(path) -> tuple[np.ndarray, tuple]:
    """Target points of a CSV or Slicer markups file: ``(positions (k, 3) LPS mm, labels)``.

    Raises:
        ConfigError: a missing or unreadable file, or one with no point.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"target file '{path}' does not exist")
    name = path.name.lower()
    if name.endswith((".mrk.json", ".fcsv")):
        from ..slicer.markups import read_markups

        lists = read_markups(path)
        positions = np.concatenate([m.positions for m in lists])
        labels = tuple(lab for m in lists for lab in m.labels)
    else:
        positions, labels = _read_csv_points(path)
    keep = np.isfinite(positions).all(axis=1)
    if not keep.any():
        raise ConfigError(f"target file '{path}' holds no point with a position")
    return positions[keep], tuple(lab for lab, k in zip(labels, keep) if k)


def _read_csv_points(path: Path) -> tuple[np.ndarray, tuple]:
    rows, labels = [], []
    with path.open(newline="", encoding="utf-8") as fh:
        for number, row in enumerate(csv.reader(fh), start=1):
            cells = [c.strip() for c in row]
            if not cells or not "".join(cells) or cells[0].startswith("#"):
                continue
            try:
                xyz = [float(c) for c in cells[-3:]]
            except ValueError:
                if not rows and number == 1:
                    continue  # a header line
                raise ConfigError(f"'{path}' line {number}: need x, y, z (mm) or label, x, y, z; got {row}") from None
            if len(cells) not in (3, 4):
                raise ConfigError(f"'{path}' line {number}: need x, y, z (mm) or label, x, y, z; got {row}")
            rows.append(xyz)
            labels.append(cells[0] if len(cells) == 4 else f"T{len(rows) - 1}")
    return np.array(rows, dtype=np.float64).reshape(-1, 3), tuple(labels)


def write_predicted_targets(path, targets, displacements, *, method: str = "mlp") -> Path:
    """Write the targets' predicted positions (undeformed position + predicted displacement).

    Args:
        path: ``.mrk.json`` (Slicer markups, LPS, one point list per sample) or ``.csv``.
        targets: the :class:`~.targets.Targets`.
        displacements: (k, 3) or (B, k, 3) float, predicted displacement at the targets, mm.
        method: the prediction's name, recorded in the points' descriptions.

    Raises:
        ModelError: another file type, or displacements of the wrong shape.
    """
    path = Path(path)
    u = np.asarray(displacements, dtype=np.float64)
    u = u[None] if u.ndim == 2 else u
    if u.ndim != 3 or u.shape[1:] != (targets.count, 3):
        raise ModelError(f"target displacements must be ({targets.count}, 3) or (B, {targets.count}, 3) mm, got {u.shape}")
    moved = targets.positions[None] + u
    name = path.name.lower()
    if name.endswith(".mrk.json"):
        from ..slicer.markups import MarkupList, write_markups

        lists = [MarkupList(PREDICTED_TARGETS_LIST if len(u) == 1 else f"{PREDICTED_TARGETS_LIST}-{b:03d}", moved[b],
                            targets.labels, (f"predicted by tissuecast ({method})",) * targets.count) for b in range(len(u))]
        return write_markups(path, lists, "LPS")
    if name.endswith(".csv"):
        with path.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["sample", "target", "label", "x_lps_mm", "y_lps_mm", "z_lps_mm", "ux_mm", "uy_mm", "uz_mm"])
            for b in range(len(u)):
                for k in range(targets.count):
                    w.writerow([b, k, targets.labels[k], *(f"{v:.6f}" for v in moved[b, k]), *(f"{v:.6f}" for v in u[b, k])])
        return path
    raise ModelError(f"predicted targets are written as {' or '.join(TARGET_OUTPUT_SUFFIXES)}, not '{path.name}'")
