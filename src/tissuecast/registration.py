"""Rigid registration (Kabsch / Procrustes) and the non-rigid part of a displacement field.

What a navigation system does with tracked fiducials today is a *rigid registration*: the
rotation ``R`` and translation ``t`` that best take the markers' reference positions ``X``
to their tracked positions ``Y`` (least squares, ``min sum_k ||R X_k + t - Y_k||^2``, with
``det R = +1``), applied to the whole mesh. :func:`rigid_registration_field` is that baseline
as a displacement field; every accuracy figure of tissuecast is reported next to it.

The *non-rigid part* of a displacement field (:func:`nonrigid_part`) is the largest vertex
residual left after the best rigid fit of the *whole* field (all vertices, equal weights):
how much of a deformation no rigid motion explains, hence the most a learned model can add
over a perfect rigid registration.

Shapes: one sample ``(k, 3)`` or a batch ``(B, k, 3)``; all lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import RegistrationError

__all__ = ["RigidTransform", "fit_rigid", "rigid_registration_field", "rigid_residuals", "nonrigid_part",
           "check_markers_span"]

# Centred marker positions whose second singular value is below this share of the first lie
# on one line (to round-off): the rotation about that line is then not determined.
_COLLINEAR_RTOL = 1e-6


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """``x -> R x + t``.

    Attributes:
        rotation: (3, 3) or (B, 3, 3) float64 proper rotations (det +1).
        translation: (3,) or (B, 3) float64, mm.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points) -> np.ndarray:
        """Moved points: (n, 3) mm -> (n, 3), or (B, n, 3) for a batch of transforms."""
        p = np.asarray(points, dtype=np.float64)
        return np.matmul(p, np.swapaxes(self.rotation, -1, -2)) + self.translation[..., None, :]

    def displacement(self, points) -> np.ndarray:
        """Displacement ``R x + t - x`` of reference points (n, 3) mm -> (n, 3) or (B, n, 3)."""
        p = np.asarray(points, dtype=np.float64)
        return self.apply(p) - p


def check_markers_span(reference, what: str = "markers") -> None:
    """Raise :class:`RegistrationError` unless ``reference`` (k, 3) mm holds >= 3 points not on one line."""
    x = np.asarray(reference, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or not np.isfinite(x).all():
        raise RegistrationError(f"{what} must be finite (k, 3) positions in mm, got shape {x.shape}")
    if len(x) < 3:
        raise RegistrationError(
            f"a rigid registration needs at least 3 {what} not on one line, got {len(x)}; place more markers")
    s = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if s[1] <= _COLLINEAR_RTOL * max(s[0], 1e-300):
        raise RegistrationError(
            f"the {len(x)} {what} lie on one line, so the rotation about that line is unknown; "
            "place at least one marker off the line")


def _kabsch(x: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> RigidTransform:
    """Best rigid map of x (B, k, 3) onto y (B, k, 3), weights w (k,) or None."""
    if w is None:
        cx, cy = x.mean(axis=1), y.mean(axis=1)
        xc, yc = x - cx[:, None], y - cy[:, None]
    else:
        ws = w / w.sum()
        cx, cy = np.einsum("k,bki->bi", ws, x), np.einsum("k,bki->bi", ws, y)
        xc, yc = (x - cx[:, None]) * ws[None, :, None], y - cy[:, None]
    h = np.matmul(np.swapaxes(yc, 1, 2), xc)  # (B, 3, 3) = sum_k y_k x_k^T
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.matmul(u, vt)))
    d[d == 0] = 1.0
    u[:, :, 2] *= d[:, None]
    rot = np.matmul(u, vt)
    return RigidTransform(rot, cy - np.einsum("bij,bj->bi", rot, cx))


def fit_rigid(reference, moved, weights=None) -> RigidTransform:
    """The least-squares rigid transform taking ``reference`` onto ``moved`` (Kabsch).

    Args:
        reference: (k, 3) float, mm, reference positions (k >= 3, not collinear).
        moved: (k, 3) or (B, k, 3) float, mm, their moved positions.
        weights: optional (k,) positive weights of the points.

    Returns:
        A :class:`RigidTransform` with rotation (3, 3) / translation (3,) for one ``moved``,
        (B, 3, 3) / (B, 3) for a batch. A rigid motion is recovered to round-off.

    Raises:
        RegistrationError: fewer than 3 points, collinear reference points, non-finite
            values, or mismatched shapes.
    """
    x = np.asarray(reference, dtype=np.float64)
    check_markers_span(x, "reference points")
    y = np.asarray(moved, dtype=np.float64)
    single = y.ndim == 2
    yb = y[None] if single else y
    if yb.ndim != 3 or yb.shape[1:] != x.shape:
        raise RegistrationError(f"moved positions must be {x.shape} or (B, {len(x)}, 3) mm, got {y.shape}")
    if not np.isfinite(yb).all():
        raise RegistrationError("moved positions contain NaN or inf")
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64).ravel()
        if w.shape != (len(x),) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise RegistrationError(f"weights must be {len(x)} non-negative numbers with a positive sum")
    t = _kabsch(np.broadcast_to(x, yb.shape), yb, w)
    return RigidTransform(t.rotation[0], t.translation[0]) if single else t


def rigid_registration_field(points, marker_ids, marker_displacements) -> np.ndarray:
    """The rigid-registration baseline: the whole mesh moved by the markers' best rigid fit.

    Args:
        points: (n, 3) float, mm, reference vertex positions.
        marker_ids: (n_d,) int, 0-based marker vertex ids (n_d >= 3, not collinear).
        marker_displacements: (n_d, 3) or (B, n_d, 3) float, mm, tracked displacements.

    Returns:
        (n, 3) or (B, n, 3) float64 displacement field, mm.
    """
    p = np.asarray(points, dtype=np.float64)
    ref = p[np.asarray(marker_ids, dtype=np.int64)]
    d = np.asarray(marker_displacements, dtype=np.float64)
    if d.shape[-2:] != ref.shape:
        raise RegistrationError(f"marker displacements must be {ref.shape} or (B, {len(ref)}, 3) mm, got {d.shape}")
    return fit_rigid(ref, ref + d).displacement(p)


def rigid_residuals(points, displacement) -> np.ndarray:
    """Per-vertex distance left after the best rigid fit of a whole field.

    Args:
        points: (n, 3) float, mm, reference vertices.
        displacement: (n, 3) or (B, n, 3) float, mm.

    Returns:
        (n,) or (B, n) float64, mm.
    """
    p = np.asarray(points, dtype=np.float64)
    u = np.asarray(displacement, dtype=np.float64)
    fit = fit_rigid(p, p + u)
    return np.linalg.norm(p + u - fit.apply(p), axis=-1)


def nonrigid_part(points, displacement, *, chunk: int = 64) -> np.ndarray | float:
    """The non-rigid part of displacement fields: the largest vertex residual after the best
    rigid fit of the whole field (all vertices, equal weights).

    Args:
        points: (n, 3) float, mm, reference vertices.
        displacement: (n, 3) or (B, n, 3) float, mm.
        chunk: samples processed at once (memory).

    Returns:
        A float (one field) or (B,) float64, mm. Zero for a rigid motion.
    """
    u = np.asarray(displacement)
    if u.ndim == 2:
        return float(rigid_residuals(points, u).max())
    out = np.empty(len(u))
    for s in range(0, len(u), chunk):
        out[s:s + chunk] = rigid_residuals(points, np.asarray(u[s:s + chunk], dtype=np.float64)).max(axis=1)
    return out
