"""Synthetic label maps with closed-form shapes, written as NRRD, NIfTI and Slicer .seg.nrrd."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])

#: the closed-form test shapes: name -> (semi-axes mm, voxel spacing mm, mesh size mm)
ELLIPSOIDS = {
    "ellipsoid 22x15x11, voxels 0.9x1.3x2.0, size 3": ((22.0, 15.0, 11.0), (0.9, 1.3, 2.0), 3.0),
    "ellipsoid 15x11x8, voxels 0.6x0.9x1.5, size 2": ((15.0, 11.0, 8.0), (0.6, 0.9, 1.5), 2.0),
}


def oblique_grid(shape, spacing, angles_deg=(20.0, -35.0, 50.0), centre=(10.0, -20.0, 30.0)) -> np.ndarray:
    """(4, 4) voxel -> LPS matrix: rotated (oblique) axes, anisotropic spacing, the grid centred on ``centre``."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix() * np.asarray(spacing, float)
    matrix[:3, 3] = np.asarray(centre, float) - matrix[:3, :3] @ ((np.asarray(shape) - 1) / 2.0)
    return matrix


def ellipsoid_mask(semi_axes, spacing, *, axes_deg=(0.0, 0.0, 10.0), angles_deg=(20.0, -35.0, 50.0),
                   centre=(10.0, -20.0, 30.0), margin=3.0):
    """Voxels (centres) inside an ellipsoid, on an oblique anisotropic grid.

    Returns:
        ``(mask (I, J, K) bool, ijk_to_lps (4, 4), axes (3, 3))``: the ellipsoid is
        ``|axes.T (x - centre) / semi_axes| <= 1`` in LPS mm; ``axes`` columns are its
        principal directions.
    """
    semi_axes = np.asarray(semi_axes, float)
    shape = np.ceil((2 * semi_axes.max() + 2 * margin) / np.asarray(spacing)).astype(int) + 2
    ijk_to_lps = oblique_grid(shape, spacing, angles_deg, centre)
    axes = Rotation.from_euler("xyz", axes_deg, degrees=True).as_matrix()
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    local = (ijk @ ijk_to_lps[:3, :3].T + ijk_to_lps[:3, 3] - np.asarray(centre)) @ axes
    mask = ((local / semi_axes) ** 2).sum(axis=1) <= 1.0
    return mask.reshape(shape), ijk_to_lps, axes


def write_nrrd(path: Path, voxels: np.ndarray, ijk_to_lps: np.ndarray | None, space: str = "left-posterior-superior") -> Path:
    """A NRRD volume in LPS (or RAS: ``space='right-anterior-superior'``); ``ijk_to_lps=None`` writes no geometry."""
    import nrrd

    header = {"kinds": ["domain"] * voxels.ndim, "encoding": "gzip"}
    if ijk_to_lps is not None:
        matrix = ijk_to_lps if space.startswith("left") else LPS_TO_RAS @ ijk_to_lps
        header.update({"space": space, "space directions": matrix[:3, :3].T, "space origin": matrix[:3, 3]})
    nrrd.write(str(path), np.ascontiguousarray(voxels), header, index_order="F")
    return Path(path)


def write_nifti(path: Path, voxels: np.ndarray, ijk_to_lps: np.ndarray, *, codes: int = 1) -> Path:
    """A NIfTI-1 volume; its affine is RAS+ (``LPS_TO_RAS @ ijk_to_lps``), qform/sform codes ``codes``."""
    import nibabel as nib

    image = nib.Nifti1Image(np.asarray(voxels), LPS_TO_RAS @ ijk_to_lps)
    image.set_qform(LPS_TO_RAS @ ijk_to_lps, code=codes)
    image.set_sform(LPS_TO_RAS @ ijk_to_lps, code=codes)
    nib.save(image, str(path))
    return Path(path)


def write_segmentation(path: Path, masks: dict[str, np.ndarray], ijk_to_lps: np.ndarray) -> Path:
    """A 3D Slicer .seg.nrrd with one segment per (name, mask), label values 1, 2, ... in one layer."""
    import slicerio

    first = next(iter(masks.values()))
    seg = slicerio.create_segmentation(first.shape, ijk_to_lps)
    for name, mask in masks.items():
        slicerio.add_segment(seg, mask, {"name": name})
    slicerio.write_segmentation(str(path), seg)
    return Path(path)
