"""Label map -> closed surface -> tetrahedral mesh, in the scan's physical (LPS) frame.

Steps (:func:`mesh_label_map`):

1. **Pieces**: the label's 6-connected components; several are refused with their sizes
   unless ``keep_largest``. Internal cavities (background enclosed by the label) are
   refused unless ``fill_cavities`` (tissuecast meshes solid bodies).
2. **Surface**: marching cubes (scikit-image, Lewiner) at the 0.501 level of the padded
   binary mask (just above 0.5: diagonal-only contacts stay apart, no non-manifold ties), in
   voxel indices, then mapped to LPS mm by the map's voxel-to-LPS matrix (spacing,
   direction/oblique axes and origin).
3. **Smoothing that does not shrink**: Taubin's lambda/mu filter (uniform Laplacian,
   lambda = 0.5, mu = -0.53) removes the voxel staircase while keeping the enclosed volume.
4. **Remeshing and tetrahedra**: :func:`tissuecast.mesh.mesher.tetrahedralize_surface`
   (gmsh re-meshes the surface at the requested edge length and fills it with tetrahedra).

:func:`label_map_fidelity` measures the result against the voxels: volume against the
labelled voxel volume, and the symmetric Hausdorff distance between the mesh surface and
the label's voxel boundary, in mm and in voxel units.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..errors import LabelMapError, MeshError, require
from .labelmap import LabelMap, read_label_map
from .tetmesh import TetMesh

__all__ = [
    "label_pieces",
    "label_surface",
    "taubin_smooth",
    "mesh_label_map",
    "mesh_from_image",
    "LabelMapFidelity",
    "label_map_fidelity",
    "SMOOTHING_ITERATIONS",
]

log = logging.getLogger(__name__)

#: Taubin passes (one lambda and one mu step each) applied by default
SMOOTHING_ITERATIONS = 30
# Taubin's filter: lambda > 0 smooths, mu < -lambda un-shrinks; pass band k = 1/lambda + 1/mu = 0.11
_TAUBIN_LAMBDA = 0.5
_TAUBIN_MU = -0.53
# iso-level of marching cubes on the 0/1 mask: just above 0.5, so that the saddle of a face
# whose two labelled voxels touch only diagonally (value exactly 0.5) falls outside and the
# voxels stay apart, as in the 6-connected pieces; at exactly 0.5 such ties give
# non-manifold edges. Vertices move by 0.001 voxel.
_MC_LEVEL = 0.501
# sample spacing of the surfaces compared by label_map_fidelity, in voxels; doubled (up to
# 1 voxel) while the label's boundary would get more than _FIDELITY_POINTS sample points
_FIDELITY_SAMPLING = 0.25
_FIDELITY_POINTS = 2_000_000


def label_pieces(mask: np.ndarray, *, keep_largest: bool = False, fill_cavities: bool = False,
                 source: str = "the label") -> np.ndarray:
    """The one solid piece of a binary mask that is meshed.

    Args:
        mask: (I, J, K) bool.
        keep_largest: keep the largest 6-connected component instead of refusing several.
        fill_cavities: fill background regions enclosed by the label instead of refusing them.
        source: the label's name in messages.

    Returns:
        (I, J, K) bool: one 6-connected component without enclosed cavities.

    Raises:
        LabelMapError: several components (unless ``keep_largest``) or cavities (unless
            ``fill_cavities``).
    """
    from scipy import ndimage

    components, count = ndimage.label(mask)
    if count > 1:
        sizes = np.bincount(components.ravel())[1:]
        order = np.argsort(sizes)[::-1]
        if not keep_largest:
            shown = ", ".join(str(int(s)) for s in sizes[order[:5]]) + (" ..." if count > 5 else "")
            raise LabelMapError(
                f"{source} is made of {count} separate pieces ({shown} voxels, face-connected); a mesh must be one "
                "body: keep the largest with --keep-largest (config mesh.keep_largest = true) or clean the segmentation"
            )
        log.info("%s: kept the largest of %d pieces (%d of %d voxels)", source, count, int(sizes[order[0]]), int(sizes.sum()))
        mask = components == order[0] + 1
    filled = ndimage.binary_fill_holes(mask)
    cavities = filled & ~mask
    if cavities.any():
        _, n_cavities = ndimage.label(cavities)
        if not fill_cavities:
            raise LabelMapError(
                f"{source} encloses {n_cavities} internal cavit{'y' if n_cavities == 1 else 'ies'} "
                f"({int(cavities.sum())} voxels); tissuecast meshes solid bodies: fill them with --fill-cavities "
                "(config mesh.fill_cavities = true) or fix the segmentation"
            )
        log.info("%s: filled %d internal cavities (%d voxels)", source, n_cavities, int(cavities.sum()))
        mask = filled
    return mask


def taubin_smooth(points: np.ndarray, triangles: np.ndarray, iterations: int = SMOOTHING_ITERATIONS) -> np.ndarray:
    """Taubin lambda/mu smoothing of a triangle surface (non-shrinking).

    Args:
        points: (n, 3) float, mm.
        triangles: (k, 3) int, 0-based.
        iterations: number of (lambda, mu) step pairs; 0 returns the points unchanged.

    Returns:
        (n, 3) float, mm: the smoothed vertex positions (connectivity unchanged).
    """
    points = np.array(points, dtype=np.float64)
    if iterations <= 0:
        return points
    tri = np.asarray(triangles, dtype=np.int64)
    rows = tri[:, [0, 1, 1, 2, 2, 0]].ravel()
    cols = tri[:, [1, 0, 2, 1, 0, 2]].ravel()
    n = len(points)
    adjacency = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    adjacency.data[:] = 1.0  # duplicates (each edge is seen from both triangles) count once
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    average = sp.diags(1.0 / np.maximum(degree, 1.0)) @ adjacency
    for _ in range(int(iterations)):
        points += _TAUBIN_LAMBDA * (average @ points - points)
        points += _TAUBIN_MU * (average @ points - points)
    return points


def label_surface(labelmap: LabelMap, *, smoothing_iterations: int = SMOOTHING_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Closed, smoothed surface of a (one-piece, cavity-free) label, in LPS mm.

    Args:
        labelmap: the label; its mask should come from :func:`label_pieces`.
        smoothing_iterations: Taubin passes (0 = the raw marching-cubes surface).

    Returns:
        ``(points (n, 3) float LPS mm, triangles (k, 3) int)``, a closed triangulated
        surface (orientation not normalised).
    """
    skimage_measure = require("skimage.measure", "image", "Surface extraction from label maps")
    padded = np.pad(labelmap.mask, 1).astype(np.float32)
    ijk, triangles, _, _ = skimage_measure.marching_cubes(padded, level=_MC_LEVEL, method="lewiner", allow_degenerate=False)
    points = labelmap.to_lps(ijk.astype(np.float64) - 1.0)
    points = taubin_smooth(points, triangles, smoothing_iterations)
    return points, np.asarray(triangles, dtype=np.int64)


