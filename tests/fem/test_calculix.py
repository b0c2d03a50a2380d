"""CalculiX interoperability: deck writer, result parsers, ccx runs against closed forms and
against the built-in solver (``tissuecast.fem.solve``).

Tests that run ``ccx`` are marked ``calculix`` and skipped when it is not installed (CI
installs the Debian package calculix-ccx, so they run there).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from scipy.optimize import brentq, fsolve

from tissuecast.errors import ConvergenceError, DependencyError, MeshFormatError, SolverSetupError
from tissuecast.fem import calculix as cx
from tissuecast.fem.material import NeoHookean

from mesh_factories import box_mesh

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="ccx (apt-get install calculix-ccx) not installed")
MAT = NeoHookean(0.021, 0.45)
#: Seed and RMS surface nodal force (N) of the 20-mode LBO field that takes the phantom (P2,
#: fixed vertices [1129, 615, 646]) to ~27 mm.
PHANTOM_SEED = 14
PHANTOM_RMS_FORCE = 0.0042


def _section(text: str, keyword: str) -> list[str]:
    """Data lines following ``keyword`` up to the next keyword line."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.upper().startswith(keyword))
    out = []
    for ln in lines[start + 1 :]:
        if ln.startswith("*"):
            break
        out.append(ln)
    return out


# ------------------------------------------------------------------------ deck writer
@pytest.mark.parametrize("order", [1, 2])
def test_deck_reads_back_with_meshio_and_keeps_ids(tmp_path, order):
    meshio = pytest.importorskip("meshio")
    mesh = box_mesh(2, 3, 2, (10.0, 12.0, 8.0))
    rng = np.random.default_rng(1)
    forces = rng.normal(size=(mesh.n_vertices, 3)) * 0.01
    forces[mesh.interior_vertices] = 0.0
    forces[0, 1] = 0.0  # zero components are not written
    fixed = mesh.interior_vertices[:2]
    path = cx.write_inp(tmp_path / "deck.inp", mesh, MAT, fixed, forces, order=order, node_sets={"MARKERS": [3, 7]})
    back = meshio.read(path, file_format="abaqus")
    nodes, cells = (mesh.points10, mesh.tets10) if order == 2 else (mesh.points, mesh.tets)
    assert back.points.shape == nodes.shape
    np.testing.assert_array_equal(back.points, nodes)  # coordinates written exactly (round-trip repr)
    assert [c.type for c in back.cells] == ["tetra10" if order == 2 else "tetra"]
    np.testing.assert_array_equal(back.cells[0].data, cells)
    # for C3D10 the midpoint of an edge between two fixed vertices is fixed too (as in fem.Problem)
    e = mesh.edges
    fixed_mid = mesh.n_vertices + np.flatnonzero(np.isin(e, fixed).all(axis=1)) if order == 2 else []
    assert order == 1 or len(fixed_mid) == 1  # the two chosen vertices share an edge
    np.testing.assert_array_equal(np.sort(back.point_sets["NFIXED"]), np.sort(np.r_[fixed, fixed_mid]))
    np.testing.assert_array_equal(back.point_sets["NVERT"], np.arange(mesh.n_vertices))
    np.testing.assert_array_equal(back.point_sets["MARKERS"], [3, 7])

    text = path.read_text()
    assert "1-based" in text.splitlines()[1] and "i = k - 1" in text.splitlines()[1]
    # element ids 1..m and node ids 1-based: vertex i is node i + 1
    elements = np.array([[int(x) for x in ln.split(",")] for ln in _section(text, "*ELEMENT")])
    np.testing.assert_array_equal(elements[:, 0], np.arange(1, len(cells) + 1))
    np.testing.assert_array_equal(elements[:, 1:] - 1, cells)
    c10, d1 = (float(x) for x in _section(text, "*HYPERELASTIC, NEO HOOKE")[0].split(","))
    assert c10 == MAT.c10 and d1 == MAT.d1
    assert _section(text, "*BOUNDARY") == ["NFIXED, 1, 3"]
    back_forces = np.zeros_like(forces)
    cload = _section(text, "*CLOAD")
    for ln in cload:
        node, dof, value = ln.split(",")
        back_forces[int(node) - 1, int(dof) - 1] = float(value)
    np.testing.assert_allclose(back_forces, forces, rtol=1e-13, atol=0)  # <= 20 characters per number for ccx
    assert len(cload) == np.count_nonzero(forces)
    assert "*STEP, NLGEOM=YES" in text
    assert f"TYPE={'C3D10' if order == 2 else 'C3D4'}," in text


