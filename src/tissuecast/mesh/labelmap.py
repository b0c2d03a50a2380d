"""Label maps (segmented scans) read into one binary mask with its physical geometry.

=====================  =======================================================
file                   read with
=====================  =======================================================
.nii .nii.gz           nibabel (NIfTI-1/2; the qform/sform affine, RAS+ in the
                       file, is converted to LPS)
.nrrd .nhdr            slicerio.read_volume (pynrrd underneath; LPS or RAS
                       ``space``, space directions and origin)
.seg.nrrd              slicerio.read_segmentation (3D Slicer segmentations:
                       segment names, label values, binary-labelmap layers)
=====================  =======================================================

Why these readers: nibabel is the reference NIfTI implementation (qform/sform rules as
the standard defines them), slicerio is written by the 3D Slicer developers for Slicer's
own NRRD and ``.seg.nrrd`` files (segment metadata, layers, LPS/RAS spaces), and both are
small pure-Python packages (pynrrd, numpy) where SimpleITK/ITK would add a ~50 MB binary
and still not know Slicer's segment names.

Coordinates: every :class:`LabelMap` maps voxel indices to **LPS** millimetres (the DICOM,
ITK and 3D Slicer file convention): ``p_LPS = ijk_to_lps @ (i, j, k, 1)``. Direction
(oblique) matrices, anisotropic spacing and the origin are kept exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import LabelMapError, require
from ..frames import LPS_TO_RAS

__all__ = ["LabelMap", "read_label_map", "label_map_format", "LABEL_MAP_SUFFIXES"]

#: file name endings read as label maps (lower case)
LABEL_MAP_SUFFIXES = (".seg.nrrd", ".nii.gz", ".nii", ".nrrd", ".nhdr")


@dataclass(frozen=True, eq=False)
class LabelMap:
    """One label (or segment) of a segmented scan as a binary mask.

    Attributes:
        mask: (I, J, K) bool, True inside the chosen label, indexed like the file's voxels.
        ijk_to_lps: (4, 4) float, voxel index (i, j, k, 1) -> LPS position in mm.
        source: file name and chosen label, for messages.
    """

    mask: np.ndarray
    ijk_to_lps: np.ndarray
    source: str

    @property
    def spacing(self) -> np.ndarray:
        """(3,) float, mm: voxel size along i, j, k."""
        return np.linalg.norm(self.ijk_to_lps[:3, :3], axis=0)

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel in mm^3."""
        return float(abs(np.linalg.det(self.ijk_to_lps[:3, :3])))

    @property
    def volume(self) -> float:
        """Labelled volume in mm^3 (voxel count times voxel volume)."""
        return float(self.mask.sum()) * self.voxel_volume

    def to_lps(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) continuous voxel indices -> (n, 3) LPS positions, mm."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.ijk_to_lps[:3, :3].T + self.ijk_to_lps[:3, 3]

    def to_ijk(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) LPS positions, mm -> (n, 3) continuous voxel indices."""
        points = np.asarray(points, dtype=np.float64)
        return np.linalg.solve(self.ijk_to_lps[:3, :3], (points - self.ijk_to_lps[:3, 3]).T).T


def label_map_format(path: str | Path) -> str | None:
    """``"segmentation"``, ``"nrrd"`` or ``"nifti"`` for a label-map file name, else None."""
    name = str(path).lower()
    if name.endswith(".seg.nrrd"):
        return "segmentation"
    if name.endswith((".nrrd", ".nhdr")):
        return "nrrd"
    if name.endswith((".nii", ".nii.gz")):
        return "nifti"
    return None


def read_label_map(path: str | Path, *, label: int | None = None, segment: str | None = None) -> LabelMap:
    """Read one label of a label map, or one segment of a 3D Slicer segmentation.

    Args:
        path: ``.nii``, ``.nii.gz``, ``.nrrd``, ``.nhdr`` or ``.seg.nrrd`` file.
        label: voxel value to mesh; None = the only non-zero value of the map.
        segment: segment name (or ID) of a ``.seg.nrrd`` segmentation; None = ``label``,
            or the only segment.

    Returns:
        The binary mask of that label with its voxel-to-LPS geometry.

    Raises:
        LabelMapError: missing or unreadable file, not 3-D, no spacing/orientation,
            non-integer voxel values, an unknown or empty label or segment, or several
            labels/segments when none was chosen.
        DependencyError: nibabel or slicerio is missing (extra ``image``).
    """
    path = Path(path)
    kind = label_map_format(path)
    if kind is None:
        raise LabelMapError(
            f"'{path}' is not a label map this reader knows; use one of " + ", ".join(LABEL_MAP_SUFFIXES)
        )
    if not path.is_file():
        raise LabelMapError(f"label map '{path}' does not exist")
    if segment is not None and kind != "segmentation":
        raise LabelMapError(f"'{path}' is not a Slicer segmentation (.seg.nrrd): choose a voxel value with label, not segment")
    if kind == "segmentation":
        return _read_segmentation(path, label, segment)
    voxels, ijk_to_lps = _read_nifti(path) if kind == "nifti" else _read_nrrd(path)
    return LabelMap(_pick_label(voxels, label, path), ijk_to_lps, f"'{path}' label {label}" if label is not None else f"'{path}'")


# ----------------------------------------------------------------- readers
def _check_voxels(voxels: np.ndarray, path: Path) -> np.ndarray:
    shape = voxels.shape
    spatial = shape[:3] if voxels.ndim >= 3 else shape
    if voxels.ndim < 3 or any(n < 2 for n in spatial):
        raise LabelMapError(
            f"'{path}' is a 2-D image (voxel grid {list(shape)}); a 3-D label map (at least 2 voxels along "
            "each axis) is needed to mesh a volume"
        )
    if voxels.ndim > 3:
        extra = shape[3:]
        if any(n != 1 for n in extra):
            raise LabelMapError(
                f"'{path}' is {voxels.ndim}-D (voxel grid {list(shape)}); a 3-D label map is needed "
                "(for a time series or several layers, save the one volume you want)"
            )
        voxels = voxels.reshape(shape[:3])
    return voxels


def _check_geometry(ijk_to_lps: np.ndarray, path: Path, hint: str) -> np.ndarray:
    matrix = np.asarray(ijk_to_lps, dtype=np.float64)
    spacing = np.linalg.norm(matrix[:3, :3], axis=0)
    if not np.isfinite(matrix).all() or (spacing <= 0).any() or abs(np.linalg.det(matrix[:3, :3])) <= 1e-12 * spacing.prod():
        raise LabelMapError(
            f"'{path}' has no usable voxel spacing/orientation (voxel-to-physical matrix "
            f"{np.round(matrix[:3, :3], 6).tolist()}); {hint}"
        )
    return matrix


def _read_nifti(path: Path) -> tuple[np.ndarray, np.ndarray]:
    nib = require("nibabel", "image", "Reading NIfTI label maps")
    try:
        image = nib.load(str(path))
        header = image.header
        voxels = np.asanyarray(image.dataobj)
    except Exception as exc:  # nibabel raises ImageFileError, EOFError, zlib errors...
        raise LabelMapError(f"could not read '{path}' as NIfTI ({type(exc).__name__}: {exc})") from exc
    voxels = _check_voxels(voxels, path)
    hint = "save it with its spacing and orientation (NIfTI qform or sform), e.g. from 3D Slicer or ITK-SNAP"
    qcode, scode = int(header["qform_code"]), int(header["sform_code"])
    if qcode == 0 and scode == 0:
        raise LabelMapError(
            f"'{path}' has no spacing/orientation (NIfTI qform_code = sform_code = 0), so its physical frame is "
            f"unknown; {hint}"
        )
    zooms = np.asarray(header.get_zooms()[:3], dtype=np.float64)
    if (zooms <= 0).any():
        raise LabelMapError(f"'{path}' has no usable voxel spacing (pixdim {zooms.tolist()}); {hint}")
    # nibabel's affine follows the standard's sform/qform choice and maps to RAS+
    return voxels, _check_geometry(LPS_TO_RAS @ _nifti_mm(header, path) @ image.affine, path, hint)


def _nifti_mm(header, path: Path) -> np.ndarray:
    """(4, 4) scaling of the NIfTI affine to mm from the file's spatial unit."""
    unit = header.get_xyzt_units()[0]
    factor = {"mm": 1.0, "meter": 1000.0, "micron": 1e-3, "unknown": 1.0}.get(unit)
    if factor is None:
        raise LabelMapError(f"'{path}' has spatial unit {unit!r}; mm, meter or micron are understood")
    return np.diag([factor, factor, factor, 1.0])


