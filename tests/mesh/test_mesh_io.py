"""read_mesh / write_mesh: round trips through every format, units, TetGen, surfaces."""

from __future__ import annotations

import logging
import re

import meshio
import numpy as np
import pytest
from mesh_factories import box_grid, cube

from tissuecast.errors import MeshError, MeshFormatError
from tissuecast.mesh import TetMesh, phantom, read_mesh, write_mesh, write_point_set
from tissuecast.mesh.io import VOLUME_FORMATS
from tissuecast.mesh.mesher import merge_duplicate_points, tetrahedralize_surface
from tissuecast.mesh.phantom import icosphere

FORMATS = sorted(VOLUME_FORMATS)  # .ele .inp .mesh .msh .node .vtk .vtu .xdmf
WITH_POINT_DATA = [".vtu", ".vtk", ".xdmf", ".msh"]


@pytest.mark.parametrize("ext", FORMATS)
def test_round_trip_every_volume_format(tmp_path, ext):
    m = phantom()
    written = write_mesh(tmp_path / f"m{ext}", m)
    assert all(p.is_file() for p in written)
    r = read_mesh(tmp_path / f"m{ext}")
    np.testing.assert_allclose(r.points, m.points, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(r.tets, m.tets)
    assert r.n_flipped == 0
    assert r.fingerprint() == m.fingerprint()


@pytest.mark.parametrize("ext", WITH_POINT_DATA)
def test_point_data_is_written_for_paraview(tmp_path, ext):
    m = box_grid(2, 2, 3)
    u = np.column_stack([m.points[:, 0], -m.points[:, 1], 0.5 * m.points[:, 2]])
    err = np.linalg.norm(u, axis=1)
    write_mesh(tmp_path / f"d{ext}", m, point_data={"displacement": u, "error": err},
               cell_data={"volume": m.tet_volumes} if ext != ".msh" else None)
    back = meshio.read(tmp_path / f"d{ext}")
    np.testing.assert_allclose(back.point_data["displacement"], u)
    np.testing.assert_allclose(np.ravel(back.point_data["error"]), err)
    if ext != ".msh":
        np.testing.assert_allclose(np.ravel(back.cell_data["volume"][0]), m.tet_volumes)


def test_point_data_of_wrong_length_is_refused(tmp_path):
    m = cube(5)
    with pytest.raises(MeshError, match=r"point_data 'displacement' must have shape \(8,\)"):
        write_mesh(tmp_path / "x.vtu", m, point_data={"displacement": np.zeros((7, 3))})


def test_point_set_vtu(tmp_path):
    p = np.arange(12.0).reshape(4, 3)
    write_point_set(tmp_path / "pts.vtu", p, {"role": np.array([1, 1, 2, 2])})
    back = meshio.read(tmp_path / "pts.vtu")
    np.testing.assert_allclose(back.points, p)
    assert back.cells[0].type == "vertex" and len(back.cells[0].data) == 4
    assert back.point_data["role"].tolist() == [1, 1, 2, 2]


@pytest.mark.parametrize("units, factor", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0)])
def test_units_convert_to_mm(tmp_path, units, factor):
    m = box_grid(2, 2, 2, size=(1.5, 2.0, 2.5))  # 3 x 4 x 5 "units" box, diagonal > 1
    write_mesh(tmp_path / "u.vtu", m)
    r = read_mesh(tmp_path / "u.vtu", units=units)
    np.testing.assert_allclose(r.points, m.points * factor)
    assert r.volume == pytest.approx(60.0 * factor**3)


def test_metres_declared_as_mm_is_refused_with_the_fix(tmp_path):
    m = box_grid(2, 2, 2, size=(0.011, 0.02, 0.035))  # a 22 x 40 x 70 mm box written in metres
    write_mesh(tmp_path / "metres.vtu", m)
    with pytest.raises(MeshError, match=r"looks like it is in metres: pass units='m' .*config: \[mesh\] units = \"m\""):
        read_mesh(tmp_path / "metres.vtu")
    np.testing.assert_allclose(read_mesh(tmp_path / "metres.vtu", units="m").extent, [22.0, 40.0, 70.0])


