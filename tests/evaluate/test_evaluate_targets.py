"""Targets (where TRE is measured): location in tetrahedra, the interior rule, regions, label maps,
point files, and the TRE / share-corrected metrics, checked against closed forms."""

import numpy as np
import pytest

import tissuecast as tc
from tissuecast.config import TargetConfig
from tissuecast.errors import ConfigError, MeshError, ModelError
from tissuecast.evaluate.metrics import share_corrected, summarize_targets, target_errors
from tissuecast.evaluate.target_files import read_target_points, write_predicted_targets
from tissuecast.evaluate.targets import (farthest_points, interior_targets, label_targets, point_targets,
                                         targets_from_config)
from tissuecast.markers import surface_depth
from tissuecast.mesh.locate import contains_points, interpolate, locate_points


@pytest.fixture(scope="module")
def mesh():
    return tc.phantom()


def _inner_points(mesh, count, seed=0):
    """Random points inside random tetrahedra (convex combinations of their corners)."""
    rng = np.random.default_rng(seed)
    tets = rng.integers(0, mesh.n_tets, count)
    w = rng.dirichlet(np.ones(4), count)
    return np.einsum("kj,kjd->kd", w, mesh.points[mesh.tets[tets]]), tets, w


def test_locate_points_recovers_tetrahedra_and_interpolates_affine_fields_exactly(mesh):
    p, tets, w = _inner_points(mesh, 300)
    loc = locate_points(mesh, p)
    np.testing.assert_array_equal(loc.tets, tets)  # a point strictly inside belongs to one tetrahedron
    np.testing.assert_allclose(loc.weights, w, atol=1e-9)
    A, b = np.random.default_rng(1).normal(size=(3, 3)), np.array([1.0, -2.0, 0.5])
    u = mesh.points @ A.T + b  # P1 interpolation reproduces affine fields
    np.testing.assert_allclose(interpolate(mesh, loc, u), p @ A.T + b, atol=1e-9)
    batch = np.stack([u, 2 * u])
    np.testing.assert_allclose(interpolate(mesh, loc, batch)[1], 2 * (p @ A.T + b), atol=1e-9)
    # a vertex has weight 1 on itself
    v = locate_points(mesh, mesh.points[[10, 500]])
    np.testing.assert_allclose(np.sort(v.weights, axis=1)[:, -1], 1.0, atol=1e-9)


def test_points_outside_are_refused_with_their_index(mesh):
    lo, hi = mesh.bounding_box
    p = np.vstack([_inner_points(mesh, 3)[0], hi + 5.0])
    with pytest.raises(MeshError, match=r"1 of 4 points lie outside the mesh, the first \(index 3\)"):
        locate_points(mesh, p)
    with pytest.raises(MeshError, match="finite"):
        locate_points(mesh, [[np.nan, 0, 0]])
    # the share of random box points found inside matches the volume ratio (Monte Carlo, 4 sigma)
    q = np.random.default_rng(2).uniform(lo, hi, size=(20000, 3))
    share = contains_points(mesh, q).mean()
    expected = mesh.volume / np.prod(hi - lo)
    assert abs(share - expected) < 4 * np.sqrt(expected * (1 - expected) / len(q))