def test_deck_prescribed_displacements_skip_free_components(tmp_path):
    mesh = box_mesh(1, 1, 1)
    f = np.zeros((mesh.n_vertices, 3))
    path = cx.write_inp(tmp_path / "p.inp", mesh, MAT, [], f, prescribed={0: [0.0, np.nan, 0.5], 7: [np.nan] * 3})
    assert _section(path.read_text(), "*BOUNDARY") == ["1, 1, 1, 0.0", "1, 3, 3, 0.5"]
    assert "*CLOAD" not in path.read_text()
    assert "*CONTROLS" not in path.read_text()
    path = cx.write_inp(tmp_path / "t.inp", mesh, MAT, [0, 1, 2], f, force_tolerance=1e-4)
    assert _section(path.read_text(), "*CONTROLS, PARAMETERS=FIELD") == ["0.0001, 0.01"]


def test_write_inp_rejects_bad_input(tmp_path):
    mesh = box_mesh(1, 1, 1)
    f = np.zeros((mesh.n_vertices, 3))
    out = tmp_path / "x.inp"
    with pytest.raises(SolverSetupError, match="shape"):
        cx.write_inp(out, mesh, MAT, [0], f[:-1])
    bad = f.copy()
    bad[2, 0] = np.nan
    with pytest.raises(SolverSetupError, match="non-finite"):
        cx.write_inp(out, mesh, MAT, [0], bad)
    loaded = f.copy()
    loaded[0, 2] = 1.0
    with pytest.raises(SolverSetupError, match="fixed vertices \\[0\\]"):
        cx.write_inp(out, mesh, MAT, [0], loaded)
    with pytest.raises(SolverSetupError, match="outside 0..7"):
        cx.write_inp(out, mesh, MAT, [8], f)
    with pytest.raises(SolverSetupError, match="order"):
        cx.write_inp(out, mesh, MAT, [0], f, order=3)
    with pytest.raises(SolverSetupError, match="c10"):
        cx.write_inp(out, mesh, object(), [0], f)
    assert not out.exists()


def test_deck_numbers_fit_ccx_field_width(tmp_path):
    """ccx rejects numbers longer than 20 characters (e.g. ``-2.786959021906976E-05``)."""
    mesh = box_mesh(1, 1, 1).scaled(1.0 / 3.0)
    forces = np.zeros((mesh.n_vertices, 3))
    forces[7] = [-2.786959021906976e-05, 1.0 / 3.0, -1e-300 / 3.0]
    text = cx.write_inp(tmp_path / "w.inp", mesh, MAT, [0, 1, 2], forces).read_text()
    numbers = [x.strip() for ln in text.splitlines() if not ln.startswith("*") and "," in ln for x in ln.split(",")]
    assert max(len(x) for x in numbers) <= 20
    back = [float(x) for x in _section(text, "*CLOAD")[0].split(",")[2:]]
    np.testing.assert_allclose(back, forces[7, :1], rtol=1e-13)


