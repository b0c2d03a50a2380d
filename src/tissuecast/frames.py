"""Patient coordinate systems (LPS, RAS) and rigid/affine frame changes.

tissuecast keeps every mesh, model and output in **LPS** millimetres (x to the patient's
Left, y to Posterior, z to Superior): the frame of DICOM, ITK, NRRD files and of the files
3D Slicer writes (Slicer itself displays in RAS and converts on load/save). RAS (x Right,
y Anterior, z Superior) differs by the sign of x and y; NIfTI files and Slicer's scene
(and so OpenIGTLink messages from Slicer) use it.

Transforms are 4 x 4 homogeneous matrices mapping column vectors, named ``AToB`` (points
in frame A -> frame B), as in SlicerIGT and PLUS: ``p_B = A_to_B @ (p_A, 1)``.
"""

from __future__ import annotations

import numpy as np

from .errors import FrameError

__all__ = ["COORDINATE_SYSTEMS", "LPS_TO_RAS", "FrameError", "convert_points", "check_transform", "apply_transform",
           "apply_rotation"]

#: the coordinate systems a file may state
COORDINATE_SYSTEMS = ("LPS", "RAS")
#: LPS <-> RAS (its own inverse): negate x and y
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _check_system(name: str) -> str:
    upper = str(name).upper()
    if upper not in COORDINATE_SYSTEMS:
        raise FrameError(f"unknown coordinate system {name!r}; use LPS or RAS")
    return upper


def convert_points(points: np.ndarray, source: str, target: str) -> np.ndarray:
    """Points from one patient coordinate system to the other.

    Args:
        points: (..., 3) float, mm.
        source, target: ``"LPS"`` or ``"RAS"`` (case-insensitive).

    Returns:
        (..., 3) float, mm (a new array).
    """
    points = np.array(points, dtype=np.float64)
    if _check_system(source) != _check_system(target):
        points[..., :2] *= -1.0
    return points


def check_transform(matrix, what: str = "transform") -> np.ndarray:
    """A 4 x 4 affine matrix (16 numbers row by row, or 4 x 4) checked to be finite and invertible.

    Raises:
        FrameError: wrong size, non-finite, last row not (0, 0, 0, 1), or singular.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.size != 16:
        raise FrameError(f"{what} must be a 4x4 matrix (16 numbers, row by row), got {m.size} numbers")
    m = m.reshape(4, 4)
    if not np.isfinite(m).all():
        raise FrameError(f"{what} holds NaN or infinite values")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise FrameError(f"{what} must end with the row 0 0 0 1, got {m[3].tolist()}")
    if abs(np.linalg.det(m[:3, :3])) < 1e-9:
        raise FrameError(f"{what} is singular (its 3x3 part has determinant {np.linalg.det(m[:3, :3]):.3g})")
    return m


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 3) points (mm) mapped by a 4 x 4 affine matrix."""
    points = np.asarray(points, dtype=np.float64)
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def apply_rotation(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """(..., 3) vectors (e.g. displacements, mm) mapped by the linear part of a 4 x 4 matrix."""
    return np.asarray(vectors, dtype=np.float64) @ matrix[:3, :3].T