def mesh_label_map(
    labelmap: LabelMap,
    mesh_size: float,
    *,
    keep_largest: bool = False,
    fill_cavities: bool = False,
    smoothing_iterations: int = SMOOTHING_ITERATIONS,
) -> TetMesh:
    """Tetrahedral mesh of a label, in the scan's LPS frame (mm).

    Args:
        labelmap: the label (see :func:`tissuecast.mesh.labelmap.read_label_map`).
        mesh_size: target tetrahedron edge length in mm (> 0).
        keep_largest, fill_cavities: see :func:`label_pieces`.
        smoothing_iterations: Taubin passes before re-meshing.

    Raises:
        LabelMapError: several pieces or cavities (see :func:`label_pieces`), or a label
            too thin to mesh.
        MeshError: gmsh could not mesh the surface.
    """
    from .mesher import tetrahedralize_surface

    mask = label_pieces(labelmap.mask, keep_largest=keep_largest, fill_cavities=fill_cavities, source=labelmap.source)
    piece = LabelMap(mask, labelmap.ijk_to_lps, labelmap.source)
    points, triangles = label_surface(piece, smoothing_iterations=smoothing_iterations)
    if len(triangles) < 4:
        raise LabelMapError(f"{labelmap.source} is too small to mesh ({int(mask.sum())} voxels)")
    try:
        return tetrahedralize_surface(points, triangles, mesh_size)
    except MeshError as exc:
        # gmsh splits a surface into patches at sharp edges before re-meshing it; on some
        # smoothed voxel surfaces that split leaves a patch it cannot parametrise. Splitting
        # for parametrisation only (no feature edges) usually succeeds.
        log.info("%s: retrying gmsh without feature edges (%s)", labelmap.source, exc)
        try:
            return tetrahedralize_surface(points, triangles, mesh_size, feature_angle=180.0)
        except MeshError as again:
            raise LabelMapError(
                f"could not mesh {labelmap.source} at mesh size {mesh_size:g} mm ({again}); thin parts of the "
                "label need a smaller mesh size, or smooth/clean the segmentation"
            ) from again


