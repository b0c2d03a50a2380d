"""Bad input: each case gives ONE clear error line, exit status 2 and no traceback from the CLI;
with --debug the typed exception (a TissuecastError that also subclasses ValueError) propagates."""

from __future__ import annotations


import meshio
import numpy as np
import pytest
from mesh_factories import CUBE_POINTS, box_grid, cube

from tissuecast import errors
from tissuecast.cli.main import main
from tissuecast.errors import ConfigError, MarkerError, MeshError, MeshFormatError, TissuecastError
from tissuecast.mesh import write_mesh


CUBE_5_TETS = cube(5, side=1.0).tets  # positively oriented, so nothing is re-oriented first


def _vtu(path, points, tets):
    meshio.write(path, meshio.Mesh(np.asarray(points, float), [("tetra", np.asarray(tets))]))
    return str(path)


def _stl(path, points, triangles):
    meshio.write(path, meshio.Mesh(np.asarray(points, float), [("triangle", np.asarray(triangles))]), binary=True)
    return str(path)


def missing_file(d):
    return ["mesh", "info", str(d / "missing.vtu")]


def unknown_format(d):
    (d / "mesh.xyz").write_text("0 0 0\n")
    return ["mesh", "info", str(d / "mesh.xyz")]


def unreadable_file(d):
    (d / "junk.vtu").write_text("this is not VTK XML")
    return ["mesh", "info", str(d / "junk.vtu")]


def no_tetrahedra(d):
    c = cube(5)
    meshio.write(d / "surf.vtu", meshio.Mesh(c.points, [("triangle", c.surface_triangles)]))
    return ["mesh", "info", str(d / "surf.vtu")]


def non_finite(d):
    p = CUBE_POINTS * 10.0
    p[3, 1] = np.nan
    return ["mesh", "info", _vtu(d / "nan.vtu", p, CUBE_5_TETS)]


def index_out_of_range(d):
    return ["mesh", "info", _vtu(d / "oor.vtu", CUBE_POINTS * 10.0, np.vstack([CUBE_5_TETS, [[0, 1, 2, 8]]]))]


def tetgen_index_out_of_range(d):
    write_mesh(d / "t.node", cube(5))
    ele = (d / "t.ele").read_text().splitlines()
    ele[1] = "1 1 2 3 99"
    (d / "t.ele").write_text("\n".join(ele) + "\n")
    return ["mesh", "info", str(d / "t.ele")]


def tetgen_truncated(d):
    write_mesh(d / "t.node", cube(5))
    (d / "t.node").write_text("\n".join((d / "t.node").read_text().splitlines()[:5]) + "\n")
    return ["mesh", "info", str(d / "t.node")]


def repeated_vertex(d):
    return ["mesh", "info", _vtu(d / "rep.vtu", CUBE_POINTS * 10.0, np.vstack([CUBE_5_TETS, [[0, 1, 2, 2]]]))]


def zero_volume(d):
    p = np.vstack([CUBE_POINTS * 10.0, [[4.0, 4.0, 0.0]]])  # vertex 8 lies in the plane of 0, 1, 2
    return ["mesh", "info", _vtu(d / "flat.vtu", p, np.vstack([CUBE_5_TETS, [[0, 1, 2, 8]]]))]


def disconnected(d):
    p = np.vstack([CUBE_POINTS * 10.0, CUBE_POINTS * 10.0 + 50.0])
    return ["mesh", "info", _vtu(d / "two.vtu", p, np.vstack([CUBE_5_TETS, CUBE_5_TETS + 8]))]


def open_surface(d):
    c = cube(6, side=10.0)
    return ["mesh", "convert", _stl(d / "open.stl", c.points, c.surface_triangles[:-1]), str(d / "out.vtu")]


def non_manifold_surface(d):
    a = cube(6, side=10.0)
    shift = np.array([10.0, 10.0, 0.0])  # second cube touches the first along one edge
    p = np.vstack([a.points, a.points + shift])
    t = np.vstack([a.surface_triangles, a.surface_triangles + 8])
    return ["mesh", "convert", _stl(d / "nm.stl", p, t), str(d / "out.vtu")]