def test_export_inp_cli_writes_the_configured_deck(tmp_path, capsys):
    meshio = pytest.importorskip("meshio")
    from tissuecast.cli.main import main
    from tissuecast.markers import markers_and_fixed
    from tissuecast.mesh import phantom

    mesh = phantom()
    markers, fixed = markers_and_fixed(mesh)
    forces = np.zeros((mesh.n_vertices, 3))
    forces[mesh.surface_vertices[:2]] = [[0.01, 0.0, -0.02], [0.0, 0.03, 0.0]]
    np.save(tmp_path / "f.npy", forces)
    assert main(["export-inp", "phantom", str(tmp_path / "a.inp"), "--forces", str(tmp_path / "f.npy")]) == 0
    assert "nodes" in capsys.readouterr().out
    back = meshio.read(tmp_path / "a.inp", file_format="abaqus")
    assert back.points.shape == mesh.points10.shape and back.cells[0].type == "tetra10"
    np.testing.assert_array_equal(back.point_sets["MARKERS"], markers)
    # the fixed vertices and the mid-edge nodes of edges joining two of them (held straight)
    from tissuecast.fem import Problem

    held = Problem(mesh, MAT, fixed, order=2).constrained_nodes[0]
    assert np.isin(fixed, held).all() and len(held) > len(fixed)  # compact pins: 769-801 share an edge
    np.testing.assert_array_equal(np.sort(back.point_sets["NFIXED"]), np.sort(held))
    assert len(_section((tmp_path / "a.inp").read_text(), "*CLOAD")) == 3
    # CSV with a header, linear elements
    np.savetxt(tmp_path / "f.csv", forces, delimiter=",", header="fx,fy,fz", comments="")
    assert main(["export-inp", "phantom", str(tmp_path / "b.inp"), "--forces", str(tmp_path / "f.csv"), "--order", "1"]) == 0
    text = (tmp_path / "b.inp").read_text()
    assert "TYPE=C3D4," in text and len(_section(text, "*CLOAD")) == 3
    # the example field (no --forces): smooth surface loads, none on fixed vertices
    assert main(["export-inp", "phantom", str(tmp_path / "c.inp")]) == 0
    assert len(_section((tmp_path / "c.inp").read_text(), "*CLOAD")) > 3 * len(mesh.surface_vertices) - 10
    # bad input: one line on stderr, exit status 2
    np.save(tmp_path / "short.npy", forces[:-1])
    assert main(["export-inp", "phantom", str(tmp_path / "d.inp"), "--forces", str(tmp_path / "short.npy")]) == 2
    assert main(["export-inp", "phantom", str(tmp_path / "d.inp"), "--forces", str(tmp_path / "f.xlsx")]) == 2
    assert "error:" in capsys.readouterr().err and not (tmp_path / "d.inp").exists()


# ----------------------------------------------------------------------------- parsers
FRD = """\
    1C
    2C                             3                                     1
 -1         1 0.00000E+00 0.00000E+00 0.00000E+00
 -1         2 1.00000E+00 0.00000E+00 0.00000E+00
 -1         3 0.00000E+00 1.00000E+00 0.00000E+00
 -3
    1PSTEP                         1           1           1
  100CL  101 5.00000E-01           3                     0    1           1
 -4  DISP        4    1
 -5  D1          1    2    1    0
 -5  D2          1    2    2    0
 -5  D3          1    2    3    0
 -5  ALL         1    2    0    0    1ALL
 -1         1 9.99999E+00 9.99999E+00 9.99999E+00
 -1         2 9.99999E+00 9.99999E+00 9.99999E+00
 -1         3 9.99999E+00 9.99999E+00 9.99999E+00
 -3
    1PSTEP                         2           1           2
  100CL  102 1.00000E+00           3                     0    2           1
 -4  DISP        4    1
 -5  D1          1    2    1    0
 -5  D2          1    2    2    0
 -5  D3          1    2    3    0
 -5  ALL         1    2    0    0    1ALL
 -1         3-1.23456E+00-2.34567E+01 3.45678E-02
 -1         1 1.00000E-03-4.00000E+00-5.00000E+00
 -1        12-7.00000E+00 8.00000E+00-9.00000E+00
 -1         2 0.00000E+00-1.50000E+01 2.50000E+01
 -3
 9999
"""