def mesh_from_image(
    path: str | Path,
    mesh_size: float,
    *,
    label: int | None = None,
    segment: str | None = None,
    keep_largest: bool = False,
    fill_cavities: bool = False,
    smoothing_iterations: int = SMOOTHING_ITERATIONS,
) -> TetMesh:
    """Read a label map (or a Slicer segment) and mesh it; see :func:`mesh_label_map`.

    Returns:
        The tetrahedral mesh, LPS mm, in the scan's physical frame.
    """
    labelmap = read_label_map(path, label=label, segment=segment)
    return mesh_label_map(labelmap, mesh_size, keep_largest=keep_largest, fill_cavities=fill_cavities,
                          smoothing_iterations=smoothing_iterations)


# ------------------------------------------------------------------ fidelity
@dataclass(frozen=True)
class LabelMapFidelity:
    """How closely a tetrahedral mesh follows the label it was made from.

    Attributes:
        label_volume: labelled voxel volume, mm^3 (voxel count x voxel volume).
        mesh_volume: tetrahedral mesh volume, mm^3.
        volume_error: (mesh - label) / label, a fraction.
        hausdorff_mm: symmetric Hausdorff distance between the mesh surface and the label's
            voxel boundary (see :func:`label_map_fidelity`), mm.
        hausdorff_voxels: the same distance measured in voxel index units (anisotropic
            spacing divided out), so 1.0 = one voxel.
        mean_distance_mm: mean distance from the boundary face centres to the mesh surface, mm.
        sampling_voxels: spacing of the sample points on both surfaces, in voxels; the
            distances are upper bounds within about this much.
        surface_p95_mm, surface_p95_voxels: 95 % of the mesh surface lies within this
            distance of the label's voxel boundary.
        boundary_p95_mm, boundary_p95_voxels: 95 % of the label's boundary (face centres)
            lies within this distance of the mesh surface; large where the mesh bridges gaps
            narrower than its elements (e.g. sulci at a vertex budget).
    """

    label_volume: float
    mesh_volume: float
    volume_error: float
    hausdorff_mm: float
    hausdorff_voxels: float
    mean_distance_mm: float
    sampling_voxels: float
    surface_p95_mm: float = float("nan")
    surface_p95_voxels: float = float("nan")
    boundary_p95_mm: float = float("nan")
    boundary_p95_voxels: float = float("nan")

    @property
    def hausdorff95_mm(self) -> float:
        """The 95th-percentile Hausdorff distance (HD95), mm: the larger of the two directed p95s."""
        return max(self.surface_p95_mm, self.boundary_p95_mm)

    @property
    def hausdorff95_voxels(self) -> float:
        """HD95 in voxel index units."""
        return max(self.surface_p95_voxels, self.boundary_p95_voxels)

    def as_dict(self) -> dict[str, float]:
        out = {k: float(v) for k, v in self.__dict__.items()}
        return out | {"hausdorff95_mm": self.hausdorff95_mm, "hausdorff95_voxels": self.hausdorff95_voxels}