def test_unknown_units_are_refused(tmp_path):
    write_mesh(tmp_path / "c.vtu", cube(5))
    with pytest.raises(MeshError, match="units must be one of 'mm', 'cm', 'm', got 'inch'"):
        read_mesh(tmp_path / "c.vtu", units="inch")


def _write_tetgen_cube(tmp_path, first: int, attributes: bool = False, nodes_per_tet: int = 4):
    c = cube(6, side=2.0)
    lines = ["# cube, ids start at %d" % first, "8 3 0 0"]
    lines += [f"{i + first} {x:.17g} {y:.17g} {z:.17g}" for i, (x, y, z) in enumerate(c.points)]
    (tmp_path / "c.node").write_text("\n".join(lines) + "\n")
    t10 = c.tets10 if nodes_per_tet == 10 else c.tets
    head = f"{c.n_tets} {nodes_per_tet} {1 if attributes else 0}"
    rows = [
        f"{j + first} " + " ".join(str(v + first) for v in t) + (f" {10.0 * j:.1f}" if attributes else "")
        for j, t in enumerate(t10)
    ]
    (tmp_path / "c.ele").write_text(head + "  # tets\n" + "\n".join(rows) + "\n")
    return c


@pytest.mark.parametrize("first", [0, 1])
@pytest.mark.parametrize("attributes", [False, True])
def test_tetgen_zero_and_one_based(tmp_path, first, attributes):
    c = _write_tetgen_cube(tmp_path, first, attributes)
    for name in ("c.node", "c.ele"):
        r = read_mesh(tmp_path / name)
        np.testing.assert_allclose(r.points, c.points)
        np.testing.assert_array_equal(r.tets, c.tets)
        assert r.volume == pytest.approx(8.0)


def test_tetgen_writer_is_one_based_with_surface_faces(tmp_path):
    c = cube(5)
    paths = write_mesh(tmp_path / "w.node", c)
    assert [p.suffix for p in paths] == [".node", ".ele", ".face"]
    node = [line.split() for line in paths[0].read_text().splitlines() if not line.startswith("#")]
    assert node[0] == ["8", "3", "0", "0"] and node[1][0] == "1"
    ele = paths[1].read_text().split()
    assert ele[:3] == ["5", "4", "0"] and int(ele[3]) == 1
    assert paths[2].read_text().splitlines()[0] == "12 1"


def test_tetra10_is_reduced_to_corners_keeping_ids(tmp_path, caplog):
    m = box_grid(2, 1, 2)
    meshio.write(tmp_path / "q.vtu", meshio.Mesh(m.points10, [("tetra10", m.tets10)]))
    with caplog.at_level(logging.INFO, logger="tissuecast.mesh.io"):
        r = read_mesh(tmp_path / "q.vtu")
    np.testing.assert_array_equal(r.tets, m.tets)
    np.testing.assert_allclose(r.points, m.points)
    assert f"dropped {len(m.edges)} vertices" in caplog.text


def test_unused_vertices_are_dropped_keeping_order(tmp_path):
    m = cube(6)
    pts = np.vstack([[[50.0, 50.0, 50.0]], m.points])  # unused vertex first: ids shift by one
    meshio.write(tmp_path / "u.vtk", meshio.Mesh(pts, [("tetra", m.tets + 1)]))
    r = read_mesh(tmp_path / "u.vtk")
    np.testing.assert_array_equal(r.tets, m.tets)
    np.testing.assert_allclose(r.points, m.points)