FRD_SHORT = """\
  100CL  101 1.00000E+00           2                     0    1           0
 -4  DISP        4    1
 -1    2-2.00000E+00-3.00000E+00-4.00000E+00
 -1    1 1.00000E+00-1.00000E+00 1.00000E-01
 -3
"""

DAT = """
 displacements (vx,vy,vz) for set NVERT and time  0.5000000E+00

         1  9.000000E+00  9.000000E+00  9.000000E+00
         2  9.000000E+00  9.000000E+00  9.000000E+00

 displacements (vx,vy,vz) for set NVERT and time  0.1000000E+01

         2 -1.500000E+01  2.500000E+01 -3.500000E-03
         1  1.234567E-03 -4.000000E+00 -5.000000E+00
"""


def test_frd_parser_fixed_width_fields_run_together(tmp_path):
    path = tmp_path / "r.frd"
    path.write_text(FRD)
    u, t = cx.read_displacements(path, 3, return_time=True)
    assert t == 1.0  # the last block, not the first
    expected = [[1e-3, -4.0, -5.0], [0.0, -15.0, 25.0], [-1.23456, -23.4567, 0.0345678]]
    np.testing.assert_array_equal(u, expected)  # rows by node id (node k -> row k - 1), not file order
    with pytest.raises(MeshFormatError, match="node 4"):
        cx.read_displacements(path, 4)  # node 12 exists, 4..11 do not
    short = tmp_path / "s.frd"
    short.write_text(FRD_SHORT)  # I5 node ids (short format)
    np.testing.assert_array_equal(cx.read_displacements(short, 2), [[1.0, -1.0, 0.1], [-2.0, -3.0, -4.0]])


def test_dat_parser_takes_last_block_in_node_order(tmp_path):
    path = tmp_path / "r.dat"
    path.write_text(DAT)
    u, t = cx.read_displacements(path, 2, return_time=True)
    assert t == 1.0
    np.testing.assert_array_equal(u, [[1.234567e-3, -4.0, -5.0], [-15.0, 25.0, -3.5e-3]])
    empty = tmp_path / "e.dat"
    empty.write_text("\n")
    with pytest.raises(MeshFormatError, match="no displacement"):
        cx.read_displacements(empty, 2)


def test_sta_summary_counts_increments_iterations_and_cutbacks(tmp_path):
    path = tmp_path / "r.sta"
    path.write_text(
        "SUMMARY OF JOB INFORMATION\n"
        "  STEP      INC     ATT  ITRS     TOT TIME     STEP TIME      INC TIME\n"
        "     1          1     1U    5  0.000000E+00  0.000000E+00  0.100000E+00\n"
        "     1          1     2     4  0.250000E-01  0.250000E-01  0.250000E-01\n"
        "     1          2     1     3  0.625000E-01  0.625000E-01  0.375000E-01\n"
    )
    s = cx.read_sta(path)
    assert (s.increments, s.iterations, s.cutbacks, s.load_fraction) == (2, 12, 1, 0.0625)
    assert cx.read_sta(tmp_path / "missing.sta") == cx.StaSummary()


def test_missing_ccx_names_the_package(tmp_path):
    mesh = box_mesh(1, 1, 1)
    path = cx.write_inp(tmp_path / "m.inp", mesh, MAT, [0, 1, 2], np.zeros((8, 3)))
    with pytest.raises(DependencyError, match="apt-get install calculix-ccx"):
        cx.run_ccx(path, executable="no-such-ccx-program")


# ---------------------------------------------------------------------- ccx vs closed form
def uniaxial_closed_form(material: NeoHookean, nominal_stress: float) -> tuple[float, float]:
    """Axial and lateral stretch of the NEO HOOKE solid under uniaxial nominal stress (MPa)."""

    def equations(x):
        lam, t = x
        j = lam * t * t
        a = 2.0 * material.c10 * j ** (-5.0 / 3.0)
        p = 2.0 * (j - 1.0) / material.d1
        s_lateral = a * (t * t - lam * lam) / 3.0 + p
        s_axial = 2.0 * a * (lam * lam - t * t) / 3.0 + p
        return [s_lateral, j * s_axial / lam - nominal_stress]

    lam, t = fsolve(equations, [1.0, 1.0], xtol=1e-14)
    return float(lam), float(t)


