"""Tracked instruments: the pose navigation reports, and the model inputs it becomes.

A tracked instrument (a retractor, a spatula: ``[[scenario.instruments]]``) pushes the tissue
with its tip. Its pose is given in the model's frame (the mesh's, LPS, mm):

- ``tip`` (3,) mm: where the tool tip is;
- ``direction`` (3,) unit: the direction it pushes in (into the tissue);
- ``depth`` mm: how far the tip lies below the reference (undeformed) outer surface, measured
  back along ``direction``: the distance from the tip to the first crossing of the surface by
  the ray ``tip - s direction``, s > 0;
- ``contact``: whether the tip touches the tissue, i.e. lies inside the reference body (an odd
  number of crossings of that ray; depth 0 otherwise).

In a simulated sample the instrument is the scenario's indentation
(:mod:`tissuecast.scenario.indentation`): the tip is the patch centre's reference position plus
the tool tip's displacement (``depth (-n_c) + slide t``), the direction the inward normal
``-n_c`` at the centre, and depth and contact follow from the reference surface as above (so a
sample and a tracked tool are described by one rule; on a curved surface the geometric depth
differs from the drawn one by the surface's sag over the slide). A sample without an
indentation (``scenario.indentation.probability`` < 1) has the instrument away from the tissue.

During surgery a tracker streams the tool's TRANSFORM (tool -> tracker frame, mapped to the
model frame as marker positions are): its translation column is the tip and its third column
(the tool's local +z axis) the push direction (:meth:`ReferenceSurface.pose_from_transform`).

The model reads a pose as :data:`POSE_FEATURES` (:func:`pose_features`): the tip (mm), the
direction, the depth (mm) and the contact flag (1/0); every feature of an instrument away from
the tissue is 0 (where it hovers does not load the tissue).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["InstrumentPose", "ReferenceSurface", "POSE_FEATURES", "POSE_UNITS", "pose_features", "features_from_arrays",
           "recorded_poses"]

#: The model inputs of one instrument, in order (``<instrument>.<feature>``), and their units.
POSE_FEATURES = ("tip_x", "tip_y", "tip_z", "direction_x", "direction_y", "direction_z", "depth", "contact")
POSE_UNITS = ("mm", "mm", "mm", "1", "1", "1", "mm", "1")
#: Rays closer than this (mm) to their own start count as starting on the surface (no crossing).
_RAY_EPS = 1e-9
#: Barycentric slack of a hit (a ray through an edge or vertex meets every triangle there) and
#: the relative distance within which hits are one crossing.
_BARY_EPS = 1e-10
_SAME_CROSSING = 1e-8


@dataclass(frozen=True, eq=False)
class InstrumentPose:
    """One instrument's pose in the model frame (module notes).

    Attributes:
        tip: (3,) float64 mm (NaN when away from the tissue and not known).
        direction: (3,) float64 unit push direction (NaN when away and not known).
        depth: mm below the reference surface along ``direction`` (0 when away).
        contact: whether the tip touches the tissue.
    """

    tip: np.ndarray
    direction: np.ndarray
    depth: float
    contact: bool

    @classmethod
    def away(cls) -> "InstrumentPose":
        """An instrument known to be away from the tissue (not in contact)."""
        nan = np.full(3, np.nan)
        return cls(nan, nan.copy(), 0.0, False)

    def features(self) -> np.ndarray:
        """(8,) float64 model inputs (:data:`POSE_FEATURES`; zeros when away)."""
        return features_from_arrays(self.tip[None], self.direction[None], np.array([self.depth]),
                                    np.array([self.contact]))[0]


def features_from_arrays(tip, direction, depth, contact) -> np.ndarray:
    """(B, 8) float64 model inputs from a batch of poses: ``tip`` (B, 3) mm, ``direction``
    (B, 3), ``depth`` (B,) mm, ``contact`` (B,) bool or 0/1; rows away from the tissue are 0."""
    tip = np.asarray(tip, dtype=np.float64).reshape(-1, 3)
    direction = np.asarray(direction, dtype=np.float64).reshape(-1, 3)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    contact = np.asarray(contact).reshape(-1).astype(bool)
    out = np.hstack([tip, direction, depth[:, None], np.ones((len(tip), 1))])
    out[~contact] = 0.0
    return out


def recorded_poses(instrument_poses: dict, s: int) -> dict:
    """``{instrument: InstrumentPose}`` of sample ``s`` as a data set recorded them (what a tracker
    would have reported), from its ``instrument_poses`` (:attr:`tissuecast.dataset.Dataset.instrument_poses`);
    an instrument not in contact is :meth:`InstrumentPose.away`."""
    out = {}
    for name, p in instrument_poses.items():
        if int(p["contact"][s]) == 1:
            out[name] = InstrumentPose(np.asarray(p["tip"][s], dtype=np.float64),
                                       np.asarray(p["direction"][s], dtype=np.float64), float(p["depth"][s]), True)
        else:
            out[name] = InstrumentPose.away()
    return out


def pose_features(poses) -> np.ndarray:
    """(B, 8) float64 model inputs of a sequence of :class:`InstrumentPose`."""
    poses = list(poses)
    return features_from_arrays(np.array([p.tip for p in poses]).reshape(-1, 3),
                                np.array([p.direction for p in poses]).reshape(-1, 3),
                                np.array([p.depth for p in poses], dtype=np.float64),
                                np.array([p.contact for p in poses], dtype=bool))


class ReferenceSurface:
    """The reference (undeformed) outer surface, for the depth and contact of a tool tip.

    Args:
        points: (n, 3) float mesh vertices, mm.
        triangles: (t, 3) int outward surface triangles (0-based vertex ids).
    """

    def __init__(self, points, triangles):
        p = np.asarray(points, dtype=np.float64)
        tri = np.asarray(triangles, dtype=np.int64)
        origin = p[tri[:, 0]]
        # (3, t) contiguous components of each triangle's first vertex and two edges: one pose per
        # tracked frame reads them with 1-D products
        self._o, self._e1, self._e2 = (np.ascontiguousarray(a.T) for a in (origin, p[tri[:, 1]] - origin,
                                                                           p[tri[:, 2]] - origin))

    @classmethod
    def of(cls, mesh) -> "ReferenceSurface":
        """The outer surface of a :class:`~tissuecast.mesh.TetMesh`."""
        return cls(mesh.points, mesh.surface_triangles)

    def crossings(self, start, ray) -> np.ndarray:
        """Distances (k,) mm, ascending, at which ``start + s ray`` (s > 0; ``ray`` (3,) unit)
        crosses the surface (Moller-Trumbore over every triangle; a ray through an edge or a
        vertex meets each triangle there at one distance, counted once)."""
        sx, sy, sz = np.asarray(start, dtype=np.float64).reshape(3)
        rx, ry, rz = np.asarray(ray, dtype=np.float64).reshape(3)
        (e1x, e1y, e1z), (e2x, e2y, e2z) = self._e1, self._e2
        hx, hy, hz = ry * e2z - rz * e2y, rz * e2x - rx * e2z, rx * e2y - ry * e2x  # ray x edge2
        det = e1x * hx + e1y * hy + e1z * hz
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        px, py, pz = sx - self._o[0], sy - self._o[1], sz - self._o[2]  # start - origin
        u = (px * hx + py * hy + pz * hz) * inv
        qx, qy, qz = py * e1z - pz * e1y, pz * e1x - px * e1z, px * e1y - py * e1x  # (start - origin) x edge1
        v = (qx * rx + qy * ry + qz * rz) * inv
        t = (e2x * qx + e2y * qy + e2z * qz) * inv
        hit = ok & (u >= -_BARY_EPS) & (v >= -_BARY_EPS) & (u + v <= 1.0 + _BARY_EPS) & (t > _RAY_EPS)
        t = np.sort(t[hit])
        if len(t) < 2:
            return t
        return t[np.r_[True, np.diff(t) > _SAME_CROSSING * np.maximum(1.0, t[1:])]]

    def pose(self, tip, direction) -> InstrumentPose:
        """The pose of a tool tip (3,) mm pushing along ``direction`` (3,) (normalised here):
        depth and contact from the crossings of the ray back from the tip (module notes).

        Raises:
            ValueError: a non-finite tip or a zero direction.
        """
        tip = np.asarray(tip, dtype=np.float64).reshape(3)
        direction = np.asarray(direction, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(direction))
        if not (np.isfinite(tip).all() and np.isfinite(direction).all() and norm > 0.0):
            raise ValueError(f"an instrument pose needs a finite tip (mm) and a non-zero direction, got tip "
                             f"{tip.tolist()} and direction {direction.tolist()}")
        direction = direction / norm
        hits = self.crossings(tip, -direction)
        inside = len(hits) % 2 == 1
        return InstrumentPose(tip, direction, float(hits[0]) if inside else 0.0, inside)

    def pose_from_transform(self, matrix) -> InstrumentPose:
        """The pose of a tool TRANSFORM (4, 4) already in the model frame: the translation
        column is the tip (mm), the third column (local +z) the push direction."""
        m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        return self.pose(m[:3, 3], m[:3, 2])
