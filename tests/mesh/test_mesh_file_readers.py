"""Every mesh or model file tissuecast writes, read back by meshio, pyvista, VTK and the way 3D
Slicer reads it; and every command that reads a mesh answers a broken file with one error line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from file_readers import read_everywhere, vtk_read

from tissuecast.cli.main import main
from tissuecast.mesh import phantom, read_mesh, write_mesh

meshio = pytest.importorskip("meshio")
pv = pytest.importorskip("pyvista")
pytest.importorskip("vtkmodules")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ellipsoid_scan(tmp_path_factory):
    pytest.importorskip("skimage")
    pytest.importorskip("slicerio")
    from labelmap_factories import ellipsoid_mask, write_nrrd

    mask, ijk_to_lps, _ = ellipsoid_mask((9.0, 7.0, 5.0), (0.8, 1.1, 1.5))
    return write_nrrd(tmp_path_factory.mktemp("scan") / "t.nrrd", mask.astype(np.uint8), ijk_to_lps)


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".vtp"])
def test_mesh_from_image_outputs(tmp_path, ellipsoid_scan, suffix, capsys):
    out = tmp_path / f"m{suffix}"
    assert main(["mesh", "from-image", str(ellipsoid_scan), str(out), "--size", "2"]) == 0
    assert "expected cost      a paper-size run" in capsys.readouterr().out
    if suffix == ".vtp":
        seen = read_everywhere(out, pv.read(out).points)  # the outer surface; the same points everywhere
        assert seen["slicer"].stated_space == "LPS" and (seen["slicer"].cell_types == 5).all()
        return
    mesh = read_mesh(out)
    seen = read_everywhere(out, mesh.points)
    assert seen["meshio"].cells_dict["tetra"].shape == (mesh.n_tets, 4)
    assert seen["slicer"].stated_space == ("LPS" if suffix == ".vtk" else None)


def test_space_array_vtu_is_read_by_vtk_pyvista_slicer_and_tissuecast_not_meshio(tmp_path):
    m = phantom()
    write_mesh(tmp_path / "s.vtu", m, point_data={"d": m.points[:, 0]}, space_array=True)
    from tissuecast.slicer.models import read_model_as_slicer

    assert read_model_as_slicer(tmp_path / "s.vtu").stated_space == "LPS"
    assert pv.read(tmp_path / "s.vtu").field_data["SPACE"][0] == "LPS"
    np.testing.assert_array_equal(vtk_read(tmp_path / "s.vtu")[0], m.points)
    np.testing.assert_array_equal(read_mesh(tmp_path / "s.vtu").points, m.points)
    with pytest.raises(SystemExit):  # meshio's documented limit: it cannot read string arrays (docs/files.md)
        meshio.read(tmp_path / "s.vtu")
    with pytest.raises(ValueError, match="space_array applies to .vtu files"):
        write_mesh(tmp_path / "s.vtk", m, space_array=True)


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".inp", ".xdmf", ".mesh"])
def test_mesh_convert_outputs(tmp_path, suffix, capsys):
    out = tmp_path / f"p{suffix}"
    assert main(["mesh", "convert", "phantom", str(out)]) == 0
    assert "would take about" in capsys.readouterr().out
    read_everywhere(out, phantom().points)


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".vtp"])
def test_predict_outputs(tmp_path, suffix):
    from serve_support import small_model

    model = small_model("single")
    model.save(tmp_path / "model")
    d = np.random.default_rng(3).normal(0.0, 1.0, (model.n_markers, 3))
    np.savetxt(tmp_path / "d.csv", d, delimiter=",")
    out = tmp_path / f"u{suffix}"
    assert main(["predict", str(tmp_path / "model"), "--markers", str(tmp_path / "d.csv"), "--out", str(out)]) == 0
    u = model.predict(d)
    mesh = model.mesh
    if suffix == ".vtu":  # the undeformed mesh with the field
        seen = read_everywhere(out, mesh.points, ("displacement_mm",))
        np.testing.assert_allclose(seen["meshio"].point_data["displacement_mm"], u, atol=1e-9)
    elif suffix == ".vtk":  # the deformed mesh
        seen = read_everywhere(out, mesh.points + u, ("displacement_mm",))
        np.testing.assert_allclose(seen["meshio"].point_data["displacement_mm"], u, atol=1e-9)
    else:
        ids = mesh.surface_vertices
        read_everywhere(out, (mesh.points + u)[ids], ("displacement_mm",))


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from dataset_helpers import small_config

    from tissuecast.dataset import simulate

    folder = tmp_path_factory.mktemp("store")
    cfg = small_config(folder, alpha=20.0)
    simulate(cfg, folder / "ds.zarr", progress=False, solver_factory="dataset_helpers:fake_solver_factory",
             workers=1)
    return folder / "ds.zarr"


@pytest.mark.parametrize("suffix", [".vtu", ".vtk"])
def test_dataset_export_outputs(tmp_path, store, suffix):
    from tissuecast.dataset import open_dataset

    ds = open_dataset(store)
    i = int(ds.select(status="done")[0])
    out = tmp_path / f"s{suffix}"
    assert main(["dataset", "export", str(store), "--sample", str(i), str(out)]) == 0
    u = np.asarray(ds.displacements[i], dtype=np.float64)
    seen = read_everywhere(out, ds.mesh.points + u, ("displacement", "force", "displacement_magnitude"))
    np.testing.assert_allclose(seen["meshio"].point_data["displacement"], u, atol=1e-6)


def test_report_vtu_writer_output(tmp_path):
    """The report's VTU folder is written by evaluate.render.write_vtu: the one mesh writer."""
    from tissuecast.evaluate.render import write_vtu

    m = phantom()
    u = np.column_stack([m.points[:, 1], -m.points[:, 0], np.zeros(m.n_vertices)]) * 0.01
    path = write_vtu(tmp_path / "test1_median.vtu", m, {"benchmark_displacement": u,
                                                         "vertex_error": np.linalg.norm(u, axis=1)})
    seen = read_everywhere(path, m.points, ("benchmark_displacement", "vertex_error"))
    np.testing.assert_allclose(seen["pyvista"].point_data["benchmark_displacement"], u)