@pytest.mark.calculix
@needs_ccx
@pytest.mark.parametrize("nominal_stress", [0.004, -0.003])  # MPa: 23 % stretch, 15 % compression
def test_ccx_uniaxial_block_matches_closed_form(tmp_path, nominal_stress):
    length = 10.0
    mesh = box_mesh(3, 3, 3, (length, length, length))
    p = mesh.points
    forces = np.zeros((mesh.n_vertices, 3))
    tri = mesh.surface_triangles
    top = tri[np.isclose(p[tri][:, :, 2], length).all(axis=1)]
    area = 0.5 * np.linalg.norm(np.cross(p[top[:, 1]] - p[top[:, 0]], p[top[:, 2]] - p[top[:, 0]]), axis=1)
    np.add.at(forces[:, 2], top.ravel(), np.repeat(nominal_stress * area / 3.0, 3))  # consistent P1 loads
    # symmetry planes x = 0, y = 0, z = 0 (rollers): the exact solution is homogeneous
    sym = np.where(np.isclose(p, 0.0), 0.0, np.nan)
    keep = ~np.isnan(sym).all(axis=1)
    path = cx.write_inp(tmp_path / "uni.inp", mesh, MAT, [], forces, order=1,
                        prescribed=(np.flatnonzero(keep), sym[keep]))
    run = cx.run_ccx(path)
    u = cx.read_displacements(run.dat, mesh.n_vertices)
    lam, t = uniaxial_closed_form(MAT, nominal_stress)
    assert abs(lam - 1.0) > 0.1
    np.testing.assert_allclose(u[:, 2], (lam - 1.0) * p[:, 2], atol=2e-5 * length)
    np.testing.assert_allclose(u[:, 0], (t - 1.0) * p[:, 0], atol=2e-5 * length)
    np.testing.assert_allclose(u[:, 1], (t - 1.0) * p[:, 1], atol=2e-5 * length)
    assert run.summary.load_fraction == 1.0 and run.summary.increments >= 2
    assert run.summary.iterations >= run.summary.increments


@pytest.mark.calculix
@needs_ccx
def test_ccx_c3d10_block_stretched_by_prescribed_displacement_matches_closed_form(tmp_path):
    """Displacement control: the top face (with its mid-edge nodes) moves by 30 % of the height."""
    length, stretch = 10.0, 1.3
    mesh = box_mesh(2, 2, 2, (length, length, length))
    p = mesh.points
    value = np.where(np.isclose(p, 0.0), 0.0, np.nan)  # rollers on x = 0, y = 0, z = 0
    value[np.isclose(p[:, 2], length), 2] = (stretch - 1.0) * length
    keep = ~np.isnan(value).all(axis=1)
    path = cx.write_inp(tmp_path / "stretch.inp", mesh, MAT, [], np.zeros((mesh.n_vertices, 3)), order=2,
                        prescribed=(np.flatnonzero(keep), value[keep]))
    text = path.read_text()
    top_mid = mesh.n_vertices + np.flatnonzero(np.isclose(mesh.points10[mesh.n_vertices :, 2], length))
    assert all(f"{k + 1}, 3, 3, 3.0" in text for k in top_mid)  # mid-edge nodes follow their edge
    run = cx.run_ccx(path)
    u = cx.read_displacements(run.dat, mesh.n_vertices)

    def lateral_stress(t):
        j = stretch * t * t
        return 2.0 * MAT.c10 * j ** (-5.0 / 3.0) * (t * t - stretch**2) / 3.0 + 2.0 * (j - 1.0) / MAT.d1

    t = brentq(lateral_stress, 0.5, 1.0, xtol=1e-15)
    assert t < 0.9
    np.testing.assert_allclose(u[:, 2], (stretch - 1.0) * p[:, 2], atol=1e-6 * length)
    np.testing.assert_allclose(u[:, :2], (t - 1.0) * p[:, :2], atol=2e-5 * length)