def looks_like_metres(d):
    write_mesh(d / "m.vtu", box_grid(2, 2, 2, size=(0.011, 0.0195, 0.035)))
    return ["mesh", "info", str(d / "m.vtu")]


def too_many_markers(d):
    return ["markers", "phantom", "--count", "150", "--out", str(d / "mk")]


def marker_id_out_of_range(d):
    return ["markers", "phantom", "--ids", "3", "5000", "--out", str(d / "mk")]


def fixed_overlaps_markers(d):
    return ["markers", "phantom", "--ids", "3", "700", "--fixed-ids", "700", "--out", str(d / "mk")]


def marker_count_zero(d):
    return ["markers", "phantom", "--count", "0", "--out", str(d / "mk")]


def unknown_config_key(d):
    (d / "c.toml").write_text("[markers]\ncout = 5\n")
    return ["config", "show", str(d / "c.toml")]


def out_of_range_config(d):
    (d / "c.toml").write_text("[material]\npoisson_ratio = 0.6\n")
    return ["config", "show", str(d / "c.toml")]


def wrong_type_config(d):
    (d / "c.toml").write_text('[markers]\ncount = "five"\n')
    return ["config", "show", str(d / "c.toml")]


CASES = [
    (missing_file, MeshFormatError, "does not exist"),
    (unknown_format, MeshFormatError, "unknown mesh format '.xyz'"),
    (unreadable_file, MeshFormatError, "could not read"),
    (no_tetrahedra, MeshFormatError, "holds no tetrahedra"),
    (non_finite, MeshError, "non-finite coordinates"),
    (index_out_of_range, MeshError, "refers to a vertex outside 0..7"),
    (tetgen_index_out_of_range, MeshFormatError, "refers to point id 99"),
    (tetgen_truncated, MeshFormatError, "truncated or malformed"),
    (repeated_vertex, MeshError, "repeats a vertex"),
    (zero_volume, MeshError, "zero volume"),
    (disconnected, MeshError, "2 disconnected pieces"),
    (open_surface, MeshError, "must be a closed manifold surface"),
    (non_manifold_surface, MeshError, "non-manifold"),
    (looks_like_metres, MeshError, "pass units='m'"),
    (too_many_markers, MarkerError, "of 150 markers could be placed"),
    (marker_id_out_of_range, MarkerError, "[5000] are outside 0..1164"),
    (fixed_overlaps_markers, MarkerError, "are both fixed vertices and markers"),
    (marker_count_zero, ConfigError, "markers.count = 0 is out of range"),
    (unknown_config_key, ConfigError, "unknown config key 'markers.cout'"),
    (out_of_range_config, ConfigError, "material.poisson_ratio = 0.6 is out of range"),
    (wrong_type_config, ConfigError, "markers.count must be an integer"),
]


@pytest.mark.parametrize("make, cls, text", CASES, ids=[c[0].__name__ for c in CASES])
def test_cli_gives_one_clear_error_line(tmp_path, capsys, make, cls, text):
    argv = make(tmp_path)
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = [x for x in captured.err.strip().splitlines() if not x.startswith(("INFO ", "DEBUG "))]
    assert len(lines) == 1, captured.err  # log lines aside, exactly one message
    assert lines[0].startswith("error: ") and text in lines[0]
    assert "Traceback" not in captured.err + captured.out


@pytest.mark.parametrize("make, cls, text", CASES, ids=[c[0].__name__ for c in CASES])
def test_debug_raises_the_typed_error(tmp_path, make, cls, text):
    argv = make(tmp_path)
    with pytest.raises(cls) as err:
        main(["--debug", *argv])
    assert isinstance(err.value, TissuecastError) and isinstance(err.value, ValueError)
    assert text in str(err.value)


def test_error_classes_subclass_builtins():
    assert issubclass(errors.MeshFormatError, errors.MeshError)
    assert issubclass(errors.ConvergenceError, RuntimeError)
    assert issubclass(errors.DependencyError, ImportError)
    with pytest.raises(errors.DependencyError, match=r"pip install 'tissuecast\[viz\]'"):
        errors.require("tissuecast_no_such_module", "viz", "Testing")