def test_markers_and_scenario_preview_outputs(tmp_path, capsys):
    assert main(["markers", "phantom", "--out", str(tmp_path / "mk")]) == 0
    m = phantom()
    doc = json.loads((tmp_path / "mk.json").read_text())
    ids = doc["markers"]["ids"] + doc["fixed"]["ids"]
    read_everywhere(tmp_path / "mk.vtu", m.points[ids])
    from tissuecast.slicer.markups import read_markups

    lists = read_markups(tmp_path / "mk.mrk.json")  # the Slicer way: coordinateSystem honoured
    np.testing.assert_allclose(lists[0].positions, m.points[doc["markers"]["ids"]])


# ------------------------------------------------------------------------ broken files
def _broken(path: Path, kind: str, good: bytes) -> Path:
    content = {"empty": b"", "truncated": good[: len(good) // 2],
               "random": np.random.default_rng(len(path.name)).bytes(3000)}[kind]
    path.write_bytes(content)
    return path


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "tissuecast.cli.main", *args], cwd=cwd, env=env, capture_output=True,
                          timeout=300)


def _one_error_line(result: subprocess.CompletedProcess, name: str) -> str:
    err = result.stderr.decode("utf-8", "replace")
    lines = [x for x in err.strip().splitlines() if not x.startswith(("INFO ", "DEBUG "))]
    assert result.returncode == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0], err
    return lines[0]


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".inp", ".stl", ".ply", ".obj", ".off", ".mesh", ".xdmf",
                                    ".node"])
