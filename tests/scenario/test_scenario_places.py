"""Places a preset names that carry over to another mesh: a 3D Slicer markups point, a direction
rule (the most anterior point...), a label-map region; their config errors; the preview."""

from __future__ import annotations

import json

import numpy as np
import pytest
from labelmap_factories import write_nifti, write_nrrd
from mesh_factories import box_grid

from tissuecast.cli.main import main
from tissuecast.config import RegionConfig, config_from_dict
from tissuecast.errors import ConfigError
from tissuecast.mesh import phantom, write_mesh
from tissuecast.scenario import surface_region
from tissuecast.scenario.regions import region_anchors
from tissuecast.slicer.markups import MarkupList, write_markups

BOX = box_grid(3, 4, 5, (2.0, 2.0, 2.0))  # 6 x 8 x 10 mm, corner at the origin


def _within(mesh, centre, radius):
    surface = mesh.surface_vertices
    return surface[np.linalg.norm(mesh.points[surface] - centre, axis=1) <= radius]


# ------------------------------------------------------------------------------- markups
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_markups_point_is_snapped_to_the_surface_in_its_frame(tmp_path, system):
    vertex = int(np.flatnonzero(np.all(BOX.points == [6.0, 4.0, 6.0], axis=1))[0])  # on the +x face
    point = BOX.points[vertex] + [1.5, 0.2, -0.3]  # placed 1.5 mm off the surface, as on the skin
    path = write_markups(tmp_path / "access.mrk.json", [MarkupList("Access", point[None])], system)
    if system == "RAS":
        assert json.loads(path.read_text())["markups"][0]["controlPoints"][0]["position"][0] == pytest.approx(-7.5)
    rule = RegionConfig(rule="markups", markups=str(path), distance=2.5)
    np.testing.assert_array_equal(region_anchors(BOX, rule, "k"), [vertex])
    np.testing.assert_array_equal(surface_region(BOX, rule, "k"), _within(BOX, BOX.points[vertex], 2.5))


def test_markups_label_picks_points_and_errors_name_the_keys(tmp_path):
    pts = np.array([[6.0, 4.0, 6.0], [0.0, 0.0, 0.0], [np.nan] * 3])
    path = write_markups(tmp_path / "p.mrk.json", [MarkupList("Places", pts, ("Access", "Base", "Unplaced"))])
    rule = RegionConfig(rule="markups", markups=str(path), markup_label="Base", distance=0.5)
    np.testing.assert_array_equal(surface_region(BOX, rule, "k"), [0])
    both = region_anchors(BOX, RegionConfig(rule="markups", markups=str(path)), "k")  # the undefined point is skipped
    assert both.tolist() == sorted([0, int(np.flatnonzero(np.all(BOX.points == [6.0, 4.0, 6.0], axis=1))[0])])
    key = "scenario.indentation.access"
    with pytest.raises(ConfigError, match=rf"{key}: '.*p.mrk.json' holds no placed point with label 'Tip'.*Access, "
                                          rf"Base.*set {key}.markup_label"):
        surface_region(BOX, RegionConfig(rule="markups", markups=str(path), markup_label="Tip"), key)
    with pytest.raises(ConfigError, match=rf"{key}: '.*p.mrk.json' holds no placed point with label 'Unplaced'"):
        surface_region(BOX, RegionConfig(rule="markups", markups=str(path), markup_label="Unplaced"), key)
    far = write_markups(tmp_path / "far.mrk.json", [MarkupList("F", np.array([[40.0, 4.0, 5.0]]))])
    with pytest.raises(ConfigError, match=rf"{key}: point 'F-1' of .* lies 34 mm from the outer surface, farther than "
                                          rf"{key}.snap = 20 mm; is the file in this mesh's frame"):
        surface_region(BOX, RegionConfig(rule="markups", markups=str(far)), key)
    assert surface_region(BOX, RegionConfig(rule="markups", markups=str(far), snap=40.0), key).size
    with pytest.raises(ConfigError, match=rf"{key}.markups: markups file '.*missing.mrk.json' does not exist"):
        surface_region(BOX, RegionConfig(rule="markups", markups=str(tmp_path / "missing.mrk.json")), key)
    (tmp_path / "bad.mrk.json").write_text("{")
    with pytest.raises(ConfigError, match=rf"{key}.markups: '.*bad.mrk.json' is not valid JSON"):
        surface_region(BOX, RegionConfig(rule="markups", markups=str(tmp_path / "bad.mrk.json")), key)