@pytest.mark.calculix
@needs_ccx
def test_ccx_failure_raises_convergence_error_with_load_fraction(tmp_path):
    mesh = box_mesh(1, 1, 2, (10.0, 10.0, 20.0))
    p = mesh.points
    forces = np.zeros((mesh.n_vertices, 3))
    forces[np.isclose(p[:, 2], 20.0), 2] = -50.0  # crushes the column: elements invert early
    path = cx.write_inp(tmp_path / "crush.inp", mesh, MAT, np.flatnonzero(np.isclose(p[:, 2], 0.0)), forces)
    with pytest.raises(ConvergenceError, match="smaller than minimum") as info:
        cx.run_ccx(path)
    assert 0.0 < info.value.load_fraction < 0.05
    assert info.value.result.summary.cutbacks > 0
    with pytest.raises(ConvergenceError, match="did not finish within"):
        cx.run_ccx(path, timeout=1e-3)
    # the backend hands back the last converged state
    from tissuecast.fem import Problem

    problem = Problem(mesh, MAT, np.flatnonzero(np.isclose(p[:, 2], 0.0)), order=2)
    with pytest.raises(ConvergenceError) as info:
        cx.solve_calculix(problem, forces)
    partial = info.value.result
    assert not partial.converged and partial.load_fraction == info.value.load_fraction < 0.05
    assert partial.displacement.shape == (mesh.n_vertices, 3) and partial.cutbacks > 0


# ------------------------------------------------------------ ccx vs the built-in solver
def _smooth_problem(mesh, rms_force: float, seed: int = 0, order: int = 2, rule: str = "spread"):
    """Paper-style set-up: 3 interior fixed vertices, a random 20-mode LBO surface field.

    Args:
        mesh: the mesh.
        rms_force: RMS surface nodal force of the field, N.
        seed: seed of the LBO weights.
        rule: fixed-vertex rule ("spread": strain; "compact": the body swings about the pins).
    """
    from tissuecast.fem import Problem
    from tissuecast.forces import field_scale, lbo_basis, lbo_field, random_lbo_weights
    from tissuecast.markers import select_fixed_vertices, select_markers

    fixed = select_fixed_vertices(mesh, 3, exclude=select_markers(mesh), rule=rule)
    basis = lbo_basis(mesh, 20)
    weights = random_lbo_weights(np.random.default_rng(seed), 20)
    forces = lbo_field(basis, weights, rms_force / field_scale(basis), mesh.n_vertices)
    return Problem(mesh, MAT, fixed, order=order), forces


def _cross_check(tmp_path, mesh, rms_force: float, seed: int = 0, low: float = 20.0, high: float = 35.0,
                 tolerances: tuple[float, float] | None = None, rule: str = "spread"):
    """Solve with ours and with ccx; return (ours, ccx) results. The force is rescaled if the
    built-in solution's peak falls outside [low, high] mm (e.g. after a change of the
    fixed-vertex rule), so the check always runs in the large-deformation range.
    ``tolerances`` = (force, displacement) convergence tolerances given to both solvers."""
    from tissuecast.config import SolverConfig
    from tissuecast.fem import Solver

    problem, forces = _smooth_problem(mesh, rms_force, seed, rule=rule)
    config = None
    deck = {}
    if tolerances is not None:
        config = SolverConfig(force_tolerance=tolerances[0], displacement_tolerance=tolerances[1])
        deck = {"force_tolerance": tolerances[0], "displacement_tolerance": tolerances[1]}
    solver = Solver(problem, config)
    ours = solver.solve(forces)
    for _ in range(3):  # damped rescaling: the response may grow much faster than the load
        if low <= ours.max_displacement <= high:
            break
        forces = forces * min(2.0, max(0.5, (0.5 * (low + high) / ours.max_displacement) ** 0.5))
        ours = solver.solve(forces)
    theirs = cx.solve_calculix(problem, forces, workdir=tmp_path / "ccx", threads=2, **deck)
    return ours, theirs