def _read_nrrd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    nrrd = require("nrrd", "image", "Reading NRRD label maps")
    slicerio = require("slicerio", "image", "Reading NRRD label maps")
    try:
        header = nrrd.read_header(str(path))
    except Exception as exc:
        raise LabelMapError(f"could not read '{path}' as NRRD ({type(exc).__name__}: {exc})") from exc
    if int(header.get("dimension", 0)) < 3:
        raise LabelMapError(
            f"'{path}' is a 2-D image (voxel grid {list(header.get('sizes', []))}); a 3-D label map is needed to mesh a volume"
        )
    hint = "save it with 'space directions' and 'space origin' (3D Slicer, ITK and pynrrd do)"
    if "space directions" not in header and "spacings" not in header:
        raise LabelMapError(f"'{path}' has no voxel spacing (neither 'space directions' nor 'spacings' in its header); {hint}")
    units = [u for u in header.get("space units", []) if u]
    if any(u != "mm" for u in units):
        raise LabelMapError(f"'{path}' has space units {units}; tissuecast reads NRRD label maps in mm "
                            "(as 3D Slicer writes them)")
    try:
        volume = slicerio.read_volume(str(path))
    except Exception as exc:
        raise LabelMapError(f"could not read '{path}' as a NRRD volume ({type(exc).__name__}: {exc})") from exc
    if volume.get("spaceDimension", 3) != 3 or "component" in volume or "sequence" in volume:
        raise LabelMapError(
            f"'{path}' is not a 3-D scalar volume (voxel grid {list(header.get('sizes', []))}); a 3-D label map is needed"
        )
    voxels = _check_voxels(np.asarray(volume["voxels"]), path)
    return voxels, _check_geometry(volume["ijkToLPS"], path, hint)


