"""`tissuecast mesh ...` and `tissuecast markers ...`, run in-process."""

from __future__ import annotations

import csv
import json

import meshio
import numpy as np
import pytest
from mesh_factories import box_grid

import tissuecast as tc
from tissuecast.cli.main import main
from tissuecast.mesh import read_mesh, write_mesh


def test_mesh_info_phantom_prints_the_figures(capsys):
    assert main(["mesh", "info", "phantom"]) == 0
    out = capsys.readouterr().out
    m = tc.phantom()
    assert f"vertices           {m.n_vertices}  ({len(m.surface_vertices)} on the surface" in out
    assert f"tetrahedra         {m.n_tets}" in out
    assert f"surface triangles  {len(m.surface_triangles)}" in out
    assert f"volume             {m.volume:.2f} mm^3" in out
    assert m.fingerprint() in out


def test_mesh_info_json_on_a_box(tmp_path, capsys):
    write_mesh(tmp_path / "box.vtu", box_grid(2, 3, 4, size=(0.5, 0.5, 0.5)))  # 1 x 1.5 x 2 cm
    assert main(["mesh", "info", str(tmp_path / "box.vtu"), "--units", "cm", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["vertices"] == 60 and info["tetrahedra"] == 144
    assert info["surface_triangles"] == 104 and info["surface_vertices"] == 54 and info["interior_vertices"] == 6
    assert info["edges"] == 255
    assert info["volume_mm3"] == pytest.approx(10 * 15 * 20)
    assert info["extent_mm"] == pytest.approx([10, 15, 20])
    assert info["surface_area_mm2"] == pytest.approx(2 * (150 + 300 + 200))


@pytest.mark.parametrize("ext", [".inp", ".node", ".vtk"])
def test_mesh_convert_round_trip(tmp_path, capsys, ext):
    m = box_grid(2, 2, 1, size=(1.0, 2.0, 3.0))
    write_mesh(tmp_path / "in.vtu", m)
    assert main(["mesh", "convert", str(tmp_path / "in.vtu"), str(tmp_path / f"out{ext}"), "--units", "cm"]) == 0
    assert f"wrote {tmp_path / f'out{ext}'}" in capsys.readouterr().out
    back = read_mesh(tmp_path / f"out{ext}")
    np.testing.assert_allclose(back.points, 10.0 * m.points)
    np.testing.assert_array_equal(back.tets, m.tets)


def test_mesh_convert_surface_to_volume(tmp_path, capsys):
    cube = box_grid(1, 1, 1, size=(12.0, 12.0, 12.0))
    write_mesh(tmp_path / "cube.stl", cube)
    assert main(["mesh", "convert", str(tmp_path / "cube.stl"), str(tmp_path / "cube.vtu"), "--mesh-size", "4"]) == 0
    m = read_mesh(tmp_path / "cube.vtu")
    assert m.volume == pytest.approx(1728.0, rel=1e-9)
    assert m.n_vertices > 27


def test_mesh_phantom_writes_the_phantom(tmp_path, capsys):
    assert main(["mesh", "phantom", str(tmp_path / "ph.vtu")]) == 0
    assert "phantom: 1165 vertices" in capsys.readouterr().out
    assert read_mesh(tmp_path / "ph.vtu").fingerprint() == tc.phantom().fingerprint()


def test_markers_on_phantom_writes_csv_json_vtu(tmp_path, capsys):
    prefix = tmp_path / "out" / "fm"
    assert main(["markers", "phantom", "--count", "5", "--start", "96", "--min-distance", "10", "--out", str(prefix)]) == 0
    out = capsys.readouterr().out
    assert "0-based" in out
    m = tc.phantom()
    markers = tc.select_markers(m, count=5, start=96, min_distance=10.0)
    fixed = tc.select_fixed_vertices(m, count=3, exclude=markers)
    doc = json.loads((tmp_path / "out" / "fm.json").read_text())
    assert doc["ids_are_0_based"] is True and doc["units"] == "mm"
    assert doc["markers"]["ids"] == markers.tolist() and doc["markers"]["ids"][0] == 96
    assert doc["fixed"]["ids"] == fixed.tolist()
    np.testing.assert_allclose(doc["markers"]["coordinates"], m.points[markers])
    assert doc["parameters"]["min_distance_mm"] == 10.0 and doc["mesh_fingerprint"] == m.fingerprint()
    assert doc["parameters"]["fixed_rule"] == "compact" and doc["parameters"]["fixed_spacing_mm"] == 5.0
    rows = list(csv.DictReader(open(tmp_path / "out" / "fm.csv")))
    assert [r["role"] for r in rows] == ["marker"] * 5 + ["fixed"] * 3
    assert [int(r["vertex_id_0based"]) for r in rows] == markers.tolist() + fixed.tolist()
    assert float(rows[0]["x_mm"]) == pytest.approx(m.points[96, 0], abs=1e-6)
    vtu = meshio.read(tmp_path / "out" / "fm.vtu")
    assert vtu.point_data["role"].tolist() == [1] * 5 + [2] * 3
    assert vtu.point_data["vertex_id"].tolist() == markers.tolist() + fixed.tolist()
    np.testing.assert_allclose(vtu.points[:5], m.points[markers])
    for i in markers:
        assert f" {int(i):6d} " in out
    # one numbering of markers everywhere: the table, the CSV's order, the markups' labels (marker
    # k is M<k>, as OpenIGTLink's Marker<k> and the input gate's "marker k")
    from tissuecast.slicer.markups import read_markups

    lists = {m.name: m for m in read_markups(tmp_path / "out" / "fm.mrk.json")}
    assert list(lists["FiducialMarkers"].labels) == [f"M{k}" for k in range(5)]
    assert list(lists["FixedVertices"].labels) == ["F0", "F1", "F2"]
    assert [int(r["order"]) for r in rows[:5]] == list(range(5))
    assert [line.split()[1] for line in out.splitlines() if line.startswith("marker ")] == [str(k) for k in range(5)]
    inside = [k for k, i in enumerate(markers) if i not in set(m.surface_vertices.tolist())]
    assert (f"note: marker(s) {inside} are interior vertices" in out) == bool(inside)
    assert main(["markers", "phantom", "--out", str(tmp_path / "default")]) == 0  # the k-center default: one inside
    assert "note: marker(s) [2] are interior vertices: an optical tracker cannot see them" in capsys.readouterr().out


def test_markers_with_user_given_ids(tmp_path, capsys):
    args = ["markers", "phantom", "--ids", "3", "7", "11", "--fixed-ids", "1000", "1001", "--out", str(tmp_path / "u")]
    assert main(args) == 0
    doc = json.loads((tmp_path / "u.json").read_text())
    assert doc["markers"]["ids"] == [3, 7, 11] and doc["fixed"]["ids"] == [1000, 1001]
    assert doc["parameters"]["user_given_markers"] is True



def test_markers_fixed_rule_flags(tmp_path, capsys):
    m = tc.phantom()
    markers = tc.select_markers(m)
    for rule, spacing in (("spread", None), ("compact", 8.0)):
        args = ["markers", "phantom", "--fixed-rule", rule, "--out", str(tmp_path / rule)]
        assert main(args + (["--fixed-spacing", str(spacing)] if spacing else [])) == 0
        doc = json.loads((tmp_path / f"{rule}.json").read_text())
        want = tc.select_fixed_vertices(m, exclude=markers, rule=rule, spacing=spacing or 5.0)
        assert doc["fixed"]["ids"] == want.tolist() and doc["parameters"]["fixed_rule"] == rule
    assert doc["fixed"]["ids"] == [769, 1078, 1009]  # compact at 8 mm: sides 8.0, 8.3, 8.4 mm
    assert main(["markers", "phantom", "--fixed-rule", "compact", "--fixed-spacing", "40", "--out", str(tmp_path / "x")]) == 2
    assert "no room for 3 compact fixed vertices" in capsys.readouterr().err


def test_markers_png(tmp_path, capsys):
    pytest.importorskip("pyvista")
    assert main(["markers", "phantom", "--out", str(tmp_path / "pic"), "--png"]) == 0
    png = (tmp_path / "pic.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_markers_reads_the_config_and_flags_override_it(tmp_path, capsys):
    write_mesh(tmp_path / "ph.vtu", tc.phantom())
    (tmp_path / "c.toml").write_text(
        f"[mesh]\npath = '{tmp_path / 'ph.vtu'}'\n[markers]\ncount = 4\nstart = 10\nmin_distance = 8.0\nfixed_count = 2\n"
    )
    assert main(["markers", "--config", str(tmp_path / "c.toml"), "--start", "20", "--out", str(tmp_path / "c")]) == 0
    doc = json.loads((tmp_path / "c.json").read_text())
    expect = tc.select_markers(tc.phantom(), count=4, start=20, min_distance=8.0)
    assert doc["markers"]["ids"] == expect.tolist() and len(doc["fixed"]["ids"]) == 2
    assert doc["parameters"]["mesh"] == str(tmp_path / "ph.vtu")