def _relative_difference(ours, theirs) -> float:
    return float(np.linalg.norm(ours.displacement - theirs.displacement, axis=1).max()) / theirs.max_displacement


@pytest.mark.calculix
@needs_ccx
def test_ccx_agrees_with_builtin_solver_on_coarse_phantom(tmp_path):
    """A coarse phantom (~200-250 vertices, ~1100-1400 P2 nodes), smooth forces, 20-35 mm."""
    pytest.importorskip("gmsh")
    from tissuecast.mesh.mesher import tetrahedralize_surface
    from tissuecast.mesh.phantom import phantom_surface

    mesh = tetrahedralize_surface(*phantom_surface(3), 9.0)
    # seed 2: 25 mm. (Seed 0 at this level: ccx cuts its increment below the minimum at 83 % of
    # the load, after 20 increments, where ours converges.)
    ours, theirs = _cross_check(tmp_path, mesh, rms_force=0.024, seed=2)
    assert theirs.converged and theirs.increments >= 2 and theirs.iterations >= theirs.increments
    assert len(theirs.residual_history) == theirs.iterations
    assert theirs.max_displacement >= 20.0
    assert _relative_difference(ours, theirs) <= 0.005


@pytest.mark.calculix
@needs_ccx
def test_ccx_agrees_when_the_body_swings_about_compact_pins(tmp_path):
    """Compact pins (a ~5 mm pinned triangle): ~21 mm is mostly a large rotation about the
    pins (dead loads swing the body like a pendulum). Both solvers must follow the same
    equilibrium branch. Measured: 21.3 mm, ccx 8 increments / 20 iterations, 0.005 % apart."""
    pytest.importorskip("gmsh")
    from tissuecast.mesh.mesher import tetrahedralize_surface
    from tissuecast.mesh.phantom import phantom_surface

    mesh = tetrahedralize_surface(*phantom_surface(3), 9.0)
    ours, theirs = _cross_check(tmp_path, mesh, rms_force=0.0038, seed=1, rule="compact")
    assert theirs.converged and theirs.max_displacement >= 20.0
    # mostly rigid: the best rigid motion (Kabsch) leaves 12 % of the peak, after a 22 degree turn
    X = mesh.points - mesh.points.mean(axis=0)
    x = X + ours.displacement - ours.displacement.mean(axis=0)
    u, _, vt = np.linalg.svd(x.T @ X)
    rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    assert np.degrees(np.arccos((np.trace(rot) - 1) / 2)) > 15.0
    assert np.linalg.norm(x - X @ rot.T, axis=1).max() < 0.2 * ours.max_displacement
    assert _relative_difference(ours, theirs) <= 0.005
    # all P2 nodes (mid-edge ones read from the .frd, 6 digits)
    nodal = np.linalg.norm(ours.nodal_displacement - theirs.nodal_displacement, axis=1).max()
    assert nodal <= 0.005 * theirs.max_displacement


@pytest.mark.calculix
@pytest.mark.slow
@needs_ccx
@pytest.mark.timeout(1800)
def test_ccx_agrees_with_builtin_solver_on_phantom(tmp_path):
    """The issue's cross-check: the phantom (P2), smooth forces reaching >= 20 mm, max vertex
    difference <= 0.5 % of the max displacement. ccx needs several minutes here."""
    from tissuecast.mesh import phantom

    # In the swing regime du/dload is large, so both solvers converge tightly (the default
    # 0.5 % residual criterion alone left 0.45 % between them at 21.7 mm).
    ours, theirs = _cross_check(tmp_path, phantom(), rms_force=PHANTOM_RMS_FORCE, seed=PHANTOM_SEED,
                                tolerances=(1e-4, 1e-3))
    assert theirs.converged and theirs.max_displacement >= 20.0
    assert _relative_difference(ours, theirs) <= 0.005
