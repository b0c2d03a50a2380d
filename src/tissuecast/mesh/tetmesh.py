"""The tetrahedral mesh every stage of tissuecast works on.

A :class:`TetMesh` is a small immutable object holding two arrays: vertex coordinates in mm
and 0-based tetrahedra. Everything else (outer surface, edges, quadratic nodes, volume,
quality) is derived on demand and cached. Construction validates the arrays and fixes
inverted vertex order, recording how many tetrahedra were flipped in ``n_flipped``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import MeshError

__all__ = ["TetMesh", "QualityStats", "TET_EDGES", "TET_FACES"]

log = logging.getLogger(__name__)

#: Local vertex pairs of the six edges of a tetrahedron, in the order used for the
#: mid-edge nodes of quadratic (10-node) tetrahedra. This is the VTK ``QUADRATIC_TETRA``,
#: gmsh ``tetra10`` and Abaqus/CalculiX ``C3D10`` order: nodes 4..9 sit on edges
#: (0,1), (1,2), (0,2), (0,3), (1,3), (2,3).
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)

#: Local vertices of the four faces of a positively oriented tetrahedron, each ordered so
#: that its right-hand normal points out of the tetrahedron. Face ``i`` is opposite to
#: vertex ``(3, 2, 1, 0)[i]``.
TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)

# A tet is called degenerate when |volume| <= this * (longest edge)^3.
_DEGENERATE_RELATIVE_VOLUME = 1e-10


@dataclass(frozen=True)
class QualityStats:
    """Quality figures of a tetrahedral mesh (all lengths in mm).

    ``radius_ratio`` is 3 * inradius / circumradius: 1 for a regular tetrahedron, 0 for a
    flat one. ``edge_ratio`` is the longest over the shortest edge of each tetrahedron.
    """

    radius_ratio_min: float
    radius_ratio_mean: float
    edge_ratio_max: float
    edge_length_min: float
    edge_length_mean: float
    edge_length_max: float
    volume_min: float
    volume_max: float

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def _signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def _checked_arrays(points, tets) -> tuple[np.ndarray, np.ndarray]:
    """Copies ``(points (n, 3) float64, tets (m, 4) int64)`` with shapes, finite coordinates,
    integer ids in range and no repeated vertex per tetrahedron checked."""
    points = np.array(points, dtype=np.float64, copy=True)
    tets = np.array(tets, copy=True)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise MeshError(f"points must be an (n, 3) array with n >= 4, got shape {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) < 1:
        raise MeshError(
            f"tets must be an (m, 4) array of vertex ids with m >= 1, got shape {tets.shape}; "
            "quadratic (10-node) connectivity must be reduced to its 4 corner nodes first"
        )
    if not np.issubdtype(tets.dtype, np.integer):
        if not np.all(np.isfinite(tets)) or np.any(tets != np.round(tets)):
            raise MeshError("tets must hold integer vertex ids")
    tets = tets.astype(np.int64)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeshError(
            f"{int(bad.sum())} vertices have non-finite coordinates (first: vertex {i} = "
            f"{points[i].tolist()}); fix or remove them in the mesh file"
        )
    n = len(points)
    if tets.min() < 0 or tets.max() >= n:
        j = int(np.flatnonzero((tets < 0).any(1) | (tets >= n).any(1))[0])
        raise MeshError(
            f"tetrahedron {j} = {tets[j].tolist()} has a vertex id outside 0..{n - 1}; "
            "ids are 0-based (subtract 1 from 1-based Abaqus/TetGen ids)"
        )
    srt = np.sort(tets, axis=1)
    rep = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
    if rep.any():
        j = int(np.flatnonzero(rep)[0])
        raise MeshError(f"tetrahedron {j} = {tets[j].tolist()} repeats a vertex; remove it from the mesh")
    return points, tets


def _checked_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) signed tetrahedron volumes, mm^3; none of them (almost) zero."""
    vol = _signed_volumes(points, tets)
    p = points[tets]
    lmax = np.max(np.linalg.norm(p[:, TET_EDGES[:, 0]] - p[:, TET_EDGES[:, 1]], axis=2), axis=1)
    flat = np.abs(vol) <= _DEGENERATE_RELATIVE_VOLUME * lmax**3
    if flat.any():
        j = int(np.flatnonzero(flat)[0])
        raise MeshError(
            f"{int(flat.sum())} tetrahedra have zero volume (first: tetrahedron {j} = "
            f"{tets[j].tolist()}, volume {vol[j]:.3g} mm^3); remesh or remove slivers"
        )
    return vol


