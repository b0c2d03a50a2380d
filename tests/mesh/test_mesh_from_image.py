"""Label map -> tetrahedral mesh: closed-form shapes on oblique anisotropic grids, a real CT
segmentation shipped with slicerio, readers against each other, and every refused input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from labelmap_factories import ELLIPSOIDS, ellipsoid_mask, oblique_grid, write_nifti, write_nrrd, write_segmentation

pytest.importorskip("skimage")
pytest.importorskip("slicerio")
pytest.importorskip("nibabel")
pytest.importorskip("gmsh")

from tissuecast.errors import ConfigError, LabelMapError  # noqa: E402
from tissuecast.mesh.from_image import label_map_fidelity, label_pieces, mesh_from_image, mesh_label_map  # noqa: E402
from tissuecast.mesh.labelmap import LabelMap, read_label_map  # noqa: E402

SHAPES = ELLIPSOIDS
CENTRE = np.array([10.0, -20.0, 30.0])


@pytest.mark.parametrize("name", list(SHAPES))
def test_ellipsoid_on_oblique_anisotropic_grid_meets_the_targets(name):
    semi, spacing, size = SHAPES[name]
    mask, ijk_to_lps, axes = ellipsoid_mask(semi, spacing)
    labelmap = LabelMap(mask, ijk_to_lps, name)
    mesh = mesh_label_map(labelmap, size)
    fidelity = label_map_fidelity(mesh, labelmap)
    assert abs(fidelity.volume_error) < 0.02  # target: within 2 % of the labelled voxel volume
    assert fidelity.hausdorff_voxels < 1.0  # target: within one voxel of the label boundary
    exact = 4.0 / 3.0 * np.pi * np.prod(semi)
    assert abs(mesh.volume - exact) / exact < 0.03  # and close to the closed form
    # the physical frame is kept: centroid at the ellipsoid's centre, longest axis along its first axis
    tet_centres = mesh.points[mesh.tets].mean(axis=1)
    w = mesh.tet_volumes / mesh.volume
    centroid = w @ tet_centres
    np.testing.assert_allclose(centroid, CENTRE, atol=0.1 * min(spacing))
    d = tet_centres - centroid
    _, vectors = np.linalg.eigh((w[:, None] * d).T @ d)
    assert abs(vectors[:, -1] @ axes[:, 0]) > 0.999


@pytest.fixture(scope="module")
def small_ellipsoid():
    return ellipsoid_mask((9.0, 7.0, 5.0), (0.8, 1.1, 1.5))


def test_nifti_ras_and_nrrd_lps_files_give_the_same_lps_mesh(tmp_path, small_ellipsoid):
    mask, ijk_to_lps, _ = small_ellipsoid
    labels = mask.astype(np.uint8) * 4
    files = [write_nrrd(tmp_path / "a.nrrd", labels, ijk_to_lps),
             write_nrrd(tmp_path / "b.nrrd", labels, ijk_to_lps, space="right-anterior-superior"),
             write_nifti(tmp_path / "c.nii.gz", labels, ijk_to_lps)]
    maps = [read_label_map(f) for f in files]
    for m in maps:
        np.testing.assert_array_equal(m.mask, mask)
        np.testing.assert_allclose(m.ijk_to_lps, ijk_to_lps, atol=1e-5)  # NIfTI stores float32
    meshes = [mesh_from_image(f, 2.0, label=4) for f in files[:2]]
    np.testing.assert_allclose(meshes[0].points, meshes[1].points, atol=1e-9)


def test_slicer_segmentation_segments_by_name(tmp_path, small_ellipsoid):
    mask, ijk_to_lps, _ = small_ellipsoid
    box = np.zeros_like(mask)
    box[2:6, 2:6, 2:5] = True
    path = write_segmentation(tmp_path / "s.seg.nrrd", {"tumour": mask, "marker box": box & ~mask}, ijk_to_lps)
    tumour = read_label_map(path, segment="tumour")
    np.testing.assert_array_equal(tumour.mask, mask)
    assert read_label_map(path, segment="marker box").mask.sum() == (box & ~mask).sum()
    mesh = mesh_from_image(path, 2.0, segment="tumour")
    assert abs(label_map_fidelity(mesh, tumour).volume_error) < 0.02
    with pytest.raises(LabelMapError, match="no segment named 'liver'.*'tumour', 'marker box'"):
        read_label_map(path, segment="liver")
    with pytest.raises(LabelMapError, match="holds 2 segments; choose one"):
        read_label_map(path)


def _real_segmentation() -> str:
    import slicerio

    return os.path.join(os.path.dirname(slicerio.__file__), "data", "Segmentation.seg.nrrd")


def test_real_ct_segmentation_from_slicerio_is_read_in_its_frame():
    """slicerio ships a real chest CT segmented in 3D Slicer (128 x 128 x 34 voxels of
    3.05 x 3.05 x 10 mm, axes (-1, -1, 1) in LPS, 7 segments in one layer)."""
    labelmap = read_label_map(_real_segmentation(), segment="right lung")
    np.testing.assert_allclose(labelmap.spacing, [3.046876, 3.046876, 10.0], rtol=1e-6)
    np.testing.assert_allclose(np.diag(labelmap.ijk_to_lps)[:3] / labelmap.spacing, [-1.0, -1.0, 1.0])
    assert labelmap.mask.sum() == 34450
    assert labelmap.to_lps(np.argwhere(labelmap.mask))[:, 0].mean() < 0  # the right lung lies at L < 0
    with pytest.raises(LabelMapError, match=r"right lung' is made of 5 separate pieces \(34445, 2, 1, 1, 1 voxels"):
        label_pieces(labelmap.mask, source=labelmap.source)
    assert read_label_map(_real_segmentation(), label=5).mask.sum() == 34450  # segment by its label value


@pytest.mark.slow
def test_real_ct_lung_is_meshed_within_two_percent_of_its_voxel_volume():
    """The right lung (keep largest, fill cavities) at mesh size 10 mm: volume -0.35 % of the
    voxels. Its Hausdorff distance is 3.5 voxels (15.8 mm), NOT within the one-voxel target:
    10 mm slices and a genus-22 surface (vessel tunnels) are more than gmsh's re-meshing of
    the smoothed surface follows at this size (docs/label-maps.md)."""
    labelmap = read_label_map(_real_segmentation(), segment="right lung")
    piece = LabelMap(label_pieces(labelmap.mask, keep_largest=True, fill_cavities=True), labelmap.ijk_to_lps, "right lung")
    mesh = mesh_label_map(piece, 10.0)
    fidelity = label_map_fidelity(mesh, piece)
    assert abs(fidelity.volume_error) < 0.02
    lo, hi = piece.to_lps(np.argwhere(piece.mask)).min(0), piece.to_lps(np.argwhere(piece.mask)).max(0)
    assert (mesh.points.min(0) > lo - piece.spacing).all() and (mesh.points.max(0) < hi + piece.spacing).all()


# ----------------------------------------------------------------- refused inputs
def _ball(shape=(16, 16, 16), centre=(8, 8, 8), radius=5.0):
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    return ((ijk - np.asarray(centre)) ** 2).sum(-1) <= radius**2


GRID = oblique_grid((16, 16, 16), (1.0, 1.2, 1.5))


def test_empty_label_is_refused(tmp_path):
    path = write_nrrd(tmp_path / "l.nrrd", _ball().astype(np.uint8) * 2, GRID)
    with pytest.raises(LabelMapError, match=r"label 3 is empty.*labels present: 2"):
        read_label_map(path, label=3)
    empty = write_nrrd(tmp_path / "e.nrrd", np.zeros((8, 8, 8), np.uint8), GRID)
    with pytest.raises(LabelMapError, match="is empty: every voxel is 0"):
        read_label_map(empty)


def test_empty_segment_is_refused(tmp_path):
    path = write_segmentation(tmp_path / "s.seg.nrrd", {"tumour": _ball(), "nothing": np.zeros((16, 16, 16), bool)}, GRID)
    with pytest.raises(LabelMapError, match="segment 'nothing' .* is empty"):
        read_label_map(path, segment="nothing")


def test_several_labels_need_a_choice(tmp_path):
    labels = _ball().astype(np.uint8)
    labels[:3] = 7
    path = write_nrrd(tmp_path / "l.nrrd", labels, GRID)
    with pytest.raises(LabelMapError, match=r"holds 2 labels \(1, 7\); choose one with --label"):
        read_label_map(path)
    assert read_label_map(path, label=7).mask.sum() == 3 * 16 * 16


def test_two_dimensional_image_is_refused(tmp_path):
    flat = write_nrrd(tmp_path / "f.nrrd", np.ones((8, 8), np.uint8), None)
    with pytest.raises(LabelMapError, match="2-D image"):
        read_label_map(flat)
    one_slice = write_nifti(tmp_path / "s.nii", np.ones((8, 8, 1), np.uint8), GRID)
    with pytest.raises(LabelMapError, match="2-D image"):
        read_label_map(one_slice)


def test_missing_spacing_is_refused(tmp_path):
    bare = write_nrrd(tmp_path / "b.nrrd", _ball().astype(np.uint8), None)
    with pytest.raises(LabelMapError, match="no voxel spacing"):
        read_label_map(bare)
    nifti = write_nifti(tmp_path / "n.nii", _ball().astype(np.uint8), GRID, codes=0)
    with pytest.raises(LabelMapError, match="qform_code = sform_code = 0"):
        read_label_map(nifti)


def test_several_pieces_are_refused_or_the_largest_kept(tmp_path):
    two = _ball((24, 16, 16), (7, 8, 8), 5.0) | _ball((24, 16, 16), (18, 8, 8), 3.0)
    path = write_nrrd(tmp_path / "two.nrrd", two.astype(np.uint8), oblique_grid((24, 16, 16), (1.0, 1.0, 1.0)))
    with pytest.raises(LabelMapError, match=r"made of 2 separate pieces \(515, 123 voxels.*--keep-largest"):
        mesh_from_image(path, 2.0)
    big = mesh_from_image(path, 2.0, keep_largest=True)
    assert abs(big.volume - 515.0) / 515.0 < 0.05


def test_cavities_are_refused_or_filled():
    hollow = _ball(radius=6.0) & ~_ball(radius=2.5)
    labelmap = LabelMap(hollow, GRID, "hollow ball")
    with pytest.raises(LabelMapError, match="encloses 1 internal cavity .*--fill-cavities"):
        mesh_label_map(labelmap, 2.0)
    filled = label_pieces(hollow, fill_cavities=True)
    np.testing.assert_array_equal(filled, _ball(radius=6.0))


def test_intensity_image_and_unknown_files_are_refused(tmp_path):
    path = write_nrrd(tmp_path / "ct.nrrd", np.linspace(-1000, 400.5, 16**3).reshape(16, 16, 16), GRID)
    with pytest.raises(LabelMapError, match="non-integer voxel values.*intensity image"):
        read_label_map(path)
    with pytest.raises(LabelMapError, match="does not exist"):
        read_label_map(tmp_path / "missing.nii.gz")
    with pytest.raises(LabelMapError, match="not a Slicer segmentation"):
        read_label_map(path, segment="x")


# ----------------------------------------------------------------- config and CLI
def test_config_mesh_path_may_name_a_label_map(tmp_path, small_ellipsoid):
    from tissuecast.config import config_from_dict
    from tissuecast.mesh.source import mesh_from_config

    mask, ijk_to_lps, _ = small_ellipsoid
    path = write_nifti(tmp_path / "t.nii.gz", mask.astype(np.int16) * 5, ijk_to_lps)
    cfg = config_from_dict({"mesh": {"path": str(path), "label": 5, "surface_mesh_size": 2.0}})
    mesh = mesh_from_config(cfg.mesh)
    assert abs(label_map_fidelity(mesh, read_label_map(path)).volume_error) < 0.02
    from tissuecast.app import check_config

    # what a path names is asked at the edge (check_config) and where the mesh is made
    with pytest.raises(ConfigError, match="mesh.label and mesh.segment apply only when mesh.path names a label map"):
        check_config(config_from_dict({"mesh": {"path": "roi.vtu", "label": 2}}))
    with pytest.raises(ConfigError, match="mesh.label and mesh.segment apply only when mesh.path names a label map"):
        mesh_from_config(config_from_dict({"mesh": {"path": "roi.vtu", "label": 2}}).mesh)
    with pytest.raises(ConfigError, match="mesh.segment names a segment of a 3D Slicer segmentation"):
        check_config(config_from_dict({"mesh": {"path": "roi.nii.gz", "segment": "liver"}}))
    with pytest.raises(ConfigError, match="mesh.units applies to mesh files"):
        check_config(config_from_dict({"mesh": {"path": "roi.nrrd", "units": "cm"}}))


def test_cli_from_image_writes_a_slicer_model_in_lps(tmp_path, small_ellipsoid, capsys):
    from tissuecast.cli.main import main
    from tissuecast.mesh import read_mesh
    from tissuecast.slicer.models import read_model_space

    mask, ijk_to_lps, _ = small_ellipsoid
    path = write_nrrd(tmp_path / "t.nrrd", mask.astype(np.uint8), ijk_to_lps)
    out = tmp_path / "t.vtu"
    assert main(["mesh", "from-image", str(path), str(out), "--size", "2"]) == 0
    text = capsys.readouterr().out
    assert "LPS coordinates" in text and "Hausdorff" in text
    assert read_model_space(out) is None  # meshio-readable: no SPACE array; Slicer takes LPS
    assert main(["mesh", "from-image", str(path), str(tmp_path / "s.vtu"), "--size", "2", "--space-array"]) == 0
    assert read_model_space(tmp_path / "s.vtu") == "LPS"  # where Slicer reads it
    mesh = read_mesh(tmp_path / "s.vtu")  # meshio, after the SPACE string array is set aside
    assert abs(mesh.volume - read_label_map(path).volume) / read_label_map(path).volume < 0.02
    assert main(["mesh", "from-image", str(path), str(tmp_path / "x.vtu"), "--label", "9"]) == 2
    assert "label 9 is empty" in capsys.readouterr().err
    # `mesh info` meshes a label map too (it has no named regions to read)
    assert main(["mesh", "info", str(path), "--mesh-size", "2", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["regions"] == [] and abs(info["volume_mm3"] - mesh.volume) / mesh.volume < 0.05