_SEG_HINT = "save the segmentation again from 3D Slicer (it writes the reference geometry)"


def _read_segmentation(path: Path, label: int | None, segment: str | None) -> LabelMap:
    slicerio = require("slicerio", "image", "Reading 3D Slicer segmentations")
    try:
        seg = slicerio.read_segmentation(str(path))
    except Exception as exc:
        raise LabelMapError(f"could not read '{path}' as a 3D Slicer segmentation ({type(exc).__name__}: {exc})") from exc
    segments = seg.get("segments", [])
    voxels = np.asarray(seg["voxels"])
    layered = voxels.ndim == 4
    if not segments:  # a plain label map saved as .seg.nrrd
        return LabelMap(_pick_label(_check_voxels(voxels, path), label, path), _check_geometry(seg["ijkToLPS"], path, _SEG_HINT),
                        f"'{path}'")
    names = [s.get("name", s.get("id", "?")) for s in segments]
    if segment is None and label is not None:
        chosen = [s for s in segments if int(s.get("labelValue", 1)) == label]
        if layered and len(chosen) > 1:
            raise LabelMapError(f"label value {label} is used by several segments of '{path}' (layers); choose one by name: "
                                + ", ".join(repr(n) for n in names))
        if not chosen:
            raise LabelMapError(f"no segment of '{path}' has label value {label}; its segments: "
                                + ", ".join(f"{n!r} ({s.get('labelValue', 1)})" for n, s in zip(names, segments)))
        info = chosen[0]
    elif segment is None:
        if len(segments) > 1:
            raise LabelMapError(f"'{path}' holds {len(segments)} segments; choose one with --segment NAME "
                                "(config mesh.segment): " + ", ".join(repr(n) for n in names))
        info = segments[0]
    else:
        found = [s for s in segments if s.get("id") == segment] or [s for s in segments if s.get("name") == segment]
        if not found:
            raise LabelMapError(f"'{path}' has no segment named {segment!r}; its segments: " + ", ".join(repr(n) for n in names))
        if len(found) > 1:
            raise LabelMapError(f"several segments of '{path}' are named {segment!r}; choose one by its ID: "
                                + ", ".join(repr(s.get("id")) for s in found))
        info = found[0]
    value = int(info.get("labelValue", 1))
    grid = voxels[int(info.get("layer", 0))] if layered else voxels
    grid = _check_voxels(grid, path)
    mask = grid == value
    name = info.get("name", info.get("id"))
    if not mask.any():
        raise LabelMapError(f"segment {name!r} of '{path}' is empty (no voxel has its label value {value}); "
                            "paint it in the Segment Editor or choose another segment")
    return LabelMap(mask, _check_geometry(seg["ijkToLPS"], path, _SEG_HINT), f"'{path}' segment {name!r}")


def _pick_label(voxels: np.ndarray, label: int | None, path: Path) -> np.ndarray:
    if voxels.dtype.kind == "b":
        voxels = voxels.astype(np.uint8)
    if voxels.dtype.kind == "f":
        bad = ~np.isfinite(voxels) | (voxels != np.round(voxels))
        if bad.any():
            raise LabelMapError(
                f"'{path}' holds non-integer voxel values (e.g. {float(voxels[bad].flat[0])!r}); it looks like an "
                "intensity image, not a label map: segment it first (e.g. 3D Slicer's Segment Editor)"
            )
    if voxels.dtype.kind not in "biuf":
        raise LabelMapError(f"'{path}' has voxels of type {voxels.dtype}; a label map holds integer labels")
    present = np.unique(voxels)
    present = present[present != 0]
    shown = ", ".join(str(int(v)) for v in present[:20]) + (" ..." if len(present) > 20 else "")
    if label is None:
        if len(present) == 0:
            raise LabelMapError(f"'{path}' is empty: every voxel is 0 (background); nothing to mesh")
        if len(present) > 1:
            raise LabelMapError(f"'{path}' holds {len(present)} labels ({shown}); choose one with --label N (config mesh.label)")
        label = int(present[0])
    mask = voxels == label
    if not mask.any():
        where = f"labels present: {shown}" if len(present) else "every voxel is 0"
        raise LabelMapError(f"label {label} is empty in '{path}': no voxel has that value ({where})")
    return mask