def test_mixed_cells_keep_only_tetrahedra(tmp_path):
    m = box_grid(1, 2, 1)
    meshio.write(tmp_path / "mix.msh", meshio.Mesh(m.points, [("triangle", m.surface_triangles), ("tetra", m.tets)]),
                 file_format="gmsh22", binary=False)
    r = read_mesh(tmp_path / "mix.msh")
    np.testing.assert_array_equal(r.tets, m.tets)


def _cube_surface(side: float):
    c = cube(6, side=side)
    return c.points, c.surface_triangles


@pytest.mark.parametrize("ext", [".stl", ".obj", ".ply", ".off"])
def test_closed_cube_surface_is_tetrahedralised_exactly(tmp_path, ext):
    pts, tri = _cube_surface(20.0)
    meshio.write(tmp_path / f"cube{ext}", meshio.Mesh(pts, [("triangle", tri.astype(np.int32))]))
    m = read_mesh(tmp_path / f"cube{ext}", mesh_size=5.0)
    assert m.volume == pytest.approx(8000.0, rel=1e-9)
    np.testing.assert_allclose(m.extent, [20.0, 20.0, 20.0], atol=1e-9)
    assert m.quality.radius_ratio_min > 0.2
    assert len(m.interior_vertices) > 0


def test_sphere_surface_volume_and_size_convergence(tmp_path):
    d, tri = icosphere(4)
    meshio.write(tmp_path / "sphere.stl", meshio.Mesh(10.0 * d, [("triangle", tri)]))
    exact = 4.0 / 3.0 * np.pi * 1000.0
    coarse = read_mesh(tmp_path / "sphere.stl", mesh_size=5.0)
    fine = read_mesh(tmp_path / "sphere.stl", mesh_size=2.5)
    assert abs(fine.volume / exact - 1) < 0.02
    assert abs(fine.volume - exact) < abs(coarse.volume - exact)  # a finer surface is closer
    assert fine.n_vertices > 2 * coarse.n_vertices
    assert np.linalg.norm(fine.points[fine.surface_vertices], axis=1) == pytest.approx(10.0, abs=0.02)


def test_surface_in_cm_is_converted_before_meshing(tmp_path):
    pts, tri = _cube_surface(2.0)  # 2 cm
    meshio.write(tmp_path / "cube.off", meshio.Mesh(pts, [("triangle", tri)]))
    m = read_mesh(tmp_path / "cube.off", units="cm", mesh_size=5.0)
    assert m.volume == pytest.approx(8000.0, rel=1e-9)


def test_tetgen_face_surface_and_surface_writers(tmp_path):
    m = phantom()
    write_mesh(tmp_path / "s.face", m)
    assert not (tmp_path / "s.ele").exists()
    r = read_mesh(tmp_path / "s.face", mesh_size=4.0)
    assert r.volume == pytest.approx(m.volume, rel=0.03)
    write_mesh(tmp_path / "s.stl", m)
    with np.errstate(over="ignore"):
        s = meshio.read(tmp_path / "s.stl")
    p, t = merge_duplicate_points(s.points, s.cells[0].data)
    assert len(t) == len(m.surface_triangles) and len(p) == len(m.surface_vertices)


def test_tetrahedralize_surface_rejects_bad_size():
    pts, tri = _cube_surface(1.0)
    with pytest.raises(MeshError, match="mesh_size must be a positive length"):
        tetrahedralize_surface(pts, tri, 0.0)


def test_meshing_runs_in_a_child_process_with_a_time_limit():
    """gmsh can hang on bad surfaces; meshing runs in a child process that is stopped with a
    clear error past the time limit, and gives the same mesh as meshing in-process."""
    gmsh = pytest.importorskip("gmsh")
    from tissuecast.mesh.phantom import icosphere, phantom_surface
    from tissuecast.mesh.mesher import start_gmsh

    p, t = icosphere(2)
    child = tetrahedralize_surface(10.0 * p, t, mesh_size=4.0)
    start_gmsh(gmsh)  # a caller that runs gmsh itself: meshed in-process
    try:
        same = tetrahedralize_surface(10.0 * p, t, mesh_size=4.0)
    finally:
        gmsh.finalize()
    np.testing.assert_array_equal(child.points, same.points)
    np.testing.assert_array_equal(child.tets, same.tets)
    fine_p, fine_t = phantom_surface()
    with pytest.raises(MeshError, match="did not finish meshing within 0 s"):
        tetrahedralize_surface(fine_p, fine_t, mesh_size=1.0, timeout=0.01)
    with pytest.raises(MeshError, match="timeout must be a positive"):
        tetrahedralize_surface(fine_p, fine_t, mesh_size=1.0, timeout=0)