def _boundary_faces(mask: np.ndarray, per_edge: int) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-index points on the faces between labelled and unlabelled voxels.

    Returns:
        ``(centres (f, 3), grid (s, 3))``: the face centres, and a grid of
        ``(per_edge + 1)^2`` points on every face (corners and edges included).
    """
    padded = np.pad(mask, 1)
    offsets = np.linspace(-0.5, 0.5, per_edge + 1)
    square = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 2)
    centres, grid = [], []
    for axis in range(3):
        change = np.diff(padded.astype(np.int8), axis=axis) != 0
        c = np.argwhere(change).astype(np.float64) - 1.0
        c[:, axis] += 0.5
        others = [a for a in range(3) if a != axis]
        g = np.repeat(c, len(square), axis=0)
        g[:, others] += np.tile(square, (len(c), 1))
        centres.append(c)
        grid.append(g)
    return np.vstack(centres), np.unique(np.round(np.vstack(grid), 6), axis=0)


def _triangle_samples(points: np.ndarray, triangles: np.ndarray, spacing: float) -> np.ndarray:
    """(s, 3) points on the triangles, no two neighbours farther apart than about ``spacing``.

    Each triangle gets a barycentric grid of n steps per edge, n from its own longest edge,
    so the samples are spread about evenly by area.
    """
    p = points[triangles]
    longest = np.linalg.norm(p[:, [1, 2, 0]] - p, axis=2).max(axis=1)
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
    out = []
    for n in np.unique(steps):
        a, b = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = a + b <= n
        bary = np.c_[a[keep], b[keep], n - a[keep] - b[keep]] / n  # (q, 3)
        out.append(np.einsum("qc,tcd->tqd", bary, p[steps == n]).reshape(-1, 3))
    return np.vstack(out)


def label_map_fidelity(mesh: TetMesh, labelmap: LabelMap) -> LabelMapFidelity:
    """Volume and Hausdorff distance of a mesh against its label's voxels.

    The label boundary is the set of faces between labelled and unlabelled voxels. The
    distance is the larger of (a) the farthest mesh-surface point from those faces and (b)
    the farthest face centre (the point halfway between a labelled voxel and its unlabelled
    neighbour, where the mask's 0.5 iso-surface crosses) from the mesh surface. Face corners
    are left out of (b): no smooth surface can follow the voxel staircase into its corners
    (up to 0.87 voxel away from any plane through the face centres). Both surfaces are
    sampled about every :data:`_FIDELITY_SAMPLING` voxel (coarser, up to one voxel, on labels
    whose boundary would need more than :data:`_FIDELITY_POINTS` samples; the spacing used is
    returned as ``sampling_voxels``) and compared with k-d trees, in
    voxel indices and in LPS mm. The 95th percentile of each directed distance is kept as
    well ((a) over the mesh-surface samples, (b) over the face centres); the 95th-percentile
    Hausdorff distance (HD95) is the larger of the two.

    Args:
        mesh: the mesh, LPS mm (e.g. from :func:`mesh_label_map`).
        labelmap: the label it was made from (after :func:`label_pieces`, if pieces were
            dropped or cavities filled).
    """
    from scipy.spatial import cKDTree

    sampling = _FIDELITY_SAMPLING
    n_faces = sum(int(np.count_nonzero(np.diff(np.pad(labelmap.mask, 1).astype(np.int8), axis=a))) for a in range(3))
    while sampling < 1.0 and n_faces * (round(1.0 / sampling) + 1) ** 2 > _FIDELITY_POINTS:
        sampling *= 2.0
    centres, faces = _boundary_faces(labelmap.mask, int(round(1.0 / sampling)))
    surface = _triangle_samples(labelmap.to_ijk(mesh.points), mesh.surface_triangles, sampling)
    to_mm = labelmap.ijk_to_lps[:3, :3]
    surface_vox = cKDTree(faces).query(surface)[0]  # mesh surface -> label boundary
    boundary_vox = cKDTree(surface).query(centres)[0]  # label boundary -> mesh surface
    surface_mm = surface @ to_mm.T
    boundary_mm, _ = cKDTree(surface_mm).query(centres @ to_mm.T)
    surface_dist_mm = cKDTree(faces @ to_mm.T).query(surface_mm)[0]
    label_volume = labelmap.volume
    return LabelMapFidelity(
        label_volume=label_volume,
        mesh_volume=mesh.volume,
        volume_error=(mesh.volume - label_volume) / label_volume,
        hausdorff_mm=float(max(surface_dist_mm.max(), boundary_mm.max())),
        hausdorff_voxels=float(max(surface_vox.max(), boundary_vox.max())),
        mean_distance_mm=float(boundary_mm.mean()),
        surface_p95_mm=float(np.percentile(surface_dist_mm, 95)),
        surface_p95_voxels=float(np.percentile(surface_vox, 95)),
        boundary_p95_mm=float(np.percentile(boundary_mm, 95)),
        boundary_p95_voxels=float(np.percentile(boundary_vox, 95)),
        sampling_voxels=sampling,
    )