@pytest.mark.parametrize("kind", ["empty", "truncated", "random"])
def test_broken_mesh_files_give_one_error_line_in_process(tmp_path, capsys, suffix, kind):
    good = write_mesh(tmp_path / f"good{suffix}", phantom())[0].read_bytes()
    path = _broken(tmp_path / f"{kind}{suffix}", kind, good)
    if suffix == ".node":
        _broken(tmp_path / f"{kind}.ele", kind, (tmp_path / "good.ele").read_bytes())
    assert main(["mesh", "info", str(path)]) == 2
    captured = capsys.readouterr()
    lines = [x for x in captured.err.strip().splitlines() if not x.startswith(("INFO ", "DEBUG "))]
    assert len(lines) == 1 and lines[0].startswith("error: ") and path.name in lines[0], captured.err
    assert captured.out == ""


def test_broken_mesh_files_give_one_error_line_on_every_command(tmp_path):
    """In a fresh process (VTK and meshio print below Python's stderr when let), per command."""
    from dataset_helpers import small_config, write_config

    good = write_mesh(tmp_path / "good.vtu", phantom())[0].read_bytes()
    for kind in ("empty", "truncated", "random"):
        _one_error_line(_run(["mesh", "info", _broken(tmp_path / f"{kind}.vtu", kind, good).name], tmp_path),
                        f"{kind}.vtu")
    bad = _broken(tmp_path / "bad.vtu", "random", good).name
    for args in (["mesh", "convert", bad, "out.vtk"], ["markers", bad], ["export-inp", bad, "x.inp"]):
        _one_error_line(_run(args, tmp_path), "bad.vtu")
    cfg = small_config(tmp_path)
    toml = write_config(cfg, tmp_path / "c.toml").read_text().replace(cfg.mesh.path, str(tmp_path / "bad.vtu"))
    (tmp_path / "c.toml").write_text(toml)
    for args in (["simulate", "c.toml", "--no-progress"], ["scenario", "preview", "c.toml", "--no-png"]):
        _one_error_line(_run(args, tmp_path), "bad.vtu")
    from serve_support import small_model

    small_model("single").save(tmp_path / "model")
    np.savetxt(tmp_path / "d.csv", np.zeros((4, 3)), delimiter=",")
    mesh_npz = tmp_path / "model" / "mesh.npz"
    good_npz = mesh_npz.read_bytes()
    for kind in ("empty", "truncated", "random"):
        _broken(mesh_npz, kind, good_npz)
        _one_error_line(_run(["predict", "model", "--markers", "d.csv"], tmp_path), "mesh.npz")


@pytest.mark.parametrize("mode", ["appended", "binary", "ascii"])
def test_a_slicer_vtu_in_ras_is_read_by_meshio_after_its_string_array_and_converted(tmp_path, mode):
    """As 3D Slicer saves a model: VTK's XML writer, RAS coordinates, SPACE = "RAS" in the field data."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints, vtkStringArray
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkUnstructuredGrid
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

    m = phantom()
    ras = m.points * [-1.0, -1.0, 1.0]
    grid = vtkUnstructuredGrid()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(ras), deep=True))
    grid.SetPoints(points)
    cells = vtkCellArray()
    cells.SetData(numpy_to_vtkIdTypeArray(np.arange(0, 4 * m.n_tets + 1, 4, dtype=np.int64), deep=True),
                  numpy_to_vtkIdTypeArray(np.ascontiguousarray(m.tets.ravel()), deep=True))
    grid.SetCells(10, cells)
    space = vtkStringArray()
    space.SetName("SPACE")
    space.InsertNextValue("RAS")
    grid.GetFieldData().AddArray(space)
    writer = vtkXMLUnstructuredGridWriter()
    writer.SetInputData(grid)
    writer.SetFileName(str(tmp_path / "slicer.vtu"))
    {"appended": writer.SetDataModeToAppended, "binary": writer.SetDataModeToBinary,
     "ascii": writer.SetDataModeToAscii}[mode]()
    writer.SetCompressorTypeToZLib()
    assert writer.Write()
    with pytest.raises(SystemExit):
        meshio.read(tmp_path / "slicer.vtu")  # what a meshio script meets with Slicer's files
    back = read_mesh(tmp_path / "slicer.vtu")  # tissuecast: the string array set aside, RAS -> LPS
    np.testing.assert_allclose(back.points, m.points, atol=1e-12)
    np.testing.assert_array_equal(back.tets, m.tets)
