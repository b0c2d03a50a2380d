"""Meshes sized for the simulation: the vertex-budget and tolerance searches, label maps and
surfaces meshed within a budget, the expected cost of a paper-size run, and the warnings."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from mesh_factories import box_grid

from tissuecast.cli.main import main
from tissuecast.config import config_from_dict
from tissuecast.errors import ConfigError, MeshError
from tissuecast.mesh import phantom, read_mesh, write_mesh
from tissuecast.mesh.run_cost import PAPER_RUNS, duration_text, paper_run_estimate
from tissuecast.mesh.sizing import (
    BUDGET_FILL,
    mesh_to_budget,
    mesh_to_tolerance,
    size_for_budget,
    surface_volume,
)

LENGTH = 60.0  # mm, the side of the boxes the fake mesher makes


def box_mesher(calls: list, fail_between=(math.inf, math.inf)):
    """size -> a box of side LENGTH with round(LENGTH / size) cells a side ((k + 1)^3 vertices);
    sizes inside ``fail_between`` raise MeshError (as gmsh may at some sizes)."""

    def make(size: float):
        calls.append(size)
        if fail_between[0] < size < fail_between[1]:
            raise MeshError(f"cannot mesh at {size}")
        k = max(1, round(LENGTH / size))
        return box_grid(k, k, k, (LENGTH / k,) * 3)

    return make


# --------------------------------------------------------------------------- the searches
@pytest.mark.parametrize("budget", [300, 1000, 5000])
def test_budget_search_returns_the_finest_box_within_the_budget(budget):
    calls = []
    sized = mesh_to_budget(box_mesher(calls), budget, LENGTH**3)
    n = sized.mesh.n_vertices
    finest = max((k + 1) ** 3 for k in range(1, 60) if (k + 1) ** 3 <= budget)
    assert n <= budget and n == finest  # the boxes' counts jump: the best one under the budget is found
    assert len(calls) == len(sized.attempts) <= 6 and [s for s, _ in sized.attempts] == calls
    assert sized.size == pytest.approx(calls[[v for _, v in sized.attempts].index(n)])


def test_budget_search_stops_once_the_budget_is_nearly_filled():
    calls = []
    budget = 8**3  # a box of 7 cells a side fills it exactly
    first = size_for_budget(LENGTH**3, budget)
    assert round(LENGTH / first) == 7  # the first guess lands there: one attempt
    sized = mesh_to_budget(box_mesher(calls), budget, LENGTH**3)
    assert sized.mesh.n_vertices == budget and len(calls) == 1 and BUDGET_FILL * budget <= budget


def test_budget_search_goes_finer_where_meshing_fails_and_errors_list_the_attempts():
    calls = []
    assert 6.5 < size_for_budget(LENGTH**3, 1000) < 7.5
    sized = mesh_to_budget(box_mesher(calls, fail_between=(6.5, 7.5)), 1000, LENGTH**3)
    assert sized.attempts[0][1] == 0 and sized.mesh.n_vertices == 1000 and not 6.5 < sized.size < 7.5
    with pytest.raises(MeshError, match=r"no mesh within 5 vertices after \d attempts \(.*mm: 8.*\); raise the budget"):
        mesh_to_budget(box_mesher([]), 5, LENGTH**3)
    with pytest.raises(MeshError, match="max_vertices must be an integer of at least 4"):
        size_for_budget(1000.0, 3)
    with pytest.raises(MeshError, match="volume must be positive"):
        size_for_budget(0.0, 100)


def test_tolerance_search_finds_the_coarsest_size_within_the_tolerance():
    calls = []
    sized = mesh_to_tolerance(box_mesher(calls), lambda m: 0.1 * m.quality.edge_length_max, 1.0, 4.0)
    assert 0.1 * sized.mesh.quality.edge_length_max <= 1.0
    coarser = [s for s in calls if s > sized.size]
    assert coarser and all(0.1 * box_mesher([])(s).quality.edge_length_max > 1.0 for s in coarser)
    with pytest.raises(MeshError, match="no mesh met the surface tolerance 0.001 mm after 6 attempts"):
        mesh_to_tolerance(box_mesher([]), lambda m: 1.0, 0.001, 60.0)  # 60, 30, ... 1.9 mm: never met
    with pytest.raises(MeshError, match="must be a positive length"):
        mesh_to_tolerance(box_mesher([]), lambda m: 1.0, 0.0, 4.0)


def test_surface_volume_of_a_sphere_with_mixed_orientation():
    from tissuecast.mesh.phantom import icosphere

    d, tri = icosphere(3)
    tri = tri.copy()
    tri[::3] = tri[::3, ::-1]  # flip a third of the triangles, as STL files often do
    exact = 4.0 / 3.0 * np.pi * 1000.0
    assert surface_volume(10.0 * d, tri) == pytest.approx(exact, rel=0.02)


# ------------------------------------------------------------------------------ label maps
@pytest.fixture(scope="module")
def ellipsoid():
    pytest.importorskip("skimage")
    pytest.importorskip("gmsh")
    from labelmap_factories import ellipsoid_mask

    from tissuecast.mesh.labelmap import LabelMap

    mask, ijk_to_lps, _ = ellipsoid_mask((22.0, 15.0, 11.0), (0.9, 1.3, 2.0))
    return LabelMap(mask, ijk_to_lps, "ellipsoid")


def test_label_map_within_a_budget_follows_the_voxels(ellipsoid):
    from tissuecast.mesh.from_image import label_map_fidelity
    from tissuecast.mesh.sizing import mesh_label_map_to_budget

    sized = mesh_label_map_to_budget(ellipsoid, 600)
    f = label_map_fidelity(sized.mesh, ellipsoid)
    assert BUDGET_FILL * 600 * 0.7 <= sized.mesh.n_vertices <= 600
    assert f.surface_p95_voxels < 1.0 and f.boundary_p95_voxels < 1.0 and f.hausdorff95_voxels < 1.0
    assert abs(f.volume_error) < 0.05  # elements of ~4 mm on a 22 x 15 x 11 mm body: chords cut a little off
    assert sized.mesh.quality.radius_ratio_min > 0.2
    assert f.hausdorff95_mm == max(f.surface_p95_mm, f.boundary_p95_mm) <= f.hausdorff_mm


def test_config_max_vertices_meshes_a_label_map_within_the_budget(tmp_path, ellipsoid):
    from labelmap_factories import write_nrrd

    from tissuecast.mesh.source import mesh_from_config

    path = write_nrrd(tmp_path / "e.nrrd", ellipsoid.mask.astype(np.uint8) * 3, ellipsoid.ijk_to_lps)
    cfg = config_from_dict({"mesh": {"path": str(path), "label": 3, "max_vertices": 400}})
    assert mesh_from_config(cfg.mesh).n_vertices <= 400


@pytest.mark.parametrize("mesh, text", [
    ({"max_vertices": 500}, "mesh.max_vertices applies when mesh.path names a label map or a closed surface"),
    ({"path": "roi.vtu", "max_vertices": 500}, "'roi.vtu' is a volume mesh, used as it is: remove mesh.max_vertices"),
    ({"path": "roi.stl", "max_vertices": 3}, "mesh.max_vertices = 3 is too small"),
    ({"path": "roi.stl", "max_vertices": -1}, "mesh.max_vertices = -1 is out of range"),
])
def test_max_vertices_config_errors_name_the_key(mesh, text):
    from tissuecast.app import check_config

    with pytest.raises(ConfigError, match=text):  # a value at loading, what the path names at the edge
        check_config(config_from_dict({"mesh": mesh}))
    assert config_from_dict({"mesh": {"path": "roi.nii.gz", "max_vertices": 500}}).mesh.max_vertices == 500


# -------------------------------------------------------------------------------- surfaces
def test_surface_within_a_budget_and_volume_meshes_refuse_one(tmp_path, capsys):
    pytest.importorskip("gmsh")
    import meshio

    from tissuecast.mesh.phantom import icosphere

    d, tri = icosphere(4)
    meshio.write(tmp_path / "sphere.stl", meshio.Mesh(20.0 * d, [("triangle", tri)]))
    m = read_mesh(tmp_path / "sphere.stl", max_vertices=300)
    assert 0.5 * 300 <= m.n_vertices <= 300
    assert main(["mesh", "convert", str(tmp_path / "sphere.stl"), str(tmp_path / "s.vtu"), "--max-vertices", "300"]) == 0
    out = capsys.readouterr().out
    assert f"{m.n_vertices} vertices" in out and "expected cost: a paper-size run" in out
    write_mesh(tmp_path / "v.vtu", phantom())
    with pytest.raises(MeshError, match="is a volume mesh, read as it is; a vertex budget"):
        read_mesh(tmp_path / "v.vtu", max_vertices=300)
    assert main(["mesh", "convert", str(tmp_path / "v.vtu"), str(tmp_path / "w.vtk"), "--max-vertices", "300"]) == 2
    assert main(["mesh", "convert", "phantom", str(tmp_path / "w.vtk"), "--max-vertices", "300"]) == 2
    assert "the built-in phantom is a fixed mesh" in capsys.readouterr().err


# -------------------------------------------------------------------------------- the CLI
def test_from_image_budget_prints_the_cost_and_options_exclude_each_other(tmp_path, ellipsoid, capsys):
    from labelmap_factories import write_nrrd

    path = write_nrrd(tmp_path / "e.nrrd", ellipsoid.mask.astype(np.uint8), ellipsoid.ijk_to_lps)
    assert main(["mesh", "from-image", str(path), str(tmp_path / "e.vtk"), "--max-vertices", "500", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["vertices"] <= 500 and doc["sizing"]["max_vertices"] == 500 and doc["sizing"]["attempts"]
    estimate = paper_run_estimate(doc["vertices"], doc["edges"])
    assert doc["paper_run"]["seconds"] == pytest.approx(estimate.seconds)
    assert main(["mesh", "from-image", str(path), str(tmp_path / "e.vtu"), "--max-vertices", "500", "--tolerance",
                 "0.01"]) == 0
    captured = capsys.readouterr()
    assert "budget 500 vertices" in captured.out and "expected cost      a paper-size run" in captured.out
    assert "500 vertices do not meet the tolerance" in captured.err
    assert main(["mesh", "from-image", str(path), str(tmp_path / "e.vtu"), "--size", "3", "--tolerance", "1"]) == 2
    assert "--size and --tolerance exclude each other" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["mesh", "from-image", str(path), str(tmp_path / "e.vtu"), "--size", "3", "--max-vertices", "9"])


def test_finer_than_asked_warning():
    from tissuecast.cli.mesh_output import FINER_THAN_ASKED, sizing_warnings

    m = phantom()
    edge = m.quality.edge_length_mean
    asked = {"max_vertices": None, "tolerance_mm": None, "attempts": []}
    (text,) = sizing_warnings(m, {**asked, "size_mm": 2.0 * edge})
    assert f"mean edge {edge:.2f} mm for a size of {2.0 * edge:g} mm" in text and "--max-vertices" in text
    assert sizing_warnings(m, {**asked, "size_mm": 0.99 * edge / FINER_THAN_ASKED}) == []
    assert sizing_warnings(m, {**asked, "size_mm": 2.0 * edge, "attempts": [(1.0, 10)]}) == []  # a search: no size asked


# -------------------------------------------------------------------------------- the cost
def test_paper_run_estimate_follows_the_measured_runs():
    for n, seconds in PAPER_RUNS:
        assert paper_run_estimate(n, 5 * n).seconds == pytest.approx(seconds, rel=0.15)  # the fit passes near each run
    small, large = paper_run_estimate(2000, 10000), paper_run_estimate(4000, 20000)
    assert 1.2 < small.exponent < 1.5 and large.seconds / small.seconds == pytest.approx(2**small.exponent)
    assert large.unknowns == 3 * (4000 + 20000) and not large.extrapolated
    brain = paper_run_estimate(43887, 260000)
    assert brain.extrapolated and "extrapolation" in brain.text() and 8 * 3600 < brain.seconds < 16 * 3600
    assert [duration_text(s) for s in (45, 1940, 37000, 3 * 86400)] == ["45 s", "32 min", "10.3 h", "3.0 days"]