def _check_every_vertex_used(n: int, tets: np.ndarray) -> None:
    used = np.zeros(n, dtype=bool)
    used[tets.ravel()] = True
    if not used.all():
        raise MeshError(
            f"{int((~used).sum())} vertices belong to no tetrahedron (first: vertex "
            f"{int(np.flatnonzero(~used)[0])}); read the file with tc.read_mesh (which drops them) "
            "or remove them"
        )


def _check_connected(n: int, tets: np.ndarray) -> None:
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    graph = sp.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    ncomp, labels = connected_components(graph, directed=False)
    if ncomp > 1:
        sizes = np.bincount(labels)
        raise MeshError(
            f"the mesh is made of {ncomp} disconnected pieces (vertex counts "
            f"{sorted(sizes.tolist(), reverse=True)[:5]}); keep one region of interest per mesh"
        )


@dataclass(frozen=True, eq=False)
class TetMesh:
    """An immutable linear tetrahedral mesh.

    Args:
        points: (n, 3) float, vertex coordinates in mm.
        tets: (m, 4) int, 0-based vertex ids of each tetrahedron. Tetrahedra with negative
            signed volume are re-ordered (vertices 1 and 2 swapped) to positive orientation;
            their number is kept in ``n_flipped``.

    Raises:
        MeshError: non-finite coordinates, wrong shapes, indices out of range, a repeated
            vertex in a tetrahedron, a zero-volume tetrahedron, vertices used by no
            tetrahedron, or a mesh made of several disconnected pieces.
    """

    points: np.ndarray
    tets: np.ndarray
    n_flipped: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        points, tets = _checked_arrays(self.points, self.tets)
        vol = _checked_volumes(points, tets)
        _check_every_vertex_used(len(points), tets)
        neg = vol < 0
        if neg.any():
            tets[neg] = tets[neg][:, [0, 2, 1, 3]]
            log.info("re-oriented %d inverted tetrahedra", int(neg.sum()))
        _check_connected(len(points), tets)
        points.setflags(write=False)
        tets.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "n_flipped", int(neg.sum()))

    # ------------------------------------------------------------------ sizes
    @property
    def n_points(self) -> int:
        """Number of vertices."""
        return len(self.points)

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra."""
        return len(self.tets)

    def __repr__(self) -> str:
        return (
            f"TetMesh({self.n_points} vertices, {self.n_tets} tetrahedra, "
            f"{len(self.surface_vertices)} on the surface, volume {self.volume:.1f} mm^3)"
        )

    # --------------------------------------------------------------- geometry
    @cached_property
    def tet_volumes(self) -> np.ndarray:
        """(m,) float, mm^3: volume of each tetrahedron (positive)."""
        v = _signed_volumes(self.points, self.tets)
        v.setflags(write=False)
        return v

    @property
    def volume(self) -> float:
        """Total volume in mm^3."""
        return float(self.tet_volumes.sum())

    @property
    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower corner (3,), upper corner (3,)) in mm."""
        return self.points.min(axis=0), self.points.max(axis=0)

    @property
    def extent(self) -> np.ndarray:
        """(3,) float, mm: side lengths of the axis-aligned bounding box."""
        lo, hi = self.bounding_box
        return hi - lo

    # ---------------------------------------------------------------- surface
    @cached_property
    def _boundary(self) -> tuple[np.ndarray, np.ndarray]:
        faces = self.tets[:, TET_FACES].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.ravel()
        if counts.max() > 2:
            raise MeshError(
                f"{int((counts > 2).sum())} triangles are shared by more than two tetrahedra: "
                "the mesh is non-manifold; remesh it"
            )
        once = counts[inverse] == 1
        owner = np.repeat(np.arange(self.n_tets), 4)[once]
        return faces[once], owner

    @property
    def surface_triangles(self) -> np.ndarray:
        """(k, 3) int: outer-surface triangles, vertex order giving outward normals."""
        return self._boundary[0]

    @cached_property
    def surface_vertices(self) -> np.ndarray:
        """(s,) int: sorted ids of the vertices on the outer surface."""
        v = np.unique(self.surface_triangles)
        v.setflags(write=False)
        return v

    @cached_property
    def interior_vertices(self) -> np.ndarray:
        """(n - s,) int: sorted ids of vertices not on the outer surface."""
        mask = np.ones(self.n_points, dtype=bool)
        mask[self.surface_vertices] = False
        return np.flatnonzero(mask)

    @property
    def surface_area(self) -> float:
        """Area of the outer surface in mm^2."""
        p = self.points[self.surface_triangles]
        return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())

    # ------------------------------------------------------------ topology
    @cached_property
    def _edges(self) -> tuple[np.ndarray, np.ndarray]:
        pairs = np.sort(self.tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
        return edges, inverse.reshape(self.n_tets, 6)

    @property
    def edges(self) -> np.ndarray:
        """(e, 2) int: unique edges, each as (smaller id, larger id), sorted."""
        return self._edges[0]

    @cached_property
    def tets10(self) -> np.ndarray:
        """(m, 10) int: quadratic connectivity (C3D10 / VTK order).

        Nodes 0..n-1 are the mesh vertices; node ``n + e`` is the midpoint of ``edges[e]``.
        """
        t = np.hstack([self.tets, self.n_points + self._edges[1]])
        t.setflags(write=False)
        return t

    @cached_property
    def points10(self) -> np.ndarray:
        """(n + e, 3) float, mm: vertices followed by edge midpoints (nodes of ``tets10``)."""
        mid = 0.5 * (self.points[self.edges[:, 0]] + self.points[self.edges[:, 1]])
        p = np.vstack([self.points, mid])
        p.setflags(write=False)
        return p

    @cached_property
    def vertex_adjacency(self) -> sp.csr_matrix:
        """(n, n) sparse 0/1 matrix: 1 where two vertices share an edge."""
        e = self.edges
        n = self.n_points
        a = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
        return a.tocsr()

    # ---------------------------------------------------------------- quality
    @cached_property
    def quality(self) -> QualityStats:
        """Quality statistics (radius ratio, edge lengths, element volumes)."""
        p = self.points[self.tets]
        vec = p[:, TET_EDGES[:, 1]] - p[:, TET_EDGES[:, 0]]
        length = np.linalg.norm(vec, axis=2)  # (m, 6)
        vol = self.tet_volumes
        f = p[:, TET_FACES]
        area = 0.5 * np.linalg.norm(np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0]), axis=2).sum(1)
        inradius = 3.0 * vol / area
        # opposite edge pairs: (01,23), (12,03), (02,13)
        a = length[:, 0] * length[:, 5]
        b = length[:, 1] * length[:, 3]
        c = length[:, 2] * length[:, 4]
        prod = (a + b + c) * (a + b - c) * (a - b + c) * (-a + b + c)
        circumradius = np.sqrt(np.maximum(prod, 0.0)) / (24.0 * vol)
        rr = 3.0 * inradius / circumradius
        return QualityStats(
            radius_ratio_min=float(rr.min()),
            radius_ratio_mean=float(rr.mean()),
            edge_ratio_max=float((length.max(1) / length.min(1)).max()),
            edge_length_min=float(length.min()),
            edge_length_mean=float(np.linalg.norm(self.points[self.edges[:, 1]] - self.points[self.edges[:, 0]], axis=1).mean()),
            edge_length_max=float(length.max()),
            volume_min=float(vol.min()),
            volume_max=float(vol.max()),
        )

    # ------------------------------------------------------------- transforms
    def deformed(self, displacement: np.ndarray) -> "TetMesh":
        """A new mesh with vertices moved by ``displacement`` ((n, 3) float, mm)."""
        u = np.asarray(displacement, dtype=np.float64)
        if u.shape != self.points.shape:
            raise MeshError(f"displacement must have shape {self.points.shape}, got {u.shape}")
        return TetMesh(self.points + u, self.tets)

    def scaled(self, factor: float) -> "TetMesh":
        """A new mesh with coordinates multiplied by ``factor`` (e.g. unit conversion)."""
        return TetMesh(self.points * float(factor), self.tets)

    def fingerprint(self, decimals: int = 6) -> str:
        """SHA-256 of the connectivity and of the coordinates rounded to ``decimals`` (mm).

        Identical on every machine for the same mesh; used to tie data sets and models to
        the mesh they were made from.
        """
        import hashlib

        h = hashlib.sha256()
        pts = np.round(self.points, decimals) + 0.0  # + 0.0 turns -0.0 into 0.0
        h.update(np.ascontiguousarray(pts, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.tets, dtype="<i8").tobytes())
        return h.hexdigest()