# ------------------------------------------------------------------------------- extreme
def test_extreme_rule_finds_the_most_anterior_point_on_any_mesh():
    mesh = phantom()
    surface = mesh.surface_vertices
    front = int(surface[np.argmin(mesh.points[surface, 1])])  # anterior = -y in LPS
    rule = RegionConfig(rule="extreme", toward="anterior", distance=6.0)
    np.testing.assert_array_equal(region_anchors(mesh, rule, "k"), [front])
    region = surface_region(mesh, rule, "k")
    np.testing.assert_array_equal(region, _within(mesh, mesh.points[front], 6.0))
    same = RegionConfig(rule="extreme", direction=(0.0, -3.0, 0.0), distance=6.0)
    np.testing.assert_array_equal(surface_region(mesh, same, "k"), region)
    # the rule travels: on the phantom moved and turned (a patient's mesh elsewhere), the same anatomical place
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z: -x becomes -y
    moved = type(mesh)(mesh.points @ turn.T + [100.0, -50.0, 20.0], mesh.tets)
    left_before = int(surface[np.argmin(mesh.points[surface, 0])])  # the old right-most (-x) point is now in front
    assert region_anchors(moved, rule, "k").tolist() == [left_before]
    # 'toward' works with the normal rule too
    normal = surface_region(mesh, RegionConfig(rule="normal", toward="posterior", angle=30.0), "k")
    np.testing.assert_array_equal(normal, surface_region(mesh, RegionConfig(rule="normal", direction=(0.0, 1.0, 0.0),
                                                                                angle=30.0), "k"))


# --------------------------------------------------------------------------------- label
@pytest.mark.parametrize("kind", ["nrrd", "nifti"])
def test_label_rule_selects_the_face_resting_on_a_segmented_structure(tmp_path, kind):
    pytest.importorskip("nibabel")
    pytest.importorskip("slicerio")
    # a 1 mm grid under and around the box; label 3 = a bony layer just below its base (z = -1 mm)
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, 3] = [-3.0, -3.0, -3.0]
    voxels = np.zeros((13, 15, 17), dtype=np.uint8)
    voxels[:, :, 2] = 3  # z = -1 mm
    voxels[0, 0, 16] = 5  # another label, away from the box
    path = (write_nrrd(tmp_path / "bone.nrrd", voxels, ijk_to_lps) if kind == "nrrd"
            else write_nifti(tmp_path / "bone.nii.gz", voxels, ijk_to_lps))  # NIfTI: RAS in the file
    region = surface_region(BOX, RegionConfig(rule="label", label_map=str(path), label=3), "scenario.attached")
    np.testing.assert_array_equal(region, np.flatnonzero(BOX.points[:, 2] == 0.0))
    key = "scenario.attached"
    with pytest.raises(ConfigError, match=rf"{key}: rule 'label' selects no surface vertex: no outer-surface vertex "
                                          "lies in or next to the label"):
        surface_region(BOX, RegionConfig(rule="label", label_map=str(path), label=5), key)
    with pytest.raises(ConfigError, match=rf"{key}.label_map: .*label 9"):
        surface_region(BOX, RegionConfig(rule="label", label_map=str(path), label=9), key)


# ----------------------------------------------------------------------------- config keys
@pytest.mark.parametrize("section, text", [
    ({"rule": "distance", "toward": "anterior"}, "scenario.attached.toward applies to rules 'normal' and 'extreme'"),
    ({"rule": "normal", "markups": "a.mrk.json"}, "scenario.attached.markups applies to rule = 'markups'"),
    ({"rule": "surface", "markup_label": "A"}, "scenario.attached.markup_label applies to rule = 'markups'"),
    ({"rule": "normal", "label_map": "s.nrrd"}, "scenario.attached.label_map applies to rule = 'label'"),
    ({"rule": "surface", "label": 2}, "scenario.attached.label applies to rule = 'label'"),
    ({"rule": "markups"}, "scenario.attached.rule = 'markups' needs scenario.attached.markups"),
    ({"rule": "markups", "markups": "access.json"}, "needs scenario.attached.markups, a 3D Slicer markups file"),
    ({"rule": "label", "label_map": "bone.vtu"}, "scenario.attached.rule = 'label' needs scenario.attached.label_map"),
    ({"rule": "extreme", "toward": "front"}, "scenario.attached.toward = 'front' is not allowed"),
    ({"rule": "markups", "markups": "a.mrk.json", "snap": 0.0}, "scenario.attached.snap = 0.0 is out of range"),
])
def test_new_region_keys_are_validated_naming_the_key(section, text):
    from tissuecast.app import check_config

    with pytest.raises(ConfigError, match=text.replace("(", r"\(").replace(")", r"\)")):
        check_config(config_from_dict({"scenario": {"attached": section}}))