def test_interior_targets_follow_the_documented_rule(mesh):
    fixed = tc.select_fixed_vertices(mesh, 3)
    t = interior_targets(mesh, count=10, exclude=fixed)
    again = interior_targets(mesh, count=10, exclude=fixed)
    np.testing.assert_array_equal(t.positions, again.positions)  # deterministic
    ids = np.array([int(lab.split("vertex ")[1].rstrip(")")) for lab in t.labels])
    np.testing.assert_array_equal(mesh.points[ids], t.positions)
    assert [lab.split()[0] for lab in t.labels] == [f"T{k}" for k in range(10)]  # 0-based, as markers are numbered
    depth = surface_depth(mesh)
    cand = np.setdiff1d(mesh.interior_vertices, fixed)
    cand = cand[depth[cand] >= 0.5 * depth[cand].max()]
    assert t.count == 10 and set(ids) <= set(cand) and not set(ids) & set(fixed)
    assert ids[0] == cand[np.argmax(depth[cand])]  # the deepest candidate first
    for k in range(1, 10):  # then each the candidate farthest from those before it
        gap = np.linalg.norm(mesh.points[cand][:, None] - mesh.points[ids[:k]][None], axis=2).min(axis=1)
        assert gap.max() == pytest.approx(np.linalg.norm(mesh.points[ids[k]] - mesh.points[ids[:k]], axis=1).min())
    assert "10 interior points" in t.description
    np.testing.assert_allclose(t.displacements(np.ones((mesh.n_vertices, 3))), 1.0)
    with pytest.raises(MeshError, match="lower evaluate.targets.depth"):
        interior_targets(mesh, depth=50.0)
    assert farthest_points(np.array([[0.0, 0, 0], [1, 0, 0], [5, 0, 0], [2, 0, 0]]), 3, 0).tolist() == [0, 2, 3]
    # a thin wall has no interior vertex: its free vertices serve, spread the same way
    from mesh_factories import box_grid

    wall = box_grid(6, 6, 1, size=(2.0, 2.0, 1.0))
    assert wall.interior_vertices.size == 0
    t = interior_targets(wall, count=4, exclude=[0, 1])
    assert t.count == 4 and "no free interior vertex" in t.description
    assert not np.any(np.all(np.isclose(t.positions[:, None], wall.points[[0, 1]][None]), axis=2))


def test_tag_targets_are_the_regions_vertices(mesh, tmp_path):
    centre = mesh.points[mesh.interior_vertices].mean(axis=0)
    region = (np.linalg.norm(mesh.points - centre, axis=1) < 8.0).astype(np.int32)
    path = tmp_path / "phantom_tumour.vtu"
    tc.write_mesh(path, mesh, point_data={"tumour": region})
    t = targets_from_config(TargetConfig(rule="tag", tag="tumour"), mesh, mesh_path=str(path))
    np.testing.assert_allclose(t.positions, mesh.points[np.flatnonzero(region)])
    with pytest.raises(MeshError, match="no region named 'tumor'"):
        targets_from_config(TargetConfig(rule="tag", tag="tumor"), mesh, mesh_path=str(path))


def test_label_targets_lie_in_the_label_and_the_mesh(mesh, tmp_path):
    from labelmap_factories import write_nrrd

    from tissuecast.mesh.labelmap import read_label_map

    lo, hi = mesh.bounding_box
    spacing = 1.5
    shape = np.ceil((hi - lo) / spacing).astype(int) + 3
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, :3] *= spacing
    ijk_to_lps[:3, 3] = lo - spacing
    centres = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3) * spacing + lo - spacing
    tumour_centre = mesh.points[np.argmax(surface_depth(mesh))]
    voxels = np.ones(len(centres), dtype=np.uint8)  # label 1: the organ; 2: the tumour, a 6 mm ball
    voxels[np.linalg.norm(centres - tumour_centre, axis=1) <= 6.0] = 2
    path = write_nrrd(tmp_path / "labels.nrrd", voxels.reshape(shape), ijk_to_lps)
    t = label_targets(mesh, read_label_map(path, label=2), count=12)
    assert t.count == 12
    assert np.all(np.linalg.norm(t.positions - tumour_centre, axis=1) <= 6.0 + 1e-9)
    assert contains_points(mesh, t.positions).all()
    via_config = targets_from_config(TargetConfig(rule="label", path=str(path), label=2, count=12), mesh)
    np.testing.assert_allclose(via_config.positions, t.positions)
    with pytest.raises(ConfigError, match="does not exist"):
        targets_from_config(TargetConfig(rule="label", path=str(tmp_path / "none.nrrd")), mesh)


def test_point_files_csv_and_markups_in_either_frame(mesh, tmp_path):
    from tissuecast.slicer.markups import MarkupList, write_markups

    p = _inner_points(mesh, 4, seed=3)[0]
    csv_path = tmp_path / "targets.csv"
    csv_path.write_text("label,x,y,z\n# a comment\n" + "\n".join(f"tip {i},{a},{b},{c}" for i, (a, b, c) in enumerate(p)))
    pos, labels = read_target_points(csv_path)
    np.testing.assert_allclose(pos, p)
    assert labels == ("tip 0", "tip 1", "tip 2", "tip 3")
    ras = write_markups(tmp_path / "targets.mrk.json", [MarkupList("Targets", p)], "RAS")
    assert '"coordinateSystem": "RAS"' in ras.read_text()
    np.testing.assert_allclose(read_target_points(ras)[0], p, atol=1e-12)  # converted back to LPS
    t = targets_from_config(TargetConfig(rule="points", path=str(ras)), mesh)
    np.testing.assert_allclose(t.positions, p, atol=1e-12)
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n1,2\n")
    with pytest.raises(ConfigError, match="line 2"):
        read_target_points(bad)
    with pytest.raises(ConfigError, match="does not exist"):
        read_target_points(tmp_path / "none.csv")


