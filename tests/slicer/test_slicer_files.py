"""3D Slicer files: markups (.mrk.json against Slicer's published schema, .fcsv, LPS/RAS) and
model files that state their coordinate system the way Slicer reads it."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from serve_support import box_mesh, small_model

from tissuecast.mesh import phantom, read_mesh
from tissuecast.slicer.markups import MarkupList, MarkupsError, markups_document, markups_schema, read_markups, write_markups

jsonschema = pytest.importorskip("jsonschema")


def _validate(doc: dict) -> None:
    jsonschema.Draft7Validator(markups_schema()).validate(doc)


def _lists():
    rng = np.random.default_rng(0)
    markers = rng.normal(0.0, 40.0, (5, 3))
    markers[3] = np.nan  # a point not placed yet
    return [MarkupList("FiducialMarkers", markers, tuple(f"M{i + 1}" for i in range(5))),
            MarkupList("FixedVertices", rng.normal(0.0, 40.0, (3, 3)))]


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_markups_validate_against_slicer_schema_and_round_trip_exactly(tmp_path, system):
    lists = _lists()
    path = write_markups(tmp_path / "m.mrk.json", lists, system)
    doc = json.loads(path.read_text())
    _validate(doc)
    assert doc["markups"][0]["coordinateSystem"] == system and "position" not in doc["markups"][0]["controlPoints"][3]
    back = read_markups(path)
    assert [m.name for m in back] == ["FiducialMarkers", "FixedVertices"]
    for a, b in zip(lists, back):
        np.testing.assert_array_equal(a.positions, b.positions)  # exact, NaN included
        assert a.labels == b.labels
    first = doc["markups"][0]["controlPoints"][0]["position"]
    sign = [1, 1, 1] if system == "LPS" else [-1, -1, 1]
    assert first == (lists[0].positions[0] * sign).tolist()


def test_schema_validation_can_fail():
    doc = markups_document(_lists())
    doc["markups"][0]["coordinateSystem"] = "XYZ"
    with pytest.raises(jsonschema.ValidationError):
        _validate(doc)
    del doc["@schema"]
    with pytest.raises(jsonschema.ValidationError):
        _validate(doc)


def test_fcsv_reads_like_slicerio_and_old_files_are_ras(tmp_path):
    slicerio = pytest.importorskip("slicerio")
    from slicerio.markups import read_markups_fcsv

    sample = os.path.join(os.path.dirname(slicerio.__file__), "data", "F_1.fcsv")  # written by 3D Slicer, LPS
    ours = read_markups(sample)[0]
    theirs = read_markups_fcsv(sample)["markups"][0]
    assert theirs["coordinateSystem"] == "LPS"
    np.testing.assert_array_equal(ours.positions, [p["position"] for p in theirs["controlPoints"]])
    assert ours.labels == tuple(p["label"] for p in theirs["controlPoints"])
    old = tmp_path / "old.fcsv"
    old.write_text("# Markups fiducial file version = 4.6\n"
                   "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                   "vtkMRMLMarkupsFiducialNode_0,1.5,-2,3,0,0,0,1,1,1,0,F-1,,\n")
    np.testing.assert_array_equal(read_markups(old)[0].positions, [[-1.5, 2.0, 3.0]])


def test_bad_markups_files_are_refused(tmp_path):
    bad = tmp_path / "b.mrk.json"
    bad.write_text(json.dumps({"@schema": "x",
                               "markups": [{"type": "Fiducial", "coordinateSystem": "XYZ", "controlPoints": []}]}))
    with pytest.raises(MarkupsError, match="unknown coordinate system 'XYZ'"):
        read_markups(bad)
    bad.write_text(json.dumps({"@schema": "x", "markups": [{"type": "Line", "controlPoints": []}]}))
    with pytest.raises(MarkupsError, match="holds no point list"):
        read_markups(bad)
    bad.write_text(json.dumps({"@schema": "x", "markups": [{"type": "Fiducial", "controlPoints": [{"position": [1, 2]}]}]}))
    with pytest.raises(MarkupsError, match="three numbers are needed"):
        read_markups(bad)


def test_markers_command_writes_valid_markups_in_the_mesh_frame(tmp_path):
    from tissuecast.cli.main import main

    prefix = tmp_path / "mk"
    assert main(["markers", "phantom", "--out", str(prefix)]) == 0
    doc = json.loads((tmp_path / "mk.mrk.json").read_text())
    _validate(doc)
    ids = json.loads((tmp_path / "mk.json").read_text())
    lists = read_markups(tmp_path / "mk.mrk.json")
    mesh = phantom()
    np.testing.assert_array_equal(lists[0].positions, mesh.points[ids["markers"]["ids"]])
    np.testing.assert_array_equal(lists[1].positions, mesh.points[ids["fixed"]["ids"]])
    assert doc["markups"][0]["name"] == "FiducialMarkers" and doc["markups"][0]["coordinateSystem"] == "LPS"
    assert lists[0].descriptions[0] == f"vertex {ids['markers']['ids'][0]} (0-based)"


@pytest.mark.parametrize("kind", ["single", "masked"])
def test_predict_reads_ras_markups_and_writes_slicer_models(tmp_path, kind, capsys):
    from tissuecast.cli.main import main
    from tissuecast.slicer.models import read_model_space

    model = small_model(kind)
    model.save(tmp_path / "model")
    rng = np.random.default_rng(1)
    positions = model.reference_marker_positions + rng.normal(0.0, 1.0, (model.n_markers, 3))
    missing = np.zeros(model.n_markers, bool)
    if kind == "masked":
        missing[1] = True
        positions[1] = np.nan
    ras = positions * [-1.0, -1.0, 1.0]
    doc = markups_document([MarkupList("tracked", positions)], "RAS")
    assert doc["markups"][0]["controlPoints"][0]["position"] == ras[0].tolist()
    path = tmp_path / "tracked.mrk.json"
    path.write_text(json.dumps(doc))
    out = tmp_path / "surface.vtp"
    assert main(["predict", str(tmp_path / "model"), "--markers", str(path), "--out", str(out)]) == 0
    d = positions - model.reference_marker_positions
    u = model.predict(d[None], missing=missing[None] if missing.any() else None)[0]
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(out))
    reader.Update()
    surface = reader.GetOutput()
    ids = model.mesh.surface_vertices
    np.testing.assert_allclose(vtk_to_numpy(surface.GetPoints().GetData()), (model.mesh.points + u)[ids], atol=1e-6)
    np.testing.assert_allclose(vtk_to_numpy(surface.GetPointData().GetArray("displacement_mm")), u[ids], atol=1e-9)
    assert read_model_space(out) == "LPS"
    vtk_out = tmp_path / "volume.vtk"
    assert main(["predict", str(tmp_path / "model"), "--markers", str(path), "--out", str(vtk_out)]) == 0
    assert read_model_space(vtk_out) == "LPS"
    np.testing.assert_allclose(read_mesh(vtk_out).points, model.mesh.points + u, atol=1e-6)


def test_model_files_state_lps_and_ras_files_are_read_as_lps(tmp_path):
    from tissuecast.slicer.models import read_model_space, write_model

    mesh = box_mesh()
    for suffix in (".vtk", ".vtp"):
        assert read_model_space(write_model(tmp_path / f"m{suffix}", mesh)) == "LPS"
    # a .vtu states no frame by default (meshio could not read it; Slicer takes LPS), unless asked
    assert read_model_space(write_model(tmp_path / "m.vtu", mesh)) is None
    assert read_model_space(write_model(tmp_path / "s.vtu", mesh, space_array=True)) == "LPS"
    raw = (tmp_path / "m.vtk").read_bytes()
    assert b"SPACE=LPS" in raw.split(b"\n")[1]  # the header line Slicer reads
    (tmp_path / "r.vtk").write_bytes(raw.replace(b"SPACE=LPS", b"SPACE=RAS", 1))  # as Slicer saves in RAS
    np.testing.assert_array_equal(read_mesh(tmp_path / "r.vtk").points, mesh.points * [-1.0, -1.0, 1.0])
    np.testing.assert_array_equal(read_mesh(tmp_path / "m.vtu").points, mesh.points)


def test_predict_writes_the_targets_predicted_positions_as_slicer_markups_and_csv(tmp_path, capsys):
    from tissuecast.cli.main import main
    from tissuecast.evaluate.targets import interior_targets
    from tissuecast.mesh.locate import interpolate, locate_points

    model = small_model("single")
    model.save(tmp_path / "model")
    positions = model.reference_marker_positions + np.random.default_rng(2).normal(0.0, 1.0, (model.n_markers, 3))
    tracked = write_markups(tmp_path / "tracked.mrk.json", [MarkupList("tracked", positions)], "RAS")
    u = model.predict(positions - model.reference_marker_positions)
    # default: the interior targets of the model's mesh (it records no [evaluate.targets])
    out = tmp_path / "targets.mrk.json"
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tracked), "--targets-out", str(out)]) == 0
    doc = json.loads(out.read_text())
    _validate(doc)
    assert doc["markups"][0]["coordinateSystem"] == "LPS" and doc["markups"][0]["name"] == "PredictedTargets"
    t = interior_targets(model.mesh, exclude=model.fixed)
    loc = locate_points(model.mesh, t.positions)
    np.testing.assert_allclose(read_markups(out)[0].positions, t.positions + interpolate(model.mesh, loc, u), atol=1e-9)
    # listed target points (a Slicer file in RAS) and CSV output, for the rigid baseline
    points = model.mesh.points[model.mesh.tets[:3]].mean(axis=1)  # three tetrahedra's centroids
    listed = write_markups(tmp_path / "tumour.mrk.json", [MarkupList("tumour", points, ("a", "b", "c"))], "RAS")
    csv_out = tmp_path / "targets.csv"
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tracked), "--method", "rigid",
                 "--targets", str(listed), "--targets-out", str(csv_out)]) == 0
    rows = np.loadtxt(csv_out, delimiter=",", skiprows=1, usecols=range(3, 9))
    rigid = model.predict(positions - model.reference_marker_positions, method="rigid")
    expected = interpolate(model.mesh, locate_points(model.mesh, points), rigid)
    np.testing.assert_allclose(rows[:, 3:], expected, atol=1e-6)
    np.testing.assert_allclose(rows[:, :3], points + expected, atol=1e-6)
    assert csv_out.read_text().splitlines()[1].split(",")[2] == "a"
    capsys.readouterr()
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tracked), "--targets", str(listed)]) == 2
    assert "add --targets-out FILE" in capsys.readouterr().err