def test_meshing_gives_the_same_mesh_whatever_the_callers_blas_threads(tmp_path):
    """gmsh's wheel links its own OpenBLAS, which takes its thread count from the environment
    when it loads; threaded, it rounds differently and gmsh re-meshes the surface differently
    (the coarse phantom's coordinates differed with one and two threads). Meshing pins it to
    one thread in its child process, so callers with any setting get the same mesh."""
    pytest.importorskip("gmsh")
    import os
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from tissuecast.mesh import mesher\n"
        "from tissuecast.mesh.shapes import phantom_mesh\n"
        "if sys.argv[2] == 'unpinned':\n"
        "    mesher.GMSH_ENVIRONMENT.clear()\n"
        "m = phantom_mesh(2.0)\n"
        "np.savez(sys.argv[1], points=m.points, tets=m.tets)\n"
    )
    meshes = []
    for threads, how in (("1", "pinned"), ("2", "pinned"), ("2", "unpinned")):
        env = {**os.environ, "OPENBLAS_NUM_THREADS": threads, "OMP_NUM_THREADS": threads}
        out = tmp_path / f"threads{threads}-{how}.npz"
        run = subprocess.run([sys.executable, "-c", code, str(out), how], env=env, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-800:]
        with np.load(out) as z:
            meshes.append((z["points"], z["tets"]))
    np.testing.assert_array_equal(meshes[0][0], meshes[1][0])
    np.testing.assert_array_equal(meshes[0][1], meshes[1][1])
    if meshes[2][0].shape == meshes[0][0].shape and np.array_equal(meshes[2][0], meshes[0][0]):
        pytest.skip("gmsh's BLAS gives the same mesh on two threads here (one core?): nothing told apart")


def test_meshing_reports_a_child_that_died_without_an_answer():
    """A meshing child that dies without an answer (here an exception other than gmsh's own
    error, as a crash would) is one clear error with its exit code and last line."""
    pytest.importorskip("gmsh")
    from tissuecast.mesh.mesher import _gmsh_in_child
    from tissuecast.mesh.phantom import icosphere

    p, t = icosphere(1)
    with pytest.raises(MeshError, match=r"gmsh crashed while meshing \(exit code 1: TypeError: .*bogus"):
        _gmsh_in_child(10.0 * p, t, {"mesh_size": 4.0, "bogus": 1}, 60.0)


def test_a_config_mesh_path_naming_no_file_names_the_key_and_the_folder_it_is_read_from(tmp_path, monkeypatch, capsys):
    from tissuecast.cli.main import main
    from tissuecast.config import MeshConfig
    from tissuecast.errors import ConfigError
    from tissuecast.mesh.source import mesh_from_config

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=rf"mesh.path = 'meshes/organ.vtu' does not exist: a relative path is read from "
                                          rf"the current folder \({re.escape(str(tmp_path))}\), not the config's"):
        mesh_from_config(MeshConfig(path="meshes/organ.vtu"))
    (tmp_path / "c.toml").write_text('[mesh]\npath = "meshes/organ.vtu"\n')
    assert main(["markers", "--config", "c.toml"]) == 2
    assert "mesh.path = 'meshes/organ.vtu' does not exist" in capsys.readouterr().err
    (tmp_path / "meshes").mkdir()
    write_mesh(tmp_path / "meshes" / "organ.vtu", phantom())  # there: read from the current folder
    assert mesh_from_config(MeshConfig(path="meshes/organ.vtu")).n_vertices == phantom().n_vertices


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(MeshFormatError, match="does not exist"):
        read_mesh(tmp_path / "missing.vtu")
    (tmp_path / "x.xyz").write_text("1 2 3\n")
    with pytest.raises(MeshFormatError, match=r"unknown mesh format '.xyz'.*\.vtu"):
        read_mesh(tmp_path / "x.xyz")
    (tmp_path / "junk.vtu").write_text("not xml")
    with pytest.raises(MeshFormatError, match="could not read .*junk.vtu"):
        read_mesh(tmp_path / "junk.vtu")
    meshio.write(tmp_path / "tri.vtu", meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshFormatError, match="holds no tetrahedra"):
        read_mesh(tmp_path / "tri.vtu")


