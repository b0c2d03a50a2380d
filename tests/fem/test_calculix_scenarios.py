"""Every scenario support and load type, alone and combined, solved by tissuecast and by ccx
(``solve_calculix``) on a coarse box (P2, 112 vertices, a few seconds of ccx each): the two
agree within 0.5 % of the peak displacement (the phantom at 15-30 mm:
benchmarks/scenarios_vs_calculix.py, docs/scenarios.md).

Tests that run ``ccx`` are marked ``calculix`` and skipped when it is not installed (CI has it).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from mesh_factories import box_mesh

from tissuecast.config import Config, with_overrides
from tissuecast.errors import ConvergenceError
from tissuecast.fem import Solver
from tissuecast.fem.calculix import DeckScenario, solve_calculix
from tissuecast.fem.springs import NodalSprings
from tissuecast.forces import field_scale, lbo_basis, lbo_field, random_lbo_weights
from tissuecast.scenario import ScenarioDraw, build_scenario, scenario_rng

needs_ccx = pytest.mark.skipif(shutil.which("ccx") is None, reason="ccx (apt-get install calculix-ccx) not installed")

SIZE = (20.0, 20.0, 40.0)
MESH = box_mesh(3, 3, 6, SIZE)
PINS = [0, 3, 12]  # three corners of the base, 0-based
BASE = {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 10.0}  # the face z = 0 is attached
INCLUSION = {"regions": [{"name": "inclusion", "rule": "distance", "point": [10.0, 10.0, 25.0], "distance": 8.0,
                          "youngs_modulus": 0.063, "poisson_ratio": 0.45}]}
SPRINGS = {"rule": "surface", "normal_stiffness": 0.0021, "tangential_stiffness": 0.0005}

#: name -> (scenario overrides, forces.loading, RMS surface nodal force N at scale 1 (0 = no
#: LBO field), multiple of the drawn gravity change, scale of all loads); the scales bring
#: the peak to 10-20 mm.
CASES = {
    "attached": ({"pins": False, "attached": BASE}, "nodal", 0.004, 0.0, 1.0),
    "springs": ({"pins": False, "springs": SPRINGS}, "traction", 0.25, 0.0, 1.0),
    "gravity": ({"pins": False, "attached": BASE, "lbo_forces": False, "gravity": {"enabled": True}}, "nodal", 0.0,
                1.6, 1.0),
    "indentation": ({"pins": False, "attached": BASE, "lbo_forces": False,
                     "indentation": {"enabled": True, "radius": 7.0, "depth": [5.0, 5.0], "slide": [2.0, 2.0],
                                     "clearance": 4.0}}, "nodal", 0.0, 0.0, 1.0),
    "materials": ({"pins": False, "attached": BASE, "materials": INCLUSION}, "nodal", 0.004, 0.0, 1.0),
    "lbo+springs": ({"springs": SPRINGS}, "nodal", 0.09, 0.0, 1.0),
    "combined": ({"pins": False, "attached": BASE, "springs": SPRINGS, "gravity": {"enabled": True},
                  "indentation": {"enabled": True, "radius": 7.0, "depth": [5.0, 5.0], "slide": [2.0, 2.0],
                                  "clearance": 4.0},
                  "materials": INCLUSION}, "traction", 0.3, 30.0, 1.0),
}


def _case(name: str, seed: int = 5):
    overrides, loading, rms, gravity, scale = CASES[name]
    cfg = with_overrides(Config(), scenario=overrides, forces={"loading": loading, "n_basis": 10})
    sc = build_scenario(MESH, cfg, np.array(PINS))
    draw = sc.draw(scenario_rng(seed))
    field = None
    if rms:
        basis = lbo_basis(MESH, 10)
        w = random_lbo_weights(np.random.default_rng(seed), basis.n_vectors)
        field = lbo_field(basis, w, scale * rms / field_scale(basis), MESH.n_points)
    if draw.body_force is not None:
        draw = ScenarioDraw(draw.gravity_direction, scale * gravity * draw.body_force, draw.indentation)
    return (sc.problem(), *sc.solve_inputs(draw, field, loading))


@pytest.mark.calculix
@needs_ccx
@pytest.mark.parametrize("name", list(CASES))
def test_scenario_type_agrees_with_calculix(name, tmp_path):
    problem, surface, extra = _case(name)
    ours = Solver(problem).solve(surface, **extra)
    ccx = solve_calculix(problem, surface, workdir=tmp_path, **extra)
    peak = np.linalg.norm(ccx.displacement, axis=1).max()
    assert 10.0 <= peak <= 25.0, peak  # large deformation, as on the phantom
    diff = np.linalg.norm(ours.displacement - ccx.displacement, axis=1).max()
    assert diff < 0.005 * peak, (name, diff / peak)
    text = (tmp_path / "tissuecast.inp").read_text()
    if "springs" in name or name == "combined":
        assert "TYPE=SPRING1" in text and "ORIENTATION=" in text  # k_t != k_n: oriented springs
    if name in ("materials", "combined"):
        assert text.count("*SOLID SECTION") == 2


def test_deck_scenario_from_problem_carries_springs_and_materials():
    problem, _, _ = _case("combined")
    deck = DeckScenario.from_problem(problem, density=1e-9, acceleration=[0.0, 0.0, -9810.0])
    assert deck.springs is problem.springs and len(deck.materials) == 2
    assert sum(len(ids) for _, _, ids in deck.materials) == MESH.n_tets
    plain, _, _ = _case("attached")
    nothing = DeckScenario.from_problem(plain)  # held, one material, no gravity: adds nothing
    assert nothing.springs is None and nothing.materials is None and nothing.acceleration is None
    assert nothing.spring_lines(1, repr) == [] and nothing.step_lines(repr) == []
    assert isinstance(problem.springs, NodalSprings)


@pytest.mark.calculix
@needs_ccx
def test_ccx_backend_reports_a_stop_with_the_state_it_reached(tmp_path):
    """A load far beyond what the box on springs carries: ccx stops, the error says how far
    it got and carries that state."""
    problem, surface, extra = _case("springs")
    with pytest.raises(ConvergenceError) as info:
        solve_calculix(problem, 40.0 * surface, workdir=tmp_path, **extra)
    assert 0.0 < info.value.load_fraction < 1.0


EMBEDDED_TOML = """
name = "embedded-box"
[solver]
force_tolerance = 1e-4
displacement_tolerance = 1e-4
[forces]
loading = "traction"
[scenario]
name = "embedded"
pins = false
[scenario.attached]
rule = "normal"
direction = [0.0, 0.0, -1.0]
angle = 10.0
[scenario.springs]
rule = "surface"
tangential_stiffness = 0.0005
[scenario.gravity]
enabled = true
density = 1e-8
[scenario.indentation]
enabled = true
radius = 7.0
clearance = 4.0
[[scenario.materials.regions]]
name = "inclusion"
rule = "distance"
point = [10.0, 10.0, 25.0]
distance = 8.0
youngs_modulus = 0.063
"""


@pytest.mark.calculix
@needs_ccx
def test_export_inp_deck_of_a_scenario_sample_is_what_our_solver_solves(tmp_path, capsys):
    """``export-inp`` of the embedded box (attached base, springs, traction LBO forces, gravity
    change as *DLOAD GRAV, indentation as *BOUNDARY values, two materials): ccx run on the deck
    gives our solution of the same sample (seed 7) to 0.5 % of the peak."""
    from tissuecast.cli.export_inp_cmd import _example_forces
    from tissuecast.cli.main import main
    from tissuecast.config import load_config
    from tissuecast.fem import calculix as cx
    from tissuecast.mesh import write_mesh

    write_mesh(tmp_path / "box.vtu", MESH)
    (tmp_path / "embedded.toml").write_text(EMBEDDED_TOML)
    deck = tmp_path / "box.inp"
    assert main(["export-inp", str(tmp_path / "box.vtu"), str(deck), "--config", str(tmp_path / "embedded.toml"),
                 "--seed", "7", "--force-rms", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "SPRING1" in out and "*DLOAD, GRAV" in out and "node set INDENT" in out
    text = deck.read_text()
    assert "TISSUE, GRAV, " in text and text.count("*SOLID SECTION") == 2 and "*NSET, NSET=INDENT" in text

    cfg = load_config(tmp_path / "embedded.toml")
    sc = build_scenario(MESH, cfg, np.zeros(0, dtype=np.int64))
    draw = sc.draw(scenario_rng(7))
    surface, extra = sc.solve_inputs(draw, _example_forces(MESH, cfg, 7, 0.05), "traction")
    ours = Solver(sc.problem(), cfg.solver).solve(surface, **extra)
    u = cx.read_displacements(cx.run_ccx(deck).dat, MESH.n_points)
    peak = np.linalg.norm(u, axis=1).max()
    assert peak > 3.0
    assert np.linalg.norm(ours.displacement - u, axis=1).max() < 0.005 * peak


def test_preview_example_deformations_are_scaled_by_the_linear_response():
    """Small target: the examples' peaks are the linear response's, so their median is
    LINEAR_AIM of forces.target_max_displacement (to 2 %); the loads are the samples' own."""
    from tissuecast.scenario.preview import LINEAR_AIM, example_deformations

    cfg = with_overrides(Config(), scenario=CASES["attached"][0], forces={"n_basis": 10, "target_max_displacement": 0.2})
    sc = build_scenario(MESH, cfg, np.zeros(0, dtype=np.int64))
    out = example_deformations(sc, cfg, [11, 12, 13])
    peaks = [np.linalg.norm(u, axis=1).max() for _, u in out]
    assert len(out) == 3 and all(title.startswith(f"example {k + 1}: peak") for k, (title, _) in enumerate(out))
    assert np.median(peaks) == pytest.approx(LINEAR_AIM * 0.2, rel=0.02)
    assert len(set(np.round(peaks, 6))) == 3  # three different samples