def test_a_label_rule_without_a_label_map_is_refused_where_the_region_is_chosen():
    # config.py checks values only; the file kind is asked by the scenario package
    rule = config_from_dict({"scenario": {"attached": {"rule": "label", "label_map": "bone.vtu"}}}).scenario.attached
    with pytest.raises(ConfigError, match="scenario.attached.rule = 'label' needs scenario.attached.label_map"):
        surface_region(BOX, rule, "scenario.attached")


def test_access_keys_are_validated_under_their_own_key():
    with pytest.raises(ConfigError, match="scenario.indentation.access.toward applies to rules"):
        config_from_dict({"scenario": {"indentation": {"access": {"rule": "surface", "toward": "anterior"}}}})


# ------------------------------------------------------------------ the preset on another mesh
def _embedded_on(mesh_path, access: dict) -> dict:
    from tissuecast.app.presets import preset_config
    from tissuecast.config import config_to_dict

    data = config_to_dict(preset_config("embedded"))
    data["mesh"]["path"] = str(mesh_path)
    data["scenario"]["indentation"]["access"] = access
    return data


def test_embedded_preset_travels_with_a_markups_access(tmp_path, capsys):
    from tissuecast.scenario import scenario_from_config

    mesh = phantom()
    shift = np.array([40.0, -25.0, 60.0])  # the same anatomy in another scan's coordinates
    write_mesh(tmp_path / "patient.vtu", type(mesh)(mesh.points + shift, mesh.tets))
    preset_point = np.array([11.9, 0.8, 32.7])  # configs/embedded.toml's access point (phantom coordinates)
    data = _embedded_on(tmp_path / "patient.vtu", {"rule": "distance", "point": preset_point.tolist(), "distance": 3.0})
    with pytest.raises(ConfigError, match=r"nearest is .* mm away\); a point in the coordinates of another mesh does not "
                                          r"carry over: give the place as a 3D Slicer point"):
        scenario_from_config(config_from_dict(data))
    # the surgeon's point, placed on the patient's scan in Slicer (saved in RAS)
    path = write_markups(tmp_path / "access.mrk.json", [MarkupList("Access", (preset_point + shift)[None])], "RAS")
    cfg = config_from_dict(_embedded_on(tmp_path / "patient.vtu", {"rule": "markups", "markups": str(path),
                                                                     "distance": 3.0}))
    _, _, _, on_patient = scenario_from_config(cfg)
    from tissuecast.app.presets import preset_config

    _, _, _, on_phantom = scenario_from_config(preset_config("embedded"))
    np.testing.assert_array_equal(on_patient.sites.access, on_phantom.sites.access)  # the same vertices
    np.testing.assert_array_equal(on_patient.attached, on_phantom.attached)
    # scenario preview shows the place on the user's mesh: VTU point data, JSON, printed coordinates
    (tmp_path / "p.toml").write_text(_toml(cfg))
    out = tmp_path / "prev" / "p"
    assert main(["scenario", "preview", str(tmp_path / "p.toml"), "--no-png", "--no-deformations", "--examples", "2",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    doc = json.loads(out.with_suffix(".json").read_text())
    anchor = doc["places"]["access"]["vertices"]
    assert len(anchor) == 1 and f"surgical access   {len(on_phantom.sites.access)} surface vertices (rule markups) at " \
                                 f"vertex {anchor[0]}" in printed
    np.testing.assert_allclose(doc["places"]["access"]["lps_mm"][0], preset_point + shift, atol=3.0)
    import meshio

    access = meshio.read(out.with_suffix(".vtu")).point_data["indentation_access"]
    np.testing.assert_array_equal(np.flatnonzero(access), doc["access"])
    np.testing.assert_array_equal(doc["access"], on_phantom.sites.access)


def _toml(cfg) -> str:
    from tissuecast.config import config_to_toml

    return config_to_toml(cfg, comments=False)