def test_tetmesh_is_returned_with_mm_and_int64():
    m = TetMesh(np.eye(4, 3) * 5.0, np.array([[0, 1, 2, 3]], dtype=np.int32))
    assert m.points.dtype == np.float64 and m.tets.dtype == np.int64


def test_tetgen_quadratic_ele_and_non_consecutive_ids(tmp_path):
    c = _write_tetgen_cube(tmp_path, 1, nodes_per_tet=10)  # .ele lists 10 nodes; midpoints absent
    # midpoint ids (9..) are not in the .node file: only the corners are read
    r = read_mesh(tmp_path / "c.ele")
    np.testing.assert_array_equal(r.tets, c.tets)
    # ids with gaps: 10, 20, ..., 80
    node = (tmp_path / "c.node").read_text().splitlines()
    node[2:] = [f"{10 * (k + 1)} " + line.split(None, 1)[1] for k, line in enumerate(node[2:])]
    (tmp_path / "c.node").write_text("\n".join(node) + "\n")
    rows = [f"{j} " + " ".join(str(10 * (v + 1)) for v in t) for j, t in enumerate(c.tets)]
    (tmp_path / "c.ele").write_text(f"{c.n_tets} 4 0\n" + "\n".join(rows) + "\n")
    r = read_mesh(tmp_path / "c.node")
    np.testing.assert_array_equal(r.tets, c.tets)
    np.testing.assert_allclose(r.points, c.points)


def _tet_surface(shift):
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) * 10.0 + shift
    return p, TetMesh(p, [[0, 1, 2, 3]]).surface_triangles


def test_surface_checks_fire():
    from tissuecast.mesh.mesher import check_closed_surface

    p1, t1 = _tet_surface(0.0)
    check_closed_surface(p1, t1)  # a closed tetrahedron surface passes
    # two closed tetrahedra touching at one vertex: every edge is shared twice, yet non-manifold
    p2, t2 = _tet_surface(-np.array([10.0, 0.0, 0.0]))
    p2 = p2 * np.array([1.0, -1.0, -1.0])  # rotate by 180 degrees about x: vertex 1 at the origin
    assert np.array_equal(p2[1], p1[0])
    pts, tri = merge_duplicate_points(np.vstack([p1, p2]), np.vstack([t1, t2 + 4]))
    assert len(pts) == 7
    with pytest.raises(MeshError, match="non-manifold at 1 vertices where separate sheets touch"):
        check_closed_surface(pts, tri)
    with pytest.raises(MeshError, match="repeated vertex"):
        check_closed_surface(p1, np.vstack([t1, [[0, 0, 1]]]))
    flat = np.vstack([p1, [[5.0, 0.0, 0.0]]])  # vertex 4 on the edge 0-1
    with pytest.raises(MeshError, match="zero-area"):
        check_closed_surface(flat, np.vstack([t1, [[0, 4, 1]]]))