def test_predicted_targets_written_as_markups_and_csv(mesh, tmp_path):
    import csv
    import json

    t = point_targets(mesh, _inner_points(mesh, 3, seed=4)[0], ("a", "b", "c"))
    u = np.random.default_rng(5).normal(size=(2, 3, 3))
    mrk = write_predicted_targets(tmp_path / "p.mrk.json", t, u)
    doc = json.loads(mrk.read_text())
    assert [m["name"] for m in doc["markups"]] == ["PredictedTargets-000", "PredictedTargets-001"]
    assert all(m["coordinateSystem"] == "LPS" for m in doc["markups"])
    np.testing.assert_allclose(doc["markups"][1]["controlPoints"][2]["position"], t.positions[2] + u[1, 2])
    with write_predicted_targets(tmp_path / "p.csv", t, u[0]).open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["label"] for r in rows] == ["a", "b", "c"]
    assert float(rows[1]["y_lps_mm"]) == pytest.approx(t.positions[1, 1] + u[0, 1, 1], abs=1e-6)
    with pytest.raises(ModelError, match="not 'p.vtu'"):
        write_predicted_targets(tmp_path / "p.vtu", t, u[0])
    with pytest.raises(ModelError, match=r"\(3, 3\)"):
        write_predicted_targets(tmp_path / "p.csv", t, u[:, :2])


def test_tre_and_share_corrected_closed_forms():
    true = np.zeros((2, 4, 3))
    true[:, :, 0] = [[1.0, 2.0, 3.0, 4.0], [2.0, 2.0, 2.0, 2.0]]
    pred = true.copy()
    pred[0, :, 1] = [0.0, 0.0, 0.0, 2.0]  # sample 0: one target 2 mm off
    tre = target_errors(pred, true)
    np.testing.assert_allclose(tre[0], [0.5, np.percentile([0, 0, 0, 2.0], 95), 2.0])
    np.testing.assert_allclose(tre[1], 0.0)
    moved = np.linalg.norm(true, axis=2).mean(axis=1)  # 2.5 and 2.0 mm
    np.testing.assert_allclose(share_corrected(tre[:, 0], moved), [1 - 0.5 / 2.5, 1.0])
    # predicting no motion corrects none of it; a target that did not move gives NaN
    np.testing.assert_allclose(share_corrected(target_errors(np.zeros_like(true), true)[:, 0], moved), 0.0, atol=1e-15)
    assert np.isnan(share_corrected([0.1], [0.0])[0])
    s = summarize_targets(np.vstack([tre, [[np.nan] * 3]]), np.r_[moved, 1.0])
    assert s.count == 3 and s.tre_mean == pytest.approx(0.25) and s.tre_max == pytest.approx(1.0)
    assert s.share_corrected_mean == pytest.approx(0.9) and s.share_corrected_worst == pytest.approx(0.8)


def test_targets_refuse_arrays_of_the_wrong_shape(mesh):
    from tissuecast.errors import MeshError
    from tissuecast.evaluate.targets import point_targets

    t = interior_targets(mesh, count=4)
    u = np.zeros((mesh.n_vertices, 3))
    assert t.displacements(u).shape == (4, 3) and t.displacements(u[None]).shape == (1, 4, 3)
    for bad in (u.ravel(), u[:100], np.zeros((mesh.n_vertices, 2))):
        with pytest.raises(MeshError, match=r"vertex fields \(n, 3\) or \(B, n, 3\) mm"):
            t.displacements(bad)
    with pytest.raises(MeshError, match="must be \\(k, 3\\) or \\(3,\\)"):
        point_targets(mesh, np.zeros((2, 2)))
    with pytest.raises(MeshError, match="transposed"):
        point_targets(mesh, t.positions[:4].T[:, :4])
    assert point_targets(mesh, t.positions[0]).count == 1