def test_merge_duplicate_points_of_triangle_soup():
    p1, t1 = _tet_surface(0.0)
    soup = p1[t1].reshape(-1, 3)  # 12 corners, as an STL stores them
    pts, tri = merge_duplicate_points(soup, np.arange(12).reshape(4, 3))
    assert len(pts) == 4
    np.testing.assert_allclose(pts[tri], p1[t1])


def test_real_gmsh_files_first_and_second_order(tmp_path):
    """Files written by gmsh itself: msh 2.2/4.1 with surface groups, and a 10-node .inp
    deck whose CPS6 surface elements meshio cannot read (they are skipped)."""
    gmsh = pytest.importorskip("gmsh")
    from tissuecast.mesh.mesher import start_gmsh

    start_gmsh(gmsh)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 10, 20, 30)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], 1)
        gmsh.model.addPhysicalGroup(2, [1, 2], 2)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 8.0)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(tmp_path / "p1.msh"))
        gmsh.option.setNumber("Mesh.MshFileVersion", 2.2)
        gmsh.write(str(tmp_path / "p1_v22.msh"))
        gmsh.model.mesh.setOrder(2)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(tmp_path / "p2.msh"))
        gmsh.write(str(tmp_path / "p2.inp"))
    finally:
        gmsh.finalize()
    ref = read_mesh(tmp_path / "p1.msh")
    assert ref.volume == pytest.approx(6000.0, rel=1e-9)
    for name in ("p1_v22.msh", "p2.msh", "p2.inp"):
        m = read_mesh(tmp_path / name)
        np.testing.assert_allclose(m.points, ref.points, atol=1e-9)  # mid-edge nodes dropped, ids kept
        np.testing.assert_array_equal(np.sort(m.tets, axis=1), np.sort(ref.tets, axis=1))


def test_mixed_triangle_orientation_is_repaired(tmp_path):
    from tissuecast.mesh.mesher import orient_surface

    d, tri = icosphere(2)
    mixed = tri.copy()
    mixed[::3] = mixed[::3][:, ::-1]  # a third of the normals point inward
    fixed = orient_surface(d, mixed)
    np.testing.assert_array_equal(np.sort(fixed, axis=1), np.sort(tri, axis=1))
    p = d[fixed]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", normals, p.mean(axis=1)) > 0)  # all outward
    inward = d[orient_surface(d, tri[:, ::-1])]  # all-inward input is turned outward
    np.testing.assert_allclose(np.cross(inward[:, 1] - inward[:, 0], inward[:, 2] - inward[:, 0]), normals)
    meshio.write(tmp_path / "mixed.stl", meshio.Mesh(10.0 * d, [("triangle", mixed)]))
    meshio.write(tmp_path / "clean.stl", meshio.Mesh(10.0 * d, [("triangle", tri)]))
    a = read_mesh(tmp_path / "mixed.stl", mesh_size=4.0)
    b = read_mesh(tmp_path / "clean.stl", mesh_size=4.0)
    assert a.volume == pytest.approx(b.volume, rel=1e-4)  # vertex order can move gmsh nodes a little


def test_meshing_with_gmsh_leaves_broken_pipes_as_python_errors():
    """gmsh's initialisation resets SIGPIPE to the default action (kill the process); after
    tetrahedralising, a write to a closed pipe must still raise BrokenPipeError, or a data-set
    run whose worker died would vanish without its error."""
    pytest.importorskip("gmsh")
    import subprocess
    import sys

    code = (
        "import os\n"
        "from tissuecast.mesh.phantom import icosphere\n"
        "from tissuecast.mesh.mesher import tetrahedralize_surface\n"
        "p, t = icosphere(2)\n"
        "tetrahedralize_surface(10.0 * p, t, mesh_size=4.0)\n"
        "r, w = os.pipe(); os.close(r)\n"
        "try:\n"
        "    os.write(w, b'x')\n"
        "except BrokenPipeError:\n"
        "    print('BrokenPipeError')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, (out.returncode, out.stderr[-500:])
    assert out.stdout.strip() == "BrokenPipeError"
